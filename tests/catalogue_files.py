"""Bad and edge input files for tests/test_catalogue.py: meshes that gmsh reads but
DOLFINx must not get, corrupt surfaces, landmarks and bases. Each maker writes one
file into a folder and returns its path.

The 3D meshes are a unit cube cut into six tetrahedra along its diagonal (every one
holds corners 0 and 7, corner i at (i & 1, i >> 1 & 1, i >> 2 & 1)); each bad variant
changes one thing about it.
"""

from __future__ import annotations

from itertools import permutations
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401  (imports dolfinx_solver first)
from fenics_elasto.mesh.gmsh_models import fresh_gmsh_model

CORNERS = np.array([[i & 1, i >> 1 & 1, i >> 2 & 1] for i in range(8)], float)
TETS = np.array([[0, a, a | b, 7] for a, b, _ in permutations((1, 2, 4))])


def cube_faces() -> dict[str, np.ndarray]:
    """The cube's boundary triangles by side: bottom (z = 0), top (z = 1), sides."""
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    facets = np.sort(TETS[:, local].reshape(-1, 3), axis=1)
    keys, counts = np.unique(facets, axis=0, return_counts=True)
    boundary = keys[counts == 1]
    z = CORNERS[boundary][:, :, 2]
    return {"bottom": boundary[(z == 0).all(axis=1)], "top": boundary[(z == 1).all(axis=1)],
            "sides": boundary[~(z == 0).all(axis=1) & ~(z == 1).all(axis=1)]}


def write_msh(path: Path, points: np.ndarray, cells: dict, facets: dict, dim: int = 3) -> Path:
    """A gmsh 4.1 file of discrete entities: ``cells`` / ``facets``: group -> (gmsh element
    type, 0-based node rows), one physical group each (empty rows: a group without elements)."""
    gmsh = fresh_gmsh_model(path.stem)
    gmsh.model.addDiscreteEntity(dim, 1)
    gmsh.model.mesh.addNodes(dim, 1, np.arange(1, len(points) + 1), np.asarray(points, float).ravel())
    tag = 1
    for d, groups in ((dim, cells), (dim - 1, facets)):
        for name, (etype, rows) in groups.items():
            if d != dim or tag > 1:
                gmsh.model.addDiscreteEntity(d, tag)
            if len(rows):
                gmsh.model.mesh.addElementsByType(tag, etype, [], (np.asarray(rows) + 1).ravel())
            gmsh.model.addPhysicalGroup(d, [tag], name=name)
            tag += 1
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    gmsh.write(str(path))
    gmsh.clear()
    return path


CUBE_TOML = """\
mesh = "{mesh}"
[materials.body]
E = 10.0
nu = 0.3
{extra}
[boundary]
fixed = ["bottom"]
[boundary.displacement.top]
value = [0.0, 0.0, 0.1]
"""


def cube(folder: Path, name: str, points=CORNERS, cells=None, facets=None, other=None) -> Path:
    """The cube mesh (or a variant) and its problem.toml; ``other``: a second cell group
    "other" (gmsh type, rows). Returns the problem.toml."""
    cells = {"body": (4, TETS)} if cells is None else cells
    if other is not None:
        cells = {**cells, "other": other}
    faces = cube_faces()
    facets = {g: (2, faces[g]) for g in ("bottom", "top", "sides")} if facets is None else facets
    write_msh(folder / f"{name}.msh", points, cells, facets)
    extra = "[materials.other]\nE = 10.0\nnu = 0.3\n" if "other" in cells else ""
    problem = folder / f"{name}.toml"
    problem.write_text(CUBE_TOML.format(mesh=f"{name}.msh", extra=extra))
    return problem


TET10_EDGES = [(0, 1), (1, 2), (2, 0), (3, 0), (3, 2), (3, 1)]  # gmsh's order of a 10-node tet's edge nodes
TRIANGLE6_EDGES = [(0, 1), (1, 2), (2, 0)]


def quadratic_cube(folder: Path, name: str, diagonal_midpoint=(0.5, 0.5, 0.5)) -> Path:
    """The cube with 10-node tets and 6-node facets, straight-sided but for the midpoint
    node of the diagonal 0-7 that every tet holds, placed at ``diagonal_midpoint``."""
    faces = cube_faces()
    edges = np.unique(np.sort(np.vstack([TETS[:, pair] for pair in TET10_EDGES]), axis=1), axis=0)
    points = np.vstack([CORNERS, CORNERS[edges].mean(axis=1)])
    points[len(CORNERS) + np.flatnonzero((edges == [0, 7]).all(axis=1))[0]] = diagonal_midpoint
    node = {tuple(e): len(CORNERS) + i for i, e in enumerate(edges)}

    def rows(corners, pairs):
        return np.array([[*c, *(node[tuple(sorted((c[a], c[b])))] for a, b in pairs)] for c in corners])

    write_msh(folder / f"{name}.msh", points, {"body": (11, rows(TETS, TET10_EDGES))},
              {g: (9, rows(faces[g], TRIANGLE6_EDGES)) for g in ("bottom", "top", "sides")})
    problem = folder / f"{name}.toml"
    problem.write_text(CUBE_TOML.format(mesh=f"{name}.msh", extra=""))
    return problem


def bad_cubes(folder: Path) -> dict[str, Path]:
    """Problem files of cube variants, each bad in one way (``good``: the control)."""
    faces = cube_faces()
    inside = np.vstack([CORNERS, [[0.6, 0.3, 0.5], [0.3, 0.2, 0.4], [2.0, 2.0, 2.0]]])
    shifted = np.vstack([CORNERS, CORNERS + [1.0, 0.0, 0.0]])
    hexahedron = np.array([[8, 9, 11, 10, 12, 13, 15, 14]])
    groups = {g: (2, faces[g]) for g in ("bottom", "top", "sides")}
    return {
        "good": cube(folder, "good"),
        "no_cells": cube(folder, "no_cells", cells={"body": (4, np.zeros((0, 4), int))}),
        "mixed": cube(folder, "mixed", shifted, other=(5, hexahedron)),
        "hexahedra": cube(folder, "hexahedra", shifted, cells={"body": (5, hexahedron)},
                          facets={"bottom": (3, [[8, 9, 11, 10]]), "top": (3, [[12, 13, 15, 14]])}),
        "twice": cube(folder, "twice", other=(4, TETS[:1])),
        "flat": cube(folder, "flat", cells={"body": (4, np.vstack([TETS, [[0, 1, 3, 2]]]))}),
        "overlap": cube(folder, "overlap", inside, cells={"body": (4, np.vstack([TETS, [[0, 1, 3, 8]]]))}),
        "crowded": cube(folder, "crowded", inside,
                        cells={"body": (4, np.vstack([TETS, [[0, 1, 3, 8], [0, 1, 3, 9]]]))}),
        "orphan": cube(folder, "orphan", inside),
        "off_mesh": cube(folder, "off_mesh", facets={**groups, "sides": (2, np.vstack([faces["sides"], [[0, 5, 6]]]))}),
        "facet_quads": cube(folder, "facet_quads", facets={**groups, "top": (3, [[4, 5, 7, 6]])}),
        "quadratic": quadratic_cube(folder, "quadratic"),
        # the diagonal's midpoint pulled out through a face: two tets' Jacobians change sign inside
        "folded": quadratic_cube(folder, "folded", (1.4, 0.5, 0.5)),
    }


def surface_lines(folder: Path) -> Path:
    """A 2D polyline (a square) saved as a surface file."""
    import pyvista as pv

    points = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    path = folder / "lines.vtp"
    pv.PolyData(points, lines=np.array([5, 0, 1, 2, 3, 0])).save(path)
    return path


def triangles_3d(folder: Path) -> Path:
    """A closed 3D triangle surface (a sphere)."""
    import pyvista as pv

    path = folder / "sphere.vtp"
    pv.Sphere(radius=3.0, center=(4.0, 5.0, 2.0)).save(path)
    return path


def points_only(folder: Path) -> Path:
    import pyvista as pv

    path = folder / "points.vtp"
    pv.PolyData(np.random.default_rng(0).random((10, 3))).save(path)
    return path


def moved(source: Path, path: Path, offset=(0.0, 0.0, 0.0), scale: float = 1.0, nan: bool = False) -> Path:
    """A copy of a surface file translated and scaled (about the origin), or with one NaN point."""
    import pyvista as pv

    mesh = pv.read(source)
    points = np.asarray(mesh.points, float) * scale + np.asarray(offset)
    if nan:
        points[0, 0] = np.nan
    mesh.points = points
    mesh.save(path)
    return path


def truncated(source: Path, path: Path, fraction: float = 0.5) -> Path:
    data = source.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def garbage(path: Path, size: int = 4096) -> Path:
    path.write_bytes(np.random.default_rng(1).integers(0, 256, size, dtype=np.uint8).tobytes())
    return path


def text(path: Path, content: str) -> Path:
    path.write_text(content)
    return path


def bases(path: Path, W, loaded_coords, **extra) -> Path:
    np.savez(path, W=W, variance=np.full(np.shape(W)[1] if np.ndim(W) == 2 else 1, 0.5),
             loaded_coords=loaded_coords, examples=2, **extra)
    return path
