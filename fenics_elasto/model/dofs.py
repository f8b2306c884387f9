"""The displacement space and its nodes: sizes, boundary node sets numbered across ranks,
clamped DOFs, and dense blocks in the space's row layout."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
from scipy.sparse import csr_matrix

from dolfinx import fem

from fenics_elasto.model.scene import Scene
from fenics_elasto.util.threads import threads_per_rank


# times_block through PETSc: columns per sparse-dense product. The whole block at once
# (the surrogate's first space at rank 240 on the default phantom: ~700 columns of 116k
# rows, 0.65 GB) made PETSc hold two more copies of it: the start's peak 9.3 GB -> 8.0 GB
# in slices, E the same to the bit.
MULTIPLY_COLUMNS = 64
# times_block through scipy from this many columns: below, copying M into scipy's CSR
# arrays costs more than it saves (the mesh part's degree-3 matrix, 54M entries, times
# one column: 2.9 s through scipy, mostly faulting in the copy, against 0.04 s).
SCIPY_COLUMNS = 8
SLAB_ROWS = 8192  # ... in slabs of this many rows, one per thread at a time


def times_block(M: PETSc.Mat, Y: np.ndarray) -> np.ndarray:
    """M Y for columns Y on this rank's rows of M's column layout (numpy), as numpy on
    M's owned rows, in Y's memory order. A wide row-major block on one rank goes through
    scipy's CSR product, which reads M once for all the columns; PETSc's sparse-dense
    product reads M once per column (the phantom's K, 116k DOFs and 9.6M entries, times
    241 columns: 0.6 s against 1.9 s). Column-major blocks (PETSc's own dense arrays,
    which scipy would first transpose: 1.4 s for 81 columns), narrow ones and every
    block across ranks go through PETSc, MULTIPLY_COLUMNS at a time."""
    (rows, columns), comm = M.getLocalSize(), M.getComm()
    if comm.getSize() == 1 and Y.flags.c_contiguous and Y.shape[1] >= SCIPY_COLUMNS:
        return _csr_times(M.getValuesCSR(), columns, Y)
    out = np.empty((rows, Y.shape[1]), order="F" if Y.flags.f_contiguous else "C")
    for start in range(0, Y.shape[1], MULTIPLY_COLUMNS):
        part = slice(start, min(start + MULTIPLY_COLUMNS, Y.shape[1]))
        D = PETSc.Mat().createDense(((columns, PETSc.DETERMINE), (PETSc.DECIDE, part.stop - part.start)), comm=comm)
        D.setUp()
        D.getDenseArray()[:] = Y[:, part]
        D.assemble()
        P = M.matMult(D)
        out[:, part] = P.getDenseArray()
        P.destroy()
        D.destroy()
    return out


def _csr_times(csr, columns: int, Y: np.ndarray) -> np.ndarray:
    """A CSR matrix (indptr, indices, values) times Y, SLAB_ROWS rows at a time on
    threads_per_rank threads: scipy's product lets go of the GIL, so the slabs run at
    once (the phantom's K times 241 columns: 0.83 s on one core, 0.40 s on two), and
    each slab's product is the only copy made besides the answer."""
    indptr, indices, values = csr
    rows = len(indptr) - 1
    out = np.empty((rows, Y.shape[1]))

    def slab(start: int) -> None:
        stop = min(start + SLAB_ROWS, rows)
        first, last = indptr[start], indptr[stop]
        part = csr_matrix((values[first:last], indices[first:last], indptr[start:stop + 1] - first),
                          shape=(stop - start, columns))
        out[start:stop] = part @ Y

    list(_pool(threads_per_rank()).map(slab, range(0, rows, SLAB_ROWS)))
    return out


@cache
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix="times_block")


os.register_at_fork(after_in_child=_pool.cache_clear)  # a forked child has none of the pool's threads


def unrolled(blocks: np.ndarray, bs: int) -> np.ndarray:
    """(n, bs) unrolled DOF indices of blocks (nodes) of a vector space."""
    return blocks[:, None] * bs + np.arange(bs)


@dataclass
class NodeSet:
    """Owned nodes (blocks of the vector space) of a boundary, numbered across ranks.

    The global numbering is canonical -- nodes sorted by position -- so forces, bases
    and landmarks mean the same under any number of MPI ranks. ``gather`` brings
    per-node rows of every rank into that order; ``local`` picks this rank's rows.
    """

    blocks: np.ndarray  # local block indices, owned only
    coords: np.ndarray  # (n, gdim) reference positions
    order: np.ndarray  # canonical position -> position in rank-concatenated order
    positions: np.ndarray  # this rank's nodes' canonical positions
    comm: MPI.Comm

    @classmethod
    def create(cls, blocks, coords, comm) -> NodeSet:
        stacked = np.concatenate(comm.allgather(coords))
        order = np.lexsort(np.round(stacked, 10).T[::-1]) if len(stacked) else np.zeros(0, int)
        inverse = np.empty_like(order)
        inverse[order] = np.arange(len(order))
        offset = comm.exscan(len(blocks)) or 0
        return cls(blocks, coords, order, inverse[offset : offset + len(blocks)], comm)

    @property
    def total(self) -> int:
        return len(self.order)

    def __len__(self) -> int:
        return len(self.blocks)

    def dofs(self, bs: int) -> np.ndarray:
        """(n, bs) local unrolled DOF indices."""
        return unrolled(self.blocks, bs)

    def gather(self, values: np.ndarray) -> np.ndarray:
        """Per-node rows of every rank, in canonical order, on every rank."""
        return np.concatenate(self.comm.allgather(np.ascontiguousarray(values)))[self.order]

    def local(self, values: np.ndarray) -> np.ndarray:
        """This rank's rows of a canonical per-node array."""
        return values[self.positions]


class DofLayout:
    """The vector Lagrange space V of a scene and where its nodes are."""

    def __init__(self, scene: Scene):
        self.scene = scene
        mesh = scene.mesh
        self.comm = mesh.comm
        self.gdim = mesh.geometry.dim
        self.V = fem.functionspace(mesh, ("Lagrange", scene.degree, (self.gdim,)))
        self.bs = self.V.dofmap.index_map_bs
        self.n_owned_blocks = self.V.dofmap.index_map.size_local
        self.dof_coords = self.V.tabulate_dof_coordinates()[:, : self.gdim]

    @property
    def num_dofs(self) -> int:
        return self.V.dofmap.index_map.size_global * self.bs

    @property
    def owned(self) -> int:
        """Owned unrolled DOFs on this rank."""
        return self.n_owned_blocks * self.bs

    def boundary_blocks(self, groups, vertices_only: bool = False) -> np.ndarray:
        """Owned local block indices of the nodes on the named facet groups.

        For P2 these include the edge midpoints, unless ``vertices_only``.
        """
        facets = self.scene.facets(groups)
        mesh = self.scene.mesh
        fdim = mesh.topology.dim - 1
        if vertices_only:
            mesh.topology.create_connectivity(fdim, 0)
            mesh.topology.create_connectivity(0, mesh.topology.dim)
            vertices = np.unique(mesh.topology.connectivity(fdim, 0).array.reshape(-1, fdim + 1)[facets])
            blocks = fem.locate_dofs_topological(self.V, 0, vertices.astype(np.int32))
        else:
            blocks = fem.locate_dofs_topological(self.V, fdim, facets)
        return np.sort(blocks[blocks < self.n_owned_blocks]).astype(np.int32)

    def node_set(self, groups, exclude_groups=(), vertices_only: bool = False) -> NodeSet:
        blocks = self.boundary_blocks(groups, vertices_only)
        if exclude_groups:
            blocks = np.setdiff1d(blocks, self.boundary_blocks(exclude_groups)).astype(np.int32)
        return NodeSet.create(blocks, self.dof_coords[blocks], self.comm)

    def clamped_dofs(self, groups) -> np.ndarray:
        """Owned local unrolled DOFs of the nodes on the groups."""
        return unrolled(self.boundary_blocks(groups), self.bs).ravel()

    def function(self, name: str = "u") -> fem.Function:
        u = fem.Function(self.V)
        u.name = name
        return u

    def dense(self, columns: int) -> PETSc.Mat:
        """A dense matrix with V's row layout (owned DOFs) and ``columns`` columns, zeroed."""
        M = PETSc.Mat().createDense(((self.owned, PETSc.DETERMINE), (PETSc.DECIDE, columns)), comm=self.comm)
        M.setUp()
        M.zeroEntries()
        M.assemble()
        return M
