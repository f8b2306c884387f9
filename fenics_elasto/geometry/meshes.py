"""Small helpers on simplex meshes given as integer rows: edges, and rows numbered alike."""

from __future__ import annotations

import numpy as np


def triangle_edges(triangles: np.ndarray) -> np.ndarray:
    """The edges 01, 12, 20 of each triangle as vertex pairs sorted within each row."""
    return np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first occurrence of each distinct row, each row's distinct index): np.unique(axis=0)
    without its slow structured sort."""
    order = np.lexsort(rows.T[::-1])
    starts = np.r_[True, np.any(np.diff(rows[order], axis=0) != 0, axis=1)]
    inverse = np.empty(len(rows), np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return order[starts], inverse


def quadratic_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges of gmsh 6-node triangles (v0, v1, v2, e01, e12, e20): (vertex pairs,
    sorted within each row; the edge's midpoint node), three rows per triangle."""
    return triangle_edges(triangles), triangles[:, 3:6].ravel()


def row_keys(rows: np.ndarray) -> np.ndarray:
    """One integer per row of non-negative integers, equal for equal rows (np.unique on
    rows is slow); rows of numbers too large to combine get their rank among the rows."""
    base = int(rows.max(initial=0)) + 1
    if base ** rows.shape[1] >= 2**63:
        return np.unique(rows, axis=0, return_inverse=True)[1].ravel().astype(np.int64)
    keys = np.zeros(len(rows), np.int64)
    for column in rows.T:
        keys = keys * base + column
    return keys
