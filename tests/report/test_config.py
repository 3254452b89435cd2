"""The reproduce config: shipped default is valid, overrides merge, bad input names the field (before any stage)."""

import subprocess
import sys

import pytest

from needletissue.errors import InputError
from needletissue.report.config import ReproduceConfig, default_dict, load_config

CLI = [sys.executable, "-c", "from needletissue.cli import main; main()"]


def test_default_is_complete_and_valid():
    cfg = load_config()
    assert isinstance(cfg, ReproduceConfig)
    # the paper's loads and Table 1 layers are the defaults
    assert cfg.ritz.forces_N == [100.0, 200.0, 300.0]
    assert [(l.thickness_mm, l.k_N_per_mm2) for l in cfg.ritz.layers] == [(22.0, 0.048), (10.0, 0.023)]


def test_every_field_has_a_description():
    def walk(model_cls):
        for name, f in model_cls.model_fields.items():
            assert f.description, f"{model_cls.__name__}.{name} has no description"
            ann = f.annotation
            sub = getattr(ann, "__args__", (ann,))
            for a in (*sub, *(getattr(x, "__args__", ()) for x in sub)):
                if isinstance(a, type) and hasattr(a, "model_fields"):
                    walk(a)

    for name, f in ReproduceConfig.model_fields.items():
        walk(f.annotation)


def test_length_fields_state_mm_in_description():
    for name, f in ReproduceConfig.model_fields["ritz"].annotation.model_fields.items():
        if name.endswith("_mm"):
            assert "mm" in f.description
        if name.endswith("_N"):
            assert " N" in f.description
        if name.endswith("_MPa"):
            assert "MPa" in f.description


def test_override_merges_one_field(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[ritz]\ndiameter_mm = 6.0\n")
    cfg = load_config(p)
    assert cfg.ritz.diameter_mm == 6.0
    assert cfg.ritz.forces_N == default_dict()["ritz"]["forces_N"]


@pytest.mark.parametrize("text, field", [
    ("[ritz]\nbogus = 1\n", "ritz.bogus"),
    ("[nonsense]\nx = 1\n", "nonsense"),
    ("[ritz]\ndiameter_mm = -5.0\n", "ritz.diameter_mm"),
    ("[ritz]\nforces_N = [100.0, 5000.0]\n", "ritz.forces_N"),
    ("[ritz]\norder = 2\n", "ritz.order"),
    ("[[ritz.layers]]\nname = 'muscle'\nthickness_mm = 0.0\nk_N_per_mm2 = 0.048\n", "ritz.layers.0.thickness_mm"),
    ("[needle_fe]\nneedles = 3\n", "needle_fe.needles"),
    ("[materials]\nstretch_max = 'big'\n", "materials.stretch_max"),
])
def test_bad_field_is_named(tmp_path, text, field):
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        load_config(p)
    assert e.value.field == field


def test_cli_bad_config_exit_2_before_any_output(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[ritz]\ndiameter_mm = 0\n")
    out = tmp_path / "res"
    r = subprocess.run([*CLI, "reproduce", "--config", str(p), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "ritz.diameter_mm" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


def test_config_show_round_trips(tmp_path):
    r = subprocess.run([*CLI, "config", "show"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    p = tmp_path / "shown.toml"
    p.write_text(r.stdout)
    assert load_config(p) == load_config()


@pytest.mark.parametrize("args", [["reproduce"], ["config"], ["config", "show"], ["study"]])
def test_help_gives_units(args):
    from typer.testing import CliRunner

    from needletissue.cli import app

    r = CliRunner().invoke(app, [*args, "--help"])
    assert r.exit_code == 0 and "Usage" in r.output
