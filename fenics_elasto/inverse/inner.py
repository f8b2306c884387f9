"""Inner problems: the boundary controls at fixed materials (docs/method.md §5).

Every solver returns an ``InnerResult`` with the optimum's full evaluation, gradients
included (the envelope theorem makes dPhi*/dtheta the partial derivative there).

- ``GaussNewton`` (Levenberg-Marquardt): in boundary modes d = W q the observed
  positions are exactly y0 + J q (J: one block solve, or the surrogate's), so each
  iteration is dense algebra plus a closest-point query; the curvature of the distance
  to a piecewise-linear target is exact (misfit.py). A Gaussian prior
  alpha/2 |q - q0|^2 towards the surface-matched start keeps what distances cannot see
  -- nodes sliding along the target -- where matching put it. It is part of the
  objective, in value and gradient alike, with alpha fixed for the whole estimate.
- ``LBFGS``: L-BFGS over the loaded boundary's displacement d (the forces
  preconditioned by the Dirichlet-to-Neumann map), two back-solves per iteration.
- ``LBFGSForces``: L-BFGS over the raw nodal forces, as the paper.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from fenics_elasto.inverse.objective import Evaluation, InverseProblem


@dataclass
class InnerResult:
    controls: np.ndarray
    evaluation: Evaluation
    iterations: int
    converged: bool
    prior: float = 0.0  # alpha/2 |q - q0|^2 at the optimum
    response: np.ndarray | None = None  # J (n, gdim, p) of the controls, where the solver had it

    @property
    def value(self) -> float:
        """Phi* at this theta: the data misfit plus the prior."""
        return self.evaluation.phi + self.prior


@dataclass
class LinearFit:
    q: np.ndarray
    phi: float  # data misfit
    prior: float
    residual: np.ndarray
    iterations: int
    converged: bool

    @property
    def value(self) -> float:
        """Phi* on this fit: the data misfit plus the prior."""
        return self.phi + self.prior


class GaussNewton:
    """Levenberg-Marquardt on y(q) = y0 + J q with the exact closest-feature curvature."""

    def __init__(self, problem: InverseProblem, q0: np.ndarray, anchor: float, maxiter: int, tol: float):
        self.problem = problem
        self.misfit = problem.misfit
        self.points = problem.points
        self.q0 = q0
        self.anchor = anchor
        self.alpha: float | None = None  # fixed on the first fit: alpha = anchor x mean curvature of the data term
        self.maxiter = maxiter
        self.tol = tol

    def fit(self, J: np.ndarray, start: np.ndarray | None = None) -> LinearFit:
        """Minimise Phi(q) + alpha/2 |q - q0|^2 for one response J (n, gdim, r), from q0
        (or from ``start``: the same objective, another path -- on a rough target it may
        end in another local minimum)."""
        n, gdim, r = J.shape
        flat = J.reshape(n * gdim, r)
        misfit = self.misfit

        if self.alpha is None:
            A = self._curvature_rows(J, self.points + (flat @ self.q0).reshape(n, gdim))
            self.alpha = self.anchor * float(np.mean(np.sum(A**2, axis=0)))
        alpha = self.alpha

        def evaluate(q):
            y = self.points + (flat @ q).reshape(n, gdim)
            residual = misfit.residual(y)
            return y, residual, misfit.cost(residual), 0.5 * alpha * float(np.sum((q - self.q0) ** 2))

        q = (self.q0 if start is None else start).copy()
        y, residual, phi, prior = evaluate(q)
        damping, nit, converged = 1e-3, 0, False
        for nit in range(1, self.maxiter + 1):  # noqa: B007 (nit is reported after the loop)
            A = self._curvature_rows(J, y)
            H = A.T @ A + alpha * np.eye(r)
            grad = flat.T @ misfit.gradient(residual).ravel() + alpha * (q - self.q0)
            # The most the Gauss-Newton model promises (the undamped step's decrease, grad H^-1
            # grad / 2): below tol, converged without trying a step (the phantom's fits spent
            # a closest-point query, or a cascade of damped ones, on learning that).
            if 0.5 * float(grad @ np.linalg.solve(H, grad)) <= self.tol * (phi + prior):
                converged = True
                break
            while True:  # Levenberg-Marquardt: damp until the objective decreases
                step = np.linalg.solve(H + damping * np.diag(np.diag(H)), -grad)
                trial = evaluate(q + step)
                if trial[2] + trial[3] < phi + prior or damping > 1e10:
                    break
                damping *= 10.0
            decrease = (phi + prior) - (trial[2] + trial[3])
            if decrease <= 0:  # no step lowers it: at the optimum to round-off
                converged = True
                break
            q, (y, residual, phi, prior) = q + step, trial
            damping = max(damping / 10.0, 1e-12)
            if decrease <= self.tol * (phi + prior):
                converged = True
                break
        return LinearFit(q, phi, prior, residual, nit, converged)

    def _curvature_rows(self, J, y) -> np.ndarray:
        """sqrt(w) C J: rows whose Gram matrix is the Gauss-Newton Hessian of the data term,
        the zero rows left out (a point closest to a face's interior has one direction of
        gdim: at rank 240 the Gram matrix of all rows was most of a fit's dense algebra)."""
        C = self.misfit.gauss_newton_rows(y)
        point, row = np.nonzero(np.any(C != 0.0, axis=2))
        return np.einsum("md,mdr->mr", C[point, row], J[point])

    def solve(self, theta, response, basis) -> InnerResult:
        """The inner optimum at theta for the response J = ``response(theta)``, evaluated in full."""
        J = response(theta)
        fit = self.fit(J)
        d = self.problem.states.to_motion(basis, fit.q)
        ev = self.problem.evaluate_displacement(theta, d, gradient=True)
        return InnerResult(fit.q, ev, fit.iterations, fit.converged, fit.prior, J)


class LBFGS:
    """L-BFGS over the loaded boundary's displacement d, or over the raw nodal forces."""

    def __init__(self, problem: InverseProblem, forces: bool, maxiter: int, tol: float):
        self.problem = problem
        self.evaluate: Callable[..., Evaluation] = problem.evaluate_forces if forces else problem.evaluate_displacement
        self.maxiter = maxiter
        self.tol = tol
        self.control_scale = 1.0
        self.phi_scale = 1.0

    def solve(self, theta, start: np.ndarray) -> InnerResult:
        cache: dict[bytes, Evaluation] = {}

        def fun(z):
            ev = self.evaluate(theta, z * self.control_scale, gradient=True)
            cache.clear()
            cache[z.tobytes()] = ev
            assert ev.grad_controls is not None  # asked for
            return ev.phi / self.phi_scale, ev.grad_controls * (self.control_scale / self.phi_scale)

        res = minimize(fun, start / self.control_scale, jac=True, method="L-BFGS-B",
                       options={"maxiter": self.maxiter, "maxcor": 30, "ftol": self.tol, "gtol": 1e-12})
        ev = cache.get(res.x.tobytes()) or self.evaluate(theta, res.x * self.control_scale, gradient=True)
        return InnerResult(res.x * self.control_scale, ev, int(res.nit), res.nit < self.maxiter)
