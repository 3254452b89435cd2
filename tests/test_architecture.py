"""The layers of docs/architecture.md, enforced: every `import needletissue...` in the package (module
level or inside a function) must point at the importing package itself or at a layer it may use."""

import ast
from pathlib import Path

import pytest

import needletissue

ROOT = Path(needletissue.__file__).parent
BASE = {"errors", "runinfo", "cells", "cache"}  # stdlib-level utilities: no package imports above them
ALLOWED = {
    "errors": set(),
    "cells": set(),
    "cache": {"errors", "runinfo"},
    "configs": set(),  # package data (default.toml)
    "runinfo": {"errors"},
    "materials": BASE,
    "fem": BASE | {"materials"},
    "imaging": BASE,
    "geometry": BASE | {"imaging"},
    "ritz": BASE | {"materials"},
    "frame": BASE | {"materials", "ritz"},
    "models": BASE | {"materials", "fem", "geometry", "imaging", "ritz", "frame"},
    "studies": BASE | {"materials", "fem", "geometry", "imaging", "ritz", "frame", "models"},
    "report": BASE | {"materials", "fem", "geometry", "imaging", "ritz", "frame", "models", "studies"},
    "commands": BASE | {"materials", "fem", "geometry", "imaging", "ritz", "frame", "models", "studies",
                        "report"},
    "cli": {"errors", "commands", "__init__"},
}


def _package_of(path: Path) -> str:
    rel = path.relative_to(ROOT)
    return rel.parts[0].removesuffix(".py") if len(rel.parts) > 1 or rel.stem != "__init__" else "__init__"


def _imported(tree: ast.AST) -> set[str]:
    """First component below `needletissue` of every import in the module."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] if node.module != "needletissue" else [f"needletissue.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] == "needletissue":
                out.add(parts[1] if len(parts) > 1 else "__init__")
    return out


MODULES = sorted(p for p in ROOT.rglob("*.py"))


def test_every_package_has_a_layer():
    assert {_package_of(p) for p in MODULES} - {"__init__"} <= set(ALLOWED)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_follow_the_layers(path):
    pkg = _package_of(path)
    if pkg == "__init__":
        return
    used = _imported(ast.parse(path.read_text(encoding="utf-8"))) - {pkg, "__version__"}
    assert used <= ALLOWED[pkg], f"{path.relative_to(ROOT)} imports {sorted(used - ALLOWED[pkg])} above its layer"


def test_the_checker_sees_function_level_imports():
    tree = ast.parse("def f():\n    from needletissue.models.needle import run_needle_model\n")
    assert _imported(tree) == {"models"}
