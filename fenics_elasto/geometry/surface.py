"""Targets and closest-point distances.

A target is a surface (3D triangles or 2D segments) or a set of landmarks. For the
matched nodes at positions x the residual is r = x - cp(x, S), the gradient of
1/2 |d(x, S)|^2 almost everywhere.

Closest points are exact point-to-simplex projections through libigl's AABB tree
(``point_mesh_squared_distance``). Measured on 10^5 points against a 44k-triangle
surface (benchmarks/gradient.py): libigl 0.36 s, VTK's static cell locator 1.2 s,
equal to 1e-15.
"""

from __future__ import annotations

from typing import Any

import igl
import numpy as np

from fenics_elasto.geometry.meshes import rings

# Queries a Surface remembers: a Gauss-Newton iteration tries both curvature models'
# steps, then asks the curvature at the one it took -- with one remembered, that was a
# fresh query half the time (the pelvis phantom's two states: ~4,500 of 27,000).
RECENT = 2


def _barycentric(p, corners):
    """Barycentric coordinates of points p in their simplex (segments or triangles)."""
    a = corners[:, 0]
    edges = corners[:, 1:] - a[:, None]  # (n, k-1, dim)
    gram = np.einsum("nid,njd->nij", edges, edges)
    rhs = np.einsum("nid,nd->ni", edges, p - a)
    lam = np.linalg.solve(gram + 1e-300 * np.eye(gram.shape[1]), rhs[..., None])[..., 0]
    return np.c_[1.0 - lam.sum(axis=1), lam]


class Surface:
    """Triangles (3D) or segments (2D) with exact closest-point queries."""

    def __init__(self, points: np.ndarray, cells: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.cells = np.ascontiguousarray(cells, dtype=np.int64)
        self.dim = self.points.shape[1]
        self._tree: Any = None  # libigl AABB tree (3D), built on the first query
        self._recent: list[list] = []  # [x, simplex, cp, features or None] of the latest queries, newest first
        self.smoothed_from: float | None = None  # the roughness of the surface smoothing.smoothed made this one from
        self.noise_gain = 1.0  # smoothing.smoothed: the share of white noise its filter let through
        self.voxels: np.ndarray | None = None  # (3, 3) the edges (columns) of the label map's voxels it was made from
        self._outward: Any = None  # outward(): per face the unit normal out of the enclosed volume, or False (open, 2D)

        corners = self.points[self.cells]
        if self.dim == 2:
            t = corners[:, 1] - corners[:, 0]
            normals = np.c_[t[:, 1], -t[:, 0]]
        else:
            normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        self.area_normals = normals  # |n| = the facet's length (2D) or twice its area (3D)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.normals = normals / np.where(length > 0, length, 1.0)

    def closest(self, x: np.ndarray) -> np.ndarray:
        return self._query(x)[1]

    @property
    def extent(self) -> float:
        """The diagonal of the bounding box."""
        return float(np.linalg.norm(np.ptp(self.points, axis=0))) if len(self.points) else 0.0

    @property
    def mean_edge(self) -> float:
        """The mean edge length: how finely the surface resolves a shape."""
        corners = self.points[self.cells]
        return float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).mean()) if len(self.cells) else 0.0

    def _query(self, x):
        simplex, cp = self._recall(x)[1:3]
        return simplex, cp.copy()

    def _recall(self, x) -> list:
        """[x, simplex, cp, features] of a query at x: one of the RECENT latest if it was
        at this x, else a new one (features None until _features fills them in)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        for entry in self._recent:
            if entry[0].shape == x.shape and np.array_equal(entry[0], x):
                return entry
        if len(x) == 0:
            return [x.copy(), np.zeros(0, np.int64), x.copy(), None]
        if self.dim == 2:  # libigl's stored AABB tree is for triangles only
            _, simplex, cp = igl.point_mesh_squared_distance(x, self.points, self.cells)
        else:
            if self._tree is None:  # built once: rebuilding it per query cost 5x the query
                self._tree = igl.AABB()
                self._tree.init(self.points, self.cells)
            _, simplex, cp = self._tree.squared_distance(self.points, self.cells, x)
        self._recent = [[x.copy(), simplex, cp, None]] + self._recent[:RECENT - 1]
        return self._recent[0]

    def on_rim(self, x: np.ndarray) -> np.ndarray:
        """Whether each x's closest point lies on the surface's rim: an edge of one face
        only (3D), an end of the outline (2D). A point past an open surface's edge lands
        there; on a closed surface none does."""
        simplex, cp = self._query(x)
        return _on_rim(self.points, self.cells, simplex, cp, 1e-7 * max(self.extent, 1e-300))

    def outward(self, x: np.ndarray) -> np.ndarray | None:
        """(n, 3) the unit normal of the face closest to each x, pointing out of the
        closed surface whatever order its triangles came in; None for a 2D outline or an
        open surface, which enclose nothing."""
        if self._outward is None:  # once: False if it encloses nothing, else per face (see _outward_normals)
            closed = self.dim == 3 and not rings(self.cells, len(self.points), self.dim)[2].any()
            self._outward = closed and self._outward_normals()
        if self._outward is False:
            return None
        return self._outward[self._query(x)[0]]

    def _outward_normals(self) -> np.ndarray:
        """Per face of this closed surface, the unit normal out of it: faces ordered alike
        per piece (BFS), each piece's signed volume positive."""
        faces, piece = igl.bfs_orient(self.cells)
        p0, p1, p2 = (self.points[faces[:, i]] for i in range(3))
        volume = np.bincount(piece, np.einsum("ij,ij->i", p0, np.cross(p1, p2)))
        turned = np.cross(p1 - p0, p2 - p0) * np.sign(volume)[piece, None]
        same = np.einsum("ij,ij->i", turned, self.area_normals) >= 0
        return np.where(same[:, None], self.normals, -self.normals)

    def curvature_directions(self, x: np.ndarray, smooth: bool = False) -> np.ndarray:
        """(n, dim, dim) rows spanning the Hessian of 1/2 d(x, S)^2 (zero rows pad).

        Closest point inside a face: the normal (the distance to a plane); on an edge:
        the two directions across the edge; at a vertex: every direction. These are
        exact for a piecewise-linear S away from its medial axis, but only inside the
        feature's Voronoi region, a thin wedge on a finely faceted surface. With
        ``smooth``, a point closest to an edge or a vertex gets the curvature of a smooth
        surface through it instead: one row, its unit distance direction (the face's
        normal at zero distance). inner.GaussNewton uses both and says why.
        """
        out, simplex, cp, active = self._features(x)
        if smooth and len(x):
            feature = active.sum(axis=1) < self.cells.shape[1]
            rows = np.flatnonzero(feature)
            offset = x[rows] - cp[rows]
            d = np.linalg.norm(offset, axis=1, keepdims=True)
            out[rows] = 0.0
            out[rows, 0] = np.where(d > 0, offset / np.where(d > 0, d, 1.0), self.normals[simplex[rows]])
        return out

    def _features(self, x):
        """curvature_directions' exact rows, with each point's simplex, closest point and
        active corners (the feature the closest point lies on); worked out once per query
        (both curvature models ask)."""
        entry = self._recall(x)
        if entry[3] is None:
            entry[3] = self._exact_rows(entry[1], entry[2])
        out, active = entry[3]
        return out.copy(), entry[1], entry[2].copy(), active

    def _exact_rows(self, simplex, cp) -> tuple[np.ndarray, np.ndarray]:
        """(out, active) of _features for closest points cp on these simplices."""
        corners = self.points[self.cells[simplex]]  # (n, k, dim)
        k = corners.shape[1]
        # Which corners carry weight: the feature the closest point lies on.
        weights = _barycentric(cp, corners)
        active = weights > 1e-9
        count = active.sum(axis=1)
        out = np.zeros((len(cp), self.dim, self.dim))
        vertex = count <= 1
        out[vertex] = np.eye(self.dim)
        interior = count == k
        out[interior, 0] = self.normals[simplex[interior]]
        edge = ~vertex & ~interior  # only in 3D (k = 3, two active corners)
        if edge.any():
            ends = np.argsort(~active[edge], axis=1, kind="stable")[:, :2]
            rows = np.flatnonzero(edge)
            t = corners[rows, ends[:, 1]] - corners[rows, ends[:, 0]]
            t /= np.linalg.norm(t, axis=1, keepdims=True)
            basis = np.eye(self.dim)[None] - t[:, :, None] * t[:, None, :]
            q, _ = np.linalg.qr(basis)
            out[rows, :2] = np.swapaxes(q[:, :, :2], 1, 2)
        return out, active


def _on_rim(points: np.ndarray, cells: np.ndarray, simplex: np.ndarray, cp: np.ndarray, tolerance: float) -> np.ndarray:
    """Surface.on_rim: whether each closest point cp (on its ``simplex``) lies within
    ``tolerance`` of one of that simplex's rim sides."""
    corners = points[cells[simplex]]
    sides = cells.shape[1]
    ends = [(k, (k + 1) % sides) for k in range(sides)] if points.shape[1] == 3 else [(0, 0), (1, 1)]
    rim = _rim_sides(cells, points.shape[1])[simplex]
    near = np.zeros(len(simplex), bool)
    for k, (a, b) in enumerate(ends):
        near |= rim[:, k] & (_to_segment(cp, corners[:, a], corners[:, b]) <= tolerance)
    return near


def _rim_sides(cells: np.ndarray, dim: int) -> np.ndarray:
    """(cells, sides): 3D, edge k (vertices k, k + 1) of each face is no other face's;
    2D, end k of each segment is no other segment's."""
    if dim == 3:
        keys = np.sort(np.stack([cells, np.roll(cells, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    else:
        keys = cells.reshape(-1, 1)
    _, which, uses = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return (uses[which.ravel()] == 1).reshape(-1, cells.shape[1])


def _to_segment(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of the points x to the segments ab (row by row; a == b: to the point)."""
    ab = b - a
    length = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(np.einsum("ij,ij->i", x - a, ab) / np.where(length > 0, length, 1.0), 0.0, 1.0)
    return np.linalg.norm(x - a - t[:, None] * ab, axis=1)
