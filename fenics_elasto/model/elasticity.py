"""Forward model: linear elasticity with cached per-material matrices.

    K(theta) = sum_m mu_m A_m + lambda_m B_m

A_m and B_m are assembled once (with the full sparsity pattern, via a DG0 indicator of
region m) and without boundary conditions; K for any material values and any set of
clamped DOFs is a linear combination plus ``zeroRowsColumns``. The solvers of K
(solvers.py: MUMPS, or CG + AMG for big meshes, as the scene's ``[solver]`` table says)
are cached per (materials, clamped set); a new material value refills a cached solver of
the same clamped set in place, so the sparsity analysis is never paid twice for it.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem

from fenics_elasto.model.scene import Scene
from fenics_elasto.model.solvers import LinearSolver, SolverCache, SolverSettings, SolverStats, rigid_body_modes


# --------------------------------------------------------------------------- materials


def lame(E, nu, plane: str = "strain"):
    """(mu, lambda) from Young's modulus and Poisson's ratio; plane stress uses lambda*."""
    E, nu = np.asarray(E, float), np.asarray(nu, float)
    mu = E / (2 * (1 + nu))
    lam = E * nu / (1 - nu**2) if plane == "stress" else E * nu / ((1 + nu) * (1 - 2 * nu))
    return mu, lam


def lame_jacobian(E, nu, plane: str = "strain"):
    """Partial derivatives (dmu/dE, dmu/dnu, dlam/dE, dlam/dnu)."""
    E, nu = np.asarray(E, float), np.asarray(nu, float)
    dmu_dE = 1 / (2 * (1 + nu))
    dmu_dnu = -E / (2 * (1 + nu) ** 2)
    if plane == "stress":
        dlam_dE = nu / (1 - nu**2)
        dlam_dnu = E * (1 + nu**2) / (1 - nu**2) ** 2
    else:
        dlam_dE = nu / ((1 + nu) * (1 - 2 * nu))
        dlam_dnu = E * (1 + 2 * nu**2) / ((1 + nu) * (1 - 2 * nu)) ** 2
    return dmu_dE, dmu_dnu, dlam_dE, dlam_dnu


def epsilon(u):
    return ufl.sym(ufl.grad(u))


def combine(c, terms):
    """sum_j c_j M_j -- the one home of K(theta) as a linear combination, for the
    assembled PETSc matrices and for their dense projections (surrogate) alike."""
    if isinstance(terms[0], np.ndarray):
        return sum(cj * M for cj, M in zip(c, terms))
    K = terms[0].duplicate(copy=False)
    for cj, M in zip(c, terms):
        K.axpy(cj, M, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
    return K


# --------------------------------------------------------------------------- node sets


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


# --------------------------------------------------------------------------- the model


SUMS_KEPT = 3  # ElasticModel.apply_stiffness: K and the derivatives of two estimated constants
COMPACT_SHARE = 0.5  # ElasticModel.terms: a region with fewer of the cells keeps its terms compact too


def stiffness_quadrature(V: fem.FunctionSpace) -> dict:
    """The quadrature of the stiffness forms on curved cells (geometry of degree g > 1;
    straight cells keep UFL's rule, exact there). For P_k elements in d dimensions, a rule
    exact for degree max(2k - 2, (d - 1)(g - 1) + k - 1): the first keeps isoparametric
    elements' optimal convergence (Ciarlet & Raviart 1972), the second integrates
    grad v det J = cof(J)^T grad_ref v exactly, so a constant stress is in equilibrium
    to round-off -- the patch test. 3D P2: degree 3 instead of UFL's 5 for the rational
    integrand, 0.9 s instead of 1.6 s for the phantom's matrices (README)."""
    g, d = V.mesh.geometry.cmaps[0].degree, V.mesh.topology.dim
    if g == 1:
        return {}
    k = V.element.basix_element.degree
    return {"quadrature_degree": max(2 * k - 2, (d - 1) * (g - 1) + k - 1)}


class ElasticModel:
    """Function space, cached material matrices, K(theta), its solvers and solves."""

    def __init__(self, scene: Scene, solver: SolverSettings | None = None, cache_size: int = 2):
        """``solver``: default from the scene's ``[solver]`` table; ``cache_size``: solvers
        kept (two: alternating material values do not refactor)."""
        self.scene = scene
        mesh = scene.mesh
        self.comm = mesh.comm
        self.gdim = mesh.geometry.dim
        self.V = fem.functionspace(mesh, ("Lagrange", scene.degree, (self.gdim,)))
        self.bs = self.V.dofmap.index_map_bs
        self.n_owned_blocks = self.V.dofmap.index_map.size_local
        self.dof_coords = self.V.tabulate_dof_coordinates()[:, : self.gdim]
        self.settings = solver or SolverSettings.from_config(scene.config.get("solver"))
        self.stats = SolverStats(self.settings.method_for(self.num_dofs))
        self._cache_size = cache_size
        self._sums: dict[tuple, PETSc.Mat] = {}  # c -> unconstrained sum_j c_j M_j: apply_stiffness's latest

    @property
    def method(self) -> str:
        """"direct" or "iterative" (``[solver] method``, "auto" resolved by size)."""
        return self.stats.method

    @property
    def factorizations(self) -> int:
        """Numeric factorizations of K so far (0 with the iterative method)."""
        return self.stats.factorizations

    # --- sizes and DOF sets

    @property
    def num_dofs(self) -> int:
        return self.V.dofmap.index_map.size_global * self.bs

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

    # --- matrices

    @property
    def terms(self) -> list:
        """M_j with K(theta) = sum_j c_j M_j: (A_m, B_m) per material, interleaved."""
        return self._assembled[0]

    @property
    def compact_terms(self) -> list:
        """Per term of ``terms``: for a small region's (under COMPACT_SHARE of the cells) the
        same matrix on its own cells' sparsity, without the whole mesh's pattern; None for
        the others. A small region's E moves only its own entries, and dK/dE x over them
        is ~8x cheaper (the phantom's prostate: 13 % of the pattern, 0.45 instead of 4.5 ms)."""
        return self._assembled[1]

    @cached_property
    def _assembled(self) -> tuple[list, list]:
        """(``terms``, ``compact_terms``).

        A_m = 2 eps(u):eps(v) and B_m = div u div v over region m, assembled on first use
        (a model that only numbers nodes -- landmarks, atlas order -- never pays for them).
        Each is integrated over its region's cells only (the integrals cost the mesh
        twice in all, not twice per material) into a matrix with the whole mesh's
        sparsity pattern, so that any K is a same-pattern linear combination. A small
        region's terms are kept on its own sparsity too (``compact_terms``).
        """
        mesh, V = self.scene.mesh, self.V
        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        # Explicit zeros on the whole pattern (a one-point rule: only the pattern matters);
        # PETSc would squeeze out entries that were preallocated but never set.
        zero = fem.Constant(mesh, 0.0) * ufl.inner(u, v) * ufl.dx(metadata={"quadrature_degree": 0})
        pattern = dolfinx.fem.petsc.assemble_matrix(fem.form(zero))
        pattern.assemble()
        metadata = stiffness_quadrature(self.V)
        total = mesh.topology.index_map(mesh.topology.dim).size_global
        out, compacts = [], []
        for material in self.scene.materials:
            cells = np.unique(self.scene.cell_tags.find(material.tag)).astype(np.int32)
            region = dolfinx.mesh.meshtags(mesh, mesh.topology.dim, cells, np.ones(len(cells), np.int32))
            dx = ufl.Measure("dx", domain=mesh, subdomain_data=region, metadata=metadata)(1)
            small = self.comm.allreduce(len(cells), op=MPI.SUM) < COMPACT_SHARE * total
            for integrand in (2 * ufl.inner(epsilon(u), epsilon(v)), ufl.div(u) * ufl.div(v)):
                form = fem.form(integrand * dx)
                M = pattern.duplicate(copy=True)
                if small:  # assembled once, on the region's sparsity; its entries added into the pattern
                    compact = dolfinx.fem.petsc.assemble_matrix(form)
                    compact.assemble()
                    M.axpy(1.0, compact, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
                else:
                    dolfinx.fem.petsc.assemble_matrix(M, form)
                    M.assemble()
                    compact = None
                out.append(M)
                compacts.append(compact)
        pattern.destroy()
        return out, compacts

    def coefficients(self, E, nu) -> np.ndarray:
        """c_j of ``terms``: (mu_m, lambda_m) of every material, interleaved."""
        mu, lam = lame(E, nu, self.scene.plane)
        return np.stack([mu, lam], axis=1).ravel()

    def coefficient_derivatives(self, E, nu) -> tuple[np.ndarray, np.ndarray]:
        """(dc/dE_m, dc/dnu_m): rows m, columns j of ``terms``."""
        dmu_dE, dmu_dnu, dlam_dE, dlam_dnu = lame_jacobian(E, nu, self.scene.plane)
        n = len(np.atleast_1d(E))
        dE, dnu = np.zeros((n, 2 * n)), np.zeros((n, 2 * n))
        rows = np.arange(n)
        dE[rows, 2 * rows], dE[rows, 2 * rows + 1] = dmu_dE, dlam_dE
        dnu[rows, 2 * rows], dnu[rows, 2 * rows + 1] = dmu_dnu, dlam_dnu
        return dE, dnu

    def stiffness(self, c) -> PETSc.Mat:
        """Unconstrained K = sum_j c_j M_j (a new matrix)."""
        return combine(c, self.terms)

    def apply_stiffness(self, c, x: PETSc.Vec, out: PETSc.Vec) -> PETSc.Vec:
        """out = (sum_j c_j M_j) x -- K(theta) x, or with c = dc/dtheta_k its derivative.
        Where every term with c_j != 0 has a compact copy (a small region's derivative),
        one product per term over its entries alone. Otherwise, with the direct method,
        the sums for the latest SUMS_KEPT c are kept (one product instead of one per term:
        every gradient of a full-space fit needs K and each dK/dtheta_k; the matrices are
        small beside the factors); the iterative method, meant for meshes where memory
        binds, forms no sum and skips zero coefficients."""
        nonzero = np.flatnonzero(c)
        if len(nonzero) < len(c) and all(self.compact_terms[j] is not None for j in nonzero):
            return self._apply_terms(c, self.compact_terms, x, out)
        if self.method == "direct":
            key = tuple(np.asarray(c, float))
            K = self._sums.pop(key, None) or self.stiffness(c)
            self._sums[key] = K  # the latest last
            while len(self._sums) > SUMS_KEPT:
                self._sums.pop(next(iter(self._sums))).destroy()
            K.mult(x, out)
            return out
        return self._apply_terms(c, self.terms, x, out)

    @staticmethod
    def _apply_terms(c, terms, x: PETSc.Vec, out: PETSc.Vec) -> PETSc.Vec:
        """out = sum_j c_j M_j x, one product per term with c_j != 0."""
        out.zeroEntries()
        tmp = out.duplicate()
        for cj, M in zip(c, terms):
            if cj != 0.0:
                M.mult(x, tmp)
                out.axpy(cj, tmp)
        tmp.destroy()
        return out

    def constrained_stiffness(self, c, clamped: np.ndarray, out: PETSc.Mat | None = None) -> PETSc.Mat:
        """K = sum_j c_j M_j with identity rows and columns on the clamped DOFs, into
        ``out`` (same pattern: the values change, the nonzero structure never does)."""
        if out is None:
            K = self.terms[0].duplicate(copy=False)
            K.setOption(PETSc.Mat.Option.KEEP_NONZERO_PATTERN, True)
        else:
            K = out
            K.zeroEntries()
        for cj, M in zip(c, self.terms):
            K.axpy(cj, M, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        start = self.V.dofmap.index_map.local_range[0] * self.bs
        K.zeroRowsColumns((clamped + start).astype(PETSc.IntType), diag=1.0)
        return K

    def factorize(self, c, clamped: np.ndarray) -> LinearSolver:
        """A ready solver of K(c) with the clamped DOFs eliminated (a MUMPS factorization,
        or CG + AMG), cached per (c, clamped set) -- see solvers.SolverCache."""
        return self.solvers.get(c, clamped)

    @cached_property
    def solvers(self) -> SolverCache:
        modes = lambda: rigid_body_modes(self.dof_coords[: self.n_owned_blocks], self.comm)  # noqa: E731
        return SolverCache(self.settings, self.stats, self.constrained_stiffness, modes, self._cache_size)

    # --- vectors and solves

    def function(self, name: str = "u") -> fem.Function:
        u = fem.Function(self.V)
        u.name = name
        return u

    def solve(self, c, clamped: np.ndarray, rhs: PETSc.Vec | None = None, prescribed=None,
              nearby: bool = False) -> fem.Function:
        """u with K u = rhs on free DOFs and u = prescribed (or 0) on the clamped DOFs.

        ``c``: the coefficients of K (``coefficients``); ``prescribed``: a Function holding
        the clamped values (others ignored); ``nearby``: a single solve may borrow the
        factors of a nearby material value (solvers.NearbySolver) instead of factorizing.
        """
        load = self.function("rhs")  # keep the Function alive: its petsc_vec borrows its memory
        b = load.x.petsc_vec
        if rhs is not None:
            rhs.copy(b)
        if prescribed is not None:
            g = prescribed.x.petsc_vec.copy()
            keep = np.zeros(len(g.array), bool)
            keep[clamped] = True
            g.array[~keep] = 0.0  # only the clamped values lift the load
            lift = self.apply_stiffness(c, g, g.duplicate())
            b.axpy(-1.0, lift)
            b.array[clamped] = g.array[clamped]
        else:
            b.array[clamped] = 0.0
        u = self.function()
        with self.solver(c, clamped, nearby) as factor:
            factor.solve(b, u.x.petsc_vec)
        u.x.scatter_forward()
        return u

    @contextmanager
    def solver(self, c, clamped: np.ndarray, nearby: bool = False, rtol: float | None = None):
        """A solver of K(c) for the solves in the ``with`` block: the cached factorization
        (``factorize``), or with ``nearby`` one borrowing the factors of a nearby material
        value (solvers.NearbySolver, to ``rtol`` if given), destroyed after the block -- its
        own K and KSP; the factors stay with their solver."""
        borrowed = self.solvers.nearby(c, clamped, rtol) if nearby else None
        try:
            yield borrowed or self.factorize(c, clamped)
        finally:
            if borrowed is not None:
                borrowed.destroy()

    def dense(self, columns: int) -> PETSc.Mat:
        """A dense matrix with V's row layout (owned DOFs) and ``columns`` columns, zeroed."""
        n_local = self.n_owned_blocks * self.bs
        M = PETSc.Mat().createDense(((n_local, PETSc.DETERMINE), (PETSc.DECIDE, columns)), comm=self.comm)
        M.setUp()
        M.zeroEntries()
        M.assemble()
        return M

    def multiply(self, M: PETSc.Mat, Y: np.ndarray) -> np.ndarray:
        """M Y for owned-row columns Y (numpy), as numpy."""
        D = self.dense(Y.shape[1])
        D.getDenseArray()[:] = Y
        P = M.matMult(D)
        out = P.getDenseArray().copy()
        P.destroy()
        D.destroy()
        return out

    def boundary_load(self, tractions: dict, pressures: dict | None = None) -> PETSc.Vec:
        """Load vector of uniform tractions {group: vector} and pressures {group: p} on
        exterior facet groups; a pressure p pushes the wall into the body, t = -p n."""
        mesh = self.scene.mesh
        fdim = mesh.topology.dim - 1
        pressures = pressures or {}
        groups = list(tractions) + list(pressures)
        facets = [self.scene.facet_groups[g] for g in groups]
        values = [np.full(len(f), i + 1, np.int32) for i, f in enumerate(facets)]
        facets, values = np.concatenate(facets), np.concatenate(values)
        order = np.argsort(facets, kind="stable")
        tags = dolfinx.mesh.meshtags(mesh, fdim, facets[order], values[order])
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
        v, n = ufl.TestFunction(self.V), ufl.FacetNormal(mesh)
        loads = [fem.Constant(mesh, np.asarray(t, float)) for t in tractions.values()]
        loads += [-fem.Constant(mesh, float(p)) * n for p in pressures.values()]
        return self.assemble_load(sum(ufl.inner(t, v) * ds(i + 1) for i, t in enumerate(loads)))

    def assemble_load(self, linear_form) -> PETSc.Vec:
        """Load vector of a UFL linear form in V (ghost contributions summed)."""
        b = dolfinx.fem.petsc.assemble_vector(fem.form(linear_form))
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return b

    def group_measure(self, group: str) -> float:
        """Length (2D) or area (3D) of a facet group."""
        mesh = self.scene.mesh
        facets = self.scene.facet_groups[group]
        tags = dolfinx.mesh.meshtags(mesh, mesh.topology.dim - 1, np.sort(facets), np.ones(len(facets), np.int32))
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
        one = fem.Constant(mesh, 1.0)
        return self.comm.allreduce(fem.assemble_scalar(fem.form(one * ds(1))), op=MPI.SUM)
