"""Reading users' files: surfaces and meshes (anything pyvista/meshio reads), landmarks.

Every reader checks what it got and says in one line what is wrong with a file; VTK's
own messages are caught and quoted, never printed.
"""

from __future__ import annotations

import logging
import re
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from fenics_elasto.geometry.surface import Surface
from fenics_elasto.util.errors import UserError, require


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
    return surface_of(read_polydata(path, "target surface"), gdim, str(path))


def surface_of(mesh, gdim: int, name: str) -> Surface:
    """A target surface from a pyvista mesh in memory (``name`` in its error lines):
    triangles in 3D, lines in 2D; a volume mesh gives its boundary."""
    import pyvista as pv

    require(isinstance(mesh, pv.DataSet), f"{name}: expected a pyvista mesh, got {type(mesh).__name__}")
    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface(algorithm=None) if gdim == 3 else mesh.extract_feature_edges()
    points = np.asarray(mesh.points, float)
    require(len(points) > 0, f"{name}: the target has no points")
    require(np.isfinite(points).all(), f"{name}: the target has NaN or infinite coordinates")
    flat = np.allclose(points[:, 2], 0.0)
    if gdim == 2:
        require(flat, f"{name}: a 2D scene needs a target in the z = 0 plane (got a 3D surface)")
        require(mesh.n_lines > 0, f"{name}: a 2D scene needs a polyline target (line cells)")
        lines = _segments(mesh.lines)
        return Surface(points[:, :2], lines)
    tri = mesh.triangulate()
    faces = tri.faces.reshape(-1, 4)[:, 1:] if tri.faces.size else np.empty((0, 3), np.int64)
    got = "a 2D polyline" if flat else "no triangles"
    require(len(faces) > 0, f"{name}: a 3D scene needs a triangle surface target (got {got})")
    return Surface(np.asarray(tri.points, float), faces)


def surface_from_arrays(points, cells, gdim: int, name: str) -> Surface:
    """A target surface from arrays: ``points`` (n, gdim) -- or (n, 3) with z = 0 in 2D --
    and ``cells`` (m, 2) segments in 2D or (m, 3) triangles in 3D, indices into points."""
    try:
        points, cells = np.asarray(points, float), np.asarray(cells)
    except (TypeError, ValueError) as err:
        raise UserError(f"{name}: points and cells must be numeric arrays ({err})") from None
    require(points.ndim == 2 and points.shape[1] in (2, 3) and len(points) > 0,
            f"{name}: points must be an (n, {gdim}) array, got shape {points.shape}")
    if gdim == 2 and points.shape[1] == 3:
        require(np.allclose(points[:, 2], 0.0), f"{name}: a 2D scene needs a target in the z = 0 plane")
        points = points[:, :2]
    require(points.shape[1] == gdim, f"{name}: points must be an (n, {gdim}) array for a {gdim}D scene, "
                                     f"got shape {points.shape}")
    require(np.isfinite(points).all(), f"{name}: the target has NaN or infinite coordinates")
    require(cells.ndim == 2 and cells.shape[1] == gdim and len(cells) > 0 and np.issubdtype(cells.dtype, np.integer),
            f"{name}: cells must be an (m, {gdim}) integer array ({'segments' if gdim == 2 else 'triangles'}), "
            f"got shape {cells.shape} of {cells.dtype}")
    require(cells.min() >= 0 and cells.max() < len(points), f"{name}: cells index points outside 0..{len(points) - 1}")
    return Surface(points, cells)


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


def landmark_arrays(source, observed, name: str = "landmarks") -> tuple[np.ndarray, np.ndarray]:
    """Landmarks in memory: (source points, observed points), two (n, d) arrays of the
    same shape with d 2 or 3; checked in one line."""
    try:
        source, observed = np.asarray(source, float), np.asarray(observed, float)
    except (TypeError, ValueError) as err:
        raise UserError(f"{name}: source and observed points must be numeric arrays ({err})") from None
    require(source.ndim == 2 and source.shape[1] in (2, 3) and len(source) > 0,
            f"{name}: the first array (the points) must be (n, 2) or (n, 3), got shape {source.shape}")
    require(observed.shape == source.shape,
            f"{name}: observed points {observed.shape} must have the shape of the source points {source.shape}")
    require(np.isfinite(source).all() and np.isfinite(observed).all(), f"{name}: NaN or infinite values")
    return source, observed


def check_landmark_dim(landmarks: tuple[np.ndarray, np.ndarray], gdim: int, name: str = "landmarks") -> None:
    """Landmarks in memory have the scene's dimension."""
    width = landmarks[0].shape[1]
    require(width == gdim, f"{name}: points of dimension {width}, but the scene is {gdim}D")


def _is_numeric_line(line: str) -> bool:
    try:
        [float(v) for v in line.split(",")]
        return True
    except ValueError:
        return False
