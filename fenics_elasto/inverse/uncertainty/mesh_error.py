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

import time
from collections.abc import Sequence

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem

from fenics_elasto.inverse.linearisation import Linearisation
from fenics_elasto.inverse.misfit import FieldTerm
from fenics_elasto.inverse.uncertainty.posterior import offset_shift
from fenics_elasto.model.solvers import (DirectSolver, IterativeSolver, SolverSettings, SolverStats, TwoLevelSolver,
                                         WarmStart, rigid_body_modes)
from fenics_elasto.model.stiffness import stiffness_form
from fenics_elasto.util.budget import available_memory
from fenics_elasto.util.logs import log

# CG finds the correction the degree-3 solve makes to the interpolated answer, to this
# share of the start's residual (a share of ||b|| asked it to whatever share of b the
# correction was: a bar's mesh part came out 0.44 on one rank and 0.42 on two, 0.42 both
# at 1e-10). The phantom at rank 80: 1e-2, 1e-3, 1e-4, 1e-6 took 4, 7, 9, 14 iterations
# for a mesh part of 0.475, 0.518, 0.531, 0.530 (0.530 in 10 at 1e-6 of ||b||).
CORRECTION_RTOL = 1e-4


# An observed point whose probe of the interpolated field misses the field's own value by
# more than this share of the largest displacement: its degree-3 value cannot be trusted.
PROBE_TOLERANCE = 1e-6


# Where a factorization runs ahead, the degree-3 set-up is made beside it if its matrix
# takes at most this share of the memory free then (the phantom's: 0.46 GB).
AHEAD_MEMORY_SHARE = 0.1
# Entries per row of the degree-3 matrix, for that check: 141 on the phantom (3D, P3).
HIGHER_ROW_ENTRIES = {2: 60, 3: 150}


def mesh_error_wanted(problem) -> bool:
    """``[uncertainty] mesh``: "on", "off", or "auto" -- in 3D, where a P2 source of curved
    organs put E 2-3 % off, and in 2D where a displacement field is observed: its many
    samples make the noise part small, and the source mesh's own error inside the body
    then leads (a user's disk, exact field: E 5.015, 95 % 5.002-5.029, for 5; with the
    mesh part 4.998-5.033). Other 2D estimates on data made elsewhere were within 0.6 %
    without it, the letter's nu within 0.3 %. Never without loaded walls to hold."""
    scene = problem.scene
    mode = (scene.config.get("uncertainty") or {}).get("mesh", "auto")
    field = any(isinstance(term, FieldTerm) for term in problem.misfit.terms)
    wanted = mode == "on" or (mode == "auto" and (scene.gdim == 3 or field))
    return wanted and bool(list(scene.config["boundary"]["loaded"]))


def higher_space(fields_space: fem.FunctionSpace) -> fem.FunctionSpace:
    """Vector Lagrange elements one degree higher than ``fields_space``'s, on its mesh."""
    mesh = fields_space.mesh
    return fem.functionspace(mesh, ("Lagrange", fields_space.element.basix_element.degree + 1, (mesh.geometry.dim,)))


class HigherDegreeModel:
    """The part of the degree-(p+1) solve that does not depend on the answer, made once:
    the space (p: the fields' space's degree), the walls' DOFs, the interpolation from
    the fields' space, the observation there, and K_h's whole pattern with the regions
    whose E and nu are both known already assembled into it (``known``, at (E, nu)).
    ``solutions`` adds the other regions at the answer. An estimate whose factorization
    runs ahead makes it meanwhile (``ahead``): on the phantom (rank 80) 2.8-3.1 s of the
    degree-3 solve's 8.2 s moved beside MUMPS, which ended when it did without them; the
    estimate took 48.3 s against 51.0 s (three alternating runs each), E and the mesh part
    the same to the last digit.
    ``blocked``: K_h by node (3 x 3) for the two-level cycle; AIJ for AMG."""

    def __init__(self, scene, fields_space: fem.FunctionSpace, known: Sequence[int], E, nu, blocked: bool,
                 observation=None, V: fem.FunctionSpace | None = None):
        mesh = scene.mesh
        self.scene, self.fields_space, self.known = scene, fields_space, list(known)
        self.V = V or higher_space(fields_space)
        self.held = fem.Function(self.V)  # the walls' values; K does not depend on them, the lifted load does
        walls = scene.facets(list(scene.config["boundary"]["fixed"]) + list(scene.config["boundary"]["loaded"]))
        self.bc = fem.dirichletbc(self.held, fem.locate_dofs_topological(self.V, mesh.topology.dim - 1, walls))
        # Blocked by node for the two-level cycle: a third less index data to assemble and
        # stream (the phantom's P3: assembly 2.6 -> 1.5 s, a product 0.046 -> 0.024 s; block
        # SOR as fast). AMG keeps AIJ (not measured blocked).
        kind = PETSc.Mat.Type.BAIJ if blocked else None
        self.K = dolfinx.fem.petsc.create_matrix(stiffness_form(scene, self.V, E, nu), kind=kind)  # the whole pattern
        if self.known:
            dolfinx.fem.petsc.assemble_matrix(self.K, stiffness_form(scene, self.V, E, nu, regions=self.known),
                                              bcs=[self.bc])
        # Flushed, not final: a final assembly would squeeze the other regions' entries,
        # never set yet, out of the pattern.
        self.K.assemble(PETSc.Mat.AssemblyType.FLUSH)
        self.interpolation = None
        if blocked:
            self.interpolation = dolfinx.fem.petsc.interpolation_matrix(fields_space, self.V)
            self.interpolation.assemble()
        self.observe = None if observation is None else observation.on_space(self.V)

    @classmethod
    def ahead(cls, problem) -> HigherDegreeModel | None:
        """The set-up for ``problem``'s answer, the known regions assembled at their values;
        None where the estimate will want no degree-3 solve or its matrix would take over
        AHEAD_MEMORY_SHARE of the memory free now (it is then made at the answer)."""
        scene = problem.scene
        if not mesh_error_wanted(problem):
            return None
        space = problem.forward.model.dofs.V
        V = higher_space(space)
        dofs = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        fits = 8.0 * dofs * HIGHER_ROW_ENTRIES[scene.gdim] <= AHEAD_MEMORY_SHARE * available_memory()
        if not scene.comm.allreduce(fits, op=MPI.LAND):
            return None
        E, nu = problem.params.materials(problem.params.initial)
        known = [i for i, m in enumerate(scene.materials) if not (m.E.estimate or m.nu.estimate)]
        return cls(scene, space, known, E, nu, blocked=True, observation=problem.observation, V=V)

    def solutions(self, E, nu, fields: list[fem.Function], coarse: DirectSolver | None = None,
                  stats: SolverStats | None = None) -> list[fem.Function]:
        """The displacement in this space with the materials (E, nu) per region (the known
        ones as made), clamped where the scene is, and every loaded wall held at each
        field (several states: one each): one K and one CG for them all, each solve
        started from its field itself (interpolated: CG finds only the correction), to
        CORRECTION_RTOL of the start's residual. ``coarse``: the factors of
        the fields' own K at these materials (or near them) with the same walls clamped,
        which make CG's preconditioner a two-level cycle (model.solvers.TwoLevelSolver);
        without them, AMG (model.solvers.IterativeSolver). ``stats``: where to count the
        solves and CG iterations. K_h is the solve's from here on: call once."""
        scene, V = self.scene, self.V
        estimated = [i for i in range(len(scene.materials)) if i not in self.known]
        if estimated:
            dolfinx.fem.petsc.assemble_matrix(self.K, stiffness_form(scene, V, E, nu, regions=estimated), bcs=[self.bc])
        self.K.assemble()
        A, self.K = self.K, None
        if coarse is None and "baij" in A.getType():  # made ahead, but no factors near the answer: AMG's kind
            A.convert(PETSc.Mat.Type.AIJ)  # in place
        indices, owned_count = self.bc.dof_indices()
        start = WarmStart(scene.mesh.comm)
        settings = SolverSettings.from_config(scene.config.get("solver"))
        stats = stats or SolverStats("iterative")
        if coarse is None:
            owned = V.tabulate_dof_coordinates()[: V.dofmap.index_map.size_local, : scene.mesh.geometry.dim]
            solver = IterativeSolver(A, indices[:owned_count], settings, stats,
                                     rigid_body_modes(owned, scene.mesh.comm), start)
        else:
            interpolation, self.interpolation = self.interpolation, None  # the cycle's from here on: destroyed with it
            if interpolation is None:
                interpolation = dolfinx.fem.petsc.interpolation_matrix(self.fields_space, V)
                interpolation.assemble()
            solver = TwoLevelSolver(A, indices[:owned_count], settings, stats, start, coarse, interpolation)
        solver.converge_from_start(CORRECTION_RTOL)
        form = stiffness_form(scene, V, E, nu)
        try:
            return [self._solve(form, u, solver, start) for u in fields]
        finally:
            solver.destroy()
            log.debug(f"higher-degree solves: {stats.iterations} iterations of {solver.name}")

    def _solve(self, form, u: fem.Function, solver, start: WarmStart) -> fem.Function:
        """One field's solve: the walls held at u, started from u."""
        self.held.interpolate(u)
        start.seed(self.held.x.petsc_vec.array[:, None])
        b = _lifted_load(form, self.bc, self.V)
        solution = fem.Function(self.V)
        try:
            solver.solve(b, solution.x.petsc_vec)
        finally:
            b.destroy()
        solution.x.scatter_forward()
        return solution

    def destroy(self) -> None:
        for matrix in (self.K, self.interpolation):
            if matrix is not None:
                matrix.destroy()
        self.K = self.interpolation = None


def higher_degree_solutions(scene, E, nu, fields: list[fem.Function],
                            coarse: DirectSolver | None = None, stats: SolverStats | None = None
                            ) -> list[fem.Function]:
    """HigherDegreeModel.solutions with nothing made ahead."""
    model = HigherDegreeModel(scene, fields[0].function_space, (), E, nu, coarse is not None)
    try:
        return model.solutions(E, nu, fields, coarse, stats)
    finally:
        model.destroy()


def _lifted_load(form, bc, V) -> PETSc.Vec:
    """The right-hand side of K u = 0 with the walls held at bc's values (no body load)."""
    mesh = V.mesh
    zero = fem.form(ufl.inner(fem.Constant(mesh, np.zeros(mesh.geometry.dim)), ufl.TestFunction(V)) * ufl.dx)
    b = dolfinx.fem.petsc.assemble_vector(zero)
    dolfinx.fem.petsc.apply_lifting(b, [form], bcs=[[bc]])
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    dolfinx.fem.petsc.set_bc(b, [bc])
    return b


def readable_difference(exact: np.ndarray, coarse: np.ndarray, finer: np.ndarray) -> tuple[np.ndarray, int]:
    """(finer - coarse at the observed points, how many were left out): the model's field u
    lies in the higher space (degree p inside p + 1), so probing it there (``coarse``)
    gives its own values back (``exact``); where it does not, by PROBE_TOLERANCE of the
    largest displacement, the point's pull-back into its curved cell failed, the finer
    field's value there is as wrong, and the row is left out (zero). A user's label-map
    scene: one point of 9,806 read 9.35e4 mm for 5 mm of motion, and made intervals of
    1e-21 to 1e23."""
    scale = max(float(np.abs(exact).max(initial=0.0)), 1e-300)
    broken = np.abs(coarse - exact).max(axis=1, initial=0.0) > PROBE_TOLERANCE * scale
    return np.where(broken[:, None], 0.0, finer - coarse), int(broken.sum())


def mesh_shift(problem, lin: Linearisation, theta, evaluation,
               prepared: HigherDegreeModel | None = None) -> tuple[np.ndarray, float, float]:
    """(ds, how far the observed points move, the largest observed displacement): ds is
    how far s = (log E, nu) moves (first order, the controls following) when the model's
    observed displacements are those of the higher-degree solve at the answer (for a
    scene mesh_error_wanted says wants it). ``prepared``: HigherDegreeModel.ahead's, used
    up here (else made now)."""
    scene = problem.scene
    start = time.perf_counter()
    E, nu = problem.params.materials(theta)
    forward = problem.forward
    factors = forward.model.solvers.factors_near(forward.coefficients(theta)[0], forward.clamped_boundary)
    model = prepared or HigherDegreeModel(scene, forward.model.dofs.V, (), E, nu, factors is not None,
                                          problem.observation)
    try:
        solutions = model.solutions(E, nu, evaluation.fields, factors)  # each state's
    finally:
        model.destroy()
    V, observe = model.V, model.observe
    assert observe is not None  # made with the problem's observation
    coarse = fem.Function(V)
    parts, motion, lost = [], 0.0, 0  # rows one state after another; the largest observed displacement
    for u, finer in zip(evaluation.fields, solutions):
        coarse.interpolate(u)
        exact = problem.observation.values(u)  # the model's own: its nodes read, not probed
        part, broken = readable_difference(exact, observe(coarse.x.array), observe(finer.x.array))
        parts.append(part)
        lost += broken
        motion = max(motion, float(np.abs(exact).max(initial=0.0)))
    eps = np.concatenate(parts)
    if lost:
        log.info(f"note: the source mesh's own error: {lost} of {len(eps)} observed points left out, where the "
                 f"degree-{V.element.basix_element.degree} field could not be read (their curved cells' map)")
    rows = problem.misfit.statistical_rows(evaluation.y, evaluation.residual)
    ds = offset_shift(lin, np.einsum("lkd,ld->lk", rows, eps).ravel())
    log.info(f"the source mesh's own error: a degree-{V.element.basix_element.degree} solve "
             f"at the answer moves the observed points by up to {np.abs(eps).max():.3g} "
             f"({time.perf_counter() - start:.1f} s)")
    comm = scene.comm
    return ds, float(comm.allreduce(np.abs(eps).max(initial=0.0), op=MPI.MAX)), float(comm.allreduce(motion, op=MPI.MAX))

