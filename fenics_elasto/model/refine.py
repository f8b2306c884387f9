"""A scene refined once, on the geometry its mesh stands for, and fields carried over.

An estimate is only as good as its source mesh; re-running it on a once-refined
source shows how much the answer still moves. ``refine_scene`` writes that source:
every simplex split uniformly (segment -> 2, triangle -> 4, tetrahedron -> 8, its
interior octahedron cut along the shortest diagonal), every physical group kept.

The idea: a simplex of geometry order p (gmsh's 3-/4-node elements p = 1, 6-/10-node
ones p = 2) split once has its children's nodes on the lattice of order 2p of the
parent -- barycentric coordinates in multiples of 1/(2p). Each lattice point gets the
parent's own map evaluated there (gmsh's Lagrange basis of the parent's type), so

- order 2: the children are order 2 again and together describe exactly the parent's
  curved geometry (its quadratic map restricted to each child is a quadratic, fixed
  by the child's six or ten nodes); a P2 field of the coarse mesh lies in the fine P2
  space;
- order 1: new nodes are edge midpoints; the geometry does not change: a polygon
  stays a polygon. (Straight-sided meshes of curved bodies stay as coarse in shape as
  they were: only the field resolution improves.)

A lattice point is named by the parent vertices it is made of, with multiplicity
(barycentric (3/4, 1/4) on edge ab is (a, a, a, b); (1/2, 1/4, 1/4) on face abc is
(a, a, b, c)), sorted. Neighbouring cells and their boundary facets give the same
point the same name, so new nodes are shared by construction, not by rounding; points
that are parent nodes ((a, a, b, b): the midpoint node of edge ab) keep their node.

Groups are carried by gmsh's entities: a child element lives in its parent's entity,
and physical groups list entities, so a child facet belongs to exactly the groups its
parent did (overlapping groups stay overlapping) and group tags and names are kept.

``prolongation`` / ``transfer_bases`` move boundary fields from a scene to its
refinement: a fine node on a coarse facet has the coarse field's value there, the
coarse facet's Lagrange basis at a lattice point -- exact for any field of the coarse
space, since the meshes are nested.
"""

from __future__ import annotations

import copy
import itertools
import os
import time
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import scipy.sparse
from mpi4py import MPI
from scipy.spatial import cKDTree

from fenics_elasto.config.toml import read_toml, toml_text
from fenics_elasto.config.problem import map_files, validate_problem
from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.util.errors import UserError, on_root, require
from fenics_elasto.mesh.gmsh_models import fresh_gmsh_model, node_positions, open_msh, physical_facets, save
from fenics_elasto.util.logs import log
from fenics_elasto.model.scene import Scene, load_scene
from fenics_elasto.geometry.meshes import unique_rows

FAMILY = {1: "Line", 2: "Triangle", 3: "Tetrahedron"}
POINT = 15  # gmsh's 1-node point element: kept as it is
SIMPLICES = (POINT, 1, 8, 2, 9, 4, 11)  # gmsh types: points, lines, triangles, tetrahedra of order 1 and 2


# --------------------------------------------------------------------------- the split of one element type


def lattice(dim: int, order: int) -> np.ndarray:
    """Every barycentric multi-index (dim + 1 integers summing to ``order``), one per row."""
    points = [m for m in itertools.product(range(order + 1), repeat=dim + 1) if sum(m) == order]
    return np.array(points, dtype=np.int64)


def to_barycentric(dim: int, local: np.ndarray) -> np.ndarray:
    """gmsh reference coordinates -> barycentric ones (lines run over [-1, 1])."""
    if dim == 1:
        return np.c_[(1 - local[:, 0]) / 2, (1 + local[:, 0]) / 2]
    return np.c_[1 - local.sum(axis=1), local]


def to_reference(dim: int, bary: np.ndarray) -> np.ndarray:
    """Barycentric coordinates -> gmsh reference coordinates, padded to (u, v, w)."""
    local = (bary[:, 1] - bary[:, 0])[:, None] if dim == 1 else bary[:, 1:]
    return np.pad(local, ((0, 0), (0, 3 - dim)))


def basis_at(gmsh, etype: int, bary: np.ndarray) -> np.ndarray:
    """(points, nodes): the Lagrange basis of gmsh element type ``etype`` at barycentric points."""
    dim = gmsh.model.mesh.getElementProperties(etype)[1]
    _, values, _ = gmsh.model.mesh.getBasisFunctions(etype, to_reference(dim, bary).ravel(), "Lagrange")
    return np.asarray(values).reshape(len(bary), -1)


def node_multi_indices(gmsh, etype: int) -> np.ndarray:
    """(nodes, dim + 1): each node of the element type as a barycentric multi-index of its order."""
    _, dim, order, _, local, _ = gmsh.model.mesh.getElementProperties(etype)
    return np.rint(to_barycentric(dim, np.reshape(local, (-1, dim))) * order).astype(np.int64)


def red_children(dim: int) -> list[np.ndarray]:
    """The uniform split's children as vertex multi-indices of order 2, positively oriented:
    one (children, dim + 1, dim + 1) array per variant (tetrahedra: the three diagonals
    of the inner octahedron)."""
    e = np.eye(dim + 1, dtype=np.int64)
    v, m = 2 * e, lambda i, j: e[i] + e[j]
    if dim == 1:
        variants = [[[v[0], m(0, 1)], [m(0, 1), v[1]]]]
    elif dim == 2:
        variants = [[[v[0], m(0, 1), m(0, 2)], [m(0, 1), v[1], m(1, 2)], [m(0, 2), m(1, 2), v[2]],
                     [m(0, 1), m(1, 2), m(0, 2)]]]
    else:
        corners = [[v[i]] + [m(i, j) for j in range(4) if j != i] for i in range(4)]
        opposite = [((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))]
        variants = []
        for a, b in opposite:
            (c, c2), (f, f2) = [pair for pair in opposite if pair != (a, b)]
            ring = [m(*c), m(*f), m(*c2), m(*f2)]  # around the diagonal m(a)-m(b)
            variants.append(corners + [[m(*a), m(*b), ring[k], ring[(k + 1) % 4]] for k in range(4)])
    out = []
    for children in np.array(variants):
        local = to_reference(dim, children.reshape(-1, dim + 1) / 2.0)[:, :dim].reshape(len(children), dim + 1, dim)
        flipped = np.linalg.det(local[:, 1:] - local[:, :1]) < 0
        children[flipped, :2] = children[flipped, 1::-1]
        out.append(children)
    return out


@dataclass(frozen=True)
class Split:
    """The uniform split of one gmsh element type, on the parent's lattice of order 2p."""

    etype: int
    dim: int
    order: int
    points: np.ndarray  # (L, dim + 1) lattice multi-indices
    parent_nodes: np.ndarray  # (nodes,) the lattice point of each parent node
    children: np.ndarray  # (variants, children, nodes) lattice points of each child's nodes
    basis: np.ndarray  # (L, nodes) the parent's shape functions at the lattice points
    diagonals: np.ndarray  # (variants, 2) lattice points at the ends of each variant's diagonal


@cache
def split_of(etype: int) -> Split:
    import gmsh

    _, dim, order, _, _, _ = gmsh.model.mesh.getElementProperties(etype)
    points = lattice(dim, 2 * order)
    index = {tuple(p): i for i, p in enumerate(points)}
    nodes = node_multi_indices(gmsh, etype)
    variants = red_children(dim)
    # A child's node with multi-index M (order p) over child vertices w_v (order 2)
    # sits at sum_v M_v w_v on the parent's lattice of order 2p.
    children = np.array([[[index[tuple(n @ child)] for n in nodes] for child in variant] for variant in variants])
    e = np.eye(dim + 1, dtype=np.int64) * order
    ends = [((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))] if dim == 3 else [((0, 1), (0, 1))]
    diagonals = np.array([[index[tuple(e[a] + e[b])], index[tuple(e[c] + e[d])]] for (a, b), (c, d) in ends])
    return Split(etype, dim, order, points, np.array([index[tuple(2 * n)] for n in nodes]), children,
                 basis_at(gmsh, etype, points / (2.0 * order)), diagonals)


# --------------------------------------------------------------------------- refining elements


@dataclass
class Batch:
    """The elements of one gmsh entity of one type, and what the split makes of them."""

    dim: int
    entity: int
    etype: int
    nodes: np.ndarray  # (elements, nodes per element) node tags
    points: np.ndarray | None = None  # (elements, L) node tag of every lattice point  } filled by
    positions: np.ndarray | None = None  # (elements, L, 3) their coordinates            } refine_batches

    def children(self) -> tuple[int, np.ndarray]:
        """(child element type, (children, nodes) node tags)."""
        if self.etype == POINT:
            return POINT, self.nodes
        split = split_of(self.etype)
        variant = np.zeros(len(self.nodes), dtype=np.int64)
        if len(split.children) > 1:  # the shortest diagonal: the better-shaped children
            assert self.positions is not None  # refine_batches placed the lattice points
            ends = self.positions[:, split.diagonals]  # (elements, variants, 2, 3)
            variant = np.argmin(np.linalg.norm(ends[:, :, 0] - ends[:, :, 1], axis=-1), axis=1)
        picked = split.children[variant].reshape(len(self.nodes), -1)
        return self.etype, np.take_along_axis(self.points, picked, axis=1).reshape(-1, split.children.shape[-1])


def lattice_keys(batch: Batch) -> np.ndarray:
    """(elements, L, 2p) each lattice point's name: its parent vertices with multiplicity, sorted."""
    split = split_of(batch.etype)
    vertices = batch.nodes[:, : split.dim + 1]
    repeat = np.stack([np.repeat(np.arange(split.dim + 1), m) for m in split.points])  # (L, 2p)
    return np.sort(vertices[:, repeat], axis=-1)


def refine_batches(batches: list[Batch], position: np.ndarray, source: Path) -> tuple[np.ndarray, np.ndarray]:
    """Node tags of every lattice point of every batch (``batch.points``); returns the
    new nodes' (tags, coordinates). ``position``: coordinates by node tag."""
    keys, known, coords = [], [], []
    for batch in batches:
        if batch.etype == POINT:
            continue
        split = split_of(batch.etype)
        batch.positions = np.einsum("ln,end->eld", split.basis, position[batch.nodes])
        keys.append(lattice_keys(batch).reshape(-1, 2 * split.order))
        tags = np.zeros((len(batch.nodes), len(split.points)), dtype=np.int64)  # 0: a new node
        tags[:, split.parent_nodes] = batch.nodes
        known.append(tags.ravel())
        coords.append(batch.positions.reshape(-1, 3))
    first, inverse = unique_rows(np.concatenate(keys))
    known_tags, coords_all = np.concatenate(known), np.concatenate(coords)  # per lattice point
    tag_of, lowest = np.zeros(len(first), np.int64), np.full(len(first), np.iinfo(np.int64).max)
    np.maximum.at(tag_of, inverse, known_tags)
    np.minimum.at(lowest, inverse[known_tags > 0], known_tags[known_tags > 0])
    at_node = tag_of > 0
    require(np.array_equal(tag_of[at_node], lowest[at_node]),
            f"{source}: two nodes stand for one point of an edge or face (the mesh is not conforming)")
    new = np.flatnonzero(tag_of == 0)
    tag_of[new] = len(position) + np.arange(len(new))  # above every existing tag
    offset = 0
    for batch in batches:
        if batch.etype != POINT:
            size = batch.nodes.shape[0] * len(split_of(batch.etype).points)
            batch.points = tag_of[inverse[offset : offset + size]].reshape(len(batch.nodes), -1)
            offset += size
    return tag_of[new], coords_all[first[new]]


# --------------------------------------------------------------------------- the .msh file


def read_batches(gmsh, source: Path) -> tuple[list[Batch], dict]:
    """Every element of every entity in a physical group, and the groups
    ((dim, tag) -> (name, entities))."""
    groups = {}
    for dim, tag in gmsh.model.getPhysicalGroups():
        groups[(dim, tag)] = (gmsh.model.getPhysicalName(dim, tag), list(gmsh.model.getEntitiesForPhysicalGroup(dim, tag)))
    require(groups, f"{source}: the mesh has no physical groups")
    entities = sorted({(dim, e) for (dim, _), (_, members) in groups.items() for e in members})
    batches = []
    for dim, entity in entities:
        types, _, nodes = gmsh.model.mesh.getElements(dim, entity)
        for etype, enodes in zip(types, nodes):
            name, _, _, count = gmsh.model.mesh.getElementProperties(etype)[:4]
            require(etype in SIMPLICES, f"{source}: elements of type {name!r} (entity {dim}:{entity}); refine "
                                        "splits points, lines, triangles and tetrahedra of order 1 or 2")
            batches.append(Batch(dim, entity, int(etype), np.asarray(enodes, np.int64).reshape(-1, count)))
    orders = {split_of(b.etype).order for b in batches if b.etype != POINT}
    require(len(orders) == 1, f"{source}: elements of orders {sorted(orders)} mixed; refine needs one geometry order")
    return batches, groups


def refine_msh(source: Path, target: Path) -> dict:
    """Write ``target``: the mesh ``source`` split once (gmsh on this rank); returns counts."""
    gmsh = open_msh(source)
    batches, groups = read_batches(gmsh, source)
    position = node_positions(gmsh)
    new_tags, new_coords = refine_batches(batches, position, source)
    elements = [(b, *b.children()) for b in batches]
    used = np.unique(np.concatenate([b.nodes.ravel() for b in batches]))
    tdim = max(b.dim for b in batches)
    fresh_gmsh_model(target.stem)
    for dim, entity in sorted({(b.dim, b.entity) for b in batches}):
        gmsh.model.addDiscreteEntity(dim, entity)
    home = min(b.entity for b in batches if b.dim == tdim)  # every node on one entity of a group
    gmsh.model.mesh.addNodes(tdim, home, np.r_[used, new_tags], np.r_[position[used], new_coords].ravel())
    for batch, ctype, children in elements:
        gmsh.model.mesh.addElementsByType(batch.entity, ctype, [], children.ravel())
    for (dim, tag), (name, members) in groups.items():
        gmsh.model.addPhysicalGroup(dim, members, tag, name)
    try:
        save(gmsh, target)
    except Exception as err:  # gmsh raises a bare Exception with its last error
        raise UserError(f"{target}: cannot write it ({err})") from None
    finally:
        gmsh.clear()
    cells = [len(b.nodes) for b in batches if b.dim == tdim]
    return {"cells": sum(cells), "refined_cells": sum(len(c) for b, _, c in elements if b.dim == tdim),
            "nodes": len(used), "refined_nodes": len(used) + len(new_tags)}


# --------------------------------------------------------------------------- the scene


def refine_scene(problem_path, out_dir, comm=MPI.COMM_WORLD) -> Path:
    """Write ``out_dir/<mesh name>.msh`` (the scene's mesh split once) and
    ``out_dir/problem.toml`` (the problem with ``mesh`` pointing at it); returns the
    new problem file. Every other file the problem names (target surfaces, landmarks,
    bases) is rewritten relative to ``out_dir``, so it still resolves. Bases trained on
    the coarse loaded nodes do not fit the refined ones: move them with ``transfer_bases``.

    gmsh runs on rank 0; under MPI every rank gets the path (or the same error).
    """
    problem_path, out_dir = Path(problem_path), Path(out_dir)

    def work():
        start = time.perf_counter()
        raw = read_toml(problem_path)
        config, _ = validate_problem(raw, str(problem_path), None)
        source = problem_path.parent / config["mesh"]
        target, path = out_dir / Path(config["mesh"]).name, out_dir / "problem.toml"
        for new, old in ((target, source), (path, problem_path)):
            require(os.path.abspath(new) != os.path.abspath(old), f"{out_dir}: the refined scene would overwrite {old}; "
                                                                  "choose another folder")
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise UserError(f"{out_dir}: cannot create it ({err.strerror})") from None
        counts = refine_msh(source, target)
        text = toml_text(refined_problem(raw, problem_path.parent, out_dir, target.name))
        try:
            path.write_text(f"# {problem_path} with its mesh refined once (fenics_elasto.refine)\n" + text)
        except OSError as err:
            raise UserError(f"{path}: cannot write it ({err.strerror})") from None
        log.info(f"refined {source.name}: {counts['cells']} -> {counts['refined_cells']} cells, "
                 f"{counts['nodes']} -> {counts['refined_nodes']} nodes ({time.perf_counter() - start:.1f} s) -> {target}")
        return path

    return on_root(comm, work)


def refined_problem(raw: dict, source_dir: Path, out_dir: Path, mesh_name: str) -> dict:
    """The problem's raw TOML with ``mesh`` = ``mesh_name`` and every other file path
    relative to ``out_dir`` (absolute ones stay as they are)."""
    raw = copy.deepcopy(raw)
    raw["mesh"] = mesh_name

    def moved(name: str) -> str:
        path = Path(name)
        return name if path.is_absolute() else os.path.relpath(source_dir / path, out_dir)

    return {key: value if key == "mesh" else map_files((key,), value, moved) for key, value in raw.items()}


# --------------------------------------------------------------------------- fields on the refined scene


def prolongation(coarse, fine, groups, exclude_groups=()) -> scipy.sparse.csr_matrix:
    """P (fine nodes x coarse nodes): per-node rows of a field of the coarse scene's space
    on the nodes of ``groups`` (minus those of ``exclude_groups``, where the field is
    zero, e.g. clamped), in canonical order (elasticity.NodeSet), to the same groups'
    nodes of ``fine`` -- the scene ``refine_scene`` made of it. Exact for every field of
    the coarse space (P1 or P2, the scenes' degree): each fine node gets the coarse
    facet's Lagrange interpolant at its lattice point. Scenes or problem paths."""
    require(len(groups) > 0, "prolongation: name at least one facet group")
    coarse = _scene(coarse)
    fine = _scene(fine, coarse.comm)
    require(coarse.degree == fine.degree, f"{fine.path}: degree {fine.degree}, but {coarse.path} has {coarse.degree}")
    nodes = [DofLayout(s).node_set(groups, exclude_groups) for s in (coarse, fine)]
    coarse_coords, fine_coords = (n.gather(n.coords) for n in nodes)
    msh = coarse.mesh_file
    coarse_points, fine_points, weights = on_root(coarse.comm, lambda: facet_lattices(msh, groups, coarse.degree))
    gdim = coarse.gdim
    scale = max(np.ptp(coarse_coords, axis=0).max(initial=0.0), 1e-300)
    gap, column = cKDTree(coarse_coords).query(coarse_points.reshape(-1, 3)[:, :gdim])
    column[gap > 1e-9 * scale] = -1  # an excluded node: the field is zero there
    require(np.isin(np.arange(len(coarse_coords)), column).all(),
            f"{msh}: the nodes of {', '.join(groups)} are not those of the scene {coarse.path}")
    gap, hit = cKDTree(fine_points.reshape(-1, 3)[:, :gdim]).query(fine_coords)
    require(len(fine_coords) == 0 or gap.max() <= 1e-9 * scale,
            f"{fine.path}: its nodes of {', '.join(groups)} are not on {msh}'s facets: it is not that scene refined")
    facet, point = np.divmod(hit, weights.shape[0])
    columns, values = column.reshape(len(coarse_points), -1)[facet], weights[point]
    rows = np.broadcast_to(np.arange(len(fine_coords))[:, None], columns.shape)
    keep = (columns >= 0) & (np.abs(values) > 1e-12)  # the coarse basis vanishes at the other lattice points
    return scipy.sparse.csr_matrix((values[keep], (rows[keep], columns[keep])), shape=(len(fine_coords), len(coarse_coords)))


def facet_lattices(msh: Path, groups, degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every facet of ``groups`` in ``msh``: its nodes of the degree-k space
    (facets, k-nodes, 3), its lattice points of order 2k -- the nodes of the degree-k
    space of its children -- (facets, L, 3), and the degree-k Lagrange basis at those
    lattice points (L, k-nodes), all by the facet's own (curved or straight) map."""
    gmsh = open_msh(msh)
    tdim = max(dim for dim, _ in gmsh.model.getPhysicalGroups())
    rows = physical_facets(gmsh, tdim)
    missing = [g for g in groups if g not in rows]
    require(not missing, f"{msh}: no facet group(s) {', '.join(missing)}")
    facets = distinct_facets(np.concatenate([rows[g] for g in groups]) + 1)  # overlapping groups: once each
    position = node_positions(gmsh)
    fdim = tdim - 1
    geometry = gmsh.model.mesh.getElementType(FAMILY[fdim], 1 if facets.shape[1] == fdim + 1 else 2)
    space = gmsh.model.mesh.getElementType(FAMILY[fdim], degree)
    nodes = node_multi_indices(gmsh, space) / float(degree)
    points = lattice(fdim, 2 * degree) / (2.0 * degree)
    coords = position[facets]
    coarse = np.einsum("kn,fnd->fkd", basis_at(gmsh, geometry, nodes), coords)
    fine = np.einsum("ln,fnd->fld", basis_at(gmsh, geometry, points), coords)
    weights = basis_at(gmsh, space, points)
    gmsh.clear()
    return coarse, fine, weights


def distinct_facets(rows: np.ndarray) -> np.ndarray:
    """Facets (rows of node tags) each once: rows of the same nodes in any order are one."""
    first, _ = unique_rows(np.sort(rows, axis=1))
    return rows[np.sort(first)]


def transfer_bases(W: np.ndarray, coarse, fine) -> np.ndarray:
    """Reduced bases W (loaded nodes x gdim, r) of the scene ``coarse`` on the loaded
    nodes of ``fine`` (its refinement), orthonormal again. Each column is the coarse
    boundary field it stands for, interpolated (``prolongation``); then QR, signs kept,
    so that the first j columns span what the first j spanned (a rank truncates alike).
    Scenes or problem paths."""
    coarse = _scene(coarse)
    fine = _scene(fine, coarse.comm)
    require(coarse.loaded == fine.loaded and coarse.fixed == fine.fixed,
            f"{fine.path}: its loaded/fixed groups differ from {coarse.path}'s")
    P = prolongation(coarse, fine, coarse.loaded, coarse.fixed)
    gdim, (n_fine, n_coarse), r = coarse.gdim, P.shape, W.shape[1]
    require(W.shape[0] == n_coarse * gdim, f"bases of {W.shape[0]} rows do not fit {coarse.path}'s "
                                             f"{n_coarse} loaded nodes x {gdim}")
    moved = (P @ W.reshape(n_coarse, gdim * r)).reshape(n_fine * gdim, r)
    Q, R = np.linalg.qr(moved)
    diagonal = np.diag(R)
    require(np.abs(diagonal).min() > 1e-10 * np.abs(diagonal).max(), "the bases lost a direction on the refined nodes")
    return Q * np.sign(diagonal)


def _scene(scene_or_path, comm=MPI.COMM_WORLD) -> Scene:
    return scene_or_path if isinstance(scene_or_path, Scene) else load_scene(scene_or_path, comm=comm)
