"""The Timoshenko-Goodier cantilever: an exact plane-stress solution, and the error of the
toolkit's solve against it (the convergence tests and the refinement tests share it)."""

import numpy as np
import ufl
from mpi4py import MPI

import dolfinx
from dolfinx import fem

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.loads import assemble_load
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values

E, NU, P = 1000.0, 0.3, 1.0
L, C = 8.0, 1.0


def timoshenko(x, y, mod=np):
    """Timoshenko-Goodier plane-stress cantilever, end shear P at x = 0, support at x = L."""
    inertia = 2 * C**3 / 3
    G = E / (2 * (1 + NU))
    ux = (-P * x**2 * y / (2 * E * inertia) - NU * P * y**3 / (6 * E * inertia) + P * y**3 / (6 * inertia * G)
          + (P * L**2 / (2 * E * inertia) - P * C**2 / (2 * inertia * G)) * y)
    uy = (NU * P * x * y**2 / (2 * E * inertia) + P * x**3 / (6 * E * inertia)
          - P * L**2 * x / (2 * E * inertia) + P * L**3 / (3 * E * inertia))
    return ux, uy


def cantilever_errors(problem, degree):
    """(L2 error, tip deflection, mean cell size) of the cantilever scene ``problem``
    (built with length L, half height C) against Timoshenko-Goodier."""
    scene = load_scene(problem, [f"degree={degree}", f"materials.beam.E={E}", f"materials.beam.nu={NU}"])
    model = ElasticModel(scene)
    mesh = scene.mesh
    x = ufl.SpatialCoordinate(mesh)
    inertia = 2 * C**3 / 3
    # Consistent nodal forces of the parabolic end shear (assembled here, independently).
    tip = scene.facet_groups["tip"]
    tags = dolfinx.mesh.meshtags(mesh, 1, np.sort(tip), np.ones(len(tip), np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    traction = ufl.as_vector([0.0, P / (2 * inertia) * (C**2 - x[1] ** 2)])
    rhs = assemble_load(ufl.inner(traction, ufl.TestFunction(model.dofs.V)) * ds(1))
    exact = model.dofs.function("exact")
    exact.interpolate(lambda p: np.stack(timoshenko(p[0], p[1])))
    clamped = model.dofs.clamped_dofs(["support"])
    u = model.solve(model.stiffness.coefficients(*material_values(scene)), clamped, rhs, prescribed=exact)
    ux, uy = timoshenko(x[0], x[1])
    diff = u - ufl.as_vector([ux, uy])
    err = np.sqrt(mesh.comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(diff, diff) * ufl.dx)), op=MPI.SUM))
    tip_node = np.argmin(np.linalg.norm(model.dofs.dof_coords, axis=1))
    tip_deflection = u.x.array.reshape(-1, 2)[tip_node, 1]
    cells = mesh.comm.allreduce(mesh.topology.index_map(2).size_local)
    return err, tip_deflection, np.sqrt(2 * L * C / cells)
