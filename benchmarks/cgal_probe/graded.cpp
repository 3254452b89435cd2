// Graded Mesh_3 on a labelled INR image, CGAL 5.5.1 (Debian libcgal-dev).
// usage: graded in.inr out.mesh hmin hmax dist cx cy cz fdist lloyd odt perturb exude sigma facet_angle ratio
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Mesh_triangulation_3.h>
#include <CGAL/Mesh_complex_3_in_triangulation_3.h>
#include <CGAL/Mesh_criteria_3.h>
#include <CGAL/Labeled_mesh_domain_3.h>
#include <CGAL/make_mesh_3.h>
#include <CGAL/Image_3.h>
#include <CGAL/Real_timer.h>
#include <fstream>
#include <string>
#include <cmath>
#include <cstdlib>
#include <iostream>
typedef CGAL::Exact_predicates_inexact_constructions_kernel K;
typedef CGAL::Labeled_mesh_domain_3<K> Mesh_domain;
typedef CGAL::Mesh_triangulation_3<Mesh_domain, CGAL::Default, CGAL::Sequential_tag>::type Tr;
typedef CGAL::Mesh_complex_3_in_triangulation_3<Tr> C3t3;
typedef CGAL::Mesh_criteria_3<Tr> Mesh_criteria;
struct Sizing {
  typedef K::FT FT; typedef Mesh_domain::Index Index;
  double hmin, hmax, dist, cx, cy, cz, scale;
  FT operator()(const K::Point_3& p, const int, const Index&) const {
    double d = std::sqrt((p.x()-cx)*(p.x()-cx)+(p.y()-cy)*(p.y()-cy)+(p.z()-cz)*(p.z()-cz));
    double t = d / dist; if (t > 1) t = 1;
    return scale * (hmin + (hmax - hmin) * t);
  }
};
int main(int argc, char** argv) {
  if (argc < 17) { std::cerr << "bad args\n"; return 1; }
  CGAL::get_default_random() = CGAL::Random(0);
  double hmin = atof(argv[3]), hmax = atof(argv[4]), dist = atof(argv[5]);
  double cx = atof(argv[6]), cy = atof(argv[7]), cz = atof(argv[8]), fdist = atof(argv[9]);
  bool lloyd = atoi(argv[10]), odt = atoi(argv[11]), perturb = atoi(argv[12]), exude = atoi(argv[13]);
  std::string wfile = argv[14]; double fangle = atof(argv[15]), ratio = atof(argv[16]);
  CGAL::Real_timer t; t.start();
  CGAL::Image_3 image;
  if (!image.read(argv[1])) { std::cerr << "read fail\n"; return 1; }
  namespace params = CGAL::parameters;
  CGAL::Image_3 w;
  bool usew = (wfile != "-");
  if (usew && !w.read(wfile.c_str())) { std::cerr << "weights read fail\n"; return 1; }
  Mesh_domain domain = usew
    ? Mesh_domain::create_labeled_image_mesh_domain(image, params::weights = w, params::relative_error_bound = 1e-6)
    : Mesh_domain::create_labeled_image_mesh_domain(image, params::relative_error_bound = 1e-6);
  std::cerr << "domain " << t.time() << " s\n";
  Sizing cell{hmin, hmax, dist, cx, cy, cz, 1.0};
  Sizing facet{hmin, std::min(hmax, getenv("FSMAX") ? atof(getenv("FSMAX")) : hmax), dist, cx, cy, cz, 1.0};
  // fdist < 0: facet distance field = |fdist| * local size (graded approximation error)
  Sizing fd{hmin, hmax, dist, cx, cy, cz, std::abs(fdist)};
  Mesh_criteria criteria = (fdist > 0) ?
    Mesh_criteria(params::facet_angle = fangle, params::facet_size = facet,
                         params::facet_distance = fdist, params::cell_radius_edge_ratio = ratio,
                         params::cell_size = cell) :
    Mesh_criteria(params::facet_angle = fangle, params::facet_size = facet,
                         params::facet_distance = fd, params::cell_radius_edge_ratio = ratio,
                         params::cell_size = cell);
  C3t3 c3t3 = CGAL::make_mesh_3<C3t3>(domain, criteria,
      params::no_perturb(), params::no_exude());
  std::cerr << "refine " << t.time() << " s, cells " << c3t3.number_of_cells_in_complex() << "\n";
  if (lloyd) { CGAL::lloyd_optimize_mesh_3(c3t3, domain, params::time_limit = (getenv("TL") ? atof(getenv("TL")) : 30.0)); std::cerr << "lloyd " << t.time() << "\n"; }
  if (odt) { CGAL::odt_optimize_mesh_3(c3t3, domain, params::time_limit = (getenv("TL") ? atof(getenv("TL")) : 30.0)); std::cerr << "odt " << t.time() << "\n"; }
  if (perturb) { CGAL::perturb_mesh_3(c3t3, domain, params::time_limit = (getenv("TL") ? atof(getenv("TL")) : 30.0), params::sliver_bound = (getenv("SB") ? atof(getenv("SB")) : 10.0)); std::cerr << "perturb " << t.time() << "\n"; }
  if (exude) { CGAL::exude_mesh_3(c3t3, params::time_limit = (getenv("TL") ? atof(getenv("TL")) : 30.0), params::sliver_bound = (getenv("SB") ? atof(getenv("SB")) : 10.0)); std::cerr << "exude " << t.time() << "\n"; }
  std::ofstream f(argv[2]); c3t3.output_to_medit(f);
  std::cerr << "total " << t.time() << " s, cells " << c3t3.number_of_cells_in_complex() << "\n";
  return 0;
}
