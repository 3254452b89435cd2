"""Smooth conforming tissue meshes (geometry.smooth): conformity, volumes against closed forms, quality,
fidelity to the label map."""

import numpy as np
import pytest

from labelmaps import ball, make_seg, nested_boxes
from needletissue.errors import InputError
from needletissue.geometry.fidelity import mesh_fidelity
from needletissue.geometry.smooth import edge_face_crossings, fix_edge_contacts, unique_edges
from needletissue.geometry.tetmesh import MeshConfig, face_pairs, tet_mesh

H = 2.0                                    # mm voxels
RADII = {"cancellous_bone": 6.0, "gluteus_maximus": 10.0, "adipose": 14.0}   # voxels


def nested_balls(n=32):
    a = np.zeros((n, n, n), np.uint8)
    a[ball(n, RADII["adipose"])] = 3
    a[ball(n, RADII["gluteus_maximus"])] = 10
    a[ball(n, RADII["cancellous_bone"])] = 2
    return a, {"cancellous_bone": 2, "adipose": 3, "gluteus_maximus": 10}


def shell_volumes():
    v = {k: 4 / 3 * np.pi * (H * r) ** 3 for k, r in RADII.items()}
    return {"cancellous_bone": v["cancellous_bone"], "gluteus_maximus": v["gluteus_maximus"] - v["cancellous_bone"],
            "adipose": v["adipose"] - v["gluteus_maximus"]}


@pytest.fixture(scope="module")
def balls():
    arr, tissues = nested_balls()
    seg = make_seg(arr, tissues, spacing=H)
    cfg = MeshConfig(size=H, method="smooth")
    mesh = tet_mesh(seg, config=cfg)
    return seg, cfg, mesh, mesh_fidelity(seg, mesh, cfg)


def test_edge_contacts_are_filled():
    a = np.zeros((3, 4, 4), np.uint8)
    a[1, 1, 1] = a[1, 2, 2] = 5          # two voxels touching along an edge only
    b, n = fix_edge_contacts(a)
    assert n == 1 and b[1, 1, 2] + b[1, 2, 1] == 5   # one of the two gap voxels joins them
    assert fix_edge_contacts(b)[1] == 0


def test_crossing_triangles_are_found_and_touching_ones_not():
    p = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0],                # triangle in z = 0
                  [0.5, 0.5, -1], [0.5, 0.5, 1], [3, 3, 1]], float)  # triangle piercing it
    f = np.array([[0, 1, 2], [3, 4, 5]])
    e, fc = edge_face_crossings(p, f)
    # the intersection segment has two ends: edge 3-4 pierces face 0, an edge of face 0 pierces face 1
    found = {(tuple(unique_edges(f)[i]), j) for i, j in zip(e, fc)}
    assert ((3, 4), 0) in found and len(found) == 2 and {j for _, j in found} == {0, 1}
    p[3:, 2] += 1.0                                                # now it only touches z = 0 at a vertex
    assert len(edge_face_crossings(p, f)[0]) == 0


def test_mesh_is_conforming_with_one_tissue_per_subdomain(balls):
    seg, _, mesh, _ = balls
    assert set(mesh.regions) == set(seg.tissues)
    tag = mesh.region_ids()
    inter, free, faces = face_pairs(mesh.cells, tag)
    key = np.sort(faces, axis=1)
    _, cnt = np.unique(key, axis=0, return_counts=True)
    assert cnt.max() == 2                                  # no face in three tetrahedra: no overlap
    assert len(np.unique(np.round(mesh.points, 9), axis=0)) == len(mesh.points)   # no duplicate nodes
    # the free boundary is the outer sphere only; interfaces are shared faces, two per nested sphere
    r_free = np.linalg.norm(mesh.points[np.unique(faces[free])] - mesh.points.mean(0), axis=1)
    assert r_free.min() > H * (RADII["adipose"] - 1)
    assert len(inter) > 0
    bone = mesh.cells[mesh.regions["cancellous_bone"]]
    musc = mesh.cells[mesh.regions["gluteus_maximus"]]
    shared = np.intersect1d(bone, musc)
    bs = np.unique(mesh.surfaces["bone_surface"])
    assert np.array_equal(np.sort(bs), np.sort(shared))      # bone surface nodes = nodes of both tissues


def test_volumes_match_label_map_and_spheres(balls):
    seg, _, mesh, fid = balls
    vol = mesh.quality().volume_mm3_by_region
    assert fid.worst_volume_error() < 0.005                  # volume restoration (label volumes)
    for name, v in shell_volumes().items():                  # analytic, incl. the voxelisation error
        assert vol[name] == pytest.approx(v, rel=0.03)


def test_quality_and_fidelity_bounds(balls):
    _, _, mesh, fid = balls
    assert fid.n_inverted == 0 and fid.n_slivers == 0
    assert fid.min_dihedral_deg >= 10.0
    assert fid.p01_dihedral_deg >= 19.0
    assert min(fid.dice.values()) >= 0.9
    assert fid.hausdorff95_voxels <= 1.0
    assert mesh.info["method"] == "smooth" and mesh.info["subdomain_label_purity"] > 0.9


def test_interfaces_are_smooth_not_staircases(balls):
    # a staircase sphere has ~50 % more area than the sphere; the smooth interface is within 5 %
    _, _, mesh, _ = balls
    f = mesh.surfaces["bone_surface"]
    p = mesh.points[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert area == pytest.approx(4 * np.pi * (H * RADII["cancellous_bone"]) ** 2, rel=0.05)


def test_nested_boxes_keep_their_volumes():
    arr, tissues = nested_boxes()
    seg = make_seg(arr, tissues, spacing=H)
    mesh = tet_mesh(seg, config=MeshConfig(size=H, method="smooth"))
    vol = mesh.quality().volume_mm3_by_region
    side = {"cortical_bone": 4, "gluteus_maximus": 8, "adipose": 12}      # voxels
    exact = {"cortical_bone": 4 ** 3, "gluteus_maximus": 8 ** 3 - 4 ** 3, "adipose": 12 ** 3 - 8 ** 3}
    for name, nvox in exact.items():
        assert vol[name] == pytest.approx(nvox * H ** 3, rel=0.03), name
    assert side  # cube sides documented above


def test_unknown_method_is_an_input_error():
    with pytest.raises(InputError, match="method"):
        MeshConfig(method="marching").validate()


def _cli(monkeypatch, capsys, *args):
    import sys

    from needletissue.cli import main

    monkeypatch.setattr(sys, "argv", ["needletissue", *map(str, args)])
    code = 0
    try:
        main()
    except SystemExit as exc:
        code = exc.code or 0
    out = capsys.readouterr()
    return code, out.out, out.err


def test_mesh_command_smooth_method(tmp_path, monkeypatch, capsys):
    import json

    arr, tissues = nested_boxes()
    seg = make_seg(arr, tissues, spacing=H)
    seg.save(tmp_path / "seg")
    code, out, err = _cli(monkeypatch, capsys, "mesh", tmp_path / "seg", "--out", tmp_path / "m",
                          "--method", "smooth", "--fidelity", "--no-surfaces")
    assert code == 0, err
    res = json.loads((tmp_path / "m" / "results.json").read_text(encoding="utf-8"))
    assert res["mesh_info"]["method"] == "smooth"
    assert res["fidelity"]["n_inverted"] == 0 and res["fidelity"]["min_dihedral_deg"] > 0
    code, _, err = _cli(monkeypatch, capsys, "mesh", tmp_path / "seg", "--out", tmp_path / "m2",
                        "--method", "marching")
    assert code == 2 and "method" in err and "Traceback" not in err

