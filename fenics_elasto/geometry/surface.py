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

import igl
import numpy as np
from scipy import sparse

from fenics_elasto.geometry.meshes import triangle_edges, unique_rows


ROUGH_SHARE = 0.1  # a target rougher than this share of its mean edge is smoothed before matching
TAUBIN_STEPS = (0.5, -0.5)  # lambda, mu of Surface.smoothed
TAUBIN_PASSES = 20  # noise falls ~13x on the phantom's organs; a clean organ moves < 1e-5 of its size


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
        self._tree = None  # libigl AABB tree (3D), built on the first query
        self._last = None  # (x, simplex, cp) of the latest query: the curvature rows ask again at the same x
        self._roughness = None
        self.smoothed_from = None  # the roughness before smoothed() made this surface
        self.noise_gain = 1.0  # smoothed(): the share of white noise its filter lets through
        self._outward = None  # outward(): per face the unit normal out of the enclosed volume, or False (open, 2D)

        corners = self.points[self.cells]
        if self.dim == 2:
            t = corners[:, 1] - corners[:, 0]
            normals = np.c_[t[:, 1], -t[:, 0]]
        else:
            normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        self._area_normals = normals  # |n| = the facet's length (2D) or twice its area (3D)
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

    def _rings(self) -> tuple[sparse.csr_matrix, np.ndarray, np.ndarray]:
        """(vertex adjacency, valence per vertex, rim): the umbrella Laplacian's parts --
        adjacency @ x / valence - x is each vertex's offset to its neighbours' mean. Rim
        vertices have no full ring of neighbours: open borders in 3D (e.g. pieces written
        apart), polyline ends and junctions in 2D."""
        n = len(self.points)
        edges = np.sort(self.cells, axis=1) if self.dim == 2 else triangle_edges(self.cells)
        first, which = unique_rows(edges)
        edges, uses = edges[first], np.bincount(which)
        valence = np.bincount(edges.ravel(), minlength=n)
        rim = np.zeros(n, bool)
        rim[edges[uses < 2].ravel()] = self.dim == 3
        if self.dim == 2:
            rim[valence != 2] = True
        ones = np.ones(len(edges))
        adjacency = sparse.coo_matrix((np.r_[ones, ones], (np.r_[edges[:, 0], edges[:, 1]],
                                                          np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
        return adjacency, valence, rim

    def is_rough(self) -> bool:
        """Noisier than its own sampling resolves: roughness above ROUGH_SHARE of the mean
        edge (clean simulated and segmented targets measure 0.0001-0.03 of it; 0.25 % noise
        on the phantom's finely sampled organs 0.27)."""
        return self.roughness() > ROUGH_SHARE * self.mean_edge

    def smoothed(self, passes: int = TAUBIN_PASSES) -> Surface:
        """Taubin's lambda|mu smoothing (a shrink step lambda = 0.5, then an inflate step
        mu = -0.5 of the umbrella Laplacian, ``passes`` times): a low-pass filter that
        removes noise at the sampling's wavelength (an eigenvalue k of the Laplacian is
        damped by (1 - k^2 / 4)^passes) while a smooth shape, k ~ 0, moves only to second
        order -- a plain Laplacian shrinks it, Taubin's mu = -0.53 inflated the phantom's
        organs by 1.4e-4 cm, worth ~1 % of E. Rim vertices stay put."""
        adjacency, valence, rim = self._rings()
        n = len(self.points)
        inner = ~rim & (valence >= 2)
        # The filter is linear and acts on each column alike: a column of unit white noise
        # beside the coordinates measures how much of the target's noise it lets through.
        probe = np.random.default_rng(0).standard_normal(n)
        columns = np.c_[self.points, probe]
        for _ in range(passes):
            for factor in TAUBIN_STEPS:
                umbrella = adjacency @ columns / np.maximum(valence, 1)[:, None] - columns
                columns += factor * inner[:, None] * umbrella
        out = Surface(columns[:, :-1], self.cells)
        out.smoothed_from = self.roughness()
        out.noise_gain = float(np.std(columns[inner, -1])) if inner.any() else 1.0
        return out

    def noise(self) -> float:
        """The noise a point matched to this surface sees: its roughness; once smoothed,
        the noise it had times the filter's gain -- the roughness left measures only the
        highest frequencies, while the filtered noise keeps wiggles a few samples long
        (the letter at 1 % noise: roughness 0.092 -> 0.006, filtered noise ~0.4 x 0.092)."""
        if self.smoothed_from is None:
            return self.roughness()
        return self.noise_gain * self.smoothed_from

    def roughness(self) -> float:
        """The noise a measured surface carries, from the surface alone: each vertex's offset
        along the normal from the mean of its neighbours (the umbrella Laplacian), whose
        variance is (1 + 1/m) x the noise's for m neighbours; the median over interior
        vertices, so that corners and feature edges (a few vertices each) do not count, and
        a smooth surface sampled finely (a simulated target) gives ~0 (curvature adds ~edge^2 /
        radius: 0.02 for 0.6-long edges on a sphere of radius 20). A fit's residual
        cannot see this noise -- the closest point to a rough surface is its nearest spike,
        so residuals run at 0.4-0.7x the noise."""
        if self._roughness is not None:
            return self._roughness
        points, cells = self.points, self.cells
        adjacency, valence, rim = self._rings()
        inner = ~rim & (valence >= 2)
        if inner.sum() < 10:
            self._roughness = 0.0
            return 0.0
        offset = points - adjacency @ points / np.maximum(valence, 1)[:, None]
        normal = np.zeros_like(points)  # area-weighted vertex normals (2D: of the two segments)
        for column in range(cells.shape[1]):
            np.add.at(normal, cells[:, column], self._area_normals)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        height = np.einsum("nd,nd->n", offset, normal)[inner]
        m = valence[inner]
        self._roughness = float(np.sqrt(np.median(height**2 / (1 + 1 / m)) / 0.454936))  # median of chi2(1): 0.4549
        return self._roughness

    def _query(self, x):
        x = np.ascontiguousarray(x, dtype=np.float64)
        if len(x) == 0:
            return np.zeros(0, np.int64), x.copy()
        last = self._last
        if last is not None and last[0].shape == x.shape and np.array_equal(last[0], x):
            return last[1], last[2].copy()  # a Gauss-Newton step's value, then its curvature: one query
        if self.dim == 2:  # libigl's stored AABB tree is for triangles only
            _, simplex, cp = igl.point_mesh_squared_distance(x, self.points, self.cells)
        else:
            if self._tree is None:  # built once: rebuilding it per query cost 5x the query
                self._tree = igl.AABB()
                self._tree.init(self.points, self.cells)
            _, simplex, cp = self._tree.squared_distance(self.points, self.cells, x)
        self._last = (x.copy(), simplex, cp.copy())
        return simplex, cp

    def outward(self, x: np.ndarray) -> np.ndarray | None:
        """(n, 3) the unit normal of the face closest to each x, pointing out of the
        closed surface whatever order its triangles came in; None for a 2D outline or an
        open surface, which enclose nothing."""
        if self._outward is None:  # once: False if it encloses nothing, else per face (see _outward_normals)
            self._outward = self.dim == 3 and not self._rings()[2].any() and self._outward_normals()
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
        same = np.einsum("ij,ij->i", turned, self._area_normals) >= 0
        return np.where(same[:, None], self.normals, -self.normals)

    def curvature_directions(self, x: np.ndarray) -> np.ndarray:
        """(n, dim, dim) rows spanning the Hessian of 1/2 d(x, S)^2 (zero rows pad).

        Closest point inside a face: the normal (the distance to a plane); on an edge:
        the two directions across the edge; at a vertex: every direction. These are
        exact for a piecewise-linear S away from its medial axis, which makes the
        Gauss-Newton model of the misfit a Newton model.
        """
        simplex, cp = self._query(x)
        corners = self.points[self.cells[simplex]]  # (n, k, dim)
        k = corners.shape[1]
        # Which corners carry weight: the feature the closest point lies on.
        weights = _barycentric(cp, corners)
        active = weights > 1e-9
        count = active.sum(axis=1)
        out = np.zeros((len(x), self.dim, self.dim))
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
        return out
