"""The body moved by its loaded boundary: fields from nodal forces or boundary motion.

    K(theta) u = P F                      (forces F on the loaded nodes; fixed nodes clamped)
    u = d on the loaded nodes, K_D u = 0  (the loaded boundary's displacement d)

Both describe the same fields: d and F are in bijection at fixed materials (F = P^T K u),
and d is F preconditioned by the boundary's Dirichlet-to-Neumann map, the better-
conditioned control. The response X(theta) of boundary modes W (d = W q) is the field
of each mode, one block solve through one factorization: the matched displacement is
then exactly linear in q. Loaded quantities are flat vectors over the loaded nodes in
canonical order (elasticity.NodeSet), the same under any number of MPI ranks.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from dolfinx import fem

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.util.errors import require
from fenics_elasto.model.scene import Scene


class BoundaryForward:
    """Forward, adjoint and response solves of a scene whose loaded boundary is unknown."""

    def __init__(self, scene: Scene, model: ElasticModel | None = None):
        require(scene.loaded, f"{scene.path}: boundary.loaded is empty: the unknown forces need a loaded boundary")
        require(scene.fixed, f"{scene.path}: boundary.fixed is empty: clamp at least one group (else the body moves freely)")
        self.scene = scene
        self.model = model or ElasticModel(scene)
        self.params = scene.parameters()
        self.gdim = scene.gdim
        self.clamped = self.model.dofs.clamped_dofs(scene.fixed)
        self.clamped_boundary = self.model.dofs.clamped_dofs(scene.fixed + scene.loaded)
        self.loaded = self.model.dofs.node_set(scene.loaded, exclude_groups=scene.fixed)
        self.forward_solves = 0
        self.adjoint_solves = 0
        self._borrow = False  # inside ``borrowing()``

    @contextmanager
    def borrowing(self):
        """Solves in the block at a material value near one already factorized borrow its
        factors (solvers.NearbySolver) instead of factorizing: an estimate whose surrogate
        stands in for the block solves holds it after its first solve (Profile.borrowing)."""
        before, self._borrow = self._borrow, True
        try:
            yield
        finally:
            self._borrow = before

    @property
    def borrows(self) -> bool:
        """Inside ``borrowing()``."""
        return self._borrow

    @property
    def force_dofs(self) -> int:
        return self.loaded.total * self.gdim

    def coefficients(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(c, dc/dtheta): K(theta) = sum_j c_j M_j, and each estimated constant's derivative row."""
        E, nu = self.params.materials(theta)
        return self.model.stiffness.coefficients(E, nu), self.params.select(*self.model.stiffness.coefficient_derivatives(E, nu))

    # --- loaded-node data <-> fields

    def load(self, values: np.ndarray, nodes=None) -> fem.Function:
        """A Function holding per-node rows (canonical order) on ``nodes`` (default: loaded)."""
        nodes = nodes or self.loaded
        f = self.model.dofs.function("load")
        f.x.array.reshape(-1, self.model.dofs.bs)[nodes.blocks] = nodes.local(np.reshape(values, (-1, self.gdim)))
        return f

    def on_loaded(self, f: fem.Function) -> np.ndarray:
        """Rows of a Function at the loaded nodes, canonical order, flat."""
        return self.loaded.gather(f.x.array.reshape(-1, self.model.dofs.bs)[self.loaded.blocks]).ravel()

    # --- solves

    def from_forces(self, theta, forces: np.ndarray) -> fem.Function:
        self.forward_solves += 1
        f = self.load(forces)  # kept alive: its petsc_vec borrows its memory
        return self.model.solve(self.coefficients(theta)[0], self.clamped, f.x.petsc_vec, nearby=self._borrow)

    def from_boundary(self, theta, d: np.ndarray) -> fem.Function:
        self.forward_solves += 1
        return self.model.solve(self.coefficients(theta)[0], self.clamped_boundary, None, prescribed=self.load(d),
                                nearby=self._borrow)

    def adjoint(self, theta, load: fem.Function, boundary: bool) -> fem.Function:
        """w with K w = load (w = 0 on the fixed nodes, and on the loaded ones if ``boundary``)."""
        self.adjoint_solves += 1
        clamped = self.clamped_boundary if boundary else self.clamped
        return self.model.solve(self.coefficients(theta)[0], clamped, load.x.petsc_vec, nearby=self._borrow)

    def reaction_forces(self, theta, u: fem.Function) -> np.ndarray:
        """F = P^T K(theta) u: the loaded-node forces that produce u."""
        Ku = self.model.dofs.function("Ku")
        self.model.stiffness.apply(self.coefficients(theta)[0], u.x.petsc_vec, Ku.x.petsc_vec)
        return self.on_loaded(Ku)

    def material_gradient(self, theta, u: fem.Function, w: fem.Function) -> np.ndarray:
        """-w^T dK/dtheta_k u for each estimated constant."""
        dKu = self.model.dofs.function("dKu")
        return -np.array([w.x.petsc_vec.dot(self.model.stiffness.apply(row, u.x.petsc_vec, dKu.x.petsc_vec))
                          for row in self.coefficients(theta)[1]])

    def field_derivative(self, theta, u: fem.Function) -> np.ndarray:
        """(owned DOFs, n_theta) du/dtheta_k at fixed boundary motion: K_D du = -dK/dtheta_k u
        on the free DOFs, du = 0 on the loaded and fixed ones (one back-solve each)."""
        c, dc = self.coefficients(theta)
        columns = []
        with self.model.solver(c, self.clamped_boundary, self._borrow) as factor:
            for row in dc:
                rhs = self.model.dofs.function("rhs")
                self.model.stiffness.apply(row, u.x.petsc_vec, rhs.x.petsc_vec)
                rhs.x.petsc_vec.scale(-1.0)
                rhs.x.petsc_vec.array[self.clamped_boundary] = 0.0
                du = self.model.dofs.function("du")
                factor.solve(rhs.x.petsc_vec, du.x.petsc_vec)
                columns.append(du.x.petsc_vec.array.copy())
        self.forward_solves += len(columns)
        return np.stack(columns, axis=1) if columns else np.zeros((len(u.x.petsc_vec.array), 0))
