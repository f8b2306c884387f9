"""Several states of one body as one inverse problem (docs/method.md §10).

Every state is observed by the same operator (the matched nodes, then every state's
landmarks and field samples), so one response J serves them all. The stacked problem
puts the states' rows one after another, and their controls likewise; the response is
block-diagonal, diag(J, ..., J): a state's rows answer its own controls only. One state
is the plain problem (every map below the identity).

Each state's target may state its own noise (``[target] noise``: one scan segmented
better than another). The states' rows are then weighed by it, by maximum likelihood:
w_k = (sigma_ref / sigma_k)^2 with sigma_ref the smallest, so that Phi / sigma_ref^2 is
the negative log-likelihood of them all and the posterior's noise is sigma_ref, given.
A noise stated for some states and not for others is refused: an estimated level for
the rest would have to come from residuals already weighed by the stated ones.
Without any, each state's level is estimated from its own residual after a fit and the
fit is made again with the weights they give (``residual_levels``; maximum likelihood
with each state's variance unknown, by reweighing until the weights settle:
weigh_by_residuals). Weighed alike instead (``[optimizer] state_noise = "alike"``),
the inclusion with one outline displaced by a smooth error of 0.02 put E at its bound;
with the noises stated or estimated, within 1.5 %
(tests/verification/test_more_than_surfaces.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fenics_elasto.util.errors import require
from fenics_elasto.util.logs import log

# residual_levels: a state's estimated level is at least this share of the largest
# (a state fitted to round-off would otherwise weigh without bound) and at least its
# target's own roughness (a surface cannot be known better than it is drawn).
LEVEL_FLOOR = 1e-3
# weigh_by_residuals: weights within this factor of the last round's are settled; at
# most this many rounds after the first outer loop (Estimator.run).
REWEIGH_SETTLED = 1.25
REWEIGH_ROUNDS = 3
# ... and before the outer loop only where the states' levels differ more than this: at
# the initial materials a residual holds their error too (the pelvis pair: levels 2.1x
# apart there, 1.03x at the answer -- a round for nothing; the inclusion with one
# outline displaced: 100x, and alike the scan found E undetermined).
EARLY_SPREAD = 10.0


@dataclass
class States:
    """The states' names, their misfits (each over the observation's rows) and their
    [target] tables; one state named "" for a plain [target]."""

    names: list[str]
    misfits: list
    specs: list[dict]
    estimated: np.ndarray | None = None  # each state's noise level from its residual (residual_levels), if set

    @property
    def count(self) -> int:
        return len(self.names)

    @property
    def noise(self) -> float | None:
        """The noise std Phi is measured in: the smallest stated noise (the one state's
        own), or None where no state states one (estimated from the residual)."""
        stated = self.stated_noise()
        return None if stated is None else min(stated)

    @property
    def weights(self) -> np.ndarray:
        """Each state's rows' weight, (noise / its noise)^2 with the stated noises, else the
        estimated levels (``estimated``); 1 with neither."""
        stated = self.stated_noise()
        levels = self.estimated if stated is None else np.asarray(stated)
        return np.ones(self.count) if levels is None else (np.min(levels) / levels) ** 2

    def reweigh(self, stacked_misfit, levels: np.ndarray | None) -> None:
        """The states' rows of ``stacked_misfit`` (misfit.stacked of ``misfits``) weighed by
        the noise levels ``levels`` from now on (None: the stated noises, or alike): in
        place, so every holder of that misfit sees it."""
        self.estimated = None if levels is None else np.asarray(levels, float)
        stacked_misfit.weights[:] = np.concatenate([w * m.weights for w, m in zip(self.weights, self.misfits)])

    def residual_levels(self, residual: np.ndarray) -> np.ndarray:
        """Each state's noise level as its own residual shows it: the rms of its weighted
        rows (each state's misfit at its own weights, the stacking's aside), floored at
        LEVEL_FLOOR x the largest and at its target's roughness. Every state has the same
        rows and controls, so the fit's own shrinking of the residual cancels in the
        ratios, which are all the weights use."""
        levels = np.array([max(np.sqrt(2.0 * misfit.cost(rows) / max(int(np.count_nonzero(misfit.weights)), 1)),
                                   misfit.roughness())
                               for misfit, rows in zip(self.misfits, self.split(residual))])
        return np.maximum(levels, LEVEL_FLOOR * levels.max())

    def stated_noise(self) -> list[float] | None:
        """Each state's stated target.noise, or None where none is stated."""
        given = [spec.get("noise") for spec in self.specs]
        if all(g is None for g in given):
            return None
        missing = [name for name, g in zip(self.names, given) if g is None]
        require(not missing, f"[[states]]: target.noise is stated for some states but not for {missing}: "
                             "state it for every state, or for none (one level is then estimated from all)")
        return [float(g) for g in given if g is not None]

    def split(self, stacked: np.ndarray) -> list[np.ndarray]:
        """Rows (or a flat control vector) cut into the states' equal parts."""
        return np.split(stacked, self.count)

    def stack_controls(self, J: np.ndarray) -> np.ndarray:
        """(n, gdim, k) responses of one state's controls -> (S n, gdim, S k), block-diagonal."""
        if self.count == 1:
            return J
        n, gdim, k = J.shape
        out = np.zeros((self.count * n, gdim, self.count * k))
        for i in range(self.count):
            out[i * n:(i + 1) * n, :, i * k:(i + 1) * k] = J
        return out

    def to_motion(self, basis: np.ndarray | None, q: np.ndarray) -> np.ndarray:
        """Every state's loaded-node displacement from its controls (W q_s, or q_s itself)."""
        return q if basis is None else np.concatenate([basis @ qs for qs in self.split(q)])

    def to_controls(self, basis: np.ndarray | None, d: np.ndarray) -> np.ndarray:
        """Every state's controls from its loaded-node displacement (W^T d_s, or d_s)."""
        return d if basis is None else np.concatenate([basis.T @ ds for ds in self.split(d)])

    def distances(self, residual: np.ndarray) -> dict[str, dict]:
        """Each state's distances, from its own rows."""
        return {name: misfit.distances(rows) for name, misfit, rows in zip(self.names, self.misfits, self.split(residual))}


def weigh_by_residuals(problem, profile, spread: float = 1.0) -> bool:
    """Several states with no noise stated: each state's rows weighed by the level of its
    own residual at the profile's best value so far (States.residual_levels) and Phi*
    solved there again; False, with nothing done, where the weights would move by less
    than REWEIGH_SETTLED or the levels lie within ``spread`` x of each other. Run after
    the first solve (only far-apart levels: EARLY_SPREAD), then after each outer loop
    (Estimator.run): the maximum-likelihood answer with each state's noise unknown.
    Weighed alike, one badly segmented state's error counts as much as the other's data
    (and the scan may find E undetermined)."""
    states = problem.states
    if states.count < 2 or states.noise is not None:
        return False
    levels = states.residual_levels(profile.best().evaluation.residual)
    moved = np.abs(np.log((np.min(levels) / levels) ** 2 / states.weights))
    if np.max(levels) <= spread * np.min(levels) or np.all(moved < np.log(REWEIGH_SETTLED)):
        return False
    before, theta = states.estimated, profile.best_theta()
    states.reweigh(problem.misfit, levels)
    log.info("states weighed by their residuals' levels: " + ", ".join(
        f"{name} {level:.3g} (weight {w:.3g})" for name, level, w in zip(states.names, levels, states.weights)))
    try:
        profile.start_over(theta, "weigh")
    except BaseException:  # the best so far stays the one its weights measured
        states.reweigh(problem.misfit, before)
        raise
    return True
