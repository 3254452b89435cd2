"""The frame model's defaults are `fe needle`'s (copied so that frame imports neither geometry nor
FElupe): this test fails when one side changes without the other."""

from needletissue import materials
from needletissue.frame import FrameModel
from needletissue.geometry.needle import NeedleGeometry
from needletissue.models.needle import MATERIALS
from needletissue.ritz import DEFAULT_LAYERS


def test_geometry_defaults_equal_fe_needle():
    g, m = NeedleGeometry(), FrameModel()
    assert m.needles == g.needles and m.diameter_mm == g.diameter and m.spacing_mm == g.spacing
    assert m.depth_mm == g.depth and m.free_length_mm == g.free_length and m.cortex_mm == g.cortical_thickness
    assert m.clamp_length_mm == g.grip_length and m.clamp_width_mm == g.clamp_width
    assert m.clamp_overhang_mm == g.clamp_overhang
    assert [(la.name, la.thickness_mm) for la in m.layers] == [("muscle", g.muscle_thickness),
                                                                 ("adipose", g.adipose_thickness)]
    assert m.layers == DEFAULT_LAYERS
    assert [x for x, _ in m.needle_xy] == list(g.needle_x) and all(y == 0 for _, y in m.needle_xy)
    assert m.load_point_mm == (0.0, 0.0, g.gripper_centre)
    lo, hi = m.clamp_box_mm
    assert (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]) == g.clamp_box


def test_material_defaults_equal_fe_needle():
    m = FrameModel()
    needle = materials.get(MATERIALS["needle_1"]).parameters
    cort = materials.get(MATERIALS["cortical_bone"]).parameters
    canc = materials.get(MATERIALS["cancellous_bone"]).parameters
    assert (m.youngs_modulus_MPa, m.poisson) == (needle["E"], needle["nu"])
    assert (m.cortical_E_MPa, m.cortical_nu) == (cort["E"], cort["nu"])
    assert (m.cancellous_E_MPa, m.cancellous_nu) == (canc["E"], canc["nu"])
