"""Run a mesher in a child Python process, so that a crash in its native code (gmsh's high-order
optimiser has aborted the whole process with SIGABRT) becomes one error, not a dead caller.

A plain subprocess, not multiprocessing: the studies run inside Dask worker processes, which are
daemonic and may not start multiprocessing children. The child dies with its parent (PDEATHSIG), so an
interrupted run leaves no mesher behind.
"""

from __future__ import annotations

import importlib
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from needletissue.errors import NeedleTissueError
from needletissue.runinfo import ignore_sigpipe


class ChildCrash(NeedleTissueError):
    """The child process died without an answer (a signal, or an unexpected exception)."""


def call_in_child(target: str, kwargs: dict, *, what: str, started=None) -> dict:
    """Call `module:function(**kwargs)` in a fresh interpreter and return its JSON-able dict.

    The package's own errors raised in the child are raised again here with their message and class
    (subclasses of NeedleTissueError that take one message); anything else becomes ChildCrash naming `what`.
    `started(proc)` is called with the child's Popen as soon as it runs.
    """
    ignore_sigpipe()
    src = str(Path(__file__).resolve().parents[2])  # the directory holding `needletissue`
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH")) if p),
               **{_PARENT: str(os.getpid())})
    with _UnwindOnSigterm(), tempfile.TemporaryDirectory(prefix="needletissue-child-") as tmp:
        answer = Path(tmp) / "answer.json"
        request = json.dumps({"target": target, "kwargs": kwargs, "answer": str(answer)})
        proc = subprocess.Popen([sys.executable, "-c", "from needletissue.geometry.child import main; main()"],
                                stdin=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
        if started is not None:
            started(proc)
        try:
            _, err = proc.communicate(request)
        except BaseException:  # interrupted: do not leave the child computing
            proc.kill()
            proc.wait()
            raise
        if proc.returncode == 0 and answer.exists():
            reply = json.loads(answer.read_text())
            if "error" not in reply:
                return reply["value"]
            raise _error_class(reply["error"])(reply["message"])
        last = (err or "").strip().splitlines()[-1:] or [""]
        if proc.returncode < 0:
            name = signal.Signals(-proc.returncode).name
            raise ChildCrash(f"{what} crashed in native code ({name}); a slightly different element size "
                             "usually avoids it")
        raise ChildCrash(f"{what} failed in its child process (exit {proc.returncode}): {last[0]}")


def start_in_child(target: str, kwargs: dict, *, what: str):
    """call_in_child from a background thread, so the caller computes meanwhile. Returns a function that
    waits for the child and returns its value (or raises its error); its `stop()` kills the child and
    waits for the thread: call it before removing anything the child writes into (a stopped run whose
    child went on writing left a folder behind)."""
    import threading

    ignore_sigpipe()   # here: the thread below may not set signal handlers
    box, lock = {}, threading.Lock()

    def started(proc):
        with lock:
            box["proc"] = proc
            if box.get("stopped"):
                proc.kill()

    def run():
        try:
            box["value"] = call_in_child(target, kwargs, what=what, started=started)
        except BaseException as exc:   # re-raised in the caller's thread by result()
            box["error"] = exc

    th = threading.Thread(target=run, daemon=True)
    th.start()

    def result():
        th.join()
        if "error" in box:
            raise box["error"]
        return box["value"]

    def stop():
        with lock:
            box["stopped"] = True
            proc = box.get("proc")
        if proc is not None and proc.poll() is None:
            proc.kill()
        th.join()

    result.stop = stop
    return result


class _UnwindOnSigterm:
    """While the child runs, SIGTERM to a process that would die of it at once (the default action: a
    `reproduce` stage worker, stopped with SIGTERM) raises SystemExit(143) instead, so that the child is
    killed and the temporary folders of the caller are removed; without it they stayed in $TMPDIR.
    A handler already set (the CLI's) is left alone. Main thread only (where Python runs handlers)."""

    def __enter__(self):
        import threading

        self.old = None
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL):
            self.old = signal.signal(signal.SIGTERM, _exit_on_signal)
        return self

    def __exit__(self, *exc):
        if self.old is not None:
            signal.signal(signal.SIGTERM, self.old)


def _exit_on_signal(signum, frame):
    raise SystemExit(128 + signum)


def _error_class(qualname: str):
    module, _, name = qualname.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return ChildCrash
    return cls if isinstance(cls, type) and issubclass(cls, NeedleTissueError) else ChildCrash


_PARENT = "NEEDLETISSUE_CHILD_PARENT"  # the pid of the process that started the child


def _die_with_parent() -> None:
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the parent's kill on interrupt still applies
        pass
    # PDEATHSIG only covers a parent that dies from now on: one killed while this interpreter started
    # (SIGTERM right after the mesher was launched) left the child meshing on as an orphan, writing the
    # mesh into the output folder after the command had exited.
    parent = os.environ.get(_PARENT)
    if parent and os.getppid() != int(parent):
        os._exit(1)


def main() -> None:
    _die_with_parent()
    req = json.loads(sys.stdin.read())
    module, _, name = req["target"].partition(":")
    try:
        value = getattr(importlib.import_module(module), name)(**req["kwargs"])
        reply = {"value": value}
    except NeedleTissueError as exc:
        # InputError takes (field, message); its str already carries both
        cls = type(exc)
        one_arg = cls.__init__ is NeedleTissueError.__init__ or cls.__init__ is Exception.__init__
        reply = {"error": f"{cls.__module__}.{cls.__qualname__}" if one_arg else "needletissue.geometry.child.ChildCrash",
                 "message": str(exc)}
    Path(req["answer"]).write_text(json.dumps(reply))
