"""The root command: --version and --help work, for the root and for every materials command."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from typer.testing import CliRunner

from needletissue import __version__
from needletissue.cli import app

runner = CliRunner()


def test_version():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0
    assert r.output.strip() == f"needletissue {__version__}"


@pytest.mark.parametrize("args", [[], ["materials"], ["materials", "list"], ["materials", "curve"],
                                  ["materials", "fit"]])
def test_help(args):
    r = runner.invoke(app, [*args, "--help"])
    assert r.exit_code == 0, r.output
    assert "Usage" in r.output


def test_console_entry_point_version():
    r = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "--version"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and __version__ in r.stdout


def test_python_dash_m_runs_the_command():
    """`python -m needletissue.cli ...` (the documented way to run from a checkout) runs the command; it
    used to import the module, do nothing and exit 0."""
    r = subprocess.run([sys.executable, "-m", "needletissue.cli", "--version"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and __version__ in r.stdout
    r = subprocess.run([sys.executable, "-m", "needletissue.cli", "ritz", "--force", "abc"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "--force" in r.stderr


def _main(*args, **kw):
    return subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", *args],
                          capture_output=True, text=True, timeout=120, **kw)


@pytest.mark.parametrize("args, named", [(["ritz", "--force", "abc"], "--force"),
                                         (["ritz", "--bogus"], "--bogus"),
                                         (["fe", "needle", "--order", "x"], "--order"),
                                         (["nosuch"], "nosuch"),
                                         (["segment"], "ct")])
def test_parser_errors_are_one_line_like_ours(args, named):
    """Typer's boxed usage panels become the one-line `error: ...` the package's own errors use."""
    r = _main(*args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and named in lines[0], r.stderr
    assert "╭" not in r.stderr and "Traceback" not in r.stderr and r.stdout == ""


@pytest.mark.parametrize("command", [["fe", "needle", "--force", "10", "--no-ritz"],
                                     ["fe", "pelvis", "--mesh-size", "8", "--order", "1", "--needle-size", "3"]])
@pytest.mark.parametrize("where", ["file", "file/sub"])
def test_fe_out_on_a_file_is_one_input_error_before_computing(tmp_path, command, where):
    # was: `fe needle` a gmsh child failure (exit 1) naming no option, `fe pelvis` a traceback after the solve
    (tmp_path / "file").write_text("keep")
    r = _main(*command, "--out", str(tmp_path / where))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --out") and "Traceback" not in r.stderr, r.stderr
    assert (tmp_path / "file").read_text() == "keep" and sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_exit_codes_pass_through():
    assert _main("--help").returncode == 0 and _main("ritz", "--force", "10", "--json").returncode == 0


def test_too_fine_needle_mesh_is_refused_before_meshing(tmp_path):
    r = _main("fe", "needle", "--mesh-size", "0.02", "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and r.stderr.startswith("error: mesh_size: about ") and "--max-tetrahedra" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def _children(pid):
    r = subprocess.run(["pgrep", "-P", str(pid), "-a"], capture_output=True, text=True)
    return dict(line.split(" ", 1) for line in r.stdout.splitlines())


@pytest.mark.parametrize("sig, code, said", [(signal.SIGTERM, 143, "stopped (SIGTERM)"),
                                             (signal.SIGINT, 130, "interrupted")])
def test_fe_needle_stopped_while_meshing_leaves_nothing(tmp_path, sig, code, said):
    # SIGTERM used to kill `fe needle` at once: its temporary folders stayed in $TMPDIR and the gmsh
    # child meshed on, writing needle_model.msh into --out after the command had exited.
    out, tmp = tmp_path / "out", tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(tmp))
    p = subprocess.Popen([sys.executable, "-c", "import signal; signal.signal(signal.SIGINT, signal.default_int_handler)"
                          "\nfrom needletissue.cli import main; main()", "fe", "needle", "--force", "10", "--no-ritz",
                          "--order", "1", "--needle-mesh-size", "2.5", "--mesh-size", "8", "--far-mesh-size", "30",
                          "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 60
    while not any("geometry.child" in a for a in _children(p.pid).values()):
        assert p.poll() is None and time.monotonic() < deadline, "the mesher child never started"
        time.sleep(0.05)
    kids = list(_children(p.pid))
    p.send_signal(sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    assert err.strip().splitlines()[-1].startswith(f"error: {said}") and "Traceback" not in err, err
    time.sleep(2)  # an orphan would mesh on and write the mesh now
    assert not [k for k in kids if os.path.exists(f"/proc/{k}")], "a child process outlived the command"
    assert list(tmp.iterdir()) == [] and not out.exists()


def test_command_summaries_are_one_line_each():
    # Typer's rich help kept the docstrings' source line breaks: summaries broke mid-sentence
    r = _main("--help", env=dict(os.environ, COLUMNS="400", TERM="dumb"))
    panel = [line for line in r.stdout.split("Commands")[1].splitlines() if line.startswith("\u2502")]
    names = [line.split()[1] for line in panel]
    assert r.returncode == 0 and len(panel) >= 10 and all(n.isidentifier() for n in names), panel


WARNED = ("hip_cortical: von Mises 508 MPa exceeds its strength 133 MPa (utilisation 3.82): the elastic model is not "
          "valid there")


class _Result:
    """What run_pelvis_model / run_needle_model return, as far as the commands' JSON output reads it."""

    def __init__(self, strength):
        self.results = [type("R", (), {"force_N": f, "strength": s})() for f, s in strength]
        self._d = {"results": [{"force_N": f, "strength": s} for f, s in strength]}

    def to_dict(self):
        return self._d


@pytest.mark.parametrize("command, module, run", [
    (["fe", "pelvis"], "needletissue.models.pelvis", "run_pelvis_model"),
    (["fe", "needle"], "needletissue.models.needle", "run_needle_model"),
])
def test_fe_commands_warn_on_stderr_where_a_stress_passes_its_strength(monkeypatch, command, module, run):
    """A stress past its material's strength is a warning line on stderr per force (the JSON on stdout keeps it
    too, and stays JSON); a force within every strength warns of nothing."""
    import importlib

    strength = [(100.0, {"validity_warnings": []}), (300.0, {"validity_warnings": [WARNED]})]
    monkeypatch.setattr(importlib.import_module(module), run, lambda *a, **k: _Result(strength))
    res = runner.invoke(app, [*command, "--json"])
    assert res.exit_code == 0, res.output
    assert res.stderr.splitlines() == [f"warning: 300 N: {WARNED}"]
    assert json.loads(res.stdout)["results"][1]["strength"]["validity_warnings"] == [WARNED]
