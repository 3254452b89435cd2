"""gmsh's initialisation reset SIGTERM to its default action at the OS level: after an in-process mesh
(`fe pelvis`, TetGen/gmsh meshes) SIGTERM killed the command outright instead of unwinding it."""

import subprocess
import sys

import pytest

PROBE = """
import os, signal, sys, time
seen = []
signal.signal(signal.SIGTERM, lambda s, f: seen.append(s))
{mesh}
os.kill(os.getpid(), signal.SIGTERM)
time.sleep(0.5)
print("handled" if seen == [signal.SIGTERM] else "not handled")
"""

CASES = {
    "initialize": "from needletissue.geometry.gmsh_init import initialize\ninitialize()\nimport gmsh\ngmsh.finalize()",
    "needle mesh in process": (
        "from needletissue.geometry.needle import NeedleGeometry, mesh_needle_model\n"
        "g = NeedleGeometry(needles=1, needle_mesh_size=2.5, mesh_size=8.0, far_mesh_size=30.0)\n"
        "mesh_needle_model(g, {out!r}, isolate=False)"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_sigterm_handler_survives_gmsh(case, tmp_path):
    code = PROBE.format(mesh=CASES[case].format(out=str(tmp_path / "m.msh")))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip().endswith("handled") and "not handled" not in r.stdout, \
        (r.returncode, r.stdout[-300:], r.stderr[-300:])


HELD = """
import os, signal, sys
sys.path.insert(0, {tmp!r})
seen = []
def handler(s, f):
    seen.append(("signal", "selfkill" in sys.modules and sys.modules["selfkill"].done))
signal.signal(signal.SIGTERM, handler)
from needletissue.geometry.gmsh_init import import_holding_signals
import_holding_signals("selfkill")
print(seen, signal.getsignal(signal.SIGTERM) is handler)
"""


def test_signal_during_native_import_waits_for_the_import(tmp_path):
    # SIGTERM raised inside VTK's extension-module initialisation (`import pyvista` in `mesh`) left a
    # half-made module and the process died of SIGSEGV; the handler must run once the import is whole
    (tmp_path / "selfkill.py").write_text("import os, signal\nos.kill(os.getpid(), signal.SIGTERM)\n"
                                          "done = True\n")
    r = subprocess.run([sys.executable, "-c", HELD.format(tmp=str(tmp_path))], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.split() == ["[('signal',", "True)]", "True"], (r.stdout, r.stderr)
