"""Tetrahedral meshes: quality metrics against closed forms, conformity, exact region volumes, .msh."""

import meshio
import numpy as np
import pytest

from labelmaps import make_seg, nested_boxes
from needletissue.errors import InputError
from needletissue.geometry.tetmesh import MeshConfig, regular_tet_volume, tet_mesh, tet_quality


def test_quality_of_the_regular_and_the_corner_tetrahedron():
    reg = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    q = tet_quality(reg, np.array([[0, 1, 2, 3]]))
    assert q["radius_ratio"][0] == pytest.approx(1.0, abs=1e-12)
    assert q["min_dihedral"][0] == pytest.approx(np.degrees(np.arccos(1 / 3)), abs=1e-9)  # 70.53 deg
    assert abs(q["volume"][0]) == pytest.approx(regular_tet_volume(np.sqrt(8)), rel=1e-12)
    corner = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    q = tet_quality(corner, np.array([[0, 1, 2, 3]]))
    # three right dihedral angles at the corner, three arccos(1/sqrt(3)) = 54.74 deg at the slanted face
    assert q["max_dihedral"][0] == pytest.approx(90.0, abs=1e-9)
    assert q["min_dihedral"][0] == pytest.approx(np.degrees(np.arccos(1 / np.sqrt(3))), abs=1e-9)
    # r_in = 1/(3+sqrt3), R = sqrt3/2 -> 3 r_in / R = 2 sqrt3 / (3 + sqrt3)
    assert q["radius_ratio"][0] == pytest.approx(2 * np.sqrt(3) / (3 + np.sqrt(3)), rel=1e-12)


@pytest.fixture(scope="module")
def boxes_mesh():
    arr, tissues = nested_boxes()
    seg = make_seg(arr, tissues)
    return seg, tet_mesh(seg, size=2.0)


def test_region_volumes_are_the_voxel_volumes(boxes_mesh):
    seg, mesh = boxes_mesh
    vox = 2.0 ** 3
    counts = {n: int((seg.array() == i).sum()) for n, i in seg.tissues.items()}
    q = mesh.quality()
    for name, c in counts.items():
        assert q.volume_mm3_by_region[name] == pytest.approx(c * vox, rel=1e-9)
    assert q.min_dihedral_deg > 0 and q.min_radius_ratio > 0      # no inverted/flat element
    assert np.all(tet_quality(mesh.points, mesh.cells)["volume"] > 0)


def test_mesh_is_conforming(boxes_mesh):
    _, mesh = boxes_mesh
    faces = np.sort(np.concatenate([mesh.cells[:, f] for f in
                                    ([0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3])]), axis=1)
    _, cnt = np.unique(faces, axis=0, return_counts=True)
    assert cnt.max() == 2  # every face shared by at most two tetrahedra (no overlaps)
    # the free faces are exactly the outer adipose box surface: area 6 * (24 mm)^2
    b = mesh.points[mesh.surfaces["boundary"]]
    area = 0.5 * np.linalg.norm(np.cross(b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]), axis=1).sum()
    assert area == pytest.approx(6 * 24.0 ** 2, rel=1e-9)
    # interface nodes are shared: the bone surface (8 mm cube) belongs to bone and muscle cells
    bs = np.unique(mesh.surfaces["bone_surface"])
    in_bone = np.isin(bs, mesh.cells[mesh.regions["cortical_bone"]])
    in_musc = np.isin(bs, mesh.cells[mesh.regions["gluteus_maximus"]])
    assert in_bone.all() and in_musc.all()
    s = mesh.points[mesh.surfaces["bone_surface"]]
    area = 0.5 * np.linalg.norm(np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]), axis=1).sum()
    assert area == pytest.approx(6 * 8.0 ** 2, rel=1e-9)


def test_physical_coordinates_follow_the_header(boxes_mesh):
    seg, mesh = boxes_mesh
    # adipose box spans voxel indices 2..13 -> voxel edges 1.5..13.5 -> x = 10 - 2*[1.5, 13.5]
    lo, hi = mesh.points.min(0), mesh.points.max(0)
    assert lo[0] == pytest.approx(10 - 27.0) and hi[0] == pytest.approx(10 - 3.0)
    assert lo[2] == pytest.approx(5 + 3.0) and hi[2] == pytest.approx(5 + 27.0)


def test_size_control(boxes_mesh):
    seg, coarse = boxes_mesh
    fine = tet_mesh(seg, size=1.5)  # below the 2 mm voxels: volume bound
    v = tet_quality(fine.points, fine.cells)["volume"]
    # TetGen's final smoothing/flips may exceed the bound on a few elements (measured max 1.36x)
    assert np.mean(v <= regular_tet_volume(1.5) * (1 + 1e-6)) > 0.99  # measured 0.994
    assert v.max() < 1.5 * regular_tet_volume(1.5)
    assert len(fine.cells) > 4 * len(coarse.cells)
    # above the voxel size: 4 mm coarsening, every interface node on the 4 mm lattice
    big = tet_mesh(seg, size=4.0)
    s = big.points[np.unique(big.surfaces["bone_surface"])]
    frac = (s - s.min(0)) / 4.0
    assert np.allclose(frac, np.round(frac), atol=1e-9)


def test_msh_has_named_physical_groups(boxes_mesh, tmp_path):
    _, mesh = boxes_mesh
    path = mesh.write_msh(tmp_path / "m.msh")
    m = meshio.read(path)
    for name, ids in mesh.regions.items():
        assert name in m.field_data and m.field_data[name][1] == 3
        n = sum(len(c) for c in m.cell_sets_dict[name].values())
        assert n == len(ids)
    assert m.field_data["bone_surface"][1] == 2
    assert np.allclose(m.points, mesh.points)
    assert mesh.materials == {"cortical_bone": "cortical_bone", "adipose": "adipose",
                              "gluteus_maximus": "muscle"}


def test_vtu_round_trips_through_meshio(boxes_mesh, tmp_path):
    _, mesh = boxes_mesh
    m = meshio.read(mesh.write_vtu(tmp_path / "m.vtu"))
    assert np.array_equal(m.points, mesh.points) and np.array_equal(m.cells_dict["tetra"], mesh.cells)
    assert np.array_equal(m.cell_data["region"][0], mesh.region_ids())
    assert not list(tmp_path.glob(".*"))                 # no temporary file left


def test_crop_and_regions(boxes_mesh):
    seg, _ = boxes_mesh
    m = tet_mesh(seg, config=MeshConfig(size=2.0, regions=["cortical_bone", "gluteus_maximus"]))
    assert set(m.regions) == {"cortical_bone", "gluteus_maximus"}
    vox = 8.0
    assert m.quality().volume_mm3_by_region["gluteus_maximus"] == pytest.approx((8 ** 3 - 4 ** 3) * vox)
    with pytest.raises(InputError, match="unknown region"):
        tet_mesh(seg, config=MeshConfig(regions=["liver"]))
    with pytest.raises(InputError, match="does not overlap"):
        tet_mesh(seg, config=MeshConfig(crop=(500, 600, 0, 10, 0, 10)))
    with pytest.raises(InputError, match="size"):
        MeshConfig(size=0).validate()


def test_tetgen_bounds_per_route_and_overrides():
    # the smooth route leaves the angles to its optimisation (no dihedral bound, tighter ratio)
    assert MeshConfig(method="smooth").tetgen_bounds() == (1.6, 0.0)
    assert MeshConfig(method="voxel").tetgen_bounds() == (2.0, 10.0)
    assert MeshConfig(method="smooth", min_dihedral=10, max_radius_edge=2).validate().tetgen_bounds() == (2, 10)
    with pytest.raises(InputError, match="min_dihedral"):
        MeshConfig(min_dihedral=40).validate()
    with pytest.raises(InputError, match="max_radius_edge"):
        MeshConfig(max_radius_edge=1.0).validate()


def test_bone_surface_split_by_bone(boxes_mesh):
    import SimpleITK as sitk

    seg, _ = boxes_mesh
    arr = seg.array()
    bones = np.zeros_like(arr)
    bone = arr == seg.tissues["cortical_bone"]
    bones[bone] = 1                               # sacrum ...
    bones[:, :, 8:][bone[:, :, 8:]] = 2           # ... and hip_left on the other half (split at i = 8)
    img = sitk.GetImageFromArray(bones)
    img.CopyInformation(seg.labels)
    seg.bones = img
    m = tet_mesh(seg, size=2.0)
    a, b = m.surfaces["bone_surface_sacrum"], m.surfaces["bone_surface_hip_left"]
    assert len(a) + len(b) == len(m.surfaces["bone_surface"])
    area = lambda f: 0.5 * np.linalg.norm(np.cross(*(m.points[f][:, k] - m.points[f][:, 0]  # noqa: E731
                                                     for k in (1, 2))), axis=1).sum()
    # 8 mm bone cube split into two 4 x 8 x 8 mm halves: one 8 x 8 end face + four 4 x 8 sides each
    assert area(a) == pytest.approx(64.0 + 4 * 32.0, rel=1e-9)
    assert area(b) == pytest.approx(area(a), rel=1e-9)
    seg.bones = None


def test_bone_box_crop(boxes_mesh):
    seg, _ = boxes_mesh
    box = seg.bone_box(margin_mm=2.0)  # bone cube: voxel centres 6..9 -> x = 10 - 2*[6, 9]
    assert box[0] == pytest.approx(10 - 18 - 2.0) and box[1] == pytest.approx(10 - 12 + 2.0)
    m = tet_mesh(seg, size=2.0, crop=box)
    # voxels 5..10 kept: bone cube + one muscle layer
    assert set(m.regions) == {"cortical_bone", "gluteus_maximus"}
    assert m.quality().volume_mm3_by_region["gluteus_maximus"] == pytest.approx((6 ** 3 - 4 ** 3) * 8.0)
