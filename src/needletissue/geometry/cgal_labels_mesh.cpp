// CGAL Mesh_3 on a labelled voxel image with voxel size fields: needletissue.geometry.graded runs it.
// usage: cgal_labels_mesh in.bin out.bin
// in.bin:  int64 nx ny nz; float64 vx vy vz facet_angle facet_distance_ratio radius_edge seed;
//          uint8 label[nz][ny][nx] (0 outside the domain); float32 cell_size[...], facet_size[...] (mm)
// out.bin: int64 n_points n_cells; float64 points[n_points][3]; int32 cells[n_cells][4]; int32 label[n_cells]
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Image_3.h>
#include <CGAL/Labeled_mesh_domain_3.h>
#include <CGAL/Mesh_complex_3_in_triangulation_3.h>
#include <CGAL/Mesh_criteria_3.h>
#include <CGAL/Mesh_triangulation_3.h>
#include <CGAL/make_mesh_3.h>
#include <CGAL/refine_mesh_3.h>
#include <CGAL/Mesh_3/initialize_triangulation_from_labeled_image.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <iostream>
#include <map>
#include <vector>

typedef CGAL::Exact_predicates_inexact_constructions_kernel K;
typedef CGAL::Labeled_mesh_domain_3<K> Domain;
typedef CGAL::Mesh_triangulation_3<Domain, CGAL::Default, CGAL::Sequential_tag>::type Tr;
typedef CGAL::Mesh_complex_3_in_triangulation_3<Tr> C3t3;
typedef CGAL::Mesh_criteria_3<Tr> Criteria;

struct VoxelField {  // a size field: its value at the nearest voxel, times a factor
  const std::vector<float>* h;
  int64_t nx, ny, nz;
  double vx, vy, vz, factor;
  int64_t index(double x, double v, int64_t n) const {
    return std::min(std::max((int64_t)std::llround(x / v), (int64_t)0), n - 1);
  }
  K::FT operator()(const K::Point_3& p, const int, const Domain::Index&) const {
    return factor * (*h)[(index(p.z(), vz, nz) * ny + index(p.y(), vy, ny)) * nx + index(p.x(), vx, nx)];
  }
};

int main(int argc, char** argv) {
  if (argc != 3) { std::cerr << "usage: cgal_labels_mesh in.bin out.bin\n"; return 2; }
  std::ifstream in(argv[1], std::ios::binary);
  int64_t n[3];
  double par[7];
  in.read((char*)n, sizeof n);
  in.read((char*)par, sizeof par);
  if (!in || n[0] < 2 || n[1] < 2 || n[2] < 2) { std::cerr << "bad header\n"; return 2; }
  const std::size_t nv = (std::size_t)(n[0] * n[1] * n[2]);
  _image* im = _createImage(n[0], n[1], n[2], 1, par[0], par[1], par[2], 1, WK_FIXED, SGN_UNSIGNED);
  in.read((char*)im->data, nv);
  std::vector<float> cell(nv), facet(nv);
  in.read((char*)cell.data(), nv * sizeof(float));
  in.read((char*)facet.data(), nv * sizeof(float));
  if (!in) { std::cerr << "short input\n"; return 2; }
  CGAL::Image_3 image(im);
  CGAL::get_default_random() = CGAL::Random((unsigned)par[6]);   // the same mesh on every run
  namespace params = CGAL::parameters;
  Domain domain = Domain::create_labeled_image_mesh_domain(image, params::relative_error_bound = 1e-6);
  VoxelField cell_size{&cell, n[0], n[1], n[2], par[0], par[1], par[2], 1.0};
  VoxelField facet_size{&facet, n[0], n[1], n[2], par[0], par[1], par[2], 1.0};
  VoxelField facet_distance{&facet, n[0], n[1], n[2], par[0], par[1], par[2], par[4]};
  Criteria criteria(params::facet_angle = par[3], params::facet_size = facet_size,
                    params::facet_distance = facet_distance, params::cell_radius_edge_ratio = par[5],
                    params::cell_size = cell_size);
  // seeds on every connected component of every label: the default random shooting misses small ones
  C3t3 c3t3;
  initialize_triangulation_from_labeled_image(c3t3, domain, image, criteria, (unsigned char)0);
  CGAL::refine_mesh_3(c3t3, domain, criteria, params::no_perturb(), params::no_exude());

  std::map<Tr::Vertex_handle, int32_t> id;
  std::vector<double> pts;
  std::vector<int32_t> cells, labels;
  for (auto c = c3t3.cells_in_complex_begin(); c != c3t3.cells_in_complex_end(); ++c) {
    for (int k = 0; k < 4; ++k) {
      auto v = c->vertex(k);
      auto it = id.find(v);
      if (it == id.end()) {
        it = id.emplace(v, (int32_t)(pts.size() / 3)).first;
        const auto& p = v->point();
        pts.insert(pts.end(), {CGAL::to_double(p.x()), CGAL::to_double(p.y()), CGAL::to_double(p.z())});
      }
      cells.push_back(it->second);
    }
    labels.push_back((int32_t)c3t3.subdomain_index(c));
  }
  int64_t counts[2] = {(int64_t)(pts.size() / 3), (int64_t)labels.size()};
  std::ofstream out(argv[2], std::ios::binary);
  out.write((const char*)counts, sizeof counts);
  out.write((const char*)pts.data(), pts.size() * sizeof(double));
  out.write((const char*)cells.data(), cells.size() * sizeof(int32_t));
  out.write((const char*)labels.data(), labels.size() * sizeof(int32_t));
  return out ? 0 : 1;
}
