"""Whether the data determine the estimated constants: the start scan read against the noise,
and the checks after the scan that end a run the data cannot decide.
"""

from __future__ import annotations

import numpy as np

from fenics_elasto.inverse.checks import stray_group
from fenics_elasto.inverse.uncertainty.answer import AnswerUncertainty
from fenics_elasto.inverse.uncertainty.profile_interval import threshold
from fenics_elasto.util.errors import UserError


SCAN_SEES = 10.0  # scan_sees: Phi* over the scan rising this many times the 95 % threshold shows the constant
EXACT_FIT = 1e-12  # scan_sees: Phi* changes below this share of the misfit at u = 0 are round-off of exact fits


def scan_excludes(values, noise: float) -> bool:
    """Does Phi* over a single constant's start scan (``values``: inner minima at values
    spread over its bounds) rise above the noise's 95 % threshold anywhere? If not, no
    scanned value is excluded and the 95 % interval spans the bounds: the 2D inclusion
    at 2 % noise passed the Laplace check at the best scan value, then after a whole
    estimate every draw's profile interval was E = 1-1000, the whole bounds."""
    return float(np.max(values) - np.min(values)) > threshold(noise)


def scan_sees(values, noise: float, phi_still: float) -> bool:
    """Does Phi* over a single constant's start scan (``values``) show it? Where the
    controls mimic nearly all of a constant's effect at one value (``Posterior.mimicked``),
    the data may still see it through the rest: on the phantom with 400 / 240 bases a
    share of 0.041 (E = 25, 4 fiducials), yet Phi* rose 50x and 155x from its minimum
    towards the bounds, and the estimate came out -0.6 %. A constant the controls mimic
    everywhere leaves Phi* flat to within the noise -- or, fitted exactly at every value
    (the full force space on matched walls), at round-off of ``phi_still``, the misfit
    of the undeformed source."""
    rise = float(np.max(values) - np.min(values))
    return rise > max(SCAN_SEES * threshold(noise), EXACT_FIT * phi_still)


def check_identifiable(answer: AnswerUncertainty, scanned: list[float], scan: int, allow: bool) -> None:
    """After the scan: a constant the data do not determine (at the best full solve:
    its 95 % interval spans its bounds, or the controls mimic nearly all of its
    effect) ends the run now, not after it; so does a single constant whose Phi* over
    the scan (``scanned``) stays within the noise's 95 % threshold everywhere, though
    the Laplace interval at one value looked narrower. A single constant the controls
    mimic locally but whose Phi* over the scan clearly rises is seen by the data: it
    runs, with a warning that its answer rests on the rest of its effect. ``scan``: values
    per constant in the start scan; ``allow``: optimizer.allow_undetermined."""
    post = answer.posterior()
    if post is None:  # no linearisation at the scan's solves: nothing to check with
        return
    undetermined = post.undetermined(answer.params.s_bounds())
    if (not undetermined and len(answer.params) == 1 and scan > 1
            and not scan_excludes(scanned, post.noise_std)):
        undetermined = {answer.params.labels[0]: "Phi* over the start scan stays within the noise's 95 % threshold: "
                                                 "none of the values scanned across its bounds is excluded"}
    if len(undetermined) == 1 == len(answer.params) and post.mimicked()[0]:
        phi_still = answer.problem.misfit.cost(answer.problem.residual_at_rest)
        if scan_sees(scanned, post.noise_std, phi_still):
            label, best = answer.params.labels[0], min(scanned)
            answer.warnings.append(
                f"{label}: the boundary forces can mimic {100 * (1 - post.separable[0]):.1f} % of its effect on the "
                f"data, yet Phi* over the start scan rises {(max(scanned) - best) / max(best, 1e-300):.3g}x above "
                "its minimum: the data see it through the rest, where a bias of the bases or the source mesh "
                "weighs more than noise (more training examples, landmarks, estimate --check-mesh)")
            undetermined = post.undetermined(answer.params.s_bounds(), seen=[label])
    if not undetermined:
        return
    why = "; ".join(f"{label}: {reason}" for label, reason in undetermined.items())
    problem = answer.problem
    stray = stray_group(problem.misfit, answer.profile.best().evaluation.residual, problem.scene.matched, always=True)
    why += f"; {stray}" if stray else ""
    remedy = ("state target.noise for the surfaces if they are known better: the landmarks' stated noise set the "
              f"interval's scale ({post.noise_std:.3g}, where the residual shows {post.residual_std:.3g}), " if
              post.noise_source == "the landmarks' stated noise" else "")
    more = "better reduced bases (more examples, a higher rank)" if answer.surrogate is not None else "reduced bases"
    message = (f"{problem.scene.path}: the data do not determine {', '.join(undetermined)} (at the best "
               f"value solved, {why}); {remedy or 'fix it, '}or add data that see it ({more}, landmarks inside "
               f"the body, more matched surfaces), or set optimizer.allow_undetermined = true")
    if not allow:
        raise UserError(message)
    answer.undetermined.update(undetermined)
    answer.warnings.append("undetermined (allow_undetermined = true): " + message.split(": ", 1)[1].split("; fix")[0])
