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

import logging
import re
import warnings
from contextlib import contextmanager
from pathlib import Path

import igl
import numpy as np
from scipy import sparse

from fenics_elasto.errors import UserError, require


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


# --------------------------------------------------------------------------- targets


@contextmanager
def quiet_vtk(raise_errors: bool = False):
    """VTK kept off the terminal: its logger silenced, the errors of its output window
    caught, what pyvista hands to the root logger kept, pyvista's warnings ignored.
    Yields the list of VTK's messages (first line each, errors first; filled at the
    end of the block), for an error line. ``raise_errors``: a VTK error raises
    pyvista's ``VTKExecutionError`` at the end of the block."""
    import pyvista as pv

    root = logging.getLogger()
    messages: list[str] = []
    logged: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            logged.append(record.getMessage().splitlines()[0])

    saved, root.handlers = root.handlers, [Keep()]  # a handler there: no basicConfig on logging.error
    try:
        with pv.vtk_verbosity("off"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            catcher = pv.VtkErrorCatcher(raise_errors=raise_errors, send_to_logging=False)
            try:
                with catcher:
                    yield messages
            finally:
                texts = [str(getattr(event, "alert", event)) for event in catcher.error_events] + logged
                messages += [_vtk_text(text) for text in texts if text.strip()]
    finally:
        root.handlers = saved


def _vtk_text(text: str) -> str:
    """A VTK message as one line, without object addresses ("Algorithm vtkPLYReader
    (0x...) returned failure for request: ..." says: vtkPLYReader failed)."""
    text = text.strip().splitlines()[0]
    failed = re.match(r"Algorithm (\w+) .*returned failure", text)
    return f"{failed.group(1)} failed" if failed else re.sub(r" \(0x[0-9a-f]+\)", "", text)


def read_polydata(path: Path, what: str = "surface"):
    """Any mesh file pyvista/meshio reads, quietly; unreadable or empty: one line."""
    import pyvista as pv

    path = Path(path)
    require(not path.is_dir(), f"{path}: is a directory, not a {what} file")
    require(path.is_file(), f"{path}: no such {what} file")
    with quiet_vtk() as messages:
        try:
            mesh = pv.read(str(path))
        except Exception as err:  # readers raise many kinds
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise UserError(f"{path}: cannot read the {what} ({reason})") from None
    require(mesh is not None and mesh.n_points > 0,
            f"{path}: cannot read the {what}" + (f" ({messages[0]})" if messages else " (no points)"))
    return mesh


def read_surface(path: Path, gdim: int) -> Surface:
    """A target surface from any file meshio/pyvista reads: triangles in 3D, lines in 2D."""
    import pyvista as pv

    mesh = read_polydata(path, "target surface")
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
    got = "a 2D polyline" if flat else "no triangles"
    require(len(faces) > 0, f"{path}: a 3D scene needs a triangle surface target (got {got})")
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
    require(not path.is_dir(), f"{path}: is a directory, not a landmark file")
    require(path.is_file(), f"{path}: no such landmark file")
    try:
        lines = path.read_text().splitlines()
        require(any(line.strip() and not line.lstrip().startswith("#") for line in lines[1:] + lines[:1]),
                f"{path}: no landmark rows (an empty file)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns of a header-only file: said below
            data = np.loadtxt(path, delimiter=",", ndmin=2, comments="#",
                              skiprows=1 if not _is_numeric_line(lines[0]) else 0)
    except ValueError as err:
        raise UserError(f"{path}: cannot read landmarks ({err})") from None
    require(data.size > 0, f"{path}: no landmark rows (only a header)")
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
