"""K(theta) = sum_m mu_m A_m + lambda_m B_m: the stiffness as an affine operator.

A_m and B_m are assembled once (each over its region's cells, into the whole mesh's
sparsity pattern) and without boundary conditions; K for any material values and any
set of clamped DOFs is a linear combination plus ``zeroRowsColumns``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from functools import cached_property

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import dolfinx.jit
from dolfinx import fem

from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.model.materials import epsilon, lame, lame_jacobian

# The stiffness kernels are compiled at -O3 and their C may reorder its sums, so the
# loops over quadrature points vectorise: reassociation only, none of -ffast-math's
# flush-to-zero or finite-only assumptions, and no -march=native (a JIT cache shared
# by different machines stays valid). benchmarks/kernel_flags.py measures both ways.
KERNEL_FLAGS = ["-O3", "-fno-math-errno", "-fassociative-math", "-fno-signed-zeros", "-fno-trapping-math"]

SUMS_KEPT = 3  # AffineStiffness.apply: K and the derivatives of two estimated constants
COMPACT_SHARE = 0.5  # AffineStiffness.terms: a region with fewer of the cells keeps its terms compact too


def combine(c, terms):
    """sum_j c_j M_j -- the one home of K(theta) as a linear combination, for the
    assembled PETSc matrices and for their dense projections (surrogate) alike."""
    if isinstance(terms[0], np.ndarray):
        return sum(cj * M for cj, M in zip(c, terms))
    K = terms[0].duplicate(copy=False)
    for cj, M in zip(c, terms):
        K.axpy(cj, M, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
    return K


def stiffness_quadrature(V: fem.FunctionSpace) -> dict:
    """The quadrature of the stiffness forms on curved cells (geometry of degree g > 1;
    straight cells keep UFL's rule, exact there). For P_k elements in d dimensions, a rule
    exact for degree max(2k - 2, (d - 1)(g - 1) + k - 1): the first keeps isoparametric
    elements' optimal convergence (Ciarlet & Raviart 1972), the second integrates
    grad v det J = cof(J)^T grad_ref v exactly, so a constant stress is in equilibrium
    to round-off -- the patch test. 3D P2: degree 3 instead of UFL's 5 for the rational
    integrand, 0.9 s instead of 1.6 s for the phantom's matrices."""
    g, d = V.mesh.geometry.cmaps[0].degree, V.mesh.topology.dim
    if g == 1:
        return {}
    k = V.element.basix_element.degree
    return {"quadrature_degree": max(2 * k - 2, (d - 1) * (g - 1) + k - 1)}


def dolfinx_compile_args() -> list[str]:
    """dolfinx's own default compiler arguments for the kernels it compiles."""
    return list(dolfinx.jit.DOLFINX_DEFAULT_JIT_OPTIONS["cffi_extra_compile_args"][0])


def kernel_options() -> dict:
    """The JIT options of the stiffness forms: dolfinx's compiler arguments followed by
    KERNEL_FLAGS, unless the user chose their own (dolfinx_jit_options.json), which win."""
    ours = dolfinx_compile_args()
    if sys.platform.startswith("win32") or dolfinx.jit.get_options()["cffi_extra_compile_args"] != ours:
        return {}
    return {"cffi_extra_compile_args": ours + KERNEL_FLAGS}


def stiffness_form(scene, V: fem.FunctionSpace, E, nu, jit_options: dict | None = None,
                   regions: Sequence[int] | None = None) -> fem.Form:
    """K's form on V with the materials (E, nu) per region: one matrix at fixed values.
    The Lame values are the form's constants, not literals in it: a literal is part of
    the form's signature, so every new material value compiled the kernels again -- 1.2 s
    of each estimate's degree-3 solve in `make demo` (18 estimates), and of every
    simulation at new materials. ``jit_options``: dolfinx's, ``kernel_options()`` by default;
    ``regions``: the indices of the materials whose cells it spans (all by default)."""
    mu, lam = lame(E, nu, scene.plane)
    return lame_form(scene, V, mu, lam, jit_options, regions)


def lame_form(scene, V: fem.FunctionSpace, mu, lam, jit_options: dict | None = None,
              regions: Sequence[int] | None = None) -> fem.Form:
    """``stiffness_form`` at the Lame values (mu, lambda) per region."""
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    mesh = scene.mesh
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=scene.cell_tags, metadata=stiffness_quadrature(V))
    chosen = range(len(scene.materials)) if regions is None else regions
    return fem.form(sum(fem.Constant(mesh, 2.0 * float(mu[i])) * ufl.inner(epsilon(u), epsilon(v))
                        * dx(scene.materials[i].tag)
                        + fem.Constant(mesh, float(lam[i])) * ufl.div(u) * ufl.div(v) * dx(scene.materials[i].tag)
                        for i in chosen),
                    jit_options=kernel_options() if jit_options is None else jit_options)


def zero_pattern(V: fem.FunctionSpace) -> PETSc.Mat:
    """Explicit zeros on the whole mesh's sparsity pattern of V (a one-point rule: only
    the pattern matters; PETSc would squeeze out entries preallocated but never set)."""
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    zero = fem.Constant(V.mesh, 0.0) * ufl.inner(u, v) * ufl.dx(metadata={"quadrature_degree": 0})
    pattern = dolfinx.fem.petsc.assemble_matrix(fem.form(zero))
    pattern.assemble()
    return pattern


def region_terms(scene, dofs: DofLayout, pattern: PETSc.Mat) -> tuple[list, list]:
    """(A_m, B_m) per material, interleaved, each in a copy of ``pattern`` (the whole
    mesh's), and per term its compact copy for a small region or None
    (AffineStiffness.compact_terms). Each integral runs over its region's cells only
    (the mesh twice in all, not twice per material), so that any K is a same-pattern
    linear combination."""
    mesh, V = scene.mesh, dofs.V
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    metadata = stiffness_quadrature(V)
    total = mesh.topology.index_map(mesh.topology.dim).size_global
    out, compacts = [], []
    for material in scene.materials:
        cells = np.unique(scene.cell_tags.find(material.tag)).astype(np.int32)
        region = dolfinx.mesh.meshtags(mesh, mesh.topology.dim, cells, np.ones(len(cells), np.int32))
        dx = ufl.Measure("dx", domain=mesh, subdomain_data=region, metadata=metadata)(1)
        small = dofs.comm.allreduce(len(cells), op=MPI.SUM) < COMPACT_SHARE * total
        for integrand in (2 * ufl.inner(epsilon(u), epsilon(v)), ufl.div(u) * ufl.div(v)):
            matrix, compact = _in_pattern(fem.form(integrand * dx, jit_options=kernel_options()), pattern, small)
            out.append(matrix)
            compacts.append(compact)
    return out, compacts


def _in_pattern(form, pattern: PETSc.Mat, small: bool) -> tuple[PETSc.Mat, PETSc.Mat | None]:
    """The form's matrix in the whole pattern, and for a small region also on its own
    sparsity (assembled once there; its entries added into the pattern)."""
    M = pattern.duplicate(copy=True)
    if not small:
        dolfinx.fem.petsc.assemble_matrix(M, form)
        M.assemble()
        return M, None
    compact = dolfinx.fem.petsc.assemble_matrix(form)
    compact.assemble()
    M.axpy(1.0, compact, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
    return M, compact


class AffineStiffness:
    """The per-material matrices M_j and their combinations K = sum_j c_j M_j."""

    def __init__(self, dofs: DofLayout, method: str):
        """``method``: the solvers' ("direct" or "iterative"), which decides whether sums
        are kept for products (``apply``)."""
        self.dofs = dofs
        self.scene = dofs.scene
        self.method = method
        self._sums: dict[tuple, PETSc.Mat] = {}  # c -> unconstrained sum_j c_j M_j: apply's latest
        self._pattern: PETSc.Mat | None = None  # the whole mesh's sparsity, until the terms take it over

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
        """(``terms``, ``compact_terms``), assembled on first use (a model that only numbers
        nodes -- landmarks, atlas order -- never pays for them): ``region_terms``."""
        pattern, self._pattern = self._whole_pattern(), None
        try:
            return region_terms(self.scene, self.dofs, pattern)
        finally:
            pattern.destroy()

    def _whole_pattern(self) -> PETSc.Mat:
        """``zero_pattern`` of the space, made once: ``at_once`` and the terms share it."""
        if self._pattern is None:
            self._pattern = zero_pattern(self.dofs.V)
        return self._pattern

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

    def matrix(self, c) -> PETSc.Mat:
        """Unconstrained K = sum_j c_j M_j (a new matrix); on a small region's own sparsity
        where every term with c_j != 0 has a compact copy (its derivative, dK/dE_m)."""
        nonzero = self._compact(c)
        if nonzero is not None:
            return combine(np.asarray(c)[nonzero], [self.compact_terms[j] for j in nonzero])
        return combine(c, self.terms)

    def _compact(self, c) -> np.ndarray | None:
        """The terms with c_j != 0 where each has a compact copy and some c_j are zero (a
        small region's derivative); else None."""
        nonzero = np.flatnonzero(c)
        if len(nonzero) < len(c) and all(self.compact_terms[j] is not None for j in nonzero):
            return nonzero
        return None

    def apply(self, c, x: PETSc.Vec, out: PETSc.Vec) -> PETSc.Vec:
        """out = (sum_j c_j M_j) x -- K(theta) x, or with c = dc/dtheta_k its derivative.
        Where every term with c_j != 0 has a compact copy (a small region's derivative),
        one product per term over its entries alone. Otherwise, with the direct method,
        the sums for the latest SUMS_KEPT c are kept (one product instead of one per term:
        every gradient of a full-space fit needs K and each dK/dtheta_k; the matrices are
        small beside the factors); the iterative method, meant for meshes where memory
        binds, forms no sum and skips zero coefficients."""
        if self._compact(c) is not None:
            return self._apply_terms(c, self.compact_terms, x, out)
        if self.method == "direct":
            key = tuple(np.asarray(c, float))
            K = self._sums.pop(key, None) or self.matrix(c)
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

    def at_once(self, c, clamped: np.ndarray) -> PETSc.Mat:
        """``constrained(c, clamped)`` (to rounding, in the same pattern) assembled in one
        pass over the mesh at the Lame values c, not summed from the terms: a
        factorization started before the terms exist need not wait for them (the
        phantom: 1.1 s against 2.4 s; the terms are then assembled beside it)."""
        if self._terms_assembled:
            return self.constrained(c, clamped)
        mu, lam = np.asarray(c, float).reshape(-1, 2).T  # interleaved as ``coefficients`` gives them
        K = self._whole_pattern().duplicate(copy=True)
        K.setOption(PETSc.Mat.Option.KEEP_NONZERO_PATTERN, True)
        dolfinx.fem.petsc.assemble_matrix(K, lame_form(self.scene, self.dofs.V, mu, lam))
        K.assemble()
        return self._clamp(K, clamped)

    @property
    def _terms_assembled(self) -> bool:
        return "_assembled" in self.__dict__

    def _clamp(self, K: PETSc.Mat, clamped: np.ndarray) -> PETSc.Mat:
        """K with identity rows and columns on the clamped DOFs."""
        start = self.dofs.V.dofmap.index_map.local_range[0] * self.dofs.bs
        K.zeroRowsColumns((clamped + start).astype(PETSc.IntType), diag=1.0)
        return K

    def constrained(self, c, clamped: np.ndarray, out: PETSc.Mat | None = None) -> PETSc.Mat:
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
        return self._clamp(K, clamped)


class FixedStiffness(AffineStiffness):
    """K at one set of materials (E, nu), assembled as one matrix: all a simulation needs.
    The affine terms are what lets an estimate change materials without assembling again,
    at the price of two whole-pattern matrices per region; at 1M DOFs the phantom's four
    took ~0.55 GB each on top of K (docs: performance, memory per rank). Here K is the
    single term, with coefficient 1 at those materials and no other."""

    def __init__(self, dofs: DofLayout, method: str, E, nu):
        super().__init__(dofs, method)
        self.E, self.nu = np.asarray(E, float), np.asarray(nu, float)

    @cached_property
    def _assembled(self) -> tuple[list, list]:
        K = dolfinx.fem.petsc.assemble_matrix(stiffness_form(self.scene, self.dofs.V, self.E, self.nu))
        K.assemble()
        return [K], [None]

    def at_once(self, c, clamped: np.ndarray) -> PETSc.Mat:
        return self.constrained(c, clamped)  # its one term is assembled at once already

    def coefficients(self, E, nu) -> np.ndarray:
        if not (np.allclose(E, self.E, rtol=1e-12) and np.allclose(nu, self.nu, rtol=1e-12)):
            raise ValueError(f"a stiffness fixed at E {self.E}, nu {self.nu} was asked for E {E}, nu {nu}")
        return np.ones(1)

    def coefficient_derivatives(self, E, nu) -> tuple[np.ndarray, np.ndarray]:
        raise TypeError("a stiffness at fixed materials has no derivatives in them: use AffineStiffness")
