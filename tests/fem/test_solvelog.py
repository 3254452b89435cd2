"""A solve's progress log (fem.solvelog.SolveLog): one line per event as it happens, and the load reached
when the solve fails or is stopped."""

import re

import numpy as np
import pytest

from needletissue.errors import ConvergenceError, InputError
from needletissue.fem import FEModel, Fixed, PrescribedDisplacement, TaggedMesh, solve
from needletissue.fem.solvelog import SolveLog, read_log


@pytest.fixture(scope="module")
def block():
    return TaggedMesh.box((10, 10, 10), (3, 3, 3), region="adipose")


def test_log_of_a_converged_solve_adds_up(block, tmp_path):
    """The increments' load factors grow to the target and add up to it; their Newton iterations and
    their count are the result's; the load is the factor times the scale."""
    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, 12.0))]
    with SolveLog(tmp_path / "log.jsonl", scale=12.0, load_key="top_mm", case="stretch") as log:
        res = solve(FEModel(block, {"adipose": "adipose"}), bcs, [0.5, 1.0], progress=False, maxiter=6, log=log)
    ev = read_log(tmp_path / "log.jsonl")
    assert ev[0] == {"event": "start", "case": "stretch"}
    assert ev[-1]["event"] == "done" and ev[-1]["load_factor"] == pytest.approx(1.0)
    inc = [e for e in ev if e["event"] == "increment"]
    assert len(inc) == res[-1].steps and sum(e["iterations"] for e in inc) == res[-1].newton_iterations
    lam = np.array([e["load_factor"] for e in inc])
    assert np.all(np.diff(lam) > 0) and lam[-1] == pytest.approx(1.0)
    assert sum(e["increment"] for e in inc) == pytest.approx(1.0)
    assert all(e["top_mm"] == pytest.approx(12.0 * e["load_factor"]) for e in inc)
    cpu = [e["cpu_s"] for e in inc]
    assert cpu == sorted(cpu)
    # the hard increment (Ogden stretch 2.2, 6 iterations) was cut back, and the log says so
    assert res[-1].cutbacks == sum(e["event"] == "cutback" for e in ev) > 0
    # each increment's relative residuals, one per Newton iteration, the last within the tolerance (1e-8); the
    # cut-back's all above it
    assert all(len(e["residuals"]) == e["iterations"] and e["residuals"][-1] < 1e-8 for e in inc)
    assert [e["residuals"] for e in inc] == res[-1].residual_norms  # the result's per-increment norms
    cut = [e for e in ev if e["event"] == "cutback"]
    assert all(len(e["residuals"]) == 6 and min(e["residuals"]) >= 1e-8 for e in cut)


def test_log_of_a_failed_solve_names_the_load_reached(block, tmp_path):
    """ConvergenceError: the last line is "failed" at the load factor the error names, which is the last
    converged increment's."""
    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, -12.0))]
    path = tmp_path / "log.jsonl"
    with pytest.raises(ConvergenceError) as info, SolveLog(path, scale=-12.0, load_key="top_mm") as log:
        solve(FEModel(block, {"adipose": "adipose"}), bcs, [0.5, 1.0], progress=False, min_step=0.01, log=log)
    reached = float(re.search(r"load factor ([0-9.]+)", str(info.value)).group(1))
    ev = read_log(path)
    assert [e["event"] for e in ev].count("failed") == 1 and ev[-1]["event"] == "failed"
    assert ev[-1]["load_factor"] == pytest.approx(reached, rel=1e-5)
    assert ev[-1]["load_factor"] == [e for e in ev if e["event"] == "increment"][-1]["load_factor"]
    assert ev[-2]["event"] == "cutback"


def test_a_stopped_solve_logs_the_load_reached(block, tmp_path):
    """A stop from outside the solver (the CLI turns SIGTERM into SystemExit; here after the third increment)
    leaves the log ending in "stopped" with the last converged load."""
    class Stopping(SolveLog):
        def __call__(self, rec):
            super().__call__(rec)
            if sum(1 for e in read_log(self.path) if e["event"] == "increment") == 3:
                raise SystemExit(143)

    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, 6.0))]
    path = tmp_path / "log.jsonl"
    with pytest.raises(SystemExit), Stopping(path) as log:
        solve(FEModel(block, {"adipose": "adipose"}), bcs, [1.0], progress=False, initial_step=0.1, max_step=0.1,
              log=log)
    ev = read_log(path)
    inc = [e for e in ev if e["event"] == "increment"]
    assert len(inc) == 3 and ev[-1]["event"] == "stopped"
    assert ev[-1]["load_factor"] == pytest.approx(0.3) == inc[-1]["load_factor"]
    assert ev[-1]["load"] == pytest.approx(0.3)


def test_a_restart_from_a_saved_state_reaches_the_same_solution(block):
    """solve(start=...) continues from the fields and body states of a converged load factor (the
    restarts of docs/contact.md): the end state equals an uninterrupted solve's to Newton's tolerance."""
    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, 6.0))]
    full = solve(FEModel(block, {"adipose": "adipose"}), bcs, [0.5, 1.0], progress=False)[-1]
    first = FEModel(block, {"adipose": "adipose"})
    solve(first, bcs, [0.5], progress=False)
    again = FEModel(block, {"adipose": "adipose"})
    for f, g in zip(again.field.fields, first.field.fields):
        f.values[:] = g.values
    for k, b in again.bodies.items():
        b.restore(first.bodies[k].checkpoint())
    events = []
    rest = solve(again, bcs, [1.0], progress=False, start=0.5, log=events.append)[-1]
    scale = np.abs(full.displacement).max()
    assert np.abs(rest.displacement - full.displacement).max() < 1e-6 * scale
    inc = [e for e in events if e["event"] == "increment"]
    assert sum(e["increment"] for e in inc) == pytest.approx(0.5)  # it did not redo the first half
    with pytest.raises(InputError, match="start"):
        solve(FEModel(block, {"adipose": "adipose"}), bcs, [0.5], progress=False, start=0.5)
