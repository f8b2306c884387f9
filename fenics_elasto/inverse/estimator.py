"""The nested estimate (docs/method.md §5): materials outside, boundary controls inside.

The outer loop minimises the profile Phi*(theta) (functional.py) over the estimated
constants in s = (log E, nu) with bounded L-BFGS-B and the envelope gradient (one
constant whose minimum the scan brackets, on a target that is not rough: cubic steps
inside the bracket). Start:
the boundary controls from iterative surface matching (matching.py), the materials
from a scan over their bounds. With reduced bases (and ``surrogate``, the default) the
outer loop runs on the reduced-basis response in the materials and solves only its
optimum in full, until the optimum lands where a full solve already is. The result is
always the best full solve. Each state's surface-matched wall motion, smoothed, joins the
bases by default (``joins_matched_motion``): the motion the data show, whatever the
training spanned.

Before any solve the set-up is checked: a target that does not overlap the matched
surface, every E estimated (only ratios are identifiable), and a full force space that
can fit the surfaces for any material (``check_determined``) end with one line.
After a reduced estimate ``bases_fit`` says how much of the wall motion the bases
can represent; bases that kept little of their held-out examples are warned about.
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.geometry.matching import joined_motion, match_surface
from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.inverse.checks import check_determined, check_extent, check_overlap, target_warnings
from fenics_elasto.inverse.inner import LBFGS, GaussNewton, InnerResult, fitted_to
from fenics_elasto.inverse.linearisation import ProfiledLinearisation
from fenics_elasto.inverse.measured_force import (apply_measured_force, measured_forces,
                                                  predicted_force_covariances)
from fenics_elasto.inverse.misfit import PointTerm
from fenics_elasto.inverse.objective import Evaluation, InverseProblem
from fenics_elasto.inverse.options import Options
from fenics_elasto.inverse.outer import minimize_on_surrogate, minimize_profile, scan_grid, surrogate_scan
from fenics_elasto.inverse.profile import LOOSE, Profile, SurrogateProfile
from fenics_elasto.inverse.reduction.bases import reach_warning, with_matched_motion
from fenics_elasto.inverse.states import EARLY_SPREAD, REWEIGH_ROUNDS, weigh_by_residuals
from fenics_elasto.inverse.report import (describe_offset, describe_uncertainty, fit_of_bases, prior_shift,
                                          run_warnings)
from fenics_elasto.inverse.report import record as result_record
from fenics_elasto.inverse.surrogate import MaterialSurrogate, release
from fenics_elasto.inverse.uncertainty.answer import AnswerUncertainty
from fenics_elasto.inverse.uncertainty.identifiability import check_identifiable
from fenics_elasto.inverse.uncertainty.mesh_error import HigherDegreeModel
from fenics_elasto.inverse.uncertainty.parts import add_model_error, largest_part, unresolved_warnings
from fenics_elasto.inverse.uncertainty.voxels import grid_aligned_warnings, mixed_source_warnings
from fenics_elasto.inverse.uncertainty.posterior import posterior_record, target_offset
from fenics_elasto.util.errors import require
from fenics_elasto.util.interrupts import Interrupted
from fenics_elasto.util.logs import log


SETTLE_SHARE = 0.05  # Estimator.settled_within: a step this share of the noise std moves no decision
SETTLE_REACH = 10.0  # ... and never coarser than this many outer_xtol


@dataclass
class EstimateResult:
    """What an estimate found: the materials, the field, the forces, and result.json's record."""

    theta: np.ndarray
    labels: list[str]
    u: object  # dolfinx Function
    forces: np.ndarray  # recovered nodal forces of the loaded nodes, flat
    evaluation: Evaluation
    record: dict = field(default_factory=dict)  # result.json
    state_forces: dict[str, np.ndarray] = field(default_factory=dict)  # several states: each one's forces
    force_covariance: dict[str, np.ndarray] = field(default_factory=dict)  # measured forces' predictions' (fit's units)

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


def choose_inner(problem: InverseProblem, options: Options, basis) -> str:
    """Gauss-Newton with bases or a small full force space; L-BFGS otherwise ("auto")."""
    inner = options.inner
    if inner == "auto":
        small = problem.force_dofs <= options.full_gn_limit
        inner = "gauss-newton" if basis is not None or small else "lbfgs"
        if inner == "lbfgs":  # a user's 40k-DOF block ran 15 minutes this way, every fit at its cap, no word why
            log.info(f"note: no reduced bases: each inner fit works in the full force space ({problem.force_dofs} "
                     "force dofs, L-BFGS), which can take many minutes; `fenics-elasto train PROBLEM --synthetic 60 "
                     "--rank 24 --out bases.npz` makes bases, given as [reduction] bases (README)")
    require(basis is None or inner == "gauss-newton", "reduced bases need optimizer.inner = 'gauss-newton'")
    require(problem.states.count == 1 or inner == "gauss-newton",
            f"{problem.scene.path}: several states need the Gauss-Newton inner solver: reduced bases ([reduction], "
            f"from `fenics-elasto train`) or a force space of at most {options.full_gn_limit} dofs")
    return inner


def joins_matched_motion(problem: InverseProblem, options: Options) -> bool:
    """Whether the states' surface-matched wall motions join the bases (with_matched_motion):
    "on", or "auto" (the default) without a measured force and on targets not smoothed
    for their roughness. A force reads the wall's whole motion, and the matched motion's
    tangential part (none: closest points) is what the prior then holds -- the pelvis
    phantom's rectum force put E -8.7 % off with it (interval missing), +1.2 % without.
    A noisy target's motion, even smoothed (smooth_matched_motions), carries what
    smoothing left of the noise into the walls, and sigma does not count it: the noise
    phantom (benchmarks/noise.py) at 1 % and 2 % of the prostate's size missed the truth
    in all five draws measured with it, held it in all five without (docs: limits)."""
    if options.matched_motion == "auto":
        return not measured_forces(problem.scene) and problem.misfit.smoothing() is None
    return options.matched_motion == "on"


def surface_matched_start(problem: InverseProblem, motions: list[np.ndarray] | None = None) -> np.ndarray:
    """Every state's loaded nodes' displacement that surface matching finds (flat, one
    state after another), from ``matched_node_motions`` (computed here if not given);
    loaded nodes that are not matched stay put."""
    motions = matched_node_motions(problem) if motions is None else motions
    return np.concatenate([problem.forward.on_loaded(problem.observation.node_field(u)) for u in motions])


def matched_node_motions(problem: InverseProblem) -> list[np.ndarray]:
    """Each state's matched nodes' displacement (n, gdim): moved onto their target surfaces
    (no surfaces: each takes its nearest landmark's or field sample's displacement)."""
    return [_matched_nodes(problem, misfit) for misfit in problem.states.misfits]


def _matched_nodes(problem: InverseProblem, misfit) -> np.ndarray:
    term = misfit.terms[0]
    nodes = problem.matched_coords
    if isinstance(term, SurfaceTerm):
        return match_surface(nodes, problem.node_groups(), term)
    rows = misfit.landmark_rows()
    rows = rows[misfit.weights[rows] > 0]  # this state's own points
    targets = np.concatenate([t.points for t in misfit.terms if isinstance(t, PointTerm)])
    moved = targets - problem.observation.points[rows]
    return moved[cKDTree(problem.observation.points[rows]).query(nodes)[1]]


def smooth_matched_motions(problem: InverseProblem, motions: list[np.ndarray]) -> list[np.ndarray]:
    """Each state's matched nodes' motion as it joins the bases: smoothed
    (geometry.matching.joined_motion) where the state has target surfaces, so that the
    target's noise does not become wall motion the model must carry (on the real
    prostate, E ratio 3, unsmoothed: 0.5 mm of noise -7.1 %, 1 mm -10.8 %; smoothed
    -4.2 % and -2.0 %)."""
    smooth = []
    for misfit, u in zip(problem.states.misfits, motions):
        term = misfit.terms[0]
        if isinstance(term, SurfaceTerm):
            edge = float(np.mean([surface.mean_edge for surface in term.surfaces]))
            u = joined_motion(problem.matched_coords, problem.node_groups(), u, term.roughness(), edge)
        smooth.append(u)
    return smooth


class Estimator:
    """The nested optimisation of one InverseProblem, optionally in a reduced basis W: the
    start scan, the outer loop, the answer. How sure the answer is lives in ``uncertainty``."""

    def __init__(self, problem: InverseProblem, options: Options, basis=None):
        self.problem = problem
        self.params = problem.params
        self.options = options
        motions = matched_node_motions(problem)
        self.d0 = surface_matched_start(problem, motions)
        self.trained_basis = basis  # as trained (bases_fit's share, result.json's rank)
        self.basis = basis  # W (force_dofs x r), with the matched wall motions, or None: the full space
        if basis is not None and joins_matched_motion(problem, options):
            joined = surface_matched_start(problem, smooth_matched_motions(problem, motions))
            self.basis = basis = with_matched_motion(basis, problem.states.split(joined))
            log.info(f"bases: rank {self.trained_basis.shape[1]} and {self.matched_columns} "
                     "surface-matched wall motion(s)")
        self.inner_name = choose_inner(problem, options, basis)
        surrogate = MaterialSurrogate(problem, basis) if basis is not None and options.surrogate else None
        self.profile = Profile(problem, self._inner(), basis, surrogate, same_within=1e-3 * options.outer_xtol)
        self.surrogate = SurrogateProfile(self.profile) if surrogate is not None else None
        self.uncertainty = AnswerUncertainty(problem, self.profile, self.surrogate, self.inner_name, options.anchor)
        self.outer_iterations = 0
        self._held = ExitStack()  # the contexts an estimate holds until ``close``

    @property
    def matched_columns(self) -> int:
        """How many of the bases' columns are the data's matched wall motions (0 without)."""
        return 0 if self.basis is None else self.basis.shape[1] - self.trained_basis.shape[1]

    def _inner(self):
        o = self.options
        if self.inner_name == "gauss-newton":
            return GaussNewton(self.problem, self.initial_controls(self.params.initial), o.anchor, o.inner_maxiter,
                               o.gauss_newton_tol)
        inner = LBFGS(self.problem, self.inner_name == "lbfgs-forces", o.inner_maxiter, o.inner_tol)
        start = self.initial_controls(self.params.initial)
        inner.control_scale = max(float(np.sqrt(np.mean(start**2))), 1e-300)
        inner.phi_scale = max(self.problem.evaluate_displacement(self.params.initial, self.d0).phi, 1e-300)
        return inner

    def initial_controls(self, theta) -> np.ndarray:
        if self.inner_name == "lbfgs-forces":
            return self.problem.forward.reaction_forces(theta, self.problem.forward.from_boundary(theta, self.d0))
        return self.problem.states.to_controls(self.basis, self.d0)

    @property
    def xtol(self) -> np.ndarray:
        """How finely the outer loop places each constant, in s: outer_xtol in log E, a
        tenth of it in nu."""
        return self.options.outer_xtol * np.where(self.params.is_E, 1.0, 0.1)

    def settled_within(self, xtol: np.ndarray) -> np.ndarray:
        """How near a solved value the surrogate's optimum must land to end the outer loop:
        ``xtol``, or SETTLE_SHARE of the best solve's noise std where that is wider (at
        most SETTLE_REACH x xtol: an undetermined constant's std would end the loop
        before its first step). Where the data determine a constant loosely its Phi* is
        flat, and the optimum creeps by steps of the inner fits' own accuracy: each round
        moved the answer by a fiftieth of its sigma for a whole round of inner fits (the
        pelvis phantom's two states: 55.39 -> 55.32 -> 55.26, sigma 3.3)."""
        post = self.uncertainty.posterior(self.profile.best())
        if post is None:
            return xtol
        return np.clip(SETTLE_SHARE * post.noise_part_s, xtol, SETTLE_REACH * xtol)

    def run(self) -> None:
        """Scan, check the data determine the materials, minimise Phi*, polish; several
        states with no noise stated are weighed by their residuals from the first solve on."""
        n = self.options.scan if len(self.params) == 1 else max(2, min(self.options.scan, 3))
        points = scan_grid(self.params, n) if self.options.scan > 1 else []  # scan = 1: the initial values only
        if self.surrogate is None:
            log.info(f"scan of {len(points) + 1} material values (start: surface matching; inner: {self.inner_name})")
            for i, theta in enumerate([self.params.initial] + points):
                self.profile.solve(theta, "scan", None if self.inner_name == "gauss-newton" else self.initial_controls(theta))
                if i == 0:
                    self.weigh_states(EARLY_SPREAD)
        else:  # one factorization at the initial values; the scan on the surrogate it seeds
            log.info(f"initial values solved in full with their sensitivities, then a scan of {len(points)} "
                     f"material values on the surrogate (inner: {self.inner_name})")
            with fitted_to(self.profile.inner, self.options.inner_tol):  # it seeds the scan only (profile.LOOSE)
                self.profile.solve(self.params.initial, LOOSE)
            self._held.enter_context(self.profile.borrowing())  # later solves on its factors where near enough
            self.weigh_states(EARLY_SPREAD)
        self.outer_iterations = self._outer(points, first=True)
        for _ in range(REWEIGH_ROUNDS):
            if not self.weigh_states():
                break
            self.outer_iterations += self._outer(points, first=False)
        else:
            log.info(f"the states' weights still moved after {REWEIGH_ROUNDS} rounds: the last ones are kept")
        self.polish()

    def _outer(self, points: list, first: bool) -> int:
        """The outer loop from the values solved so far (with the surrogate, after its scan
        of ``points``); ``first``: check the scan says the data determine the materials."""
        smooth = not self.problem.misfit.rough()
        if self.surrogate is None:
            if first:
                self._check_identifiable([result.value for _, result, _ in self.profile.solved])
            return minimize_profile(self.profile, self.xtol, self.options.outer_maxiter, smooth=smooth)
        # The scan's fits stop at inner_tol (1e-6 of Phi), not the Gauss-Newton share of it
        # (1e-10) that values near the optimum need: they only place a bracket and say
        # whether the data determine the materials, and far from the optimum the tail is
        # longest (the default phantom's rank-240 scan: 199, 69 and 58 iterations, 27 s of
        # a 150 s estimate, against 24, 13 and 24; docs/performance.md).
        with fitted_to(self.profile.inner, self.options.inner_tol):
            start, scanned, known = surrogate_scan(self.surrogate, points)
        if first:
            self._check_identifiable([self.profile.best().value] + scanned)
        return minimize_on_surrogate(self.profile, self.surrogate, self.xtol, self.options.outer_maxiter, start, known,
                                     smooth=smooth, settled_within=self.settled_within)

    def weigh_states(self, spread: float = 1.0) -> bool:
        """Several states with no noise stated: weighed by their residuals' levels at the
        best value so far, where ``state_noise`` is "residual" (states.weigh_by_residuals)."""
        return self.options.state_noise == "residual" and weigh_by_residuals(self.problem, self.profile, spread)

    def _check_identifiable(self, scanned: list[float]) -> None:
        check_identifiable(self.uncertainty, scanned, self.options.scan, self.options.allow_undetermined)

    def polish(self) -> None:
        """An L-BFGS inner solve warm-started along the path may stop above the inner
        optimum: re-solve the best material value cold, from the surface-matched start. A
        loosely fitted start (profile.LOOSE) still the best is fitted again, tightly."""
        if min(self.profile.solved, key=lambda item: item[1].value)[2] == LOOSE:
            self.profile.solve(self.profile.best_theta(), "outer")
        if self.inner_name == "gauss-newton":
            return  # always cold: Phi* is path independent
        theta = self.profile.best_theta()
        cold = self.profile.inner.solve(theta, self.initial_controls(theta))
        self.profile.inner_iterations += cold.iterations
        if cold.value < self.profile.best().value:
            self.profile.solved.append((self.params.to_s(theta) + 0.0, cold, "cold"))
            log.info(f"  cold  {self.params.describe(theta)}  Phi* = {cold.value:.6e} (re-solved from the start)")

    def final(self) -> tuple[np.ndarray, InnerResult, np.ndarray]:
        """(theta, inner result, nodal forces) of the best full solve."""
        theta, best = self.profile.best_theta(), self.profile.best()
        if self.inner_name == "lbfgs-forces":
            return theta, best, best.controls
        return theta, best, self.problem.forward.reaction_forces(theta, best.evaluation.u)

    def close(self) -> None:
        """Whatever happened: later solves of this problem factorize again; the surrogate's
        own matrices go."""
        self._held.close()
        if self.profile.surrogate is not None:
            self.profile.surrogate.destroy()


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
            "are identifiable (scaling K and F together leaves u unchanged): fix one region's E as the reference, "
            "or give a measured force ([boundary.measured_force.GROUP])")
    options = options or Options.from_scene(scene)
    phi_undeformed = check_overlap(problem)
    extent_warnings = check_extent(problem)
    checks = [check_determined(problem, basis, options, choose_inner(problem, options, basis)),
              None if basis is None else reach_warning(held_out, basis.shape[1])]
    warnings = list(scene.warnings) + [w for w in checks if w]
    if basis is not None:  # its first solve is the initial values' block: factorized while the estimator is set up
        forward = problem.forward
        forward.model.factorize_ahead(forward.coefficients(problem.params.initial)[0], forward.clamped_boundary)
    estimator = Estimator(problem, options, basis)
    # the degree-3 solve's set-up beside the factorization too (its first solve waits for it)
    prepared = HigherDegreeModel.ahead(problem) if basis is not None else None
    try:
        result = _run(estimator, warnings, extent_warnings, phi_undeformed, held_out, start, prepared)
    finally:
        estimator.close()
        if prepared is not None:
            prepared.destroy()
    measured = measured_forces(scene)
    if measured:
        apply_measured_force(problem, result, measured)
    return result


def _run(estimator: Estimator, warnings: list[str], extent_warnings: list[str], phi_undeformed: float,
         held_out: float | None, start: float, prepared: HigherDegreeModel | None = None) -> EstimateResult:
    """The estimator's run (to its best so far on Ctrl-C), its uncertainty and result.json's
    record (``prepared``: the degree-3 solve's set-up, made ahead)."""
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
    note = (f"not computed: interrupted, and the {estimator.inner_name} inner solver keeps no response of the "
            "controls (profiling them out would take another inner fit's solves)")
    try:
        post, fit = _uncertainty(estimator, theta, best, interrupted, prepared)
    except KeyboardInterrupt:  # the answer stands; what was being worked out of its uncertainty goes
        interrupted, note = True, "not computed: interrupted while it was being worked out"
        post, fit = None, fit_of_bases(estimator, theta, best, None, interrupted=True)
        log.info("interrupted while working out the uncertainty: writing the answer without it")
    uncertainty_seconds = time.perf_counter() - clock
    warnings = (warnings + estimator.uncertainty.warnings + run_warnings(estimator, theta, interrupted, fit, post)
                + unresolved_warnings(post) + grid_aligned_warnings(problem, best.evaluation.y)
                + mixed_source_warnings(problem)
                + extent_warnings + target_warnings(problem, best, estimator.options.state_noise))
    for text in warnings:
        log.warning(text)
    record = result_record(estimator, theta, best, phi_undeformed, warnings, interrupted, start)
    record["bases_fit"] = fit if fit is None else {**fit, "held_out_energy": held_out}
    record["uncertainty"] = posterior_record(post) if post is not None else {"note": note}
    if post is not None:  # what the answer's posterior, offset and profile interval cost
        record["uncertainty"]["seconds"] = round(uncertainty_seconds, 3)
    smoothing = problem.misfit.smoothing()
    if smoothing is not None:
        record["uncertainty"]["target_smoothed"] = smoothing
    if post is not None:
        fits = problem.misfit.group_distances(best.evaluation.residual, problem.scene.matched)
        for line in describe_uncertainty(post, theta) + largest_part(post, fits) + describe_offset(post):
            log.info(line)
    state_forces = {}
    if problem.states.count > 1:  # each state's distances and forces; ``forces`` and ``u`` are the first's
        state_forces = {name: problem.forward.reaction_forces(theta, u)
                        for name, u in zip(problem.states.names, best.evaluation.fields)}
        record["states"] = state_records(problem.states, best.evaluation.residual, estimator.options.state_noise)
        for name, entry in record["states"].items():  # each state's own warnings, also in the whole run's list
            prefix = f"state {name}: "
            entry["warnings"] = [w[len(prefix):] for w in record.get("warnings", []) if w.startswith(prefix)]
    force_covariance = _force_covariance(estimator, theta, best, post) if not interrupted else {}
    record["wall_time_s"] = round(time.perf_counter() - start, 3)
    return EstimateResult(theta, list(problem.params.labels), best.evaluation.u, forces, best.evaluation, record,
                          state_forces, force_covariance)


def _uncertainty(estimator: Estimator, theta, best: InnerResult, interrupted: bool,
                 prepared: HigherDegreeModel | None) -> tuple:
    """(the answer's posterior or None, result.json's bases_fit): the posterior with its
    target offset, profile interval and model error -- only the first two after an
    ``interrupted`` run."""
    problem = estimator.problem
    if not interrupted:
        estimator.uncertainty.linearise_answer(theta, best)
    post = estimator.uncertainty.posterior(best)
    if post is not None:  # the final answer's only: the set-up check's posterior has no use for it
        lin = estimator.profile.linearisation(best)
        assert lin is not None  # the posterior is made from it
        post.offset = target_offset(problem.misfit, lin, best.evaluation)
    if post is not None and not interrupted:
        estimator.uncertainty.profile_likelihood_interval(post)
    fit = fit_of_bases(estimator, theta, best, post, interrupted)
    if post is not None and not interrupted:
        post.prior_shift_s = prior_shift(estimator, theta, post.noise_part_s)
    if estimator.profile.surrogate is not None:  # its last use was the prior's check (prior_shift)
        release(estimator.profile.surrogate)  # a degree-3 matrix made now reuses its memory
    if post is not None and not interrupted:
        add_model_error(problem, post, theta, best.evaluation, estimator.profile.linearisation(best), fit, prepared)
    return post, fit


def state_records(states, residual: np.ndarray, state_noise: str) -> dict[str, dict]:
    """result.json's ``states``: each state's distances, forces file, the weight its rows
    had, and its noise level: stated, or its residual's at the answer (the weights
    follow it to states.REWEIGH_SETTLED), or none (weighed alike)."""
    levels, source = states.stated_noise(), "stated"
    if levels is None and state_noise == "residual":
        levels, source = list(states.residual_levels(residual)), "residual"
    elif levels is None:
        source = "alike"
    out = {}
    for i, (name, distances) in enumerate(states.distances(residual).items()):
        out[name] = {"distances": distances, "forces": f"forces_{name}.csv", "weight": float(states.weights[i]),
                     "noise": None if levels is None else float(levels[i]), "noise_from": source}
    return out


def _force_covariance(estimator: Estimator, theta, best: InnerResult, post) -> dict[str, np.ndarray]:
    """The measured forces' predictions' covariances (measured_force.predicted_force_covariances),
    while the answer's factors are held; none without measured forces or the controls' Jacobian."""
    measured = measured_forces(estimator.problem.scene)
    lin = estimator.profile.linearisation(best)
    if not measured or post is None or lin is None or isinstance(lin, ProfiledLinearisation):
        return {}
    return predicted_force_covariances(estimator.problem, estimator.basis, theta, lin, post.noise_std, measured)
