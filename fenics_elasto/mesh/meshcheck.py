"""A gmsh mesh checked before DOLFINx builds on it.

DOLFINx trusts its input: a facet group whose triangles are not faces of the volume
mesh ends the process inside its reader with ``MPI_Abort`` ("Invalid rank"), a mesh
whose volume gmsh failed to fill (it logs the error and writes the surfaces anyway)
with an IndexError, overlapping elements with "Duplicate mesh entity detected" or a
singular stiffness matrix. ``check_mesh`` looks at the gmsh model first and refuses,
in one line naming the file and the group, a mesh that is not a simplicial mesh of a
body with its boundary groups on it:

- the cells (the cell physical groups' elements) are triangles (2D) or tetrahedra
  (3D) of one type and order, none repeated, none flat, no curved one folded over;
- every facet of a cell belongs to one or two cells, and where two, they lie on
  opposite sides of it (else the cells overlap). With that, the boundary (the facets
  of one cell) is closed: the boundary of a boundary is empty;
- every node lies on a cell (no orphans: a node of nothing is a dangling DOF);
- every element of a facet group is a facet of a cell, of the cells' order.

(gmsh_models.py reads gmsh's log of errors; this module looks at what it made.)
"""

from __future__ import annotations

import numpy as np

from fenics_elasto.geometry.meshes import row_keys
from fenics_elasto.util.errors import UserError, require

FLAT = 1e-10  # a cell whose measure is below this fraction of (mean edge)^dim is flat


def _elements(gmsh, dim: int, tag: int) -> list[tuple[int, np.ndarray]]:
    """(element type, node rows) of a physical group's elements, per type."""
    out = []
    for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
        types, _, nodes = gmsh.model.mesh.getElements(dim, entity)
        for etype, enodes in zip(types, nodes):
            width = gmsh.model.mesh.getElementProperties(etype)[3]
            out.append((int(etype), np.asarray(enodes, np.int64).reshape(-1, width)))
    return out


def _name(gmsh, dim: int, tag: int) -> str:
    return gmsh.model.getPhysicalName(dim, tag) or str(tag)


def _where(position: np.ndarray, nodes: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in position[nodes].mean(axis=0)) + ")"


def check_mesh(gmsh, label: str, tdim: int) -> None:
    """Refuse (UserError naming ``label``) a gmsh model that is not a sound mesh; see
    the module docstring. ``tdim``: the cells' dimension (2 or 3)."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    position = np.zeros((int(tags.max()) + 1 if len(tags) else 1, 3))
    position[tags] = coords.reshape(-1, 3)
    cells, etype = _cells(gmsh, label, tdim)
    corners = cells[:, : tdim + 1]
    _check_cells(label, corners, position)
    _check_curved(gmsh, label, tdim, etype, position)
    facets, sides = _facets(corners, position)
    keys = _check_facets(label, facets, sides, position)
    _check_facet_groups(gmsh, label, tdim, etype, keys)
    orphans = np.setdiff1d(tags, cells)
    if len(orphans):
        raise UserError(f"{label}: {len(orphans)} node(s) belong to no cell, e.g. at "
                        f"{_where(position, orphans[:1])}; a mesh of the body's volume only, please")


def _cells(gmsh, label: str, tdim: int) -> tuple[np.ndarray, int]:
    """The node rows of every cell group's elements, and their one element type."""
    rows, types = [], set()
    for _, tag in gmsh.model.getPhysicalGroups(tdim):
        elements = _elements(gmsh, tdim, tag)
        require(sum(len(r) for _, r in elements), f"{label}: cell group {_name(gmsh, tdim, tag)!r} has no cells "
                                                   "(did gmsh fail to mesh its volume?)")
        types |= {t for t, _ in elements}
        rows += [r for _, r in elements]
    names = sorted(gmsh.model.mesh.getElementProperties(t)[0] for t in types)
    require(len(types) == 1, f"{label}: cells of mixed type ({', '.join(names)}); one type and order, please")
    etype = types.pop()
    require(gmsh.model.mesh.getElementProperties(etype)[5] == tdim + 1,
            f"{label}: cells are {names[0]}; fenics_elasto needs {'triangles' if tdim == 2 else 'tetrahedra'}")
    return np.concatenate(rows), etype


def _check_cells(label: str, corners: np.ndarray, position: np.ndarray) -> None:
    """No cell twice (in two groups, say), none flat."""
    _, counts = np.unique(row_keys(np.sort(corners, axis=1)), return_counts=True)
    require(counts.max() == 1, f"{label}: {int((counts > 1).sum())} cell(s) appear more than once "
                               "(in two cell groups?); each cell belongs to one region")
    x = position[corners]
    edges = x[:, 1:] - x[:, :1]
    if corners.shape[1] == 4:
        measure = np.abs(np.einsum("ij,ij->i", edges[:, 0], np.cross(edges[:, 1], edges[:, 2])))
    else:
        measure = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
    scale = np.linalg.norm(edges, axis=2).mean(axis=1) ** (corners.shape[1] - 1)
    flat = np.flatnonzero(measure <= FLAT * scale)
    if len(flat):
        raise UserError(f"{label}: {len(flat)} flat (zero-volume) cell(s), e.g. at {_where(position, corners[flat[0]])}")


def folds(gmsh, tags) -> np.ndarray:
    """Which of the elements ``tags`` fold over: det J changes sign inside (gmsh's
    bounds of it over each whole element)."""
    if not len(tags):
        return np.zeros(0, bool)
    low, high = (np.asarray(gmsh.model.mesh.getElementQualities(tags, q)) for q in ("minDetJac", "maxDetJac"))
    return (low <= 0) & (high >= 0)


def _check_curved(gmsh, label: str, tdim: int, etype: int, position: np.ndarray) -> None:
    """No curved cell folds over: its Jacobian determinant keeps one sign (gmsh's bounds
    of det J over the whole cell; either sign is fine -- an inverted cell is merely
    numbered the other way round). A folded cell's stiffness is wrong while every solve
    still succeeds, and its children overlap when the mesh is refined."""
    if gmsh.model.mesh.getElementProperties(etype)[2] == 1:
        return  # straight-sided: _check_cells' volumes say it all
    for _, tag in gmsh.model.getPhysicalGroups(tdim):
        for entity in gmsh.model.getEntitiesForPhysicalGroup(tdim, tag):
            tags = gmsh.model.mesh.getElementsByType(etype, entity)[0]
            folded = np.asarray(tags)[folds(gmsh, tags)]
            if len(folded):
                nodes = np.asarray(gmsh.model.mesh.getElement(int(folded[0]))[1], np.int64)
                raise UserError(f"{label}: {len(folded)} curved cell(s) fold over (their Jacobian changes sign), "
                                f"e.g. at {_where(position, nodes)}; untangle them (gmsh: Mesh.HighOrderOptimize "
                                "= 1) or mesh with straight-sided cells")


def _facets(corners: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every cell's facets as sorted corner rows, and on which side of each its cell's
    remaining corner lies (+1 or -1)."""
    k = corners.shape[1]
    local = np.array([[j for j in range(k) if j != i] for i in range(k)])
    facets = np.sort(corners[:, local], axis=2).reshape(-1, k - 1)
    opposite = corners.reshape(-1)
    x = position[facets]
    spans = [x[:, j] - x[:, 0] for j in range(1, k - 1)] + [position[opposite] - x[:, 0]]
    if k == 4:
        side = np.einsum("ij,ij->i", spans[0], np.cross(spans[1], spans[2]))
    else:
        side = spans[0][:, 0] * spans[1][:, 1] - spans[0][:, 1] * spans[1][:, 0]
    return facets, np.sign(side)


def _check_facets(label: str, facets: np.ndarray, sides: np.ndarray, position: np.ndarray):
    """Each facet in one or two cells, two on opposite sides. Returns the distinct
    facets (sorted corner rows)."""
    _, first, index, counts = np.unique(row_keys(facets), return_index=True, return_inverse=True, return_counts=True)
    keys, index = facets[first], index.ravel()
    crowded = np.flatnonzero(counts > 2)
    if len(crowded):
        raise UserError(f"{label}: {len(crowded)} facet(s) shared by more than two cells, e.g. at "
                        f"{_where(position, keys[crowded[0]])}; the cells overlap")
    order = np.argsort(index, kind="stable")
    pairs = order[np.repeat(counts == 2, counts)].reshape(-1, 2)
    same = np.flatnonzero(sides[pairs[:, 0]] == sides[pairs[:, 1]])
    if len(same):
        raise UserError(f"{label}: {len(same)} pair(s) of cells overlap (on the same side of a shared facet), "
                        f"e.g. at {_where(position, facets[pairs[same[0], 0]])}")
    return keys


def _check_facet_groups(gmsh, label: str, tdim: int, cell_type: int, keys: np.ndarray) -> None:
    """Every facet group's elements are facets of the cells, of the cells' order."""
    order = gmsh.model.mesh.getElementProperties(cell_type)[2]
    for _, tag in gmsh.model.getPhysicalGroups(tdim - 1):
        name = _name(gmsh, tdim - 1, tag)
        for etype, rows in _elements(gmsh, tdim - 1, tag):
            props = gmsh.model.mesh.getElementProperties(etype)
            require(props[5] == tdim and props[2] == order,
                    f"{label}: facet group {name!r} has {props[0]} elements; the cells' facets are order-{order} "
                    f"{'lines' if tdim == 2 else 'triangles'}")
            corners = np.sort(rows[:, :tdim], axis=1)
            ids = row_keys(np.concatenate([keys, corners]))
            outside = int((~np.isin(ids[len(keys):], ids[: len(keys)])).sum())
            require(not outside, f"{label}: facet group {name!r}: {outside} of its {len(rows)} elements "
                                      "are not facets of any cell (a surface apart from the volume mesh?)")
