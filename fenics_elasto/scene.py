"""A scene: mesh with named regions and boundaries, materials, and the problem's settings.

A scene is a gmsh ``.msh`` plus a ``problem.toml`` beside it (see interface.md).
Everything a user can get wrong is checked here, once, with a one-line message.
"""

from __future__ import annotations

import copy

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mpi4py import MPI

import dolfinx
import dolfinx.io.gmsh
from dolfinx.io.utils import distribute_entity_data

from fenics_elasto.errors import UserError, require

ELASTIC_KEYS = ("E", "nu")


@dataclass
class Parameter:
    """One material constant: fixed, or estimated within bounds from an initial value."""

    value: float
    estimate: bool = False
    bounds: tuple[float, float] | None = None


@dataclass
class Material:
    name: str
    tag: int
    E: Parameter
    nu: Parameter


@dataclass
class Scene:
    path: Path
    mesh: dolfinx.mesh.Mesh
    cell_tags: dolfinx.mesh.MeshTags
    materials: list[Material]
    facet_groups: dict[str, np.ndarray]  # group -> local facet indices (full membership)
    config: dict
    plane: str = "strain"
    degree: int = 2
    fixed: list[str] = field(default_factory=list)
    loaded: list[str] = field(default_factory=list)
    matched: list[str] = field(default_factory=list)
    displacement: dict[str, dict] = field(default_factory=dict)  # prescribed, per group
    load: dict[str, np.ndarray] = field(default_factory=dict)  # total force, per group
    match_vertices_only: bool = False

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


# --------------------------------------------------------------------------- TOML


def parse_override(text: str) -> tuple[list[str], object]:
    """``materials.prostate.E=50`` -> (["materials", "prostate", "E"], 50)."""
    key, sep, value = text.partition("=")
    require(bool(sep) and key.strip(), f"--set {text!r}: expected KEY=VALUE")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value.strip()
    return key.strip().split("."), parsed


def apply_overrides(config: dict, overrides) -> None:
    for text in overrides:
        keys, value = parse_override(text)
        node = config
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            require(isinstance(node, dict), f"--set {text!r}: {k} is not a table")
        node[keys[-1]] = value


def read_toml(path: Path) -> dict:
    require(path.is_file(), f"{path}: no such problem file")
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: not valid TOML ({err})") from None


def _number(value, where: str) -> float:
    require(
        isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
        f"{where}: expected a finite number, got {value!r}",
    )
    return float(value)


def parse_parameter(spec, where: str, key: str) -> Parameter:
    """``E = 10`` (fixed) or ``E = {estimate = true, initial = 30, bounds = [1, 500]}``."""
    if isinstance(spec, dict):
        unknown = set(spec) - {"estimate", "initial", "value", "bounds"}
        require(not unknown, f"{where}: unknown key(s) {sorted(unknown)}")
        value = _number(spec.get("initial", spec.get("value")), f"{where}.initial")
        estimate = bool(spec.get("estimate", False))
        bounds = spec.get("bounds")
        if bounds is not None:
            require(isinstance(bounds, list) and len(bounds) == 2, f"{where}.bounds: expected [low, high]")
            bounds = (_number(bounds[0], f"{where}.bounds"), _number(bounds[1], f"{where}.bounds"))
            require(bounds[0] < bounds[1], f"{where}.bounds: low must be below high")
            require(bounds[0] <= value <= bounds[1], f"{where}: initial {value} outside bounds {list(bounds)}")
        elif estimate:
            bounds = (value / 20, value * 20) if key == "E" else (0.0, 0.499)
        param = Parameter(value, estimate, bounds)
    else:
        param = Parameter(_number(spec, where))
    lo, hi = param.bounds if param.bounds else (param.value, param.value)
    if key == "E":
        require(lo > 0 and param.value > 0, f"{where}: Young's modulus must be > 0")
    else:
        require(-1 < lo and hi < 0.5, f"{where}: Poisson's ratio must lie in (-1, 0.5)")
    return param


# --------------------------------------------------------------------------- mesh


def _on_root(comm, work):
    """Run ``work()`` on rank 0 and share its result, or its UserError, with every rank."""
    result, error = None, None
    if comm.rank == 0:
        try:
            result = work()
        except UserError as err:
            error = str(err)
    error = comm.bcast(error, root=0)
    if error is not None:
        raise UserError(error)
    return result


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


def gmsh_facet_groups(gmsh, tdim: int) -> dict[str, np.ndarray]:
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


def read_msh(path: Path, comm=MPI.COMM_WORLD):
    """Read a gmsh .msh into (mesh, cell_tags, cell group names->tag, facet groups).

    ``dolfinx.io.gmsh.read_from_msh`` keeps one tag per facet, so overlapping facet
    groups (``feet`` inside ``outline``) would lose members. Each facet group is
    therefore distributed on its own, from gmsh's physical groups, and kept as an
    array of local facet indices with its full membership.
    """
    import gmsh

    def open_model():
        require(path.is_file(), f"{path}: no such mesh file")
        fresh_gmsh_model(path.stem)
        try:
            gmsh.merge(str(path))
        except Exception as err:  # gmsh raises a bare Exception with its last error
            raise UserError(f"{path}: gmsh cannot read it ({err})") from None
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
        return tdim, gmsh_facet_groups(gmsh, tdim)

    try:
        tdim, facet_rows = _on_root(comm, open_model) or (None, None)
        tdim = comm.bcast(tdim, root=0)
        try:  # model_to_mesh shares its own errors across ranks
            data = dolfinx.io.gmsh.model_to_mesh(gmsh.model if comm.rank == 0 else None, comm, 0, gdim=tdim)
        except RuntimeError as err:
            raise UserError(f"{path}: cannot build a mesh from it ({err})") from None
    finally:
        if comm.rank == 0 and gmsh.isInitialized():
            gmsh.model.remove()

    mesh = data.mesh
    names = comm.bcast(sorted(facet_rows) if comm.rank == 0 else None, root=0)
    fdim = tdim - 1
    mesh.topology.create_connectivity(fdim, tdim)
    facet_groups = {}
    for name in names:
        rows = facet_rows[name] if comm.rank == 0 else None
        width = comm.bcast(rows.shape[1] if comm.rank == 0 else None, root=0)
        if rows is None:
            rows = np.empty((0, width), np.int64)
        local, _ = distribute_entity_data(mesh, fdim, rows, np.zeros(len(rows), np.int32))
        facets = dolfinx.mesh.meshtags_from_entities(
            mesh, fdim, dolfinx.graph.adjacencylist(local), np.zeros(len(local), np.int32)
        ).indices
        facet_groups[name] = np.asarray(facets, dtype=np.int32)
    cell_groups = {n: g.tag for n, g in data.physical_groups.items() if g.dim == tdim}
    return mesh, data.cell_tags, cell_groups, facet_groups


# --------------------------------------------------------------------------- scene


def _group_list(config: dict, key: str, facet_groups: dict, path: Path) -> list[str]:
    names = config.get("boundary", {}).get(key, [])
    if isinstance(names, str):
        names = [names]
    for g in names:
        require(g in facet_groups, f"{path}: boundary.{key}: unknown facet group {g!r} (have {sorted(facet_groups)})")
    return list(names)


def _global_count(comm, facets: np.ndarray, mesh) -> int:
    owned = facets < mesh.topology.index_map(mesh.topology.dim - 1).size_local
    return comm.allreduce(int(owned.sum()), op=MPI.SUM)


def _parse_vector(spec, gdim: int, where: str) -> np.ndarray:
    require(isinstance(spec, list) and len(spec) == gdim, f"{where}: expected a {gdim}-vector")
    return np.array([_number(v, where) for v in spec])


def _parse_displacement(spec, gdim: int, where: str) -> dict:
    """A prescribed affine displacement u(x) = value + G (x - center).

    G is ``gradient`` (a gdim x gdim matrix) plus ``scale`` times the identity
    (``scale`` alone inflates about ``center``).
    """
    require(isinstance(spec, dict), f"{where}: expected a table with value / scale / gradient / center")
    unknown = set(spec) - {"value", "scale", "gradient", "center"}
    require(not unknown, f"{where}: unknown key(s) {sorted(unknown)}")
    gradient = spec.get("gradient", [[0.0] * gdim] * gdim)
    require(isinstance(gradient, list) and len(gradient) == gdim, f"{where}.gradient: expected {gdim} rows")
    gradient = np.array([_parse_vector(row, gdim, f"{where}.gradient") for row in gradient])
    return {
        "value": _parse_vector(spec.get("value", [0.0] * gdim), gdim, f"{where}.value"),
        "gradient": gradient + _number(spec.get("scale", 0.0), f"{where}.scale") * np.eye(gdim),
        "center": _parse_vector(spec.get("center", [0.0] * gdim), gdim, f"{where}.center"),
    }


def load_scene(problem, overrides=(), comm=MPI.COMM_WORLD) -> Scene:
    """Read ``problem.toml`` and its mesh; check every name and value."""
    path = Path(problem)
    config = read_toml(path)
    apply_overrides(config, overrides)

    require("mesh" in config, f"{path}: missing key 'mesh'")
    return _configure(path, config, *read_msh(path.parent / config["mesh"], comm))


def reconfigure(scene: Scene, overrides) -> Scene:
    """The scene with more ``--set`` overrides, on the same mesh (not read again):
    many simulations of one mesh share one ElasticModel."""
    config = copy.deepcopy(scene.config)
    apply_overrides(config, overrides)
    require(config["mesh"] == scene.config["mesh"], f"{scene.path}: reconfigure keeps the mesh; load the other one")
    cell_groups = {m.name: m.tag for m in scene.materials}
    return _configure(scene.path, config, scene.mesh, scene.cell_tags, cell_groups, scene.facet_groups)


def _configure(path: Path, config: dict, mesh, cell_tags, cell_groups: dict, facet_groups: dict) -> Scene:
    """Check the TOML settings against the mesh's groups and build the Scene."""
    comm = mesh.comm
    gdim = mesh.geometry.dim

    plane = config.get("plane", "strain")
    require(plane in ("strain", "stress"), f"{path}: plane must be 'strain' or 'stress', got {plane!r}")
    degree = config.get("degree", 2)
    require(degree in (1, 2), f"{path}: degree must be 1 or 2, got {degree!r}")

    tables = config.get("materials", {})
    for name in tables:
        require(name in cell_groups, f"{path}: materials.{name}: unknown cell group (have {sorted(cell_groups)})")
    materials = []
    for name, tag in sorted(cell_groups.items(), key=lambda item: item[1]):
        require(name in tables, f"{path}: cell group {name!r} has no [materials.{name}] table")
        table = tables[name]
        for key in ELASTIC_KEYS:
            require(key in table, f"{path}: materials.{name}: missing {key}")
        E, nu = (parse_parameter(table[k], f"{path}: materials.{name}.{k}", k) for k in ELASTIC_KEYS)
        materials.append(Material(name, tag, E, nu))

    groups = {k: _group_list(config, k, facet_groups, path) for k in ("fixed", "loaded", "matched")}
    for key, names in groups.items():
        for g in names:
            require(_global_count(comm, facet_groups[g], mesh) > 0, f"{path}: boundary.{key}: group {g!r} has no facets")
    boundary = config.get("boundary", {})
    displacement = {
        g: _parse_displacement(spec, gdim, f"{path}: boundary.displacement.{g}")
        for g, spec in boundary.get("displacement", {}).items()
    }
    load = {g: _parse_vector(spec, gdim, f"{path}: boundary.load.{g}") for g, spec in boundary.get("load", {}).items()}
    for key, names in (("displacement", displacement), ("load", load)):
        for g in names:
            require(g in facet_groups, f"{path}: boundary.{key}: unknown facet group {g!r}")

    fixed = np.concatenate([facet_groups[g] for g in groups["fixed"]] or [np.empty(0, np.int32)])
    loaded = np.concatenate([facet_groups[g] for g in groups["loaded"]] or [np.empty(0, np.int32)])
    shared = comm.allreduce(int(np.intersect1d(fixed, loaded).size), op=MPI.SUM)
    require(shared == 0, f"{path}: boundary.fixed and boundary.loaded share {shared} facets; a facet is either clamped or loaded")
    constrained = comm.allreduce(len(fixed) + sum(len(facet_groups[g]) for g in displacement), op=MPI.SUM)
    require(constrained > 0, f"{path}: boundary.fixed is empty: clamp at least one group (rigid motions)")

    return Scene(
        path=path, mesh=mesh, cell_tags=cell_tags, materials=materials, facet_groups=facet_groups,
        config=config, plane=plane, degree=degree, displacement=displacement, load=load, **groups,
        match_vertices_only=boundary.get("match_nodes", "all") == "vertices",
    )
