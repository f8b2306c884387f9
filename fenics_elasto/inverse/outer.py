"""The outer loop over the materials: the start scan's grid, Phi* minimised in s = (log E, nu)
with every value solved in full (cubic steps inside a bracket, or bounded L-BFGS-B), or
on the reduced-basis surrogate with its optimum solved in full.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from fenics_elasto.util.logs import log
from fenics_elasto.inverse.profile import LOOSE, Profile, SurrogateProfile


BRACKET_GUARD = 0.05  # bracketed_minimum: a step keeps this share of the bracket from its ends


def scan_grid(params, n: int) -> list[np.ndarray]:
    """The start scan: a grid of n values per estimated constant at the centres of n equal
    parts of its bounds (log-spaced for E)."""
    q = (np.arange(n) + 0.5) / n
    low, high = np.array(params.bounds, float).reshape(len(params), 2).T
    s_low, s_high = params.to_s(low), params.to_s(high)
    axes = [params.to_theta(s_low + qi * (s_high - s_low)) for qi in q]
    return [np.array([axes[i][k] for k, i in enumerate(index)])
            for index in itertools.product(range(n), repeat=len(params))]


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
        (x, f, g), downhill = _lowest_and_downhill(points)
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


def surrogate_scan(surrogate: SurrogateProfile, points) -> tuple[np.ndarray, list[float], list]:
    """Phi* on the surrogate at each scan point (dense algebra, no factorization): the
    best of them and of the full solves, in s, the values scanned, and (s, Phi*,
    dPhi*/ds) of each point (what a bracket search starts from)."""
    profile, params = surrogate.profile, surrogate.params
    best_s, best = params.to_s(profile.best_theta()), profile.best().value
    values, known = [], []
    for theta in points:
        s = params.to_s(theta)
        value, gradient = surrogate.value_and_gradient(s)
        values.append(value)
        known.append((s, value, gradient))
        log.info(f"  scan  {params.describe(theta)}  Phi* ~ {values[-1]:.6e}  (surrogate)")
        if values[-1] < best:
            best_s, best = s, values[-1]
    return best_s, values, known


def minimize_on_surrogate(profile: Profile, surrogate: SurrogateProfile, xtol: np.ndarray, maxiter: int,
                          start=None, scanned=(), smooth: bool = True, settled_within=None) -> int:
    """Optimise s on the surrogate (from ``start``, then from the best full solve), solve
    its optimum in full (a new snapshot), repeat until the optimum lands where a full
    solve already is: within ``xtol``, or within ``settled_within(xtol)`` (per constant,
    in s) where given. One constant on a ``smooth`` Phi*: cubic steps inside a bracket
    (first the ``scanned`` points', (s, Phi*, dPhi*/ds) each, then one made around the
    best full solve), as the full-space loop; on a rough one Brent's search on values in
    such a bracket; several: bounded L-BFGS-B (``surrogate_minimum``). Returns the rounds."""
    params = profile.params
    method = "L-BFGS-B" if len(params) > 1 else "cubic steps" if smooth else "Brent's search"
    log.info(f"outer {method} on the reduced-basis response "
             f"in the materials ({profile.surrogate.size} directions)")
    for rounds in range(1, maxiter + 1):
        x0 = start if start is not None and rounds == 1 else params.to_s(profile.best_theta())
        # The surrogate's minimum is placed as finely as the loop's end needs it: to the
        # share of the noise std that settles the loop (Estimator.settled_within), not to
        # xtol alone: on a rough target (bounded L-BFGS-B, each evaluation a whole inner
        # fit) the pelvis phantom with 0.5 mm of segmentation noise (sigma 11 % of E)
        # spent 22 + 17 inner fits placing E to 1e-4.
        within = xtol if settled_within is None else settled_within(xtol)
        x, evaluations = surrogate_minimum(surrogate, x0, within, scanned if rounds == 1 else (), smooth)
        theta = params.to_theta(x)
        log.info(f"  surrogate optimum {params.describe(theta)}  ({evaluations} evaluations)")
        if any(np.all(np.abs(x - s) < within) for s, _, stage in profile.solved if stage != LOOSE):
            return rounds
        profile.solve(theta, "outer")
    return maxiter


BRACKET_STEP = 0.02  # _bracketed_on_surrogate: the first trial step around the start, in s (2 % of E)


def surrogate_minimum(surrogate: SurrogateProfile, x0, xtol, known=(), smooth: bool = True,
                      step: float = BRACKET_STEP, bounds=None) -> tuple[np.ndarray, int]:
    """The minimum of Phi* on the surrogate near x0 and the evaluations it took: for one
    constant on a ``smooth`` Phi*, cubic steps inside a bracket (the ``known`` points',
    (s, Phi*, dPhi*/ds) each, if they make one, else one made by steps from x0 that
    double from ``step``); on a rough one, Brent's search on values in such a bracket;
    else bounded L-BFGS-B. Within ``bounds`` (per constant, in s; the parameters' own by
    default)."""
    # Each evaluation is a whole inner fit, exact only to the inner tolerance: cubic steps
    # and L-BFGS-B stop once a step moves every constant by less than xtol / 10, not
    # chase digits of Phi*; Brent's search stops on its bracket's width, xtol itself.
    bounds = surrogate.params.s_bounds() if bounds is None else bounds
    found = None
    if len(surrogate.params) == 1 and smooth:
        found = _bracketed_on_surrogate(surrogate, x0, list(known), 0.1 * float(xtol[0]), step, bounds[0])
    elif len(surrogate.params) == 1:
        found = _brent_on_surrogate(surrogate, x0, list(known), float(xtol[0]), step, bounds[0])
    return found if found is not None else _lbfgsb_on_surrogate(surrogate, x0, 0.1 * xtol, bounds)


def _brent_on_surrogate(surrogate: SurrogateProfile, x0, known: list, xtol: float, first_step: float,
                        bounds) -> tuple[np.ndarray, int]:
    """The minimum of one constant on a rough Phi* by Brent's bounded search on values
    alone, to ``xtol``, in a bracket around the lowest of x0 and the ``known`` points
    ((s, Phi*, slope) each; ``bracket``). On a rough target the inner fits' minima
    differ from one value to the next by more than the data's noise moves Phi*, so its
    slope is mostly that difference and a gradient method chases it: on the pelvis
    phantom with 0.5 mm of segmentation noise, bounded L-BFGS-B took 11 + 61 + 21 inner
    fits (250 s in all) placing E to 1e-3 in log E, with sigma 0.18 there."""
    values = {float(s[0]): float(v) for s, v, _ in known}
    before = len(values)
    value = remembered_values(surrogate, values)
    value(x0[0])
    low, high = bracket(value, values, min(values, key=values.__getitem__), first_step, bounds)
    if high - low > xtol:
        minimize_scalar(value, bounds=(low, high), method="bounded", options={"xatol": xtol})
    return np.array([min(values, key=values.__getitem__)]), len(values) - before


def remembered_values(surrogate: SurrogateProfile, values: dict) -> Callable[[float], float]:
    """Phi* of one constant at s on ``surrogate``, each s fitted once (``values`` holds
    those fitted, and those known before)."""
    def value(x) -> float:
        x = float(x)
        if x not in values:
            values[x] = float(surrogate.value_and_gradient(np.array([x]))[0])
        return values[x]

    return value


def bracket(value, values: dict, x: float, step: float, bounds) -> tuple[float, float]:
    """(low, high) around a minimum of ``value`` (``values``: those known, x the lowest):
    on each side, steps from the lowest that double from ``step`` (at most 6) until a
    point above it lies there, or the bound."""
    for side, bound in ((-1.0, bounds[0]), (1.0, bounds[1])):
        size = step
        for _ in range(6):
            if _above(values, x, side) is not None or x == bound:
                break
            trial = float(np.clip(x + side * size, *bounds))
            if value(trial) < values[x]:
                x = trial
            size *= 2
    low, high = _above(values, x, -1.0), _above(values, x, 1.0)
    return (bounds[0] if low is None else low), (bounds[1] if high is None else high)


def _above(values: dict, x: float, side: float) -> float | None:
    """The nearest point on this side of x with a higher value, if any."""
    higher = [y for y, v in values.items() if (y - x) * side > 0 and v > values[x]]
    return min(higher, key=lambda y: abs(y - x)) if higher else None


def _lbfgsb_on_surrogate(surrogate: SurrogateProfile, x0, xtol, bounds) -> tuple[np.ndarray, int]:
    scale = max(surrogate.profile.best().value, 1e-300)

    def scaled(s):
        value, gradient = surrogate.value_and_gradient(s)
        return value / scale, gradient / scale

    res = minimize(scaled, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                   callback=Settle(x0, xtol), options={"maxiter": 100, "ftol": 1e-14, "gtol": 1e-10})
    return res.x, int(res.nfev)


def _bracketed_on_surrogate(surrogate: SurrogateProfile, x0, known: list, xtol: float,
                            first_step: float, bounds) -> tuple[np.ndarray, int] | None:
    """The minimum of one constant by cubic steps on the surrogate, from the ``known``
    points or, without a bracket among them, from x0 and steps downhill of it that
    double until the slope turns (at most 6; a bound the slope still falls at is the
    minimum; None if none turns: L-BFGS-B then).
    (The phantom's rank-80 estimate: L-BFGS-B spent 22 + 18 inner fits here, each ~45
    closest-point queries on the target.)"""
    points = [(float(s[0]), float(v), float(g[0])) for s, v, g in known]
    evaluated: list[tuple[float, float, float]] = []

    def slope(x: float) -> tuple[float, float]:
        value, gradient = surrogate.value_and_gradient(np.array([x]))
        evaluated.append((x, float(value), float(gradient[0])))
        return float(value), float(gradient[0])

    if not _brackets(points):
        low, high = bounds
        x = float(x0[0])
        points = [(x, *slope(x))]
        step = -np.sign(points[0][2]) * first_step
        for _ in range(6):
            trial = float(np.clip(x + step, low, high))
            if trial == points[-1][0]:  # at the bound, still downhill (else it would bracket)
                return np.array([trial]), len(evaluated)
            points.append((trial, *slope(trial)))
            if _brackets(points):
                break
            step *= 2
    if bracketed_minimum(slope, points, xtol, 40) is None:
        return None
    best = min(points + evaluated, key=lambda p: p[1])
    return np.array([best[0]]), len(evaluated)


def _lowest_and_downhill(points: list) -> tuple[tuple[float, float, float], list]:
    """The lowest of these (x, f, f') points, and the points on its downhill side."""
    x, f, g = min(points, key=lambda p: p[1])
    return (x, f, g), [p for p in points if (p[0] - x) * g < 0]


def _brackets(points: list) -> bool:
    """Whether the lowest of these points is a minimum or has another on its downhill side."""
    if not points:
        return False
    lowest, downhill = _lowest_and_downhill(points)
    return lowest[2] == 0.0 or bool(downhill)
