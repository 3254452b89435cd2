"""reproduce's output folder: complete or absent, never half-written; the HTML report is self-contained."""

import json

import pytest

from needletissue.errors import InputError
from needletissue.report.config import load_config
from needletissue.report.pipeline import MARKER, Comparison, Stage, StageResult, run_reproduce
from needletissue.report.paper import PAPER


def _always(cfg, ctx):
    return True, ""


def _writes(value):
    def run(cfg, ctx):
        d = ctx.stage_dir("s")
        (d / "data.txt").write_text(str(value))
        return StageResult({"value": value}, files=[d / "data.txt"],
                           comparisons=[Comparison("Ritz tip deflection at 300 N", value, "mm",
                                                   "ritz_tip_deflection_300N_mm")])
    return run


def _interrupted(cfg, ctx):
    (ctx.stage_dir("s") / "partial.txt").write_text("half")
    raise KeyboardInterrupt


def _die(cfg, ctx):
    import os

    os._exit(139)


def _broken(cfg, ctx):
    raise RuntimeError("solver exploded")


def test_complete_run_has_marker_results_and_comparison(tmp_path):
    out = tmp_path / "res"
    res = run_reproduce(load_config(), out, [Stage("s", "S", _writes(18.0), _always)], progress=False)
    assert res.ok and (out / MARKER).exists()
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    row = data["comparison_with_paper"][0]
    assert row["paper"] == PAPER["ritz_tip_deflection_300N_mm"].value
    assert row["difference"] == pytest.approx(18.0 - 17.63)
    assert (out / "config.toml").exists() and (out / "versions.json").exists()
    md = (out / "comparison.md").read_text(encoding="utf-8").splitlines()
    assert md[2].startswith("| Ritz tip deflection at 300 N | 18 mm | 17.63 mm | agrees (within 5 %) |")  # 2.1 %
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "17.63" in html and "src=\"http" not in html  # nothing fetched from elsewhere
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".res.")]


def test_interrupted_run_leaves_no_folder_and_keeps_previous(tmp_path):
    out = tmp_path / "res"
    with pytest.raises(KeyboardInterrupt):
        run_reproduce(load_config(), out, [Stage("s", "S", _interrupted, _always)], progress=False)
    assert not out.exists()
    run_reproduce(load_config(), out, [Stage("s", "S", _writes(1.0), _always)], progress=False)
    with pytest.raises(KeyboardInterrupt):
        run_reproduce(load_config(), out, [Stage("s", "S", _writes(2.0), _always),
                                           Stage("t", "T", _interrupted, _always)], progress=False)
    # the earlier complete result is still there, untouched
    assert (out / "s" / "data.txt").read_text(encoding="utf-8") == "1.0"
    assert not (out / "s" / "partial.txt").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".res.")]


def test_failed_stage_is_reported_and_others_run(tmp_path):
    out = tmp_path / "res"
    res = run_reproduce(load_config(), out, [Stage("a", "A", _broken, _always),
                                             Stage("s", "S", _writes(3.0), _always)], progress=False)
    assert not res.ok
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert data["stages"]["a"]["status"] == "failed" and "solver exploded" in data["stages"]["a"]["reason"]
    assert data["stages"]["s"]["status"] == "ok"


def test_refuses_foreign_folder(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("precious")
    with pytest.raises(InputError, match="--out"):
        run_reproduce(load_config(), out, [], progress=False)
    assert (out / "thesis.tex").read_text(encoding="utf-8") == "precious"


def test_isolated_stage_that_crashes_fails_alone(tmp_path):
    """A stage whose process dies (here: os._exit, as a segfault would) is a failed stage; the run ends."""
    out = tmp_path / "res"
    res = run_reproduce(load_config(), out, [Stage("crash", "C", _die, _always, isolated=True),
                                             Stage("s", "S", _writes(3.0), _always)], progress=False)
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert data["stages"]["crash"]["status"] == "failed" and "died" in data["stages"]["crash"]["reason"]
    assert data["stages"]["s"]["status"] == "ok" and not res.ok


def _waits_for_partner(cfg, ctx):
    # succeeds only if the partner stage runs at the same time (run one after the other, it times out)
    import time

    partner = ctx.run_dir / "partner.flag"
    t_end = time.monotonic() + 90
    while not partner.exists():
        if time.monotonic() > t_end:
            raise TimeoutError("the partner stage never ran beside this one")
        time.sleep(0.02)
    return StageResult({"saw_partner": True})


def _partner(cfg, ctx):
    (ctx.run_dir / "partner.flag").write_text("here")
    return StageResult({"partner": True})


def _reads_previous(cfg, ctx):
    return StageResult({"after": sorted(ctx.previous)})


def test_isolated_stages_run_side_by_side_and_results_stay_in_order(tmp_path):
    """The FE stages (isolated) start together and overlap; a later stage still sees every earlier result."""
    out = tmp_path / "res"
    res = run_reproduce(load_config(), out, [Stage("a", "A", _waits_for_partner, _always, isolated=True),
                                             Stage("b", "B", _partner, _always, isolated=True),
                                             Stage("off", "Off", _broken, lambda c, x: (False, "off")),
                                             Stage("last", "L", _reads_previous, _always)], progress=False)
    assert res.ok, [o.reason for o in res.outcomes]
    assert [o.name for o in res.outcomes] == ["a", "b", "off", "last"]
    assert res.outcomes[3].result.data == {"after": ["a", "b"]}
    assert res.outcomes[2].status == "skipped"


def _mkl_threads_seen(cfg, ctx):
    import os

    return StageResult({"mkl_threads": os.environ.get("MKL_NUM_THREADS")})


@pytest.mark.parametrize("user", [None, "3"])
def test_side_by_side_stages_share_the_cores_mkl_threads(tmp_path, monkeypatch, user):
    """Two isolated stages on n cores get n // 2 MKL threads each (at least 1): more threads than cores wait for
    each other; a user's MKL_NUM_THREADS wins; in-process stages are left alone."""
    import os

    if user is None:
        monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("MKL_NUM_THREADS", user)
    res = run_reproduce(load_config(), tmp_path / "res",
                        [Stage("a", "A", _mkl_threads_seen, _always, isolated=True),
                         Stage("b", "B", _mkl_threads_seen, _always, isolated=True),
                         Stage("c", "C", _mkl_threads_seen, _always)], progress=False)
    assert res.ok, [o.reason for o in res.outcomes]
    share = user or str(max(1, len(os.sched_getaffinity(0)) // 2))
    assert [o.result.data["mkl_threads"] for o in res.outcomes] == [share, share, user]


def test_result_folder_and_files_follow_the_umask(tmp_path):
    import os
    import stat

    old = os.umask(0o022)
    try:
        out = tmp_path / "res"
        run_reproduce(load_config(), out, [Stage("s", "S", _writes(1.0), _always)], progress=False)
    finally:
        os.umask(old)
    assert stat.S_IMODE(out.stat().st_mode) == 0o755
    for name in ("report.html", "results.json", "config.toml", "versions.json", MARKER):
        assert stat.S_IMODE((out / name).stat().st_mode) == 0o644, name


def test_results_are_relocatable(tmp_path):
    """No path to the temporary folder (or any absolute path inside the result) survives in the files."""
    def stage(cfg, ctx):
        d = ctx.stage_dir("s")
        (d / "x.vtu").write_text("v")
        return StageResult({"vtu": str(d / "x.vtu"), "nested": [{"file": str(d / "x.vtu")}]}, files=[d / "x.vtu"])

    out = tmp_path / "res"
    run_reproduce(load_config(), out, [Stage("s", "S", stage, _always)], progress=False)
    for f in out.rglob("*"):
        if f.suffix in (".json", ".toml", ".html"):
            assert str(tmp_path) not in f.read_text(encoding="utf-8"), f
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))["stages"]["s"]
    assert data["result"]["vtu"] == "s/x.vtu" == data["files"][0] and (out / data["result"]["vtu"]).is_file()


SLOW_STAGE = '''
import os, time

def run(cfg, ctx):
    d = ctx.stage_dir("slow")
    (ctx.run_dir.parent / "worker.pid").write_text(str(os.getpid()))
    for i in range(600):
        (d / "tick.txt").write_text(str(i))
        time.sleep(0.1)
'''

DRIVER = '''
import sys
sys.path.insert(0, sys.argv[1])
from slowstage import run
from needletissue.report.config import load_config
from needletissue.report.pipeline import Stage, run_reproduce
run_reproduce(load_config(), sys.argv[2], [Stage("slow", "Slow", run, lambda c, x: (True, ""), isolated=True)],
              progress=False)
'''


@pytest.mark.parametrize("sig, code", [("SIGTERM", 143), ("SIGINT", None)])
def test_signal_stops_workers_removes_temp_folder_and_exits_non_zero(tmp_path, sig, code):
    """Before: SIGTERM left the hidden temp folder and a worker computing on for 30 s."""
    import os
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "slowstage.py").write_text(SLOW_STAGE)
    runs = tmp_path / "runs"
    runs.mkdir()
    out = runs / "res"
    p = subprocess.Popen([sys.executable, "-c", DRIVER, str(tmp_path), str(out)], stderr=subprocess.PIPE, text=True)
    pid_file = runs / "worker.pid"
    t0 = time.time()
    while not pid_file.exists() or not pid_file.read_text():
        assert p.poll() is None and time.time() - t0 < 60, p.stderr.read() if p.poll() is not None else "slow start"
        time.sleep(0.1)
    worker = int(pid_file.read_text())
    p.send_signal(getattr(signal, sig))
    rc = p.wait(timeout=30)
    assert rc != 0 and (code is None or rc == code), rc
    for _ in range(50):  # the worker is gone (terminated and reaped, not orphaned)
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        os.kill(worker, signal.SIGKILL)
        pytest.fail("the worker process survived")
    assert sorted(x.name for x in runs.iterdir()) == ["worker.pid"]  # no result, no hidden temp folder


@pytest.mark.parametrize("where", ["proc", "under_file"])
def test_unwritable_out_is_refused_before_any_stage(tmp_path, where):
    (tmp_path / "f").write_text("x")
    out = {"proc": "/proc/needletissue-test/res", "under_file": tmp_path / "f" / "res"}[where]
    with pytest.raises(InputError) as e:
        run_reproduce(load_config(), out, [Stage("a", "A", _broken, _always)], progress=False)
    assert e.value.field == "--out" and sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_verdicts_state_their_tolerance():
    """agrees within 5 % of the paper's value, differs beyond (with the signed difference), a criterion
    row is read against its limit, a row without a like-for-like paper value has no verdict."""
    assert Comparison("q", 17.7, "mm", "ritz_tip_deflection_300N_mm").verdict == "agrees (within 5 %)"
    assert Comparison("q", 25.13, "mm", "ritz_tip_deflection_300N_mm").verdict == "differs (+43 %, tolerance 5 %)"
    assert Comparison("q", 0.01, "MPa", "traction_rmse_muscle_MPa", limit=0.05).verdict.startswith("meets")
    assert Comparison("q", 25.13, "mm", None).verdict == ""
