"""Study runner: Dask LocalCluster == serial, a killed study resumes with every case computed once,
a failing case is reported with its parameters and does not stop the others, config errors come first."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest

from needletissue import ritz
from needletissue.errors import InputError
from needletissue.studies.config import load_study, parse_study
from needletissue.studies.runner import CHUNK_DIR, run_study

CLI = [sys.executable, "-c", "from needletissue.cli import main; main()"]

LHS = """
[study]
name = "t"
model = "ritz"
method = "latin_hypercube"
samples = {samples}
seed = 11
chunk_size = {chunk}

[fixed]
free_length_mm = 84.0

[parameters.force_N]
distribution = "uniform"
low = 100.0
high = 300.0

[parameters.tissue_thickness_mm]
distribution = "truncnorm"
mean = 31.82
std = 5.43
low = 15.0
high = 48.0

[parameters.diameter_mm]
distribution = "uniform"
low = 4.5
high = 6.0
"""


def _write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _outputs(res):
    return res.results.drop(columns=["run_id", "error", "chunk_wall_time_s", "chunk_start_unix",
                                      "chunk_end_unix", "chunk_worker"], errors="ignore").sort_values("case_id").reset_index(drop=True)


def test_local_cluster_two_workers_equals_serial(tmp_path):
    """A real 2-worker LocalCluster, reached through --scheduler ADDRESS (the CLI's default cluster is
    exercised by the kill-and-resume test)."""
    from dask.distributed import LocalCluster

    cfg = load_study(_write(tmp_path, LHS.format(samples=1200, chunk=150)))
    serial = run_study(cfg, tmp_path / "serial", serial=True, progress=False, analyse=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        dask = run_study(cfg, tmp_path / "dask", scheduler=cluster.scheduler_address, progress=False,
                         analyse=False)
    assert dask.timing["workers"] == 2
    assert serial.n_ok == dask.n_ok == 1200
    pd.testing.assert_frame_equal(_outputs(serial), _outputs(dask), check_exact=False, rtol=1e-12)
    # both ran every chunk in their own run, on different executors
    ids = {pd.read_parquet(p)["run_id"][0] for p in (tmp_path / "dask" / CHUNK_DIR).iterdir()}
    assert len(ids) == 1


def test_case_mapping_matches_direct_ritz_solve(tmp_path):
    """A study case equals ritz.solve on the same needle and layers (total thickness split 22:10)."""
    cfg = parse_study({"study": {"method": "grid", "model": "ritz"}, "fixed": {"free_length_mm": 84.0},
                       "parameters": {"force_N": {"values": [300.0]}, "tissue_thickness_mm": {"values": [40.0]}}})
    res = run_study(cfg, tmp_path / "o", serial=True, progress=False, analyse=False)
    direct = ritz.solve_batch([300.0], free_length_mm=84.0, thickness_mm=[40.0 * 22 / 32, 40.0 * 10 / 32],
                              k_N_per_mm2=[0.048, 0.023])
    assert res.results["tip_deflection_mm"][0] == pytest.approx(direct.tip_deflection_mm[0], rel=1e-12)


def test_failing_case_is_reported_and_others_finish(tmp_path):
    # 200 mm of tissue on an 84 mm free length cannot be built: those cases fail, the rest are computed.
    cfg = parse_study({"study": {"method": "grid", "model": "ritz", "chunk_size": 100},
                       "fixed": {"free_length_mm": 84.0},
                       "parameters": {"force_N": {"values": [100.0, 200.0, 300.0]},
                                      "tissue_thickness_mm": {"values": [20.0, 200.0, 32.0]}}})
    res = run_study(cfg, tmp_path / "o", serial=True, progress=False)
    assert res.n_failed == 3 and res.n_ok == 6
    for f in res.failures:
        assert f["parameters"]["tissue_thickness_mm"] == 200.0
        assert "thickness" in f["error"]
    ok = res.results[res.results.status == "ok"]
    assert np.isfinite(ok["tip_deflection_mm"]).all()
    data = json.loads((tmp_path / "o" / "results.json").read_text(encoding="utf-8"))
    assert data["n_failed"] == 3 and data["failures"][0]["parameters"]["force_N"] in (100.0, 200.0, 300.0)
    assert len(pd.read_csv(tmp_path / "o" / "failures.csv")) == 3


def test_killed_study_resumes_and_computes_every_case_once(tmp_path):
    n = 200
    cfg_path = _write(tmp_path, LHS.format(samples=n, chunk=1))
    out = tmp_path / "o"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "MPLBACKEND": "Agg"}
    proc = subprocess.Popen([*CLI, "study", "--config", str(cfg_path), "--out", str(out), "--quiet"],
                            env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    chunks = out / CHUNK_DIR
    deadline = time.time() + 180  # a cold Numba cache compiles the Ritz kernel first
    try:
        while time.time() < deadline:
            if chunks.is_dir() and len(list(chunks.glob("chunk_*.parquet"))) >= 10:
                break
            if proc.poll() is not None:
                pytest.fail(f"study ended before it could be killed: {proc.stderr.read().decode()[-2000:]}")
            time.sleep(0.01)
        else:
            pytest.fail("no chunks written within 180 s")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the study and its Dask workers, all at once
        proc.wait()
    before = {p.name: (p.stat().st_mtime_ns, pd.read_parquet(p)["run_id"][0]) for p in chunks.glob("chunk_*.parquet")}
    assert 10 <= len(before) < n, "the kill must land part-way"
    assert not (out / "results.json").exists()  # nothing claims the study finished

    res = run_study(load_study(cfg_path), out, serial=True, progress=False, analyse=False)
    assert res.resumed == len(before) and res.computed_this_run == n - len(before)
    assert res.n_ok == n and res.results["case_id"].is_unique
    for name, (mtime, run_id) in before.items():  # finished chunks were not recomputed
        p = chunks / name
        assert p.stat().st_mtime_ns == mtime and pd.read_parquet(p)["run_id"][0] == run_id
    logged = [json.loads(line)["chunk"] for line in (out / "runs.jsonl").read_text(encoding="utf-8").splitlines() if line.strip()]
    assert len(logged) == len(set(logged))  # no chunk persisted twice
    # and the numbers equal an uninterrupted run
    one_chunk = _write(tmp_path, LHS.format(samples=n, chunk=n), "ref.toml")  # same seed: same cases
    ref = run_study(load_study(one_chunk), tmp_path / "ref", serial=True, progress=False, analyse=False)
    pd.testing.assert_frame_equal(_outputs(res).drop(columns="status"), _outputs(ref).drop(columns="status"))


def test_other_config_in_same_folder_is_refused(tmp_path):
    run_study(load_study(_write(tmp_path, LHS.format(samples=10, chunk=5))), tmp_path / "o",
              serial=True, progress=False, analyse=False)
    with pytest.raises(InputError, match="another study"):
        run_study(load_study(_write(tmp_path, LHS.format(samples=12, chunk=5), "b.toml")), tmp_path / "o",
                  serial=True, progress=False, analyse=False)


@pytest.mark.parametrize("snippet, field", [
    ("[parameters.diameter_mm]\ndistribution = 'normal'\nmean = 5.0\nstd = 1.0\n", "parameters.diameter_mm"),
    ("[parameters.k_muscle_N_per_mm2]\ndistribution = 'uniform'\nlow = -0.01\nhigh = 0.1\n",
     "parameters.k_muscle_N_per_mm2"),
    ("[parameters.needle_colour]\nvalues = [1.0]\n", "parameters.needle_colour"),
])
def test_nonphysical_or_unknown_parameter_fails_before_computing(tmp_path, snippet, field):
    base = LHS.format(samples=10, chunk=5).replace("[parameters.diameter_mm]\ndistribution = \"uniform\"\n"
                                                   "low = 4.5\nhigh = 6.0\n", "")
    if "values" in snippet:
        snippet = "[parameters.needle_colour]\ndistribution = 'uniform'\nlow = 1.0\nhigh = 2.0\n"
    p = _write(tmp_path, base + snippet)
    with pytest.raises(InputError) as e:
        load_study(p)
    assert e.value.field == field
    if field != "parameters.diameter_mm":
        return  # the CLI path once is enough
    r = subprocess.run([*CLI, "study", "--config", str(p), "--out", str(tmp_path / "o")], capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert r.returncode == 2 and field in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()


GRID = """
[study]
name = "g"
model = "ritz"
method = "grid"

[parameters.force_N]
values = [100.0, {value}]
"""


def _cli_study(tmp_path, config, *args):
    return subprocess.run([*CLI, "study", "--config", str(config), "--quiet", *args], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}, timeout=120)


@pytest.mark.parametrize("where", ["file", "under_file", "proc"])
def test_unwritable_out_is_refused_and_nothing_is_written(tmp_path, where):
    """--out an existing file, under a file, or where no folder can be made (/proc: read-only even for
    root, who ignores permission bits): an InputError naming --out, nothing written; the CLI once."""
    cfg = load_study(_write(tmp_path, GRID.format(value=200.0)))
    (tmp_path / "a_file").write_text("keep")
    out = {"file": tmp_path / "a_file", "under_file": tmp_path / "a_file" / "o",
           "proc": "/proc/needletissue-test/o"}[where]
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(InputError) as e:
        run_study(cfg, out, serial=True, progress=False)
    assert e.value.field == "--out"
    assert sorted(p.name for p in tmp_path.iterdir()) == before and (tmp_path / "a_file").read_text() == "keep"
    if where == "proc":
        r = _cli_study(tmp_path, tmp_path / "s.toml", "--out", str(out), "--serial")
        assert r.returncode == 2 and r.stderr.startswith("error: --out: "), r.stderr
        assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_grid_value_is_refused_before_anything(tmp_path, value):
    with pytest.raises(InputError) as e:
        load_study(_write(tmp_path, GRID.format(value=value)))
    assert e.value.field == "parameters.force_N.values.1" and "finite" in str(e.value)


@pytest.mark.parametrize("address", ["nonsense://x:1", pytest.param("tcp://127.0.0.1:1", marks=pytest.mark.slow)])
def test_unreachable_scheduler_is_one_line_and_nothing_is_written(tmp_path, address):
    """Before: a traceback after cases.parquet and study.json were written (the slow case waits out the
    10 s connect timeout)."""
    r = _cli_study(tmp_path, _write(tmp_path, GRID.format(value=200.0)), "--out", str(tmp_path / "o"),
                   "--scheduler", address)
    assert r.returncode == 2 and r.stderr.startswith("error: --scheduler: ") and address in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()
