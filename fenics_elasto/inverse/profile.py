"""The profile functional Phi*(theta) = min over the boundary controls (docs/method.md §5).

Phi* is what the outer loop minimises over the materials, in s = (log E, nu). Two
implementations behind one interface, ``value_and_gradient(s)``:

- ``Profile``: every value solved in full (a factorization of K(theta), then the inner
  solver) -- with bases, after the first, made exact on the first's factors instead
  where that is cheaper (MaterialSurrogate.refine). Each solved theta is kept: a value
  within a hair of one solved before is not solved again (L-BFGS-B re-evaluates its
  start and creeps by 1e-9 steps near the optimum -- each step a factorization).
- ``SurrogateProfile``: with reduced bases, Phi* on the reduced-basis response in the
  materials (surrogate.py): J(theta) and dJ/dtheta from the solved snapshots, the
  same Gauss-Newton fit, no factorization.

For a clean function of theta the Gauss-Newton fit always starts from the same
surface-matched controls q0 (no path dependence through warm starts), runs to a
tight tolerance, and the prior it adds is in the value as in the gradient. By the
envelope theorem dPhi*/dtheta is the partial derivative at the inner optimum.

``linearise`` gives what the Gauss-Newton Hessian of Phi* needs (posterior.py): the
residual's Jacobians in the controls and in s at an inner optimum, weighted by the
noise model's rows (misfit.statistical_rows: a surface point is measured along its
normal only). ``linearise_profiled`` gives the same without the controls' Jacobian
(the full force space with L-BFGS), profiling the controls out by LSQR on solves.
"""

from __future__ import annotations


from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from fenics_elasto.util.logs import log
from fenics_elasto.inverse.inner import GaussNewton, InnerResult
from fenics_elasto.util.interrupts import check_interrupt
from fenics_elasto.inverse.surrogate import DERIVATIVE_TOL

BRACKET_GUARD = 0.05  # bracketed_minimum: a step keeps this share of the bracket from its ends


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
        return self.A_s, self.schur

    def fitted_controls(self) -> float:
        return self.controls_hat

    def sensitivity(self) -> np.ndarray:
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


def envelope_gradient(misfit, fit, dJ: np.ndarray) -> np.ndarray:
    """dPhi*/dtheta of a Gauss-Newton fit on a response J with derivatives dJ: the
    partial derivative at the inner optimum (the prior does not depend on theta)."""
    g = misfit.gradient(fit.residual)
    return np.array([np.sum(g * (dJk @ fit.q)) for dJk in dJ])


class Profile:
    """Phi*(theta) with every value solved in full; keeps every solved point."""

    def __init__(self, problem, inner, basis=None, surrogate=None, same_within: float = 1e-6):
        self.problem = problem
        self.params = problem.params
        self.inner = inner
        self.basis = basis
        self.surrogate = surrogate  # fed with the mode fields of every solve
        self.same_within = same_within
        self.solved: list[tuple[np.ndarray, InnerResult, str]] = []  # (s, result, stage)
        self.linearisations: dict[int, Linearisation] = {}  # id(result) -> at that solve (Gauss-Newton)
        self.inner_iterations = 0
        self.unconverged = 0  # solves that stopped at the inner iteration limit, the interval's ("ci") aside

    # --- solving

    def response(self, theta) -> np.ndarray:
        """J(theta) in full (one factorization); a snapshot for the surrogate."""
        if self.surrogate is None:
            return self.problem.response(theta, self.basis)
        forward = self.problem.forward
        X = forward.response_block(theta, self.basis)
        order = 2 if len(self.params) <= 2 else 1  # second order: 1 + n + n(n+1)/2 fields per mode
        self.surrogate.add(theta, X, forward.response_sensitivities(theta, X, order))
        return self.problem.observation.rows(X)

    def known(self, s) -> InnerResult | None:
        for s_seen, result, _ in self.solved:
            if np.all(np.abs(np.asarray(s) - s_seen) < self.same_within):
                return result
        return None

    def solve(self, theta, stage: str, start: np.ndarray | None = None) -> InnerResult:
        s = self.params.to_s(theta)
        result = self.known(s)
        if result is not None:
            return result
        check_interrupt(self.problem.scene.comm)  # under MPI every rank stops here together
        on_surrogate = self._on_refined_surrogate(theta) if isinstance(self.inner, GaussNewton) else None
        if on_surrogate is not None:
            result, dy = on_surrogate
        elif isinstance(self.inner, GaussNewton):
            result = self.inner.solve(theta, self.response, self.basis)
        else:
            result = self.inner.solve(theta, start if start is not None else self.best().controls)
        self.inner_iterations += result.iterations
        # A profile-interval value only places an end, bracketed to END_PRECISION anyway: on a
        # rough target its inner fit may creep to the limit without moving the answer.
        self.unconverged += not result.converged and stage != "ci"
        self.solved.append((s, result, stage))
        if result.response is not None:
            if on_surrogate is None:  # n_theta back-solves on the factorization at hand
                dy = self.problem.observation.rows(self.problem.forward.field_derivative(theta, result.evaluation.u))
            self.linearisations[id(result)] = linearise(self.problem, theta, result, result.response, dy, self.inner.alpha)
            result.response = None  # kept in the linearisation only
        log.info(f"  {stage:5s} {self.params.describe(theta)}  Phi* = {result.value:.6e}  "
                 f"({result.iterations} inner iterations{'' if result.converged else ', NOT converged'})")
        return result

    def _on_refined_surrogate(self, theta) -> tuple[InnerResult, np.ndarray] | None:
        """With ``forward.borrow`` (an estimate's solves after its first) and the factors
        of a nearby material value at hand: the inner optimum at theta and the observed
        positions' derivative in theta at fixed controls, both from the surrogate refined
        at theta on those factors to a relative equation residual of REFINE_TOL
        (MaterialSurrogate.refine) -- what a full solve gives, without its factorization.
        None where it cannot, or where that would cost more than a factorization."""
        forward = self.problem.forward
        if self.surrogate is None or not forward.borrow:
            return None
        factors = forward.model.solvers.closest(forward.coefficients(theta)[0], forward.clamped_boundary)
        steps = self.surrogate.refine(theta, factors, budget=factors.seconds) if factors is not None else None
        if steps is None:
            return None
        fit = self.inner.fit(self.surrogate.response(theta)[0])
        more = self.surrogate.refine(theta, factors, fit.q, DERIVATIVE_TOL)  # the derivative along the optimum's controls
        if more is None:
            return None
        log.info(f"  surrogate refined at {self.params.describe(theta)} on nearby factors ({steps} + {more} block "
                 f"back-solves, equation residual {self.surrogate.residual(theta):.1e}): no factorization")
        J, dJ = self.surrogate.response(theta)
        fit = self.inner.fit(J)  # the same optimum, on the space the derivatives grew (exact to tol before)
        u = self.problem.model.dofs.function()
        owned = self.surrogate.G.shape[0]
        u.x.array[:owned] = self.surrogate.fields(theta) @ fit.q
        u.x.scatter_forward()
        evaluation = self.problem.evaluate_field(theta, u)
        evaluation.grad_theta = envelope_gradient(self.inner.misfit, fit, dJ)
        dy = np.stack([dJk @ fit.q for dJk in dJ], axis=-1)
        return InnerResult(fit.q, evaluation, fit.iterations, fit.converged, fit.prior, J), dy

    def value_and_gradient(self, s) -> tuple[float, np.ndarray]:
        theta = self.params.to_theta(s)
        result = self.solve(theta, "outer")
        return result.value, result.evaluation.grad_theta * self.params.dtheta_ds(theta)

    # --- what was found

    def best(self) -> InnerResult:
        return min((result for _, result, _ in self.solved), key=lambda r: r.value)

    def linearisation(self, result: InnerResult) -> Linearisation | None:
        return self.linearisations.get(id(result))

    def best_theta(self) -> np.ndarray:
        s, _, _ = min(self.solved, key=lambda item: item[1].value)
        return self.params.to_theta(s)

    def history(self) -> list[dict]:
        return [{"stage": stage, "theta": list(map(float, self.params.to_theta(s))), "phi": result.value,
                 "misfit": result.evaluation.phi, "inner": result.iterations}
                for s, result, stage in self.solved]


class SurrogateProfile:
    """Phi*(theta) on the reduced-basis response in the materials: dense algebra only."""

    def __init__(self, profile: Profile):
        self.profile = profile
        self.params = profile.params
        self.fit_inner: GaussNewton = profile.inner
        self.evaluations = 0

    def fit(self, s, start: np.ndarray | None = None):
        """The inner fit (a LinearFit) at s on the surrogate, from q0 or ``start``."""
        J, _ = self.profile.surrogate.response(self.params.to_theta(s))
        return self.fit_inner.fit(J, start)

    def inner_spread(self, s, starts, cold=None) -> tuple[float, np.ndarray]:
        """How far apart in Phi* the inner fits at s end from q0 (``cold``, if already
        made) and from each of ``starts`` (0 for a convex inner problem; on a rough target
        the fit's local minima, which a cold start picks among as theta moves: Phi*'s
        jaggedness), and the controls of the lowest."""
        fits = [cold if cold is not None else self.fit(s)] + [self.fit(s, start) for start in starts]
        values = [fit.value for fit in fits]
        return float(max(values) - min(values)), fits[int(np.argmin(values))].q

    def value_and_gradient(self, s) -> tuple[float, np.ndarray]:
        theta = self.params.to_theta(s)
        J, dJ = self.profile.surrogate.response(theta)
        fit = self.fit_inner.fit(J)
        self.evaluations += 1
        return fit.value, envelope_gradient(self.fit_inner.misfit, fit, dJ) * self.params.dtheta_ds(theta)


# --------------------------------------------------------------------------- the outer loop


def minimize_profile(profile: Profile, xtol: np.ndarray, maxiter: int, smooth: bool = True) -> int:
    """Minimise Phi* over s, every value solved in full; stops once a step moves every
    constant by less than ``xtol`` (more digits of E would cost factorizations, not
    accuracy). One constant, a ``smooth`` Phi* and a minimum the solved values bracket:
    cubic steps inside the bracket (``bracketed_minimum``); else L-BFGS-B from the best
    solved value. On a jagged Phi* (a rough target) the bracket's local steps stopped in
    worse local minima than L-BFGS-B's long ones (2D inclusion, 0.5 % noise, 10 draws:
    higher Phi* in 6, mean error +5.8 % against +0.1 %). Returns the iterations."""
    params = profile.params
    if len(params) == 1 and smooth:
        def slope(x: float) -> tuple[float, float]:  # Phi* and dPhi*/ds (solved values are kept)
            value, grad = profile.value_and_gradient(np.array([x]))
            return float(value), float(grad[0])

        known = [(float(s[0]), *slope(float(s[0]))) for s, _, _ in profile.solved]
        log.info("outer: cubic steps inside the scan's bracket, if it makes one (envelope gradient)")
        iterations = bracketed_minimum(slope, known, float(xtol[0]), maxiter)
        if iterations is not None:
            return iterations
    scale = max(profile.best().value, 1e-300)  # L-BFGS-B's tolerances are absolute below 1
    settle = Settle(params.to_s(profile.best_theta()), xtol)

    def objective(s):
        value, grad = profile.value_and_gradient(s)
        return value / scale, grad / scale

    log.info("outer L-BFGS-B over the materials (envelope gradient)")
    minimize(objective, settle.s, jac=True, method="L-BFGS-B", bounds=params.s_bounds(), callback=settle,
             options={"maxiter": maxiter, "ftol": 1e-12, "gtol": 1e-9})
    return settle.iterations


def bracketed_minimum(value_and_gradient, known: list[tuple[float, float, float]], xtol: float,
                      maxiter: int) -> int | None:
    """A local minimum of f in one variable (``value_and_gradient(x)`` -> (f, f')), from
    points (x, f, f') already known whose lowest has another on its downhill side: the
    minimum lies between the two, and the minimiser of the cubic matching f and f' at
    both ends is the next point (kept BRACKET_GUARD of the bracket inside it). Stops when
    that cubic puts the minimum within ``xtol`` of the lowest point, or once a step moves
    x by less. The scan's values and envelope gradients make the first bracket, so the
    full-space outer loop spends no solve on a first step of unknown length (L-BFGS-B's
    went to E's bound on the phantom: a factorization and an inner solve wasted).
    Returns the points evaluated; None, with nothing evaluated, if the known points
    bracket no minimum (it lies at a bound or beyond them: L-BFGS-B, which handles bounds)."""
    points = list(known)
    for iteration in range(maxiter):
        x, f, g = min(points, key=lambda p: p[1])
        downhill = [p for p in points if (p[0] - x) * g < 0]
        if not downhill:
            return iteration if g == 0.0 or iteration else None
        far = min(downhill, key=lambda p: abs(p[0] - x))
        step = cubic_minimizer((x, f, g), far)
        if abs(step - x) < xtol:
            return iteration
        lo, hi = sorted((x, far[0]))
        step = float(np.clip(step, lo + BRACKET_GUARD * (hi - lo), hi - BRACKET_GUARD * (hi - lo)))
        points.append((step, *value_and_gradient(step)))
        if abs(step - x) < xtol:
            return iteration + 1
    return maxiter


def cubic_minimizer(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    """The minimiser of the cubic through (x, f, f') at a and b (Nocedal & Wright eq.
    3.59), or the secant root of f' where that cubic has none."""
    (xa, fa, ga), (xb, fb, gb) = a, b
    d1 = ga + gb - 3 * (fa - fb) / (xa - xb)
    root = d1 * d1 - ga * gb
    if root < 0 or gb - ga + 2 * np.sign(xb - xa) * np.sqrt(root) == 0:
        return xa - ga * (xb - xa) / (gb - ga) if gb != ga else 0.5 * (xa + xb)
    d2 = np.sign(xb - xa) * np.sqrt(root)
    return float(xb - (xb - xa) * (gb + d2 - d1) / (gb - ga + 2 * d2))


class Settle:
    """An L-BFGS-B callback that ends the run once a step moves every coordinate by less
    than ``xtol`` (more digits would cost solves, not accuracy); counts the iterations."""

    def __init__(self, s0, xtol):
        self.s, self.xtol, self.iterations = np.array(s0, float), np.asarray(xtol), 0

    def __call__(self, intermediate_result):
        self.iterations += 1
        settled = np.all(np.abs(intermediate_result.x - self.s) < self.xtol)
        self.s = intermediate_result.x.copy()
        if settled:
            raise StopIteration


def surrogate_scan(surrogate: SurrogateProfile, points) -> tuple[np.ndarray, list[float]]:
    """Phi* on the surrogate at each scan point (dense algebra, no factorization): the
    best of them and of the full solves, in s, and the values scanned."""
    profile, params = surrogate.profile, surrogate.params
    best_s, best = params.to_s(profile.best_theta()), profile.best().value
    values = []
    for theta in points:
        values.append(surrogate.value_and_gradient(params.to_s(theta))[0])
        log.info(f"  scan  {params.describe(theta)}  Phi* ~ {values[-1]:.6e}  (surrogate)")
        if values[-1] < best:
            best_s, best = params.to_s(theta), values[-1]
    return best_s, values


def minimize_on_surrogate(profile: Profile, surrogate: SurrogateProfile, xtol: np.ndarray, maxiter: int,
                          start=None) -> int:
    """Optimise s on the surrogate (from ``start``, then from the best full solve), solve
    its optimum in full (a new snapshot), repeat until the optimum lands where a full
    solve already is. Returns the rounds."""
    params = profile.params
    log.info(f"outer L-BFGS-B on the reduced-basis response in the materials ({profile.surrogate.size} directions)")

    def scaled(s, scale):
        value, gradient = surrogate.value_and_gradient(s)
        return value / scale, gradient / scale

    for rounds in range(1, maxiter + 1):
        x0 = start if start is not None and rounds == 1 else params.to_s(profile.best_theta())
        # Each evaluation is a whole inner fit, exact only to the inner tolerance: stop once
        # a step moves every constant by less than xtol / 10, not chase digits of Phi*.
        res = minimize(scaled, x0, args=(max(profile.best().value, 1e-300),),
                       jac=True, method="L-BFGS-B", bounds=params.s_bounds(), callback=Settle(x0, 0.1 * xtol),
                       options={"maxiter": 100, "ftol": 1e-14, "gtol": 1e-10})
        theta = params.to_theta(res.x)
        log.info(f"  surrogate optimum {params.describe(theta)}  (equation residual "
                 f"{profile.surrogate.residual(theta):.1e}, {res.nfev} evaluations)")
        if any(np.all(np.abs(res.x - s) < xtol) for s, _, _ in profile.solved):
            return rounds
        profile.solve(theta, "outer")
    return maxiter
