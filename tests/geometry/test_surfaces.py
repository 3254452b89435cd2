"""Tissue surfaces: closed, manifold, and close to the analytic sphere they sample."""

import numpy as np
import pytest

from labelmaps import ball, make_seg
from needletissue.errors import InputError
from needletissue.geometry.surfaces import surfaces, tissue_surface


def test_sphere_surface_volume_and_area(tmp_path):
    h, r_vox = 1.0, 12.0
    seg = make_seg(ball(32, r_vox) * 3, {"adipose": 3}, spacing=h)
    ts = surfaces(seg)
    rep = ts.reports["adipose"]
    assert rep.watertight and rep.manifold
    R = r_vox * h
    # windowed-sinc smoothing does not shrink: volume and area of the ball within 3 % / 5 %
    assert rep.volume_mm3 == pytest.approx(4 / 3 * np.pi * R ** 3, rel=0.03)
    assert rep.area_mm2 == pytest.approx(4 * np.pi * R ** 2, rel=0.05)
    # centred where the header puts the image centre (LPS flip of x and y)
    c = np.asarray(ts.surfaces["adipose"].center)
    assert np.allclose(c, [10 - 15.5, -20 - 15.5, 5 + 15.5], atol=0.3)
    paths = ts.write(tmp_path)
    assert {p.name for p in paths} == {"adipose.stl", "adipose.vtp"}


def test_decimation_keeps_volume():
    seg = make_seg(ball(32, 12) * 3, {"adipose": 3}, spacing=1.0)
    full, _ = tissue_surface(seg.labels, 3)
    dec, _ = tissue_surface(seg.labels, 3, target_edge_mm=3.0)
    assert dec.n_cells < 0.5 * full.n_cells
    assert abs(dec.volume) == pytest.approx(abs(full.volume), rel=0.02)
    assert dec.n_open_edges == 0 and dec.is_manifold


def test_empty_tissue_is_an_error():
    seg = make_seg(ball(16, 5) * 3, {"adipose": 3, "iliopsoas": 10})
    with pytest.raises(InputError, match="empty tissue"):
        surfaces(seg, ["iliopsoas"])
