"""gmsh, quietly: fresh models with default options, meshing and saving with one-line
errors, and facet groups read back as node rows or triangulations."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fenics_elasto.errors import UserError, require


def fresh_gmsh_model(name: str):
    """An empty gmsh model with default options (options are global: they would leak
    from one model to the next); gmsh stays quiet."""
    import gmsh

    if not gmsh.isInitialized():
        gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.clear()
    gmsh.option.restoreDefaults()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add(name)
    return gmsh


def open_msh(path: Path, name: str | None = None):
    """A fresh gmsh model holding the mesh file ``path``; a missing or unreadable file
    is one line naming it."""
    require(Path(path).is_file(), f"{path}: no such mesh file")
    gmsh = fresh_gmsh_model(name or Path(path).stem)
    try:
        gmsh.merge(str(path))
    except Exception as err:  # gmsh raises a bare Exception with its last error
        raise UserError(f"{path}: gmsh cannot read it ({err})") from None
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
    try:
        gmsh.model.mesh.generate(dim)
    except Exception as err:  # gmsh raises a bare Exception with its last error
        raise UserError(f"gmsh could not mesh {path.name} at this size ({err}); try another --size") from None


def write_msh(gmsh, path: Path, dim: int) -> None:
    generate(gmsh, path, dim)
    save(gmsh, path)


def save(gmsh, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    gmsh.write(str(path))


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
    """The facet groups of a 3D .msh file as (points, triangles)."""
    require(Path(msh).is_file(), f"{msh}: no such mesh file")
    with GmshModel("surfaces") as gmsh:
        gmsh.merge(str(msh))
        return physical_surfaces(gmsh)
