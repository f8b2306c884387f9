"""The residual linearised at an inner optimum: what the Gauss-Newton Hessian of Phi* needs.

``linearise`` gives the residual's Jacobians in the controls and in s = (log E, nu) at an
inner optimum, weighted by the noise model's rows (misfit.statistical_rows: a surface
point is measured along its normal only); the posterior (uncertainty/posterior.py)
profiles the controls out of it. ``linearise_profiled`` gives the same without the
controls' Jacobian (the full force space with L-BFGS), profiling them out by LSQR.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fenics_elasto.inverse.inner import InnerResult


@dataclass
class Linearisation:
    """The weighted residual e = sqrt(w) C r at an inner optimum and its Jacobians:
    the Gauss-Newton Hessian of Phi in (q, s) is [A_q A_s]^T [A_q A_s] + diag(prior, 0)."""

    residual: np.ndarray  # (m,)
    A_q: np.ndarray  # (m, p) in the controls
    A_s: np.ndarray  # (m, n_theta) in s = (log E, nu)
    prior: float  # alpha: the prior's curvature on every control
    informative: int  # residual components the target constrains (1 per surface point on a face, ...)

    _eliminated: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def profiled(self) -> tuple[np.ndarray, np.ndarray]:
        """(B, S): the sensitivity in s with the controls profiled out,
        B = A_s - A_q X with X = (A_q^T A_q + alpha I)^-1 A_q^T A_s, and the Schur
        complement S = A_s^T B = B^T B + alpha X^T X (the Gauss-Newton Hessian of Phi* in s)."""
        return self._eliminate()[:2]

    def fitted_controls(self) -> float:
        """The controls' share of the hat matrix's trace, tr(A_q (A_q^T A_q + alpha I)^-1 A_q^T)."""
        return self._eliminate()[2]

    def _eliminate(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(B, S, the controls' hat trace) from one solve with A_q^T A_q + alpha I, once:
        a posterior asks for them three times (laplace, the patch covariance, the offset)."""
        if self._eliminated is None:
            p, n = self.A_q.shape[1], self.A_s.shape[1]
            gram = self.A_q.T @ self.A_q
            X = np.linalg.lstsq(gram + self.prior * np.eye(p), np.hstack([self.A_q.T @ self.A_s, gram]), rcond=None)[0]
            B = self.A_s - self.A_q @ X[:, :n]
            self._eliminated = (B, self.A_s.T @ B, float(np.trace(X[:, n:])))
        return self._eliminated

    def sensitivity(self) -> np.ndarray:
        """diag(A_s^T A_s): each constant's own effect on the data, controls fixed."""
        return np.einsum("mk,mk->k", self.A_s, self.A_s)


@dataclass
class ProfiledLinearisation(Linearisation):
    """A Linearisation whose A_q was too big to keep (the full force space with L-BFGS:
    a column per loaded DOF, a solve each): A_q is empty and A_s holds B already
    (``linearise_profiled``); what B cannot tell is kept beside it."""

    schur: np.ndarray | None = None  # S
    controls_hat: float = 0.0  # the controls' hat trace, counted
    own: np.ndarray | None = None  # diag(A_s^T A_s) before profiling

    def profiled(self) -> tuple[np.ndarray, np.ndarray]:
        assert self.schur is not None
        return self.A_s, self.schur

    def fitted_controls(self) -> float:
        return self.controls_hat

    def sensitivity(self) -> np.ndarray:
        assert self.own is not None
        return self.own


def linearise(problem, theta, result: InnerResult, J: np.ndarray, dy_dtheta: np.ndarray, alpha: float) -> Linearisation:
    """The Linearisation at theta from the controls' response J (n, gdim, p) and the
    observed positions' derivative in theta at fixed controls (n, gdim, n_theta)."""
    rows, weighted, A_s = _weighted(problem, theta, result, dy_dtheta)
    A_q = np.einsum("lkd,ldr->lkr", rows, J).reshape(len(weighted), -1)
    return Linearisation(weighted, A_q, A_s, alpha, _informative(rows))


def _weighted(problem, theta, result: InnerResult, dy_dtheta: np.ndarray):
    """(sqrt(w) C rows, the weighted residual e, A_s) at an inner optimum."""
    rows = problem.misfit.statistical_rows(result.evaluation.y, result.evaluation.residual)  # sqrt(w) C
    weighted = np.einsum("lkd,ld->lk", rows, result.evaluation.residual).ravel()
    A_theta = np.einsum("lkd,ldr->lkr", rows, dy_dtheta).reshape(len(weighted), -1)
    return rows, weighted, A_theta * problem.params.dtheta_ds(theta)


def _informative(rows) -> int:
    return int(np.sum(np.linalg.norm(rows, axis=2) > 0))


PROFILED_TOL = 1e-8  # linearise_profiled: LSQR's relative tolerance
PROFILE_PROBES = 4  # linearise_profiled: random probes for the mean curvature of the data term


def linearise_profiled(problem, theta, result: InnerResult, anchor: float, alpha: float | None = None,
                       maxiter: int = 500) -> ProfiledLinearisation:
    """The Linearisation at an optimum of the full force space without A_q (a column per
    loaded DOF, a solve each): the controls profiled out of A_s directly, column by
    column, by damped LSQR on min |A_q x - a|^2 + alpha |x|^2 -- A_q applied by one solve
    (``observed_motion``), A_q^T by one adjoint solve (``pull_back``) on the
    factorization at theta.

    alpha is the Gauss-Newton fit's own prior (anchor x the data term's mean curvature
    per control, here from PROFILE_PROBES random sign vectors: E|A_q z|^2 = tr A_q^T A_q),
    so both inner solvers give one posterior; L-BFGS has no prior in its objective, but
    without one the directions the data barely see (a wall sliding along its target)
    make LSQR crawl, and their share of the answer is the prior's in either case. The
    range of A_q is the same for forces or boundary motion as the controls (a bijection
    at fixed materials), and A_s at either's fixed value differ by a column in it, so
    boundary motion serves both. The controls' hat trace is counted as min(controls,
    informative rows) -- an upper bound, so the noise's degrees of freedom err low and
    its std high."""
    from scipy.sparse.linalg import LinearOperator, lsqr

    rows, weighted, A_s = _weighted(problem, theta, result, problem.observation.rows(
        problem.forward.field_derivative(theta, result.evaluation.u)))
    n, k, _ = rows.shape
    A_q = LinearOperator(
        (n * k, problem.force_dofs), dtype=float,
        matvec=lambda d: np.einsum("lkd,ld->lk", rows, problem.observed_motion(theta, np.ravel(d))).ravel(),
        rmatvec=lambda z: problem.pull_back(theta, np.einsum("lkd,lk->ld", rows, np.reshape(z, (n, k))))[0])
    if alpha is None:
        signs = np.random.default_rng(0).choice([-1.0, 1.0], (PROFILE_PROBES, problem.force_dofs))
        alpha = anchor * float(np.mean([np.sum(A_q.matvec(z) ** 2) for z in signs])) / problem.force_dofs
    X = np.stack([lsqr(A_q, a, damp=np.sqrt(alpha), atol=PROFILED_TOL, btol=PROFILED_TOL, iter_lim=maxiter)[0]
                  for a in A_s.T], axis=1)
    B = A_s - np.stack([A_q.matvec(x) for x in X.T], axis=1)
    informative = _informative(rows)
    return ProfiledLinearisation(weighted, np.zeros((n * k, 0)), B, alpha, informative, B.T @ B + alpha * X.T @ X,
                                 float(min(problem.force_dofs, informative)), np.einsum("mk,mk->k", A_s, A_s))
