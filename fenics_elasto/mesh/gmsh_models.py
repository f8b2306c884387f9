"""gmsh, quietly: fresh models with default options, meshing and saving with one-line
errors, and facet groups read back as node rows or triangulations.

gmsh does not always raise: with our options it logs an error and goes on (a truncated
file is "read", a surface mesh that overlaps itself leaves the volume empty). So its
log is read after every merge and meshing (``gmsh_errors``), a meshed dimension must
hold elements, and a mesh is checked (meshcheck.py) before it is saved or read.
"""

from __future__ import annotations

import re
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.interrupts import restore_handlers
from fenics_elasto.mesh.meshcheck import check_mesh, folds


def fresh_gmsh_model(name: str):
    """An empty gmsh model with default options (options are global: they would leak
    from one model to the next); gmsh stays quiet."""
    import gmsh

    if not gmsh.isInitialized():
        gmsh.initialize(interruptible=False)
        restore_handlers()  # gmsh resets SIGTERM and SIGHUP to their default: they would kill the run
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.clear()
    gmsh.option.restoreDefaults()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add(name)
    return gmsh


@contextmanager
def gmsh_errors():
    """Collect gmsh's logged errors (and a raised one) into the yielded list; the
    list is filled when the block ends."""
    import gmsh

    errors: list[str] = []
    gmsh.logger.start()
    try:
        yield errors
    except Exception as err:  # gmsh raises a bare Exception carrying its last error
        errors.append(str(err))
    finally:
        try:
            logged = gmsh.logger.get()
        except UnicodeDecodeError:  # gmsh quotes what it could not parse: bytes of a binary file
            logged = ["Error: unreadable bytes"]
        errors[:0] = [line.removeprefix("Error: ") for line in logged if line.startswith("Error")]
        gmsh.logger.stop()


def open_msh(path: Path, name: str | None = None):
    """A fresh gmsh model holding the mesh file ``path``; a missing file, one that is
    not a gmsh .msh, or one gmsh reports errors reading: one line naming it."""
    path = Path(path)
    require(path.is_file(), f"{path}: no such mesh file")
    with open(path, "rb") as f:
        require(f.read(11) == b"$MeshFormat", f"{path}: not a gmsh .msh file (it does not begin with $MeshFormat)")
    gmsh = fresh_gmsh_model(name or path.stem)
    with gmsh_errors() as errors:
        gmsh.merge(str(path))
    require(not errors, f"{path}: gmsh cannot read it ({errors[0] if errors else ''})")
    return gmsh


class GmshModel:
    """A fresh gmsh model with default options (they are global and would leak
    from one scene to the next), cleared again on exit."""

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        return fresh_gmsh_model(self.name)

    def __exit__(self, *exc):
        import gmsh

        gmsh.clear()


def physical_facets(gmsh, tdim: int) -> dict[str, np.ndarray]:
    """Every facet physical group's facets as rows of 0-based input node indices."""
    groups = {}
    for dim, tag in gmsh.model.getPhysicalGroups(tdim - 1):
        name = gmsh.model.getPhysicalName(dim, tag) or str(tag)
        rows = []
        for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
            types, _, nodes = gmsh.model.mesh.getElements(dim, entity)
            for etype, enodes in zip(types, nodes):
                n = gmsh.model.mesh.getElementProperties(etype)[3]
                rows.append(np.asarray(enodes, dtype=np.int64).reshape(-1, n) - 1)
        groups[name] = np.concatenate(rows) if rows else np.empty((0, tdim), np.int64)
    return groups


def generate(gmsh, path: Path, dim: int) -> None:
    """Mesh up to ``dim``. gmsh may log an error and leave a dimension empty (a surface
    mesh that overlaps itself: no tetrahedra) without raising: that is a failure too,
    named by the group of the surface gmsh blames."""
    with gmsh_errors() as errors:
        gmsh.model.mesh.generate(dim)
    if errors or not sum(len(t) for t in gmsh.model.mesh.getElements(dim)[1]):
        cause = (errors or ["no elements"])[-1]
        groups = _blamed(gmsh, cause)
        raise MeshingFailed(f"gmsh could not mesh {path.name} at this size ({cause}"
                            f"{': ' + ', '.join(groups) if groups else ''}); try another --size", groups)


class MeshingFailed(UserError):
    """gmsh failed; ``groups``: the physical groups of the surfaces it blames."""

    def __init__(self, message: str, groups: list[str]):
        super().__init__(message)
        self.groups = groups


def _blamed(gmsh, message: str) -> list[str]:
    """The physical groups of the surfaces or curves a gmsh message names."""
    names = set()
    for word, dim in (("surface", 2), ("curve", 1)):
        for tag in map(int, re.findall(rf"{word} (\d+)", message, flags=re.IGNORECASE)):
            names |= {gmsh.model.getPhysicalName(dim, g) for g in gmsh.model.getPhysicalGroupsForEntity(dim, tag)}
    return sorted(names - {""})


def write_msh(gmsh, path: Path, dim: int) -> None:
    generate(gmsh, path, dim)
    save(gmsh, path)


def save(gmsh, path: Path) -> None:
    """Check the mesh as a scene reader will (meshcheck.py), then write it. A mesh the
    toolkit made and cannot use is refused with the lever the user has: the sizes (the
    check's own advice names gmsh's options, for meshes made elsewhere)."""
    try:
        check_mesh(gmsh, f"{path.name} as meshed", max(d for d, _ in gmsh.model.getPhysicalGroups()))
    except UserError as err:
        raise UserError(f"{err} -- this mesh is the toolkit's own: a slightly different size or organ_size meshes "
                        "it anew (a user's prostate map failed at size 8 and meshed at 6)") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    gmsh.write(str(path))


TET10_EDGES = ((0, 1, 4), (1, 2, 5), (2, 0, 6), (3, 0, 7), (2, 3, 8), (3, 1, 9))  # gmsh's 10-node tet: ends, midpoint


def folded_tetrahedra(gmsh) -> tuple[np.ndarray, np.ndarray]:
    """(tags, node rows) of the 10-node tetrahedra that fold over (meshcheck.folds)."""
    tets, nodes = gmsh.model.mesh.getElementsByType(11)
    folded = folds(gmsh, tets)
    return np.asarray(tets, np.int64)[folded], np.asarray(nodes, np.int64).reshape(-1, 10)[folded]


STRAIGHTENING_ROUNDS = 50  # untangle: at most this many rounds of straightening folded cells


def untangle(gmsh) -> int:
    """Unfold the curved tetrahedra that curving a mesh's boundary folded over (a thin
    cell at a curved wall whose midpoint passes its opposite face): gmsh's high-order
    optimisation of a layer around each, boundary nodes fixed, then the edge midpoints
    of any cell still folded put back on its straight edges (its walls then follow
    their chords there). Returns how many cells were straightened."""
    if not len(folded_tetrahedra(gmsh)[0]):
        return 0  # the usual case: det J's bounds over every cell are computed once, not twice
    gmsh.option.setNumber("Mesh.HighOrderNumLayers", 1)
    gmsh.option.setNumber("Mesh.HighOrderFixBoundaryNodes", 1)
    # Three passes, not gmsh's 25: they unfold as many (four atlas patients at h = 1.6:
    # 28 -> 11, 16 -> 0, 36 -> 0, 27 -> 27 either way; the phantom from STL files 43 -> 33
    # against 43 -> 32) in 3.0 s against 5.5 s, and 3.5 s against 8.5 s.
    gmsh.option.setNumber("Mesh.HighOrderPassMax", 3)
    gmsh.model.mesh.optimize("HighOrder")
    straightened = 0
    # Straightening one cell's edges can fold a neighbour sharing them, and that one the
    # next (a prostate label map's scene: 79, 3, 1, 1 cells in four rounds, refused when
    # three were allowed); a straight cell cannot fold, so the rounds end.
    for _round in range(STRAIGHTENING_ROUNDS):
        _, nodes = folded_tetrahedra(gmsh)
        if not len(nodes):
            break
        straightened += len(nodes)
        position = node_positions(gmsh)
        for a, b, m in TET10_EDGES:
            for node, point in zip(nodes[:, m], (position[nodes[:, a]] + position[nodes[:, b]]) / 2):
                gmsh.model.mesh.setNode(int(node), point, [])
    return straightened


def node_positions(gmsh) -> np.ndarray:
    """Coordinates of every node of the current gmsh mesh, indexed by node tag."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    position = np.zeros((int(tags.max()) + 1, 3))
    position[tags] = coords.reshape(-1, 3)
    return position


def physical_surfaces(gmsh) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every facet group of the current 3D gmsh mesh as (points, triangles), the
    points numbered per group in node-tag order."""
    position = node_positions(gmsh)
    surfaces = {}
    for name, rows in physical_facets(gmsh, 3).items():
        used, local = np.unique(rows + 1, return_inverse=True)
        surfaces[name] = (position[used], local.reshape(rows.shape))
    return surfaces


def read_surfaces(msh: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The facet groups of a 3D .msh file as (points, triangles); a file that is not a
    sound 3D mesh (meshcheck.py): one line."""
    gmsh = open_msh(msh, "surfaces")
    try:
        require(gmsh.model.getPhysicalGroups(3), f"{msh}: not a 3D mesh with physical groups")
        check_mesh(gmsh, str(msh), 3)
        return physical_surfaces(gmsh)
    finally:
        gmsh.clear()
