"""Needle-frame reduced-order model: n Schanz pins (geometrically exact rods) from their tips in the
bone (elastic foundation: cortex and cancellous bone) through the tissue layers (the paper's springs)
to a clamp (rigid, or an elastic bar: clamp="elastic"), loaded by a full wrench. docs/frame.md.

    from needletissue import frame
    r = frame.solve(force=(0, 300, 0))                      # fe needle's defaults: 2 pins, 5 mm, l = 100
    r = frame.solve((0, 300, 0), model=frame.FrameModel(needles=1, root="rigid", tissue=False,
                                                        clamp_length_mm=0, free_length_mm=84))
    c = frame.compensate(target_mm=(0, 5, 0), force=(0, 300, 0))     # clamp pose to command
    params, ci = frame.calibrate(points)                    # foundation and tissue factors from FE

The compiled kernel (Numba) is imported on first solve, so that `needletissue --help` stays fast.
"""

from needletissue.frame.model import FrameModel

_LAZY = {
    "solve": "solver", "solve_wrenches": "solver", "solve_batch": "solver", "pose": "solver",
    "BatchResult": "solver", "FrameResult": "solver", "NeedleResult": "solver",
    "compensate": "aim", "Compensation": "aim",
    "calibrate": "fitting", "calibration": "fitting", "CalibrationPoint": "fitting", "Calibration": "fitting",
    "plot_frame": "plot",
}

__all__ = ["FrameModel", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"needletissue.frame.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'needletissue.frame' has no attribute {name!r}")
