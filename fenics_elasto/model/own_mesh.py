"""A scene over a user's own DOLFINx mesh and MeshTags (``Scene.from_mesh``).

The settings are the tables of a problem file given as dicts -- ``materials`` as
[materials], ``boundary`` as [boundary] -- and pass the same schema, with the same
one-line messages; the names of regions and facet groups map to tag values of the
user's ``cell_tags`` and ``facet_tags`` instead of a .msh's physical groups.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from mpi4py import MPI

from fenics_elasto.config.problem import validate_problem
from fenics_elasto.model.scene import Scene, configure
from fenics_elasto.util.errors import require

SOURCE = "Scene.from_mesh"  # names the scene in error lines; its folder is the caller's working directory
MESH_NAME = "<dolfinx mesh>"  # the [mesh] entry of a scene that has no mesh file


def plain(value: Any) -> Any:
    """Python values as a TOML file would give them: tuples and arrays as lists, NumPy
    numbers as floats, ints and bools, mappings as dicts."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def _global_any(comm, flag: bool) -> bool:
    return bool(comm.allreduce(int(flag), op=MPI.MAX))


def _check_tags(mesh, cell_tags, facet_tags) -> None:
    import dolfinx.mesh

    require(isinstance(mesh, dolfinx.mesh.Mesh),
            f"{SOURCE}: mesh must be a dolfinx.mesh.Mesh, got {type(mesh).__name__} {str(mesh)[:60]!r} (a problem "
            "file: fe.load_scene; a .msh file: dolfinx.io.gmsh.read_from_msh first)")
    tdim = mesh.topology.dim
    require(mesh.geometry.dim == tdim, f"{SOURCE}: a {tdim}D mesh in {mesh.geometry.dim}D space; "
                                       "the mesh's geometric and topological dimensions must agree")
    require(tdim in (2, 3), f"{SOURCE}: expected a 2D or 3D mesh, got dimension {tdim}")
    require(getattr(cell_tags, "dim", None) == tdim, f"{SOURCE}: cell_tags must be MeshTags of the cells (dim {tdim}), "
                                                     f"got dim {getattr(cell_tags, 'dim', None)}")
    require(getattr(facet_tags, "dim", None) == tdim - 1, f"{SOURCE}: facet_tags must be MeshTags of the facets "
                                                          f"(dim {tdim - 1}), got dim {getattr(facet_tags, 'dim', None)}")
    for name, tags in (("cell_tags", cell_tags), ("facet_tags", facet_tags)):  # the same count of cells is not enough
        require(tags.topology is mesh.topology._cpp_object,
                f"{SOURCE}: {name} were made on another mesh than the one given (their topology is not the mesh's)")


def cell_regions(mesh, cell_tags, regions: Mapping[str, int]) -> dict[str, int]:
    """{region name: cell tag value}, every tag carried by some cell and every owned cell
    in a region."""
    require(isinstance(regions, Mapping) and len(regions) > 0,
            f"{SOURCE}: regions must map each region's name to its cell tag, like {{'matrix': 1}}")
    out = {}
    for name, tag in regions.items():
        require(isinstance(tag, (int, np.integer)) and not isinstance(tag, bool),
                f"{SOURCE}: regions.{name}: expected a cell tag (an integer), got {tag!r}")
        require(_global_any(mesh.comm, bool(np.any(cell_tags.values == tag))),
                f"{SOURCE}: regions.{name}: no cell carries tag {tag} (cell_tags has {sorted(set(cell_tags.values.tolist()))})")
        out[str(name)] = int(tag)
    require(len(set(out.values())) == len(out), f"{SOURCE}: regions: two regions share a tag ({out})")
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    tagged = np.unique(cell_tags.indices[np.isin(cell_tags.values, list(out.values()))])
    untagged = mesh.comm.allreduce(owned - int(np.sum(tagged < owned)), op=MPI.SUM)
    require(untagged == 0, f"{SOURCE}: {untagged} cells carry none of the regions' tags {sorted(out.values())}; "
                           "every cell needs a region (and its material)")
    return out


def facet_groups(mesh, facet_tags, groups: Mapping[str, int | Sequence[int]]) -> dict[str, np.ndarray]:
    """{group name: local facet indices}: the facets carrying the group's tag (or any of
    its tags; groups may overlap)."""
    require(isinstance(groups, Mapping), f"{SOURCE}: groups must map each facet group's name to its facet tag(s), "
                                         "like {'bottom': 1, 'outline': [1, 2, 3]}")
    out = {}
    for name, tags in groups.items():
        values = np.atleast_1d(np.asarray(tags))
        require(values.ndim == 1 and values.size > 0 and np.issubdtype(values.dtype, np.integer),
                f"{SOURCE}: groups.{name}: expected a facet tag or a list of them (integers), got {tags!r}")
        facets = np.unique(facet_tags.indices[np.isin(facet_tags.values, values)]).astype(np.int32)
        have = sorted(set(facet_tags.values.tolist()))
        require(_global_any(mesh.comm, len(facets) > 0),
                f"{SOURCE}: groups.{name}: no facet carries tag(s) {values.tolist()} (facet_tags has {have})")
        out[str(name)] = facets
    return out


def scene_from_mesh(mesh, cell_tags, facet_tags, regions: Mapping[str, int], groups: Mapping[str, int | Sequence[int]],
                    materials: Mapping[str, Any], boundary: Mapping[str, Any] | None = None, degree: int = 2,
                    plane: str = "strain", settings: Mapping[str, Any] | None = None) -> Scene:
    """The Scene of ``Scene.from_mesh``: the settings checked as a problem file's, the
    names checked against the tags."""
    _check_tags(mesh, cell_tags, facet_tags)
    cells = cell_regions(mesh, cell_tags, regions)
    facets = facet_groups(mesh, facet_tags, groups)
    extra = plain(dict(settings or {}))
    for key in ("mesh", "materials", "boundary", "degree", "plane"):
        require(key not in extra, f"{SOURCE}: settings.{key}: give it as its own argument")
    require("curve" not in extra, f"{SOURCE}: settings.curve: a DOLFINx mesh is used as given, never curved on load; "
            "give it curved (geometry of degree 2, e.g. gmsh's order 2), or write it as .msh for a problem file")
    raw = {"mesh": MESH_NAME, "degree": degree, "plane": plane, "curve": "off", "materials": plain(materials),
           "boundary": plain(dict(boundary or {})), **extra}
    config, _ = validate_problem(copy.deepcopy(raw), SOURCE, None, mesh.geometry.dim)
    return configure(Path(SOURCE), raw, config, mesh, cell_tags, cells, facets)
