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

The solve is CG (no factorization of the bigger system), preconditioned by a two-level
cycle whose coarse level is the estimate's own factorized K at (or near) the answer
(model.solvers.TwoLevelSolver): the space one degree lower lies inside this one, so
that coarse operator costs nothing more. On the pelvis phantom's plain gmsh source
(43k DOFs, P3 138k) the mesh part took 11-15 s with AMG (5 s of it AMG's setup) and
takes 5-7 s with the cycle, the same part of sigma (benchmarks/profile_estimate.py). Without
the factors (the iterative method, a big mesh) it is CG + AMG as before. (A two-level
cycle over a coarser *mesh* took 8 iterations but 150 s to form its coarse operator,
PETSc's P^T A P.)
"""

from __future__ import annotations

from dataclasses import replace

import time

import numpy as np
import ufl
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem

from fenics_elasto.inverse.linearisation import Linearisation
from fenics_elasto.inverse.uncertainty.posterior import offset_shift
from fenics_elasto.model.solvers import (DirectSolver, IterativeSolver, SolverSettings, SolverStats, TwoLevelSolver,
                                         WarmStart, rigid_body_modes)
from fenics_elasto.model.stiffness import stiffness_form
from fenics_elasto.util.logs import log

# The correction the degree-3 solve finds is ~1 % of u (the phantom: 3e-3 of 0.3); its
# mesh part of sigma to 2 digits needs u to ~1e-4, not the estimate's 1e-8 (measured on
# the family's order-1 source: 1e-6 and the seeded start gave the mesh part 1.48 as before,
# the step 15.7 s -> 11.3 s; AMG's setup, 5 s, is most of the rest).
HIGHER_DEGREE_RTOL = 1e-6


def higher_degree_solutions(scene, E, nu, fields: list[fem.Function],
                            coarse: DirectSolver | None = None, stats: SolverStats | None = None
                            ) -> list[fem.Function]:
    """The displacement one degree higher than the fields' space with the materials (E, nu)
    per region, clamped where the scene is, and every loaded wall held at each field
    (several states: one each): one K and one CG for them all, each solve started from
    its field itself (interpolated: CG finds only the correction), to
    HIGHER_DEGREE_RTOL or the scene's tighter [solver] rtol. ``coarse``: the factors of
    the fields' own K at these materials (or near them) with the same walls clamped,
    which make CG's preconditioner a two-level cycle (model.solvers.TwoLevelSolver);
    without them, AMG (model.solvers.IterativeSolver). ``stats``: where to count the
    solves and CG iterations."""
    mesh = scene.mesh
    V = fem.functionspace(mesh, ("Lagrange", fields[0].function_space.element.basix_element.degree + 1,
                                 (mesh.geometry.dim,)))
    held = fem.Function(V)  # the walls' values; K does not depend on them, the lifted load does
    walls = scene.facets(list(scene.config["boundary"]["fixed"]) + list(scene.config["boundary"]["loaded"]))
    bc = fem.dirichletbc(held, fem.locate_dofs_topological(V, mesh.topology.dim - 1, walls))
    form = stiffness_form(scene, V, E, nu)
    # Blocked by node (3 x 3) for the two-level cycle: a third less index data to assemble and
    # stream (the phantom's P3: assembly 2.6 -> 1.5 s, a product 0.046 -> 0.024 s; block SOR as
    # fast). AMG keeps AIJ (not measured blocked).
    A = dolfinx.fem.petsc.assemble_matrix(form, bcs=[bc], kind=None if coarse is None else PETSc.Mat.Type.BAIJ)
    A.assemble()
    indices, owned_count = bc.dof_indices()
    owned = V.tabulate_dof_coordinates()[: V.dofmap.index_map.size_local, : mesh.geometry.dim]
    start = WarmStart(mesh.comm)
    settings = SolverSettings.from_config(scene.config.get("solver"))
    settings = replace(settings, rtol=max(settings.rtol, HIGHER_DEGREE_RTOL))
    stats = stats or SolverStats("iterative")
    if coarse is None:
        solver = IterativeSolver(A, indices[:owned_count], settings, stats, rigid_body_modes(owned, mesh.comm), start)
    else:
        interpolation = dolfinx.fem.petsc.interpolation_matrix(fields[0].function_space, V)
        interpolation.assemble()  # the cycle's from here on: destroyed with it
        solver = TwoLevelSolver(A, indices[:owned_count], settings, stats, start, coarse, interpolation)
    solutions = []
    try:
        for u in fields:
            held.interpolate(u)
            start.seed(held.x.petsc_vec.array[:, None])
            b = _lifted_load(form, bc, V)
            solution = fem.Function(V)
            try:
                solver.solve(b, solution.x.petsc_vec)
            finally:
                b.destroy()
            solution.x.scatter_forward()
            solutions.append(solution)
    finally:
        solver.destroy()
    log.debug(f"higher-degree solves: {stats.iterations} iterations of {solver.name}")
    return solutions


def _lifted_load(form, bc, V) -> PETSc.Vec:
    """The right-hand side of K u = 0 with the walls held at bc's values (no body load)."""
    mesh = V.mesh
    zero = fem.form(ufl.inner(fem.Constant(mesh, np.zeros(mesh.geometry.dim)), ufl.TestFunction(V)) * ufl.dx)
    b = dolfinx.fem.petsc.assemble_vector(zero)
    dolfinx.fem.petsc.apply_lifting(b, [form], bcs=[[bc]])
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    dolfinx.fem.petsc.set_bc(b, [bc])
    return b


def mesh_shift(problem, lin: Linearisation, theta, evaluation) -> np.ndarray | None:
    """ds: how far s = (log E, nu) moves (first order, the controls following) when the
    model's observed displacements are those of the higher-degree solve at the answer;
    None where the scene has no walls to hold or a point could not be probed."""
    scene = problem.scene
    if not list(scene.config["boundary"]["loaded"]):
        return None
    start = time.perf_counter()
    E, nu = problem.params.materials(theta)
    forward = problem.forward
    factors = forward.model.solvers.factors_near(forward.coefficients(theta)[0], forward.clamped_boundary)
    solutions = higher_degree_solutions(scene, E, nu, evaluation.fields, factors)  # each state's
    V = solutions[0].function_space
    observe = problem.observation.on_space(V)
    coarse = fem.Function(V)
    parts = []  # rows one state after another
    for u, finer in zip(evaluation.fields, solutions):
        coarse.interpolate(u)
        parts.append(observe(finer.x.array) - observe(coarse.x.array))
    eps = np.concatenate(parts)
    rows = problem.misfit.statistical_rows(evaluation.y, evaluation.residual)
    ds = offset_shift(lin, np.einsum("lkd,ld->lk", rows, eps).ravel())
    log.info(f"the source mesh's own error: a degree-{V.element.basix_element.degree} solve "
             f"at the answer moves the observed points by up to {np.abs(eps).max():.3g} "
             f"({time.perf_counter() - start:.1f} s)")
    return ds

