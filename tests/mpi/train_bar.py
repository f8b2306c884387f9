"""Run under mpiexec: train bases on a bar whose loaded end lies on one rank, and save
what training gave (its explained variance) and on how many ranks the loaded end lies."""

import json
import sys

import numpy as np
from mpi4py import MPI

import fenics_elasto as fe
import dolfinx

comm = MPI.COMM_WORLD
mesh = dolfinx.mesh.create_box(comm, [[0.0, 0.0, 0.0], [6.0, 1.0, 1.0]], [24, 4, 4])
tdim = mesh.topology.dim
mesh.topology.create_connectivity(tdim - 1, tdim)
facets = dolfinx.mesh.locate_entities_boundary(mesh, tdim - 1, lambda x: np.full(x.shape[1], True))
middle = dolfinx.mesh.compute_midpoints(mesh, tdim - 1, facets)
facet_values = np.where(middle[:, 0] < 1e-9, 1, np.where(middle[:, 0] > 6.0 - 1e-9, 2, 3)).astype(np.int32)
cells = np.arange(mesh.topology.index_map(tdim).size_local + mesh.topology.index_map(tdim).num_ghosts, dtype=np.int32)
cell_values = np.where(dolfinx.mesh.compute_midpoints(mesh, tdim, cells)[:, 0] < 3.0, 1, 2).astype(np.int32)
scene = fe.Scene.from_mesh(
    mesh, dolfinx.mesh.meshtags(mesh, tdim, cells, cell_values),
    dolfinx.mesh.meshtags(mesh, tdim - 1, facets, facet_values),
    regions={"a": 1, "b": 2}, groups={"clamped": 1, "loaded": 2, "sides": 3},
    materials={"a": {"E": 1.0, "nu": 0.3}, "b": {"E": {"estimate": True, "initial": 2.0, "bounds": [0.2, 20.0]}, "nu": 0.3}},
    boundary={"fixed": ["clamped"], "loaded": ["loaded"], "matched": ["loaded", "sides"]})
bases = fe.train(scene, synthetic=12, rank=4)
owned = facets[facet_values == 2] < mesh.topology.index_map(tdim - 1).size_local
holding = comm.allreduce(int(owned.any()))
if comm.rank == 0:
    with open(sys.argv[1], "w") as out:
        json.dump({"variance": np.asarray(bases.variance).tolist(), "ranks_holding_the_end": holding,
                   "W": np.asarray(bases.W).tolist(), "coords": np.asarray(bases.loaded_coords).tolist()}, out)
