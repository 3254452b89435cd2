"""Anatomical pelvis model: meshing and one coarse quadratic solve, against the label-volume read as
baseline in the same run (ratios are what to compare across machines). Needs ../shared/data.

    PYTHONPATH=src python -m pytest benchmarks/bench_pelvis.py --benchmark-only
    PYTHONPATH=src python benchmarks/bench_pelvis.py [SIZE ...]   # the two meshers side by side (table)
"""

from __future__ import annotations

import pytest

from needletissue.geometry import pelvis as gp

pytestmark = pytest.mark.data


@pytest.fixture(scope="module")
def site_and_volume():
    vol = gp.ct_label_volume()
    site = gp.standard_site(vol)
    return gp.crop_to_site(vol, site), site


def test_bench_label_volume(benchmark):
    benchmark.pedantic(gp.ct_label_volume, rounds=3, iterations=1)


def test_bench_mesh_default(benchmark, site_and_volume):
    vol, site = site_and_volume
    m = benchmark.pedantic(gp.build_mesh, args=(vol, site), kwargs=dict(mesh_size=3.0), rounds=2, iterations=1)
    benchmark.extra_info["tetrahedra"] = len(m.cells)


def smooth_mesh(vol, site, mesh_size=6.0):
    from needletissue.imaging.segment import segment

    d = gp.data_dir() / "pelvis_ct"
    seg = segment(d / "example_ct.nii.gz", d / "example_seg_fast_force_split.nii.gz")
    return gp.build_mesh_smooth(seg, vol, site, mesh_size=mesh_size)


def test_bench_mesh_smooth(benchmark, site_and_volume):
    vol, site = site_and_volume
    m = benchmark.pedantic(smooth_mesh, args=(vol, site), rounds=1, iterations=1)
    benchmark.extra_info["tetrahedra"] = len(m.cells)


def test_bench_solve_coarse(benchmark):
    from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

    cfg = PelvisConfig(mesher="box", mesh_size=6.0, needle_size=3.0, far_size=18.0, forces=[100.0, 200.0, 300.0], figures=False)
    res = benchmark.pedantic(run_pelvis_model, args=(cfg,), rounds=1, iterations=1)
    benchmark.extra_info["tetrahedra"] = res.mesh["tetrahedra"]
    benchmark.extra_info["dofs"] = res.mesh["dofs"]
    benchmark.extra_info["max_needle_deformation_mm_300N"] = res.results[-1].max_needle_deformation_mm


if __name__ == "__main__":   # box (graded) against smooth (segment + mesh route) meshes: size, quality, volumes, CPU
    import sys
    import time

    from needletissue.models.pelvis.model import mesh_quality

    vol = gp.ct_label_volume()
    site = gp.standard_site(vol)
    vol = gp.crop_to_site(vol, site)
    print("| mesher | size mm | tets | nodes | min / 1st pct dihedral deg | < 10 deg | volume vs labels | CPU s |")
    print("|---|---|---|---|---|---|---|---|")
    for size in [float(a) for a in sys.argv[1:]] or [3.0, 6.0]:
        for name, build in (("box", lambda: gp.build_mesh(vol, site, mesh_size=size)),
                            ("smooth", lambda: smooth_mesh(vol, site, size))):
            t = time.process_time()
            m = build()
            cpu = time.process_time() - t
            q = mesh_quality(m, vol)
            err = ", ".join(f"{k} {100 * v:+.1f} %" for k, v in q["volume_error_vs_labels"].items())
            print(f"| {name} | {size:g} | {len(m.cells):,} | {len(m.points):,} | {q['min_dihedral_deg']:.1f} / "
                  f"{q['p01_dihedral_deg']:.1f} | {q['below_10_deg']} | {err} | {cpu:.1f} |", flush=True)
