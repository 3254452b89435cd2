"""Anatomical pelvis model: meshing and one coarse quadratic solve, against the label-volume read as
baseline in the same run (ratios are what to compare across machines). Needs ../shared/data.

    PYTHONPATH=src python -m pytest benchmarks/bench_pelvis.py --benchmark-only
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


def test_bench_solve_coarse(benchmark):
    from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

    cfg = PelvisConfig(mesh_size=6.0, needle_size=3.0, far_size=18.0, forces=[100.0, 200.0, 300.0], figures=False)
    res = benchmark.pedantic(run_pelvis_model, args=(cfg,), rounds=1, iterations=1)
    benchmark.extra_info["tetrahedra"] = res.mesh["tetrahedra"]
    benchmark.extra_info["dofs"] = res.mesh["dofs"]
    benchmark.extra_info["max_needle_deformation_mm_300N"] = res.results[-1].max_needle_deformation_mm
