"""Shared fixtures. Meshes are built once per session into a temporary folder; the
FFCx JIT cache (~/.cache/fenics) stays warm across tests and runs."""

import contextlib
import logging
import subprocess
import sys
from pathlib import Path

import pytest

import fenics_elasto  # noqa: F401  (imports dolfinx_solver first)
from fenics_elasto.mesh.builtin import build_scene

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent  # the helpers (independent.py, targets.py, mpi/) live here
BIN = Path(sys.executable).parent


@pytest.fixture(scope="session")
def scenes(tmp_path_factory):
    """Built-in scenes at test sizes: name -> problem.toml path."""
    base = tmp_path_factory.mktemp("scenes")
    return {
        "letter-a": build_scene("letter-a", base / "letter-a"),
        "cantilever": build_scene("cantilever", base / "cantilever"),
        "prostate-phantom": build_scene("prostate-phantom", base / "phantom", size=1.6),
    }


def run_cli(*args, mpi: int = 0, timeout: int = 600) -> subprocess.CompletedProcess:
    """Run the console script (optionally under mpiexec) and capture its output."""
    cmd = [str(BIN / "fenics-elasto"), *map(str, args)]
    if mpi:
        cmd = [str(BIN / "mpiexec"), "-n", str(mpi), *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def run_mpi_script(script: Path, ranks: int, *args, timeout: int = 600) -> subprocess.CompletedProcess:
    cmd = [str(BIN / "mpiexec"), "-n", str(ranks), sys.executable, str(script), *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def assert_picture(path: Path, min_coverage: float = 0.005) -> None:
    """A real picture: a PNG of which some part is drawn, in several colours."""
    import numpy as np
    from PIL import Image

    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    background = image[0, 0]
    drawn = np.abs(image - background).sum(axis=2) > 30
    assert drawn.mean() > min_coverage, f"{path}: only {drawn.mean():.2%} drawn"
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20, f"{path}: too few colours"


@contextlib.contextmanager
def logged(lines: list):
    """The library's progress and warning lines, collected into ``lines``."""
    from fenics_elasto.util.logs import log

    class Keep(logging.Handler):
        def emit(self, record):
            lines.append(record.getMessage())

    keep, level = Keep(), log.level
    log.addHandler(keep)
    log.setLevel(logging.INFO)
    try:
        yield lines
    finally:
        log.removeHandler(keep)
        log.setLevel(level)


def pytest_collection_modifyitems(items):
    """Slow tests first: on two workers (make test), a long test that starts last would
    set the suite's time alone."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
