"""Finer target surfaces where their flat faces cut the corners of a curved shape.

A target's vertices lie on the organ, its flat faces inside it wherever it curves: an
STL of a sphere of radius R with edges e lies about e^2 / 12 R inside on average. The
E of a stiff region rests on motions of its surface about that small -- a user's core
(1,920 triangles) came out 8-12 % soft, its interval missing the truth. The source mesh
is curved on load; the target is refined here instead: each face split in four (a 2D
segment in two), the new vertices at its edges' midpoints lifted onto the smooth
surface through the old ones -- Phong's projection halved, which for a quadric through a
face's corners is its height over the face to leading order -- until the faces' mean
lift is under FACETED of their edges, at most MAX_LEVELS times. Where neighbouring faces
meet at a crease (CREASE_DEGREES: a box's edges, a letter's corners) nothing is lifted.
The closest points, the misfit and its gradient stay those of a flat polyhedron.
"""

from __future__ import annotations

import numpy as np

from fenics_elasto.geometry.surface import Surface
from fenics_elasto.util.logs import log

# Neighbouring faces meeting at more than this angle are a crease of the shape itself: a
# clean segmentation or an STL of a curved organ meets its neighbours at a few degrees.
CREASE_DEGREES = 30.0
# A target is refined while its faces' mean lift at their centres exceeds this share of
# its mean edge (the user's core: 2.7 %; one level halves it; their block's 0.29 % alone
# put its nu out of its interval), at most MAX_LEVELS times and to at most MAX_CELLS
# faces (each level multiplies them by 4 in 3D, 2 in 2D). The pelvis phantom's simulated
# targets (26-42k faces, 0.45-0.5 %) stay as they are: refined to 105-167k faces, every
# closest-point query on them took twice as long.
FACETED = 2.5e-3
MAX_LEVELS = 2
MAX_CELLS = 100_000
SPLIT = {2: 2, 3: 4}  # the faces a level makes of one


def corner_normals(surface: Surface) -> np.ndarray:
    """(faces, corners, dim): at each face's corner, the area-weighted mean normal of the
    faces around that vertex that meet the face at less than CREASE_DEGREES (each turned
    to the face's side first: the faces' order does not matter), unit length."""
    faces = surface.cells
    corner_vertex = faces.ravel()
    incident = np.argsort(corner_vertex, kind="stable") // faces.shape[1]  # faces around each vertex, in turn
    degree = np.bincount(corner_vertex, minlength=len(surface.points))
    start = np.concatenate([[0], np.cumsum(degree)])[corner_vertex]
    own = np.repeat(np.arange(len(faces)), faces.shape[1])
    total = np.zeros((len(corner_vertex), surface.dim))
    crease = np.cos(np.radians(CREASE_DEGREES))
    for j in range(int(degree.max(initial=0))):
        has = degree[corner_vertex] > j
        corner, other = np.flatnonzero(has), incident[start[has] + j]
        cosine = np.einsum("nd,nd->n", surface.normals[other], surface.normals[own[corner]])
        keep = np.abs(cosine) >= crease
        np.add.at(total, corner[keep], np.sign(cosine[keep])[:, None] * surface.area_normals[other[keep]])
    length = np.linalg.norm(total, axis=1, keepdims=True)
    return (total / np.where(length > 0, length, 1.0)).reshape(faces.shape + (surface.dim,))


def lifts(surface: Surface, normals: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(faces, dim): how far the smooth surface lies off each face at the point with
    barycentric weights ``bary`` (the same for every face): 1/2 sum_i b_i ((v_i - p) . m_i)
    (m_i . n) n, m_i the corner normals, n the face's. Unchanged by either normal's sign."""
    corners = surface.points[surface.cells]
    p = np.einsum("k,fkd->fd", bary, corners)
    n = surface.normals
    height = np.einsum("fkd,fkd->fk", corners - p[:, None], normals) * np.einsum("fkd,fd->fk", normals, n)
    return 0.5 * (height @ bary)[:, None] * n


def faceting(surface: Surface, normals: np.ndarray | None = None) -> float:
    """The faces' mean lift at their centres, in mean edges."""
    if len(surface.cells) == 0 or surface.mean_edge <= 0:
        return 0.0
    normals = corner_normals(surface) if normals is None else normals
    k = surface.cells.shape[1]
    return float(np.linalg.norm(lifts(surface, normals, np.full(k, 1.0 / k)), axis=1).mean()) / surface.mean_edge


def refined(surface: Surface, normals: np.ndarray) -> Surface:
    """Every face split at its edges' midpoints, each lifted onto the smooth surface (the
    mean of its faces' lifts there)."""
    cells, k = surface.cells, surface.cells.shape[1]
    pairs = [(0, 1), (1, 2), (2, 0)] if k == 3 else [(0, 1)]
    edges = np.stack([np.sort(cells[:, list(pair)], axis=1) for pair in pairs], axis=1)  # (faces, pairs, 2)
    unique, which = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
    which = which.reshape(len(cells), len(pairs))
    moved = np.zeros((len(unique), surface.dim))
    for j, (a, b) in enumerate(pairs):
        bary = np.zeros(k)
        bary[[a, b]] = 0.5
        np.add.at(moved, which[:, j], lifts(surface, normals, bary))
    uses = np.bincount(which.ravel(), minlength=len(unique))[:, None]
    middle = surface.points[unique].mean(axis=1) + moved / uses
    m = which + len(surface.points)  # the midpoints' vertex numbers, per face and edge
    if k == 2:
        new = np.concatenate([np.c_[cells[:, 0], m[:, 0]], np.c_[m[:, 0], cells[:, 1]]])
    else:
        new = np.concatenate([np.c_[cells[:, 0], m[:, 0], m[:, 2]], np.c_[cells[:, 1], m[:, 1], m[:, 0]],
                              np.c_[cells[:, 2], m[:, 2], m[:, 1]], m])
    out = Surface(np.vstack([surface.points, middle]), new)
    out.smoothed_from, out.noise_gain = surface.smoothed_from, surface.noise_gain
    return out


def finer_where_faceted(surface: Surface, name: str) -> Surface:
    """``surface`` refined while its faces cut its curves' corners by more than FACETED of
    an edge (module docstring), with one line saying so."""
    start, levels = surface, 0
    normals = corner_normals(surface)  # each level's, for its measure and its split alike
    share = before = faceting(surface, normals)
    while share > FACETED and levels < MAX_LEVELS and len(surface.cells) * SPLIT[surface.dim] <= MAX_CELLS:
        surface = refined(surface, normals)
        levels += 1
        normals = corner_normals(surface)
        share = faceting(surface, normals)
    if levels:
        log.info(f"note: {name}: its flat faces cut its curves' corners by {100 * before:.2g} % of an edge on average: "
                 f"refined {levels}x onto the smooth surface through its vertices ({len(start.cells)} -> "
                 f"{len(surface.cells)} faces, {100 * share:.2g} % left)")
    return surface
