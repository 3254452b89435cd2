"""Every code block in README.md runs: Python blocks execute (numbers in their comments are checked to
the printed digits, a comment starting "True" is a claim that must hold), console blocks rerun and print what the README shows, command synopses name only
options that exist, and the two set-up commands are the Makefile's. After a change that moves a
console output, `python tests/readme_blocks.py --update` rewrites those blocks from a real run."""

from __future__ import annotations

import ast
import re
import subprocess
import sys

import pytest

from readme_blocks import ROOT, blocks, console_commands, environment, matches, run_console

BLOCKS = blocks()
HEAVY = ("run_pelvis_model(", "run_needle_model(", "compare_interfaces(", "solve(model")
NUMBERS = re.compile(r"#\s*([-+]?\d[\d.eE+-]*(?:\s*,\s*[-+]?\d[\d.eE+-]*)*)\s*(?:$|[,;:(])")


def _python_params():
    for b in BLOCKS:
        if b.lang == "python":
            marks = [pytest.mark.slow] if any(h in b.text for h in HEAVY) else []
            yield pytest.param(b, id=b.id, marks=marks)


def _printed_tolerance(token: str) -> float:
    mantissa = token.lower().split("e")[0]
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    exponent = int(token.lower().split("e")[1]) if "e" in token.lower() else 0
    return 0.5 * 10.0 ** (exponent - decimals)


@pytest.mark.parametrize("block", list(_python_params()))
def test_python_block_runs_and_its_numbers_hold(block, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    lines = block.text.splitlines()
    namespace: dict = {"__name__": "__readme__"}
    checked = 0
    for stmt in ast.parse(block.text).body:
        code = compile(ast.Module([stmt], []), block.id, "exec")
        if not isinstance(stmt, ast.Expr):
            exec(code, namespace)
            continue
        value = eval(compile(ast.Expression(stmt.value), block.id, "eval"), namespace)
        comment = lines[stmt.end_lineno - 1].partition("#")[2].strip()
        if comment.startswith("True"):  # a claim the example makes: it must hold
            assert value is True or value == True, f"{block.id}: `{ast.unparse(stmt)}` is {value!r}"  # noqa: E712
            checked += 1
            continue
        m = NUMBERS.search(lines[stmt.end_lineno - 1])
        if m:
            printed = [t.strip() for t in m.group(1).split(",")]
            values = value if isinstance(value, tuple) else (value,)
            assert len(values) == len(printed), f"{block.id}: {lines[stmt.end_lineno - 1]!r}"
            for v, t in zip(values, printed):
                assert abs(float(v) - float(t)) <= _printed_tolerance(t) * (1 + 1e-9), (
                    f"{block.id}: `{ast.unparse(stmt)}` gives {float(v)!r}, the README prints {t}")
                checked += 1
    assert checked or not any(NUMBERS.search(ln) for ln in lines)


def _console_params():
    for b in BLOCKS:
        if b.lang == "console":
            for cmd, expected in console_commands(b):
                if cmd.startswith("needletissue "):
                    marks = [pytest.mark.slow] if " study " in f" {cmd} " else []
                    yield pytest.param(cmd, expected, id=f"{b.id}:{cmd.split(' --')[0]}", marks=marks)


@pytest.mark.parametrize("command, expected", list(_console_params()))
def test_console_block_prints_what_the_readme_shows(command, expected, tmp_path):
    actual = run_console(command, tmp_path)
    assert matches(expected, actual), (
        "README output differs from a real run (update with `python tests/readme_blocks.py --update`):\n"
        + "\n".join(actual))


def test_matching_forgives_timings_and_ellipses_only():
    assert matches(["done in 20.5 s 0:00:11", "a"], ["done in 3.1 s 0:01:02", "a"])
    assert matches(["x", "...", "y"], ["x", "1", "2", "y"]) and matches(["x", "...", "y"], ["x", "y"])
    assert not matches(["tip 5.8883 mm"], ["tip 5.8884 mm"])
    assert not matches(["a", "b"], ["a", "b", "c"])


def _synopses():
    """(command words, options) of every `needletissue ...` line of the bash/plain blocks."""
    out = []
    for b in BLOCKS:
        if b.lang not in ("bash", ""):
            continue
        logical: list[str] = []
        for line in b.text.splitlines():
            if logical and (line.startswith((" ", "\t")) or logical[-1].endswith("\\")):
                logical[-1] = logical[-1].rstrip("\\") + " " + line.strip()
            else:
                logical.append(line.strip())
        for line in logical:
            if not line.startswith("needletissue "):
                continue
            words = []
            for w in line.split()[1:]:
                if not re.fullmatch(r"[a-z][a-z_]*", w):
                    break
                words.append(w)
            out.append(pytest.param(words, sorted(set(re.findall(r"--[a-z][a-z0-9-]*", line))),
                                    id=f"{b.id}:{' '.join(words)}"))
    return out


@pytest.mark.parametrize("words, options", _synopses())
def test_synopsis_names_only_real_options(words, options):
    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", *words, "--help"],
                       capture_output=True, text=True, env=dict(environment(), COLUMNS="200"), timeout=120)
    assert p.returncode == 0, p.stderr
    missing = [o for o in options if not re.search(rf"{re.escape(o)}(?![a-z0-9-])", p.stdout)]
    assert not missing, f"`needletissue {' '.join(words)} --help` has no {missing}"


def test_the_two_setup_commands_are_the_makefiles():
    (setup,) = [b for b in BLOCKS if b.lang == "bash" and b.text.startswith("make demo")]
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    for line in setup.text.splitlines():
        target, _, comment = line.partition("#")
        target = target.split()[1]
        assert re.search(rf"^{target}:", makefile, re.M), target
        said = re.search(r"`([^`]+)`", comment)
        if said:  # the command the comment names is the recipe's
            recipe = re.search(rf"^{target}:.*\n((?:\t.*\n)+)", makefile, re.M).group(1)
            assert said.group(1) in recipe.replace("$(BIN)/", ""), (target, said.group(1))


def test_the_demo_block_lists_the_pipeline_stages_in_order():
    from needletissue.report.stages import stage_list

    (demo,) = [b for b in BLOCKS if b.lang == "console" and b.text.startswith("$ make demo")]
    shown = [ln[2:].split(" ok ")[0].strip() for ln in demo.text.splitlines() if ln.startswith("• ")]
    assert shown == [s.title for s in stage_list()]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """One run of `make demo`'s command (the default configuration), as a user gets it."""
    from readme_blocks import run_demo

    out = tmp_path_factory.mktemp("demo") / "results"
    p = run_demo(out)
    assert p.returncode == 0, p.stderr[-3000:]
    return out, p


@pytest.mark.slow
def test_demo_runs_every_stage_and_writes_what_the_readme_says(demo):
    import json

    out, p = demo
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert {k: v["status"] for k, v in data["stages"].items()} == {k: "ok" for k in data["stages"]}
    # the reconciliation ran its chain, and every row that differs from the paper has a measured reason
    from needletissue.report.pipeline import NO_REASON

    assert data["reconciliation"]["chain"] and data["reconciliation"]["ratio_300_vs_100N"]
    differs = [c for c in data["comparison_with_paper"] if c["verdict"].startswith("differs")]
    assert differs and all(c["reason"] and c["reason"] != NO_REASON for c in differs), differs
    (block,) = [b for b in BLOCKS if b.lang == "console" and b.text.startswith("$ make demo")]
    lines = block.text.strip().splitlines()
    wrote = " ".join(lines[next(i for i, ln in enumerate(lines) if ln.startswith("wrote ")):])
    files = [f.strip() for f in wrote.split(":", 1)[1].split(",")]
    assert all((out / f).is_file() for f in files), files
    assert wrote.split("(")[0] in p.stdout.replace(str(out), "results").replace("\n", " ")


@pytest.mark.slow
def test_readme_comparison_is_the_demos(demo):
    from readme_blocks import README, comparison_section, report_differences

    out, _ = demo
    text = README.read_text(encoding="utf-8")
    a, b = comparison_section(text)
    differences = report_differences(text[a:b], (out / "comparison.md").read_text(encoding="utf-8"))
    assert not differences, (
        "README's comparison differs from make demo's comparison.md "
        "(python tests/readme_blocks.py --update --demo RESULTS_DIR):\n" + "\n".join(differences))


def test_comparison_check_catches_a_changed_number_or_word():
    from readme_blocks import report_differences

    row = "| FE at 100 N | 2.083 mm | 5.815 mm | differs (-64 %) | frame 2.28 mm |"
    assert report_differences(row, row.replace("2.083", "2.06").replace("-64", "-65")) == []
    assert report_differences(row, row.replace("differs", "agrees")) == []
    assert report_differences(row, row.replace("2.083", "2.5")) == ["2.083 vs 2.5"]
    assert report_differences(row, row.replace("frame", "ritz"))[0] == "the words differ:"


@pytest.mark.slow
@pytest.mark.browser
def test_demo_report_and_its_3d_views_work_in_chromium(demo):
    sys.path.insert(0, str(ROOT / "tests" / "report"))
    from test_viewer import open_in_browser

    out, _ = demo
    for width in (1200, 390):
        with open_in_browser(out / "report.html", width=width) as (page, errors):
            page.wait_for_function("[...document.querySelectorAll('.ntv')].every(v => v.dataset.ready === '1')",
                                   timeout=60000)
            drawn = page.evaluate("[...document.querySelectorAll('.ntv')].map(v => v.viewer.drawn)")
            assert len(drawn) >= 1 and all(n > 100 for n in drawn), drawn
            assert page.evaluate("document.documentElement.scrollWidth") <= width, "scrolls sideways"
            assert not errors, errors
            assert all(src.startswith("data:") for src in page.eval_on_selector_all("img", "e => e.map(i => i.src)"))
