"""Several stiffness systems solved at once on one factorization: CG preconditioned by
the factors of K(c0), each column its own CG, all columns in lock step.

K(c) and K(c0) are sums of the same positive semidefinite material matrices, so the
preconditioned spectrum lies within [min c/c0, max c/c0] (solvers.NearbySolver) and CG
needs at most ~sqrt(spread)/2 ln(2/rtol) steps. In lock step each step is one block
back-solve of every column together: a pass over the factors costs nearly the same for
one column as for fifty (the default phantom, 116k DOFs: 0.2 s for one, ~1 s for 54),
so the columns of several material values share it. Training's material levels use it
(reduction.synthetic): one factorization where there was one per level.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from fenics_elasto.model.dofs import DofLayout, times_block
from fenics_elasto.model.solvers import DirectSolver, SolverError


def over_budget(comm, start: float, steps: int, rate: float, worst: float, budget: float) -> bool:
    """Whether the steps still needed to bring a residual down by ``worst`` at ``rate``
    per step, each as long as the ``steps`` taken since ``start``, would take longer than
    ``budget`` seconds (what is spent is spent either way; the slowest rank's clock, so
    that all ranks decide alike)."""
    spent = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
    needed = np.inf if rate >= 1 else np.log(worst) / -np.log(rate)
    return spent / steps * needed > comm.allreduce(budget, op=MPI.MAX)


def cg_steps_bound(spread: float, rtol: float) -> int:
    """CG's steps to ``rtol`` at most for a preconditioned spectrum of this spread."""
    return int(np.ceil(0.5 * np.sqrt(spread) * np.log(2.0 / rtol)))


class LockstepCG:
    """K_i X_i = B_i for the systems (K_i, B_i) (owned rows, dense), by CG preconditioned
    with ``base``'s factors, every column in lock step (the module's docstring)."""

    def __init__(self, base: DirectSolver, dofs: DofLayout, systems: Sequence[tuple[PETSc.Mat, np.ndarray]],
                 rtol: float):
        self.base, self.dofs, self.rtol = base, dofs, rtol
        self.operators = [K for K, _ in systems]
        bounds = np.cumsum([0] + [B.shape[1] for _, B in systems])
        self.columns = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        self.B = np.hstack([B for _, B in systems])
        self.comm = base.comm

    def solve(self, maxiter: int, budget: float = np.inf) -> tuple[list[np.ndarray], int]:
        """(the solutions X_i, the steps taken). A SolverError if ``maxiter`` steps do not
        reach rtol, or once the steps still needed at the rate seen would take longer than
        ``budget`` seconds (what the caller would pay otherwise: factorizations)."""
        start = time.perf_counter()
        scale = self.rtol * self._norms(self.B)
        X, R = np.zeros_like(self.B), self.B.copy()
        Z = self._preconditioned(R)
        P, rz = Z.copy(), self._dots(R, Z)
        last = None
        for step in range(1, maxiter + 1):
            Q = self._times_K(P)
            open_ = rz != 0.0  # a zero right-hand side is solved already
            alpha = np.divide(rz, self._dots(P, Q), out=np.zeros_like(rz), where=open_)
            X += alpha * P
            R -= alpha * Q
            worst = float(np.max(self._norms(R) / np.maximum(scale, 1e-300)))
            if worst <= 1.0:
                self.base.stats.solves += self.B.shape[1]
                self.base.stats.iterations += step
                return [X[:, c] for c in self.columns], step
            if last is not None and over_budget(self.comm, start, step, worst / last, worst, budget):
                break
            last = worst
            Z = self._preconditioned(R)
            rz_new = self._dots(R, Z)
            P = Z + np.divide(rz_new, rz, out=np.zeros_like(rz), where=open_) * P
            rz = rz_new
        raise SolverError(f"CG on the factors of a nearby material value stopped after {step} steps above rtol "
                          f"{self.rtol:g}")

    def _preconditioned(self, R: np.ndarray) -> np.ndarray:
        """F^-1 R through the base's factors: one block back-solve of every column."""
        B, Z = self.dofs.dense(R.shape[1]), self.dofs.dense(R.shape[1])
        B.getDenseArray()[:] = R
        self.base.apply_factors(B, Z)
        out = Z.getDenseArray().copy()
        for M in (B, Z):
            M.destroy()
        return out

    def _times_K(self, P: np.ndarray) -> np.ndarray:
        """K_i P_i for every system's columns."""
        out = np.empty_like(P)
        for K, columns in zip(self.operators, self.columns):
            out[:, columns] = times_block(K, np.ascontiguousarray(P[:, columns]))
        return out

    def _dots(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        return self.comm.allreduce(np.einsum("ij,ij->j", A, B), op=MPI.SUM)

    def _norms(self, A: np.ndarray) -> np.ndarray:
        return np.sqrt(self._dots(A, A))
