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
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from fenics_elasto.util.logs import log
from fenics_elasto.inverse.inner import GaussNewton, InnerResult
from fenics_elasto.util.interrupts import check_interrupt
from fenics_elasto.inverse.refinement import DERIVATIVE_TOL, refine
from fenics_elasto.inverse.linearisation import Linearisation, linearise
from fenics_elasto.model.responses import response_block, response_sensitivities


def envelope_gradient(misfit, fit, dJ: np.ndarray) -> np.ndarray:
    """dPhi*/dtheta of a Gauss-Newton fit on a response J with derivatives dJ: the
    partial derivative at the inner optimum (the prior does not depend on theta)."""
    g = misfit.gradient(fit.residual)
    return np.array([np.sum(g * (dJk @ fit.q)) for dJk in dJ])


# The stage of a solve whose inner fit stopped at inner_tol, not at the tolerance the
# optimum's fits keep: the surrogate path's first solve, which only seeds the scan (its
# value, beside the surrogate's, places the bracket and says whether the data determine the
# materials). It never ends the outer loop nor answers for a later solve at its value, so
# the answer is always a tight fit. The default phantom's rank-240 start: 77 -> 15
# iterations (5.4 -> 1.1 s), Phi* 1e-6 higher, E the same to the bit.
LOOSE = "start"

# Where the full force space's fits stop at their limit, more iterations are the slow lever
# (a user's kidney: 100 s a material value, 400 iterations, not converged): said once as it
# happens, and in the run's warning.
NO_BASES_REMEDY = ", or give reduced bases (`fenics-elasto train`), whose fits take a few Gauss-Newton steps"


def _say_solved(stage: str, where: str, result: InnerResult, first_at_limit: bool) -> None:
    """The progress line of a solve; the first fit at its limit without bases says what helps."""
    log.info(f"  {stage:5s} {where}  Phi* = {result.value:.6e}  "
             f"({result.iterations} inner iterations{'' if result.converged else ', NOT converged'})")
    if first_at_limit:
        log.info(f"  note: the inner fit stopped at its iteration limit: raise optimizer.inner_maxiter{NO_BASES_REMEDY}")


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
        self.earlier: list[tuple[np.ndarray, InnerResult, str]] = []  # solved on a misfit weighed otherwise
        self.linearisations: dict[int, Linearisation] = {}  # id(result) -> at that solve (Gauss-Newton)
        self.inner_iterations = 0
        self.unconverged = 0  # solves that stopped at the inner iteration limit, the interval's ("ci") aside

    # --- solving

    def response(self, theta) -> np.ndarray:
        """J(theta) in full (one factorization); a snapshot for the surrogate."""
        if self.surrogate is None:
            return self.problem.response(theta, self.basis)
        X = response_block(self.problem.forward, theta, self.basis)
        order = 2 if len(self.params) <= 2 else 1  # second order: 1 + n + n(n+1)/2 fields per mode
        J = self.problem.states.stack_controls(self.problem.observation.rows(X))
        self.surrogate.add(theta, X, response_sensitivities(self.problem.forward, theta, X, order))  # over X's memory
        return J

    def surrogate_response(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(J, dJ/dtheta) on the surrogate, every state's rows and controls."""
        J, dJ = self.surrogate.response(theta)
        if self.problem.states.count == 1:
            return J, dJ
        return self.problem.states.stack_controls(J), np.stack([self.problem.states.stack_controls(dJk) for dJk in dJ])

    def known(self, s) -> InnerResult | None:
        for s_seen, result, stage in self.solved:
            if stage != LOOSE and np.all(np.abs(np.asarray(s) - s_seen) < self.same_within):
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
                dy = self.problem.field_rows(theta, result.evaluation)
            self.linearisations[id(result)] = linearise(self.problem, theta, result, result.response, dy, self.inner.alpha)
            result.response = None  # kept in the linearisation only
        _say_solved(stage, self.params.describe(theta), result, first_at_limit=self.basis is None
                    and self.unconverged == 1 and not result.converged and stage != "ci")
        return result

    def _on_refined_surrogate(self, theta) -> tuple[InnerResult, np.ndarray] | None:
        """Inside ``borrowing()`` (an estimate's solves after its first) and the factors
        of a nearby material value at hand: the inner optimum at theta and the observed
        positions' derivative in theta at fixed controls, both from the surrogate refined
        at theta on those factors to a relative equation residual of REFINE_TOL
        (MaterialSurrogate.refine) -- what a full solve gives, without its factorization.
        None where it cannot, or where that would cost more than a factorization."""
        forward = self.problem.forward
        if self.surrogate is None or not forward.borrows:
            return None
        factors = forward.model.solvers.closest(forward.coefficients(theta)[0], forward.clamped_boundary)
        steps = refine(self.surrogate, theta, factors, budget=factors.seconds) if factors is not None else None
        if steps is None:
            return None
        first = self.inner.fit(self.surrogate_response(theta)[0])
        controls = np.stack(self.problem.states.split(first.q), axis=1)  # each state's
        more = refine(self.surrogate, theta, factors, controls, DERIVATIVE_TOL)  # the derivative along the optimum's controls
        if more is None:
            return None
        log.info(f"  surrogate refined at {self.params.describe(theta)} on nearby factors ({steps} + {more} block back-"
                 f"solves, equation residual {self.surrogate.residuals.first(theta):.1e} -> "
                 f"{self.surrogate.residuals.modes(theta):.1e}): no factorization")
        J, dJ = self.surrogate_response(theta)
        # The same optimum on the space the derivatives grew (J moved by the refinement's tolerance):
        # from the first fit's controls, a few iterations, not a second fit from q0 (rank 240: 67 -> 2).
        fit = self.inner.fit(J, first.q)
        fields, owned, modes = [], self.surrogate.G.shape[0], self.surrogate.fields(theta)
        for q in self.problem.states.split(fit.q):
            u = self.problem.model.dofs.function()
            u.x.array[:owned] = modes @ q
            u.x.scatter_forward()
            fields.append(u)
        evaluation = self.problem.evaluate_field(theta, fields)
        evaluation.grad_theta = envelope_gradient(self.inner.misfit, fit, dJ)
        dy = np.stack([dJk @ fit.q for dJk in dJ], axis=-1)
        return InnerResult(fit.q, evaluation, first.iterations + fit.iterations, fit.converged, fit.prior, J), dy

    def start_over(self, theta, stage: str) -> InnerResult:
        """Phi* solved anew at theta after the misfit's weights changed, the values before set
        aside (another functional's); on an interrupt before that solve ends, they stay."""
        earlier, self.solved = self.solved, []
        try:
            result = self.solve(theta, stage)
        except BaseException:
            self.solved = earlier
            raise
        self.earlier += earlier
        return result

    @contextmanager
    def borrowing(self):
        """Solves in the block borrow the factors of a nearby material value where they
        can (forward.borrowing): after the first solve, whose factors the surrogate's
        refinement works on."""
        with self.problem.forward.borrowing():
            yield

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

    @property
    def every_solve(self) -> list[tuple[np.ndarray, InnerResult, str]]:  # in order, start_over's set aside first
        return self.earlier + self.solved

    def history(self) -> list[dict]:
        return [{"stage": stage, "theta": list(map(float, self.params.to_theta(s))), "phi": result.value,
                 "misfit": result.evaluation.phi, "inner": result.iterations}
                for s, result, stage in self.every_solve]


class SurrogateProfile:
    """Phi*(theta) on the reduced-basis response in the materials: dense algebra only."""

    def __init__(self, profile: Profile):
        self.profile = profile
        self.params = profile.params
        self.fit_inner: GaussNewton = profile.inner
        self.evaluations = 0

    def fit(self, s, start: np.ndarray | None = None):
        """The inner fit (a LinearFit) at s on the surrogate, from q0 or ``start``."""
        J, _ = self.response(self.params.to_theta(s))
        return self.fit_inner.fit(J, start)

    def response(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(J, dJ/dtheta) on the surrogate."""
        return self.profile.surrogate_response(theta)

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
        J, dJ = self.response(theta)
        fit = self.fit_inner.fit(J)
        self.evaluations += 1
        return fit.value, envelope_gradient(self.fit_inner.misfit, fit, dJ) * self.params.dtheta_ds(theta)


class FewerModes(SurrogateProfile):
    """Phi*(theta) on the surrogate with only some of each state's boundary modes, its
    ``columns`` of the bases: where the answer goes with fewer bases (report.fit_of_bases:
    the leading half, the bases being ordered by the energy they hold, to tell whether
    it has settled in the rank; the trained modes without the data's own wall motion).
    The prior's weight is the full fit's; its anchor, the surface-matched start, keeps
    those modes. Its fits stop at ``tol`` (the inner solver's by default)."""

    def __init__(self, profile: Profile, columns: np.ndarray, tol: float | None = None):
        super().__init__(profile)
        full = profile.basis.shape[1]
        self.keep = np.concatenate([state * full + columns for state in range(profile.problem.states.count)])
        inner = profile.inner
        self.fit_inner = GaussNewton(inner.problem, inner.q0[self.keep], inner.anchor, inner.maxiter,
                                     inner.tol if tol is None else tol)
        self.fit_inner.alpha = inner.alpha

    def response(self, theta) -> tuple[np.ndarray, np.ndarray]:
        J, dJ = self.profile.surrogate_response(theta)
        return J[..., self.keep], dJ[..., self.keep]


class WeakerPrior(SurrogateProfile):
    """Phi*(theta) with the Gauss-Newton prior's weight alpha divided by ``factor``: where
    the answer goes with less of what placed the walls' sliding along their target
    (report.prior_shift). On the surrogate where there is one, else on full
    responses (a factorization each: the full force space of a small problem). Its fits
    stop at ``tol``."""

    def __init__(self, profile: Profile, factor: float, tol: float):
        super().__init__(profile)
        inner = profile.inner
        self.fit_inner = GaussNewton(inner.problem, inner.q0, inner.anchor / factor, inner.maxiter, tol)
        self.fit_inner.alpha = inner.alpha / factor

    def value_and_gradient(self, s) -> tuple[float, np.ndarray]:
        if self.profile.surrogate is not None:
            return super().value_and_gradient(s)
        fit = self.fit_inner.fit(self.profile.problem.response(self.params.to_theta(s), self.profile.basis))
        self.evaluations += 1
        return fit.value, np.full(len(s), np.nan)  # values only (report.prior_shift)
