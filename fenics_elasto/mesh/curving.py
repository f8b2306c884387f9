"""Straight-sided meshes of curved bodies, curved on load.

Most meshers write order-1 (straight-sided) simplices: a curved organ becomes a polyhedron
inscribed in it, and with P2 elements its edge midpoints sit on chords, up to the sag
c^2 / (8 R) inside the surface a target describes (edge c, radius of curvature R). On a
3D phantom meshed plainly by gmsh that cost E 5-7 % (issue #31) -- a geometric error no
finer field fixes.

``curve_mesh`` gives such a mesh order-2 geometry (on rank 0, in the open gmsh model):
gmsh adds the edge midpoints, and every midpoint on a surface -- the boundary, and the
interfaces between regions -- moves onto a smooth surface reconstructed through the
facets:

- the surface is cut into smooth patches along its feature edges (facets meeting at more
  than FEATURE_ANGLE: a box's edges, a cylinder's caps), and each patch's vertices get
  their normal (the angle-weighted mean of its facets'). Where the file keeps gmsh's CAD
  faces (``_cad_faces``), an edge inside one face is never a feature, whatever its angle:
  a clamped bone bar meshed with three or four facets around meets at 90-120 degrees,
  as a prism does, and read by angle alone stayed one (E 2-5 % low on the plain-gmsh
  family, docs: validation). A flat CAD face stays flat even where a curved face meets it
  tangentially (a box's rounded edges), which no angle can tell (``_on_flat_faces``);
- an edge inside a patch follows the circular arc through its ends that meets the
  planes of their normals at the angles the chord makes with them (their mean, phi):
  its midpoint is (a + b) / 2 + (|b - a| / 2) tan(phi / 2) along n_a + n_b -- exact on a
  sphere and along a cylinder's circles, and nothing moves on a flat patch. (The cubic of PN
  triangles, (a + b) / 2 - (w_ab n_a + w_ba n_b) / 8 with w_ab = (b - a) . n_a, falls
  short of the arc by 3/8 R phi^4: on the pelvis phantom's prostate (edge 0.45, radii
  1.1-1.6 cm) its midpoints lie 6.0e-4 cm inside on average, the arc's 1.4e-4 (the
  bladder's: 1.9e-4 and 2.6e-5; with the exact normals 1.6e-4 and 5e-7 -- the rest is
  the vertex normals');
- a feature edge follows the cubic Hermite curve along its feature line, whose tangent
  at a vertex points from the previous vertex of the line to the next: a straight line
  stays straight, a cap's circle is followed; where a line ends or branches (a corner),
  the chord is the tangent.

Cells the curved midpoints fold over are then unfolded (their surface midpoints moved
back towards the chord until they do not). A mesh is
curved only where it is straight-sided (order 1), for P2 fields, and where some surface
actually bends (a polygon or a box stays as it is); on load, in 3D only (``curve_if_straight``):
a straight-sided 2D source matched at its vertices was already within 0.1 % (the
independent inclusion, E ratio 5: +0.11 %), and curved it gave +0.32 % at 5x the inner
iterations far from the answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fenics_elasto.mesh.gmsh_models import node_positions
from fenics_elasto.mesh.meshcheck import folds
from fenics_elasto.util.logs import log

FEATURE_ANGLE = np.radians(35.0)  # facets meeting at more: a feature edge (kept sharp)
BENT_ANGLE = np.radians(0.5)  # a surface whose facets all meet at less is flat: nothing to curve
COARSE_ANGLE = np.radians(20.0)  # a surface whose facets meet at more on average (sharp edges aside) is coarse
SHARP_ANGLE = np.radians(60.0)  # ... where facets meeting at more are taken for its sharp edges, not its curvature
MOVE_LIMIT = 0.25  # a midpoint moves by at most this share of its edge (noisy normals)
CELLS = {2: (2, 9, ((0, 1, 3), (1, 2, 4), (2, 0, 5))),  # tdim: (order-1 type, order-2 type, its edges' midpoints)
         3: (4, 11, ((0, 1, 4), (1, 2, 5), (2, 0, 6), (3, 0, 7), (2, 3, 8), (3, 1, 9)))}


@dataclass
class Curving:
    """What ``curve_mesh`` did."""

    moved: int  # surface edge midpoints moved
    largest: float  # the largest move
    largest_share: float  # ... relative to its edge
    straightened: int  # cells whose folding midpoints were put back on their chords
    coarse: dict[str, CoarseSurface]  # facet group name -> how it was read, where too coarse to tell its curvature


@dataclass
class CoarseSurface:
    """A facet group whose facets meet at over COARSE_ANGLE on average (``_coarse_groups``)."""

    angle: float  # the mean angle (radians) between its neighbouring facets, its sharp edges aside
    on_faces: bool  # its facets lie on CAD faces (``_cad_faces``), which told its curvature from its features
    largest_move: float  # the largest move of the midpoints of edges between two of its facets


@dataclass
class Surface:
    """The facets of a mesh's surfaces (boundary and interfaces) with outward-consistent
    normals, as node tags; ``group`` tells apart surfaces that meet (region, or boundary)."""

    facets: np.ndarray  # (m, tdim) node tags
    normals: np.ndarray  # (m, 3) unit normals, oriented consistently per surface
    group: np.ndarray  # (m,) which surface each facet is on
    face: np.ndarray  # (m,) the CAD face (gmsh surface entity) each facet lies on, -1 where unknown
    index: dict[tuple, int]  # each facet's row by its sorted node tags (_facet_index): gmsh's elements -> rows


def curve_if_straight(gmsh, tdim: int, path) -> tuple[str | None, list[str]]:
    """A straight-sided 3D mesh in the open gmsh model whose surfaces bend, curved
    (``curve_mesh``), with one line saying so; returns that line (None if nothing was
    curved) and the warnings for surfaces too coarse to tell their curvature."""
    if tdim != 3 or not straight_sided(gmsh, tdim):
        return None, []
    done = curve_mesh(gmsh, tdim)
    if done is None:
        return None, []
    unfolded = f"; {done.straightened} thin cells kept partly straight so as not to fold" if done.straightened else ""
    note = (f"note: {Path(path).name}: straight-sided (order 1) with curved surfaces: curved on load, {done.moved} "
            f"surface edge midpoints moved onto smooth surfaces through its facets (largest move {done.largest:.3g}, "
            f"{100 * done.largest_share:.0f} % of its edge{unfolded}); curve = \"off\" keeps it straight")
    log.info(note)
    return note, [f"{Path(path).name}: {name}: neighbouring facets meet at {np.degrees(group.angle):.0f} degrees on average, "
            f"too coarse to tell its curvature well: {COARSE_READING[group.on_faces]}, and may be off by a part of its "
            f"sag (its midpoints moved up to {group.largest_move:.2g}), which can move an estimated E by several % -- mesh it "
            "finer (2-3x more facets across it)" for name, group in done.coarse.items()]


# How a coarse surface was read, and what that cost on the plain-gmsh pelvis family's
# clamped bones (3-4 facets around; docs: validation).
COARSE_READING = {True: "it was curved along the file's CAD faces (the family's bones so: E within 2 % at E = 50)",
                  False: "where its facets meet at over 35 degrees it was kept as sharp edges, as no CAD faces tell "
                         "(the family's bones so: E 3-5 % low)"}


def kept_straight_warnings(gmsh, tdim: int, path) -> list[str]:
    """A straight-sided 3D mesh whose surfaces bend, loaded without curving (curve =
    "off", or P1 fields): a warning that its facets' error in the shape is in no part of
    sigma. Measured on a new user's plain-gmsh box with a ball (E 4, truth by
    scikit-fem): kept straight, fiducials gave 3.882 (3.778-3.989) and a field 4.165
    (4.056-4.277), both intervals missing; curved on load 4.052 and 3.972, holding."""
    if tdim != 3 or not straight_sided(gmsh, tdim) or _bent_surface(gmsh, tdim) is None:
        return []
    return [f"{Path(path).name}: straight-sided (order 1) with curved surfaces, kept straight (curve = \"off\", or P1 "
            "fields): the facets' error in the shape is in no part of sigma (the mesh part solves again on the same "
            "facets) and can move E by a few % outside its interval; curve = \"auto\" with P2 fields curves it"]


def _bent_surface(gmsh, tdim: int):
    """(node positions, the mesh's surface, its edges, their patches, the facets' angles
    at them) of the mesh in the open gmsh model; None where every surface is flat (its
    facets meet at under BENT_ANGLE on average): nothing to curve."""
    position = node_positions(gmsh)
    surface = mesh_surfaces(gmsh, tdim, position)
    edges, patches = surface_edges(surface, tdim)
    angles = _edge_angles(surface, edges)
    if _bend(surface, edges, angles, tdim) < BENT_ANGLE:
        return None
    return position, surface, edges, patches, angles


def straight_sided(gmsh, tdim: int) -> bool:
    """Is the mesh's geometry of order 1 (gmsh's 3-node triangles / 4-node tetrahedra)?"""
    types = {int(t) for t in gmsh.model.mesh.getElementTypes(tdim)}
    return types == {CELLS[tdim][0]}


def curve_mesh(gmsh, tdim: int) -> Curving | None:
    """Curve a straight-sided mesh whose surfaces bend (module docstring), in the open
    gmsh model; None (nothing done) where every surface is flat."""
    bent = _bent_surface(gmsh, tdim)
    if bent is None:
        return None
    position, surface, edges, patches, angles = bent
    targets = midpoint_targets(surface, edges, patches, angles, position, tdim)
    move = targets - (position[edges.ends[:, 0]] + position[edges.ends[:, 1]]) / 2
    size = np.linalg.norm(move, axis=1)
    coarse = _coarse_groups(gmsh, tdim, surface, edges, angles, size)  # before the order-2 elements replace these
    renumber = _set_order_2(gmsh, tdim)
    midpoint = _midpoint_nodes(gmsh, tdim)
    length = np.linalg.norm(position[edges.ends[:, 1]] - position[edges.ends[:, 0]], axis=1)
    ends = np.sort(renumber[edges.ends], axis=1)
    nodes = np.array([midpoint[(int(a), int(b))] for a, b in ends])
    for node, point in zip(nodes, targets):
        gmsh.model.mesh.setNode(int(node), point, [])
    straightened = _unfold(gmsh, tdim, nodes, targets - move)
    at = int(np.argmax(size))
    return Curving(len(nodes), float(size[at]), float(size[at] / length[at]), straightened, coarse)


UNFOLD_STEPS = (0.5, 0.25, 0.0)  # the share of its move a folding cell's surface midpoint keeps, tried in turn
RELAX_ROUNDS = 3  # rounds of moving folding cells' inner midpoints with their surface, before straightening


def _unfold(gmsh, tdim: int, nodes: np.ndarray, chords: np.ndarray) -> int:
    """Cells that a curved midpoint folds over (det J changes sign inside: a thin cell at
    a curved wall) are relaxed first: their inner midpoints (off the surfaces) move with
    the cell's surface midpoints, by the mean of their moves -- the interior follows the
    wall. Cells still folded then get their surface midpoints moved back towards their
    chords, halfway, a quarter, then all the way, until none folds. Returns the number of
    cells partly straightened. (On the pelvis's plain gmsh source one thin cell under the
    prostate's top, straightened, left its surface 0.037 inside the ellipsoid. gmsh's own
    high-order optimiser was tried first: on a box with a ball and a tube, meshed
    plainly, it aborted the process -- "Failed to reach critical value ... ScaledJac".)"""
    surface_node = {int(n): i for i, n in enumerate(nodes)}
    position = node_positions(gmsh)
    targets = {int(n): p for n, p in zip(nodes, position[nodes])}
    origin: dict[int, np.ndarray] = {}  # inner midpoints moved so far: where they were
    for _ in range(RELAX_ROUNDS):
        _, rows = _folded(gmsh, tdim)
        if not len(rows):
            return 0
        _relax_inner(gmsh, rows[:, tdim + 1:], surface_node, targets, chords, origin)
    treated: set[int] = set()
    for keep in UNFOLD_STEPS:
        tags, rows = _folded(gmsh, tdim)
        if not len(tags):
            break
        treated.update(map(int, tags))
        for node in {int(n) for n in rows[:, tdim + 1:].ravel()} & surface_node.keys():
            chord = chords[surface_node[node]]
            gmsh.model.mesh.setNode(node, chord + keep * (targets[node] - chord), [])
    return len(treated)


def _relax_inner(gmsh, midpoints: np.ndarray, surface_node: dict, targets: dict, chords: np.ndarray,
                 origin: dict[int, np.ndarray]) -> None:
    """Each folded cell's inner midpoints (rows of ``midpoints``) move from where they
    were (``origin``, filled here) by the mean move of the cell's surface midpoints away
    from their chords (a midpoint shared by several such cells: the mean of theirs)."""
    position = node_positions(gmsh)
    shifts: dict[int, list[np.ndarray]] = {}
    for row in midpoints:
        moves = [targets[int(n)] - chords[surface_node[int(n)]] for n in row if int(n) in surface_node]
        if not moves:
            continue
        for n in row:
            if int(n) not in surface_node:
                shifts.setdefault(int(n), []).append(np.mean(moves, axis=0))
    for node, moves in shifts.items():
        start = origin.setdefault(node, position[node].copy())
        gmsh.model.mesh.setNode(node, start + np.mean(moves, axis=0), [])


def _folded(gmsh, tdim: int) -> tuple[np.ndarray, np.ndarray]:
    """(tags, node rows) of the order-2 cells whose det J changes sign inside."""
    tags, nodes = gmsh.model.mesh.getElementsByType(CELLS[tdim][1])
    rows = np.asarray(nodes, np.int64).reshape(len(tags), -1)
    folded = folds(gmsh, tags)
    return np.asarray(tags, np.int64)[folded], rows[folded]


# --------------------------------------------------------------------------- the surfaces


def mesh_surfaces(gmsh, tdim: int, position: np.ndarray) -> Surface:
    """Every facet on the boundary or between two regions (cell physical groups), each
    normal pointing out of its cell (on an interface: out of the lower-numbered region)."""
    cells, region = _cells_with_regions(gmsh, tdim)
    local = np.array([[j for j in range(tdim + 1) if j != i] for i in range(tdim + 1)])  # facet i: opposite vertex i
    facets = cells[:, local].reshape(-1, tdim)  # (cells x (tdim + 1), tdim)
    opposite = cells.reshape(-1)  # facet i of a cell lies opposite its vertex i
    owner = np.repeat(np.arange(len(cells)), tdim + 1)
    key = np.sort(facets, axis=1)
    order = np.lexsort(key.T[::-1])
    key, facets, opposite, owner = key[order], facets[order], opposite[order], owner[order]
    start = np.r_[True, np.any(np.diff(key, axis=0) != 0, axis=1)]
    first = np.flatnonzero(start)
    count = np.diff(np.r_[first, len(key)])
    second = first + 1
    pair = count == 2
    interface = np.zeros(len(first), bool)
    interface[pair] = region[owner[first[pair]]] != region[owner[second[pair]]]
    keep = (count == 1) | interface
    rows = first[keep]
    # an interface facet belongs to the lower-numbered region's cell; the boundary's to its one cell
    other = region[owner[np.minimum(rows + 1, len(owner) - 1)]]
    swap = interface[keep] & (other < region[owner[rows]])
    low, high = np.minimum(region[owner[rows]], other), np.maximum(region[owner[rows]], other)
    rows = np.where(swap, rows + 1, rows)
    group = np.where(interface[keep], low * (int(region.max()) + 1) + high, -1)  # boundary: -1
    normals = _outward_normals(position, facets[rows], position[opposite[rows]], tdim)
    index = _facet_index(facets[rows])
    return Surface(facets[rows], normals, group, _cad_faces(gmsh, tdim, index), index)


def _cad_faces(gmsh, tdim: int, index: dict[tuple, int]) -> np.ndarray:
    """The gmsh entity each facet lies on, where that entity is a CAD face: one bounded
    by curves (gmsh writes a cylinder as its side and two caps, a box as six faces, and
    keeps their bounding curves in the .msh; classifySurfaces' patches have them too). A
    face is smooth inside, so an edge between two facets of one face is curvature
    whatever its angle: a bone bar meshed with four facets around is a cylinder, not a
    prism. -1 (the angles alone decide) on an entity with no bounding curves -- a closed
    surface merged from an STL, or a mesh converted from elsewhere, whose one entity may
    hold a box's edges. ``index``: the surface facets' (``_facet_index``)."""
    out = np.full(len(index), -1, np.int64)
    for _, tag in gmsh.model.getEntities(tdim - 1):
        if gmsh.model.getBoundary([(tdim - 1, tag)], oriented=False):
            out[_entity_facets(gmsh, tdim, index, tag)] = tag
    return out


def _facet_index(facets: np.ndarray) -> dict[tuple, int]:
    """Surface facets (node-tag rows) by their sorted node tags."""
    return {tuple(row): i for i, row in enumerate(np.sort(facets, axis=1).tolist())}


def _entity_facets(gmsh, tdim: int, index: dict[tuple, int], entity: int) -> list[int]:
    """The surface facets (rows of ``index``'s facets) that a gmsh facet entity's elements are."""
    _, nodes = gmsh.model.mesh.getElementsByType(CELLS[tdim - 1][0], entity)
    rows = np.sort(np.asarray(nodes, np.int64).reshape(-1, tdim), axis=1).tolist()
    return [i for i in (index.get(tuple(r)) for r in rows) if i is not None]


def _cells_with_regions(gmsh, tdim: int) -> tuple[np.ndarray, np.ndarray]:
    """(cells as node-tag rows of their vertices, the physical group of each)."""
    rows, region = [], []
    for dim, tag in gmsh.model.getPhysicalGroups(tdim):
        for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
            _, nodes = gmsh.model.mesh.getElementsByType(CELLS[tdim][0], entity)
            block = np.asarray(nodes, np.int64).reshape(-1, tdim + 1)
            rows.append(block)
            region.append(np.full(len(block), tag))
    return np.concatenate(rows), np.concatenate(region)


def _outward_normals(position: np.ndarray, facets: np.ndarray, inside: np.ndarray, tdim: int) -> np.ndarray:
    """Unit normals of facets (node-tag rows), pointing away from the points ``inside``."""
    a = position[facets[:, 0]]
    if tdim == 3:
        n = np.cross(position[facets[:, 1]] - a, position[facets[:, 2]] - a)
    else:
        t = position[facets[:, 1]] - a
        n = np.c_[t[:, 1], -t[:, 0], np.zeros(len(t))]
    n *= np.where(np.einsum("ij,ij->i", n, inside - a) > 0, -1.0, 1.0)[:, None]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


@dataclass
class Edges:
    """The edges of the surface facets: in 3D the triangles' edges, in 2D the segments
    themselves. ``facets`` lists the surface facets on each edge (-1 pads)."""

    ends: np.ndarray  # (k, 2) node tags, sorted within each row
    facets: np.ndarray  # (k, 2) the (up to two) surface facets that share it, -1 where fewer; more: a feature
    shared: np.ndarray  # (k,) how many surface facets share it
    one_face: np.ndarray  # (k,) between two facets of one CAD face (``_cad_faces``): curvature, never a feature

    def curvature(self, angles: np.ndarray) -> np.ndarray:
        """Which edges bend a smooth surface: two facets of one CAD face, or (where no face
        tells) meeting at less than FEATURE_ANGLE."""
        return (self.facets[:, 1] >= 0) & ((angles < FEATURE_ANGLE) | self.one_face)


def surface_edges(surface: Surface, tdim: int) -> tuple[Edges, np.ndarray]:
    """(the surface's edges, the smooth patch of each facet)."""
    m = len(surface.facets)
    if tdim == 3:
        ends = np.sort(surface.facets[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        facet_of = np.repeat(np.arange(m), 3)
    else:
        ends = np.sort(surface.facets, axis=1)
        facet_of = np.arange(m)
    if tdim == 2:  # a segment is its own edge; its neighbours meet it at its vertices
        edges = Edges(ends, np.c_[facet_of, np.full(m, -1)], np.ones(m, int), np.zeros(m, bool))
        return edges, _patches(surface, _vertex_neighbours(surface), m)
    order = np.lexsort(ends.T[::-1])
    ends, facet_of = ends[order], facet_of[order]
    start = np.r_[True, np.any(np.diff(ends, axis=0) != 0, axis=1)]
    first = np.flatnonzero(start)
    shared = np.diff(np.r_[first, len(ends)])
    pairs = np.c_[facet_of[first], np.where(shared >= 2, facet_of[np.minimum(first + 1, len(ends) - 1)], -1)]
    face = surface.face[pairs[:, 0]]
    one_face = (shared == 2) & (face >= 0) & (face == surface.face[pairs[:, 1]])
    edges = Edges(ends[first], pairs, shared, one_face)
    same_group = surface.group[pairs[:, 0]] == surface.group[pairs[:, 1]]
    smooth = (shared == 2) & edges.curvature(_edge_angles(surface, edges)) & same_group
    return edges, _patches(surface, pairs[smooth], m)


def _vertex_neighbours(surface: Surface) -> np.ndarray:
    """2D: pairs of segments that share a vertex and turn by less than FEATURE_ANGLE."""
    m = len(surface.facets)
    vertex = surface.facets.ravel()
    segment = np.repeat(np.arange(m), 2)
    order = np.argsort(vertex, kind="stable")
    vertex, segment = vertex[order], segment[order]
    same = vertex[1:] == vertex[:-1]
    a, b = segment[:-1][same], segment[1:][same]
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", surface.normals[a], surface.normals[b]), -1.0, 1.0))
    keep = (turn < FEATURE_ANGLE) & (surface.group[a] == surface.group[b])
    return np.c_[a[keep], b[keep]]


def _patches(surface: Surface, links: np.ndarray, count: int) -> np.ndarray:
    """Connected components of the facets joined by ``links`` (pairs of facets)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(count, count))
    return connected_components(graph, directed=False)[1]


def _edge_angles(surface: Surface, edges: Edges) -> np.ndarray:
    """The angle between the normals of the two facets on each edge (pi where not two)."""
    a, b = edges.facets[:, 0], edges.facets[:, 1]
    two = b >= 0
    angle = np.full(len(a), np.pi)
    cosine = np.einsum("ij,ij->i", surface.normals[a[two]], surface.normals[b[two]])
    angle[two] = np.arccos(np.clip(cosine, -1.0, 1.0))
    return angle


def _bend(surface: Surface, edges: Edges, angles: np.ndarray, tdim: int) -> float:
    """The largest angle between neighbouring facets of a smooth patch (0: all flat)."""
    if tdim == 2:
        pairs = _vertex_neighbours(surface)
        cosine = np.einsum("ij,ij->i", surface.normals[pairs[:, 0]], surface.normals[pairs[:, 1]])
        turns = np.arccos(np.clip(cosine, -1.0, 1.0))
        return float(turns.max(initial=0.0))
    return float(np.max(np.where(edges.curvature(angles), angles, 0.0), initial=0.0))


def _coarse_groups(gmsh, tdim: int, surface: Surface, edges: Edges, angles: np.ndarray,
                   moves: np.ndarray) -> dict[str, CoarseSurface]:
    """The facet groups whose neighbouring facets meet at over COARSE_ANGLE on average
    (their sharp edges aside): too few facets to tell their curvature (a radius of
    curvature under ~3 facet edges).
    Off CAD faces, a tube with six facets or fewer around meets at SHARP_ANGLE or more,
    as a prism's sides do: it is taken for one. ``moves``: how far each surface edge's
    midpoint moves."""
    if tdim == 2:
        return {}
    out: dict[str, CoarseSurface] = {}
    for dim, tag in gmsh.model.getPhysicalGroups(tdim - 1):
        mine = np.zeros(len(surface.facets), bool)
        for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
            mine[_entity_facets(gmsh, tdim, surface.index, entity)] = True
        inside = mine[edges.facets[:, 0]] & (edges.facets[:, 1] >= 0) & mine[np.maximum(edges.facets[:, 1], 0)]
        bent = angles[inside & ((angles < SHARP_ANGLE) | edges.one_face)]
        if len(bent) and float(np.mean(bent)) > COARSE_ANGLE:
            name = gmsh.model.getPhysicalName(dim, tag) or str(tag)
            out[name] = CoarseSurface(float(np.mean(bent)), bool((surface.face[mine] >= 0).all()),
                                      float(moves[inside].max(initial=0.0)))
    return out


# --------------------------------------------------------------------------- the midpoints


def midpoint_targets(surface: Surface, edges: Edges, patches: np.ndarray, angles: np.ndarray,
                     position: np.ndarray, tdim: int) -> np.ndarray:
    """Where each surface edge's midpoint goes (module docstring), capped at MOVE_LIMIT
    of its edge."""
    a, b = position[edges.ends[:, 0]], position[edges.ends[:, 1]]
    chord = (a + b) / 2
    curving = edges.curvature(angles) if tdim == 3 else np.ones(len(a), bool)
    first, second = _on_flat_faces(surface, edges)
    flat = (first & second) | (curving & (first | second))  # on a flat face, or where one meets it smoothly
    smooth = curving & ~flat
    out = chord.copy()
    if smooth.any():
        normals = _patch_normals(surface, patches, position)
        patch = patches[edges.facets[smooth, 0]]
        na = normals[(patch, edges.ends[smooth, 0])]
        nb = normals[(patch, edges.ends[smooth, 1])]
        out[smooth] = chord[smooth] + _arc_sag(b[smooth] - a[smooth], na, nb)
    if tdim == 3 and (~curving).any():  # a feature line runs on through its straight pieces (their tangents)
        out[~curving] = _feature_midpoints(edges, ~curving, position)
    out[flat] = chord[flat]
    move = out - chord
    limit = MOVE_LIMIT * np.linalg.norm(b - a, axis=1)
    size = np.linalg.norm(move, axis=1)
    return chord + move * np.minimum(1.0, limit / np.maximum(size, 1e-300))[:, None]


def _on_flat_faces(surface: Surface, edges: Edges) -> tuple[np.ndarray, np.ndarray]:
    """Per edge, whether its first and its second facet lie on a flat CAD face
    (``_cad_faces``: facets within BENT_ANGLE of one plane); such edges stay straight.
    Where a flat face meets a curved one tangentially (a box's side and its rounded
    edge) no angle tells them apart, and the vertex normals there, shared with the
    curved face, bent the flat face's midpoints outward (by up to 2.8e-3 on a rounded
    box of 3 x 2, 7 % of its edge)."""
    face = surface.face
    known = face >= 0
    if not known.any():
        return np.zeros(len(edges.ends), bool), np.zeros(len(edges.ends), bool)
    count = int(face.max()) + 1
    mean = np.zeros((count, surface.normals.shape[1]))
    np.add.at(mean, face[known], surface.normals[known])
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    cosine = np.einsum("ij,ij->i", surface.normals[known], mean[face[known]])
    bent = np.zeros(count, bool)
    np.logical_or.at(bent, face[known], cosine < np.cos(BENT_ANGLE))
    flat_facet = known & ~bent[np.maximum(face, 0)]
    first, second = edges.facets[:, 0], edges.facets[:, 1]
    return flat_facet[first], (second < 0) | flat_facet[np.maximum(second, 0)]


def _arc_sag(d: np.ndarray, na: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """From the chord's middle to the middle of the circular arc over chord ``d`` = b - a
    whose ends meet the planes of their normals na, nb at the angles they make with the
    chord (their mean, phi): (|d| / 2) tan(phi / 2) along na + nb."""
    length = np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    below_a = np.clip(-np.einsum("ij,ij->i", d, na) / length, -1.0, 1.0)  # sin of b's drop below a's plane
    below_b = np.clip(np.einsum("ij,ij->i", d, nb) / length, -1.0, 1.0)  # ... and of a's below b's
    phi = (np.arcsin(below_a) + np.arcsin(below_b)) / 2
    direction = na + nb
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
    return (length / 2 * np.tan(phi / 2))[:, None] * direction


class _PatchNormals(dict):
    """(patch, node tag) -> unit normal, looked up for arrays of both."""

    def __getitem__(self, key):
        patch, node = key
        return np.array([dict.__getitem__(self, (int(p), int(n))) for p, n in zip(patch, node)])


def _patch_normals(surface: Surface, patches: np.ndarray, position: np.ndarray) -> _PatchNormals:
    """Each patch's vertex normals: the mean of its facets' normals at the vertex, each
    weighted by the facet's angle there (independent of how the facets are cut)."""
    tdim = surface.facets.shape[1]
    sums: dict[tuple[int, int], np.ndarray] = {}
    for corner in range(tdim):
        node = surface.facets[:, corner]
        if tdim == 3:
            u = position[surface.facets[:, (corner + 1) % 3]] - position[node]
            v = position[surface.facets[:, (corner + 2) % 3]] - position[node]
            cosine = np.einsum("ij,ij->i", u, v) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-300)
            weight = np.arccos(np.clip(cosine, -1.0, 1.0))
        else:
            weight = np.ones(len(node))
        for p, n, w, normal in zip(patches, node, weight, surface.normals):
            key = (int(p), int(n))
            sums[key] = sums.get(key, 0.0) + w * normal
    return _PatchNormals({k: v / max(np.linalg.norm(v), 1e-300) for k, v in sums.items()})


def _feature_midpoints(edges: Edges, feature: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Midpoints of feature edges on the Hermite curve along their feature lines."""
    ends = edges.ends[feature]
    neighbours: dict[int, list[int]] = {}
    for a, b in ends:
        neighbours.setdefault(int(a), []).append(int(b))
        neighbours.setdefault(int(b), []).append(int(a))
    a, b = position[ends[:, 0]], position[ends[:, 1]]
    chord = b - a
    length = np.linalg.norm(chord, axis=1)
    direction = chord / np.maximum(length, 1e-300)[:, None]
    ta = np.array([_tangent(int(n), neighbours, position, d) for n, d in zip(ends[:, 0], direction)])
    tb = np.array([_tangent(int(n), neighbours, position, d) for n, d in zip(ends[:, 1], direction)])
    return (a + b) / 2 + length[:, None] * (ta - tb) / 8


def _tangent(node: int, neighbours: dict, position: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The feature line's unit tangent at ``node``, oriented along ``direction``: from its
    previous vertex to its next where exactly two feature edges meet, else the chord."""
    near = neighbours[node]
    if len(near) != 2:
        return direction
    t = position[near[1]] - position[near[0]]
    t /= max(np.linalg.norm(t), 1e-300)
    return t if t @ direction >= 0 else -t


def _set_order_2(gmsh, tdim: int) -> np.ndarray:
    """gmsh's setOrder(2), which numbers the nodes anew (elements keep their order and
    their vertices' order): old node tag -> new one."""
    _, before = gmsh.model.mesh.getElementsByType(CELLS[tdim][0])
    before = np.asarray(before, np.int64).reshape(-1, tdim + 1)
    gmsh.model.mesh.setOrder(2)
    _, after = gmsh.model.mesh.getElementsByType(CELLS[tdim][1])
    after = np.asarray(after, np.int64).reshape(len(before), -1)[:, : tdim + 1]
    renumber = np.full(int(before.max()) + 1, -1, np.int64)
    renumber[before] = after
    return renumber


def _midpoint_nodes(gmsh, tdim: int) -> dict[tuple[int, int], int]:
    """After setOrder(2): (sorted edge ends) -> the node tag of the edge's midpoint."""
    _, nodes = gmsh.model.mesh.getElementsByType(CELLS[tdim][1])
    rows = np.asarray(nodes, np.int64).reshape(-1, len(CELLS[tdim][2]) + tdim + 1)
    out: dict[tuple[int, int], int] = {}
    for i, j, m in CELLS[tdim][2]:
        lo, hi = np.minimum(rows[:, i], rows[:, j]), np.maximum(rows[:, i], rows[:, j])
        out.update(zip(zip(lo.tolist(), hi.tolist()), rows[:, m].tolist()))
    return out
