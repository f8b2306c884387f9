"""How sure: the Laplace (Gauss-Newton) posterior of the estimated constants.

With noise std s per residual component, Phi / s^2 is a negative log-posterior: the
data term 1/(2 s^2) |e|^2 and the controls' Gaussian prior alpha/(2 s^2) |q - q0|^2.
At the optimum its Gauss-Newton Hessian in (q, s = (log E, nu)) is

    H = ([A_q A_s]^T [A_q A_s] + diag(alpha, 0)) / s^2

(functional.Linearisation). The controls are nuisance parameters: the marginal
covariance of s is the inverse of the Schur complement

    S = A_s^T (I - A_q (A_q^T A_q + alpha I)^-1 A_q^T) A_s / s^2,

the Hessian of the profile Phi*(s) / s^2. The noise s comes from the residual,
s^2 = |e|^2 / (m - p_eff), m the informative residual components and p_eff the trace
of the hat matrix (the effective number of fitted parameters), unless ``[target] noise``
gives it -- or unless the target surfaces themselves are rougher: the closest point to
a rough surface is its nearest spike, so the residual sees 0.4-0.7x a measured
surface's noise, while a local quadratic fit of the surface's own vertices sees it
(Surface.roughness); s is the larger of the two. In log E the interval is symmetric; reported in E it is not.

That counts every residual row as independent noise. A residual that is structured in
space -- a voxelised or re-meshed target's staircase, a source mesh too coarse for the
target's shape -- moves the answer far more than noise of its size: on the real prostate
a 1 mm voxel target (residual 0.05 mm) put E +5.9 % off with a noise std of 1.9 %, and
smoothing that target (its rms distance to the truth 0.05 -> 0.025 mm) moved E
another +7 %. So the residual's own spatial patches are asked too (``patch_covariance``:
a cluster-robust sandwich) and where they disagree more than noise would, the std and
the interval are widened to theirs (measured there: 2.6x, the interval then holding the
truth). What remains unstated is a bias the residual cannot show: bases that cannot
represent the wall motion (reduction.missing_wall_motion warns about it), a target
offset as a whole (reported by ``target_offset``, not added). Identifiability: a
constant whose 95 % interval spans its bounds is not determined by the data,
nor one whose effect the controls mimic nearly all of (``separable``) -- unless, a
single constant, its Phi* over the start scan clearly rises all the same (``scan_sees``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fenics_elasto.inverse.linearisation import Linearisation
from fenics_elasto.model.scene import shift_in_units
from fenics_elasto.inverse.uncertainty.profile_interval import Z95, profile_std


# Measured share of a constant's effect the controls cannot mimic: 0.58 (letter A nu),
# 0.76 (a user's inclusion E, vertices only), 0.91 (phantom E, bases); 0.011 for the
# phantom's E in the full force space, where every E fits the organ surfaces.
SEPARABLE_MIN = 0.05


@dataclass
class Posterior:
    labels: list[str]
    s: np.ndarray  # the optimum in s = (log E, nu)
    covariance: np.ndarray  # of s
    noise_std: float
    noise_source: str  # "given" | "the residual" | "the target's roughness" | "the landmarks' stated noise"
    dof: float  # m - p_eff
    is_E: np.ndarray
    separable: np.ndarray  # per constant: the share of its effect the controls cannot mimic (0: none)
    residual_std: float = 0.0  # the noise the residual alone shows
    profile_s: np.ndarray | None = None  # (n, 2) the profile-likelihood 95 % interval in s, where computed
    profile_open: np.ndarray | None = None  # (n, 2) its ends that lie at their bounds (Phi* stayed below the threshold)
    patch_covariance: np.ndarray | None = None  # of s, from how the residual's patches pull (patch_covariance)
    offset: tuple | None = None  # (delta, ds): a target offset out by delta and how far s moves (target_offset)
    inner_spread: float | None = None  # how far apart the inner fit's minima at the answer are, where measured
    model_parts_s: dict[str, np.ndarray] | None = None  # the model's own error: part -> std in s (parts.py)
    mesh_shift_s: np.ndarray | None = None  # how far a degree higher would move the answer, where computed (parts.py)
    prior_shift_s: np.ndarray | None = None  # how far a 100x weaker prior would move it, where measured (report.prior_shift)
    mesh_moves: tuple[float, float] | None = None  # the degree-3 solve's move of the observed points, and their motion
    rank_part_s: np.ndarray | None = None  # the half-rank shift's share of the bases part, where measured (parts.py)

    @property
    def method(self) -> str:
        return "profile likelihood" if self.profile_s is not None else "laplace"

    @property
    def noise_part_s(self) -> np.ndarray:
        """In s: the noise std (noise_std_s), widened to the patch std where the residual
        is structured (``widening``)."""
        return self.noise_std_s * self.widening

    @property
    def model_std_s(self) -> np.ndarray:
        """In s: the std of the model's own error, its parts (mesh, bases) added in quadrature."""
        parts = list((self.model_parts_s or {}).values())
        return np.sqrt(sum(p**2 for p in parts)) if parts else np.zeros(len(self.labels))

    @property
    def std_s(self) -> np.ndarray:
        """In s: the noise part and the model's own error together."""
        return np.hypot(self.noise_part_s, self.model_std_s)

    def parts_s(self) -> dict[str, np.ndarray]:
        """Each source of error's std in s: the noise, then the model's parts."""
        return {"noise": self.noise_part_s, **(self.model_parts_s or {})}

    def set_profile(self, ends, bounds) -> None:
        """The profile-likelihood interval of the single estimated constant (in s), and
        which of its ends are open (at their bound)."""
        self.profile_s = np.array([ends], float)
        self.profile_open = np.isclose(self.profile_s, np.array([bounds], float), rtol=0.0, atol=1e-12)

    @property
    def noise_std_s(self) -> np.ndarray:
        """The Laplace std, or where the profile interval exists ``profile_std``'s."""
        if self.profile_s is not None:
            return profile_std(self.s, self.profile_s, self.profile_open)
        return self.laplace_std_s

    @property
    def laplace_std_s(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def patch_std_s(self) -> np.ndarray:
        if self.patch_covariance is None:
            return np.zeros(len(self.labels))
        return np.sqrt(np.maximum(np.diag(self.patch_covariance), 0.0))

    @property
    def widening(self) -> np.ndarray:
        """Per constant, >= 1: the patch std over the noise std where it is larger -- a
        residual that is structured in space (patches of the target disagree) moves the
        answer more than independent noise of its size would."""
        base = self.noise_std_s
        ok = np.isfinite(base) & (base > 0) & np.isfinite(self.patch_std_s)
        return np.where(ok, np.maximum(1.0, self.patch_std_s / np.where(ok, base, 1.0)), 1.0)

    def interval(self, level: float = Z95) -> np.ndarray:
        """(n, 2) the 95 % interval of each constant in its own units (E: from log E): the
        profile likelihood's where it was computed, else the Laplace one; each side
        stretched by ``widening``."""
        if self.profile_s is not None and level == Z95:
            low, high = self.profile_s.T
        else:
            low, high = self.s - level * self.laplace_std_s, self.s + level * self.laplace_std_s
        model = level * self.model_std_s
        low = self.s - np.hypot(self.widening * (self.s - low), model)
        high = self.s + np.hypot(self.widening * (high - self.s), model)
        return np.stack([np.where(self.is_E, np.exp(low), low), np.where(self.is_E, np.exp(high), high)], axis=1)

    def std(self) -> np.ndarray:
        """Each constant's std in its own units (E: delta method, E sigma_logE)."""
        return self.in_units(self.std_s)

    def in_units(self, sd_s: np.ndarray) -> np.ndarray:
        """A std in s -> in each constant's own units (E: delta method, E sigma_logE)."""
        value = np.where(self.is_E, np.exp(self.s), self.s)
        return np.where(self.is_E, value * sd_s, sd_s)

    def correlation(self) -> np.ndarray:
        d = np.where(self.laplace_std_s > 0, self.laplace_std_s, 1.0)
        return self.covariance / np.outer(d, d)

    def spans_bounds(self, bounds_s: list) -> np.ndarray:
        """Per constant: does its 95 % interval (in s) cover its bounds? A profile interval
        (clipped to them) reaching both, a Laplace one at least as wide; an infinite std."""
        low, high = np.array(bounds_s, float).reshape(len(self.labels), 2).T
        if self.profile_s is not None:
            ends = self.s[:, None] + self.widening[:, None] * (self.profile_s - self.s[:, None])
            return (ends[:, 0] <= low + 1e-12) & (ends[:, 1] >= high - 1e-12)
        sd = self.std_s
        return ~np.isfinite(sd) | (2 * Z95 * sd >= (1.0 - 1e-9) * (high - low))

    def mimicked(self) -> np.ndarray:
        """Per constant: can the boundary controls mimic nearly all of its effect on the
        data here (``separable`` below SEPARABLE_MIN)?"""
        return np.asarray(self.separable) < SEPARABLE_MIN

    def undetermined(self, bounds_s: list, seen=()) -> dict[str, str]:
        """The constants the data do not determine, and why: the boundary controls can
        mimic nearly all of its effect on the data (``separable`` below SEPARABLE_MIN:
        any value fits, noise or not), or its 95 % interval (in s) spans its bounds (the
        noise hides it: a Laplace interval as wide, a profile interval open at both).
        The constants in ``seen`` were shown by other means to be seen by the data
        (``scan_sees``): only their interval counts."""
        out = {}
        for label, spans, share, mimicked in zip(self.labels, self.spans_bounds(bounds_s), self.separable,
                                                 self.mimicked()):
            if mimicked and label not in seen:
                out[label] = f"the boundary forces can mimic {100 * (1 - share):.1f} % of its effect on the data"
            elif spans:
                out[label] = "its 95 % interval spans its bounds"
        return out


def posterior_record(post: Posterior) -> dict:
    """result.json's ``uncertainty``: per constant its std, interval and the parts of its
    std; how the noise was found; what widened or could move the answer."""
    labelled = lambda values: {label: float(v) for label, v in zip(post.labels, values)}  # noqa: E731
    parts = {part: post.in_units(sd) for part, sd in post.parts_s().items()}
    out: dict[str, object] = {label: {"std": float(sd), "ci95": [float(lo), float(hi)],
                                      "parts": {part: float(v[i]) for part, v in parts.items()}}
                              for i, (label, sd, (lo, hi)) in enumerate(zip(post.labels, post.std(), post.interval()))}
    out["separable"] = labelled(post.separable)
    out["noise_std"] = post.noise_std
    out["noise"] = {"given": "given", "the residual": "estimated from the residual",
                    "the target's roughness": "the target's roughness",
                    "the landmarks' stated noise": "the landmarks' stated noise"}[post.noise_source]
    out["residual_noise_std"] = post.residual_std
    out["interval"] = post.method
    out["dof"] = post.dof
    if post.patch_covariance is not None:
        out["noise_only_std"] = labelled(post.in_units(post.noise_std_s))
        out["patch_std"] = labelled(post.in_units(post.patch_std_s))
        out["widened"] = labelled(post.widening)
    if post.offset is not None:
        delta, ds = post.offset
        shift = shift_in_units(post.is_E, ds)
        out["target_offset"] = {"offset": delta, "shift": {label: float(v) if np.isfinite(v) else None
                                                            for label, v in zip(post.labels, shift)}}
    if post.inner_spread is not None:
        out["inner_spread"] = post.inner_spread
    if post.mesh_shift_s is not None:
        out["mesh_shift"] = labelled(shift_in_units(post.is_E, post.mesh_shift_s))
    if post.prior_shift_s is not None:
        out["prior_shift"] = labelled(shift_in_units(post.is_E, post.prior_shift_s))
    if len(post.labels) > 1:
        out["correlation"] = post.correlation().tolist()
    return out


def posterior_at(profile, result, noise: float | None = None, floor: float = 0.0,
                 floor_from: str = "the target's roughness") -> Posterior | None:
    """The posterior at one of the profile's solves, where it has a Linearisation (every
    Gauss-Newton solve; with L-BFGS the answer, once Estimator.linearise_answer made
    one); None otherwise."""
    lin = profile.linearisation(result)
    if lin is None:
        return None
    s = next(s for s, r, _ in profile.solved if r is result)
    params = profile.params
    post = laplace(lin, params.labels, s, params.is_E, noise, floor, floor_from)
    post.patch_covariance = patch_covariance(lin, result.evaluation.y, profile.problem.states.count)
    return post


OFFSET_SHARE = 0.1  # the segmentation bias reported: this share of the targets' mean edge


def target_offset(misfit, lin: Linearisation, evaluation) -> tuple[float, np.ndarray] | None:
    """(delta, ds): how far s moves (first order, the controls following) when every
    closed target surface is moved out along its normal by delta -- a segmentation that
    is too big all round by a tenth of its own resolution (OFFSET_SHARE of the mean
    edge). The residual cannot show such a bias; with organ surfaces only E rests on
    motions of micrometres (the real prostate: 4-7 um out moved E by -0.82 %, this
predicts -0.85 %). None
    without a closed target surface."""
    dr = misfit.offset_residual(evaluation.y) if misfit is not None else None
    if dr is None:
        return None
    delta = OFFSET_SHARE * float(np.mean([s.mean_edge for s in misfit.surfaces]))
    rows = misfit.statistical_rows(evaluation.y, evaluation.residual)
    return delta, delta * offset_shift(lin, np.einsum("lkd,ld->lk", rows, dr).ravel())


def laplace(lin: Linearisation, labels, s, is_E, noise: float | None = None, floor: float = 0.0,
            floor_from: str = "the target's roughness") -> Posterior:
    """The posterior of s from a Linearisation at the optimum (noise: known std or None;
    ``floor``: the least noise std the data allow, which the residual may underestimate --
    the targets' roughness, or what stated landmark noise asks -- named by ``floor_from``)."""
    B, schur = lin.profiled()
    # tr(A H^-1 A^T), the fitted parameters: the controls' share plus tr(S^-1 B^T B)
    hat = lin.fitted_controls() + np.trace(np.linalg.lstsq(schur, B.T @ B, rcond=None)[0])
    dof = max(lin.informative - hat, 1.0)
    residual_std = float(np.sqrt(np.sum(lin.residual**2) / dof))
    noise_std = float(noise) if noise is not None else max(residual_std, floor)
    covariance = noise_std**2 * _inverse(schur)
    own = lin.sensitivity()
    separable = np.diag(schur) / np.where(own > 0, own, 1.0)
    source = "given" if noise is not None else floor_from if floor > residual_std else "the residual"
    return Posterior(list(labels), np.asarray(s, float), covariance, noise_std, source, float(dof),
                     np.asarray(is_E, bool), separable, residual_std)


def patch_covariance(lin: Linearisation, positions: np.ndarray, states: int = 1) -> np.ndarray:
    """The covariance of s from the residual itself, robust to errors correlated in space
    (a cluster-robust sandwich): the first-order pull of residual row l on s is
    S^-1 b_l e_l, b_l the row of A_s with the controls profiled out; summed over spatial
    patches P (recursive bisection of the observed positions into ~sqrt(n) patches),

        C = S^-1 (sum_P g_P g_P^T) S^-1 P/(P-1),   g_P = sum_{l in P} b_l e_l.

    At the optimum the pulls cancel overall; how strongly whole patches disagree is what
    a structured residual (a target's staircase or remeshing, a source mesh too coarse)
    does to the answer -- which the Laplace covariance, counting every row as independent
    noise, cannot see. Several states' rows (``states`` equal blocks) are patched each on
    its own: one segmentation's errors do not correlate with another's."""
    B, S_inv, known = _profiled(lin)
    gdim = positions.shape[1]
    patch = state_patches(positions, states)[np.arange(len(lin.residual)) // gdim]
    count = int(patch.max()) + 1
    pulls = np.stack([np.bincount(patch, B[:, k] * lin.residual, minlength=count) for k in range(B.shape[1])], axis=1)
    out = known @ (pulls.T @ pulls) @ known * count / (count - 1)
    return np.where(np.isfinite(S_inv), out, np.inf)


def _profiled(lin: Linearisation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B, S^-1, S^-1 with its infinite entries zeroed): the sensitivity in s with the
    controls profiled out, B = A_s - A_q (A_q^T A_q + alpha I)^-1 A_q^T A_s, and the
    inverse Schur complement S = A_s^T B, infinite along undetermined constants -- zeroed
    for products (then marked inf or NaN by the caller, not inf * 0). A change de of the
    residual moves the optimum by ds = -S^-1 B^T de."""
    B, schur = lin.profiled()
    S_inv = _inverse(schur)
    return B, S_inv, np.where(np.isfinite(S_inv), S_inv, 0.0)


def offset_shift(lin: Linearisation, de: np.ndarray) -> np.ndarray:
    """ds (first order) when the weighted residual changes by ``de`` and the controls
    follow: -S^-1 B^T de."""
    return offset_matrix(lin) @ de


def offset_matrix(lin: Linearisation) -> np.ndarray:
    """-S^-1 B^T: ``offset_shift``'s map from the weighted residual's change to ds; NaN
    rows for an undetermined constant (no first order)."""
    B, S_inv, known = _profiled(lin)
    return np.where(np.isfinite(np.diag(S_inv))[:, None], -known @ B.T, np.nan)


def state_patches(positions: np.ndarray, states: int) -> np.ndarray:
    """A patch index per row: each state's block of rows bisected into ~sqrt(its rows) patches."""
    out, first = [], 0
    for block in np.split(positions, states):
        patch = spatial_patches(block, max(2, round(np.sqrt(len(block)))))
        out.append(patch + first)
        first += int(patch.max()) + 1
    return np.concatenate(out)


def spatial_patches(points: np.ndarray, count: int) -> np.ndarray:
    """A patch index per point: recursive bisection at the median of the longest extent,
    until there are about ``count`` patches of equal size (deterministic)."""
    patch = np.zeros(len(points), int)
    groups = [np.arange(len(points))]
    while len(groups) < count and max(len(g) for g in groups) > 1:
        g = groups.pop(int(np.argmax([len(g) for g in groups])))
        axis = int(np.argmax(np.ptp(points[g], axis=0)))
        order = g[np.argsort(points[g, axis], kind="stable")]
        groups += [order[: len(g) // 2], order[len(g) // 2:]]
    for i, g in enumerate(groups):
        patch[g] = i
    return patch


def _inverse(S: np.ndarray) -> np.ndarray:
    """S^-1 for a symmetric positive semidefinite S; directions S does not see: inf."""
    w, V = np.linalg.eigh((S + S.T) / 2)
    tiny = w <= 1e-14 * max(float(np.abs(w).max()), 1e-300)
    inv = np.where(tiny, np.inf, 1.0 / np.where(tiny, 1.0, w))
    with np.errstate(invalid="ignore"):
        out = (V * inv) @ V.T
    return np.where(np.isnan(out), np.inf, out)
