"""needletissue.imaging: CT reading and tissue segmentation.

    from needletissue.imaging import segment, Segmentation, read_ct
    seg = segment("ct.nii.gz", "labels.nii.gz"); seg.save("out")   # tissues.nii.gz + tissues.json

Coordinates: LPS mm of the image header. See docs/imaging.md.
"""

_EXPORTS = {
    "segment": "segment", "Segmentation": "segment", "SegmentationConfig": "segment",
    "material_for": "segment", "TISSUE_IDS": "segment", "read_ct": "io", "read_labels": "io",
    "read_image": "io", "data_path": "data",
}


def __getattr__(name):  # lazy: keeps `needletissue --help` fast
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(name)
