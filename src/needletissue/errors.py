"""Errors a user can act on. The CLI turns InputError into exit code 2 without a traceback."""

from __future__ import annotations

import math
from numbers import Real


class NeedleTissueError(Exception):
    """Base class of the package's own errors."""


class InputError(NeedleTissueError, ValueError):
    """Bad input: names the field and what is allowed."""

    def __init__(self, field: str, message: str):
        self.field, self.message = field, message
        super().__init__(f"{field}: {message}")


class ConvergenceError(NeedleTissueError, RuntimeError):
    """A solver did not converge; never return its state as an answer."""


def check_number(field: str, value, *, gt=None, ge=None, le=None, lt=None) -> float:
    """Return value as float or raise InputError naming the field and the allowed range."""
    if isinstance(value, bool) or not isinstance(value, Real):
        raise InputError(field, f"expected a number, got {value!r}")
    value = float(value)
    if math.isnan(value) or math.isinf(value):
        raise InputError(field, f"must be finite, got {value}")
    bounds = []
    if gt is not None:
        bounds.append(f"> {gt}")
    if ge is not None:
        bounds.append(f">= {ge}")
    if lt is not None:
        bounds.append(f"< {lt}")
    if le is not None:
        bounds.append(f"<= {le}")
    ok = (
        (gt is None or value > gt)
        and (ge is None or value >= ge)
        and (lt is None or value < lt)
        and (le is None or value <= le)
    )
    if not ok:
        raise InputError(field, f"must be {' and '.join(bounds)}, got {value}")
    return value


# One force range for every model and command (ritz, fe needle, fe pelvis, reproduce, studies): the
# reduction forces of pelvic fracture surgery reach a few hundred N (the paper: 100-300 N); 2000 N
# leaves room for studies while catching typos (1e6) that no model here is meant for.
FORCE_LIMIT_N = 2000.0
FORCE_RANGE_HELP = (f"|F| <= {FORCE_LIMIT_N:g} N, the force range shared by ritz, fe needle, fe pelvis and "
                    "reproduce (F > 0 in the FE models, whose direction is its own option)")


def check_force(field: str, value, *, signed: bool = False) -> float:
    """A reduction force in N within the shared range: 0 < F <= FORCE_LIMIT_N, or |F| <= it with signed."""
    f = check_number(field, value)
    if abs(f) > FORCE_LIMIT_N if signed else not 0 < f <= FORCE_LIMIT_N:
        allowed = f"|F| <= {FORCE_LIMIT_N:g} N" if signed else f"0 < F <= {FORCE_LIMIT_N:g} N"
        raise InputError(field, f"must be {allowed} (the force range shared by ritz, fe needle, fe pelvis "
                                f"and reproduce), got {f:g}")
    return f
