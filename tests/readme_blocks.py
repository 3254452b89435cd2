"""The README's code blocks as data: parse them, run their console commands, compare or update.

`python tests/readme_blocks.py --update [--demo RESULTS_DIR]` reruns every `$ needletissue ...` console
block and writes the real output back into README.md (timings are the only thing the comparison
forgives), and puts the comparison table of a `make demo` run (RESULTS_DIR, or a new run) between its
markers.
"""

from __future__ import annotations

import difflib
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```\n", re.S | re.M)
# Wall times and elapsed clocks change run to run; everything else must match.
# Progress bars take the width the terminal leaves them.
TIMING = [(re.compile(r"\b\d+:\d\d:\d\d\b"), "<clock>"), (re.compile(r"\b\d+(\.\d+)? s\b"), "<t> s"),
          (re.compile("\u2501+"), "\u2501")]


@dataclass(frozen=True)
class Block:
    line: int       # line of the opening fence, 1-based
    lang: str
    text: str
    start: int      # character offsets of the body in README.md
    end: int

    @property
    def id(self) -> str:
        return f"README.md:{self.line}:{self.lang or 'text'}"


def blocks(text: str | None = None) -> list[Block]:
    text = README.read_text(encoding="utf-8") if text is None else text
    out = []
    for m in FENCE.finditer(text):
        out.append(Block(text.count("\n", 0, m.start()) + 1, m.group(1), m.group(2), m.start(2), m.end(2)))
    return out


def console_commands(block: Block) -> list[tuple[str, list[str]]]:
    """(command, expected output lines) for each `$ ` prompt of a console block."""
    cmds: list[tuple[str, list[str]]] = []
    for line in block.text.splitlines():
        if line.startswith("$ "):
            cmds.append((line[2:], []))
        elif cmds:
            cmds[-1][1].append(line)
    for _, lines in cmds:
        while lines and not lines[-1].strip():
            lines.pop()
    return cmds


def environment() -> dict:
    env = dict(os.environ, COLUMNS="100", NO_COLOR="1", TERM="dumb", PYTHONWARNINGS="ignore")
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def run_console(command: str, cwd: Path) -> list[str]:
    """Run a README console command as a user would (shell, the venv's needletissue), in cwd, where
    `examples` points at the repository's examples folder. Returns stdout and stderr lines."""
    examples = cwd / "examples"
    if not examples.exists():
        examples.symlink_to(ROOT / "examples")
    p = subprocess.run(command, shell=True, cwd=cwd, env=environment(), capture_output=True, text=True,
                       timeout=900)
    if p.returncode != 0:
        raise AssertionError(f"`{command}` exited {p.returncode}:\n{p.stderr[-3000:]}")
    lines = (p.stdout + p.stderr).splitlines()
    return [ln.rstrip() for ln in lines if ln.strip()]


def normalise(lines: list[str]) -> list[str]:
    out = []
    for ln in lines:
        for pattern, repl in TIMING:
            ln = pattern.sub(repl, ln)
        out.append(ln.rstrip())
    return out


def matches(expected: list[str], actual: list[str]) -> bool:
    """Line by line after normalising timings; a line `...` stands for any number of lines."""
    exp, act = normalise([e for e in expected if e.strip()]), normalise(actual)
    pattern = "".join(r"(?:[^\n]*\n)*?" if e == "..." else re.escape(e) + "\n" for e in exp)
    return re.fullmatch(pattern, "".join(a + "\n" for a in act)) is not None


BEGIN, END = "<!-- comparison:begin", "<!-- comparison:end -->"
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
VERDICT = re.compile(r"\b(?:meets|fails) the criterion|\b(?:agrees|differs)\b")


def report_differences(expected: str, actual: str, rel: float = 0.15, absolute: float = 0.05) -> list[str]:
    """Where two renderings of the demo's comparison differ beyond install jitter: the words must be the same
    (a verdict may flip: its number moves), every number within `rel` or `absolute`. The demo's anatomical
    mesh (gmsh, box route) is not the same on every install: 2.083 vs 2.060 mm at 100 N, and the
    differences of close numbers move most (|frame - FE| 0.390 vs 0.436 mm, 'FE -8.7 / -9.7 % from the limit')."""
    def split(text):
        text = VERDICT.sub("<verdict>", text)
        return NUMBER.sub("<n>", text), [float(x) for x in NUMBER.findall(text)]

    (skel_e, num_e), (skel_a, num_a) = split(expected), split(actual)
    if skel_e != skel_a:
        diff = difflib.unified_diff(skel_e.splitlines(), skel_a.splitlines(), lineterm="", n=0)
        return ["the words differ:", *list(diff)[2:12]]
    return [f"{e:g} vs {a:g}" for e, a in zip(num_e, num_a)
            if abs(e - a) > max(rel * max(abs(e), abs(a)), absolute)]


def comparison_section(text: str) -> tuple[int, int]:
    """Offsets of the generated comparison table between its markers."""
    start = text.index("\n", text.index(BEGIN)) + 1
    return start, text.index(END)


def demo_command(out: Path) -> list[str]:
    """`make demo`'s recipe, writing into out instead of results/."""
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    recipe = re.search(r"^demo:.*\n\t(.*)$", makefile, re.M).group(1).split()
    exe = Path(sys.executable).parent / Path(recipe[0]).name
    args = recipe[1:]
    args[args.index("--out") + 1] = str(out)
    return [str(exe), *args]


def run_demo(out: Path) -> subprocess.CompletedProcess:
    return subprocess.run(demo_command(out), env=environment(), capture_output=True, text=True, timeout=3600)


def update(cwd: Path, demo: Path | None = None) -> None:
    text = README.read_text(encoding="utf-8")
    if demo is None:
        demo = cwd / "demo"
        p = run_demo(demo)
        if p.returncode != 0:
            raise SystemExit(f"make demo's command failed:\n{p.stderr[-3000:]}")
        # the demo block: its stage lines and summary as a user sees them (results/ for the folder)
        shown = [ln.rstrip().replace(str(demo), "results") for ln in (p.stdout + p.stderr).splitlines()
                 if ln.startswith(("\u2022 ", "wrote ", "versions.json"))]
        (block,) = [b for b in blocks(text) if b.lang == "console" and b.text.startswith("$ make demo")]
        text = text[:block.start] + "\n".join(["$ make demo", "...", *shown]) + "\n" + text[block.end:]
    a, b = comparison_section(text)
    text = text[:a] + (demo / "comparison.md").read_text(encoding="utf-8") + text[b:]
    for b in reversed(blocks(text)):
        if b.lang != "console" or "$ needletissue" not in b.text:
            continue
        body = []
        for cmd, _ in console_commands(b):
            body += [f"$ {cmd}", *run_console(cmd, cwd), ""]
        text = text[:b.start] + "\n".join(body).rstrip() + "\n" + text[b.end:]
    README.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    import tempfile

    args = sys.argv[1:]
    if not args or args[0] != "--update" or len(args) not in (1, 3) or (len(args) == 3 and args[1] != "--demo"):
        sys.exit("usage: python tests/readme_blocks.py --update [--demo RESULTS_DIR]")
    with tempfile.TemporaryDirectory() as tmp:
        update(Path(tmp), Path(args[2]).resolve() if len(args) == 3 else None)
