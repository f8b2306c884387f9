"""Nested optimisation (method.md §4): materials outside, boundary forces inside.

Phi*(theta) = min_F Phi(theta, F) is evaluated by an inner optimisation over the
loaded-boundary forces at fixed theta, re-using one factorization. By the envelope
theorem dPhi*/dtheta is the partial derivative at the inner optimum (one adjoint
solve), so the outer loop is a bounded L-BFGS-B over the estimated constants (log E,
nu). Start: forces from iterative surface matching, materials from a scan.

Inner solvers (``[optimizer] inner``):
- ``gauss-newton`` (default while the loaded boundary has at most ``full_gn_limit``
  DOFs, and always with reduced bases): the matched displacement is linear in the
  boundary modes, J q, with J from one block solve; Levenberg-Marquardt on the
  point-to-plane residuals then needs no FE solve per iteration.
- ``lbfgs``: L-BFGS over the forces in boundary-displacement coordinates (the forces
  preconditioned by the Dirichlet-to-Neumann map), two back-solves per iteration.
- ``lbfgs-forces``: L-BFGS over the raw nodal forces, as in the paper.

With reduced bases the outer loop runs on a surrogate (``surrogate.py``, on by
default): the scan's solves span the mode fields of every material value, the
materials are optimised on that reduced-basis response (dense algebra, no
factorization), and only its optimum is solved in full -- until the optimum stops
moving. The result is always a full solve.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from fenics_elasto.errors import require
from fenics_elasto.matching import match_surface
from fenics_elasto.objective import Evaluation, InverseProblem

INNER_SOLVERS = ("auto", "gauss-newton", "lbfgs", "lbfgs-forces")


@dataclass
class Options:
    inner: str = "auto"
    inner_maxiter: int = 400
    outer_maxiter: int = 40
    outer_xtol: float = 1e-3  # the outer loop stops once a step moves log E by less (nu: a tenth of it)
    scan: int = 5  # material values per estimated constant in the initial scan
    inner_tol: float = 1e-6  # relative decrease of Phi that ends the inner loop
    full_gn_limit: int = 1500  # largest full force space for which "auto" picks Gauss-Newton
    anchor: float = 1e-4  # Gauss-Newton: pull towards the surface-matched start (see _gauss_newton)
    surrogate: bool = True  # reduced bases: outer loop on the reduced-basis response in the materials

    @classmethod
    def from_scene(cls, scene) -> "Options":
        table = dict(scene.config.get("optimizer", {}))
        known = set(cls.__dataclass_fields__)
        unknown = set(table) - known
        require(not unknown, f"{scene.path}: [optimizer]: unknown key(s) {sorted(unknown)} (have {sorted(known)})")
        inner = table.get("inner", "auto")
        require(inner in INNER_SOLVERS, f"{scene.path}: optimizer.inner: {inner!r} is not one of {INNER_SOLVERS}")
        return cls(**table)


@dataclass
class Progress:
    """Evaluations of Phi* so far, and the best one (what an interrupt returns)."""

    history: list = field(default_factory=list)
    best: tuple | None = None  # (phi, theta, controls)

    def record(self, theta, controls, phi, inner_iterations, stage):
        self.history.append({"stage": stage, "theta": list(map(float, theta)), "phi": phi, "inner": inner_iterations})
        if self.best is None or phi < self.best[0]:
            self.best = (phi, np.array(theta), controls.copy())


class NestedEstimator:
    """The nested optimisation of one InverseProblem, optionally in a reduced basis W."""

    def __init__(self, problem: InverseProblem, options: Options | None = None, say=print, basis=None):
        self.problem = problem
        self.options = options or Options()
        self.basis = basis  # W (force_dofs x r) or None: the full space
        self.say = say if problem.scene.comm.rank == 0 else (lambda *_: None)
        self.log_scale = np.array([key == "E" for _, key in problem.estimated])
        self.progress = Progress()
        self.inner_iterations = 0
        self.outer_iterations = 0
        self.surrogate_evaluations = 0
        inner = self.options.inner
        if inner == "auto":
            small = problem.force_dofs <= self.options.full_gn_limit
            inner = "gauss-newton" if basis is not None or small else "lbfgs"
        require(basis is None or inner == "gauss-newton", "reduced bases need optimizer.inner = 'gauss-newton'")
        self.inner = inner
        # Controls: q (boundary displacement d = W q) for gauss-newton; d for lbfgs;
        # the nodal forces F for lbfgs-forces.
        self.evaluate = problem.evaluate_forces if inner == "lbfgs-forces" else problem.evaluate_displacement
        self.control_scale = 1.0
        self.phi_scale = 1.0
        self.initial_phi = None  # Phi* at the initial materials (first solve until known)
        self.anchor = None  # reduced coordinates of the surface-matched boundary displacement
        self.seen = []  # (log E, nu), controls, evaluation of every Phi* solved
        self.surrogate = None
        if basis is not None and self.options.surrogate:
            from fenics_elasto.surrogate import MaterialSurrogate

            self.surrogate = MaterialSurrogate(problem, basis)

    # --- variables: log E and nu

    def to_s(self, theta):
        return np.where(self.log_scale, np.log(np.where(self.log_scale, theta, 1.0)), theta)

    def to_theta(self, s):
        return np.where(self.log_scale, np.exp(s), s)

    def boundary(self, q):
        """The loaded-boundary displacement of reduced coordinates q."""
        return q if self.basis is None else self.basis @ q

    # --- initial controls from surface matching

    def matched_boundary_displacement(self) -> np.ndarray:
        """Surface-match the matched nodes to the target; the loaded nodes' share, flat.

        Loaded nodes that are not matched start at zero displacement.
        """
        p = self.problem
        u_match = match_surface(p.matched_coords, p.matched_groups(), p.target)
        return p.on_loaded(p.load(u_match, p.matched))

    def initial_controls(self, theta, d0) -> np.ndarray:
        if self.inner == "lbfgs-forces":
            return self.problem.reaction_forces(theta, self.problem.evaluate_displacement(theta, d0).u)
        if self.basis is not None:
            return self.basis.T @ d0
        return d0

    # --- inner problems: forces at fixed materials

    def solve_inner(self, theta, controls0) -> tuple[np.ndarray, Evaluation, int]:
        if self.inner == "gauss-newton":
            controls, nit = self._gauss_newton(self.response(theta), controls0)
            ev = self.problem.evaluate_displacement(theta, self.boundary(controls), "both")
        else:
            controls, ev, nit = self._lbfgs(theta, controls0)
        self.inner_iterations += nit
        return controls, ev, nit

    def _lbfgs(self, theta, controls0):
        cache = {}

        def fun(z):
            ev = self.evaluate(theta, z * self.control_scale, "both")
            cache.clear()
            cache[z.tobytes()] = ev
            return ev.phi / self.phi_scale, ev.grad_controls * (self.control_scale / self.phi_scale)

        res = minimize(fun, controls0 / self.control_scale, jac=True, method="L-BFGS-B",
                       options={"maxiter": self.options.inner_maxiter, "maxcor": 30,
                                "ftol": self.options.inner_tol, "gtol": 1e-12})
        ev = cache.get(res.x.tobytes()) or self.evaluate(theta, res.x * self.control_scale, "both")
        return res.x * self.control_scale, ev, res.nit

    def response(self, theta) -> np.ndarray:
        """J(theta) solved in full (one factorization); a snapshot for the surrogate."""
        if self.surrogate is None:
            return self.problem.response(theta, self.basis)
        X = self.problem.response_block(theta, self.basis)
        self.surrogate.add(theta, X)
        return self.problem.matched_rows(X)

    def _gauss_newton(self, J, q):
        """Levenberg-Marquardt on the exact closest-feature curvature; x(q) = x0 + J q exactly.

        Surface distances do not see nodes sliding along the target, so a faint pull
        (``anchor`` times the mean curvature) towards the surface-matched start keeps
        the unseen, tangential part of the boundary motion where matching put it.
        """
        p = self.problem
        n, gdim, r = J.shape
        flat = J.reshape(n * gdim, r)
        q0 = self.anchor if self.anchor is not None else q.copy()
        pull = None

        def misfit(q):
            x = p.matched_coords + (flat @ q).reshape(n, gdim)
            res = p.target.residual(x)
            return x, res, 0.5 * float(np.sum(res**2)) + 0.5 * pull * float(np.sum((q - q0) ** 2))

        damping, nit = 1e-3, 0
        for nit in range(1, self.options.inner_maxiter + 1):
            x = p.matched_coords + (flat @ q).reshape(n, gdim)
            A = np.einsum("lkd,ldr->lkr", p.target.curvature_directions(x), J).reshape(-1, r)
            H = A.T @ A
            if pull is None:
                pull = self.options.anchor * float(np.mean(np.diag(H)))
                x, res, phi = misfit(q)
            H[np.diag_indices(r)] += pull
            grad = flat.T @ res.ravel() + pull * (q - q0)
            while True:  # Levenberg-Marquardt: damp until the objective decreases
                step = np.linalg.solve(H + damping * np.diag(np.diag(H)), -grad)
                x_new, res_new, phi_new = misfit(q + step)
                if phi_new < phi or damping > 1e10:
                    break
                damping *= 10.0
            if phi_new >= phi:
                break
            decrease = phi - phi_new
            q, res, phi = q + step, res_new, phi_new
            damping = max(damping / 10.0, 1e-12)
            if decrease <= self.options.inner_tol * phi:
                break
        return q, nit

    def phi_star(self, theta, controls0, stage: str):
        """Phi*(theta) and its inner optimum. A material value within 1e-3 xtol of one
        solved before is not solved again: L-BFGS-B re-evaluates its start (the best
        scan point), and near the optimum its line search can creep by 1e-9 steps,
        where Phi* is flat to the inner tolerance -- each step a factorization."""
        s = self.to_s(np.asarray(theta, float))
        for s_seen, controls, ev in self.seen:
            if np.all(np.abs(s - s_seen) < 1e-3 * self.options.outer_xtol):
                return controls, ev
        controls, ev, nit = self.solve_inner(theta, controls0)
        self.progress.record(theta, controls, ev.phi, nit, stage)
        self.say(f"  {stage:5s} {self._describe(theta)}  Phi* = {ev.phi:.6e}  ({nit} inner iterations)")
        self.seen.append((s, controls, ev))
        return controls, ev

    def _describe(self, theta) -> str:
        return "  ".join(f"{m}.{k} = {v:.5g}" for (m, k), v in zip(self.problem.estimated, theta))

    # --- the whole estimate

    def scan_points(self) -> list[np.ndarray]:
        axes = []
        for (lo, hi), log in zip(self.problem.bounds(), self.log_scale):
            n = self.options.scan if len(self.log_scale) == 1 else max(2, min(self.options.scan, 3))
            q = (np.arange(n) + 0.5) / n
            axes.append(np.exp(np.log(lo) + q * (np.log(hi) - np.log(lo))) if log else lo + q * (hi - lo))
        return [np.array(point) for point in itertools.product(*axes)]

    def run(self):
        p = self.problem
        theta0 = p.initial_theta()
        d0 = self.matched_boundary_displacement()
        controls0 = self.initial_controls(theta0, d0)
        self.anchor = controls0 if self.inner == "gauss-newton" else None
        self.control_scale = max(float(np.sqrt(np.mean(controls0**2))), 1e-300)
        if self.surrogate is not None:
            # The initial materials need no solve of their own: the scan's snapshots give Phi* there too.
            self._scan(self.scan_points(), theta0, controls0, d0)
            self.phi_scale = max(self.progress.best[0], 1e-300)
            self.initial_phi = self.surrogate_phi(self.to_s(theta0), {"q": controls0})[0] * self.phi_scale
            return self._outer_on_surrogate()
        self.phi_scale = max(self.evaluate(theta0, self.boundary(controls0)).phi, 1e-300)
        self._scan([theta0] + self.scan_points(), theta0, controls0, d0)
        self._outer_solved()

    def _scan(self, candidates, theta0, controls0, d0):
        self.say(f"scan of {len(candidates)} material values (start: surface matching; inner: {self.inner})")
        for theta in candidates:
            _, ev = self.phi_star(theta, controls0 if theta is theta0 else self.initial_controls(theta, d0), "scan")
            self.initial_phi = ev.phi if self.initial_phi is None else self.initial_phi

    def _outer_solved(self):
        """L-BFGS-B over the materials, every value solved in full."""
        _, theta_best, controls_best = self.progress.best
        warm = {"controls": controls_best}

        def objective(s):
            theta = self.to_theta(s)
            controls, ev = self.phi_star(theta, warm["controls"], "outer")
            warm["controls"] = controls
            grad_s = ev.grad_theta * np.where(self.log_scale, theta, 1.0)
            return ev.phi / self.phi_scale, grad_s / self.phi_scale

        last = {"s": self.to_s(theta_best)}
        xtol = self.xtol()

        def count(intermediate_result):
            self.outer_iterations += 1
            settled = np.all(np.abs(intermediate_result.x - last["s"]) < xtol)
            last["s"] = intermediate_result.x.copy()
            if settled:
                raise StopIteration  # more digits of E would cost factorizations, not accuracy

        self.say("outer L-BFGS-B over the materials (envelope gradient)")
        minimize(objective, self.to_s(theta_best), jac=True, method="L-BFGS-B", bounds=self.s_bounds(), callback=count,
                 options={"maxiter": self.options.outer_maxiter, "ftol": 1e-10, "gtol": 1e-7})

    def xtol(self) -> np.ndarray:
        return self.options.outer_xtol * np.where(self.log_scale, 1.0, 0.1)

    def s_bounds(self) -> list:
        return [tuple(self.to_s(np.array(b))) for b in self.problem.bounds()]

    # --- the outer loop on the reduced-basis response in the materials

    def surrogate_phi(self, s, warm):
        """Phi*(theta) and its envelope gradient in s from the surrogate's J(theta): no FE solve."""
        theta = self.to_theta(s)
        J, dJ = self.surrogate.response(theta)
        q, _ = self._gauss_newton(J, warm["q"])
        warm["q"] = q
        self.surrogate_evaluations += 1
        n, gdim, r = J.shape
        residual = self.problem.target.residual(self.problem.matched_coords + (J.reshape(-1, r) @ q).reshape(n, gdim))
        grad_theta = np.array([np.sum(residual * (dJk @ q)) for dJk in dJ])
        phi = 0.5 * float(np.sum(residual**2))
        return phi / self.phi_scale, grad_theta * np.where(self.log_scale, theta, 1.0) / self.phi_scale

    def _outer_on_surrogate(self):
        """Optimise the materials on the surrogate, solve its optimum in full (a new
        snapshot), repeat until the optimum lands where a full solve already is."""
        self.say(f"outer L-BFGS-B on the reduced-basis response in the materials ({self.surrogate.size} directions)")
        xtol = self.xtol()
        for _ in range(self.options.outer_maxiter):
            _, theta_best, controls_best = self.progress.best
            warm = {"q": controls_best}
            res = minimize(self.surrogate_phi, self.to_s(theta_best), args=(warm,), jac=True, method="L-BFGS-B",
                           bounds=self.s_bounds(), options={"maxiter": 100, "ftol": 1e-12, "gtol": 1e-9})
            self.outer_iterations += 1
            theta = self.to_theta(res.x)
            self.say(f"  surrogate optimum {self._describe(theta)}  (equation residual "
                     f"{self.surrogate.residual(theta):.1e}, {res.nfev} evaluations)")
            if any(np.all(np.abs(res.x - s_seen) < xtol) for s_seen, _, _ in self.seen):
                return
            self.phi_star(theta, warm["q"], "outer")

    def final(self):
        """(theta, forces, evaluation) of the best point seen."""
        _, theta, controls = self.progress.best
        if self.inner == "lbfgs-forces":
            return theta, controls, self.problem.evaluate_forces(theta, controls)
        ev = self.problem.evaluate_displacement(theta, self.boundary(controls))
        return theta, self.problem.reaction_forces(theta, ev.u), ev


def check_overlap(problem: InverseProblem) -> float:
    """Refuse a target that does not lie on the matched surface; return Phi at u = 0."""
    scene = problem.scene
    x = problem.matched_coords
    residual = problem.target.residual(x)
    size = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
    distance = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    require(distance < 0.25 * size,
            f"{scene.path}: the target does not overlap the matched surface "
            f"(rms distance {distance:.3g} vs matched size {size:.3g}); is it in the same units and frame?")
    return 0.5 * float(np.sum(residual**2))


def estimate(problem: InverseProblem, options: Options | None = None, say=print, basis: np.ndarray | None = None):
    """Run the nested optimisation -> (result dict, displacement, forces).

    On Ctrl-C it stops and returns the best result so far (``interrupted``: true).
    """
    start = time.perf_counter()
    scene = problem.scene
    require(problem.estimated, f"{scene.path}: nothing to estimate: mark at least one E or nu with estimate = true")
    fixed_E = [m.name for m in scene.materials if not m.E.estimate]
    require(fixed_E, f"{scene.path}: every E is estimated, but with unknown boundary forces only ratios of E "
                     "are identifiable (scaling K and F together leaves u unchanged): fix one region's E as the reference")
    phi_undeformed = check_overlap(problem)
    estimator = NestedEstimator(problem, options or Options.from_scene(scene), say, basis)
    interrupted = False
    try:
        estimator.run()
    except KeyboardInterrupt:
        interrupted = True
        estimator.say("interrupted: writing the best result so far")
        require(estimator.progress.best is not None, "interrupted before the first evaluation: nothing to write")
    theta, forces, final = estimator.final()
    E, nu = problem.materials(theta)
    comm = scene.comm
    result = {
        "materials": {m.name: {"E": float(E[i]), "nu": float(nu[i])} for i, m in enumerate(scene.materials)},
        "estimated": [f"{m}.{k}" for m, k in problem.estimated],
        "objective": {"undeformed": phi_undeformed, "initial": estimator.initial_phi, "final": final.phi},
        "surface_distance": problem.surface_distance(final.residual),
        "iterations": {"outer": estimator.outer_iterations, "inner": estimator.inner_iterations,
                       "evaluations": len(estimator.progress.history),
                       "surrogate_evaluations": estimator.surrogate_evaluations},
        "factorizations": problem.model.factorizations,
        "solves": {"forward": problem.forward_solves, "adjoint": problem.adjoint_solves},
        "dofs": problem.model.num_dofs,
        "force_dofs": problem.force_dofs,
        "rank": None if basis is None else int(basis.shape[1]),
        "inner_solver": estimator.inner,
        "degree": scene.degree,
        "mpi_ranks": comm.size,
        "interrupted": interrupted,
        "wall_time_s": round(time.perf_counter() - start, 3),
        "history": estimator.progress.history,
    }
    return result, final.u, forces


def run_estimate(problem_path: Path, out: Path, overrides=()) -> dict:
    """The ``estimate`` command: load, estimate, write result.json, pictures and fields."""
    from fenics_elasto.io import write_point_csv, write_solution
    from fenics_elasto.render import plot_convergence, target_polydata
    from fenics_elasto.scene import load_scene

    scene = load_scene(problem_path, overrides)
    problem = InverseProblem(scene)
    basis = reduced_basis(problem)
    say = (lambda text: print(text, flush=True)) if scene.comm.rank == 0 else (lambda *_: None)
    say(f"estimate {', '.join(f'{m}.{k}' for m, k in problem.estimated)}: {problem.model.num_dofs} dofs, "
        f"{problem.force_dofs} force dofs" + (f" reduced to rank {basis.shape[1]}" if basis is not None else "")
        + f", {problem.matched.total} matched nodes")
    result, u, forces = estimate(problem, say=say, basis=basis)
    target = target_polydata(problem) if scene.comm.rank == 0 else None
    out = Path(out)
    write_solution(out, scene, u, result, target=target, title=_title(result))
    points = problem.loaded.gather(problem.loaded.coords)
    if scene.comm.rank == 0:
        target.save(out / "target.vtp")
        plot_convergence(result, out / "convergence.png")
        write_point_csv(out / "forces.csv", points, forces.reshape(len(points), -1), "f")
    say(f"{_title(result)}; rms distance {result['surface_distance']['rms']:.3g}, "
        f"{result['factorizations']} factorizations, {result['wall_time_s']:.1f} s -> {out}")
    return result


def reduced_basis(problem: InverseProblem) -> np.ndarray | None:
    """W from the scene's [reduction] table (bases file and rank), or None."""
    from fenics_elasto.reduction import load_bases

    scene = problem.scene
    table = scene.config.get("reduction")
    if not table:
        return None
    require(isinstance(table, dict) and "bases" in table, f"{scene.path}: [reduction] needs bases = \"file.npz\"")
    unknown = set(table) - {"bases", "rank"}
    require(not unknown, f"{scene.path}: [reduction]: unknown key(s) {sorted(unknown)}")
    rank = table.get("rank")
    require(rank is None or (isinstance(rank, int) and rank >= 1), f"{scene.path}: reduction.rank must be an integer >= 1")
    return load_bases(scene.path.parent / table["bases"], problem, rank)


def _title(result: dict) -> str:
    parts = []
    for name in result["estimated"]:
        material, key = name.split(".")
        parts.append(f"{name} = {result['materials'][material][key]:.4g}")
    return "estimate: " + ", ".join(parts)
