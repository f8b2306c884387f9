"""The profile-likelihood 95 % interval of one constant: where Phi* rises the noise's
threshold above its minimum, and the std that interval stands for.
"""

from __future__ import annotations

import numpy as np


Z95 = 1.959964  # the two-sided 95 % quantile of the standard normal
CHI2_95 = Z95**2  # ... and of chi-square with one degree of freedom (3.841459)


def threshold(noise: float) -> float:
    """How far Phi* rises above its minimum at the ends of the 95 % profile interval,
    CHI2_95 noise^2 / 2 (Phi* / noise^2 is the negative log-likelihood)."""
    return 0.5 * CHI2_95 * noise**2


END_PRECISION = 0.05  # profile_interval: an end bracketed within this share of its distance is found
END_CLOSE = 0.15  # profile_interval: a value within this share of the threshold (in sqrt(Phi* rise)) gives the end


def profile_interval(value, s_hat: float, std: float, noise: float, bounds, tries: int = 8,
                     known=()) -> tuple[float, float]:
    """The 95 % profile-likelihood interval of one constant in s: where Phi*(s) (``value``,
    the controls profiled out) rises CHI2_95 noise^2 / 2 above its minimum -- Phi* /
    noise^2 is the negative log-likelihood. It follows Phi*'s own shape, which the Laplace
    interval (the same for a quadratic Phi*) cannot: a constant that the data bound more
    weakly on one side (a stiff inclusion barely deforms whether 10x or 50x the tissue)
    gets a longer arm there, up to its bound. Secant steps on sqrt(Phi* - Phi*_min),
    linear in s for a quadratic Phi*, from the Laplace ends: 1-2 values per side. A value
    within END_CLOSE of the threshold gives the end by the secant through it, not
    evaluated (exact for a quadratic Phi*; the letter at 0.5 % noise: within 3 % of the
    arm the next values found, where the Laplace end -- 5-25 % off the threshold -- was
    followed by a 1.5x step and a secant, 3 values a side), and so does a bracket
    narrower than END_PRECISION of its distance (a jagged Phi* -- a rough target's
    inner fits hopping between local minima -- has no end more precise than that: on
    the letter at 0.5 % noise the secant took 7 values, each inner fit up to 400
    iterations, to move the end by 1 % of its arm).

    ``known``: (s, Phi*) pairs of the same function already computed (the estimate's
    scan and line searches): they seed each side's bracket, so values are computed only
    between them (the 2D inclusion at 0.5 % noise: its line searches had often been
    within a few % of the profile's values, which computed them again)."""
    phi_hat = value(s_hat)
    target = np.sqrt(0.5 * CHI2_95) * noise
    ends = []
    for direction, bound in ((-1.0, bounds[0]), (1.0, bounds[1])):
        room = abs(bound - s_hat)
        side = [(direction * (s - s_hat), np.sqrt(max(phi - phi_hat, 0.0)) - target) for s, phi in known]
        below, above = _bracket([(0.0, -target)] + [(t, g) for t, g in side if 0 < t <= room])
        laplace = min(Z95 * std, room) if np.isfinite(std) and std > 0 else room
        t, done = _next_offset(below, above, target, room, laplace)
        for _ in range(tries if not done else 0):
            g = np.sqrt(max(value(s_hat + direction * t) - phi_hat, 0.0)) - target
            if g < 0:
                below = (t, g)
                if t >= room:  # still inside at the bound: open to it
                    break
            else:
                above = (t, g)
            t, done = _next_offset(below, above, target, room, t)
            if done:
                break
        ends.append(s_hat + direction * t)
    return ends[0], ends[1]


def _bracket(side) -> tuple[tuple[float, float], tuple[float, float] | None]:
    """(offset, g) of the farthest value inside the interval, and of the nearest one
    outside beyond it (None if none is); ``side`` includes the optimum, (0, -target). On
    a jagged Phi* the values inside and outside interleave: every value inside is one
    the data cannot exclude, so the interval reaches the farthest of them."""
    below = max((t, g) for t, g in side if g < 0)
    outside = [(t, g) for t, g in side if g >= 0 and t > below[0]]
    return below, min(outside) if outside else None


def _next_offset(below, above, target: float, room: float, first: float) -> tuple[float, bool]:
    """The next offset to compute from the bracket so far, and whether it is the end.
    Nothing outside yet: ``first`` if nothing inside either (the Laplace end), else the
    secant from the optimum (g = -target there) through the farthest value inside -- the
    end if that value is within END_CLOSE of the threshold, else at least 1.5x as far
    (a flat Phi* would creep) and no nearer than ``first``. Bracketed: the secant
    within; the end once the value nearer the threshold is within END_CLOSE of it or the
    bracket is narrower than END_PRECISION of its distance (no chasing a jagged Phi*)."""
    (t0, g0) = below
    if above is None:
        if t0 == 0.0:
            return first, False
        if t0 >= room:
            return room, True
        secant = t0 * target / max(g0 + target, 1e-300)
        if abs(g0) < END_CLOSE * target:
            return min(room, secant), True
        return min(room, max(1.5 * t0, secant, first)), False
    t1, g1 = above
    t = t0 + (t1 - t0) * (-g0) / (g1 - g0)
    return t, min(-g0, g1) < END_CLOSE * target or t1 - t0 < END_PRECISION * t


JITTER_NOISE = 1.05  # an inner spread raising the noise level of the threshold less than this leaves the interval
JITTER_STARTS = 6  # other starts for the inner spread, spread over the profile's evaluations


def jitter_noise(noise: float, spread: float) -> float:
    """The noise level whose 95 % profile threshold, CHI2_95 noise^2 / 2, also clears an
    inner spread: Phi* computed from one start lies anywhere up to ``spread`` above the
    inner problem's best minimum, so a value of the constant is excluded only where
    Phi* rises above its minimum by the noise's threshold plus that spread. On the
    phantom at 2 % noise (0.65 mm on organs sampled every 0.3 mm) the inner minima were
    0.01-0.03 apart in Phi* against a threshold of 0.0007, and three draws gave E = 30,
    63, 65 (truth 50) with noise-only intervals ~10 units wide."""
    return float(np.sqrt(noise**2 + 2.0 * spread / CHI2_95))


JAGGED_SHARE = 0.5  # a profile-interval side under this share of the Laplace one is not trusted


def untrusted_sides(ends, s_hat: float, std: float, bounds) -> tuple[tuple[float, float], bool]:
    """The profile interval's ends, each side shorter than JAGGED_SHARE of the Laplace
    one replaced by the Laplace end (within the bounds); and whether any was. A side that
    short means Phi* jumps right beside the answer -- a jagged misfit (inner fits landing
    in other local minima on a rough target), not information: measured, sigmas of
    0.002 % of E on noisy phantom targets. A skewed Phi*'s short side (a stiff
    inclusion's) is ~0.8. A side that ends at its bound is open to it, not short (the
    letter's nu = 0.053 at 0.5 % noise: its side reached nu = 0, then read as jagged and
    replaced by a Laplace end at nu = -0.14, outside the bounds)."""
    reach = Z95 * std
    short = [abs(end - s_hat) < JAGGED_SHARE * reach and end != bound for end, bound in zip(ends, bounds)]
    low = max(s_hat - reach, bounds[0]) if short[0] else ends[0]
    high = min(s_hat + reach, bounds[1]) if short[1] else ends[1]
    return (low, high), any(short)


def profile_std(s, ends, open_ends) -> np.ndarray:
    """One std per constant from its profile interval. Closed at both ends: 1 / sqrt of
    the mean of its two sides' information, each side's (Z95 / arm)^2 -- the curvature
    of the quadratic that rises the threshold over that arm. Open at a bound (Phi*
    stayed below the threshold up to it): the half-width / Z95 -- the bound, not the
    data, ends that side and truncates the answer's scatter there, and the interval's
    extent is the only scale left. Why not the half-width everywhere: on a skewed Phi*
    the long arm says where the data stop excluding values -- the interval's business --
    while the estimates scatter by the information, which adds over the sides where
    lengths do not. The inclusion's E at 0.5 % noise (30 draws): arms / 1.96 of 0.31 and
    0.88 in log E against a spread of the estimates of 0.36; sigma / spread 1.56 from the
    half-width, 1.16 from this. Chosen after measuring several rules (docs/uncertainty.md)."""
    s = np.asarray(s, float)
    ends = np.asarray(ends, float)
    arms = np.abs(ends - s[:, None]) / Z95
    closed = ~np.asarray(open_ends, bool).any(axis=1) & (arms > 0).all(axis=1)
    information = (1.0 / np.where(arms > 0, arms, 1.0) ** 2).mean(axis=1)
    half = (ends[:, 1] - ends[:, 0]) / (2 * Z95)
    return np.where(closed, 1.0 / np.sqrt(information), half)
