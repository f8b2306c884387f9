"""A scene mesh's parallel copy: the .msh as DOLFINx made it, kept beside it in XDMF.

A gmsh file is read by rank 0 and scattered from there (``dolfinx.io.gmsh``), so that
one rank holds the whole mesh, and gmsh's model of it besides: ~5 GB at a million
DOFs, ~50 GB at ten million. XDMF (HDF5) is read in parallel, each rank a slice. So
the first load of a .msh writes what it made -- the mesh (curved, if it was curved on
load), its cell tags, every facet group as a tag set of its own (groups may overlap),
their names -- into ``<stem>.dolfinx/`` beside it; every later load reads that on all
ranks at once, without gmsh, checks or curving.

The copy is keyed by the .msh's size and modification time and by the curving
setting, so an edited .msh or another ``curve`` makes a new one. It is written into a
temporary folder and renamed into place: a process stopped half-way, or another one
loading the same scene, never sees half a copy. A folder that cannot be written to (an
installed package's meshes) gets no copy; its scenes are read from the .msh each time.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from mpi4py import MPI

import dolfinx
from dolfinx.io import XDMFFile

from fenics_elasto.util.logs import log

FORMAT = 2  # raised when what the copy holds changes (2: the warnings of a mesh kept straight)
INFO = "copy.json"  # written last: a folder without it is no copy


def folder_of(msh: Path) -> Path:
    return msh.with_name(msh.stem + ".dolfinx")


def _key(msh: Path, curve: bool) -> dict:
    stat = msh.stat()
    return {"format": FORMAT, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "curve": bool(curve)}


def _current_info(msh: Path, curve: bool) -> dict | None:
    """The copy's info if it is a copy of this .msh with this curving, else None."""
    try:
        info = json.loads((folder_of(msh) / INFO).read_text())
        return info if info.get("key") == _key(msh, curve) else None
    except (OSError, ValueError):
        return None


def read_copy(msh: Path, curve: bool, comm=MPI.COMM_WORLD, announce: bool = True):
    """(mesh, cell_tags, cell groups, facet groups, warnings) from the current copy of
    ``msh``, read in parallel; None when there is none. ``announce``: log the copy's
    note (the curving's line), which a first read has just logged itself."""
    info = comm.bcast(_current_info(msh, curve) if comm.rank == 0 else None, root=0)
    if info is None:
        return None
    with XDMFFile(comm, str(folder_of(msh) / "mesh.xdmf"), "r") as file:
        mesh = file.read_mesh(name="mesh")
        fdim = mesh.topology.dim - 1
        mesh.topology.create_entities(fdim)
        mesh.topology.create_connectivity(fdim, fdim + 1)
        cell_tags = file.read_meshtags(mesh, "cells")
        facet_groups = {name: np.asarray(file.read_meshtags(mesh, f"facets_{i}").indices, dtype=np.int32)
                        for i, name in enumerate(info["facet_groups"])}
    if info["note"] and announce:
        log.info(f"{info['note']} (read from its parallel copy {folder_of(msh).name}/)")
    return mesh, cell_tags, info["cell_groups"], facet_groups, info["warnings"]


def write_copy(msh: Path, curve: bool, loaded: tuple, note: str | None, comm=MPI.COMM_WORLD) -> None:
    """Keep ``loaded`` = (mesh, cell_tags, cell groups, facet groups, warnings), just made
    from ``msh``, as its parallel copy; nothing when its folder cannot be written to."""
    mesh, cell_tags, cell_groups, facet_groups, warnings = loaded
    temp = comm.bcast(_temporary_folder(msh) if comm.rank == 0 else None, root=0)
    if temp is None:
        return
    try:
        _write_tags(Path(temp) / "mesh.xdmf", mesh, cell_tags, facet_groups)
    except RuntimeError as err:  # HDF5's errors (a full disk) are collective
        if comm.rank == 0:
            shutil.rmtree(temp, ignore_errors=True)
        log.info(f"note: {msh.name}: no parallel copy written ({err})")
        return
    if comm.rank == 0:
        info = {"key": _key(msh, curve), "cell_groups": cell_groups, "facet_groups": sorted(facet_groups),
                "warnings": warnings, "note": note}
        (Path(temp) / INFO).write_text(json.dumps(info, indent=1))
        _move_into_place(Path(temp), msh, curve)
    comm.barrier()


def _temporary_folder(msh: Path) -> str | None:
    try:
        return tempfile.mkdtemp(prefix=f".{msh.stem}.dolfinx.", dir=msh.parent)
    except OSError:
        return None


def _write_tags(path: Path, mesh, cell_tags, facet_groups: dict) -> None:
    tdim = mesh.topology.dim
    with XDMFFile(mesh.comm, str(path), "w") as file:
        file.write_mesh(mesh)
        cells = dolfinx.mesh.meshtags(mesh, tdim, cell_tags.indices, cell_tags.values)
        cells.name = "cells"
        file.write_meshtags(cells, mesh.geometry)
        for i, name in enumerate(sorted(facet_groups)):
            facets = np.unique(facet_groups[name]).astype(np.int32)
            tags = dolfinx.mesh.meshtags(mesh, tdim - 1, facets, np.ones(len(facets), np.int32))
            tags.name = f"facets_{i}"
            file.write_meshtags(tags, mesh.geometry)


def _move_into_place(temp: Path, msh: Path, curve: bool) -> None:
    """Rename the finished copy into place, replacing a stale one; if another process
    has just put a current copy there, keep that one (the rename then fails)."""
    folder = folder_of(msh)
    if folder.exists() and _current_info(msh, curve) is None:
        shutil.rmtree(folder, ignore_errors=True)
    try:
        os.rename(temp, folder)
    except OSError:
        shutil.rmtree(temp, ignore_errors=True)
