"""The atlas (multi-source training, paper §3.3.3): patients that share loaded nodes.

An atlas is a set of loaded-surface triangulations (group -> (points, triangles)), e.g.
``atlas_surfaces`` of one patient's mesh. Every patient's mesh is built around it
(``build_prostate_phantom(atlas=...)``): the atlas triangles are surface-matched onto
that patient's organs (``fit_surfaces``), put onto the exact organ geometry, and gmsh
meshes the volume around them (``mesh_inside``). So all patients have the same loaded
nodes -- the vertices and (P2) edge midpoints of the atlas triangles -- and a field in
atlas numbering (``atlas_nodes``, ``atlas_order``, ``to_atlas``/``from_atlas``) means
the same thing on each of them: bases move between patients by a permutation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.util.errors import require
from fenics_elasto.mesh.gmsh_models import generate, node_positions, read_surfaces, save, untangle
from fenics_elasto.geometry.matching import match_surface
from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.geometry.surface import Surface
from fenics_elasto.geometry.meshes import quadratic_edges, triangle_edges

PHANTOM_LOADED = ("bladder", "rectum")  # the phantom's loaded groups: its default atlas


def atlas_surfaces(msh: Path, groups=PHANTOM_LOADED) -> dict:
    """An atlas for ``build_prostate_phantom(atlas=...)``: a mesh's loaded surfaces."""
    surfaces = read_surfaces(msh)
    missing = [g for g in groups if g not in surfaces]
    require(not missing, f"{msh}: no facet group(s) {', '.join(missing)} to serve as the atlas")
    return {g: surfaces[g] for g in groups}


def fit_surfaces(template: dict, onto: dict) -> dict:
    """Each template triangulation (group -> (points, triangles: 3 or 6 nodes)) with its
    vertices surface-matched onto the same group of ``onto``; the triangles are kept
    and the midpoint nodes of 6-node triangles go to the middle of their moved edges."""
    names = list(template)
    vertices = {g: np.unique(template[g][1][:, :3]) for g in names}
    points = np.concatenate([template[g][0][vertices[g]] for g in names])
    groups = np.repeat(np.arange(len(names)), [len(vertices[g]) for g in names])
    target = SurfaceTerm([Surface(onto[g][0], onto[g][1][:, :3]) for g in names], groups)
    moved = points + match_surface(points, groups, target)
    fitted = {}
    for i, g in enumerate(names):
        positions, triangles = template[g][0].copy(), template[g][1]
        positions[vertices[g]] = moved[groups == i]
        if triangles.shape[1] == 6:
            pairs, middle = quadratic_edges(triangles)
            positions[middle] = positions[pairs].mean(axis=1)
        fitted[g] = (positions, triangles)
    return fitted
def onto_geometry(gmsh, faces: list[int], points: np.ndarray) -> np.ndarray:
    """Each point moved to the closest point of the CAD faces (not of their mesh, whose
    facets cut inside curved organs: a node there would be a fake displacement)."""
    candidates = np.stack([np.reshape(gmsh.model.getClosestPoint(2, f, points.ravel())[0], (-1, 3)) for f in faces])
    nearest = np.argmin(np.linalg.norm(candidates - points, axis=2), axis=0)
    return candidates[nearest, np.arange(len(points))]


def mesh_inside(gmsh, surfaces: dict, volumes: dict, path: Path) -> None:
    """Tetrahedralise the volumes bounded by given triangulated surfaces, keeping those
    triangles -- vertices, and the midpoint nodes of 6-node triangles -- exactly: a
    new model of discrete surfaces, meshed inside, then made quadratic.

    ``volumes``: name -> the surface groups bounding it (outer and inner shells).
    The vertices get consecutive node tags in the order of each group's points.
    """
    gmsh.model.add("around-surfaces")
    first, corners, edge_keys, edge_points = 1, [], [], []
    for tag, (name, (points, triangles)) in enumerate(surfaces.items(), 1):
        vertices = np.unique(triangles[:, :3])
        node_tag = np.zeros(len(points), np.int64)
        node_tag[vertices] = np.arange(first, first + len(vertices))
        gmsh.model.addDiscreteEntity(2, tag)
        gmsh.model.mesh.addNodes(2, tag, node_tag[vertices], points[vertices].ravel())
        gmsh.model.mesh.addElementsByType(tag, 2, [], node_tag[triangles[:, :3]].ravel())
        gmsh.model.addPhysicalGroup(2, [tag], name=name)
        corners.append(points[vertices])
        if triangles.shape[1] == 6:
            pairs, middle = quadratic_edges(triangles)
            edge_keys.append(_edge_key(node_tag[pairs] - 1))
            edge_points.append(points[middle])
        first += len(vertices)
    tag_of = {name: tag for tag, name in enumerate(surfaces, 1)}
    volume = {name: gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop([tag_of[s] for s in shells])])
              for name, shells in volumes.items()}
    gmsh.model.geo.synchronize()
    for name, tag in volume.items():
        gmsh.model.addPhysicalGroup(3, [tag], name=name)
    # The surfaces carry the sizes; the volume grades between them.
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
    gmsh.option.setNumber("Mesh.ElementOrder", 1)
    generate(gmsh, path, 3)
    if edge_keys:
        _curve_surfaces(gmsh, np.concatenate(corners), np.concatenate(edge_keys), np.concatenate(edge_points))
        untangle(gmsh)  # curved walls fold a few thin cells over (15-36 per phantom patient at h = 1.6)
    save(gmsh, path)


def _edge_key(pairs: np.ndarray) -> np.ndarray:
    """One integer per edge of (sorted) node-tag pairs."""
    return pairs[:, 0] * (1 << 31) + pairs[:, 1]


def _curve_surfaces(gmsh, corners: np.ndarray, keys: np.ndarray, midpoints: np.ndarray) -> None:
    """Quadratic elements whose surface edges (``keys`` of pairs of rows of ``corners``)
    have the given midpoint nodes. setOrder renumbers nodes, so corners are found by
    position."""
    gmsh.option.setNumber("Mesh.SecondOrderLinear", 1)  # straight first; the surface ones are moved below
    gmsh.model.mesh.setOrder(2)
    keys, first = np.unique(keys, return_index=True)
    midpoints = midpoints[first]
    position = node_positions(gmsh)
    tree = cKDTree(corners)
    for _, tag in gmsh.model.getEntities(2):
        nodes = gmsh.model.mesh.getElementsByType(9, tag)[1].reshape(-1, 6).astype(np.int64)
        gap, corner = tree.query(position[nodes[:, :3]])
        pairs, middle = quadratic_edges(np.c_[corner, nodes[:, 3:]])
        at = np.searchsorted(keys, _edge_key(pairs))
        found = (keys[np.minimum(at, len(keys) - 1)] == _edge_key(pairs)) & np.repeat(gap.max(axis=1) < 1e-9, 3)
        for node, point in zip(middle[found], midpoints[at[found]]):
            gmsh.model.mesh.setNode(int(node), point, [])


def atlas_nodes(surfaces: dict, degree: int) -> np.ndarray:
    """The loaded nodes in atlas numbering: per group, its vertices (in the order of
    its points), then (degree 2) its edges' midpoint nodes, edges in sorted order.

    Surfaces of 3-node triangles (flat meshes) have straight midpoints.
    """
    require(degree in (1, 2), f"atlas numbering is defined for degree 1 or 2, not {degree}")
    parts = []
    for points, triangles in surfaces.values():
        parts.append(points[np.unique(triangles[:, :3])])
        if degree == 2:
            pairs = triangle_edges(triangles)
            midpoints = points[quadratic_edges(triangles)[1]] if triangles.shape[1] == 6 else points[pairs].mean(axis=1)
            _, first = np.unique(pairs, axis=0, return_index=True)
            parts.append(midpoints[first])
    return np.concatenate(parts)


def atlas_order(problem, atlas: dict) -> np.ndarray:
    """Each atlas node's index among the problem's loaded nodes.

    The patient's mesh must have been built around ``atlas``: its loaded surfaces
    have the atlas's triangles, and its loaded nodes are exactly the atlas nodes.
    """
    scene = problem.scene
    msh = scene.mesh_file
    own = scene.comm.bcast(read_surfaces(msh) if scene.comm.rank == 0 else None, root=0)
    built_around = all(g in atlas and g in own and np.array_equal(_topology(own[g]), _topology(atlas[g]))
                       for g in scene.loaded)
    require(built_around, f"{msh}: its loaded surfaces ({', '.join(scene.loaded)}) were not built around "
                          "this atlas; mesh the patient with the atlas")
    nodes = atlas_nodes({g: own[g] for g in scene.loaded}, scene.degree)
    coords = problem.loaded.gather(problem.loaded.coords)
    gap, order = cKDTree(coords).query(nodes)
    tol = 1e-9 * np.ptp(coords, axis=0).max()
    require(len(nodes) == len(coords) and gap.max() <= tol and len(np.unique(order)) == len(order),
            f"{msh}: its loaded nodes are not the atlas nodes ({len(coords)} vs {len(nodes)}, worst gap {gap.max():.2g})")
    return order


def _topology(surface) -> np.ndarray:
    """A triangulation's triangles as sorted vertex triples (vertices numbered in
    point order), in sorted order: equal for equal triangulations."""
    corners = surface[1][:, :3]
    rank = np.searchsorted(np.unique(corners), corners)
    return np.unique(np.sort(rank, axis=1), axis=0)


def to_atlas(field: np.ndarray, order: np.ndarray) -> np.ndarray:
    """A per-node field (rows node*gdim + component, optionally with columns) in atlas numbering."""
    return field.reshape(len(order), -1, *field.shape[1:])[order].reshape(field.shape)


def from_atlas(field: np.ndarray, order: np.ndarray) -> np.ndarray:
    """An atlas-numbered per-node field on the patient's own loaded nodes."""
    out = np.empty_like(field)
    out.reshape(len(order), -1, *field.shape[1:])[order] = field.reshape(len(order), -1, *field.shape[1:])
    return out
