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


class Surface:
    """Triangles (3D) or segments (2D) with exact closest-point queries."""

    def __init__(self, points: np.ndarray, cells: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.cells = np.ascontiguousarray(cells, dtype=np.int64)
        self.dim = self.points.shape[1]

    def closest(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        if len(x) == 0:
            return x.copy()
        return igl.point_mesh_squared_distance(x, self.points, self.cells)[2]


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
