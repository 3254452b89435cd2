"""needletissue.geometry: surfaces, conforming tetrahedral meshes, thickness along needle paths,
offset layers around bone surfaces, extra solids (needles, clamp) in the label map.

    from needletissue.geometry import surfaces, tet_mesh, thickness_along
    mesh = tet_mesh(seg, size=3.0); mesh.write_msh("model.msh")   # named physical volumes per tissue
    mesh = tet_mesh(seg, size=3.0, method="smooth")               # smooth shared tissue interfaces

See docs/imaging.md.
"""

_EXPORTS = {
    "surfaces": "surfaces", "tissue_surface": "surfaces", "tet_mesh": "tetmesh",
    "MeshConfig": "tetmesh", "TetMesh": "tetmesh", "thickness_along": "thickness",
    "site_thickness": "thickness", "from_surfaces": "ssm", "mean_pelvis": "ssm", "LayerConfig": "ssm",
    "resample": "solids", "paint_cylinder": "solids", "paint_box": "solids",
    "smooth_tet_mesh": "smooth", "smooth_interfaces": "smooth", "mesh_fidelity": "fidelity",
}


def __getattr__(name):  # lazy imports
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(name)
