"""What a mesh will cost, known before it is made.

A mesh of a region of measure V (area or volume) with element size h(x) has about
``integral dV / (c h(x)^dim)`` cells; the scene builders estimate that integral from
their geometry and size field (meshing.py). ``check_mesh_cost`` turns the count into
the memory and time gmsh will need and refuses, in one line, a mesh that cannot fit
in the memory available (before gmsh fills it and the machine swaps), or warns with
the expected memory and time when it will be long.

The rates are measured here (gmsh 4.15, 2 cores, quadratic elements, optimisation
included; `fenics-elasto mesh` under ``/usr/bin/time``): letter-a h = 0.02, 200k
triangles in 21 s, ~0.6 kB each; prostate-phantom h = 0.7, 74k tetrahedra in 15 s,
~1.8 kB each. They are rounded up, as the estimate of the count is good to ~20 %.
"""

from __future__ import annotations

import os

from fenics_elasto.util.errors import UserError
from fenics_elasto.util.logs import log

CELLS_PER_VOLUME = {2: 1 / 0.43, 3: 1 / 0.19}  # cells per h^dim of area/volume (gmsh, measured on the scenes)
BYTES_PER_CELL = {2: 1000.0, 3: 2500.0}
SECONDS_PER_CELL = {2: 1.2e-4, 3: 2.5e-4}
DOFS_PER_CELL = {2: 4.0, 3: 4.5}  # vector P2: 2 x (vertices + edges) per triangle, 3 x per tetrahedron
BASE_BYTES = 300e6  # Python, gmsh and the FE stack before the first cell
WARN_SECONDS = 60.0
WARN_MEMORY_SHARE = 0.25  # warn when the mesh needs more than this share of the free memory
CELL_NAMES = {2: "triangles", 3: "tetrahedra"}


def available_memory() -> float:
    """Bytes the system can give without swapping (MemAvailable), or the physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def _bytes(value: float) -> str:
    return f"{value / 1e9:.3g} GB" if value >= 1e9 else f"{value / 1e6:.0f} MB"


def _seconds(value: float) -> str:
    return f"{value / 3600:.2g} h" if value >= 3600 else f"{value / 60:.2g} min" if value >= 60 else f"{value:.0f} s"


def check_mesh_cost(label: str, cells: float, dim: int, size: float, available: float | None = None) -> None:
    """Refuse a mesh of about ``cells`` cells that cannot fit in memory; warn about a
    long one. ``label`` names the command and size at fault (``mesh letter-a --size
    0.001``); ``size``: the element size given, to say which one would fit (the count
    goes as size^-dim)."""
    available = available_memory() if available is None else available
    memory = BASE_BYTES + cells * BYTES_PER_CELL[dim]
    seconds = cells * SECONDS_PER_CELL[dim]
    count = f"about {cells:.2g} {CELL_NAMES[dim]} (~{cells * DOFS_PER_CELL[dim]:.2g} DOFs at degree 2)"
    if memory > available:
        fits = (available - BASE_BYTES) / BYTES_PER_CELL[dim]
        smallest = size * (cells / max(fits, 1.0)) ** (1 / dim)
        raise UserError(f"{label}: {count} would need ~{_bytes(memory)} to mesh, {_bytes(available)} available; "
                        f"use a size >= {smallest:.3g}")
    if seconds > WARN_SECONDS or memory > WARN_MEMORY_SHARE * available:
        log.warning(f"{label}: {count}: meshing takes ~{_seconds(seconds)} and ~{_bytes(memory)}; "
                    "a solve on it needs much more")
