"""Offset layers around bone surfaces, and solids painted into the label map."""

import numpy as np
import pytest
import pyvista as pv

from labelmaps import make_seg, nested_boxes
from needletissue.errors import InputError
from needletissue.geometry.solids import paint_cylinder, resample
from needletissue.geometry.ssm import LayerConfig, from_surfaces
from needletissue.geometry.tetmesh import MeshConfig, tet_mesh
from needletissue.geometry.thickness import thickness_along


def test_offset_layers_have_the_given_thickness(tmp_path):
    p = tmp_path / "ball.stl"
    pv.Sphere(radius=20.0, theta_resolution=60, phi_resolution=60).save(str(p))
    h = 1.5
    seg = from_surfaces([p], LayerConfig(muscle_thickness=22.0, adipose_thickness=10.0, spacing=h))
    assert set(seg.tissues) == {"cortical_bone", "cancellous_bone", "muscle", "adipose"}
    # radial path from outside to the centre: adipose 10, muscle 22 (+- one voxel of staircase)
    r = thickness_along(seg, (80.0, 0.0, 0.0), (-1, 0, 0), step_mm=0.1)
    assert r.bone_hit
    assert r.thickness_by_tissue["adipose"] == pytest.approx(10.0, abs=h)
    assert r.thickness_by_tissue["muscle"] == pytest.approx(22.0, abs=h)
    assert r.bone_point[0] == pytest.approx(20.0, abs=h)
    # shell volumes against the analytic spherical shells
    v = seg.volumes_mm3()
    shell = lambda a, b: 4 / 3 * np.pi * (b ** 3 - a ** 3)  # noqa: E731
    assert v["muscle"] == pytest.approx(shell(20, 42), rel=0.05)
    assert v["adipose"] == pytest.approx(shell(42, 52), rel=0.05)


def test_open_surface_is_rejected(tmp_path):
    p = tmp_path / "open.stl"
    pv.Sphere(radius=5).clip("z").save(str(p))
    with pytest.raises(InputError, match="open.stl.*not watertight"):
        from_surfaces([p])


def test_needle_cylinder_becomes_a_conforming_region():
    arr, tissues = nested_boxes()
    seg = make_seg(arr, tissues, spacing=2.0, direction=(1, 0, 0, 0, 1, 0, 0, 0, 1), origin=(0, 0, 0))
    fine = resample(seg, 0.5)
    assert fine.labels.GetSize() == (64, 64, 64)
    # a 4 mm diameter pin from outside the adipose into the bone cube
    p0, p1, r = np.array([15.0, 15.0, 30.0]), np.array([15.0, 15.0, 10.0]), 2.0
    paint_cylinder(fine, "needle_1", p0, p1, r)
    vol = fine.volumes_mm3()["needle_1"]
    assert vol == pytest.approx(np.pi * r ** 2 * 20.0, rel=0.08)
    m = tet_mesh(fine, config=MeshConfig(size=1.0, coarsen=False))
    assert "needle_1" in m.regions and m.materials["needle_1"] == "needle"
    assert m.quality().volume_mm3_by_region["needle_1"] == pytest.approx(vol, rel=1e-9)
    with pytest.raises(InputError, match="already exists"):
        paint_cylinder(fine, "needle_1", p0, p1, r)
