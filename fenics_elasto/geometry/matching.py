"""Iterative surface matching (paper §3.2.1): move surface nodes onto a target.

First each group is aligned affinely (ICP: closest points, then the least-squares
affine map), which gets the smooth, tangential part of organ motion right -- an
inflation or a shift -- where closest points alone would let nodes slide. Then each
step moves every node by  -k_D d(x, S) + k_N (mean of its neighbours' displacement -
its own displacement). The spring term acts on displacements, so it keeps the node
spacing without shrinking the surface; k_N is relaxed so the nodes end on the target.
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


def affine_alignment(points, groups, target, iterations: int = 40) -> np.ndarray:
    """Displacements of a per-group affine ICP fit of ``points`` to ``target``."""
    homogeneous = np.c_[points, np.ones(len(points))]
    x = points.copy()
    for _ in range(iterations):
        goal = x - target.residual(x)
        for g in np.unique(groups):
            rows = groups == g
            if rows.sum() > points.shape[1] + 1:
                M = np.linalg.lstsq(homogeneous[rows], goal[rows], rcond=None)[0]
                x[rows] = homogeneous[rows] @ M
    return x - points


def match_surface(points, groups, target, iterations: int = 60, k_data: float = 0.5,
                  k_spring: float = 0.9, k_spring_final: float = 0.3, affine: bool = True) -> np.ndarray:
    """Displacements that bring ``points`` onto ``target`` (anything with ``residual(x)``: a misfit.SurfaceTerm)."""
    nbrs = neighbours(points, groups)
    u = affine_alignment(points, groups, target) if affine else np.zeros_like(points)
    for k_n in np.geomspace(k_spring, k_spring_final, iterations):
        r = target.residual(points + u)
        u += -k_data * r + k_n * (u[nbrs].mean(axis=1) - u)
    return u
