"""Gradient checks as a public tool: the Taylor test.

For a differentiable f with gradient g at x, the first-order remainder
|f(x + h d) - f(x) - h g.d| shrinks like h^2; with a wrong gradient it shrinks like h.
``taylor_test`` halves h and returns the observed rates. Near round-off the remainders
stop shrinking and the rates mean nothing: the result says so (``at_roundoff``), so a
test can start from a larger h instead of passing or failing by accident.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TaylorResult:
    rates: np.ndarray  # log2 of successive remainder ratios (2 for a correct gradient)
    remainders: np.ndarray
    steps: np.ndarray
    at_roundoff: bool  # the smallest remainders are at the level of f's round-off

    @property
    def rate(self) -> float:
        """The rate over the last two halvings (the asymptotic one)."""
        return float(np.min(self.rates[-2:]))


def taylor_test(f, x, direction, gradient, h0: float, halvings: int = 4) -> TaylorResult:
    """Rates of |f(x + h d) - f(x) - h g.d| for h = h0, h0/2, ... (``halvings`` times)."""
    x, direction = np.asarray(x, float), np.asarray(direction, float)
    base = float(f(x))
    slope = float(np.dot(gradient, direction))
    steps = h0 / 2.0 ** np.arange(halvings + 1)
    remainders = np.array([abs(float(f(x + h * direction)) - base - h * slope) for h in steps])
    with np.errstate(divide="ignore", invalid="ignore"):
        rates = np.log2(remainders[:-1] / remainders[1:])
    roundoff = 1e-13 * max(abs(base), 1e-300) * 10
    return TaylorResult(rates, remainders, steps, bool(remainders[-1] < roundoff))
