"""Speed of CT -> tissues -> surfaces -> tetrahedral mesh on the example CT (target < 2 min, 2 cores).

Baseline in the same run: reading the CT (SimpleITK). The pipeline's median is reported as an absolute
time and as a ratio to that baseline (machine-independent-ish).
"""

import time

import pytest

from needletissue.imaging.data import CT_NAME, LABELS_NAME, require_shared

pytestmark = pytest.mark.data

_times = {}


def _read():
    from needletissue.imaging.io import read_ct

    return read_ct(require_shared(CT_NAME))


def _pipeline():
    from needletissue.geometry.surfaces import surfaces
    from needletissue.geometry.tetmesh import tet_mesh
    from needletissue.imaging.segment import segment

    c0 = time.process_time()
    t0 = time.perf_counter()
    seg = segment(require_shared(CT_NAME), require_shared(LABELS_NAME))
    t1 = time.perf_counter()
    surfaces(seg)
    t2 = time.perf_counter()
    mesh = tet_mesh(seg, size=3.0)
    t3 = time.perf_counter()
    return {"segment_s": t1 - t0, "surfaces_s": t2 - t1, "tet_mesh_s": t3 - t2,
            "cpu_s": time.process_time() - c0,  # this process only: the machine may be shared
            "tetrahedra": len(mesh.cells), "nodes": len(mesh.points)}


def test_bench_read_ct_baseline(benchmark):
    benchmark.pedantic(_read, rounds=3, iterations=1)
    _times["read"] = benchmark.stats.stats.median


def test_bench_segment_surfaces_mesh(benchmark):
    info = benchmark.pedantic(_pipeline, rounds=1, iterations=1)
    benchmark.extra_info.update(info)
    med = benchmark.stats.stats.median
    if "read" in _times:
        benchmark.extra_info["ratio_to_read_ct"] = med / _times["read"]
    print(f"\nCT -> mesh: {med:.1f} s ({info}); target < 120 s on 2 cores")
