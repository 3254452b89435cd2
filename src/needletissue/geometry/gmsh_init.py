"""gmsh.initialize() that leaves the process's signal handling as it was.

gmsh's C++ initialisation resets SIGTERM to its default action at the OS level, while Python still
reports its own handler. After any in-process mesh (the anatomical model, TetGen/gmsh meshes), SIGTERM
then killed the command outright: no `finally`, so temporary folders, child processes (the figure
renderer went on and wrote its PNG after the command had gone) and half a result folder stayed behind.
"""

from __future__ import annotations

import signal
import threading

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def initialize() -> None:
    """gmsh.initialize(interruptible=False), then Python's SIGINT/SIGTERM handlers installed again."""
    import gmsh

    gmsh.initialize(interruptible=False)
    rearm_signals()


def rearm_signals() -> None:
    """Install again, at the OS level, the Python handlers of SIGINT and SIGTERM (main thread only:
    Python allows signal.signal nowhere else)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for s in _SIGNALS:
        handler = signal.getsignal(s)
        if handler is not None:  # None: not set from Python, nothing to restore
            signal.signal(s, handler)
