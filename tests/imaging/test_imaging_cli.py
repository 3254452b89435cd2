"""`needletissue segment / mesh / thickness` end to end on the phantom; bad input -> exit code 2."""

import json

import meshio
import pytest

from phantom import R_BODY, R_BONE


def test_segment_mesh_thickness(phantom_ct, tmp_path, run_cli):
    seg_dir, mesh_dir = tmp_path / "seg", tmp_path / "mesh"
    code, out, err = run_cli("segment", phantom_ct, "--out", seg_dir)
    assert code == 0, err
    tissues = json.loads((seg_dir / "tissues.json").read_text(encoding="utf-8"))
    assert {"cortical_bone", "cancellous_bone", "muscle", "adipose"} <= set(tissues)
    for f in ("tissues.nii.gz", "config.toml", "versions.json", "results.json"):
        assert (seg_dir / f).is_file()
    code, out, err = run_cli("mesh", seg_dir, "--size", 4, "--out", mesh_dir)
    assert code == 0, err
    m = meshio.read(mesh_dir / "mesh.msh")
    assert {"cortical_bone", "muscle", "adipose"} <= set(m.field_data)
    assert (mesh_dir / "surfaces" / "adipose.stl").is_file() and (mesh_dir / "mesh.vtu").is_file()
    res = json.loads((mesh_dir / "results.json").read_text(encoding="utf-8"))
    assert res["quality"]["min_dihedral_deg"] > 0
    assert res["mesh_info"]["method"] == "smooth" and res["wall_time_s"]["surfaces"] > 0   # the defaults
    assert all(r["watertight"] and r["manifold"] for r in res["surfaces"].values())
    # phantom centre in LPS: origin (100, 50, -20), direction diag(-1, -1, 1), 64 x 64 voxels of 2 mm
    cx, cy = 100 - 63.0, 50 - 63.0
    code, out, err = run_cli("thickness", seg_dir, f"--entry={cx + 80},{cy},20",
                         "--direction=-1,0,0", "--json")
    assert code == 0, err
    r = json.loads(out)
    assert r["soft_tissue_thickness_mm"] == pytest.approx(R_BODY - R_BONE, abs=2.0)  # 2 mm voxels
    assert r["frame"].startswith("LPS")


def test_bad_input_exit_code_2(tmp_path, run_cli, phantom_ct):
    bad = tmp_path / "scan.nii.gz"
    bad.write_text("hello")
    code, _, err = run_cli("segment", bad, "--out", tmp_path / "o")
    assert code == 2 and "scan.nii.gz" in err and "Traceback" not in err
    code, _, err = run_cli("mesh", tmp_path / "nothing", "--out", tmp_path / "o")
    assert code == 2 and "tissues.nii.gz" in err
    code, _, err = run_cli("segment", phantom_ct, "--out", tmp_path / "o",
                       "--cortical-thickness", "-1")
    assert code == 2 and "cortical_thickness" in err


def test_output_folder_that_cannot_be_made_exit_code_2(tmp_path, run_cli, phantom_ct):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = run_cli("segment", phantom_ct, "--out", blocker / "seg")
    assert code == 2 and str(blocker / "seg") in err and "cannot write" in err


def test_mesh_stopped_leaves_no_output(phantom_ct, tmp_path, run_cli):
    # `mesh` used to write surfaces/ straight into --out: SIGTERM mid-run left a folder of surfaces
    # without mesh.msh or results.json, which looked like a (surface-only) result
    import os
    import signal
    import subprocess
    import sys
    import time

    seg_dir, out = tmp_path / "seg", tmp_path / "mesh"
    assert run_cli("segment", phantom_ct, "--out", seg_dir)[0] == 0
    p = subprocess.Popen([sys.executable, "-m", "needletissue.cli", "mesh", str(seg_dir), "--size", "4",
                          "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=dict(os.environ))
    deadline = time.monotonic() + 60
    while True:   # the surfaces child running: the command is past its checks and meshing
        kids = subprocess.run(["pgrep", "-P", str(p.pid), "-a"], capture_output=True, text=True).stdout
        if "geometry.child" in kids:
            break
        assert p.poll() is None and time.monotonic() < deadline, "the surfaces child never started"
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143 and "stopped (SIGTERM)" in err, err
    time.sleep(1)  # an orphaned child would write its surfaces now
    assert not out.exists()
