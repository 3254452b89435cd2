"""Errors a user can act on. The CLI turns InputError into exit code 2 without a traceback."""

from __future__ import annotations

import math
from numbers import Real


class NeedleTissueError(Exception):
    """Base class of the package's own errors."""


class InputError(NeedleTissueError, ValueError):
    """Bad input: names the field and what is allowed."""

    def __init__(self, field: str, message: str):
        self.field = field
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
