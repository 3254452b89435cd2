"""Run a study on Dask (or serially), chunk by chunk, resumable.

Layout of the output folder::

    study.json            fingerprint + resolved config; a rerun with another config is refused
    cases.parquet         every case (case_id, parameters), deterministic from the seed
    chunks/chunk_NNNNNN.parquet   one per finished chunk, written atomically (temp file + rename)
    runs.jsonl            one line per persisted chunk: run id, chunk, cases, failed, time
    results.parquet, results.csv, failures.csv, summary.json, figures/, config.toml, versions.json,
    results.json          written after the last chunk; results.json last of all (completion marker)

A chunk file either exists whole or not at all, so a run stopped at any point loses only the chunks in
flight; the next run skips every chunk on disk and computes the rest.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from needletissue.errors import InputError
from needletissue.runinfo import check_output_dir, make_dir, write_atomic, write_json
from needletissue.studies.config import StudyConfig
from needletissue.studies.models import get_model, run_chunk
from needletissue.studies.sampling import design

CHUNK_DIR = "chunks"


@dataclass
class StudyResult:
    """What a study run produced. ``results`` holds cases, outputs, status and error per case."""

    out_dir: Path
    n_cases: int
    n_ok: int
    n_failed: int
    computed_this_run: int
    resumed: int
    wall_time_s: float
    results: pd.DataFrame = field(repr=False)
    timing: dict = field(default_factory=dict)
    failures: list[dict] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)


def fingerprint(cfg: StudyConfig) -> str:
    blob = json.dumps(cfg.model_dump(mode="json"), sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def chunk_size(cfg: StudyConfig) -> int:
    return cfg.study.chunk_size or get_model(cfg.study.model).default_chunk_size


def chunk_path(out_dir: Path, i: int) -> Path:
    return out_dir / CHUNK_DIR / f"chunk_{i:06d}.parquet"


def _to_parquet_bytes(df: pd.DataFrame) -> bytes:
    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    return buf.getvalue()


def _prepare(cfg: StudyConfig, out_dir: Path) -> pd.DataFrame:
    """Create or reopen the study folder; refuse a folder that holds a different study."""
    make_dir(out_dir)
    meta_path = out_dir / "study.json"
    fp = fingerprint(cfg)
    if meta_path.exists():
        old = json.loads(meta_path.read_text(encoding="utf-8")).get("fingerprint")
        if old != fp:
            raise InputError("--out", f"{out_dir} holds another study (fingerprint {old}, this one {fp}); "
                             "use a new folder or the same config to resume")
    cases = design(cfg)
    if not meta_path.exists():
        write_atomic(out_dir / "cases.parquet", _to_parquet_bytes(cases))
        write_json(meta_path, {"fingerprint": fp, "config": cfg.model_dump(mode="json")})
    return cases


def _chunk_done(out_dir: Path, i: int, ids: np.ndarray) -> bool:
    p = chunk_path(out_dir, i)
    if not p.exists():
        return False
    try:
        got = pd.read_parquet(p, columns=["case_id"])["case_id"].to_numpy()
    except Exception:
        return False  # unreadable: recompute (never happens with atomic writes, but costs nothing)
    return np.array_equal(np.sort(got), ids)


def _persist(out_dir: Path, i: int, df: pd.DataFrame, run_id: str) -> None:
    df = df.copy()
    df["run_id"] = run_id
    write_atomic(chunk_path(out_dir, i), _to_parquet_bytes(df))
    line = json.dumps({"run_id": run_id, "chunk": i, "cases": int(len(df)),
                       "failed": int((df["status"] != "ok").sum()), "time": time.time()})
    with open(out_dir / "runs.jsonl", "a", encoding="utf-8") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


class _Progress:
    """Rich progress bar over cases: done, failed, remaining."""

    def __init__(self, total: int, done: int, failed: int, enabled: bool, title: str):
        self.total, self.done, self.failed = total, done, failed
        self.bar = None
        if enabled:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn(f"[bold]{title}"), BarColumn(),
                TextColumn("done {task.fields[done]:,}  [red]failed {task.fields[failed]:,}[/red]  "
                           "remaining {task.fields[remaining]:,}"),
                TimeElapsedColumn(), TimeRemainingColumn(), transient=False,
            )
            self.task = self.bar.add_task(title, total=total, completed=done, **self._fields())

    def _fields(self):
        return dict(done=self.done, failed=self.failed, remaining=self.total - self.done)

    def __enter__(self):
        if self.bar:
            self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self.bar:
            self.bar.__exit__(*exc)

    def advance(self, n: int, failed: int):
        self.done += n
        self.failed += failed
        if self.bar:
            self.bar.update(self.task, completed=self.done, **self._fields())


def _client(scheduler: str | None, workers: int):
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, ValueError, TypeError) as exc:  # unreachable, refused, or not an address
            msg = " ".join(str(exc).split()) or type(exc).__name__
            raise InputError("--scheduler", f"cannot reach a Dask scheduler at {scheduler!r}: {msg}") from None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=40)
    return Client(cluster), cluster


def run_study(cfg: StudyConfig, out_dir: str | Path, *, scheduler: str | None = None, workers: int = 2,
              serial: bool = False, progress: bool = True, analyse: bool = True) -> StudyResult:
    """Compute every case not yet on disk, then merge, summarise and plot.

    serial=True runs in this process (no Dask); otherwise a LocalCluster of ``workers`` processes, or
    the existing cluster at ``scheduler`` (e.g. 'tcp://10.0.0.5:8786').
    """
    t0 = time.perf_counter()
    out_dir = check_output_dir(out_dir, "--out")  # before any file is written or worker started
    model = get_model(cfg.study.model)
    early = _client(scheduler, workers) if scheduler and not serial else None  # unreachable: nothing written
    try:
        return _run(cfg, out_dir, model, early, scheduler, workers, serial, progress, analyse, t0)
    finally:
        if early is not None:
            early[0].close()


def _run(cfg, out_dir, model, early, scheduler, workers, serial, progress, analyse, t0) -> StudyResult:
    cases = _prepare(cfg, out_dir)
    params = [c for c in cases.columns if c != "case_id"]
    cs = chunk_size(cfg)
    n = len(cases)
    bounds = [(i, s, min(s + cs, n)) for i, s in enumerate(range(0, n, cs))]
    ids = cases["case_id"].to_numpy()
    pending = [b for b in bounds if not _chunk_done(out_dir, b[0], ids[b[1]:b[2]])]
    resumed = n - sum(e - s for _, s, e in pending)
    failed_before = _count_failed(out_dir, [b for b in bounds if b not in pending])
    run_id = uuid.uuid4().hex[:12]
    fixed = dict(cfg.fixed)
    model_params = [p for p in params if p != "block"]

    def task_input(s, e):
        return cases.iloc[s:e][["case_id", *model_params]].reset_index(drop=True)

    chunk_compute = []
    spans = []  # (worker, start, end) wall clock per computed chunk
    n_workers = 1
    cluster_start = 0.0
    t_compute = t_end = time.perf_counter()
    t_unix = time.time()
    with _Progress(n, resumed, failed_before, progress, cfg.study.name) as bar:
        if pending and serial:
            for i, s, e in pending:
                df = run_chunk(model.name, task_input(s, e), fixed)
                _persist(out_dir, i, df, run_id)
                chunk_compute.append(float(df["chunk_wall_time_s"].iloc[0]))
                spans.append(_span(df))
                bar.advance(len(df), int((df["status"] != "ok").sum()))
            t_end = time.perf_counter()
        elif pending:
            from dask.distributed import as_completed

            client, cluster = early or _client(scheduler, workers)
            cluster_start = time.perf_counter() - t_compute
            t_compute = time.perf_counter()  # the cluster's start-up is reported apart
            t_unix = time.time()
            n_workers = max(1, len(client.scheduler_info().get("workers", {})) or workers)
            try:
                futures = {}
                for i, s, e in pending:
                    fut = client.submit(run_chunk, model.name, task_input(s, e), fixed, pure=False,
                                        key=f"chunk-{run_id}-{i}")
                    futures[fut] = i
                for fut in as_completed(futures):
                    df = fut.result()
                    _persist(out_dir, futures[fut], df, run_id)
                    chunk_compute.append(float(df["chunk_wall_time_s"].iloc[0]))
                    spans.append(_span(df))
                    bar.advance(len(df), int((df["status"] != "ok").sum()))
                t_end = time.perf_counter()  # before the cluster shuts down
            finally:
                if early is None:
                    client.close()
                if cluster is not None:
                    cluster.close()

    computed = n - resumed
    phase = max(0.0, t_end - t_compute)
    busy = sum(chunk_compute)
    timing = {"cluster_start_s": cluster_start, "compute_phase_wall_s": phase, "sum_chunk_compute_s": busy,
              "workers": n_workers, "chunks_computed": len(chunk_compute),
              # wall time x workers beyond the time spent inside case functions: transfer, scheduling,
              # persistence and idle workers at the end, relative to the compute time.
              "overhead_fraction": (phase * n_workers - busy) / busy if busy > 0 else None,
              **_scheduling(spans, t_unix, busy)}
    results = merge(out_dir, cases, len(bounds))
    res = StudyResult(
        out_dir=out_dir, n_cases=n, n_ok=int((results["status"] == "ok").sum()),
        n_failed=int((results["status"] != "ok").sum()), computed_this_run=computed, resumed=resumed,
        wall_time_s=0.0, results=results, timing=timing,
    )
    res.failures = failure_records(results, model_params)
    if analyse:
        from needletissue.studies.report import write_outputs

        write_outputs(cfg, res, model_params)
    res.wall_time_s = time.perf_counter() - t0
    return res


def _span(df: pd.DataFrame) -> tuple[str, float, float]:
    r = df.iloc[0]
    return str(r["chunk_worker"]), float(r["chunk_start_unix"]), float(r["chunk_end_unix"])


def _scheduling(spans, t0: float, busy: float) -> dict:
    """Split the non-compute time per worker: waiting for its first task and gaps between its tasks
    (scheduling, transfer, result handling) versus idling after its last task while others finish
    (load imbalance, not scheduling)."""
    if not spans or busy <= 0:
        return {}
    end = max(e for _, _, e in spans)
    gaps = idle = 0.0
    for w in {w for w, _, _ in spans}:
        mine = sorted((s, e) for ww, s, e in spans if ww == w)
        gaps += max(0.0, mine[0][0] - t0) + sum(max(0.0, b[0] - a[1]) for a, b in zip(mine, mine[1:]))
        idle += end - mine[-1][1]
    return {"scheduling_gaps_s": gaps, "scheduling_overhead_fraction": gaps / busy,
            "idle_at_end_s": idle, "idle_at_end_fraction": idle / busy}


def _count_failed(out_dir: Path, done_bounds) -> int:
    total = 0
    for i, _, _ in done_bounds:
        total += int((pd.read_parquet(chunk_path(out_dir, i), columns=["status"])["status"] != "ok").sum())
    return total


def merge(out_dir: Path, cases: pd.DataFrame, n_chunks: int) -> pd.DataFrame:
    """Cases joined with every chunk's outputs; each case exactly once (checked)."""
    parts = [pd.read_parquet(chunk_path(out_dir, i)) for i in range(n_chunks)]
    out = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame({"case_id": []})
    if out["case_id"].duplicated().any() or len(out) != len(cases):
        raise RuntimeError(f"{out_dir}: chunk files do not cover every case exactly once")
    return cases.merge(out, on="case_id", how="left", validate="one_to_one")


def failure_records(results: pd.DataFrame, params: list[str]) -> list[dict]:
    bad = results[results["status"] != "ok"]
    return [{"case_id": int(r.case_id), "parameters": {p: float(getattr(r, p)) for p in params},
             "error": r.error} for r in bad.itertuples()]
