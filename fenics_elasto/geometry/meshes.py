"""Small helpers on simplex meshes given as integer rows: edges, and rows numbered alike."""

from __future__ import annotations

import numpy as np
from scipy import sparse


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


def rings(cells: np.ndarray, count: int, dim: int) -> tuple[sparse.csr_matrix, np.ndarray, np.ndarray]:
    """(vertex adjacency, valence per vertex, rim) of ``count`` points joined by simplex
    ``cells`` (segments in 2D, triangles in 3D): the umbrella Laplacian's parts --
    adjacency @ x / valence - x is each vertex's offset to its neighbours' mean. Rim
    vertices have no full ring of neighbours: open borders in 3D (e.g. pieces written
    apart), polyline ends and junctions in 2D."""
    n = count
    edges = np.sort(cells, axis=1) if dim == 2 else triangle_edges(cells)
    first, which = unique_rows(edges)
    edges, uses = edges[first], np.bincount(which)
    valence = np.bincount(edges.ravel(), minlength=n)
    rim = np.zeros(n, bool)
    rim[edges[uses < 2].ravel()] = dim == 3
    if dim == 2:
        rim[valence != 2] = True
    ones = np.ones(len(edges))
    adjacency = sparse.coo_matrix((np.r_[ones, ones], (np.r_[edges[:, 0], edges[:, 1]],
                                                      np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
    return adjacency, valence, rim
