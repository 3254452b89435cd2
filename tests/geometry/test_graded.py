"""geometry.graded: CGAL's graded interfaces of a label map (the compiled helper), and its errors."""

from __future__ import annotations

import numpy as np
import pytest

from needletissue.errors import InputError
from needletissue.geometry import graded
from needletissue.geometry.smooth import CORRIDOR, label_volumes
from needletissue.geometry.tetmesh import unique_rows


R = 8.0   # mm, the ball's radius


@pytest.fixture(scope="module")
def ball(cgal):
    """A ball (label 2) in a block (label 1), 1 mm voxels, a corridor (label 255) 22 mm from the ball's
    centre; edges 0.75 mm at the corridor growing to 2 mm at 30 mm."""
    n = 48
    z, y, x = np.mgrid[:n, :n, :n].astype(float)
    arr = np.ones((n, n, n), np.uint8)
    arr[(x - 14) ** 2 + (y - 24) ** 2 + (z - 24) ** 2 <= R * R] = 2
    arr[20:28, 20:28, 34:40] = CORRIDOR
    h = graded.size_field(arr, (1.0, 1.0, 1.0), CORRIDOR, 0.75, 2.0, 30.0)
    return arr, h, graded.graded_interfaces(arr, (1.0, 1.0, 1.0), h, restore=False)


def test_graded_interfaces_close_every_tissue_and_follow_the_ball(ball):
    """Each label's faces close (every edge twice), the ball's volume converges to its voxels' as the
    triangles shrink (an inscribed polyhedron loses ~e^2 / R^2: measured -7.1 / -3.5 / -2.3 / -1.5 % at mean
    edges 2.9 / 2.0 / 1.6 / 1.1 mm), its interface lies within one voxel of the sphere, and the faces are
    oriented out of side a (the volumes add up to the block)."""
    arr, _, s = ball
    coarse = graded.graded_interfaces(arr, (1.0, 1.0, 1.0), graded.size_field(arr, (1, 1, 1), CORRIDOR, 1.5, 6.0, 30.0),
                                      restore=False)
    for lab in np.unique(s.boundary_labels):
        f = s.faces[(s.boundary_labels == lab).any(1)]
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        assert np.all(unique_rows(e)[2] == 2), lab
    vol = label_volumes(s.points, s.faces, s.boundary_labels)
    voxels = np.bincount(arr.ravel(), minlength=256)
    err = vol[2] / voxels[2] - 1
    err_coarse = label_volumes(coarse.points, coarse.faces, coarse.boundary_labels)[2] / voxels[2] - 1
    assert -0.02 < err < 0 and err_coarse < 3 * err
    assert vol[1] + vol[2] + vol[CORRIDOR] == pytest.approx(arr.size, rel=0.01)
    on_ball = np.unique(s.faces[(s.boundary_labels == 2).any(1)])
    r = np.linalg.norm(s.points[on_ball] - (14, 24, 24), axis=1)
    assert np.abs(r - R).max() < 1.0


def test_graded_interfaces_grow_away_from_the_corridor_and_repeat(ball, cgal):
    """Triangles near the corridor are smaller than those far from it (the size field), and a second run
    gives the same triangles to the bit (CGAL seeded, sequential)."""
    arr, h, s = ball
    t = s.points[s.faces]
    edge = np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2).mean(1)
    dist = np.linalg.norm(t.mean(1) - (37, 24, 24), axis=1)
    assert edge[dist > 30].mean() > 1.8 * edge[dist < 10].mean()
    again = graded.graded_interfaces(arr, (1.0, 1.0, 1.0), h, restore=False)
    assert np.array_equal(again.points, s.points) and np.array_equal(again.faces, s.faces)


def test_restored_interfaces_keep_each_labels_volume_and_the_fixed_faces(ball):
    """With the volumes restored (the default), the coarse ball (-7 % raw) encloses its voxels' volume to
    0.1 %, still within one voxel of the sphere, the corridor's faces and the cut planes do not move, and a
    target volume given for a label is the one it gets."""
    arr, _, _ = ball
    h = graded.size_field(arr, (1, 1, 1), CORRIDOR, 1.5, 6.0, 30.0)
    raw = graded.graded_interfaces(arr, (1.0, 1.0, 1.0), h, restore=False)
    s = graded.graded_interfaces(arr, (1.0, 1.0, 1.0), h, fixed_labels=(CORRIDOR,))
    assert np.array_equal(raw.faces, s.faces)
    voxels = np.bincount(arr.ravel(), minlength=256).astype(float)
    vol = label_volumes(s.points, s.faces, s.boundary_labels)
    assert raw.info["volume_change_cgal"][2] < -0.03
    assert abs(vol[2] / voxels[2] - 1) < 1e-3   # (the block keeps the box's rounded edges: its faces are fixed)
    on_ball = np.unique(s.faces[(s.boundary_labels == 2).any(1)])
    assert np.abs(np.linalg.norm(s.points[on_ball] - (14, 24, 24), axis=1) - R).max() < 1.0
    corridor = np.unique(s.faces[(s.boundary_labels == CORRIDOR).any(1)])
    plane = np.isclose(s.points, -0.5).any(1) | np.isclose(s.points, len(arr) - 0.5).any(1)
    for fixed in (corridor, np.flatnonzero(plane)):
        assert len(fixed) and np.array_equal(s.points[fixed], raw.points[fixed])
    target = voxels * 1.0
    target[2] *= 1.02
    bigger = graded.graded_interfaces(arr, (1.0, 1.0, 1.0), h, volumes=target)
    assert label_volumes(bigger.points, bigger.faces, bigger.boundary_labels)[2] == pytest.approx(target[2], rel=1e-3)


def test_pieces_smaller_than_their_element_are_merged_and_the_rest_kept():
    """A 2x2x2-voxel pocket where elements are 3 mm goes to its surroundings, the same pocket where they are
    0.75 mm stays, as do each label's largest piece and the outside that reaches the border; a small air
    bubble (0) inside is filled."""
    arr = np.ones((20, 20, 30), np.uint8)
    arr[:, :, :5] = 0                      # outside, on the border
    arr[4:6, 4:6, 8:10] = 2                # fine pocket (h 0.75)
    arr[4:6, 4:6, 24:26] = 2               # coarse pocket (h 3)
    arr[10:16, 10:16, 10:16] = 2           # label 2's largest piece
    arr[12:14, 12:14, 26:28] = 0           # air bubble (h 3)
    h = np.where(np.arange(30) < 15, 0.75, 3.0).astype(np.float32)[None, None, :] * np.ones(arr.shape, np.float32)
    out, n = graded.drop_small_components(arr, (1, 1, 1), h)
    assert n == 16
    assert (out[4:6, 4:6, 24:26] == 1).all() and (out[12:14, 12:14, 26:28] == 1).all()
    assert (out[4:6, 4:6, 8:10] == 2).all() and (out[10:16, 10:16, 10:16] == 2).all() and (out[:, :, :5] == 0).all()
    assert np.count_nonzero(out != arr) == n


def test_missing_compiler_or_cgal_is_named(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-xyz")
    with pytest.raises(graded.MissingCGAL, match="no C.. compiler .* libcgal-dev"):
        graded.helper()
    monkeypatch.setenv("CXX", "true")   # a "compiler" that finds no headers
    with pytest.raises(graded.MissingCGAL, match="no CGAL headers"):
        graded.helper()


def test_bad_graded_settings_name_the_field():
    from needletissue.geometry.tetmesh import MeshConfig

    with pytest.raises(InputError, match="far_size"):
        MeshConfig(size=3.0, far_size=2.0, method="smooth").validate()
    with pytest.raises(InputError, match="far_size.*smooth"):
        MeshConfig(size=3.0, far_size=12.0).validate()
    with pytest.raises(InputError, match="cell_size"):
        graded.mesh_labels(np.ones((4, 4, 4), np.uint8), (1, 1, 1), np.zeros((4, 4, 4)))
    with pytest.raises(InputError, match="labels"):
        graded.mesh_labels(np.zeros((4, 4, 4), np.uint8), (1, 1, 1), np.ones((4, 4, 4)))
    with pytest.raises(InputError, match="labels must be 0..255"):
        graded.mesh_labels(np.full((4, 4, 4), 300), (1, 1, 1), np.ones((4, 4, 4)))


def test_fe_pelvis_smooth_without_cgal_says_what_to_install(run_cli, monkeypatch):
    """`fe pelvis` (its default mesher, graded) where no compiler is found: exit 1 before any meshing, naming the
    package and the uniform and box alternatives."""
    monkeypatch.setenv("CXX", "no-such-compiler-xyz")
    for args in (["--mesher", "smooth"], ["--ssm"], []):
        code, out, err = run_cli("fe", "pelvis", *args, "--force", "100")
        assert code == 1 and "libcgal-dev" in err and "--far-size" in err and "--mesher box" in err, (args, err)
