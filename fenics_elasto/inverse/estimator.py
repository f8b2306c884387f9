"""The nested estimate (docs/method.md §5): materials outside, boundary controls inside.

The outer loop minimises the profile Phi*(theta) (functional.py) over the estimated
constants in s = (log E, nu) with bounded L-BFGS-B and the envelope gradient (one
constant whose minimum the scan brackets, on a target that is not rough: cubic steps
inside the bracket). Start:
the boundary controls from iterative surface matching (matching.py), the materials
from a scan over their bounds. With reduced bases (and ``surrogate``, the default) the
outer loop runs on the reduced-basis response in the materials and solves only its
optimum in full, until the optimum lands where a full solve already is. The result is
always the best full solve.

Before any solve the set-up is checked: a target that does not overlap the matched
surface, every E estimated (only ratios are identifiable), and a full force space that
can fit the surfaces for any material (``check_determined``) end with one line.
After a reduced estimate ``bases_fit`` says how much of the wall motion the bases
can represent; bases that kept little of their held-out examples are warned about.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.inverse.profile import (Profile, SurrogateProfile, linearise_profiled, minimize_on_surrogate,
    minimize_profile, surrogate_scan)
from fenics_elasto.util.logs import log
from fenics_elasto.inverse.inner import GaussNewton, InnerResult, LBFGS
from fenics_elasto.util.interrupts import Interrupted
from fenics_elasto.geometry.matching import match_surface
from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.inverse.objective import Evaluation, InverseProblem
from fenics_elasto.inverse.uncertainty.posterior import (JITTER_NOISE, JITTER_STARTS, Z95, Posterior, jitter_noise,
    posterior_at, profile_interval, scan_excludes, scan_sees, target_offset, threshold, untrusted_sides)
from fenics_elasto.inverse.reduction.bases import bases_fit, missing_wall_motion, reach_warning
from fenics_elasto.inverse.surrogate import MaterialSurrogate


@dataclass
class Options:
    inner: str = "auto"
    inner_maxiter: int = 400
    outer_maxiter: int = 40
    outer_xtol: float = 1e-3  # the outer loop stops once a step moves log E by less (nu: a tenth of it)
    scan: int = 5  # material values per estimated constant in the initial scan (1: the initial values only)
    inner_tol: float = 1e-6  # relative decrease of Phi that ends an L-BFGS inner loop (Gauss-Newton: its square)
    full_gn_limit: int = 1500  # largest full force space for which "auto" picks Gauss-Newton
    anchor: float = 1e-4  # Gauss-Newton prior towards the surface-matched start, relative to the data curvature
    surrogate: bool = True  # reduced bases: outer loop on the reduced-basis response in the materials
    allow_undetermined: bool = False  # run a set-up the data cannot determine (with a warning)

    @classmethod
    def from_scene(cls, scene) -> Options:
        """The scene's [optimizer] table (checked and completed by config.py)."""
        return cls(**scene.config["optimizer"])


@dataclass
class EstimateResult:
    """What an estimate found: the materials, the field, the forces, and result.json's record."""

    theta: np.ndarray
    labels: list[str]
    u: object  # dolfinx Function
    forces: np.ndarray  # recovered nodal forces of the loaded nodes, flat
    evaluation: Evaluation
    record: dict = field(default_factory=dict)  # result.json

    def __getitem__(self, key):
        return self.record[key]

    @property
    def estimated(self) -> dict[str, float]:
        return dict(zip(self.labels, map(float, self.theta)))

    @property
    def materials(self) -> dict:
        return self.record["materials"]

    @property
    def warnings(self) -> list[str]:
        return self.record["warnings"]


# --------------------------------------------------------------------------- checks


def check_overlap(problem: InverseProblem) -> float:
    """Refuse a target that does not lie on the observed surface; return Phi at u = 0."""
    y = problem.observation.points
    residual = problem.residual_at_rest
    observed = problem.misfit.weights > 0
    size = float(np.linalg.norm(np.ptp(y, axis=0)))
    distance = float(np.sqrt(np.mean(np.sum(residual[observed] ** 2, axis=1)))) if observed.any() else 0.0
    require(distance < 0.25 * size,
            f"{problem.scene.path}: the target does not overlap the matched surface "
            f"(rms distance {distance:.3g} vs matched size {size:.3g}); is it in the same units and frame?")
    return problem.misfit.cost(residual)


def check_determined(problem: InverseProblem, basis, options: Options, inner: str) -> str | None:
    """Refuse a full force space that can fit the data for any material; None if fine.

    Only for the L-BFGS inner solvers: with Gauss-Newton the linearisation after the
    scan tells (``Estimator.check_identifiable``), and counting is too strict where
    elasticity smooths a few more boundary directions than constraints away. Counting,
    generically: the loaded nodes' displacements are the controls; each
    matched surface point asks one (normal) constraint, each landmark gdim. A loaded
    node that is itself matched meets its own constraint, leaving gdim - 1 free
    directions; every other loaded node leaves gdim. When the free directions are at
    least the remaining constraints plus the materials, the target is fitted exactly
    whatever the materials are (walls sliding along their target, forces scaling).
    """
    if basis is not None or inner == "gauss-newton":
        return None
    misfit, observation = problem.misfit, problem.observation
    surface = misfit.surface_rows()
    surface = surface[misfit.weights[surface] > 0]
    node_is_loaded = _nodes_in(problem, observation.nodes, problem.loaded)
    own = int(np.sum(node_is_loaded[surface[surface < observation.node_count]]))
    free = problem.force_dofs - own
    constraints = len(surface) - own + problem.gdim * len(misfit.landmark_rows()) + len(problem.params)
    if free < constraints:
        return None
    message = (f"{problem.scene.path}: the full force space cannot determine {', '.join(problem.params.labels)}: "
               f"its {free} free boundary directions exceed the {constraints} the target constrains, so every "
               f"material fits it exactly; give reduced bases ([reduction], e.g. from `fenics-elasto train "
               f"{problem.scene.path.name} --synthetic 40 --rank 20 --out bases.npz`) or landmarks inside the body "
               f"([target] landmarks), or set optimizer.allow_undetermined = true")
    if not options.allow_undetermined:
        raise UserError(message)
    return "undetermined set-up (allow_undetermined = true): " + message.split(": ", 1)[1].split("; give")[0]


def _nodes_in(problem, nodes, other) -> np.ndarray:
    """For each node of ``nodes`` (canonical order): is it a node of ``other``?"""
    tree = cKDTree(other.gather(other.coords)) if other.total else None
    points = nodes.gather(nodes.coords)
    if tree is None or not len(points):
        return np.zeros(len(points), bool)
    gap, _ = tree.query(points)
    return gap < 1e-12 * max(1.0, float(np.ptp(points)))


# --------------------------------------------------------------------------- the estimate


def choose_inner(problem: InverseProblem, options: Options, basis) -> str:
    """Gauss-Newton with bases or a small full force space; L-BFGS otherwise ("auto")."""
    inner = options.inner
    if inner == "auto":
        small = problem.force_dofs <= options.full_gn_limit
        inner = "gauss-newton" if basis is not None or small else "lbfgs"
    require(basis is None or inner == "gauss-newton", "reduced bases need optimizer.inner = 'gauss-newton'")
    return inner


def surface_matched_start(problem: InverseProblem) -> np.ndarray:
    """The loaded nodes' displacement that surface matching finds (flat): matched nodes
    moved onto their target surfaces (landmarks only: each takes its nearest landmark's
    displacement); loaded nodes that are not matched stay put."""
    term = problem.misfit.terms[0]
    nodes = problem.matched_coords
    if isinstance(term, SurfaceTerm):
        u = match_surface(nodes, problem.node_groups(), term)
    else:
        rows = problem.misfit.landmark_rows()
        moved = problem.misfit.terms[-1].points - problem.observation.points[rows]
        u = moved[cKDTree(problem.observation.points[rows]).query(nodes)[1]]
    return problem.forward.on_loaded(problem.observation.node_field(u))



class Estimator:
    """The nested optimisation of one InverseProblem, optionally in a reduced basis W."""

    def __init__(self, problem: InverseProblem, options: Options, basis=None):
        self.problem = problem
        self.params = problem.params
        self.options = options
        self.basis = basis  # W (force_dofs x r) or None: the full space
        self.inner_name = choose_inner(problem, options, basis)
        self.d0 = surface_matched_start(problem)
        surrogate = MaterialSurrogate(problem, basis) if basis is not None and options.surrogate else None
        self.profile = Profile(problem, self._inner(), basis, surrogate, same_within=1e-3 * options.outer_xtol)
        self.surrogate = SurrogateProfile(self.profile) if surrogate is not None else None
        self.outer_iterations = 0
        self.warnings: list[str] = []
        self.undetermined: set[str] = set()  # constants found undetermined and run anyway (allow_undetermined)

    def _inner(self):
        o = self.options
        if self.inner_name == "gauss-newton":
            q0 = self.d0 if self.basis is None else self.basis.T @ self.d0
            return GaussNewton(self.problem, q0, o.anchor, o.inner_maxiter, o.inner_tol**2)
        inner = LBFGS(self.problem, self.inner_name == "lbfgs-forces", o.inner_maxiter, o.inner_tol)
        self.start = self.initial_controls(self.params.initial)
        inner.control_scale = max(float(np.sqrt(np.mean(self.start**2))), 1e-300)
        inner.phi_scale = max(self.problem.evaluate_displacement(self.params.initial, self.d0).phi, 1e-300)
        return inner

    # --- start

    def initial_controls(self, theta) -> np.ndarray:
        if self.inner_name == "lbfgs-forces":
            return self.problem.forward.reaction_forces(theta, self.problem.forward.from_boundary(theta, self.d0))
        return self.d0 if self.basis is None else self.basis.T @ self.d0

    # --- the loop

    def run(self) -> None:
        """Scan, check the data determine the materials, minimise Phi*, polish."""
        n = self.options.scan if len(self.params) == 1 else max(2, min(self.options.scan, 3))
        points = self.params.scan(n) if self.options.scan > 1 else []  # scan = 1: the initial values only
        xtol = self.options.outer_xtol * np.where(self.params.is_E, 1.0, 0.1)
        if self.surrogate is None:
            points = [self.params.initial] + points
            log.info(f"scan of {len(points)} material values (start: surface matching; inner: {self.inner_name})")
            for theta in points:
                self.profile.solve(theta, "scan", self._start_for(theta))
            self.check_identifiable([result.value for _, result, _ in self.profile.solved])
            self.outer_iterations = minimize_profile(self.profile, xtol, self.options.outer_maxiter,
                                                     smooth=not self.problem.misfit.rough())
        else:  # one factorization at the initial values; the scan on the surrogate it seeds
            log.info(f"initial values solved in full with their sensitivities, then a scan of {len(points)} "
                     f"material values on the surrogate (inner: {self.inner_name})")
            self.profile.solve(self.params.initial, "start")
            self.problem.forward.borrow = True  # later solves on its factors where near enough (Profile.response)
            start, scanned = surrogate_scan(self.surrogate, points)
            self.check_identifiable([self.profile.best().value] + scanned)
            self.outer_iterations = minimize_on_surrogate(self.profile, self.surrogate, xtol, self.options.outer_maxiter,
                                                          start)
        self.polish()

    def posterior(self, result: InnerResult | None = None) -> Posterior | None:
        noise = (self.problem.scene.config["target"] or {}).get("noise")
        floor = self.problem.misfit.roughness() if noise is None else 0.0
        return posterior_at(self.profile, result or self.profile.best(), noise, floor)

    def linearise_answer(self, theta, best: InnerResult) -> None:
        """The L-BFGS inner solvers keep no response of the controls: the answer's
        Linearisation with the controls profiled out by LSQR (functional.linearise_profiled:
        two solves per step on the answer's factorization, less than one inner fit's cost)."""
        if self.profile.linearisation(best) is not None:
            return
        forward = self.problem.forward
        start, solves = time.perf_counter(), (forward.forward_solves, forward.adjoint_solves)
        self.profile.linearisations[id(best)] = linearise_profiled(self.problem, theta, best, self.options.anchor)
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
        if self.surrogate is not None:
            def value(s):
                fits.append((s, self.surrogate.fit(np.atleast_1d(s))))
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
        """A jagged Phi* on the surrogate: re-fit at the answer from fits met on the way,
        JITTER_STARTS of them spread from the lowest s to the highest (each start is a
        whole inner fit; the nearest four alone all fell in one basin on the phantom at
        2 % noise: spread 0.0004 where all 16 found 0.03). If their minima lie far apart,
        follow the lowest one's branch in s (a fit warm-started from it: continuous in s,
        unlike cold fits that hop between minima) to where it rises above the noise's
        threshold plus that spread. Returns the interval's ends and whether Phi* is
        still to be reported as ``jagged`` (a spread too small to matter)."""
        s_hat, std, bounds = float(post.s[0]), float(post.laplace_std_s[0]), self.params.s_bounds()[0]
        start = time.perf_counter()
        met = sorted(((s, fit) for s, fit in fits if s != s_hat), key=lambda item: item[0])
        pick = np.unique(np.linspace(0, len(met) - 1, min(JITTER_STARTS, len(met))).round().astype(int))
        starts = [met[i][1].q for i in pick]
        cold = next((fit for s, fit in fits if s == s_hat), None)  # the profile interval's own first fit
        post.inner_spread, q_best = self.surrogate.inner_spread(np.atleast_1d(s_hat), starts, cold)
        noise = jitter_noise(post.noise_std, post.inner_spread)
        log.info(f"inner fits at the answer from {len(starts) + 1} starts end up to {post.inner_spread:.3g} apart "
                 f"in Phi* ({time.perf_counter() - start:.1f} s)")
        if noise <= JITTER_NOISE * post.noise_std:
            return ends, jagged

        def branch(s):
            return self.surrogate.fit(np.atleast_1d(s), q_best).value

        reach = Z95 * std
        start = time.perf_counter()
        low, high = profile_interval(branch, s_hat, std, noise, bounds)
        log.info(f"interval on the lowest minimum's branch, threshold raised by the spread "
                 f"({time.perf_counter() - start:.1f} s)")
        self.warnings.append(
            f"{self.params.labels[0]}: the inner fit ends in minima up to {post.inner_spread:.3g} apart in Phi* from "
            f"different starts ({post.inner_spread / threshold(post.noise_std):.2g}x what the noise moves in "
            "a 95 % interval: a target rougher than its sampling): the interval allows for them")
        return (max(min(low, s_hat - reach), bounds[0]), min(max(high, s_hat + reach), bounds[1])), False

    def check_identifiable(self, scanned: list[float]) -> None:
        """After the scan: a constant the data do not determine (at the best full solve:
        its 95 % interval spans its bounds, or the controls mimic nearly all of its
        effect) ends the run now, not after it; so does a single constant whose Phi* over
        the scan (``scanned``) stays within the noise's 95 % threshold everywhere, though
        the Laplace interval at one value looked narrower. A single constant the controls
        mimic locally but whose Phi* over the scan clearly rises is seen by the data: it
        runs, with a warning that its answer rests on the rest of its effect."""
        post = self.posterior()
        undetermined = {} if post is None else post.undetermined(self.params.s_bounds())
        if (post is not None and not undetermined and len(self.params) == 1 and self.options.scan > 1
                and not scan_excludes(scanned, post.noise_std)):
            undetermined = {self.params.labels[0]: "Phi* over the start scan stays within the noise's 95 % threshold: "
                                                   "none of the values scanned across its bounds is excluded"}
        if len(undetermined) == 1 == len(self.params) and post.mimicked()[0]:
            phi_still = self.problem.misfit.cost(self.problem.residual_at_rest)
            if scan_sees(scanned, post.noise_std, phi_still):
                label, best = self.params.labels[0], min(scanned)
                self.warnings.append(
                    f"{label}: the boundary forces can mimic {100 * (1 - post.separable[0]):.1f} % of its effect on the "
                    f"data, yet Phi* over the start scan rises {(max(scanned) - best) / max(best, 1e-300):.3g}x above "
                    "its minimum: the data see it through the rest, where a bias of the bases or the source mesh "
                    "weighs more than noise (more training examples, landmarks, estimate --check-mesh)")
                undetermined = post.undetermined(self.params.s_bounds(), seen=[label])
        if not undetermined:
            return
        why = "; ".join(f"{label}: {reason}" for label, reason in undetermined.items())
        message = (f"{self.problem.scene.path}: the data do not determine {', '.join(undetermined)} (at the best "
                   f"value solved, {why}); fix it, or add data that see it (reduced bases, landmarks inside the body, more "
                   f"matched surfaces), or set optimizer.allow_undetermined = true")
        if not self.options.allow_undetermined:
            raise UserError(message)
        self.undetermined.update(undetermined)
        self.warnings.append("undetermined (allow_undetermined = true): " + message.split(": ", 1)[1].split("; fix")[0])

    def close(self) -> None:
        """Whatever happened: later solves of this problem factorize again; the surrogate's
        own matrices go."""
        self.problem.forward.borrow = False
        if self.profile.surrogate is not None:
            self.profile.surrogate.destroy()

    def _start_for(self, theta):
        return None if self.inner_name == "gauss-newton" else self.initial_controls(theta)

    def polish(self) -> None:
        """An L-BFGS inner solve warm-started along the path may stop above the inner
        optimum: re-solve the best material value cold, from the surface-matched start."""
        if self.inner_name == "gauss-newton":
            return  # always cold: Phi* is path independent
        theta = self.profile.best_theta()
        cold = self.profile.inner.solve(theta, self.initial_controls(theta))
        self.profile.inner_iterations += cold.iterations
        if cold.value < self.profile.best().value:
            self.profile.solved.append((self.params.to_s(theta) + 0.0, cold, "cold"))
            log.info(f"  cold  {self.params.describe(theta)}  Phi* = {cold.value:.6e} (re-solved from the start)")

    # --- the answer

    def final(self) -> tuple[np.ndarray, InnerResult, np.ndarray]:
        """(theta, inner result, nodal forces) of the best full solve."""
        theta, best = self.profile.best_theta(), self.profile.best()
        forward = self.problem.forward
        if self.inner_name == "lbfgs-forces":
            return theta, best, best.controls
        return theta, best, forward.reaction_forces(theta, best.evaluation.u)



def estimate(problem: InverseProblem, options: Options | None = None, basis: np.ndarray | None = None,
             held_out: float | None = None) -> EstimateResult:
    """Run the nested optimisation. On Ctrl-C it stops and returns the best result so far
    (``interrupted``: true). ``held_out``: the share of held-out examples' energy the
    bases kept in training (reduction.held_out_energy), if known."""
    start = time.perf_counter()
    scene = problem.scene
    require(len(problem.params), f"{scene.path}: nothing to estimate: mark at least one E or nu with estimate = true")
    require(any(not m.E.estimate for m in scene.materials),
            f"{scene.path}: every E is estimated, but with unknown boundary forces only ratios of E "
            "are identifiable (scaling K and F together leaves u unchanged): fix one region's E as the reference")
    options = options or Options.from_scene(scene)
    phi_undeformed = check_overlap(problem)
    extent_warnings = check_extent(problem)
    warnings = [w for w in [check_determined(problem, basis, options, choose_inner(problem, options, basis)),
                            None if basis is None else reach_warning(held_out, basis.shape[1])] if w]
    estimator = Estimator(problem, options, basis)
    try:
        return _run(estimator, warnings, extent_warnings, phi_undeformed, held_out, start)
    finally:
        estimator.close()


def _run(estimator: Estimator, warnings: list[str], extent_warnings: list[str], phi_undeformed: float,
         held_out: float | None, start: float) -> EstimateResult:
    """The estimator's run (to its best so far on Ctrl-C), its uncertainty and result.json's record."""
    problem = estimator.problem
    interrupted = False
    try:
        estimator.run()
    except KeyboardInterrupt as signal:
        if not estimator.profile.solved:
            raise Interrupted(f"{signal} before the first evaluation: nothing written") from None
        interrupted = True
        log.info("interrupted: writing the best result so far")
    theta, best, forces = estimator.final()
    clock = time.perf_counter()
    if not interrupted:
        estimator.linearise_answer(theta, best)
    post = estimator.posterior(best)
    if post is not None:  # the final answer's only: the set-up check's posterior has no use for it
        post.offset = target_offset(problem.misfit, estimator.profile.linearisation(best), best.evaluation)
    if post is not None and not interrupted:
        estimator.profile_likelihood_interval(post)
    uncertainty_seconds = time.perf_counter() - clock
    fit = fit_of_bases(estimator, theta, best)
    warnings = (warnings + estimator.warnings + _warnings(estimator, theta, interrupted, fit, post) + extent_warnings
                + _target_warnings(problem, best))
    for text in warnings:
        log.warning(text)
    record = _record(estimator, theta, best, phi_undeformed, warnings, interrupted, start)
    record["bases_fit"] = fit if fit is None else {**fit, "held_out_energy": held_out}
    record["uncertainty"] = post.record() if post is not None else {
        "note": f"not computed: interrupted, and the {estimator.inner_name} inner solver keeps no response of the "
                "controls (profiling them out would take another inner fit's solves)"}
    if post is not None:  # what the answer's posterior, offset and profile interval cost
        record["uncertainty"]["seconds"] = round(uncertainty_seconds, 3)
    smoothing = problem.misfit.smoothing() if problem.misfit is not None else None
    if smoothing is not None:
        record["uncertainty"]["target_smoothed"] = smoothing
    if post is not None:
        for line in describe_uncertainty(post, theta) + describe_offset(post):
            log.info(line)
    record["wall_time_s"] = round(time.perf_counter() - start, 3)
    return EstimateResult(theta, list(problem.params.labels), best.evaluation.u, forces, best.evaluation, record)


def describe_uncertainty(post: Posterior, theta) -> list[str]:
    """``prostate.E = 48.6 ± 1.9 (95 %: 45.0-52.4)`` per estimated constant, and how much
    a structured residual widened it (posterior.patch_covariance)."""
    return [f"{label} = {value:.4g} ± {sd:.2g} (95 %: {lo:.4g}-{hi:.4g})"
            + (f"; widened {w:.2g}x: the residual is structured, not noise" if w > WIDENED_NOTE else "")
            for label, value, sd, (lo, hi), w in zip(post.labels, theta, post.std(), post.interval(), post.widening)]


WIDENED_NOTE = 1.05  # a widening of the interval worth a word


def describe_offset(post: Posterior) -> list[str]:
    """How far a target bigger all round (posterior.target_offset) would move each constant."""
    if post.offset is None:
        return []
    delta, ds = post.offset
    moved = [f"{label} by {100 * np.expm1(d):+.2g} %" if is_E else f"{label} by {d:+.2g}"
             for label, d, is_E in zip(post.labels, ds, post.is_E) if np.isfinite(d)]
    if not moved:
        return []
    return [f"a target {delta:.3g} bigger all round (a tenth of its edge: a segmentation bias no residual shows) "
            f"would move {', '.join(moved)} (first order)"]


def fit_of_bases(estimator: Estimator, theta, best: InnerResult) -> dict | None:
    """result.json's ``bases_fit``: the share of the surface-matched wall motion the bases
    span, and how far the estimate moves when they may also use what they miss
    (reduction.missing_wall_motion; relative for E, absolute for nu)."""
    fit = bases_fit(estimator.basis, estimator.d0)
    lin = estimator.profile.linearisation(best)
    if fit is None or lin is None:
        return fit
    missing = missing_wall_motion(estimator.problem, estimator.basis, theta, best.evaluation, lin)
    params = estimator.params
    shift = np.where(params.is_E, np.expm1(missing["shift_s"]), missing["shift_s"])
    return {**fit, "missing_wall_rms": missing["missing_wall_rms"],
            "shift_if_enriched": {label: float(v) for label, v in zip(params.labels, shift)},
            "shift_if_enriched_s": [float(v) for v in missing["shift_s"]]}


def _warnings(estimator: Estimator, theta, interrupted: bool, fit=None, post=None) -> list[str]:
    out = []
    profile = estimator.profile
    if profile.unconverged:
        out.append(f"the inner solver stopped at its iteration limit ({estimator.options.inner_maxiter}) at "
                   f"{profile.unconverged} of {sum(stage != 'ci' for *_, stage in profile.solved)} material "
                   "values: raise optimizer.inner_maxiter")
    for label, value, (lo, hi) in zip(estimator.params.labels, theta, estimator.params.bounds):
        if np.isclose(value, lo, rtol=1e-3) or np.isclose(value, hi, rtol=1e-3):
            out.append(f"{label} = {value:.4g} is at its bound [{lo:g}, {hi:g}]: widen the bounds or check the set-up")
    if fit is not None and fit["wall_motion_explained"] < 0.9:
        out.append(f"the bases explain {100 * fit['wall_motion_explained']:.0f} % of the wall motion surface "
                   "matching finds; train with more or other examples (e.g. --synthetic)")
    out += _bias_warnings(estimator.params, fit, post)
    return out


BIAS_MIN = (0.02, 0.01)  # a shift of log E (about 2 %) or of nu worth a warning, if also above 1 sigma


def _bias_warnings(params, fit, post) -> list[str]:
    """Bases that miss wall motion which would move a constant by more than its std
    (and more than BIAS_MIN): a bias the interval does not show."""
    if not fit or "shift_if_enriched_s" not in fit:
        return []
    std = post.std_s if post is not None else np.zeros(len(params))
    out = []
    for label, is_E, shift, shift_s, sd in zip(params.labels, params.is_E, fit["shift_if_enriched"].values(),
                                                fit["shift_if_enriched_s"], std):
        if abs(shift_s) > max(BIAS_MIN[0] if is_E else BIAS_MIN[1], sd):
            moved = f"{100 * shift:+.1f} %" if is_E else f"{shift:+.3f}"
            out.append(f"the bases miss wall motion (rms {fit['missing_wall_rms']:.3g}) that would move {label} by "
                       f"about {moved} (first order), more than its interval says: train with more or other examples "
                       "(--synthetic N with a higher rank)")
    return out


PROFILE_DOFS = 60_000  # without bases, the profile interval's few full solves only below this size

EXTENT_RATIO = 1.5  # a target this much larger or smaller than the surface it matches is suspect
UNITS_RATIO = 3.0  # ... and this much larger is never right (mm against cm is 10x): refused
NOISE_RATIO = 3.0  # a final rms distance above this x [target] noise fits badly


def check_extent(problem: InverseProblem) -> list[str]:
    """A target that overlaps the source (check_overlap) can still be wrong: in other
    units (10x larger) or of another part. Compare each target surface's extent with
    the matched nodes it is compared with: more than UNITS_RATIO x larger is refused
    (no elasticity turns a surface into one three times its size), beyond EXTENT_RATIO
    either way is a warning (a partial segmentation is smaller and may be right)."""
    out, misfit, spec = [], problem.misfit, problem.scene.config["target"] or {}
    matched = problem.scene.matched
    for rows, term in zip(misfit.slices, misfit.terms):
        for i, surface in enumerate(getattr(term, "surfaces", [])):
            name = f"target.surface ({spec['surface']})" if spec.get("surface") else \
                f"target.surfaces.{matched[i]} ({spec['surfaces'][matched[i]]})"
            own = problem.observation.points[rows][term.surface_of == i]
            size = float(np.linalg.norm(np.ptp(own, axis=0))) if len(own) else 0.0
            if size <= 0:
                continue
            ratio = surface.extent / size
            message = (f"{name} spans {ratio:.3g} x the matched surface it is compared with "
                       f"({surface.extent:.3g} vs {size:.3g}): in other units, or of another part?")
            require(ratio <= UNITS_RATIO, message)
            if not 1 / EXTENT_RATIO < ratio < EXTENT_RATIO:
                out.append(message)
    return out


def _target_warnings(problem: InverseProblem, best: InnerResult) -> list[str]:
    """The final rms distance against what the target can resolve: NOISE_RATIO x
    [target] noise if given, else the target's mean edge length."""
    out, spec = [], problem.scene.config["target"] or {}
    surfaces = [s for term in problem.misfit.terms for s in getattr(term, "surfaces", [])]
    distances = problem.distances(best.evaluation.residual)
    for kind, distance in distances.items():
        if spec.get("noise"):
            scale, what = NOISE_RATIO * spec["noise"], f"{NOISE_RATIO:g} x target.noise"
        elif kind == "surface" and surfaces:
            scale, what = float(np.mean([s.mean_edge for s in surfaces])), "the target's mean edge length"
        else:
            continue
        if distance["rms"] > scale:
            out.append(f"the final rms {kind} distance {distance['rms']:.3g} is above {what} ({scale:.3g}): "
                       "the model does not fit the target; check its units, frame and the set-up")
    return out


def _record(estimator: Estimator, theta, best: InnerResult, phi_undeformed, warnings, interrupted, start) -> dict:
    problem, profile = estimator.problem, estimator.profile
    E, nu = problem.params.materials(theta)
    initial = profile.solved[0][1].value if profile.solved else None
    return {
        "materials": {m.name: {"E": float(E[i]), "nu": float(nu[i])} for i, m in enumerate(problem.scene.materials)},
        "estimated": list(problem.params.labels),
        "objective": {"undeformed": phi_undeformed, "initial": initial, "final": best.evaluation.phi,
                      "prior": best.prior},
        "surface_distance": problem.distances(best.evaluation.residual).get(
            "surface", problem.distances(best.evaluation.residual).get("landmarks")),
        "distances": problem.distances(best.evaluation.residual),
        "iterations": {"outer": estimator.outer_iterations, "inner": profile.inner_iterations,
                       "evaluations": len(profile.solved),
                       "surrogate_evaluations": estimator.surrogate.evaluations if estimator.surrogate else 0},
        "factorizations": problem.model.factorizations,
        "solves": {"forward": problem.forward.forward_solves, "adjoint": problem.forward.adjoint_solves},
        "dofs": problem.model.dofs.num_dofs,
        "force_dofs": problem.force_dofs,
        "rank": None if estimator.basis is None else int(estimator.basis.shape[1]),
        "inner_solver": estimator.inner_name,
        "match_nodes": "vertices" if problem.observation.vertices_only else "all",
        "degree": problem.scene.degree,
        "mpi_ranks": problem.scene.comm.size,
        "interrupted": interrupted,
        "warnings": warnings,
        "wall_time_s": round(time.perf_counter() - start, 3),
        "history": profile.history(),
    }
