"""Smooth random fields: Gaussian-process samples by random Fourier features.

A zero-mean, unit-variance field with the squared-exponential covariance
exp(-|x - y|^2 / (2 L^2)) is approximated by sqrt(2/F) sum_f w_f cos(omega_f . x + b_f)
with omega ~ N(0, I / L^2), b ~ U(0, 2 pi), w ~ N(0, 1) (Rahimi & Recht 2007). The draws
depend only on the random generator, never on where the field is evaluated: one seed is
one function of space, the same on every mesh that samples it.
"""

from __future__ import annotations

import numpy as np

FEATURES = 64


class SmoothFields:
    """``count`` independent fields of ``components`` components each, in ``dim`` dimensions."""

    def __init__(self, count: int, components: int, dim: int, length: float, rng):
        self.omega = rng.standard_normal((count, components, FEATURES, dim)) / length
        self.phase = rng.uniform(0.0, 2 * np.pi, (count, components, FEATURES))
        self.weight = rng.standard_normal((count, components, FEATURES))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(count, n, components) values at the points (n, dim). One field at a time: all
        at once, the waves alone took count x components x FEATURES x n doubles (400
        tractions at a 24k-node mesh's nodes: 19 GB)."""
        out = np.empty((len(self.weight), len(points), self.weight.shape[1]))
        for c, (omega, phase, weight) in enumerate(zip(self.omega, self.phase, self.weight)):
            waves = np.cos(np.einsum("kfd,nd->kfn", omega, points) + phase[..., None])
            out[c] = np.sqrt(2.0 / FEATURES) * np.einsum("kf,kfn->nk", weight, waves)
        return out
