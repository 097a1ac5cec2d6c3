"""The package's shape, checked: the rules of ``../shared/STYLE.md`` that a linter does not check.

The layers themselves (method never imports io, stages or report; only the CLI and ``run`` import stages)
are import-linter contracts in ``pyproject.toml`` (``make lint``); here: which modules may import the
libraries that touch the outside world, and how large a module, class or function may grow.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "batchpose"
MODULES = sorted(PACKAGE.rglob("*.py"))

#: Largest module (lines), class (lines) and function (lines) the package keeps; past them, split.
MAX_MODULE, MAX_CLASS, MAX_FUNCTION = 600, 300, 80

#: External packages only these modules (paths under batchpose/, glob patterns) may import.
OWNERS = {
    "mcap": ("io/mcap_*.py",),
    "mcap_protobuf": ("io/mcap_*.py",),
    "mcap_ros1": ("io/mcap_*.py",),
    "mcap_ros2": ("io/mcap_*.py",),
    "foxglove_schemas_protobuf": ("io/mcap_*.py",),
    "av": ("io/video.py",),
    "pyrender": ("method/render.py",),
    "OpenGL": ("method/render.py",),
    "matplotlib": ("report/figures.py",),
    "joblib": ("stages/*.py",),
    "dask": ("run.py", "stages/*.py"),
}


def _imported(tree: ast.AST) -> set[str]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def _rel(path: Path) -> str:
    return path.relative_to(PACKAGE).as_posix()


@pytest.mark.parametrize("path", MODULES, ids=_rel)
def test_outside_world_libraries_are_imported_by_their_owner_only(path):
    rel = Path(_rel(path))
    for lib in _imported(ast.parse(path.read_text())) & set(OWNERS):
        assert any(rel.match(p) for p in OWNERS[lib]), f"{rel} imports {lib}; only {OWNERS[lib]} may"


@pytest.mark.parametrize("path", MODULES, ids=_rel)
def test_modules_classes_and_functions_stay_small(path):
    text = path.read_text()
    n_lines = len(text.splitlines())
    assert n_lines <= MAX_MODULE, f"{_rel(path)}: {n_lines} lines (at most {MAX_MODULE})"
    for node in ast.walk(ast.parse(text)):
        size = (node.end_lineno or node.lineno) - node.lineno + 1 if hasattr(node, "lineno") else 0
        if isinstance(node, ast.ClassDef):
            assert size <= MAX_CLASS, f"{_rel(path)}: class {node.name} has {size} lines (at most {MAX_CLASS})"
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            assert size <= MAX_FUNCTION, f"{_rel(path)}: {node.name}() has {size} lines (at most {MAX_FUNCTION})"


def test_no_test_hook_in_the_product():
    """Runs are stopped part-way by a test fixture (tests/conftest.py ``stop_run``), not by a product flag."""
    for path in MODULES:
        assert "max_pairs" not in path.read_text(), f"{_rel(path)} still has the max_pairs test hook"
