"""Output: result.json, the displacement for ParaView, surfaces as .vtp.

Meshes and displacements are gathered to rank 0 (owned entities only, so nothing is
written twice) and written there.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from mpi4py import MPI

import dolfinx
from dolfinx import fem


def vertex_blocks(V: fem.FunctionSpace) -> np.ndarray:
    """Map geometry node -> block (node) of V at the same vertex.

    For Lagrange spaces the first DOFs of each cell sit on its vertices, in the same
    local order as the (affine) geometry's nodes.
    """
    mesh = V.mesh
    geom = mesh.geometry.dofmaps[0]
    nverts = geom.shape[1]
    out = np.full(mesh.geometry.x.shape[0], -1, np.int64)
    out[geom.ravel()] = V.dofmap.list[:, :nverts].ravel()
    return out


def gather_entities(u: fem.Function, dim: int, entities: np.ndarray):
    """(points, connectivity, displacement) of owned entities, gathered on rank 0.

    Points are duplicated per entity; ``pyvista``'s ``clean`` merges them.
    """
    mesh = u.function_space.mesh
    gdim = mesh.geometry.dim
    mesh.topology.create_connectivity(dim, mesh.topology.dim)
    owned = entities[entities < mesh.topology.index_map(dim).size_local]
    nodes = dolfinx.mesh.entities_to_geometry(mesh, dim, owned.astype(np.int32))
    width = nodes.shape[1] if nodes.ndim == 2 else dim + 1
    nodes = nodes.reshape(-1, width)
    points = mesh.geometry.x[nodes.ravel()]
    disp = u.x.array.reshape(-1, gdim)[vertex_blocks(u.function_space)[nodes.ravel()]]
    points = mesh.comm.gather(points, root=0)
    disp = mesh.comm.gather(disp, root=0)
    if mesh.comm.rank != 0:
        return None
    points, disp = np.concatenate(points), np.concatenate(disp)
    cells = np.arange(len(points)).reshape(-1, width)
    pad = np.zeros((len(disp), 3))
    pad[:, :gdim] = disp
    return points, cells, pad


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


def surface(u: fem.Function, facets: np.ndarray, deformed: bool = True):
    """The (deformed) surface of the given facets, on rank 0 (None elsewhere)."""
    mesh = u.function_space.mesh
    data = gather_entities(u, mesh.topology.dim - 1, facets)
    return None if data is None else polydata(*data, deformed=deformed)


def write_displacement(u: fem.Function, out: Path) -> Path:
    """The displacement field for ParaView (VTX / ADIOS2 .bp)."""
    path = out / "displacement.bp"
    with dolfinx.io.VTXWriter(u.function_space.mesh.comm, path, [u], engine="BP4") as writer:
        writer.write(0.0)
    return path


def write_point_csv(path: Path, points: np.ndarray, vectors: np.ndarray, prefix: str) -> None:
    """Rows ``point, vector``; header x0.. then <prefix>0.. (landmarks: X, forces: f)."""
    dim = points.shape[1]
    header = ",".join([f"x{i}" for i in range(dim)] + [f"{prefix}{i}" for i in range(vectors.shape[1])])
    np.savetxt(path, np.c_[points, vectors], delimiter=",", header=header, comments="")


def write_landmarks(path: Path, points: np.ndarray, displaced: np.ndarray) -> None:
    """CSV of ``source point, target point`` rows (the [target] landmarks format)."""
    write_point_csv(path, points, displaced, "X")


def write_json(data: dict, path: Path, comm=MPI.COMM_WORLD) -> None:
    if comm.rank == 0:
        path.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(type(value))


def write_matched_surfaces(out: Path, scene, u: fem.Function) -> None:
    """``surface_<group>.vtp`` per matched group and ``surface.vtp`` with all (deformed).

    These are ready-made targets for ``estimate``.
    """
    out = Path(out)
    matched = [surface(u, scene.facet_groups[g]) for g in scene.matched]
    if scene.comm.rank == 0:
        import pyvista as pv

        out.mkdir(parents=True, exist_ok=True)
        for g, mesh in zip(scene.matched, matched):
            mesh.save(out / f"surface_{g}.vtp")
        if matched:
            pv.merge(matched).clean(tolerance=0.0).save(out / "surface.vtp")


def write_solution(out: Path, scene, u: fem.Function, result: dict, target=None, title: str = "") -> dict:
    """Everything a solve leaves behind: result.json, displacement.bp, surfaces, screenshot.png.

    ``surface.vtp`` holds the deformed matched groups together (usable as a target);
    ``surface_<group>.vtp`` each one alone.
    """
    from fenics_elasto.render import render

    out = Path(out)
    if scene.comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    scene.comm.barrier()
    write_displacement(u, out)
    tdim = scene.mesh.topology.dim
    shown = list(dict.fromkeys(scene.matched + scene.loaded + list(scene.displacement) + scene.fixed))
    deformed = {g: surface(u, scene.facet_groups[g]) for g in shown}
    reference = {g: surface(u, scene.facet_groups[g], deformed=False) for g in shown}
    if tdim == 2:
        context = gather_entities(u, tdim, np.arange(scene.mesh.topology.index_map(tdim).size_local, dtype=np.int32))
    else:
        scene.mesh.topology.create_connectivity(tdim - 1, tdim)
        context = gather_entities(u, tdim - 1, dolfinx.mesh.exterior_facet_indices(scene.mesh.topology))
    write_matched_surfaces(out, scene, u)
    if scene.comm.rank == 0:
        render(out / "screenshot.png", deformed, reference, polydata(*context), target, title, dim=scene.gdim)
    write_json(result, out / "result.json", scene.comm)
    return result
