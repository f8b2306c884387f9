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

from pathlib import Path

import igl
import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.errors import UserError, require


def _barycentric(p, corners):
    """Barycentric coordinates of points p in their simplex (segments or triangles)."""
    a = corners[:, 0]
    edges = corners[:, 1:] - a[:, None]  # (n, k-1, dim)
    gram = np.einsum("nid,njd->nij", edges, edges)
    rhs = np.einsum("nid,nd->ni", edges, p - a)
    lam = np.linalg.solve(gram + 1e-300 * np.eye(gram.shape[1]), rhs[..., None])[..., 0]
    return np.c_[1.0 - lam.sum(axis=1), lam]


def triangle_edges(triangles: np.ndarray) -> np.ndarray:
    """The edges 01, 12, 20 of each triangle as vertex pairs sorted within each row."""
    return np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)


def quadratic_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges of gmsh 6-node triangles (v0, v1, v2, e01, e12, e20): (vertex pairs,
    sorted within each row; the edge's midpoint node), three rows per triangle."""
    return triangle_edges(triangles), triangles[:, 3:6].ravel()


class Surface:
    """Triangles (3D) or segments (2D) with exact closest-point queries."""

    def __init__(self, points: np.ndarray, cells: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.cells = np.ascontiguousarray(cells, dtype=np.int64)
        self.dim = self.points.shape[1]
        self._tree = None  # libigl AABB tree (3D), built on the first query

        corners = self.points[self.cells]
        if self.dim == 2:
            t = corners[:, 1] - corners[:, 0]
            normals = np.c_[t[:, 1], -t[:, 0]]
        else:
            normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.normals = normals / np.where(length > 0, length, 1.0)

    def closest(self, x: np.ndarray) -> np.ndarray:
        return self._query(x)[1]

    def _query(self, x):
        x = np.ascontiguousarray(x, dtype=np.float64)
        if len(x) == 0:
            return np.zeros(0, np.int64), x.copy()
        if self.dim == 2:  # libigl's stored AABB tree is for triangles only
            _, simplex, cp = igl.point_mesh_squared_distance(x, self.points, self.cells)
            return simplex, cp
        if self._tree is None:  # built once: rebuilding it per query cost 5x the query
            self._tree = igl.AABB()
            self._tree.init(self.points, self.cells)
        _, simplex, cp = self._tree.squared_distance(self.points, self.cells, x)
        return simplex, cp

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


# --------------------------------------------------------------------------- targets


def read_surface(path: Path, gdim: int) -> Surface:
    """A target surface from any file meshio/pyvista reads: triangles in 3D, lines in 2D."""
    import pyvista as pv

    require(path.is_file(), f"{path}: no such target file")
    try:
        mesh = pv.read(str(path))
    except Exception as err:  # readers raise many kinds
        raise UserError(f"{path}: cannot read the target surface ({err})") from None
    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface(algorithm=None) if gdim == 3 else mesh.extract_feature_edges()
    points = np.asarray(mesh.points, float)
    require(len(points) > 0, f"{path}: the target has no points")
    require(np.isfinite(points).all(), f"{path}: the target has NaN or infinite coordinates")
    flat = np.allclose(points[:, 2], 0.0)
    if gdim == 2:
        require(flat, f"{path}: a 2D scene needs a target in the z = 0 plane (got a 3D surface)")
        require(mesh.n_lines > 0, f"{path}: a 2D scene needs a polyline target (line cells)")
        lines = _segments(mesh.lines)
        return Surface(points[:, :2], lines)
    tri = mesh.triangulate()
    faces = tri.faces.reshape(-1, 4)[:, 1:] if tri.faces.size else np.empty((0, 3), np.int64)
    require(len(faces) > 0, f"{path}: a 3D scene needs a triangle surface target (got {'a 2D polyline' if flat else 'no triangles'})")
    return Surface(np.asarray(tri.points, float), faces)


def _segments(lines: np.ndarray) -> np.ndarray:
    """pyvista's flat [n, i0, ..., in-1, n, ...] polylines as (m, 2) segments."""
    out, i = [], 0
    while i < len(lines):
        n = lines[i]
        ids = lines[i + 1 : i + 1 + n]
        out.append(np.c_[ids[:-1], ids[1:]])
        i += n + 1
    return np.concatenate(out)


def read_landmarks(path: Path, gdim: int) -> tuple[np.ndarray, np.ndarray]:
    """CSV rows ``source point, target point`` (2*gdim numbers; a header line is allowed)."""
    require(path.is_file(), f"{path}: no such landmark file")
    try:
        data = np.loadtxt(path, delimiter=",", ndmin=2, comments="#",
                          skiprows=1 if not _is_numeric_line(path.read_text().splitlines()[0]) else 0)
    except (ValueError, IndexError) as err:
        raise UserError(f"{path}: cannot read landmarks ({err})") from None
    require(data.shape[1] == 2 * gdim,
            f"{path}: expected {2 * gdim} columns (source point, target point) for a {gdim}D scene, got {data.shape[1]}")
    require(np.isfinite(data).all(), f"{path}: landmarks contain NaN or infinite values")
    return data[:, :gdim], data[:, gdim:]


def _is_numeric_line(line: str) -> bool:
    try:
        [float(v) for v in line.split(",")]
        return True
    except ValueError:
        return False


class Target:
    """Residuals r_l = x_l - target(x_l) for the matched nodes, in global node order.

    ``surfaces``: one Surface per matched node (indices into ``surface_of``), or
    landmarks: fixed target points for a subset of nodes (others contribute nothing).
    """

    def __init__(self, surfaces: list[Surface], surface_of: np.ndarray, landmark_nodes=None, landmark_points=None):
        self.surfaces = surfaces
        self.surface_of = surface_of
        self.landmark_nodes = landmark_nodes
        self.landmark_points = landmark_points

    def closest(self, x: np.ndarray) -> np.ndarray:
        """The corresponding target point of every node (x itself where there is none)."""
        if self.landmark_nodes is not None:
            out = x.copy()
            out[self.landmark_nodes] = self.landmark_points
            return out
        out = np.empty_like(x)
        for i, surface in enumerate(self.surfaces):
            rows = np.flatnonzero(self.surface_of == i)
            out[rows] = surface.closest(x[rows])
        return out

    def residual(self, x: np.ndarray) -> np.ndarray:
        return x - self.closest(x)

    def curvature_directions(self, x: np.ndarray) -> np.ndarray:
        """(n, dim, dim): rows spanning each node's Gauss-Newton curvature of 1/2 |r|^2."""
        out = np.zeros(x.shape + (x.shape[1],))
        if self.landmark_nodes is not None:
            out[self.landmark_nodes] = np.eye(x.shape[1])
            return out
        for i, surface in enumerate(self.surfaces):
            rows = np.flatnonzero(self.surface_of == i)
            out[rows] = surface.curvature_directions(x[rows])
        return out


def load_target(scene, matched_coords: np.ndarray, matched_group: np.ndarray) -> Target:
    """The [target] of a scene for its matched nodes (global order, on every rank).

    ``matched_group``: index into ``scene.matched`` of each node's group.
    """
    spec = scene.config.get("target")
    where = f"{scene.path}: [target]"
    require(isinstance(spec, dict) and spec, f"{where}: missing; give surface, surfaces or landmarks")
    base = scene.path.parent
    keys = [k for k in ("surface", "surfaces", "landmarks") if k in spec]
    require(len(keys) == 1, f"{where}: give exactly one of surface, surfaces, landmarks")
    if "landmarks" in spec:
        source, points = read_landmarks(base / spec["landmarks"], scene.gdim)
        nodes = cKDTree(matched_coords).query(source)[1]
        require(len(np.unique(nodes)) == len(nodes), f"{base / spec['landmarks']}: two landmarks snap to the same matched node")
        return Target([], np.zeros(len(matched_coords), int), nodes, points)
    if "surface" in spec:
        return Target([read_surface(base / spec["surface"], scene.gdim)], np.zeros(len(matched_coords), int))
    surfaces = spec["surfaces"]
    require(isinstance(surfaces, dict), f"{where}.surfaces: expected a table group = file")
    missing = [g for g in scene.matched if g not in surfaces]
    require(not missing, f"{where}.surfaces: no surface for matched group(s) {missing}")
    unknown = [g for g in surfaces if g not in scene.matched]
    require(not unknown, f"{where}.surfaces: {unknown} not in boundary.matched")
    return Target([read_surface(base / surfaces[g], scene.gdim) for g in scene.matched], matched_group)
