"""Forward simulation: prescribed loads and displacements -> displacement field.

Used for synthetic targets: ``[boundary.displacement]`` groups are clamped to the given
displacement -- affine, u = value + G (x - center), plus an optional smooth random
``ripple`` (fields.py: one seed is one field of space, the same on any mesh) --
``[boundary.load]`` groups carry a total force spread as a uniform traction,
``[boundary.pressure]`` groups a pressure that pushes the wall into the body (an organ
filling: a bulge, not an affine motion), and ``fixed`` groups are clamped at zero.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from dolfinx import fem

from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.loads import boundary_load, group_measure
from fenics_elasto.util.errors import require
from fenics_elasto.geometry.fields import SmoothFields
from fenics_elasto.files.writers import write_landmarks
from fenics_elasto.model.observation import probe
from fenics_elasto.model.scene import Scene


@dataclass
class Simulation:
    model: ElasticModel
    u: fem.Function
    result: dict


def material_values(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The current (initial or fixed) E and nu of every region, in scene order."""
    return (np.array([m.E.value for m in scene.materials]), np.array([m.nu.value for m in scene.materials]))


def prescribed_function(model: ElasticModel, displacement: dict) -> fem.Function:
    """u(x) = value + G (x - center) [+ ripple(x)] on the nodes of each prescribed group."""
    g = model.dofs.function("prescribed")
    values = g.x.array.reshape(-1, model.dofs.bs)
    for group, spec in displacement.items():
        blocks = model.dofs.boundary_blocks([group])
        x = model.dofs.dof_coords[blocks]
        values[blocks] = spec["value"] + (x - spec["center"]) @ spec["gradient"].T
        if spec.get("ripple"):
            ripple = spec["ripple"]
            rng = np.random.default_rng(ripple["seed"])
            values[blocks] += ripple["amplitude"] * SmoothFields(1, model.dofs.gdim, model.dofs.gdim, ripple["length"], rng)(x)[0]
    return g


def simulate(scene: Scene, model: ElasticModel | None = None) -> Simulation:
    start = time.perf_counter()
    E, nu = material_values(scene)
    model = model or ElasticModel(scene, fixed=(E, nu))  # its own: K at these materials only
    require(scene.load or scene.displacement or scene.pressure,
            f"{scene.path}: nothing to simulate: add [boundary.load], [boundary.pressure] or [boundary.displacement]")
    require(scene.fixed or scene.displacement, f"{scene.path}: boundary.fixed is empty: clamp at least one group (rigid motions)")
    clamped = model.dofs.clamped_dofs(scene.fixed + list(scene.displacement))
    rhs = None
    if scene.load or scene.pressure:
        tractions = {g: total / group_measure(model.scene, g) for g, total in scene.load.items()}
        rhs = boundary_load(model.dofs, tractions, scene.pressure)
    prescribed = prescribed_function(model, scene.displacement) if scene.displacement else None
    u = model.solve(model.stiffness.coefficients(E, nu), clamped, rhs, prescribed, nearby=True)  # a shared model: no refactoring
    magnitude = np.linalg.norm(u.x.array.reshape(-1, model.dofs.bs)[: model.dofs.n_owned_blocks], axis=1)
    result = {
        "materials": {m.name: {"E": m.E.value, "nu": m.nu.value} for m in scene.materials},
        "max_displacement": scene.comm.allreduce(float(magnitude.max(initial=0.0)), op=MPI.MAX),
        "group_forces": group_forces(model, model.stiffness.coefficients(E, nu), u),
        "factorizations": model.factorizations,
        "solver": model.stats.as_dict(),
        "dofs": model.dofs.num_dofs,
        "degree": scene.degree,
        "wall_time_s": round(time.perf_counter() - start, 3),
    }
    return Simulation(model, u, result)


def group_forces(model: ElasticModel, c, u: fem.Function) -> dict[str, list[float]]:
    """The total force applied to the body through each displaced, loaded or pressed
    group: K u summed over its nodes, those on a fixed group left out (there K u holds the
    clamp's reaction too) -- what a load cell measures, and what an estimate's
    [boundary.measured_force] compares with (measured_force.group_forces)."""
    scene, dofs = model.scene, model.dofs
    Ku = dofs.function("Ku")
    model.stiffness.apply(c, u.x.petsc_vec, Ku.x.petsc_vec)
    values = Ku.x.array.reshape(-1, dofs.bs)
    fixed = dofs.boundary_blocks(scene.fixed) if scene.fixed else np.zeros(0, np.int32)
    out = {}
    for group in dict.fromkeys([*scene.displacement, *scene.load, *scene.pressure]):
        blocks = np.setdiff1d(dofs.boundary_blocks([group]), fixed)
        out[group] = scene.comm.allreduce(values[blocks].sum(axis=0), op=MPI.SUM).tolist()
    return out


def write_landmarks_for(scene: Scene, u: fem.Function, path: Path, noise: float = 0.0, seed: int = 0) -> Path:
    """A landmark target (exact node correspondence): ``u``, from any mesh, probed at
    the scene's matched nodes, plus optional Gaussian noise of std ``noise``."""
    nodes = DofLayout(scene).node_set(scene.matched)
    points = nodes.gather(nodes.coords)
    moved = points + probe(u, points)
    moved += noise * np.random.default_rng(seed).standard_normal(moved.shape)
    if scene.comm.rank == 0:
        write_landmarks(path, points, moved)
    return path
