"""The source mesh's own error in the answer: one solve a degree higher, at the answer.

An estimate compares the model's surfaces with the target's, so the model's
discretisation error is read as if it were the tissue's response: on a curved P2
source of the pelvis phantom E came out 2-3 % high or low, the same way at every noise
level (docs: validation). The error is estimated in the approximation-error way
(Kaipio & Somersalo 2007): at the answer, the walls that carry the unknown forces are
held where the estimate put them, and the body between them is solved again with
elements one degree higher on the same mesh (a space that contains the estimate's).
The difference at the observed points, eps, is what the estimate's own model got
wrong there; mapped through the answer's linearisation (controls following, as for
``target_offset``) it gives ds, the shift a better model would make, reported as the
``mesh`` part of sigma (parts.py says why it is not applied as a correction).

The solve is one conjugate-gradient run preconditioned by smoothed aggregation:
no factorization, about 10 s on the pelvis phantom's plain gmsh source (138k DOFs).
"""

from __future__ import annotations

import time

import numpy as np
import ufl
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem

from fenics_elasto.inverse.linearisation import Linearisation
from fenics_elasto.inverse.uncertainty.posterior import offset_shift
from fenics_elasto.model.materials import epsilon, lame
from fenics_elasto.model.observation import PointProbe
from fenics_elasto.model.solvers import rigid_body_modes
from fenics_elasto.model.stiffness import stiffness_quadrature
from fenics_elasto.util.logs import log

RTOL = 1e-7  # the higher-degree solve: eps is ~1e-2 of u, so u to well below that


def higher_degree_solution(scene, E, nu, u: fem.Function) -> fem.Function:
    """The displacement one degree higher than ``u``'s space with the materials (E, nu)
    per region, clamped where the scene is, and every loaded wall held at ``u``."""
    V_low = u.function_space
    mesh = scene.mesh
    V = fem.functionspace(mesh, ("Lagrange", V_low.element.basix_element.degree + 1, (mesh.geometry.dim,)))
    held = fem.Function(V)
    held.interpolate(u)
    walls = scene.facets(list(scene.config["boundary"]["fixed"]) + list(scene.config["boundary"]["loaded"]))
    bc = fem.dirichletbc(held, fem.locate_dofs_topological(V, mesh.topology.dim - 1, walls))
    A, b = _system(scene, V, E, nu, bc)
    assert b is not None
    owned = V.tabulate_dof_coordinates()[: V.dofmap.index_map.size_local, : mesh.geometry.dim]
    A.setNearNullSpace(rigid_body_modes(owned, mesh.comm))
    solution = fem.Function(V)
    ksp = _smoothed_aggregation_cg(A)
    try:
        ksp.solve(b, solution.x.petsc_vec)
        reason, iterations = ksp.getConvergedReason(), ksp.getIterationNumber()
    finally:
        for obj in (ksp, A, b):
            obj.destroy()
    solution.x.scatter_forward()
    if reason < 0:
        raise ArithmeticError(f"the degree-{V.element.basix_element.degree} solve did not converge ({reason})")
    log.debug(f"higher-degree solve: {iterations} CG iterations")
    return solution


def _system(scene, V, E, nu, bc, rhs: bool = True) -> tuple[PETSc.Mat, PETSc.Vec | None]:
    """K and (``rhs``) the lifted right-hand side of the problem on V (no body load)."""
    mesh = scene.mesh
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=scene.cell_tags, metadata=stiffness_quadrature(V))
    mu, lam = lame(E, nu, scene.plane)
    a = sum(2 * float(m) * ufl.inner(epsilon(u), epsilon(v)) * dx(material.tag)
            + float(lm) * ufl.div(u) * ufl.div(v) * dx(material.tag)
            for material, m, lm in zip(scene.materials, mu, lam))
    form = fem.form(a)
    A = dolfinx.fem.petsc.assemble_matrix(form, bcs=[bc])
    A.assemble()
    if not rhs:
        return A, None
    zero = fem.form(ufl.inner(fem.Constant(mesh, np.zeros(mesh.geometry.dim)), v) * ufl.dx)
    b = dolfinx.fem.petsc.assemble_vector(zero)
    dolfinx.fem.petsc.apply_lifting(b, [form], bcs=[[bc]])
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    dolfinx.fem.petsc.set_bc(b, [bc])
    return A, b


def _smoothed_aggregation_cg(A: PETSc.Mat) -> PETSc.KSP:
    """CG on A with PETSc's smoothed aggregation (GAMG, the rigid-body modes as its
    near-nullspace, Chebyshev-Jacobi smoothing): on the pelvis's degree-3 space (138k
    DOFs) 47 iterations and 9 s with setup, where a two-level cycle over the estimate's
    own space took 8 iterations but 150 s to form its coarse operator (PETSc's P^T A P)."""
    ksp = PETSc.KSP().create(A.getComm())
    prefix = f"mesh_error_{id(ksp)}_"
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(A)
    ksp.setType("cg")
    ksp.setTolerances(rtol=RTOL, max_it=1000)
    ksp.getPC().setType("gamg")
    options = PETSc.Options()
    settings = {"pc_gamg_threshold": 0.01, "mg_levels_ksp_type": "chebyshev", "mg_levels_pc_type": "jacobi"}
    for key, value in settings.items():
        options[prefix + key] = value
    ksp.setFromOptions()
    for key in settings:
        options.delValue(prefix + key)
    return ksp


def mesh_shift(problem, lin: Linearisation, theta, evaluation) -> np.ndarray | None:
    """ds: how far s = (log E, nu) moves (first order, the controls following) when the
    model's observed displacements are those of the higher-degree solve at the answer;
    None where the scene has no walls to hold or a point could not be probed."""
    scene = problem.scene
    if not list(scene.config["boundary"]["loaded"]):
        return None
    start = time.perf_counter()
    E, nu = problem.params.materials(theta)
    u = evaluation.u
    finer = higher_degree_solution(scene, E, nu, u)
    points = problem.observation.points
    probe = PointProbe(finer.function_space, points)
    coarse = fem.Function(finer.function_space)
    coarse.interpolate(u)
    eps = _gathered(probe, finer) - _gathered(probe, coarse)
    rows = problem.misfit.statistical_rows(evaluation.y, evaluation.residual)
    ds = offset_shift(lin, np.einsum("lkd,ld->lk", rows, eps[: rows.shape[0]]).ravel())
    log.info(f"the source mesh's own error: a degree-{finer.function_space.element.basix_element.degree} solve "
             f"at the answer moves the observed points by up to {np.abs(eps).max():.3g} "
             f"({time.perf_counter() - start:.1f} s)")
    return ds


def _gathered(probe: PointProbe, u: fem.Function) -> np.ndarray:
    """(n, gdim) values of u at the probe's points, on every rank."""
    return probe.values(u.x.array)
