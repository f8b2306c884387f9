"""A scene: mesh with named regions and boundaries, materials, and the problem's settings.

A scene is a gmsh ``.msh`` plus a ``problem.toml`` beside it (the format: docs/scenes.md).
Everything a user can get wrong is checked here, once, with a one-line message.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mpi4py import MPI

import dolfinx
import dolfinx.io.gmsh
from dolfinx.io.utils import distribute_entity_data

from fenics_elasto.config.problem import PROBLEM, check_gdim, validate_problem
from fenics_elasto.config.toml import apply_overrides, read_toml
from fenics_elasto.util.errors import UserError, on_root, require
from fenics_elasto.mesh.gmsh_models import open_msh, physical_facets
from fenics_elasto.util.logs import log
from fenics_elasto.mesh.curving import curve_if_straight, kept_straight_warnings
from fenics_elasto.mesh.meshcheck import check_mesh
from fenics_elasto.model.mesh_copy import read_copy, write_copy

ELASTIC_KEYS = ("E", "nu")


@dataclass
class Parameter:
    """One material constant: fixed, or estimated within bounds from an initial value."""

    value: float
    estimate: bool = False
    bounds: tuple[float, float] | None = None


@dataclass
class Material:
    """A region's material: its name, its cell tag, E and nu."""

    name: str
    tag: int
    E: Parameter
    nu: Parameter


@dataclass
class Scene:
    """A mesh with named regions (each with its material) and named facet groups, and the
    problem's settings: which groups are clamped, loaded and matched, the target, the
    optimiser, the solver. Made by ``load_scene`` (a problem.toml and its .msh) or
    ``Scene.from_mesh`` (a DOLFINx mesh and its MeshTags); ``path`` names it in
    messages, and relative file names in its settings are relative to its folder."""

    path: Path
    mesh: dolfinx.mesh.Mesh
    cell_tags: dolfinx.mesh.MeshTags
    materials: list[Material]
    facet_groups: dict[str, np.ndarray]  # group -> local facet indices (full membership)
    config: dict  # normalised by config.py's schema
    raw: dict  # the TOML as read, overrides applied (reconfigure starts from it)
    plane: str = "strain"
    degree: int = 2
    fixed: list[str] = field(default_factory=list)
    loaded: list[str] = field(default_factory=list)
    matched: list[str] = field(default_factory=list)
    displacement: dict[str, dict] = field(default_factory=dict)  # prescribed, per group
    load: dict[str, np.ndarray] = field(default_factory=dict)  # total force, per group
    pressure: dict[str, float] = field(default_factory=dict)  # pressure pushing the wall in, per group
    match_nodes: str = "auto"  # "auto" | "all" | "vertices" (observation.matched_vertices_only)
    force_reference: str | None = None  # the region whose E a measured force scales (measured_force.py)
    warnings: list[str] = field(default_factory=list)  # what loading it found worth a warning (curving)

    @property
    def gdim(self) -> int:
        return self.mesh.geometry.dim

    @property
    def comm(self):
        return self.mesh.comm

    @property
    def mesh_file(self) -> Path:
        return self.path.parent / self.config["mesh"]

    def facets(self, groups) -> np.ndarray:
        """Local facet indices in the union of the named groups."""
        parts = [self.facet_groups[g] for g in groups]
        return np.unique(np.concatenate(parts)) if parts else np.empty(0, np.int32)

    def estimated(self) -> list[tuple[str, str]]:
        """(material, key) of every estimated constant, in a fixed order."""
        return [(m.name, k) for m in self.materials for k in ELASTIC_KEYS if getattr(m, k).estimate]

    def material(self, name: str) -> Material:
        return next(m for m in self.materials if m.name == name)

    def parameters(self) -> Parameters:
        return Parameters(self)

    @classmethod
    def from_mesh(cls, mesh: dolfinx.mesh.Mesh, cell_tags: dolfinx.mesh.MeshTags, facet_tags: dolfinx.mesh.MeshTags,
                  regions: Mapping[str, int], groups: Mapping[str, int | Sequence[int]], materials: Mapping[str, Any],
                  boundary: Mapping[str, Any] | None = None, degree: int = 2, plane: str = "strain",
                  settings: Mapping[str, Any] | None = None) -> Scene:
        """A scene over your own DOLFINx mesh and its tags.

        ``regions`` maps each region's name to its value in ``cell_tags`` (every cell in
        one region), ``groups`` each facet group's name to its value(s) in ``facet_tags``
        (groups may overlap: ``{"outline": [1, 2, 3]}``). ``materials`` and ``boundary``
        are the problem file's [materials] and [boundary] tables as dicts, ``settings``
        its other tables (``target``, ``optimizer``, ``reduction``, ``solver``,
        ``units``); paths in them are relative to the working directory. Checked as a
        problem file is: a bad name or value raises UserError with one line.

        The mesh is used as given. A problem file's straight-sided (order 1) ``.msh`` is
        curved on load where its surfaces are curved ([curve], "auto"); this one is not:
        on curved surfaces that can be worth a few % of E (the pelvis phantom's plain gmsh
        order-1 source: -7.7 % straight, -3.5 % curved on load). Give the mesh curved -- a geometry
        of degree 2, e.g. gmsh's order 2 -- or write it as ``.msh`` for a problem file.
        """
        from fenics_elasto.model.own_mesh import scene_from_mesh

        return scene_from_mesh(mesh, cell_tags, facet_tags, regions, groups, materials, boundary, degree, plane, settings)


def shift_in_units(is_E, ds) -> np.ndarray:
    """A move in s = (log E, nu) as each constant reads it: relative for E (0.05 is
    +5 %), absolute for nu."""
    ds = np.asarray(ds, float)
    return np.where(is_E, np.expm1(ds), ds)


class Parameters:
    """The estimated constants theta -- (material, "E" or "nu") in scene order -- and the
    map theta -> (E, nu) of every region. The optimiser works in s = (log E, nu): E
    ratios are what the data determine, and they span decades."""

    def __init__(self, scene: Scene):
        self.names = scene.estimated()
        self.labels = [f"{m}.{k}" for m, k in self.names]
        order = [m.name for m in scene.materials]
        self.index = np.array([order.index(m) for m, _ in self.names], dtype=int)
        self.is_E = np.array([k == "E" for _, k in self.names], dtype=bool)
        self.fixed_E = np.array([m.E.value for m in scene.materials])
        self.fixed_nu = np.array([m.nu.value for m in scene.materials])
        params = [getattr(scene.material(m), k) for m, k in self.names]
        self.initial = np.array([p.value for p in params])
        self.bounds = [p.bounds for p in params]

    def __len__(self) -> int:
        return len(self.names)

    def materials(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(E, nu) of every region with the estimated entries taken from theta."""
        theta = np.atleast_1d(np.asarray(theta, float))
        E, nu = self.fixed_E.copy(), self.fixed_nu.copy()
        E[self.index[self.is_E]] = theta[self.is_E]
        nu[self.index[~self.is_E]] = theta[~self.is_E]
        return E, nu

    def select(self, d_dE: np.ndarray, d_dnu: np.ndarray) -> np.ndarray:
        """Rows d/dtheta_k from per-material derivative rows d/dE_m and d/dnu_m."""
        return np.where(self.is_E[:, None], d_dE[self.index], d_dnu[self.index])

    # --- the optimiser's coordinates s = (log E, nu)

    def to_s(self, theta) -> np.ndarray:
        theta = np.asarray(theta, float)
        return np.where(self.is_E, np.log(np.where(self.is_E, theta, 1.0)), theta)

    def to_theta(self, s) -> np.ndarray:
        s = np.asarray(s, float)
        return np.where(self.is_E, np.exp(np.where(self.is_E, s, 0.0)), s)

    def dtheta_ds(self, theta) -> np.ndarray:
        """The chain rule's diagonal: dE/dlog E = E, dnu/dnu = 1."""
        return np.where(self.is_E, theta, 1.0)

    def s_bounds(self) -> list[tuple[float, float]]:
        low, high = np.array(self.bounds, float).reshape(len(self), 2).T
        return list(zip(self.to_s(low), self.to_s(high)))

    def describe(self, theta) -> str:
        return "  ".join(f"{label} = {value:.5g}" for label, value in zip(self.labels, np.atleast_1d(theta)))


# --------------------------------------------------------------------------- mesh


def read_msh(path: Path, comm=MPI.COMM_WORLD, curve: bool = False):
    """Read a gmsh .msh into (mesh, cell_tags, cell group names->tag, facet groups,
    warnings); ``curve``: give a straight-sided mesh of curved surfaces curved geometry
    (mesh/curving.py; one line says so, the warnings what it could not tell). The
    first read keeps what it made as the .msh's parallel copy, which later reads take
    on every rank at once (mesh_copy.py).

    ``dolfinx.io.gmsh.read_from_msh`` keeps one tag per facet, so overlapping facet
    groups (``feet`` inside ``outline``) would lose members. Each facet group is
    therefore distributed on its own, from gmsh's physical groups, and kept as an
    array of local facet indices with its full membership.
    """
    import gmsh

    copied = read_copy(path, curve, comm)
    if copied is not None:
        return copied
    facet_rows: dict[str, np.ndarray] = {}  # rank 0: every facet group's facets as node rows
    try:
        tdim, names, note, warnings = on_root(comm, lambda: _open_checked(path, facet_rows, curve))
        try:  # model_to_mesh shares its own errors across ranks
            data = dolfinx.io.gmsh.model_to_mesh(gmsh.model if comm.rank == 0 else None, comm, 0, gdim=tdim)
        except RuntimeError as err:
            raise UserError(f"{path}: cannot build a mesh from it ({err})") from None
    finally:
        if comm.rank == 0 and gmsh.isInitialized():
            gmsh.model.remove()
    facet_groups = _distribute_facet_groups(data.mesh, names, facet_rows, comm)
    cell_groups = {n: g.tag for n, g in data.physical_groups.items() if g.dim == tdim}
    loaded = data.mesh, data.cell_tags, cell_groups, facet_groups, warnings
    write_copy(path, curve, loaded, note, comm)
    # What was just written is read back, so that the first load and every later one give
    # the same mesh in the same order (the XDMF read numbers cells and nodes its own way):
    # without this, a first simulate and a second one differed in their DOF order.
    return read_copy(path, curve, comm, announce=False) or loaded


def _open_checked(path: Path, facet_rows: dict, curve: bool) -> tuple[int, list[str], str | None, list[str]]:
    """Rank 0: open the .msh in gmsh, check what DOLFINx's reader would choke on, and
    fill ``facet_rows`` (group name -> facets as node rows); (tdim, facet group names,
    the curving's note and warnings)."""
    import gmsh

    open_msh(path)
    groups = gmsh.model.getPhysicalGroups()
    require(groups, f"{path}: the mesh has no physical groups")
    tdim = max(d for d, _ in groups)
    require(tdim in (2, 3), f"{path}: expected a 2D or 3D mesh, found dimension {tdim}")
    _, coords, _ = gmsh.model.mesh.getNodes()
    coords = coords.reshape(-1, 3)
    require(np.isfinite(coords).all(), f"{path}: the mesh has NaN or infinite coordinates")
    require(tdim == 3 or np.allclose(coords[:, 2], 0), f"{path}: a 2D mesh must lie in the z = 0 plane")
    cell_groups = [t for d, t in groups if d == tdim]
    require(cell_groups, f"{path}: no cell (region) physical groups")
    unnamed = [t for t in cell_groups if not gmsh.model.getPhysicalName(tdim, t)]
    require(not unnamed, f"{path}: cell physical group(s) {unnamed} have no name; the problem file names "
                         "each region's material (gmsh: Physical Volume(\"name\") = ...)")
    check_mesh(gmsh, str(path), tdim)
    note, warnings = curve_if_straight(gmsh, tdim, path) if curve else (None, kept_straight_warnings(gmsh, tdim, path))
    facet_rows.update(physical_facets(gmsh, tdim))
    return tdim, sorted(facet_rows), note, warnings


def _distribute_facet_groups(mesh, names: list[str], facet_rows: dict, comm) -> dict[str, np.ndarray]:
    """Each facet group (node rows on rank 0) as local facet indices on every rank."""
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, fdim + 1)
    facet_groups = {}
    for name in names:
        width = comm.bcast(facet_rows[name].shape[1] if comm.rank == 0 else None, root=0)
        rows = facet_rows[name] if comm.rank == 0 else np.empty((0, width), np.int64)
        local, _ = distribute_entity_data(mesh, fdim, rows, np.zeros(len(rows), np.int32))
        facets = dolfinx.mesh.meshtags_from_entities(
            mesh, fdim, dolfinx.graph.adjacencylist(local), np.zeros(len(local), np.int32)
        ).indices
        facet_groups[name] = np.asarray(facets, dtype=np.int32)
    return facet_groups


# --------------------------------------------------------------------------- scene


def _global_count(comm, facets: np.ndarray, mesh) -> int:
    owned = facets < mesh.topology.index_map(mesh.topology.dim - 1).size_local
    return comm.allreduce(int(owned.sum()), op=MPI.SUM)


def load_scene(problem, overrides=(), comm=MPI.COMM_WORLD, command: str | None = None) -> Scene:
    """Read ``problem.toml`` (checked by config.py's schema, for ``command``: "simulate",
    "estimate", "train", or None for types and ranges only) and its mesh; check every
    group name against the mesh."""
    path = Path(problem)
    raw = read_toml(path)
    overridden = apply_overrides(raw, overrides, PROBLEM, str(path))
    config, warnings = validate_problem(raw, str(path), command, None, overridden)
    for text in warnings:  # simulate-only tables in an estimate: harmless, said once
        log.info(f"note: {text}")
    curve = config["curve"] == "auto" and config["degree"] == 2  # P1 fields on curved cells gain nothing
    mesh, cell_tags, cell_groups, facet_groups, mesh_warnings = read_msh(path.parent / config["mesh"], comm, curve)
    check_gdim(config, mesh.geometry.dim, str(path), overridden)
    return configure(path, raw, config, mesh, cell_tags, cell_groups, facet_groups, warnings=mesh_warnings)


def reconfigure(scene: Scene, overrides, command: str | None = None) -> Scene:
    """The scene with more ``--set`` overrides, on the same mesh (not read again):
    many simulations of one mesh share one ElasticModel."""
    raw = copy.deepcopy(scene.raw)
    overridden = apply_overrides(raw, overrides, PROBLEM, str(scene.path))
    config, _ = validate_problem(raw, str(scene.path), command, scene.gdim, overridden)
    require(config["mesh"] == scene.config["mesh"], f"{scene.path}: reconfigure keeps the mesh; load the other one")
    cell_groups = {m.name: m.tag for m in scene.materials}
    return configure(scene.path, raw, config, scene.mesh, scene.cell_tags, cell_groups, scene.facet_groups,
                      warnings=scene.warnings)


def _parameter(spec: dict) -> Parameter:
    return Parameter(spec["value"], spec["estimate"], tuple(spec["bounds"]) if spec["bounds"] else None)


def _check_groups(path: Path, config: dict, cell_groups: dict, facet_groups: dict, mesh) -> None:
    """Every name in the problem is a group of the mesh, and every region has a material."""
    comm = mesh.comm
    for name in config["materials"]:
        require(name in cell_groups, f"{path}: materials.{name}: unknown cell group (have {sorted(cell_groups)})")
    for name in cell_groups:
        require(name in config["materials"], f"{path}: cell group {name!r} has no [materials.{name}] table")
    boundary = config["boundary"]
    named = [(k, g) for k in ("fixed", "loaded", "matched") for g in boundary[k]]
    named += [(k, g) for k in ("displacement", "load", "pressure") for g in boundary[k]]
    for key, g in named:
        require(g in facet_groups, f"{path}: boundary.{key}: unknown facet group {g!r} (have {sorted(facet_groups)})")
        require(_global_count(comm, facet_groups[g], mesh) > 0, f"{path}: boundary.{key}: group {g!r} has no facets")
    fixed = np.concatenate([facet_groups[g] for g in boundary["fixed"]] or [np.empty(0, np.int32)])
    loaded = np.concatenate([facet_groups[g] for g in boundary["loaded"]] or [np.empty(0, np.int32)])
    shared = comm.allreduce(int(np.intersect1d(fixed, loaded).size), op=MPI.SUM)
    require(shared == 0, f"{path}: boundary.fixed and boundary.loaded share {shared} facets; a facet is either clamped or loaded")


def _displacement(spec: dict, gdim: int) -> dict:
    """u(x) = value + (gradient + scale I)(x - center), missing parts zero."""
    zero = np.zeros(gdim)
    gradient = np.array(spec["gradient"]) if spec["gradient"] is not None else np.zeros((gdim, gdim))
    return {"value": np.array(spec["value"]) if spec["value"] is not None else zero,
            "gradient": gradient + spec["scale"] * np.eye(gdim),
            "center": np.array(spec["center"]) if spec["center"] is not None else zero,
            "ripple": spec["ripple"]}


def configure(path: Path, raw: dict, config: dict, mesh, cell_tags, cell_groups: dict, facet_groups: dict,
               warnings: list[str] | None = None) -> Scene:
    """Check the normalised settings against the mesh's groups and build the Scene."""
    _check_groups(path, config, cell_groups, facet_groups, mesh)
    materials = [Material(name, tag, _parameter(config["materials"][name]["E"]), _parameter(config["materials"][name]["nu"]))
                 for name, tag in sorted(cell_groups.items(), key=lambda item: item[1])]
    boundary = config["boundary"]
    gdim = mesh.geometry.dim
    return Scene(
        path=path, mesh=mesh, cell_tags=cell_tags, materials=materials, facet_groups=facet_groups,
        config=config, raw=raw, plane=config["plane"], degree=config["degree"],
        fixed=boundary["fixed"], loaded=boundary["loaded"], matched=boundary["matched"],
        displacement={g: _displacement(spec, gdim) for g, spec in boundary["displacement"].items()},
        load={g: np.array(v) for g, v in boundary["load"].items()},
        pressure=dict(boundary["pressure"]),
        match_nodes=boundary["match_nodes"],
        warnings=list(warnings or []),
    )
