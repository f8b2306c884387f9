"""The response of boundary modes: the field X(theta) of each mode W of the loaded
boundary's motion, and its derivatives in the materials.

For reduced bases the matched displacement is exactly linear in the modes'
coordinates: J(theta) = O X(theta). X costs one block solve through one factorization
(MatMatSolve over the r right-hand sides at once, ~8x faster than r single solves);
its derivatives in the materials cost block back-solves on the same factorization
(the surrogate's seed: inverse/surrogate.py).
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from fenics_elasto.model.dofs import times_block
from fenics_elasto.model.forward import BoundaryForward


def response_sensitivities(forward: BoundaryForward, theta, X: np.ndarray, order: int = 2) -> list[np.ndarray]:
    """Derivatives of the mode fields X(theta) (response_block) along the estimated
    constants, on the factorization X was solved with (block back-solves only):

        K dX_k  = -D_k X                    (D_k = dK/dtheta_k)
        K dX_kl = -(D_k dX_l + D_l dX_k)     (order 2, k <= l)

    on the free DOFs, zero on the loaded and fixed ones (the boundary modes do not
    depend on the materials). The second order leaves out d2K/dtheta2 -- exact along
    E, whose coefficients are linear in it; for nu it only shapes the space the
    surrogate searches (surrogate.py), which stays exact at every full solve."""
    c, dc = forward.coefficients(theta)
    factor = forward.model.factorize(c, forward.clamped_boundary)
    D = [forward.model.stiffness.matrix(row) for row in dc]

    def solve(*products) -> np.ndarray:  # -K^{-1} sum D Y, with the Dirichlet rows zero
        block = forward.model.dofs.dense(X.shape[1])
        rhs = block.getDenseArray()
        for M, Y in products:
            rhs -= times_block(M, Y)
        rhs[forward.clamped_boundary] = 0.0
        out = forward.model.dofs.dense(X.shape[1])
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
    forward.forward_solves += (len(first) + len(second)) * X.shape[1]
    return first + second

def lift(forward: BoundaryForward, basis: np.ndarray | None = None) -> PETSc.Mat:
    """The boundary modes as fields: W on the loaded DOFs, zero elsewhere (dense, owned rows)."""
    W = np.eye(forward.force_dofs) if basis is None else basis
    r = W.shape[1]
    G = forward.model.dofs.dense(r)
    rows = forward.loaded.dofs(forward.model.dofs.bs).ravel()
    G.getDenseArray()[rows] = forward.loaded.local(W.reshape(forward.loaded.total, forward.gdim * r)).reshape(-1, r)
    return G

def response_block(forward: BoundaryForward, theta, basis: np.ndarray | None = None, rtol: float | None = None) -> np.ndarray:
    """X (owned DOFs, r): the field of each boundary mode (W: force_dofs x r; None: all).

    The r right-hand sides [-K W on free rows, W on the loaded rows] go through the
    one factorization of K_D as a dense block (MatMatSolve). Inside ``forward.borrowing()`` a single
    mode (reduction.missing_wall_motion's) is a single solve on nearby factors, to
    ``rtol`` if given (a diagnostic needs fewer CG steps); a block pays a factorization
    (CG would take each column alone).
    """
    c = forward.coefficients(theta)[0]
    G = lift(forward, basis)
    K = forward.model.stiffness.matrix(c)
    rhs = K.matMult(G)  # both PETSc dense blocks: one product, no round trip through numpy
    block = rhs.getDenseArray()
    block *= -1.0
    block[forward.clamped_boundary] = G.getDenseArray()[forward.clamped_boundary]
    X = forward.model.dofs.dense(G.getSize()[1])
    with forward.model.solver(c, forward.clamped_boundary, forward.borrows and G.getSize()[1] == 1, rtol) as factor:
        factor.solve_many(rhs, X)
    out = X.getDenseArray().copy()
    for M in (G, K, rhs, X):
        M.destroy()
    return out
