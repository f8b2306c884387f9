"""Load vectors of a scene: tractions and pressures on facet groups, any linear form."""

from __future__ import annotations

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem

from fenics_elasto.model.dofs import DofLayout


def boundary_load(dofs: DofLayout, tractions: dict, pressures: dict | None = None) -> PETSc.Vec:
    """Load vector of uniform tractions {group: vector} and pressures {group: p} on
    exterior facet groups; a pressure p pushes the wall into the body, t = -p n."""
    scene = dofs.scene
    mesh = scene.mesh
    fdim = mesh.topology.dim - 1
    pressures = pressures or {}
    groups = list(tractions) + list(pressures)
    per_group = [scene.facet_groups[g] for g in groups]
    facets = np.concatenate(per_group)
    values = np.concatenate([np.full(len(f), i + 1, np.int32) for i, f in enumerate(per_group)])
    order = np.argsort(facets, kind="stable")
    tags = dolfinx.mesh.meshtags(mesh, fdim, facets[order], values[order])
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    v, n = ufl.TestFunction(dofs.V), ufl.FacetNormal(mesh)
    loads = [fem.Constant(mesh, np.asarray(t, float)) for t in tractions.values()]
    loads += [-fem.Constant(mesh, float(p)) * n for p in pressures.values()]
    return assemble_load(sum(ufl.inner(t, v) * ds(i + 1) for i, t in enumerate(loads)))


def assemble_load(linear_form) -> PETSc.Vec:
    """Load vector of a UFL linear form (ghost contributions summed)."""
    b = dolfinx.fem.petsc.assemble_vector(fem.form(linear_form))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    return b


def group_measure(scene, group: str) -> float:
    """Length (2D) or area (3D) of a facet group."""
    mesh = scene.mesh
    facets = scene.facet_groups[group]
    tags = dolfinx.mesh.meshtags(mesh, mesh.topology.dim - 1, np.sort(facets), np.ones(len(facets), np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    one = fem.Constant(mesh, 1.0)
    return mesh.comm.allreduce(fem.assemble_scalar(fem.form(one * ds(1))), op=MPI.SUM)
