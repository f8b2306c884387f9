"""The reduced-basis response in the materials: J(theta) for every theta from a few solves.

With reduced force bases the matched displacement is J(theta) q, and J(theta) costs a
factorization of K(theta) -- the dominant cost of an estimate. But the mode fields X(theta)
(one per boundary mode) vary smoothly with the materials, and K(theta) = sum_j c_j(theta) M_j
is affine in the Lame coefficients. So (the reduced-basis method for parametrised PDEs):

    X(theta) ~ G + V a(theta),   (V^T K(theta) V) a = -V^T K(theta) G,

with G the boundary modes (W on the loaded DOFs) and V an orthonormal basis of the interior
parts X(theta_i) - G of the solves done so far ("snapshots"). All products V^T M_j V and
V^T M_j G are kept, so J(theta) and dJ/dtheta are small dense algebra, exact at every
snapshot (Galerkin reproduces a solution that lies in the space). The residual
K(theta)(G + V a) on the free DOFs says how far from exact it is elsewhere. Memory:
V and M_j V, (1 + 2 x materials) x DOFs x (r x snapshots) numbers.
"""

from __future__ import annotations

import numpy as np
from mpi4py import MPI

from fenics_elasto.elasticity import combine
from fenics_elasto.objective import InverseProblem


class MaterialSurrogate:
    """J(theta), dJ/dtheta and the equation residual from the snapshots added so far."""

    def __init__(self, problem: InverseProblem, basis: np.ndarray):
        self.problem = problem
        self.comm = problem.scene.comm
        self.forward = problem.forward
        self.terms = problem.model.terms
        lift = self.forward.lift(basis)
        self.G = lift.getDenseArray().copy()
        self.MG = [problem.model.multiply(M, self.G) for M in self.terms]
        lift.destroy()
        self.free = np.ones(len(self.G), bool)
        self.free[self.forward.clamped_boundary] = False
        self.matched_G = problem.observation.rows(self.G)
        r = self.G.shape[1]
        self.V = np.zeros((len(self.G), 0))
        self.MV = [np.zeros((len(self.G), 0)) for _ in self.terms]
        self.VMV = [np.zeros((0, 0)) for _ in self.terms]
        self.VMG = [np.zeros((0, r)) for _ in self.terms]
        self.matched_V = problem.observation.rows(self.V)
        self.snapshots = []  # theta of every snapshot added

    # --- distributed linear algebra on owned rows

    def _dot(self, X, Y) -> np.ndarray:
        return self.comm.allreduce(X.T @ Y, op=MPI.SUM)

    # --- building the space

    @property
    def size(self) -> int:
        return self.V.shape[1]

    def add(self, theta, X: np.ndarray, sensitivities=()) -> int:
        """Add the mode fields X (owned rows, r) solved at theta, and their derivatives in
        the materials (forward.response_sensitivities: fields that vanish on the
        boundary); returns the directions kept."""
        Y = np.hstack([X - self.G, *sensitivities])
        Y[~self.free] = 0.0
        scale = np.sqrt(max(np.max(np.diag(self._dot(Y, Y))), 1e-300))
        for _ in range(2):  # Gram-Schmidt against V, twice for round-off
            Y -= self.V @ self._dot(self.V, Y)
        s2, U = np.linalg.eigh(self._dot(Y, Y))
        keep = s2 > (1e-10 * scale) ** 2
        Q = Y @ (U[:, keep] / np.sqrt(s2[keep]))
        MQ = [self.problem.model.multiply(M, Q) for M in self.terms]
        for j in range(len(self.terms)):
            cross = self._dot(self.V, MQ[j])
            self.VMV[j] = np.block([[self.VMV[j], cross], [cross.T, self._dot(Q, MQ[j])]])
            self.VMG[j] = np.vstack([self.VMG[j], self._dot(Q, self.MG[j])])
            self.MV[j] = np.hstack([self.MV[j], MQ[j]])
        self.V = np.hstack([self.V, Q])
        self.matched_V = np.concatenate([self.matched_V, self.problem.observation.rows(Q)], axis=2)
        self.snapshots.append(np.array(theta, float))
        return int(keep.sum())

    # --- evaluating

    def coefficients(self, theta) -> np.ndarray:
        """a (size, r): the reduced coordinates of the mode fields at theta."""
        return self._solve(self.forward.coefficients(theta)[0])[1]

    def _solve(self, c):
        K = combine(c, self.VMV)
        return K, -np.linalg.solve(K, combine(c, self.VMG))

    def response(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """J (n_matched, gdim, r) and dJ/dtheta (n_estimated, n_matched, gdim, r)."""
        c, dc = self.forward.coefficients(theta)
        K, a = self._solve(c)
        J = self.matched_G + self.matched_V @ a
        dJ = []
        for dck in dc:
            dJ.append(self.matched_V @ -np.linalg.solve(K, combine(dck, self.VMV) @ a + combine(dck, self.VMG)))
        return J, np.array(dJ)

    def fields(self, theta) -> np.ndarray:
        """G + V a(theta): the surrogate's mode fields (owned rows, r)."""
        return self.G + self.V @ self.coefficients(theta)

    def residual(self, theta) -> float:
        """||K(theta)(G + V a)|| on the free DOFs relative to ||K(theta) G|| there: 0 is exact."""
        c = self.forward.coefficients(theta)[0]
        a = self._solve(c)[1]
        load = combine(c, self.MG)
        R = load + combine(c, self.MV) @ a
        return float(np.sqrt(np.sum(self._dot(R[self.free], R[self.free]).diagonal())
                             / max(np.sum(self._dot(load[self.free], load[self.free]).diagonal()), 1e-300)))
