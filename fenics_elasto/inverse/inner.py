"""Inner problems: the boundary controls at fixed materials (docs/method.md §5).

Every solver returns an ``InnerResult`` with the optimum's full evaluation, gradients
included (the envelope theorem makes dPhi*/dtheta the partial derivative there).

- ``GaussNewton`` (Levenberg-Marquardt): in boundary modes d = W q the observed
  positions are exactly y0 + J q (J: one block solve, or the surrogate's), so each
  iteration is dense algebra plus one or two closest-point queries: two curvature
  models, the facets' and the smooth surface's, the better step taken (``GaussNewton``).
  A Gaussian prior
  alpha/2 |q - q0|^2 towards the surface-matched start keeps what distances cannot see
  -- nodes sliding along the target -- where matching put it. It is part of the
  objective, in value and gradient alike, with alpha fixed for the whole estimate.
- ``LBFGS``: L-BFGS over the loaded boundary's displacement d (the forces
  preconditioned by the Dirichlet-to-Neumann map), two back-solves per iteration.
- ``LBFGSForces``: L-BFGS over the raw nodal forces, as the paper.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager
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
    """Levenberg-Marquardt on y(q) = y0 + J q with two Gauss-Newton models, the better
    step of the two taken: the facets' exact curvature (misfit.gauss_newton_rows), and
    the smooth surface's at the facets' edges and vertices -- there a point's distance
    along its unit residual only (Surface.curvature_directions with ``smooth``).

    Why two: the exact curvature of a point closest to a vertex (every direction) or an
    edge (two) holds only inside that feature's Voronoi region. At the letter's corners
    the fit needs it: the smooth model alone took 400 iterations where the exact one
    takes 6. On a finely faceted surface, and at a crease where the fit's points sit on
    both sides, the region is a thin wedge or the point keeps leaving it, and the full
    curvature pins the point's place along the surface: the model refused the sliding
    a fit needs. Measured on the default phantom (5,522 matched nodes; targets of 7e4-1e5
    triangles, the rectum a capped tube): the exact model alone needed 136 iterations to
    converge at rank 80, and stopped at the 400-iteration cap 0.6 % above the optimum
    at rank 240; with both, 22 and 57 iterations to a lower Phi. Each iteration then pays
    two closest-point queries where the models differ. Only the model changes: the
    objective (its prior weight alpha included) is the same.

    The fit stops when the undamped steps of both models promise less than ``tol`` of
    Phi, or the step taken gains less. (A floor at a hundredth of a chi-square unit,
    Phi/(100 n) for n rows, was tried: it cut the phantom's fits to 6 and 10 iterations,
    but Phi* then stopped being a smooth function of the materials to the precision
    the outer gradient's Taylor test asks -- not kept.)
    """

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
        end in another local minimum), to the solver's ``tol`` (``fitted_to`` sets another)."""
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
            grad = flat.T @ misfit.gradient(residual).ravel() + alpha * (q - self.q0)
            hessians = self._hessians(J, y, alpha)
            # The most the Gauss-Newton models promise (the undamped step's decrease, grad H^-1
            # grad / 2): below tol for both, converged without trying a step (the phantom's fits
            # spent a closest-point query, or a cascade of damped ones, on learning that).
            if max(0.5 * float(grad @ np.linalg.solve(H, grad)) for H in hessians) <= self.tol * (phi + prior):
                converged = True
                break
            while True:  # Levenberg-Marquardt: damp until the objective decreases; the better model's step
                steps = [np.linalg.solve(H + damping * np.diag(np.diag(H)), -grad) for H in hessians]
                step, trial = min(((s, evaluate(q + s)) for s in steps), key=lambda pair: pair[1][2] + pair[1][3])
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
        """sqrt(w) C J with the facets' exact curvature (gauss_newton_rows): it sets the
        prior's weight alpha, as it always has."""
        return self._rows_times(self.misfit.gauss_newton_rows(y), J)

    def _hessians(self, J, y, alpha) -> list[np.ndarray]:
        """The Gauss-Newton matrices of the two models (the class's docstring): the facets'
        exact curvature, and the smooth surface's at their edges and vertices -- one when
        no point is closest to such a feature. The rows the models share are summed once:
        on the default phantom the models differ at 4-8 of 5,522 points."""
        exact = self.misfit.gauss_newton_rows(y)
        smooth = self.misfit.gauss_newton_rows(y, smooth=True)
        differ = np.any(exact != smooth, axis=(1, 2))[:, None, None]
        shared = self._gram(np.where(differ, 0.0, exact), J) + alpha * np.eye(J.shape[2])
        if not differ.any():
            return [shared]
        return [shared + self._gram(np.where(differ, C, 0.0), J) for C in (exact, smooth)]

    @classmethod
    def _gram(cls, C, J) -> np.ndarray:
        """(C J)^T (C J) over the nonzero rows of C."""
        A = cls._rows_times(C, J)
        return A.T @ A

    @staticmethod
    def _rows_times(C, J) -> np.ndarray:
        """The nonzero rows of C J (at rank 240 the Gram matrix of all rows was most of a
        fit's dense algebra)."""
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


@contextmanager
def fitted_to(inner, tol: float):
    """The inner solver's fits inside the block stop at ``tol`` instead of its own: the
    values that only place a bracket (the scan, the start that seeds it)."""
    own, inner.tol = inner.tol, tol
    try:
        yield
    finally:
        inner.tol = own
