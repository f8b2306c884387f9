"""Surface files as segmentations give them -> closed, outward-oriented shells.

Organ surfaces exported from a CT/MR segmentation carry defects: stray specks (a few
triangles apart from the organ), duplicated points (STL stores every triangle's
corners anew), duplicated or collapsed triangles, inconsistent or inward normals,
small holes. ``closed_shells`` repairs what is safe -- each repair is one printed
line -- in this order:

1. merge points closer than 1e-7 of the surface's size; drop triangles that collapse
   (a repeated corner) and duplicated triangles;
2. drop components (edge-connected) whose area is under 1 % of the largest one's;
3. orient every component consistently (libigl's BFS), fill each hole whose radius is
   at most 5 % of the surface's size with a fan from the hole's centre, and turn each
   component's normals outward (positive enclosed volume);
4. keep the sharp edges that part faces (a box's edges) as edges of the mesh;
and what it cannot make a closed surface in place -- an edge shared by more than two
triangles, a larger opening, a surface that touches or passes through itself (found
from the winding number just inside and outside of every triangle: 1 and 0 on a simple
closed surface) -- it rebuilds from the region the surface encloses (rebuild.py),
saying what that changed; it refuses only what encloses nothing.

Libraries: pyvista/VTK (BSD-3) to read any surface format and to cut the outer
surface along patch planes, libigl (MPL-2) for duplicates, orientation, winding
numbers and distances, SciPy (BSD-3) for components.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.files.readers import quiet_vtk
from fenics_elasto.geometry.meshes import row_keys
from fenics_elasto.util.logs import log

MERGE_TOLERANCE = 1e-7  # of the bounding-box diagonal
SPECK_FRACTION = 0.01  # components under 1 % of the largest one's area are specks
FACE_SHARE = 0.01  # sharp edges are kept where they part faces of at least 1 % of the area
HOLE_FRACTION = 0.05  # holes up to 5 % of the bounding-box diagonal (radius) are filled


@dataclass
class Shell:
    """One closed, outward-oriented component of a surface (triangles index points)."""

    role: str  # "body", "region" or "cavity"
    name: str  # the region's or cavity's name; the body's material
    label: str  # for messages: 'regions.prostate (prostate.stl)'
    points: np.ndarray
    triangles: np.ndarray
    features: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))  # edges kept as curves
    patches: np.ndarray | None = None  # per triangle: bit p set if on patch p's side

    @cached_property
    def volume(self) -> float:
        return enclosed_volume(self.points, self.triangles)

    @cached_property
    def bounds(self) -> np.ndarray:
        return np.array([self.points.min(axis=0), self.points.max(axis=0)])


# A voxel staircase (_unstepped): this many triangles at least, 95 % of its area facing at
# most this many directions (a voxel export's faces: 6, SurfaceNets' also their diagonals)
STAIRCASE_TRIANGLES = 200
STAIRCASE_DIRECTIONS = 26
STAIRCASE_EDGES = 3  # ... and at least this many times the sharp edges of a box of as many triangles


# --------------------------------------------------------------------------- reading


def read_triangles(path: Path, label: str) -> tuple[np.ndarray, np.ndarray]:
    """Points and triangles of any surface file pyvista/meshio reads (polygons are
    triangulated; a volume mesh gives its boundary)."""
    import pyvista as pv

    require(path.is_file(), f"{label}: no such file {path}")
    require(path.stat().st_size > 0, f"{label}: the file is empty")
    messages = []
    try:
        with quiet_vtk(raise_errors=True) as messages:
            mesh = pv.read(path)
            if isinstance(mesh, pv.MultiBlock):
                mesh = mesh.combine()
            if not isinstance(mesh, pv.PolyData):
                mesh = mesh.extract_surface(algorithm="dataset_surface")
            lines = mesh.n_lines
            mesh = mesh.triangulate()
    except Exception as err:  # readers raise anything from ValueError to VTK execution errors
        cause = messages[0] if messages else str(err).splitlines()[0] if str(err) else type(err).__name__
        raise UserError(f"{label}: cannot read it as a surface ({cause})") from None
    require(mesh.n_points > 0, f"{label}: no points ({messages[0] if messages else 'empty or unreadable file'})")
    require(mesh.n_cells > lines, f"{label}: only lines, no triangles (a 2D curve?); a surface needs triangles")
    points = np.asarray(mesh.points, dtype=float)
    require(np.isfinite(points).all(), f"{label}: NaN or infinite coordinates")
    triangles = mesh.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    return points, triangles


# --------------------------------------------------------------------------- topology


def enclosed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume enclosed by a closed triangulation (> 0 for outward normals)."""
    p = points - points.mean(axis=0)
    a, b, c = p[triangles[:, 0]], p[triangles[:, 1]], p[triangles[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (points[triangles[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def directed_edges(triangles: np.ndarray) -> np.ndarray:
    """(3 m, 2) the edges of every triangle, in its orientation."""
    return triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def edge_use(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges (sorted pairs), the edge of each directed edge, and how many
    triangles use each edge."""
    undirected = np.sort(directed_edges(triangles), axis=1)
    _, first, which, count = np.unique(row_keys(undirected), return_index=True, return_inverse=True, return_counts=True)
    return undirected[first], which.ravel(), count


def _components(triangles: np.ndarray) -> np.ndarray:
    """Component id of every triangle (connected through shared edges)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    _, which, count = edge_use(triangles)
    owner = np.repeat(np.arange(len(triangles)), 3)
    shared = sp.coo_matrix((np.ones(len(which)), (owner, which))).tocsr()
    graph = shared @ shared.T  # triangles sharing an edge
    return connected_components(graph, directed=False)[1]


# --------------------------------------------------------------------------- repairs


def _merge_points(points, triangles, label):
    import igl

    size = np.linalg.norm(np.ptp(points, axis=0))
    used = np.unique(triangles)
    merged, _, index = igl.remove_duplicate_vertices(points[used], MERGE_TOLERANCE * size)
    remap = np.zeros(len(points), np.int64)
    remap[used] = index
    duplicates = len(used) - len(merged)
    if duplicates:
        log.info(f"{label}: merged {duplicates} duplicated points")
    return merged, remap[triangles]


def _drop_bad_triangles(triangles, label):
    collapsed = (triangles[:, 0] == triangles[:, 1]) | (triangles[:, 1] == triangles[:, 2]) | (triangles[:, 2] == triangles[:, 0])
    triangles = triangles[~collapsed]
    _, first = np.unique(row_keys(np.sort(triangles, axis=1)), return_index=True)
    duplicated = len(triangles) - len(first)
    if collapsed.any():
        log.info(f"{label}: dropped {collapsed.sum()} collapsed triangles (a repeated corner)")
    if duplicated:
        log.info(f"{label}: dropped {duplicated} duplicated triangles")
    return triangles[np.sort(first)]


def without_specks(points: np.ndarray, triangles: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
    """The surface without its stray pieces (``_drop_specks``), its points compacted."""
    kept = _drop_specks(points, triangles, label)
    used, local = np.unique(kept, return_inverse=True)
    return points[used], local.reshape(-1, 3)


def _drop_specks(points, triangles, label):
    component = _components(triangles)
    area = np.bincount(component, weights=triangle_areas(points, triangles))
    specks = area < SPECK_FRACTION * area.max()
    if specks.any():
        sizes = np.bincount(component)[specks]
        count = f"{sizes.min()} triangles each" if sizes.min() == sizes.max() else f"{sizes.min()}-{sizes.max()} triangles"
        # a label map's speck is smoothed to almost a point before it is measured: its area says nothing there
        share = 100 * area[specks].sum() / area.sum()
        of_area = f", {share:.2g} % of the area" if share >= 0.01 else ""
        log.info(f"{label}: dropped {specks.sum()} stray piece(s) ({count}{of_area}; kept pieces of at least "
                 f"{100 * SPECK_FRACTION:g} % of the largest's area)")
    return triangles[~specks[component]]


def _orient_consistently(triangles, label):
    import igl

    oriented, component = igl.bfs_orient(triangles)
    # each component follows its first triangle; count the ones that disagreed with the majority
    flipped = np.bincount(component, weights=_reversed(triangles, oriented))
    disagreeing = int(np.minimum(flipped, np.bincount(component) - flipped).sum())
    if disagreeing:
        log.info(f"{label}: re-oriented {disagreeing} triangles to agree with their neighbours")
    _, count = np.unique(row_keys(directed_edges(oriented)), return_counts=True)
    require((count == 1).all(), f"{label}: not orientable (a Moebius-like piece); cannot make it a closed surface")
    return oriented


def _reversed(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Per row: does ``after`` list the same triangle in the opposite orientation?"""
    position = np.argmax(before == after[:, :1], axis=1)
    return before[np.arange(len(before)), (position + 1) % 3] != after[:, 1]


def _fill_holes(points, triangles, label):
    """Close each small hole with a fan from the centroid of its rim (the fan takes
    the orientation of the triangles around it)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = directed_edges(triangles)
    _, which, count = edge_use(triangles)
    rim = edges[count[which] == 1]
    if not len(rim):
        return points, triangles
    n = len(points)
    _, hole = connected_components(coo_matrix((np.ones(len(rim)), (rim[:, 0], rim[:, 1])), shape=(n, n)), directed=False)
    hole_of_edge = np.unique(hole[rim[:, 0]], return_inverse=True)[1].ravel()
    holes = hole_of_edge.max() + 1
    centre = np.array([points[np.unique(rim[hole_of_edge == h])].mean(axis=0) for h in range(holes)])
    radius = np.zeros(holes)
    np.maximum.at(radius, hole_of_edge, np.linalg.norm(points[rim[:, 0]] - centre[hole_of_edge], axis=1))
    limit = HOLE_FRACTION * np.linalg.norm(np.ptp(points[np.unique(triangles)], axis=0))
    if radius.max() > limit:
        defect = (f"an opening of radius {radius.max():.3g} at {_point(centre[np.argmax(radius)])} (openings up to "
                  f"{limit:.3g}, 5 % of its size, are filled in place)")
        raise NotClosed(f"{label}: not a closed surface: {defect}", defect)
    fan = np.c_[rim[:, 1], rim[:, 0], n + hole_of_edge]
    log.info(f"{label}: filled {holes} hole(s) (largest radius {radius.max():.3g}, {len(rim)} rim edges)")
    return np.vstack([points, centre]), np.vstack([triangles, fan])


def _orient_outward(points, triangles, label):
    component = _components(triangles)
    inward = [c for c in range(component.max() + 1)
              if enclosed_volume(points, triangles[component == c]) < 0]
    if inward:
        log.info(f"{label}: turned the inward-facing normals of {len(inward)} component(s) outward")
        flip = np.isin(component, inward)
        triangles = triangles.copy()
        triangles[flip] = triangles[flip][:, [0, 2, 1]]
    return triangles, component


def _touching_pieces(triangles: np.ndarray, component: np.ndarray) -> np.ndarray:
    """Vertices used by two edge-connected pieces: where a segmentation's diagonal
    voxels meet, marching cubes and SurfaceNets make such bow-ties, and each piece alone
    is closed while together they are no solid gmsh can mesh."""
    vertex = triangles.ravel()
    piece = np.repeat(component, 3)
    pairs = np.unique(np.c_[vertex, piece], axis=0)
    used, count = np.unique(pairs[:, 0], return_counts=True)
    return used[count > 1]


def self_intersecting(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles whose two sides do not see winding numbers 1 (inside) and 0 (outside):
    on a closed outward surface that does not pass through itself there are none."""
    import igl

    a, b, c = (points[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    length = np.linalg.norm(normal, axis=1)
    ok = length > 0
    centroid = (a + b + c) / 3
    # a hundredth of the triangle's size off its centroid, on either side
    offset = 0.01 * (normal[ok] / np.sqrt(length[ok])[:, None])
    probes = np.vstack([centroid[ok] - offset, centroid[ok] + offset])
    w = igl.fast_winding_number(points, triangles, probes).reshape(2, -1)
    bad = np.zeros(len(triangles), bool)
    bad[ok] = (np.abs(w[0] - 1) > 0.5) | (np.abs(w[1]) > 0.5)
    return bad


class NotClosed(UserError):
    """A surface that the repairs in place cannot make closed; ``defect`` says why."""

    def __init__(self, message: str, defect: str):
        super().__init__(message)
        self.defect = defect


def closed_shells(path: Path, label: str, role: str, name: str) -> list[Shell]:
    """The file's closed components, repaired or rebuilt (see the module docstring),
    outward; a voxel staircase smoothed as a label map's surfaces are."""
    points, triangles = read_triangles(path, label)
    shells = [featured(_unstepped(shell)) for shell in solid_shells(points, triangles, label, role, name)]
    for shell in shells:
        if len(shell.features):
            log.info(f"{label}: its sharp edges ({len(shell.features)} triangle edges) are kept as edges of the mesh")
    return shells


def featured(shell: Shell) -> Shell:
    """The shell with its sharp edges as features (feature_edges)."""
    return Shell(shell.role, shell.name, shell.label, shell.points, shell.triangles,
                 feature_edges(shell.points, shell.triangles))


def _unstepped(shell: Shell) -> Shell:
    """The shell with its points Taubin-smoothed (label_surfaces.smoothed) if it is a voxel
    staircase: an export with its smoothing off (ITK-SNAP, Slicer) has its faces in a few
    directions only, and gmsh failed to mesh such a body (its corners and steps every
    voxel); the same voxels as a label map are smoothed first."""
    from fenics_elasto.geometry.label_surfaces import smoothed

    n = len(shell.triangles)
    if n < STAIRCASE_TRIANGLES or (directions := _face_directions(shell.points, shell.triangles)) > STAIRCASE_DIRECTIONS:
        return shell
    # A box faces 6 ways too, but its sharp edges are its 12 edges' ~12 sqrt(n / 12); a
    # staircase's are most of its edges (a quarter to a third of a voxel export's)
    steps = len(sharp_edges(shell.points, shell.triangles))
    if steps < STAIRCASE_EDGES * 12 * np.sqrt(n / 12):
        return shell
    log.info(f"{shell.label}: a voxel staircase (its faces point {directions} ways, {steps} edges are steps): "
             "smoothed as a label map's surfaces are")
    return Shell(shell.role, shell.name, shell.label, smoothed(shell.points, shell.triangles), shell.triangles)


def _face_directions(points: np.ndarray, triangles: np.ndarray) -> int:
    """How many directions (to a hundredth) 95 % of the surface's area faces."""
    from fenics_elasto.geometry.surface import Surface

    surface = Surface(points, triangles)
    area = np.linalg.norm(surface.area_normals, axis=1)
    _, which = np.unique(np.round(surface.normals, 2), axis=0, return_inverse=True)
    shares = np.sort(np.bincount(which.ravel(), area))[::-1].cumsum() / max(area.sum(), 1e-300)
    return int(np.searchsorted(shares, 0.95) + 1)


def solid_shells(points: np.ndarray, triangles: np.ndarray, label: str, role: str, name: str) -> list[Shell]:
    """``shells_of``, or where the surface cannot be closed in place, the shells of the
    surface rebuilt from what it encloses (rebuild.py)."""
    from fenics_elasto.mesh.rebuild import rebuilt

    try:
        shells = shells_of(points, triangles, label, role, name)
        crossing = _crossing_pieces(shells)
        if crossing:
            raise NotClosed(f"{label}: {crossing}", crossing)
        return shells
    except NotClosed as err:
        return shells_of(*rebuilt(points, triangles, label, err.defect), label, role, name)


def _crossing_pieces(shells: list[Shell]) -> str | None:
    """Pieces of one file that pass through each other (some of one's vertices inside the
    other, some not; a piece wholly inside another is nested, not crossing), said; or None."""
    import igl

    for i, a in enumerate(shells):
        for b in shells[i + 1:]:
            inside = np.abs(igl.fast_winding_number(b.points, b.triangles, a.points)) >= 0.5
            if inside.any() and not inside.all():
                return f"two of its pieces pass through each other ({int(inside.sum())} vertices of one inside the other)"
    return None


def shells_of(points: np.ndarray, triangles: np.ndarray, label: str, role: str, name: str) -> list[Shell]:
    """The closed components of a triangulation in memory, repaired like a file's, outward."""
    points, triangles = _merge_points(points, triangles, label)
    triangles = _drop_bad_triangles(triangles, label)
    require(len(triangles) > 0, f"{label}: no triangles left after dropping collapsed ones")
    triangles = _drop_specks(points, triangles, label)
    edges, _, count = edge_use(triangles)
    if count.max() > 2:
        defect = f"{np.sum(count > 2)} edges are shared by more than two triangles (non-manifold)"
        raise NotClosed(f"{label}: {defect}, e.g. near {_point(points[edges[np.argmax(count)]].mean(axis=0))}; "
                        "cannot make it a closed surface", defect)
    triangles = _orient_consistently(triangles, label)
    points, triangles = _fill_holes(points, triangles, label)
    _, _, count = edge_use(triangles)
    if not (count == 2).all():
        defect = f"{np.sum(count != 2)} edges are not shared by two triangles (an opening too wide to fill)"
        raise NotClosed(f"{label}: cannot be made a closed surface ({defect})", defect)
    triangles, component = _orient_outward(points, triangles, label)
    touching = _touching_pieces(triangles, component)
    if len(touching):
        defect = f"two of its pieces touch at {len(touching)} vertices (a bow-tie: each piece closed, not apart)"
        raise NotClosed(f"{label}: {defect}, e.g. at {_point(points[touching[0]])}", defect)
    shells = [_shell(role, name, label, points, triangles[component == c]) for c in range(component.max() + 1)]
    for shell in shells:  # one by one: a piece inside another sees winding number 2, rightly
        crossing = self_intersecting(shell.points, shell.triangles)
        if crossing.any():
            where = shell.points[shell.triangles[crossing][0]].mean(axis=0)
            defect = f"the surface passes through itself ({crossing.sum()} triangles)"
            raise NotClosed(f"{label}: {defect}, e.g. near {_point(where)}; cannot use it", defect)
    return shells


def _point(x: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in x) + ")"


def _shell(role, name, label, points, triangles) -> Shell:
    used, local = np.unique(triangles, return_inverse=True)
    return Shell(role, name, label, points[used], local.reshape(-1, 3))


# --------------------------------------------------------------------------- features


def sharp_edges(points: np.ndarray, triangles: np.ndarray, degrees: float = 45.0) -> np.ndarray:
    """Edges where the surface turns by more than ``degrees`` (a box's edges)."""
    import igl

    return np.asarray(igl.sharp_edges(points, triangles, np.radians(degrees)), dtype=np.int64).reshape(-1, 2)


def feature_edges(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The sharp edges that part faces of at least FACE_SHARE of the surface's area: a
    box's or a machined part's edges, kept as curves so that the mesh keeps its corners
    (smoothed over, a box's edges were cut off 2 mm deep by 8 mm elements). A noisy
    segmentation's stray sharp edges part no such faces and stay smooth. The surface is
    closed (every edge between two triangles)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    edges, which, _ = edge_use(triangles)
    pair = np.repeat(np.arange(len(triangles)), 3)[np.argsort(which, kind="stable")].reshape(-1, 2)
    keys = row_keys(np.vstack([edges, np.sort(sharp_edges(points, triangles), axis=1)]))  # one numbering for both
    sharp = np.isin(keys[:len(edges)], keys[len(edges):])
    area = triangle_areas(points, triangles)
    while True:
        smooth = pair[~sharp]
        joined = sp.coo_matrix((np.ones(len(smooth)), (smooth[:, 0], smooth[:, 1])), shape=(len(triangles),) * 2)
        face = connected_components(joined, directed=False)[1]
        large = np.bincount(face, area) >= FACE_SHARE * area.sum()
        a, b = face[pair[:, 0]], face[pair[:, 1]]
        parting = sharp & (a != b) & large[a] & large[b]
        if (parting == sharp).all():
            return edges[sharp]
        sharp = parting


def cut_by_planes(shell: Shell, planes: list[tuple[np.ndarray, np.ndarray]]) -> Shell:
    """The shell cut along each plane (point, normal) through its triangles: every
    triangle lies on one side of every plane; ``patches`` gets bit p for the side
    (c - point) . normal > 0 of plane p, and the cut lines join ``features``."""
    import pyvista as pv

    surface = pv.PolyData.from_regular_faces(shell.points, shell.triangles)
    for point, normal in planes:
        with quiet_vtk(raise_errors=True):
            surface = _cut(surface, point, normal)
    points = np.asarray(surface.points, dtype=float)
    triangles = surface.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    centroid = points[triangles].mean(axis=1)
    bits = np.zeros(len(triangles), np.int64)
    for p, (point, normal) in enumerate(planes):
        bits |= ((centroid - point) @ normal > 0).astype(np.int64) << p
    _, which, count = edge_use(triangles)
    require((count == 2).all(), f"{shell.label}: cutting it along the patch planes left it open (please report)")
    edges = np.sort(directed_edges(triangles), axis=1)
    side = np.repeat(bits, 3)
    first = np.full(len(count), -1)
    first[which[::-1]] = side[::-1]  # the bits of one of each edge's two triangles
    cut = edges[side != first[which]]
    cut = cut[np.unique(row_keys(cut), return_index=True)[1]]
    # the only features before a cut are sharp edges (feature_edges), now split where the planes cross them
    sharp = feature_edges(points, triangles) if len(shell.features) else np.empty((0, 2), np.int64)
    return Shell(shell.role, shell.name, shell.label, points, triangles, np.vstack([sharp, cut]), bits)


def _cut(surface, point, normal):
    """Both sides of the plane, welded back into one triangulation along the cut."""
    import pyvista as pv

    above, below = surface.clip(normal=-np.asarray(normal), origin=point, return_clipped=True)
    both = pv.merge([above.extract_surface(algorithm="dataset_surface"), below.extract_surface(algorithm="dataset_surface")])
    return both.triangulate().clean(tolerance=1e-9, absolute=False)
