"""Iterative surface matching (paper §3.2.1): move surface nodes onto a target.

Each step moves every node by  -k_D d(x, S) + k_N (mean of its neighbours' displacement
- its own displacement). The spring term acts on displacements, so it keeps the node
spacing without shrinking the surface; k_N is relaxed over the iterations so the
nodes end on the target.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def neighbours(points: np.ndarray, groups: np.ndarray, k: int = 6) -> np.ndarray:
    """(n, k) indices of each node's k nearest nodes within its own group."""
    out = np.empty((len(points), k), np.int64)
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        kk = min(k + 1, len(rows))
        _, idx = cKDTree(points[rows]).query(points[rows], kk)
        idx = np.atleast_2d(idx)[:, 1:] if kk > 1 else np.zeros((len(rows), 1), np.int64)
        out[rows] = rows[np.pad(idx, ((0, 0), (0, k - idx.shape[1])), mode="edge")]
    return out


def match_surface(points, groups, target, iterations: int = 60, k_data: float = 0.5,
                  k_spring: float = 0.9, k_spring_final: float = 0.3) -> np.ndarray:
    """Displacements that bring ``points`` onto ``target`` (a surface.Target)."""
    nbrs = neighbours(points, groups)
    u = np.zeros_like(points)
    for k_n in np.geomspace(k_spring, k_spring_final, iterations):
        r = target.residual(points + u)
        u += -k_data * r + k_n * (u[nbrs].mean(axis=1) - u)
    return u
