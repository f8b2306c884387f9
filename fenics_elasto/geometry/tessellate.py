"""Mesh entities as flat pieces for output: watertight, oriented, in linear time.

Surfaces written by ``simulate`` are fed back as targets and training examples, so
they must be what they stand for: a closed group closed, every triangle oriented
like its neighbours, outward. A curved (P2-geometry) facet with a P2 displacement is
written as ``pieces`` x ``pieces`` flat triangles (a line as ``pieces`` segments): a
flat facet would cut inside a curved organ by its sag (~0.02 cm on the phantom), a
fake displacement to a surface target.

The pieces' points form a lattice on each facet. Points are not merged by position
afterwards (VTK's ``clean``, O(n log n) and the bulk of the output time on large
meshes): each gets a key from the mesh itself -- a corner its global node number, a
point on an edge the edge's two global node numbers and its step along the edge
(counted from the lower number, so both facets of an edge agree), an interior point
its facet -- and equal keys are one point. Under MPI each rank sends its owned
entities with their keys; rank 0 numbers the points.

Orientation: each facet is first turned away from a cell it bounds (outward on the
body's boundary); rank 0 then makes each connected piece consistent (libigl's
``bfs_orient``) and turns every closed one outward (positive enclosed volume). An
open piece inside the body (part of an interface) keeps a consistent orientation
whose side is arbitrary.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

import dolfinx

PIECES = 4  # flat pieces per curved facet edge, while a surface has few facets
MAX_TRIANGLES = 1_000_000  # ... and fewer beyond: a fine mesh's facets are flat enough already


def default_pieces(facets: int) -> int:
    """Pieces per curved facet edge for a surface of ``facets`` facets: PIECES, fewer
    when that would exceed MAX_TRIANGLES (the sag of a facet falls as its size squared)."""
    return int(np.clip(np.sqrt(MAX_TRIANGLES / max(facets, 1)), 1, PIECES))


@dataclass
class Lattice:
    """Points on a reference simplex (rows of ``shape``: the entity's node weights) and
    the cells between them. Per point: its corner ``ends`` -- (a, a) at corner a, (a, b)
    on the edge from corner a to b, (-1, -1) inside -- and ``step``, its position
    along that edge counted from a (of ``level`` steps)."""

    shape: np.ndarray
    cells: np.ndarray
    ends: np.ndarray
    step: np.ndarray
    level: int


def corner_lattice(width: int) -> Lattice:
    """The corners of a flat simplex of ``width`` vertices, one cell."""
    ends = np.repeat(np.arange(width)[:, None], 2, axis=1)
    return Lattice(np.eye(width), np.arange(width)[None], ends, np.zeros(width, int), 1)


def line_lattice(level: int) -> Lattice:
    """``level`` segments of a quadratic line (nodes v0, v1, midpoint)."""
    t = np.arange(level + 1) / level
    shape = np.c_[(1 - t) * (1 - 2 * t), t * (2 * t - 1), 4 * t * (1 - t)]
    ends = np.full((level + 1, 2), -1)
    ends[0], ends[-1] = 0, 1
    return Lattice(shape, np.c_[np.arange(level), np.arange(1, level + 1)], ends, np.zeros(level + 1, int), level)


def triangle_lattice(level: int) -> Lattice:
    """``level``^2 triangles of a quadratic triangle (nodes v0, v1, v2, e01, e12, e20),
    oriented as (v0, v1, v2)."""
    ij = np.array([(i, j) for i in range(level + 1) for j in range(level + 1 - i)])
    index = {tuple(p): n for n, p in enumerate(ij)}
    cells = []
    for i, j in ij:
        if i + j < level:
            cells.append((index[i, j], index[i + 1, j], index[i, j + 1]))
        if i + j < level - 1:
            cells.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    l1, l2 = ij.T / level
    l0 = 1 - l1 - l2
    shape = np.c_[l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), 4 * l0 * l1, 4 * l1 * l2, 4 * l2 * l0]
    i, j = ij.T
    ends, step = np.full((len(ij), 2), -1), np.zeros(len(ij), int)
    for where, a, b, k in ((j == 0, 0, 1, i), (i + j == level, 1, 2, j), (i == 0, 2, 0, level - j)):
        ends[where], step[where] = (a, b), k[where]
    for (ci, cj), corner in (((0, 0), 0), ((level, 0), 1), ((0, level), 2)):
        ends[index[ci, cj]], step[index[ci, cj]] = corner, 0
    return Lattice(shape, np.array(cells), ends, step, level)


def node_blocks(V: dolfinx.fem.FunctionSpace) -> np.ndarray:
    """Map geometry node -> block (node) of V at the same point (-1 where V has none).

    Lagrange DOFs and geometry nodes share one local layout (vertices first, then
    edges): all nodes match when V has the geometry's degree, the vertices otherwise.
    """
    mesh = V.mesh
    geom, dofs = mesh.geometry.dofmaps[0], V.dofmap.list
    shared = geom.shape[1] if geom.shape[1] == dofs.shape[1] else dolfinx.cpp.mesh.cell_num_vertices(mesh.topology.cell_type)
    out = np.full(mesh.geometry.x.shape[0], -1, np.int64)
    out[geom[:, :shared].ravel()] = dofs[:, :shared].ravel()
    return out


def _quadratic_order(nodes: np.ndarray, x: np.ndarray) -> np.ndarray:
    """6-node triangles (vertices first) reordered to v0, v1, v2, e01, e12, e20.

    Which edge each midpoint node sits on is read from the positions (the nearest
    straight midpoint), not assumed from a node ordering.
    """
    corners = x[nodes[:, :3]]
    straight = corners[:, [[0, 1], [1, 2], [2, 0]]].mean(axis=2)  # (n, edge, gdim)
    gap = np.linalg.norm(x[nodes[:, 3:]][:, :, None] - straight[:, None], axis=3)  # (n, node, edge)
    ordered = nodes.copy()
    ordered[np.arange(len(nodes))[:, None], 3 + gap.argmin(axis=2)] = nodes[:, 3:]
    return ordered


def _away_from_cells(mesh, entities: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Triangles (v0, v1, v2, e01, e12, e20) turned so that their normal points away
    from the first cell each bounds."""
    tdim = mesh.topology.dim
    f2c = mesh.topology.connectivity(tdim - 1, tdim)
    cells = f2c.array[f2c.offsets[entities]]
    x = mesh.geometry.x
    inside = x[mesh.geometry.dofmaps[0][cells, : tdim + 1]].mean(axis=1)
    corners = x[nodes[:, :3]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flip = np.einsum("ij,ij->i", normal, corners.mean(axis=1) - inside) < 0
    swapped = nodes[:, [0, 2, 1, 5, 4, 3][: nodes.shape[1]]]
    return np.where(flip[:, None], swapped, nodes)


def _lattice_for(mesh, dim: int, nodes: np.ndarray, curved: bool, pieces: int) -> tuple[np.ndarray, Lattice]:
    """The entities' nodes (ordered for the lattice) and the lattice to place on them."""
    if not curved:
        return nodes[:, : dim + 1], corner_lattice(dim + 1)
    if dim == 1:
        return nodes, line_lattice(pieces)
    return _quadratic_order(nodes, mesh.geometry.x), triangle_lattice(pieces)


def gather_entities(u: dolfinx.fem.Function, dim: int, entities: np.ndarray,
                    pieces: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(points, cells, displacement) of owned ``entities`` of dimension ``dim`` on rank 0
    (None elsewhere), points padded to 3D, shared by construction (module docstring).

    Cells come as their vertices. Curved facets with a displacement on their midpoints
    come as pieces^dim flat ones (``pieces`` None: ``default_pieces`` of their count).
    """
    mesh = u.function_space.mesh
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    mesh.topology.create_connectivity(dim, tdim)
    owned = entities[entities < mesh.topology.index_map(dim).size_local].astype(np.int32)
    width = math.comb(dim + mesh.geometry.cmaps[0].degree, dim)  # geometry nodes of a simplex of dimension dim
    nodes = dolfinx.mesh.entities_to_geometry(mesh, dim, owned).reshape(len(owned), width)  # a rank may own none
    blocks = node_blocks(u.function_space)
    curved = mesh.comm.allreduce(bool(dim < tdim and nodes.shape[1] > dim + 1 and (blocks[nodes] >= 0).all()),
                                 op=MPI.LAND)
    if pieces is None:
        pieces = default_pieces(mesh.comm.allreduce(len(owned)))
    nodes, lattice = _lattice_for(mesh, dim, nodes, curved, pieces)
    if dim == 2 and tdim == 3:
        nodes = _away_from_cells(mesh, owned, nodes)
    x, values = mesh.geometry.x[:, :gdim], u.x.array.reshape(-1, gdim)
    points = np.matmul(lattice.shape, x[nodes]).reshape(-1, gdim)  # (entities, lattice points, gdim)
    disp = np.matmul(lattice.shape, values[blocks[nodes]]).reshape(-1, gdim)
    numbers = np.asarray(mesh.geometry.input_global_indices, np.int64)
    count = mesh.comm.allreduce(int(numbers.max(initial=-1)) + 1, op=MPI.MAX)
    keys = _keys(numbers[nodes[:, : dim + 1]], lattice, count)
    parts = mesh.comm.gather((points, disp, keys), root=0)
    if mesh.comm.rank != 0:
        return None
    return _assemble(parts, lattice, gdim, oriented=dim == 2 and tdim == 3)


def _keys(corners: np.ndarray, lattice: Lattice, count: int) -> np.ndarray:
    """(n, points) int64: the key of each lattice point of each entity -- equal for the
    same point of neighbouring entities -- or -1 for a point inside the entity.
    ``corners``: global node numbers of the entities' corners; ``count``: how many there are."""
    a_end, b_end = lattice.ends.T
    inside = a_end < 0
    a = corners[:, np.where(inside, 0, a_end)]
    b = corners[:, np.where(inside, 0, b_end)]
    step = np.broadcast_to(lattice.step, a.shape)
    low, high = np.minimum(a, b), np.maximum(a, b)
    step = np.where(a <= b, step, lattice.level - step)  # counted from the lower node number
    keys = (low.astype(np.int64) * (count + 1) + high) * (lattice.level + 1) + step
    return np.where(inside, -1, keys)


def _assemble(parts, lattice: Lattice, gdim: int, oriented: bool):
    """Rank 0: one point per key, cells renumbered, closed pieces outward."""
    points = np.concatenate([p for p, _, _ in parts])
    disp = np.concatenate([d for _, d, _ in parts])
    keys = np.concatenate([k for _, _, k in parts])  # (entities, lattice points)
    per = len(lattice.shape)
    flat = keys.ravel()
    shared = flat >= 0
    number = np.empty(len(flat), np.int64)
    unique, first, inverse = np.unique(flat[shared], return_index=True, return_inverse=True)
    number[shared] = inverse.ravel()
    number[~shared] = len(unique) + np.arange(int((~shared).sum()))
    keep = np.concatenate([np.flatnonzero(shared)[first], np.flatnonzero(~shared)])
    cells = number.reshape(-1, per)[:, lattice.cells].reshape(-1, lattice.cells.shape[1])
    xyz, pad = np.zeros((len(keep), 3)), np.zeros((len(keep), 3))
    xyz[:, :gdim], pad[:, :gdim] = points[keep], disp[keep]
    if oriented and len(cells):
        cells = orient_outward(xyz, cells)
    return xyz, cells, pad


def orient_outward(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles oriented consistently per connected piece, each closed piece outward."""
    import igl

    triangles, piece = igl.bfs_orient(np.ascontiguousarray(triangles, dtype=np.int64))
    piece = piece.ravel()
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, which, uses = np.unique(edges[:, 0] * len(points) + edges[:, 1], return_inverse=True, return_counts=True)
    open_piece = np.zeros(piece.max() + 1, bool)
    open_piece[np.repeat(piece, 3)[uses[which.ravel()] == 1]] = True
    p = points - points.mean(axis=0)
    a, b, c = p[triangles[:, 0]], p[triangles[:, 1]], p[triangles[:, 2]]
    volume = np.bincount(piece, np.einsum("ij,ij->i", a, np.cross(b, c)), minlength=len(open_piece))
    inward = (~open_piece & (volume < 0))[piece]
    triangles[inward] = triangles[inward][:, [0, 2, 1]]
    return triangles
