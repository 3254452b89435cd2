"""A solve's progress as JSON lines, written as it happens (`solve(..., log=SolveLog(path))`).

A contact solve of the anatomical model runs for tens of minutes; its progress display goes to the
terminal only, so a run in the background, or one that was stopped, could not say which load it had
reached. One line per event, flushed at once: "start" (what the caller gives), "increment" (converged:
load factor, the caller's load, Newton iterations and their relative residuals, CPU and wall seconds, smallest
barrier distance per contact interface), "cutback" (with its residuals), then "done", or "failed" / "stopped" with the load reached (also for an
exception raised outside the solver's own failure, e.g. SIGTERM or Ctrl-C, when used as a context
manager).
"""

from __future__ import annotations

import json
from pathlib import Path

from needletissue.runinfo import to_jsonable

SOLVE_LOG = "solve_log.jsonl"  # its name in a run's --out folder (fe needle, fe pelvis)


class SolveLog:
    """Callable log for fem.solve; `scale` turns a load factor into the caller's load (e.g. N) under the
    key `load_key`. Use as a context manager: an exception leaving the block is logged with the load
    reached (the last converged increment), then re-raised."""

    def __init__(self, path: str | Path, scale: float = 1.0, load_key: str = "load", **start):
        self.path = Path(path)
        self.scale, self.load_key = float(scale), load_key
        self.reached = 0.0  # load factor of the last converged increment
        self.ended = False
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "w", encoding="utf-8")  # a new run starts a new log
        self._write({"event": "start", **start})

    def _write(self, rec: dict) -> None:
        self._file.write(json.dumps(to_jsonable(rec), default=str) + "\n")
        self._file.flush()

    def __call__(self, rec: dict) -> None:
        rec = dict(rec)
        lam = rec.get("load_factor")
        if lam is not None:
            rec[self.load_key] = lam * self.scale
        if rec.get("event") == "increment":
            self.reached = lam
        self.ended |= rec.get("event") in ("done", "failed")
        self._write(rec)

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is not None and not self.ended:  # e.g. SIGTERM (the CLI raises it), Ctrl-C, a bug
            event = "failed" if isinstance(exc, Exception) else "stopped"
            self({"event": event, "load_factor": self.reached, "reason": f"{kind.__name__}: {exc}"})
        elif kind is None and not self.ended:
            self({"event": "done", "load_factor": self.reached})
        self.close()
        return False



def read_log(path: str | Path) -> list[dict]:
    """The events of a SolveLog file (a line cut off by a kill is skipped)."""
    out = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out
