"""`needletissue reproduce`: an explicit list of stages, each config -> (result dataclass, figures, files).

The whole run is written into a hidden temporary folder beside ``--out`` and renamed into place at the
end, so an interrupted run never leaves a folder that looks finished. ``results.json`` is written
last inside it; the folder also holds the completion marker ``.needletissue-reproduce``.
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from needletissue.errors import InputError
from needletissue.models.render import stop_workers
from needletissue.report.config import ReproduceConfig, annotated_toml
from needletissue.report.paper import PAPER
from needletissue.runinfo import (check_output_dir, current_umask, ignore_sigpipe, make_dir, to_jsonable,
                                  version_record, write_atomic, write_json)

MARKER = ".needletissue-reproduce"
# A reproduced number "agrees" with the paper's when within 5 % of it: the paper prints 3-5 digits and
# states no uncertainty; 5 % is above our mesh/order errors (docs/needle_model.md, docs/ritz.md) and below
# every difference whose cause the docs trace to a modelling choice.
AGREEMENT_PERCENT = 5.0


@dataclass
class Comparison:
    """One reproduced number beside the paper's value (when the paper gives one)."""

    quantity: str
    ours: float | str
    unit: str
    paper_key: str | None = None  # only for a like-for-like value (same model, needles, force, length)
    note: str = ""
    tolerance_percent: float | None = AGREEMENT_PERCENT  # "agrees" within this of the paper's value
    limit: float | None = None  # instead: a criterion ours < limit (the paper's RMSE < 0.05 MPa)
    reason: str = ""  # why it differs from the paper, measured (set by the reconciliation stage)

    @property
    def verdict(self) -> str:
        """agrees / differs / meets the criterion: the row's reading, stated with its tolerance."""
        if self.limit is not None and isinstance(self.ours, (int, float)):
            return (f"meets the criterion (< {self.limit:.3g} {self.unit})" if self.ours < self.limit
                    else f"fails the criterion (< {self.limit:.3g} {self.unit})")
        rel = self.relative_percent
        if rel is None or self.tolerance_percent is None:
            return ""
        if abs(rel) <= self.tolerance_percent:
            return f"agrees (within {self.tolerance_percent:.3g} %)"
        return f"differs ({rel:+.0f} %, tolerance {self.tolerance_percent:.3g} %)"

    @property
    def paper(self):
        return PAPER[self.paper_key].value if self.paper_key else None

    @property
    def difference(self):
        if self.paper is None or not isinstance(self.ours, (int, float)):
            return None
        return self.ours - self.paper

    @property
    def relative_percent(self):
        d = self.difference
        return None if d is None or self.paper == 0 else 100.0 * d / self.paper

    def to_json(self) -> dict:
        return {"quantity": self.quantity, "ours": self.ours, "unit": self.unit, "paper": self.paper,
                "difference": self.difference, "relative_difference_percent": self.relative_percent,
                "verdict": self.verdict,
                "paper_source": PAPER[self.paper_key].source if self.paper_key else None, "note": self.note,
                "reason": self.reason or None}


@dataclass
class StageResult:
    """What a stage returns: its result dataclass, figures and data files (paths in the run folder)."""

    data: Any
    figures: list[Path] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    comparisons: list[Comparison] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    views: list = field(default_factory=list)  # (title, report.viewer.Scene): interactive 3D views
    # measured reasons for other stages' rows that differ from the paper, by the row's quantity
    reasons: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Stage:
    name: str
    title: str
    run: Callable[[ReproduceConfig, "StageContext"], StageResult]
    enabled: Callable[[ReproduceConfig, "StageContext"], tuple[bool, str]]
    # Run in a child process: a crash in native code (mesher, sparse solver, VTK) then fails this
    # stage only instead of the whole run. The function must be importable (module level).
    isolated: bool = False


def _start_isolated(stage: Stage, cfg: ReproduceConfig, ctx: "StageContext", side_by_side: int = 1):
    """Start an isolated stage in its own process now; `_collect` waits for it. Isolated stages (the FE
    models) start together at the beginning and run beside the in-process stages: on two cores the needle
    FE and the anatomical model overlap. `side_by_side` stages share the cores: each child's sparse solver
    gets its share of MKL threads (unless MKL_NUM_THREADS is set): threads beyond the cores wait for each
    other."""
    import multiprocessing as mp
    import os
    from concurrent.futures import ProcessPoolExecutor

    from needletissue.fem.linsolve import granted_threads

    ignore_sigpipe()   # a dead worker: BrokenProcessPool, not a dead caller
    threads = os.environ.get("MKL_NUM_THREADS") or str(max(1, granted_threads() // side_by_side))
    pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"),
                               initializer=_mkl_threads, initargs=(threads,))
    return pool, pool.submit(_timed, stage.run, cfg, StageContext(ctx.run_dir, ctx.ct, ctx.labels))


def _mkl_threads(threads: str):
    """In an isolated stage's child, before MKL loads: its share of the cores."""
    import os

    os.environ["MKL_NUM_THREADS"] = threads


def _collect(stage: Stage, started) -> tuple[StageResult, float]:
    from concurrent.futures.process import BrokenProcessPool

    pool, fut = started
    try:
        return fut.result()
    except BrokenProcessPool:
        raise RuntimeError(f"the {stage.name} stage's process died (a crash in native code, e.g. a "
                           "segmentation fault, or killed for memory)") from None
    finally:
        if fut.done():  # interrupted while waiting: the caller stops the worker instead of waiting for it
            pool.shutdown(wait=True, cancel_futures=True)


def _timed(run, cfg, ctx) -> tuple[StageResult, float]:
    """The stage's result and its own wall time (an isolated stage's, not the time spent waiting for it)."""
    ts = time.perf_counter()
    res = _run_noting_warnings(run, cfg, ctx)
    return res, time.perf_counter() - ts


def _run_noting_warnings(run, cfg, ctx) -> StageResult:
    """A stage's warnings become notes of its result (the report shows them; no stray stderr lines)."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        res = run(cfg, ctx)
    seen = set(res.notes)
    for w in caught:
        note = f"warning: {w.message}"
        if note not in seen and not issubclass(w.category, (DeprecationWarning, FutureWarning)):
            res.notes.append(note)
            seen.add(note)
    return res


class _StopOnSignals:
    """While reproduce runs: SIGTERM (and SIGINT, as KeyboardInterrupt) unwind the run, so that workers
    are stopped and the temporary folder removed; SIGTERM then exits with code 143 (128 + 15). Without
    it SIGTERM killed the process at once, leaving the folder and orphan workers computing on."""

    def __enter__(self):
        import threading

        self.old = None
        if threading.current_thread() is threading.main_thread():  # signals go to the main thread only
            self.old = signal.signal(signal.SIGTERM, self._raise)
        return self

    @staticmethod
    def _raise(signum, frame):
        raise SystemExit(128 + signum)

    def __exit__(self, *exc):
        if self.old is not None:
            signal.signal(signal.SIGTERM, self.old)


@dataclass
class StageContext:
    """Where a stage writes (its own sub-folder of the run folder) and run-wide inputs."""

    run_dir: Path
    ct: Path | None = None
    labels: Path | None = None
    previous: dict[str, StageResult] = field(default_factory=dict)

    def stage_dir(self, name: str) -> Path:
        d = self.run_dir / name
        d.mkdir(parents=True, exist_ok=True)
        return d


@dataclass
class StageOutcome:
    name: str
    title: str
    status: str  # ok | skipped | failed
    wall_time_s: float
    reason: str = ""
    result: StageResult | None = None


@dataclass
class ReproduceResult:
    out_dir: Path
    outcomes: list[StageOutcome]
    wall_time_s: float

    @property
    def ok(self) -> bool:
        return all(o.status != "failed" for o in self.outcomes)


def _check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / MARKER).exists())):
        raise InputError("--out", f"{out} exists and is not a needletissue reproduce folder; "
                         "give a new or empty folder")


def run_reproduce(cfg: ReproduceConfig, out: str | Path, stages: list[Stage], *, ct: Path | None = None,
                  labels: Path | None = None, progress: bool = True) -> ReproduceResult:
    """Run the enabled stages in order into a temporary folder, write the report, rename into ``out``."""
    from needletissue.report.html import write_report

    out = Path(out).resolve()
    _check_out(out)
    check_output_dir(out, "--out")  # a read-only place: one error line before any stage runs
    make_dir(out.parent)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    except OSError as exc:
        raise InputError("--out", f"{out}: cannot write in {out.parent}: {exc.strerror or exc}") from None
    os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes it private; the result folder should not be
    t0 = time.perf_counter()
    outcomes: list[StageOutcome] = []
    try:
        with _StopOnSignals():
            return _stages(cfg, out, tmp, stages, ct, labels, progress, t0, outcomes, write_report)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _stages(cfg, out, tmp, stages, ct, labels, progress, t0, outcomes, write_report) -> ReproduceResult:
    """The stages in order into tmp, then the run files and the report; rename tmp to out."""
    from needletissue.report.html import comparison_markdown

    ctx = StageContext(run_dir=tmp, ct=ct, labels=labels)
    enabled = {s.name: s.enabled(cfg, ctx) for s in stages}
    started = {}
    isolated = [s for s in stages if s.isolated and enabled[s.name][0]]
    with _StageProgress(stages, progress) as bar:
        try:
            for stage in isolated:
                started[stage.name] = _start_isolated(stage, cfg, ctx, side_by_side=len(isolated))
                bar.start(stage)
            for stage in stages:
                _run_stage(stage, cfg, ctx, enabled[stage.name], started.get(stage.name), bar, outcomes)
        except BaseException:  # interrupted (SIGINT/SIGTERM): stop the workers, do not wait for them
            for pool, _ in started.values():
                stop_workers(pool)
            raise
        finally:
            for pool, _ in started.values():
                pool.shutdown(wait=True, cancel_futures=True)
    _attach_reasons(outcomes)
    result = ReproduceResult(out, outcomes, time.perf_counter() - t0)
    write_atomic(tmp / "config.toml", annotated_toml(cfg))
    write_json(tmp / "versions.json", version_record())
    write_report(tmp, cfg, result)
    payload = results_json(cfg, result, tmp)
    write_json(tmp / "results.json", payload)
    write_atomic(tmp / "comparison.md", comparison_markdown(payload["comparison_with_paper"], payload["reconciliation"]))
    write_atomic(tmp / MARKER, f"complete {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
    _swap(tmp, out)
    return result


def _run_stage(stage, cfg, ctx, enabled, started, bar, outcomes) -> None:
    """One stage's outcome, in stage order: run it here, or wait for its process (started). A failed stage
    is reported; the others still run."""
    on, reason = enabled
    if not on:
        outcomes.append(StageOutcome(stage.name, stage.title, "skipped", 0.0, reason))
        bar.finish(stage, "skipped", reason)
        return
    if started is None:
        bar.start(stage)
    ts = time.perf_counter()
    try:
        res, dt = _collect(stage, started) if started else _timed(stage.run, cfg, ctx)
    except Exception as exc:
        msg = f"{type(exc).__name__}: {exc}"
        outcomes.append(StageOutcome(stage.name, stage.title, "failed", time.perf_counter() - ts,
                                     msg + "\n" + traceback.format_exc(limit=6)))
        bar.finish(stage, "failed", msg)
        return
    ctx.previous[stage.name] = res
    outcomes.append(StageOutcome(stage.name, stage.title, "ok", dt, result=res))
    bar.finish(stage, "ok", f"{dt:.1f} s")


NO_REASON = "reason not measured in this run (the reconciliation stage did not run or has no measurement for this row)"


def _attach_reasons(outcomes: list[StageOutcome]) -> None:
    """Every row that differs from the paper gets its measured reason, or says that it has none."""
    reasons = {k: v for o in outcomes if o.result for k, v in o.result.reasons.items()}
    for o in outcomes:
        for c in (o.result.comparisons if o.result else []):
            if c.verdict.startswith("differs") and not c.reason:
                c.reason = reasons.get(c.quantity, NO_REASON)


def _swap(tmp: Path, out: Path) -> None:
    """Replace out by tmp. Between the two renames out is absent, never half-written."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{time.time_ns()}"
        out.rename(old)
    tmp.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def results_json(cfg: ReproduceConfig, result: ReproduceResult, run_dir: Path) -> dict:
    def rel(p):
        return str(Path(p).relative_to(run_dir)) if Path(p).is_absolute() else str(p)

    stages = {}
    for o in result.outcomes:
        entry = {"title": o.title, "status": o.status, "wall_time_s": o.wall_time_s}
        if o.reason:
            entry["reason"] = o.reason
        if o.result is not None:
            entry["result"] = to_jsonable(o.result.data)
            entry["figures"] = [rel(p) for p in o.result.figures]
            entry["files"] = [rel(p) for p in o.result.files]
            entry["notes"] = o.result.notes
        stages[o.name] = entry
    comparisons = [c.to_json() for o in result.outcomes if o.result for c in o.result.comparisons]
    rec = next((o.result.data for o in result.outcomes if o.name == "reconciliation" and o.result), None)
    return {"wall_time_s": result.wall_time_s, "ok": result.ok, "stages": stages,
            "comparison_with_paper": comparisons, "reconciliation": None if rec is None else rec.to_json()}


class _StageProgress:
    """One Rich progress line per stage: spinner while it runs, then ok / skipped / failed."""

    def __init__(self, stages: list[Stage], enabled: bool):
        self.p = None
        if enabled:
            from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

            self.p = Progress(SpinnerColumn(finished_text="•"), TextColumn("{task.description}"),
                              TextColumn("{task.fields[status]}"), TimeElapsedColumn())
            self.ids = {s.name: self.p.add_task(s.title, total=1, start=False, status="[dim]waiting")
                        for s in stages}

    def __enter__(self):
        if self.p:
            self.p.__enter__()
        return self

    def __exit__(self, *exc):
        if self.p:
            self.p.__exit__(*exc)

    def start(self, stage: Stage):
        if self.p:
            self.p.start_task(self.ids[stage.name])
            self.p.update(self.ids[stage.name], status="[yellow]running")

    def finish(self, stage: Stage, status: str, text: str):
        if self.p:
            colour = {"ok": "green", "skipped": "dim", "failed": "red"}[status]
            from rich.markup import escape

            short = escape(text.splitlines()[0][:60]) if text else ""
            self.p.update(self.ids[stage.name], completed=1, status=f"[{colour}]{status}[/{colour}] {short}")
            self.p.stop_task(self.ids[stage.name])
