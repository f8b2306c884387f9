"""Run under mpiexec: read a .msh (through its parallel copy, or writing it) and save
what the read gave, in numbers that do not depend on the ranks (``mesh_summary``)."""

import json
import sys
from pathlib import Path

import numpy as np
from mpi4py import MPI

import fenics_elasto  # noqa: F401  (dolfinx_solver first)
from fenics_elasto.model.scene import read_msh


def mesh_summary(path: Path, curve: bool, comm=MPI.COMM_WORLD) -> dict:
    """What a read gives, in numbers that do not depend on the ranks or the ordering."""
    mesh, cell_tags, cell_groups, facet_groups, warnings = read_msh(path, comm, curve)
    tdim = mesh.topology.dim
    owned_facets = mesh.topology.index_map(tdim - 1).size_local
    owned_cells = cell_tags.indices < mesh.topology.index_map(tdim).size_local
    owned_nodes = mesh.geometry.x[: mesh.geometry.index_map().size_local]
    return {"cells": mesh.topology.index_map(tdim).size_global, "degree": mesh.geometry.cmaps[0].degree,
            "cell_groups": cell_groups, "warnings": warnings,
            "facets": {name: comm.allreduce(int((f < owned_facets).sum())) for name, f in facet_groups.items()},
            "tag_sum": comm.allreduce(int(cell_tags.values[owned_cells].sum())),
            "moment": float(f"{comm.allreduce(float(np.sum(owned_nodes**2))):.12g}")}


if __name__ == "__main__":
    summary = mesh_summary(Path(sys.argv[1]), curve=True)
    if MPI.COMM_WORLD.rank == 0:
        Path(sys.argv[2]).write_text(json.dumps(summary))
