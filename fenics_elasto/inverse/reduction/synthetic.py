"""Training examples without scans: smooth random motions of the scene's own loaded walls.

Reduced force bases must span the wall motions a patient will show; example scans are
rarely at hand, and motions a toolkit can easily prescribe (affine inflations and
shifts) are too narrow: on a real prostate, bases from affine examples put E 52 % off,
while bases from walls bulging under pressure got it within 4 %. So three kinds:

1. **Affine wall motion**, all of it: per wall the gdim shifts and gdim^2 linear maps
   about its centre (inflation, stretch, shear, rotation) are the first columns of the
   bases (``affine_basis``), kept before any PCA -- they are what organs do first, and
   a few random affine examples would leave gaps in that span.
2. **Pressure and traction** (physically plausible, two thirds of the examples): a
   smooth random pressure p on each loaded wall (its own sign and size per wall: one
   organ fills while another empties), plus a smaller smooth random tangential
   traction, pushed through the forward model with the estimated materials drawn over
   their bounds, at a few material levels (``levels``). The middle level is factorized
   and solves its examples as one block; the others' examples are solved together by
   CG on its factors (model.block_cg), or factorized each where that would not pay.
3. **Smooth random displacement modes** (a third): per wall a Gaussian-process sample
   (squared-exponential kernel of length ``length``; random Fourier features).

Every example is scaled to rms wall displacement ``amplitude``: in an uncentred PCA
(reduction.pca) this makes the kinds count alike, and it matters when synthetic
examples join scanned ones. Defaults from the scene: ``length`` half the loaded walls'
mean extent, ``amplitude`` 2 % of the scene's diameter.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import ufl
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
from dolfinx import fem

from fenics_elasto.model.block_cg import LockstepCG, cg_steps_bound
from fenics_elasto.model.dofs import times_block
from fenics_elasto.model.solvers import DirectSolver, SolverError, coefficient_spread
from fenics_elasto.util.errors import require
from fenics_elasto.geometry.fields import SmoothFields
from fenics_elasto.util.logs import log

# The solved examples' relative residual: each is one of many wall motions whose leading
# directions become the bases, and what rank 80 leaves of 120 examples' energy (0.03 %
# on the default phantom) is far above what a residual of 1e-4 leaves in one. Measured
# (train --synthetic 120 --rank 80, examples to 1e-4 against 1e-6): on the default
# phantom with compressed factors the bases' largest principal angle was 8e-6, with
# one refinement step per block fewer; on the 32k-DOF phantom with CG + AMG 2.8e-4, in
# 40 s instead of 69 s; the estimates from either the same E to 4 digits.
EXAMPLE_RTOL = 1e-4


@dataclass
class Generator:
    """Settings of the synthetic examples (stored with the bases for provenance)."""

    count: int
    seed: int = 0
    length: float | None = None  # mesh units; None: from the scene
    amplitude: float | None = None  # mesh units; None: from the scene
    levels: int = 3  # material values shared by the solved examples (one factorization: _borrowed_walls)
    solved_share: float = 2 / 3  # pressure/traction examples; the rest are displacement modes

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("count", "seed", "length", "amplitude", "levels", "solved_share")}


def smooth_fields(points: np.ndarray, count: int, length: float, rng, components: int = 1) -> np.ndarray:
    """(count, n, components) Gaussian-process samples of length ``length`` at the points."""
    return SmoothFields(count, components, points.shape[1], length, rng)(points)


class WallLoads:
    """Load vectors of pressure and traction fields on the loaded walls, as matrices
    assembled once: f = B p (pressure p, scalar nodal values) and f = M t (traction t)."""

    def __init__(self, forward):
        model = forward.model
        mesh, V = model.dofs.V.mesh, model.dofs.V
        fdim = mesh.topology.dim - 1
        facets = np.sort(forward.scene.facets(forward.scene.loaded)).astype(np.int32)
        tags = dolfinx.mesh.meshtags(mesh, fdim, facets, np.ones(len(facets), np.int32))
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)(1)
        self.Q = fem.functionspace(mesh, ("Lagrange", forward.scene.degree))
        n, v = ufl.FacetNormal(mesh), ufl.TestFunction(V)
        self.pressure = _assembled(fem.form(-ufl.TrialFunction(self.Q) * ufl.inner(n, v) * ds))
        self.traction = _assembled(fem.form(ufl.inner(ufl.TrialFunction(V), v) * ds))
        gdim = mesh.geometry.dim
        self.q_points = self.Q.tabulate_dof_coordinates()[: self.Q.dofmap.index_map.size_local, :gdim]
        self.v_points = model.dofs.dof_coords[: model.dofs.n_owned_blocks]

    def block(self, matrix: PETSc.Mat, columns: np.ndarray, model) -> PETSc.Mat:
        """matrix @ columns (owned rows of the trial space) as a dense Mat in V's layout."""
        out = model.dofs.dense(columns.shape[1])
        out.getDenseArray()[:] = times_block(matrix, columns)
        return out


def _assembled(form) -> PETSc.Mat:
    M = dolfinx.fem.petsc.assemble_matrix(form)
    M.assemble()
    return M


def default_scales(problem) -> tuple[float, float]:
    """(length, amplitude) from the scene: half the loaded walls' mean extent, 2 % of
    the scene's diameter."""
    forward = problem.forward
    points = forward.loaded.gather(forward.loaded.coords)
    groups = problem.loaded_groups()
    extents = [np.ptp(points[groups == g], axis=0).max() for g in np.unique(groups)]
    everything = problem.model.dofs.comm.allgather(problem.model.dofs.dof_coords[: problem.model.dofs.n_owned_blocks])
    stacked = np.concatenate(everything)
    diameter = float(np.linalg.norm(np.ptp(stacked, axis=0)))
    return 0.5 * float(np.mean(extents)), 0.02 * diameter


def affine_basis(problem) -> np.ndarray:
    """(force_dofs, at most walls x (gdim + gdim^2)) orthonormal: every affine motion of
    each loaded wall on its own, u = b + A (x - centre), in that order; those a wall
    cannot show are left out (a flat wall has no extent along its normal: its columns
    there vanish to round-off, and QR had made each a direction of pure noise, kept first
    in the bases -- a bar's bases on one rank and on two then differed by 44 degrees)."""
    forward = problem.forward
    points = forward.loaded.gather(forward.loaded.coords)
    groups = problem.loaded_groups()
    gdim = points.shape[1]
    columns = []
    for g in np.unique(groups):
        rows = groups == g
        local = points[rows] - points[rows].mean(axis=0)
        for i in range(gdim):
            for part in [np.ones(rows.sum())] + [local[:, j] for j in range(gdim)]:
                column = np.zeros(points.shape)
                column[rows, i] = part
                columns.append(column.ravel())
    return orthonormal_in_order(np.stack(columns, axis=1))


def orthonormal_in_order(A: np.ndarray, tol: float = 1e-8) -> np.ndarray:
    """Orthonormal columns spanning A's, taken in A's order (Gram-Schmidt, twice for
    round-off); a column with less than ``tol`` of A's largest column left once the
    earlier ones are taken out adds no direction."""
    kept: list[np.ndarray] = []
    scale = max(float(np.linalg.norm(A, axis=0).max(initial=0.0)), 1e-300)
    for a in A.T:
        v = a.copy()
        for _ in range(2):
            for q in kept:
                v -= (q @ v) * q
        if np.linalg.norm(v) > tol * scale:
            kept.append(v / np.linalg.norm(v))
    return np.stack(kept, axis=1) if kept else np.zeros((len(A), 0))


def synthetic_examples(problem, generator: Generator) -> np.ndarray:
    """(force_dofs, count) loaded-wall displacements of ``generator.count`` examples."""
    require(generator.count >= 1, f"the number of synthetic examples (--synthetic) must be >= 1, got {generator.count}")
    forward = problem.forward
    rng = np.random.default_rng(generator.seed)
    length, amplitude = default_scales(problem)
    length = generator.length or length
    amplitude = generator.amplitude or amplitude
    require(length > 0 and amplitude > 0,
            f"the length and amplitude (--length, --amplitude) must be > 0, got {length} and {amplitude}")
    points = forward.loaded.gather(forward.loaded.coords)
    groups = problem.loaded_groups()
    solved = int(round(generator.solved_share * generator.count))
    modes = generator.count - solved
    log.info(f"synthetic examples: {solved} pressure/traction (solved at {min(generator.levels, max(solved, 1))} "
             f"material values), {modes} displacement modes; length {length:.3g}, amplitude {amplitude:.3g}")
    columns = [pressure_examples(problem, solved, length, rng, generator.levels)] if solved else []
    if modes > 0:
        columns.append(displacement_modes(points, groups, modes, length, rng).reshape(modes, -1).T)
    data = np.concatenate(columns, axis=1)
    rms = np.sqrt(np.mean(data**2, axis=0))
    return data * (amplitude / np.where(rms > 0, rms, 1.0))


def displacement_modes(points, groups, count: int, length: float, rng) -> np.ndarray:
    """(count, n, gdim): an independent smooth random vector field on each wall."""
    out = np.zeros((count,) + points.shape)
    for g in np.unique(groups):
        rows = groups == g
        out[:, rows] = smooth_fields(points[rows], count, length, rng, components=points.shape[1])
    return out


def material_levels(problem, count: int, rng) -> list[np.ndarray]:
    """``count`` values of the estimated constants spread over their bounds (log E)."""
    params = problem.params
    low, high = np.array(params.bounds, float).reshape(len(params), 2).T
    s_low, s_high = params.to_s(low), params.to_s(high)
    # A Latin hypercube: each constant's range in ``count`` strata, one value in each.
    quantiles = (np.arange(count)[:, None] + rng.uniform(0.2, 0.8, (count, len(params)))) / count
    quantiles = rng.permuted(quantiles, axis=0)
    return [params.to_theta(s_low + q * (s_high - s_low)) for q in quantiles]


def pressure_examples(problem, count: int, length: float, rng, levels: int) -> np.ndarray:
    """(force_dofs, count): walls moved by random smooth pressure and traction fields,
    solved through the forward model at a few material values (one factorization: the
    middle value's; _borrowed_walls).
    Every random draw comes first, in the order the examples were always drawn in, so
    that the middle level's factorization runs beside the fields' evaluation and the
    loads' assembly (serial: solvers.SolverCache.ahead)."""
    forward, model = problem.forward, problem.model
    loads = WallLoads(forward)
    q_groups = _group_of(problem, loads.q_points)
    v_groups = _group_of(problem, loads.v_points)
    pressure = SmoothFields(count, 1, forward.gdim, length, rng)
    traction = SmoothFields(count, forward.gdim, forward.gdim, length, rng)
    # each wall its own sign and size: one fills, one empties. Every rank's walls, not its own: a
    # rank without a wall drew fewer sizes, and its material levels then differed (a bar's loaded
    # end on one rank of two: MUMPS refused blocks of 4 and 5 columns, INFOG(1) = -22)
    walls = np.unique(np.concatenate(model.dofs.V.mesh.comm.allgather(np.unique(q_groups[q_groups >= 0]))))
    sizes = [rng.normal(0.0, 1.0, count)[:, None] for _ in walls]
    thetas = material_levels(problem, min(levels, count), rng)
    first = _middle(problem, thetas)  # factorized; the others borrow its factors (_borrowed_walls)
    out = np.zeros((forward.force_dofs, count))
    with model.solvers.one_at_a_time():
        model.factorize_ahead(forward.coefficients(thetas[first])[0], forward.clamped)
        p = wall_fields(loads.q_points, q_groups, pressure)[..., 0]
        t = 0.3 * wall_fields(loads.v_points, v_groups, traction)
        for g, size in zip(walls, sizes):
            p[:, q_groups == g] += size
            t[:, v_groups == g] *= np.abs(size)[..., None]
        P = loads.block(loads.pressure, p.T, model)
        T = loads.block(loads.traction, t.reshape(count, -1).T, model)
        P.axpy(1.0, T)
        rhs = P.getDenseArray()
        rhs[forward.clamped] = 0.0
        level_of = np.arange(count) % len(thetas)
        chosen = [np.flatnonzero(level_of == level) for level in range(len(thetas))]
        out[:, chosen[first]], column_seconds = _solved_walls(problem, thetas[first], rhs[:, chosen[first]])
        log.info(f"  {len(chosen[first])} pressure/traction examples at {problem.params.describe(thetas[first])}")
        others = [level for level in range(len(thetas)) if level != first]
        solved = _borrowed_walls(problem, thetas[first], [(thetas[level], rhs[:, chosen[level]]) for level in others],
                                 column_seconds)
        for level, walls in zip(others, solved):
            out[:, chosen[level]] = walls
        for M in (P, T):
            M.destroy()
    return out


def _middle(problem, thetas: list[np.ndarray]) -> int:
    """The level nearest the middle of the others (in s = log E, nu): the one whose
    factors precondition them best."""
    s = np.array([problem.params.to_s(theta) for theta in thetas])
    return int(np.argmin([np.abs(s - si).max(axis=0).sum() for si in s]))


def _solved_walls(problem, theta, rhs: np.ndarray) -> tuple[np.ndarray, float]:
    """(force_dofs, k): the loaded walls' motion under the loads ``rhs`` (owned rows, k
    columns) at the materials theta, to EXAMPLE_RTOL; and the seconds a column took per
    pass over the factors (their solves timed alone)."""
    forward, model = problem.forward, problem.model
    B, X = model.dofs.dense(rhs.shape[1]), model.dofs.dense(rhs.shape[1])
    B.getDenseArray()[:] = rhs
    with model.factorize(forward.coefficients(theta)[0], forward.clamped).loosened(EXAMPLE_RTOL) as solver:
        solver.ready()
        start, steps = time.perf_counter(), model.stats.iterations
        solver.solve_many(B, X)
        passes = 1 + model.stats.iterations - steps  # refinement steps apply the factors again
        column_seconds = (time.perf_counter() - start) / (passes * rhs.shape[1])
    walls = _walls(problem, X.getDenseArray())
    for M in (B, X):
        M.destroy()
    return walls, column_seconds


def _borrowed_walls(problem, first: np.ndarray, levels: list[tuple[np.ndarray, np.ndarray]],
                    column_seconds: float) -> list[np.ndarray]:
    """Each level's walls (``_solved_walls``: its theta, its loads) by CG on the factors
    of the ``first`` level's K, all levels' columns one block (``_lockstep``): one
    factorization for the whole training, where CG's bound on the steps, at
    ``column_seconds`` per column and step, costs less than factorizing each level.
    Each level factorized as before otherwise."""
    solved = _lockstep(problem, first, levels, column_seconds) if levels else None
    if solved is not None:
        return solved
    solved = []
    for theta, rhs in levels:
        solved.append(_solved_walls(problem, theta, rhs)[0])
        log.info(f"  {rhs.shape[1]} pressure/traction examples at {problem.params.describe(theta)}")
    return solved


def _lockstep(problem, first: np.ndarray, levels: list[tuple[np.ndarray, np.ndarray]],
              column_seconds: float) -> list[np.ndarray] | None:
    """``_borrowed_walls`` by lock-step CG on the first level's factors (model.block_cg):
    on the default phantom (116k DOFs) the levels E 203.5 and 3.48 on the factors at 23.2
    took 10 steps together, where each refactorization took 10-13 s. None with CG + AMG
    (no factors), where CG would cost more than the factorizations it saves (predicted,
    or at the rate seen), or where it did not converge."""
    forward, model = problem.forward, problem.model
    c0 = forward.coefficients(first)[0]
    base = model.solvers.factors_near(c0, forward.clamped)
    coefficients = [forward.coefficients(theta)[0] for theta, _ in levels]
    spreads = [coefficient_spread(c, c0) for c in coefficients]
    known = [spread for spread in spreads if spread is not None]
    if not isinstance(base, DirectSolver) or len(known) < len(spreads):
        return None
    steps, budget = cg_steps_bound(max(known), EXAMPLE_RTOL), len(levels) * base.seconds
    predicted = steps * sum(rhs.shape[1] for _, rhs in levels) * column_seconds
    if not lockstep_pays(predicted, budget):
        log.info(f"  each level factorized: CG on the first's factors would take up to {predicted:.0f} s, "
                 f"the factorizations {budget:.0f} s")
        return None
    systems = [(model.solvers.stiffness(c, forward.clamped), rhs) for c, (_, rhs) in zip(coefficients, levels)]
    try:  # the stiffness matrices go whatever happens
        solutions, steps = LockstepCG(base, model.dofs, systems, EXAMPLE_RTOL).solve(steps, budget)
    except SolverError as why:
        log.info(f"  {why}: each level factorized instead")
        return None
    finally:
        for K, _ in systems:
            K.destroy()
    for theta, rhs in levels:
        log.info(f"  {rhs.shape[1]} pressure/traction examples at {problem.params.describe(theta)} "
                 f"(CG on the factors at {problem.params.describe(first)}: {steps} steps)")
    return [_walls(problem, X) for X in solutions]


def lockstep_pays(predicted: float, budget: float) -> bool:
    """Whether CG's predicted seconds stay below the factorizations' (``budget``): at
    rank 80 (120 examples) CG's 54 columns do, at rank 240 (400) its 534 do not."""
    return predicted < budget


def _walls(problem, X: np.ndarray) -> np.ndarray:
    """(force_dofs, k): the loaded walls' part of solutions X (owned rows, k columns)."""
    forward = problem.forward
    rows = forward.loaded.dofs(problem.model.dofs.bs).ravel()
    fields = X[rows].reshape(len(forward.loaded), forward.gdim * X.shape[1])
    return forward.loaded.gather(fields).reshape(-1, X.shape[1])


def wall_fields(points: np.ndarray, groups: np.ndarray, fields: SmoothFields) -> np.ndarray:
    """(count, n, components): the drawn smooth random ``fields`` at the nodes on a wall
    (``groups`` >= 0), 0 elsewhere -- the wall-load matrices see nothing else, and the
    fields are evaluated only where they act (the default phantom: 12 % of the nodes)."""
    on_wall = groups >= 0
    values = fields(points[on_wall])
    out = np.zeros((values.shape[0], len(points), values.shape[2]))
    out[:, on_wall] = values
    return out


def _group_of(problem, points: np.ndarray) -> np.ndarray:
    """Index into scene.loaded of the wall each point (a node) lies on, -1 elsewhere."""
    from scipy.spatial import cKDTree

    forward = problem.forward
    wall = forward.loaded.gather(forward.loaded.coords)
    gap, nearest = cKDTree(wall).query(points)
    scale = max(1.0, float(np.abs(wall).max()))
    return np.where(gap < 1e-9 * scale, problem.loaded_groups()[nearest], -1)
