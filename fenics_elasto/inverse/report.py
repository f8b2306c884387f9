"""What an estimate says: its warnings, the printed lines on how sure it is, and
result.json's record.
"""

from __future__ import annotations

import time

import numpy as np

from fenics_elasto.inverse.inner import InnerResult
from fenics_elasto.model.scene import shift_in_units
from fenics_elasto.util.logs import log
from fenics_elasto.inverse.outer import BRACKET_STEP, bracket, remembered_values, surrogate_minimum
from fenics_elasto.inverse.profile import NO_BASES_REMEDY, FewerModes, WeakerPrior
from fenics_elasto.inverse.uncertainty.posterior import Posterior
from fenics_elasto.inverse.reduction.bases import bases_fit, missing_wall_motion

from typing import TYPE_CHECKING


if TYPE_CHECKING:  # the driver these functions report on (it imports them)
    from fenics_elasto.inverse.estimator import Estimator


def describe_uncertainty(post: Posterior, theta) -> list[str]:
    """``prostate.E = 48.6 ± 1.9 (95 %: 45.0-52.4)`` per estimated constant, and how much
    a structured residual widened it (posterior.patch_covariance)."""
    return [f"{label} = {value:.4g} ± {sd:.2g} (95 %: {lo:.4g}-{hi:.4g}){widened_note(w)}"
            for label, value, sd, (lo, hi), w in zip(post.labels, theta, post.std(), post.interval(), post.widening)]


WIDENED_NOTE = 1.05  # a widening of the interval worth a word


def widened_note(widening: float) -> str:
    """``; widened 2x: ...`` where a structured residual widened an interval that much, else ""."""
    return f"; widened {widening:.2g}x: the residual is structured, not noise" if widening > WIDENED_NOTE else ""


def describe_offset(post: Posterior) -> list[str]:
    """How far a target bigger all round (posterior.target_offset) would move each constant."""
    if post.offset is None:
        return []
    delta, ds = post.offset
    return offset_lines(delta, zip(post.labels, ds, post.is_E))


def offset_lines(delta: float, shifts) -> list[str]:
    """The line of ``describe_offset`` from the offset ``delta`` and (label, shift in s,
    is E) per constant (result.json's target_offset holds the shifts in units)."""
    # first order: past a factor e either way a percentage reads as nonsense (-1e+02 %), and
    # a factor as much (a user's "by a factor 0.0018", once 3.5e-15): the offset that moves
    # it 10 % instead (theirs made 35 um bigger, a tenth of that offset, moved E -80 %)
    moved = [(f"{label} by {100 * np.expm1(d):+.2g} %" if abs(d) <= 1 else
              f"{label} beyond first order ({np.log(1.1) * delta / abs(d):.2g} bigger would move it 10 %)")
             if is_E else f"{label} by {d:+.2g}" for label, d, is_E in shifts if np.isfinite(d)]
    if not moved:
        return []
    return [f"a target {delta:.3g} bigger all round (a tenth of its edge: a segmentation bias no residual shows) "
            f"would move {', '.join(moved)} (first order)"]


def fit_of_bases(estimator: Estimator, theta, best: InnerResult, post: Posterior | None = None,
                 interrupted: bool = False) -> dict | None:
    """result.json's ``bases_fit``: the share of the surface-matched wall motion the bases
    span, how far the estimate moves when they may also use what they miss
    (reduction.missing_wall_motion) and when they are cut to half their rank
    (half_rank_shift); relative for E, absolute for nu. After an ``interrupted`` run
    the share only: the two moves cost fits a user who stopped the run is not waiting for."""
    fit = bases_fit(estimator.trained_basis, np.stack(estimator.problem.states.split(estimator.d0), axis=1))
    lin = estimator.profile.linearisation(best)
    if fit is None or lin is None or interrupted:
        return fit
    missing = missing_wall_motion(estimator.problem, estimator.basis, theta, best.evaluation, lin)
    params = estimator.params
    shift = shift_in_units(params.is_E, missing["shift_s"])
    B, _ = lin.profiled()  # what of each constant's effect the forces cannot mimic, per residual row
    signal = np.sqrt(np.sum(B**2, axis=0) / max(lin.informative, 1)) * np.log1p(SIGNAL_CHANGE)
    out = {**fit, "missing_wall_rms": missing["missing_wall_rms"],
           "signal_rms": {label: float(v) for label, v in zip(params.labels, signal)},
           "shift_if_enriched": {label: float(v) for label, v in zip(params.labels, shift)},
           "shift_if_enriched_s": [float(v) for v in missing["shift_s"]]}
    std_s = None if post is None else post.noise_part_s
    moves = {"shift_at_half_rank": half_rank_shift(estimator, theta, std_s),
             "shift_without_matched_motion": matched_motion_shift(estimator, theta, std_s)}
    for key, move in moves.items():
        if move is not None:
            out[key] = {label: float(v) for label, v in zip(params.labels, shift_in_units(params.is_E, move))}
            out[f"{key}_s"] = [float(v) for v in move]
    return out


def half_rank_shift(estimator: Estimator, theta, std_s=None) -> np.ndarray | None:
    """How far s = (log E, nu) moves when the bases are cut to half their rank: the
    minimum of Phi* on the surrogate with each state's leading modes only, from the
    answer (dense algebra, no solve). One first-order enrichment (shift_if_enriched)
    cannot see a wall motion far from the training's: the pelvis phantom's "emptied"
    state, rank 80, gave E 85 (truth 50, interval 74-99) with that shift at -1.4 %, and
    E 179 at rank 40 (50.8 at rank 240). Found to a quarter of the noise's std
    ``std_s`` where given, which it is compared with (RANK_SIGMAS of them), its bracket
    made in steps of that std (that case: 52 s, then 23 s, then 15.5 s) and kept within
    RANK_REACH of them: a move that far is reported at that edge, a lower bound (the
    fits far from the answer are the costly ones). The matched wall motions
    (with_matched_motion) stay: they are the data's, not the training's. None without a
    surrogate or below rank 4."""
    trained, basis = estimator.trained_basis, estimator.basis
    if estimator.surrogate is None or trained is None or basis is None or trained.shape[1] < 4:
        return None
    start = time.perf_counter()
    x, evaluations = _minimum_with(estimator, np.arange(estimator.matched_columns + trained.shape[1] // 2), theta, std_s)
    log.info(f"the bases cut to rank {trained.shape[1] // 2}: {estimator.params.describe(estimator.params.to_theta(x))} "
             f"on the surrogate ({evaluations} evaluations, {time.perf_counter() - start:.1f} s)")
    return x - estimator.params.to_s(theta)


def matched_motion_shift(estimator: Estimator, theta, std_s=None) -> np.ndarray | None:
    """How far s moves without the data's own wall motion in the bases (the trained
    modes only), on a target smoothed for its roughness: there that motion carries
    what smoothing left of the target's noise into the walls, and E follows it. The
    phantom at 1 % noise (benchmarks/noise.py) gave E 56.6, 56.5, 55.5 with it
    (truth 50, every interval missing) and 53.3 without (the first draw, holding).
    Found as half_rank_shift's, on the surrogate; None where the bases hold no matched
    motion or the target was not smoothed."""
    matched = estimator.matched_columns
    if (estimator.surrogate is None or not matched or estimator.problem.misfit.smoothing() is None
            or estimator.trained_basis is None):
        return None
    start = time.perf_counter()
    x, evaluations = _minimum_with(estimator, matched + np.arange(estimator.trained_basis.shape[1]), theta, std_s)
    log.info(f"without the matched wall motion in the bases: {estimator.params.describe(estimator.params.to_theta(x))} "
             f"on the surrogate ({evaluations} evaluations, {time.perf_counter() - start:.1f} s)")
    return x - estimator.params.to_s(theta)


def prior_shift(estimator: Estimator, theta, std_s) -> np.ndarray | None:
    """How far s = (log E, nu) moves when the Gauss-Newton prior is PRIOR_WEAKER times
    weaker: the lowest of Phi* on the surrogate (or on full responses without bases)
    at the answer and at steps from it of PRIOR_SIGMAS noise stds, doubling towards lower
    values until they rise (outer.bracket; at most six) -- enough to tell a move past
    PRIOR_SIGMAS, to within a factor of two, in 3 to 8 fits. Where the prior outweighs
    the data misfit, the answer may rest on where surface matching put the loaded walls'
    sliding, which the distances cannot see. None where the prior is below the misfit
    at the answer (the default phantom's: 0.57x), with several constants, or without
    Gauss-Newton."""
    best = estimator.profile.best()
    if (estimator.inner_name != "gauss-newton" or len(estimator.params) != 1
            or best.prior <= PRIOR_CHECK * best.evaluation.phi):
        return None
    start = time.perf_counter()
    weaker = WeakerPrior(estimator.profile, PRIOR_WEAKER, estimator.options.inner_tol)
    values: dict[float, float] = {}
    value = remembered_values(weaker, values)
    s = float(estimator.params.to_s(theta)[0])
    value(s)
    bracket(value, values, s, PRIOR_SIGMAS * float(std_s[0]), estimator.params.s_bounds()[0])
    x = min(values, key=values.__getitem__)
    log.info(f"the prior {PRIOR_WEAKER:g}x weaker: {estimator.params.describe(estimator.params.to_theta([x]))} "
             f"({len(values)} evaluations, {time.perf_counter() - start:.1f} s)")
    return np.array([x - s])


def _minimum_with(estimator: Estimator, columns: np.ndarray, theta, std_s=None) -> tuple[np.ndarray, int]:
    """(s at the minimum of Phi* on the surrogate with each state's ``columns`` of the
    bases only, from the answer (dense algebra, no solve); the evaluations it took)."""
    params = estimator.params
    # found to a quarter of sigma: its fits stop at inner_tol, as the scan's (Estimator._outer)
    fewer = FewerModes(estimator.profile, columns, estimator.options.inner_tol)
    s = params.to_s(theta)
    xtol, step, bounds = estimator.xtol, BRACKET_STEP, params.s_bounds()
    if std_s is not None:  # surrogate_minimum stops at a tenth of xtol; a bracket made in sigmas
        std_s = np.asarray(std_s, float)
        xtol = np.maximum(xtol, 2.5 * std_s)
        step = max(step, float(np.min(std_s)))
        bounds = [(max(low, x - RANK_REACH * sd), min(high, x + RANK_REACH * sd)) if sd > 0 else (low, high)
                  for (low, high), x, sd in zip(bounds, s, std_s)]
    x, evaluations = surrogate_minimum(fewer, s, xtol, smooth=not estimator.problem.misfit.rough(), step=step,
                                       bounds=bounds)
    return np.asarray(x, float), evaluations


def run_warnings(estimator: Estimator, theta, interrupted: bool, fit=None, post=None) -> list[str]:
    out = []
    profile = estimator.profile
    if interrupted:  # result.json's "interrupted" says it too, but a reader of the warnings alone would not know
        out.append(f"interrupted before the estimate ended: the answer is the best of the {len(profile.solved)} "
                   "material values solved so far, not the optimum" + ("; reduced bases (`fenics-elasto train`) make "
                   "each one a few Gauss-Newton steps" if profile.basis is None else ""))
    if profile.unconverged:
        out.append(f"the inner solver stopped at its iteration limit ({estimator.options.inner_maxiter}) at "
                   f"{profile.unconverged} of {sum(stage != 'ci' for *_, stage in profile.solved)} material "
                   "values: raise optimizer.inner_maxiter" + (NO_BASES_REMEDY if profile.basis is None else ""))
    for label, value, (lo, hi) in zip(estimator.params.labels, theta, estimator.params.bounds):
        if _at(value, lo) or _at(value, hi):
            out.append(f"{label} = {value:.4g} is at its bound [{lo:g}, {hi:g}]: widen the bounds or check the set-up")
    if fit is not None and fit["wall_motion_explained"] < 0.9:
        out.append(f"the bases explain {100 * fit['wall_motion_explained']:.0f} % of the wall motion surface "
                   "matching finds; train with more or other examples (e.g. --synthetic)")
    out += _prior_warnings(estimator, post)
    out += (_bias_warnings(estimator.params, fit, post) + _rank_warnings(estimator.params, fit, post)
            + _matched_motion_warnings(estimator.params, fit, post) + _open_interval_warnings(estimator.params, post, theta))
    return out


def _prior_warnings(estimator: Estimator, post) -> list[str]:
    """An answer that moves by more than PRIOR_SIGMAS sigmas (and BIAS_MIN) when the
    Gauss-Newton prior is PRIOR_WEAKER times weaker (prior_shift): the data alone do not
    settle it, and sigma does not count that. Which answer is right the check cannot
    tell: a user's bar (nu from its own exact target) gave 0.3238 for 0.3 and 0.3049
    with the weaker prior; the 2D inclusion's two states in the full force space gave
    39.83 for 40 and about 30 with it."""
    if post is None or post.prior_shift_s is None:
        return []
    out = []
    anchor = estimator.options.anchor
    for label, is_E, shift_s, sd in zip(post.labels, post.is_E, post.prior_shift_s, post.std_s):
        if sd > 0 and abs(shift_s) > max(BIAS_MIN[0] if is_E else BIAS_MIN[1], PRIOR_SIGMAS * sd):
            moved = f"{100 * np.expm1(shift_s):+.0f} %" if is_E else f"{shift_s:+.3f}"
            out.append(f"{label} moves by about {moved} ({abs(shift_s) / sd:.0f} sigma) with the prior that holds the "
                       f"loaded walls where surface matching put them {PRIOR_WEAKER:g}x weaker (optimizer.anchor "
                       f"{anchor:g} -> {anchor / PRIOR_WEAKER:g}): the data alone do not settle it, and its interval "
                       "does not count that -- add data that see the walls' sliding along their targets (landmarks, "
                       "another state, a measured force), or compare the answers at both anchors")
    return out


def _at(value: float, bound: float) -> bool:
    """Whether an answer sits at a bound (the optimizer stops within a hair of it)."""
    return bool(np.isclose(value, bound, rtol=1e-3))


def _open_interval_warnings(params, post, theta) -> list[str]:
    """A 95 % interval that reaches past a bound: the data bound the constant on one side
    only (the label-map chain pushed 1.5 mm: 294 in 45-1578 for bounds 2-500), or, where
    the value sits at that bound, the bound holds it and not the data (a user's bounds
    0.5-20 for a truth of 40 that the data pin at 38-45: 13.3-30.0 was read as 'at least
    13.3, weakly determined', and the other constant moved 13 % with it)."""
    if post is None:
        return []
    out = []
    for label, value, (low, high), (lo, hi) in zip(params.labels, theta, post.interval(), params.bounds):
        above, below = high > hi * (1 + 1e-9), low < lo * (1 - 1e-9)
        side = "upper" if above else "lower" if below else None
        if above and below:  # a user's swapped targets: the core at its lower bound, 0.96-708 for 2-500
            out.append(f"{label}: its 95 % interval ({low:.4g}-{high:.4g}) reaches past both its bounds ({lo:g}-{hi:g}): "
                       "the data do not bound it; is the target right (its files, groups and frame), or its noise "
                       "larger than this constant's signal (bases_fit.signal_rms)?")
        elif side and _at(value, hi if above else lo):
            others = "; the other constants are fitted with it held there" if len(params.labels) > 1 else ""
            out.append(f"{label}: its 95 % interval ({low:.4g}-{high:.4g}) reaches past its {side} bound, where the "
                       f"value sits: the bound holds it, not the data, and the interval is not the answer's -- widen "
                       f"the bounds{others}")
        elif side:
            bound, other = (hi, f"at least {low:.4g}") if side == "upper" else (lo, f"at most {high:.4g}")
            out.append(f"{label}: its 95 % interval ({low:.4g}-{high:.4g}) reaches past its {side} bound {bound:g}: "
                       f"the data bound it on one side only; read it as {other}, and the value as weakly determined")
    return out


BIAS_MIN = (0.02, 0.01)  # a shift of log E (about 2 %) or of nu worth a warning, if also above 1 sigma
SIGNAL_CHANGE = 0.1  # bases_fit.signal_rms: how far the data move, rms, when an E changes by 10 % (forces refitted)


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


def _rank_warnings(params, fit, post) -> list[str]:
    """An answer that moves by RANK_SIGMAS or more when the bases are cut to half their
    rank (half_rank_shift): not settled in the rank."""
    if not fit or "shift_at_half_rank_s" not in fit or post is None:
        return []
    out = []
    # against sigma without the move's own share of it (parts.RANK_PART), which a move of
    # any size would otherwise keep within a few of its sigmas
    own = post.rank_part_s if post.rank_part_s is not None else np.zeros(len(post.labels))
    others = np.sqrt(np.maximum(post.std_s**2 - own**2, 0.0))
    for label, is_E, shift, shift_s, sd, noise_sd in zip(params.labels, params.is_E, fit["shift_at_half_rank"].values(),
                                                          fit["shift_at_half_rank_s"], others, post.noise_part_s):
        if sd > 0 and abs(shift_s) > max(BIAS_MIN[0] if is_E else BIAS_MIN[1], RANK_SIGMAS * sd):
            moved = f"{100 * shift:+.0f} %" if is_E else f"{shift:+.3f}"
            far = "at least " if abs(shift_s) >= (1 - 1e-6) * RANK_REACH * noise_sd else ""  # the search's edge
            out.append(f"{label} moves by {far}{moved} ({far}{abs(shift_s) / sd:.0f} sigma) when the bases are cut to half "
                       "their rank: it has not settled in the rank, and more bases may move it as far -- train with "
                       "more examples and a higher rank (--synthetic N --rank R), or bases from motion like this case's")
    return out


def _matched_motion_warnings(params, fit, post) -> list[str]:
    """A smoothed target's answer that moves by more than its std (and more than
    BIAS_MIN) without the data's own wall motion in the bases (matched_motion_shift):
    the noise that motion carries is not in sigma."""
    if not fit or "shift_without_matched_motion_s" not in fit or post is None:
        return []
    out = []
    for label, is_E, shift, shift_s, sd in zip(params.labels, params.is_E, fit["shift_without_matched_motion"].values(),
                                                fit["shift_without_matched_motion_s"], post.std_s):
        if sd > 0 and abs(shift_s) > max(BIAS_MIN[0] if is_E else BIAS_MIN[1], sd):
            moved = f"{100 * shift:+.1f} %" if is_E else f"{shift:+.3f}"
            out.append(f"{label} moves by {moved} ({abs(shift_s) / sd:.1f} sigma) without the target's own wall motion "
                       "in the bases: on a target this noisy that motion carries what smoothing left of the noise, "
                       "which the interval does not count -- compare with --set optimizer.matched_motion='off'")
    return out


PRIOR_CHECK = 1.0  # prior_shift: measured where the prior is more than this many times the misfit at the answer
PRIOR_WEAKER = 100.0  # ... with the prior this many times weaker
PRIOR_SIGMAS = 2.0  # ... in steps of this many noise stds; said where the answer moves by more than this many sigmas
# A half-rank shift worth a warning, in stds of the answer: the pelvis phantom's filled
# state moved 1.8 sigma (E 50.0 -> 55.2 at rank 40 of 80, truth 50), its emptied state
# 10 sigma (85 -> 179; truth 50, reached at rank 240).
RANK_SIGMAS = 4.0
RANK_REACH = 8.0  # ... searched for within this many stds of the answer: far enough to tell a warning


def record(estimator: Estimator, theta, best: InnerResult, phi_undeformed, warnings, interrupted, start) -> dict:
    problem, profile = estimator.problem, estimator.profile
    E, nu = problem.params.materials(theta)
    initial = profile.every_solve[0][1].value if profile.every_solve else None
    distances = problem.distances(best.evaluation.residual)
    return {
        "materials": {m.name: {"E": float(E[i]), "nu": float(nu[i])} for i, m in enumerate(problem.scene.materials)},
        "estimated": list(problem.params.labels),
        "objective": {"undeformed": phi_undeformed, "initial": initial, "final": best.evaluation.phi,
                      "prior": best.prior},
        "surface_distance": next(iter(distances.values())),  # the first kind of data
        "distances": distances,
        # interrupted, the outer loop never returned its count: its solves so far
        "iterations": {"outer": sum(kind == "outer" for *_, kind in profile.solved) if interrupted
                       else estimator.outer_iterations,
                       "inner": profile.inner_iterations,
                       "evaluations": len(profile.every_solve),
                       "surrogate_evaluations": estimator.surrogate.evaluations if estimator.surrogate else 0},
        "factorizations": problem.model.factorizations,
        "solves": {"forward": problem.forward.forward_solves, "adjoint": problem.forward.adjoint_solves},
        "dofs": problem.model.dofs.num_dofs,
        "force_dofs": problem.force_dofs,
        "rank": None if estimator.trained_basis is None else int(estimator.trained_basis.shape[1]),
        "inner_solver": estimator.inner_name,
        "match_nodes": "vertices" if problem.observation.vertices_only else "all",
        "degree": problem.scene.degree,
        "mpi_ranks": problem.scene.comm.size,
        "interrupted": interrupted,
        "warnings": warnings,
        "wall_time_s": round(time.perf_counter() - start, 3),
        "history": profile.history(),
    }
