"""The surrogate made exact at a material value without factorizing K there.

The equations' residuals at theta, preconditioned by the factors of K at a nearby
material value, join the surrogate's space until they are small: Galerkin on the space
so grown is a block Krylov method preconditioned by those factors (docs/method.md §7).
An estimate pays one factorization this way (its first), where it paid one per outer
step.
"""

from __future__ import annotations

import time

import numpy as np

from fenics_elasto.inverse.surrogate import MaterialSurrogate
from fenics_elasto.model.block_cg import over_budget

# refine: the relative equation residual that stands in for a solve. The answer's E comes
# from the surrogate's optimum either way; at 1e-6 instead of 1e-8 sigma moved by 3e-8
# (relative) on the phantom and 2 of 5-8 block steps were saved.
REFINE_TOL = 1e-6
# ... and for the modes' derivative along the optimum's controls (dJ/dtheta q): it enters
# the outer gradient and the posterior's dy only, where a relative error e moves the
# optimum by ~e sqrt(n_matched) of sigma (3e-3 at 1e-4) and sigma by e.
DERIVATIVE_TOL = 1e-4
REFINE_MAXITER = 20


def refine(surrogate: MaterialSurrogate, theta, factors, q=None, tol: float = REFINE_TOL, maxiter: int = REFINE_MAXITER,
           budget: float = np.inf) -> int | None:
    """Make the surrogate's J(theta) (and with controls ``q``, dJ/dtheta q) exact to ``tol``
    (``MaterialSurrogate.residuals``) without factorizing K(theta): add the equations' residuals at
    theta, preconditioned by the ``factors`` of K at a nearby material value
    (solvers.SolverCache.closest), to the space until they are that small. Galerkin
    on the space so grown is a block Krylov method preconditioned by those factors:
    the error falls at least like CG's, by (sqrt(k) - 1) / (sqrt(k) + 1) per step for
    a spread k of the coefficients (0.13 at k = 1.7, the phantom's start E 30 to its
    answer 51.5). Returns the steps (one block back-solve each), None if ``maxiter``
    of them did not reach ``tol``, or once the steps still needed at the rate seen
    would take longer than ``budget`` seconds (a factorization's: then it is cheaper)."""
    start, last = time.perf_counter(), None
    for step in range(maxiter + 1):
        settled = surrogate.residuals.known(theta)  # the mode fields' on this space, if worked out
        R, relative = surrogate.residuals.blocks(theta, q, modes=q is None or settled is None or settled > tol)
        worst = float(np.max(relative)) / tol
        if worst <= 1:
            return step
        if step == maxiter or (last is not None and over_budget(surrogate.comm, start, step, worst / last, worst, budget)):
            return None
        last = worst
        kept = [block for block, size in zip(R, relative) if size > tol]
        del R  # the residuals are the estimate's largest blocks after V: freed as soon as they are used
        surrogate.extend([_preconditioned(surrogate, factors, kept)])
    return None


def _preconditioned(surrogate: MaterialSurrogate, factors, blocks: list[np.ndarray]) -> np.ndarray:
    """F^-1 [blocks] through the factors, row-major. Takes the blocks over (the list is
    emptied): each is freed once in PETSc's column-major block, which goes before the
    solution is copied out."""
    dofs = surrogate.problem.model.dofs
    widths = [block.shape[1] for block in blocks]
    B, Z = dofs.dense(sum(widths)), dofs.dense(sum(widths))
    start = 0
    for width in widths:
        B.getDenseArray()[:, start:start + width] = blocks.pop(0)
        start += width
    factors.apply_factors(B, Z)
    B.destroy()
    out = Z.getDenseArray().copy()
    Z.destroy()
    return out
