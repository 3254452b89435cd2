"""Aim correction: the clamp pose a robot must command so that the bone fragment reaches its target.

The bone fragment moves rigidly (the pins are held in it); the construct between bone and clamp deflects
under the wrench the robot applies, so the bone lags the clamp by the frame model's relative pose
(c, Q) (clamp relative to bone). With the bone at its target pose (R_b, t_b; rotation about the bone
point B, the bone surface under the clamp centre), the clamp must be at

    C_cmd = B + t_b + R_b (C + u_C - B),     R_cmd = R_b Q,

with u_C, Q the clamp-centre displacement and rotation relative to the bone under the wrench in the
bone's frame. A wrench given in the world frame is W_bone = R_b^T W (one solve). A wrench measured by a
force sensor in the clamp (wrench_frame="clamp") turns with the clamp: W_bone = Q W_sensor, and Q
depends on the answer: fixed-point iteration, each solve warm-started from the last (the model is
nonlinear), until Q changes by less than tol_rad. The residual is the bone pose that the commanded clamp
pose gives with the last solve's deflection, minus the target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from needletissue.errors import ConvergenceError, InputError
from needletissue.frame.model import FrameModel
from needletissue.frame.solver import FrameResult, _vec, expm, logm, pose, solve

FRAMES = ("world", "clamp")


@dataclass(frozen=True)
class Compensation:
    clamp_displacement_mm: tuple   # command: displacement of the clamp centre (world, from the unloaded pose)
    clamp_rotation_rad: tuple      # command: rotation vector of the clamp (world)
    residual_mm: tuple             # predicted bone-point position minus target
    residual_rad: tuple            # predicted bone rotation minus target (rotation vector of R_pred R_b^T)
    correction_mm: tuple           # command minus the naive rigid command (what the deflection costs)
    iterations: int                # fixed-point passes (1 for a world-frame wrench)
    state: np.ndarray              # Newton unknowns of the last solve (warm start of the next call)
    result: FrameResult | None     # the full frame solve at the final wrench (bone frame), detail=True

    def to_json(self) -> dict:
        return {"clamp_displacement_mm": list(self.clamp_displacement_mm),
                "clamp_rotation_rad": list(self.clamp_rotation_rad), "residual_mm": list(self.residual_mm),
                "residual_rad": list(self.residual_rad), "correction_mm": list(self.correction_mm),
                "iterations": self.iterations,
                "result": None if self.result is None else self.result.to_json()}


def compensate(target_mm=(0.0, 0.0, 0.0), target_rad=(0.0, 0.0, 0.0), force=None, moment=None,
               model: FrameModel | None = None, *, wrench_frame: str = "world", tol_rad: float = 1e-10,
               max_iter: int = 30, initial=None, detail: bool = False,
               error_estimate: bool = False) -> Compensation:
    """Clamp pose to command so that the bone point B moves by target_mm and the bone turns by
    target_rad (rotation vector, about B), under the wrench force (N) / moment (N mm) at the load point.

    detail=False (the control loop): only the compiled pose solve; `result` is None and `state` the
    Newton unknowns for the next call's `initial`. detail=True: `result` is the full FrameResult."""
    model = FrameModel() if model is None else model
    if wrench_frame not in FRAMES:
        raise InputError("wrench_frame", f"must be one of {FRAMES}, got {wrench_frame!r}")
    t_b = _vec("target_mm", target_mm)
    R_b = expm(_vec("target_rad", target_rad))
    F = _vec("force_N", force)
    M = _vec("moment_Nmm", moment)
    B = np.array([*model.centre_xy, 0.0])
    C = np.array(model.clamp_centre_mm)
    Q = np.eye(3)
    state = initial
    for it in range(1, max_iter + 1):
        Rw = R_b.T if wrench_frame == "world" else Q
        if detail:
            r = solve(Rw @ F, Rw @ M, model, initial=state, error_estimate=error_estimate)
            state, uC, rot = r.state, np.array(r.clamp_displacement_mm), r.clamp_rotation_rad
        else:
            uC, rot, _, state = pose(Rw @ F, Rw @ M, model, initial=state)
            r = None
        Q_new = expm(rot)
        change = float(np.linalg.norm(logm(Q_new @ Q.T)))
        Q = Q_new
        if wrench_frame == "world" or change <= tol_rad:
            break
    else:
        raise ConvergenceError(f"compensate: the clamp-frame wrench did not settle in {max_iter} passes "
                               f"(last change {change:.3g} rad)")
    C_cmd = B + t_b + R_b @ (C + uC - B)
    R_cmd = R_b @ Q
    # prediction: the bone pose the command produces when the sensor wrench is turned by the clamp's
    # final rotation (one more solve), minus the target
    if wrench_frame == "world":
        res_t, res_r = np.zeros(3), np.zeros(3)
    else:
        u2, rot2, _, _ = pose(Q @ F, Q @ M, model, initial=state)
        Q2 = expm(rot2)
        R_pred = R_cmd @ Q2.T
        B_pred = C_cmd - R_pred @ (C + u2 - B)
        res_t = B_pred - (B + t_b)
        res_r = logm(R_pred @ R_b.T)
    naive = B + t_b + R_b @ (C - B)
    return Compensation(tuple((C_cmd - C).tolist()), tuple(logm(R_cmd).tolist()), tuple(res_t.tolist()),
                        tuple(res_r.tolist()), tuple((C_cmd - naive).tolist()), it, state, r)
