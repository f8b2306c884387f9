"""The package's rooms: data flows one way through the layers, and every class and
function stays short enough to read (docs/layout.md)."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "fenics_elasto"
LAYERS = ["util", "config", "geometry", "files", "mesh", "model", "inverse", "app"]  # bottom to top
MODULES = sorted(PACKAGE.rglob("*.py"))


def _layer(path: Path) -> str | None:
    parts = path.relative_to(PACKAGE).parts
    return parts[0] if len(parts) > 1 and parts[0] in LAYERS else None


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_import_against_the_layers(path):
    """A module imports only from its own layer and the ones below it."""
    layer = _layer(path)
    if layer is None:
        return
    upward = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("fenics_elasto."):
            other = node.module.split(".")[1]
            if other in LAYERS and LAYERS.index(other) > LAYERS.index(layer):
                upward.append(f"line {node.lineno}: {node.module}")
    assert not upward, upward


def test_no_long_classes_or_functions():
    """No class over 150 lines, no function over 60 (docstrings included)."""
    long = []
    for path in MODULES:
        for node in ast.walk(ast.parse(path.read_text())):
            size = getattr(node, "end_lineno", 0) - getattr(node, "lineno", 0) + 1
            if isinstance(node, ast.ClassDef) and size > 150 or isinstance(node, ast.FunctionDef) and size > 60:
                long.append(f"{path.relative_to(PACKAGE)}:{node.name} ({size} lines)")
    assert not long, long


@pytest.mark.xdist_group("grouping-check")
def test_grouped_tests_share_a_worker(request):
    """Under make test's --dist loadgroup, an xdist_group test carries its group in its node
    id; pytest 9.2 with pytest-xdist 3.8 dropped it silently, and the family3d tests went to
    both workers, each making the truth (~65 s). Pin pytest where the group survives."""
    if getattr(request.config.option, "loadgroup", False):  # set on xdist's workers only
        assert request.node.nodeid.endswith("@grouping-check"), f"{request.node.nodeid}: pin pytest (constraints.txt)"
