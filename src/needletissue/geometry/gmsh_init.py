"""gmsh.initialize() that leaves the process's signal handling as it was.

gmsh's C++ initialisation resets SIGTERM to its default action at the OS level, while Python still
reports its own handler. After any in-process mesh (the anatomical model, TetGen/gmsh meshes), SIGTERM
then killed the command outright: no `finally`, so temporary folders, child processes (the figure
renderer went on and wrote its PNG after the command had gone) and half a result folder stayed behind.
"""

from __future__ import annotations

import importlib
import os
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


def import_holding_signals(*modules: str) -> None:
    """Import native extension modules with SIGINT/SIGTERM held until every import is done, then act on
    a signal that came meanwhile. A Python handler that raised inside VTK's extension-module
    initialisation (SIGTERM during `import pyvista`) left it half made; the process died of SIGSEGV."""
    if threading.current_thread() is not threading.main_thread():
        for m in modules:
            importlib.import_module(m)
        return
    caught: list[int] = []
    old = {s: signal.getsignal(s) for s in _SIGNALS}
    for s in _SIGNALS:
        signal.signal(s, lambda signum, frame: caught.append(signum))
    try:
        for m in modules:
            importlib.import_module(m)
    finally:
        for s, handler in old.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
    if caught:
        handler = old[caught[0]]
        if callable(handler):
            handler(caught[0], None)
        elif handler != signal.SIG_IGN:
            os.kill(os.getpid(), caught[0])  # the default action, now that the imports are whole
