"""Output: result.json, the displacement for ParaView, surfaces as .vtp.

Meshes and displacements are gathered to rank 0 (owned entities only, so nothing is
written twice) and written there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import dolfinx
from dolfinx import fem


def node_blocks(V: fem.FunctionSpace) -> np.ndarray:
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


def _pieces(dim: int, level: int) -> np.ndarray:
    """Quadratic Lagrange shape functions (rows) at the corners of the ``level``-fold
    subdivision of a line (nodes v0, v1, m) or triangle (v0, v1, v2, e01, e12, e20)."""
    if dim == 1:
        t = np.arange(level + 1) / level
        lam = np.stack([np.c_[1 - t[:-1], t[:-1]], np.c_[1 - t[1:], t[1:]]], axis=1).reshape(-1, 2)
        l0, l1 = lam.T
        return np.c_[l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), 4 * l0 * l1]
    corners = []
    for i in range(level):
        for j in range(level - i):
            corners += [(i, j), (i + 1, j), (i, j + 1)]
            if i + j < level - 1:
                corners += [(i + 1, j), (i + 1, j + 1), (i, j + 1)]
    l1, l2 = np.array(corners, float).T / level
    l0 = 1 - l1 - l2
    return np.c_[l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), 4 * l0 * l1, 4 * l1 * l2, 4 * l2 * l0]


def gather_entities(u: fem.Function, dim: int, entities: np.ndarray, level: int = 4):
    """(points, connectivity, displacement) of owned entities, gathered on rank 0.

    Cells come as their vertices. Quadratic facets of a curved (P2-geometry) mesh
    with a P2 displacement come as ``level``^(dim) flat pieces of the curved deformed
    facet: a flat facet would cut inside a curved organ by its sag (~0.02 cm on the
    phantom), a fake displacement to a surface target. Points are duplicated per
    piece; ``pyvista``'s ``clean`` merges them.
    """
    mesh = u.function_space.mesh
    gdim = mesh.geometry.dim
    mesh.topology.create_connectivity(dim, mesh.topology.dim)
    owned = entities[entities < mesh.topology.index_map(dim).size_local]
    width = dim + 1
    nodes = dolfinx.mesh.entities_to_geometry(mesh, dim, owned.astype(np.int32))
    nodes = nodes.reshape(len(owned), -1) if len(owned) else np.zeros((0, width), np.int32)
    blocks = node_blocks(u.function_space)
    x, values = mesh.geometry.x[:, :gdim], u.x.array.reshape(-1, gdim)
    if dim < mesh.topology.dim and nodes.shape[1] > width and (blocks[nodes] >= 0).all():
        nodes = _quadratic_order(nodes, x) if dim == 2 else nodes
        shape = _pieces(dim, level)
        points = np.einsum("ak,nkd->nad", shape, x[nodes]).reshape(-1, gdim)
        disp = np.einsum("ak,nkd->nad", shape, values[blocks[nodes]]).reshape(-1, gdim)
    else:  # cells, flat facets, or nodes that V has no DOF on: the corners
        nodes = nodes[:, :width].ravel()
        points, disp = x[nodes], values[blocks[nodes]]
    points = mesh.comm.gather(points, root=0)
    disp = mesh.comm.gather(disp, root=0)
    if mesh.comm.rank != 0:
        return None
    points, disp = np.concatenate(points), np.concatenate(disp)
    cells = np.arange(len(points)).reshape(-1, width)
    pad = np.zeros((len(disp), 3))
    pad[:, :gdim] = disp
    xyz = np.zeros((len(points), 3))
    xyz[:, :gdim] = points
    return xyz, cells, pad


def polydata(points, cells, displacement, deformed: bool = True):
    """A pyvista mesh of lines (2D facets), triangles (3D facets, 2D cells) or tetrahedra, with |u|."""
    import pyvista as pv

    width = cells.shape[1]
    conn = np.hstack([np.full((len(cells), 1), width), cells]).ravel()
    xyz = points + (displacement if deformed else 0.0)
    if width == 4:
        grid = pv.UnstructuredGrid(conn, np.full(len(cells), pv.CellType.TETRA, np.uint8), xyz)
    else:
        grid = pv.PolyData(xyz, lines=conn) if width == 2 else pv.PolyData(xyz, faces=conn)
    grid.point_data["displacement"] = displacement
    grid.point_data["|u|"] = np.linalg.norm(displacement, axis=1)
    return grid.clean(tolerance=0.0) if width < 4 else grid.clean(tolerance=0.0, remove_unused_points=True)


def surface(u: fem.Function, facets: np.ndarray, deformed: bool = True, pieces: int = 4):
    """The (deformed) surface of the given facets, on rank 0 (None elsewhere); curved
    facets as ``pieces`` x ``pieces`` flat ones."""
    mesh = u.function_space.mesh
    data = gather_entities(u, mesh.topology.dim - 1, facets, pieces)
    return None if data is None else polydata(*data, deformed=deformed)


def write_displacement(u: fem.Function, path: Path) -> Path:
    """The displacement field for ParaView (VTX / ADIOS2 .bp, a folder) at ``path``."""
    with dolfinx.io.VTXWriter(u.function_space.mesh.comm, path, [u], engine="BP4") as writer:
        writer.write(0.0)
    return path


def point_csv(points: np.ndarray, vectors: np.ndarray, prefix: str) -> str:
    """CSV rows ``point, vector``; header x0.. then <prefix>0.. (landmarks: X, forces: f)."""
    import io

    dim = points.shape[1]
    header = ",".join([f"x{i}" for i in range(dim)] + [f"{prefix}{i}" for i in range(vectors.shape[1])])
    text = io.StringIO()
    np.savetxt(text, np.c_[points, vectors], delimiter=",", header=header, comments="")
    return text.getvalue()


def write_point_csv(path: Path, points: np.ndarray, vectors: np.ndarray, prefix: str) -> None:
    Path(path).write_text(point_csv(points, vectors, prefix))


def write_landmarks(path: Path, points: np.ndarray, displaced: np.ndarray) -> None:
    """CSV of ``source point, target point`` rows (the [target] landmarks format)."""
    write_point_csv(path, points, displaced, "X")


def write_matched_surfaces(out: Path, scene, u: fem.Function, pieces: int = 4, place=None) -> None:
    """``surface_<group>.vtp`` per matched group and ``surface.vtp`` with all (deformed).

    These are ready-made targets for ``estimate``. ``pieces``: a curved facet is
    written as pieces x pieces flat triangles; their sag is an error of the target
    (Table-1 case, target h = 1.3: E = 51.93 from 4 x 4 pieces, 51.66 from 8 x 8).
    ``place(name)``: where to write each file (a result folder's temporary names);
    default ``out / name``.
    """
    out = Path(out)
    place = place or (lambda name: out / name)
    matched = [surface(u, scene.facet_groups[g], pieces=pieces) for g in scene.matched]
    if scene.comm.rank == 0:
        import pyvista as pv

        out.mkdir(parents=True, exist_ok=True)
        for g, mesh in zip(scene.matched, matched):
            mesh.save(place(f"surface_{g}.vtp"))
        if matched:
            pv.merge(matched).clean(tolerance=0.0).save(place("surface.vtp"))


def write_solution(folder, scene, u: fem.Function, target=None, title: str = "") -> None:
    """Everything a solve leaves behind, into an ``outputs.OutputFolder`` (inside its
    ``writing()``): displacement.bp, surface.vtp and surface_<group>.vtp (deformed,
    usable as targets), screenshot.png. Collective."""
    from fenics_elasto.render import render

    write_displacement(u, folder.path_for("displacement.bp"))
    tdim = scene.mesh.topology.dim
    shown = list(dict.fromkeys(scene.matched + scene.loaded + list(scene.displacement) + scene.fixed))
    deformed = {g: surface(u, scene.facet_groups[g]) for g in shown}
    reference = {g: surface(u, scene.facet_groups[g], deformed=False) for g in shown}
    if tdim == 2:
        context = gather_entities(u, tdim, np.arange(scene.mesh.topology.index_map(tdim).size_local, dtype=np.int32))
    else:
        scene.mesh.topology.create_connectivity(tdim - 1, tdim)
        context = gather_entities(u, tdim - 1, dolfinx.mesh.exterior_facet_indices(scene.mesh.topology))
    write_matched_surfaces(folder.path, scene, u, place=folder.path_for)
    if scene.comm.rank == 0:
        render(folder.path_for("screenshot.png"), deformed, reference, polydata(*context), target, title,
               dim=scene.gdim, fixed=scene.fixed, units=scene.config.get("units") or "")
