"""The forward model's facade: a scene's DOF layout, its affine stiffness, and the solvers
of K(theta) with the solves they make.

The solvers (solvers.py: MUMPS, or CG + AMG for big meshes, as the scene's ``[solver]``
table says) are cached per (materials, clamped set); a new material value refills a
cached solver of the same clamped set in place, so the sparsity analysis is never paid
twice for it.
"""

from __future__ import annotations

from contextlib import contextmanager
from functools import cached_property

import numpy as np
from petsc4py import PETSc

from dolfinx import fem

from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.model.scene import Scene
from fenics_elasto.model.solvers import LinearSolver, SolverCache, SolverSettings, SolverStats, rigid_body_modes
from fenics_elasto.model.stiffness import AffineStiffness, FixedStiffness


class ElasticModel:
    """A scene's space (``dofs``), K(theta) (``stiffness``), and the cached solvers of K."""

    def __init__(self, scene: Scene, solver: SolverSettings | None = None, cache_size: int = 2,
                 fixed: tuple | None = None):
        """``solver``: default from the scene's ``[solver]`` table; ``cache_size``: solvers
        kept (two: alternating material values do not refactor); ``fixed``: (E, nu) per
        region for a model that is only ever solved at those values (a simulation): K
        then is one matrix, not an affine sum (stiffness.FixedStiffness)."""
        self.scene = scene
        self.dofs = DofLayout(scene)
        self.settings = solver or SolverSettings.from_config(scene.config.get("solver"))
        self.stats = SolverStats(self.settings.method_for(self.dofs.num_dofs))
        self.stiffness = (AffineStiffness(self.dofs, self.stats.method) if fixed is None
                          else FixedStiffness(self.dofs, self.stats.method, *fixed))
        self._cache_size = cache_size

    @property
    def method(self) -> str:
        """"direct" or "iterative" (``[solver] method``, "auto" resolved by size)."""
        return self.stats.method

    @property
    def factorizations(self) -> int:
        """Numeric factorizations of K so far (0 with the iterative method)."""
        return self.stats.factorizations

    @cached_property
    def solvers(self) -> SolverCache:
        dofs = self.dofs
        modes = lambda: rigid_body_modes(dofs.dof_coords[: dofs.n_owned_blocks], dofs.comm)  # noqa: E731
        return SolverCache(self.settings, self.stats, self.stiffness.constrained, modes, self._cache_size,
                           self.stiffness.at_once, few_solves=isinstance(self.stiffness, FixedStiffness))

    def factorize(self, c, clamped: np.ndarray) -> LinearSolver:
        """A ready solver of K(c) with the clamped DOFs eliminated (a MUMPS factorization,
        or CG + AMG), cached per (c, clamped set) -- see solvers.SolverCache."""
        return self.solvers.get(c, clamped)

    def factorize_ahead(self, c, clamped: np.ndarray) -> None:
        """Start ``factorize(c, clamped)``'s factorization now, beside the caller's next
        work (serial, direct: solvers.SolverCache.ahead); its first solve waits for it."""
        self.solvers.ahead(c, clamped)

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

    def solve(self, c, clamped: np.ndarray, rhs: PETSc.Vec | None = None, prescribed=None,
              nearby: bool = False) -> fem.Function:
        """u with K u = rhs on free DOFs and u = prescribed (or 0) on the clamped DOFs.

        ``c``: the coefficients of K (``stiffness.coefficients``); ``prescribed``: a
        Function holding the clamped values (others ignored); ``nearby``: see ``solver``.
        """
        load = self.dofs.function("rhs")  # keep the Function alive: its petsc_vec borrows its memory
        b = load.x.petsc_vec
        if rhs is not None:
            rhs.copy(b)
        if prescribed is not None:  # only the clamped values lift the load
            g = prescribed.x.petsc_vec.copy()
            keep = np.zeros(len(g.array), bool)
            keep[clamped] = True
            g.array[~keep] = 0.0
            b.axpy(-1.0, self.stiffness.apply(c, g, g.duplicate()))
            b.array[clamped] = g.array[clamped]
        else:
            b.array[clamped] = 0.0
        u = self.dofs.function()
        with self.solver(c, clamped, nearby) as factor:
            factor.solve(b, u.x.petsc_vec)
        u.x.scatter_forward()
        return u
