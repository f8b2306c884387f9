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
from petsc4py import PETSc

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

    def response_sensitivities(self, theta, X: np.ndarray, order: int = 2) -> list[np.ndarray]:
        """Derivatives of the mode fields X(theta) (response_block) along the estimated
        constants, on the factorization X was solved with (block back-solves only):

            K dX_k  = -D_k X                    (D_k = dK/dtheta_k)
            K dX_kl = -(D_k dX_l + D_l dX_k)     (order 2, k <= l)

        on the free DOFs, zero on the loaded and fixed ones (the boundary modes do not
        depend on the materials). The second order leaves out d2K/dtheta2 -- exact along
        E, whose coefficients are linear in it; for nu it only shapes the space the
        surrogate searches (surrogate.py), which stays exact at every full solve."""
        c, dc = self.coefficients(theta)
        factor = self.model.factorize(c, self.clamped_boundary)
        D = [self.model.stiffness.matrix(row) for row in dc]

        def solve(*products) -> np.ndarray:  # -K^{-1} sum D Y, with the Dirichlet rows zero
            block = self.model.dofs.dense(X.shape[1])
            rhs = block.getDenseArray()
            for M, Y in products:
                rhs -= self.model.dofs.multiply(M, Y)
            rhs[self.clamped_boundary] = 0.0
            out = self.model.dofs.dense(X.shape[1])
            factor.solve_many(block, out)
            values = out.getDenseArray().copy()
            block.destroy()
            out.destroy()
            return values

        first = [solve((Dk, X)) for Dk in D]
        second = [solve((D[k], first[j]), (D[j], first[k]))
                  for k in range(len(D)) for j in range(k, len(D))] if order >= 2 else []
        for M in D:
            M.destroy()
        self.forward_solves += (len(first) + len(second)) * X.shape[1]
        return first + second

    def lift(self, basis: np.ndarray | None = None) -> PETSc.Mat:
        """The boundary modes as fields: W on the loaded DOFs, zero elsewhere (dense, owned rows)."""
        W = np.eye(self.force_dofs) if basis is None else basis
        r = W.shape[1]
        G = self.model.dofs.dense(r)
        rows = self.loaded.dofs(self.model.dofs.bs).ravel()
        G.getDenseArray()[rows] = self.loaded.local(W.reshape(self.loaded.total, self.gdim * r)).reshape(-1, r)
        return G

    def response_block(self, theta, basis: np.ndarray | None = None, rtol: float | None = None) -> np.ndarray:
        """X (owned DOFs, r): the field of each boundary mode (W: force_dofs x r; None: all).

        The r right-hand sides [-K W on free rows, W on the loaded rows] go through the
        one factorization of K_D as a dense block (MatMatSolve). Inside ``borrowing()`` a single
        mode (reduction.missing_wall_motion's) is a single solve on nearby factors, to
        ``rtol`` if given (a diagnostic needs fewer CG steps); a block pays a factorization
        (CG would take each column alone).
        """
        c = self.coefficients(theta)[0]
        G = self.lift(basis)
        K = self.model.stiffness.matrix(c)
        rhs = K.matMult(G)
        block = rhs.getDenseArray()
        block *= -1.0
        block[self.clamped_boundary] = G.getDenseArray()[self.clamped_boundary]
        X = self.model.dofs.dense(G.getSize()[1])
        with self.model.solver(c, self.clamped_boundary, self._borrow and G.getSize()[1] == 1, rtol) as factor:
            factor.solve_many(rhs, X)
        out = X.getDenseArray().copy()
        for M in (G, K, rhs, X):
            M.destroy()
        return out
