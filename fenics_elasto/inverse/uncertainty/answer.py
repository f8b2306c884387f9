"""How sure the answer is: its posterior, its linearisation where the inner solver kept none,
and the profile-likelihood interval of a single constant.
"""

from __future__ import annotations

import time

import numpy as np

from fenics_elasto.inverse.inner import InnerResult
from fenics_elasto.inverse.linearisation import linearise_profiled
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.inverse.profile import Profile, SurrogateProfile
from fenics_elasto.inverse.uncertainty.posterior import Posterior, posterior_at
from fenics_elasto.inverse.uncertainty.profile_interval import (JITTER_NOISE, JITTER_STARTS, Z95, jitter_noise,
                                                                profile_interval, threshold, untrusted_sides)
from fenics_elasto.util.logs import log

PROFILE_DOFS = 60_000  # without bases, the profile interval's few full solves only below this size


class AnswerUncertainty:
    """The uncertainty of an estimate's answer, from the profile of Phi* it solved.

    ``warnings`` collects what it found worth saying; ``undetermined`` the constants
    already said to be undetermined (identifiability.check_identifiable), so none is
    said twice."""

    def __init__(self, problem: InverseProblem, profile: Profile, surrogate: SurrogateProfile | None,
                 inner_name: str, anchor: float):
        self.problem = problem
        self.params = problem.params
        self.profile = profile
        self.surrogate = surrogate
        self.inner_name = inner_name
        self.anchor = anchor
        self.warnings: list[str] = []
        self.undetermined: set[str] = set()

    def posterior(self, result: InnerResult | None = None) -> Posterior | None:
        noise = self.problem.states.noise  # [target] noise, or the states' smallest (states.py)
        misfit = self.problem.misfit
        floors = {"the target's roughness": misfit.roughness(), "the landmarks' stated noise": misfit.stated_floor()}
        floor_from = max(floors, key=floors.__getitem__)
        floor = floors[floor_from] if noise is None else 0.0
        return posterior_at(self.profile, result or self.profile.best(), noise, floor, floor_from)

    def linearise_answer(self, theta, best: InnerResult) -> None:
        """The L-BFGS inner solvers keep no response of the controls: the answer's
        Linearisation with the controls profiled out by LSQR (functional.linearise_profiled:
        two solves per step on the answer's factorization, less than one inner fit's cost)."""
        if self.profile.linearisation(best) is not None:
            return
        forward = self.problem.forward
        start, solves = time.perf_counter(), (forward.forward_solves, forward.adjoint_solves)
        self.profile.linearisations[id(best)] = linearise_profiled(self.problem, theta, best, self.anchor)
        log.info(f"answer linearised, the force space profiled out by LSQR ({forward.forward_solves - solves[0]} "
                 f"forward and {forward.adjoint_solves - solves[1]} adjoint solves, {time.perf_counter() - start:.1f} s)")

    def profile_likelihood_interval(self, post: Posterior) -> None:
        """The profile-likelihood 95 % interval of a single estimated constant, in place
        of the Laplace one: on the surrogate (dense algebra) with bases, by full solves on
        small meshes (PROFILE_DOFS), not at all on big ones without bases (each value a
        factorization and an inner fit -- nor with the L-BFGS inner solvers, whose fits
        take tens of solves each). Where Phi* is jagged on the surrogate, the inner fit at the answer
        is re-run from the other fits met on the way: minima that far apart in Phi* raise
        the interval's threshold by as much (posterior.jitter_noise)."""
        full_solves = self.surrogate is None
        if len(self.params) != 1 or (full_solves and (self.problem.model.dofs.num_dofs > PROFILE_DOFS
                                                      or self.inner_name != "gauss-newton")):
            return
        fits = []  # (s, fit): the surrogate's inner optima met along the way, starts for the spread
        known = []  # (s, Phi*) the estimate's own full solves computed: the same function, already at hand
        surrogate = self.surrogate
        if surrogate is not None:
            def value(s):
                fits.append((s, surrogate.fit(np.atleast_1d(s))))
                return fits[-1][1].value
        else:
            value = lambda s: self.profile.solve(self.params.to_theta(np.atleast_1d(s)), "ci").value  # noqa: E731
            known = [(float(s[0]), result.value) for s, result, _ in self.profile.solved]
        s_hat, std, bounds = float(post.s[0]), float(post.laplace_std_s[0]), self.params.s_bounds()[0]
        ends = profile_interval(value, s_hat, std, post.noise_std, bounds, known=known)
        ends, jagged = untrusted_sides(ends, s_hat, std, bounds)
        # A target rough enough to be smoothed may have an inner problem with several minima
        # though the few profile values met none: a phantom target at 2 % noise read E = 63.5,
        # 54.7-73.2 (truth 50), where the same draw on another source mesh showed a jagged side
        # and, checked, read 29-242.
        rough = self.problem.misfit.smoothing() is not None
        if (jagged or rough) and fits:
            ends, jagged = self._allow_for_inner_minima(post, fits, ends, jagged)
        if jagged:
            self.warnings.append(f"{self.params.labels[0]}: Phi* is not smooth beside the answer (a rough target, or "
                                 "an inner fit with several minima): the interval is the Laplace one on that side")
        post.set_profile(ends, bounds)
        for label, reason in post.undetermined(self.params.s_bounds(), seen=self.params.labels).items():
            if label in self.undetermined:
                continue  # said after the scan already
            self.warnings.append(f"undetermined: {label}: {reason}, whatever the start scan showed: any value "
                                 "within them fits the data (landmarks, reduced bases or a fixed reference E would "
                                 "determine it)")

    def _allow_for_inner_minima(self, post: Posterior, fits, ends, jagged: bool) -> tuple[tuple[float, float], bool]:
        """A jagged Phi* on the surrogate: re-fit at the answer from fits met on the way
        (those at a bound of s aside), JITTER_STARTS of them spread from the lowest s to
        the highest (each start is a
        whole inner fit; the nearest four alone all fell in one basin on the phantom at
        2 % noise: spread 0.0004 where all 16 found 0.03). If their minima lie far apart,
        follow the lowest one's branch in s (a fit warm-started from it: continuous in s,
        unlike cold fits that hop between minima) to where it rises above the noise's
        threshold plus that spread. Returns the interval's ends and whether Phi* is
        still to be reported as ``jagged`` (a spread too small to matter)."""
        surrogate = self.surrogate
        assert surrogate is not None  # fits on the surrogate are what was jagged
        s_hat, std, bounds = float(post.s[0]), float(post.laplace_std_s[0]), self.params.s_bounds()[0]
        start = time.perf_counter()
        # Not from a fit at a bound of s: the profile reached it only because the interval
        # search stops there, and its controls are far from any the data allow. On the
        # noisy pelvis with 4 fiducials, the fit at E = 2 (Phi* 0.34 against 0.195) ended
        # 8.0e-3 above the six others (within 9.5e-4) and alone made sigma 16.6 instead of 6.4.
        met = sorted(((s, fit) for s, fit in fits if s != s_hat and not np.isclose(s, bounds).any()),
                     key=lambda item: item[0])
        pick = np.unique(np.linspace(0, len(met) - 1, min(JITTER_STARTS, len(met))).round().astype(int))
        starts = [met[i][1].q for i in pick]
        cold = next((fit for s, fit in fits if s == s_hat), None)  # the profile interval's own first fit
        post.inner_spread, q_best = surrogate.inner_spread(np.atleast_1d(s_hat), starts, cold)
        noise = jitter_noise(post.noise_std, post.inner_spread)
        log.info(f"inner fits at the answer from {len(starts) + 1} starts end up to {post.inner_spread:.3g} apart "
                 f"in Phi* ({time.perf_counter() - start:.1f} s)")
        if noise <= JITTER_NOISE * post.noise_std:
            return ends, jagged

        def branch(s):
            return surrogate.fit(np.atleast_1d(s), q_best).value

        reach = Z95 * std
        start = time.perf_counter()
        low, high = profile_interval(branch, s_hat, std, noise, bounds)
        log.info(f"interval on the lowest minimum's branch, threshold raised by the spread "
                 f"({time.perf_counter() - start:.1f} s)")
        # The cause only where the target was smoothed for its roughness: an outside check's
        # exact, smooth targets (a liver pressed by a probe) read "a target rougher than its
        # sampling" too, which sent the user to look for noise that was not there.
        cause = ": a target rougher than its sampling" if self.problem.misfit.smoothing() is not None else ""
        self.warnings.append(
            f"{self.params.labels[0]}: the inner fit ends in minima up to {post.inner_spread:.3g} apart in Phi* from "
            f"different starts ({post.inner_spread / threshold(post.noise_std):.2g}x what the noise moves in "
            f"a 95 % interval{cause}): the interval allows for them")
        return (max(min(low, s_hat - reach), bounds[0]), min(max(high, s_hat + reach), bounds[1])), False

