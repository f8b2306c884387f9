"""The misfit Phi(theta, F) and its hand-derived adjoint gradients (method.md §2-3).

    forward:  K u = P F                   adjoint:  K w = Q^T r
    dPhi/dF = P^T w                       dPhi/dtheta_k = -w^T (dK/dtheta_k) u

K is symmetric, so one factorization serves both solves. theta are the estimated
material constants (E_m, nu_m) in the order of ``Scene.estimated()``; F is the flat
vector of nodal forces on the loaded nodes, in global node order, on every rank.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from petsc4py import PETSc

from fenics_elasto.elasticity import ElasticModel, lame_jacobian
from fenics_elasto.errors import require
from fenics_elasto.scene import Scene
from fenics_elasto.surface import Target, load_target


@dataclass
class Evaluation:
    phi: float
    u: object  # dolfinx Function
    residual: np.ndarray  # (n_matched, gdim), global order
    grad_controls: np.ndarray | None = None  # dPhi/dF or dPhi/dd
    grad_theta: np.ndarray | None = None


class InverseProblem:
    """Forward and adjoint solves of one scene with unknown loaded-node forces."""

    def __init__(self, scene: Scene, model: ElasticModel | None = None, target: Target | None | bool = None):
        """``target``: a Target, None to read the scene's [target], False for none (training)."""
        require(scene.loaded, f"{scene.path}: boundary.loaded is empty: the unknown forces need a loaded boundary")
        require(scene.matched, f"{scene.path}: boundary.matched is empty: nothing to compare with the target")
        self.scene = scene
        self.model = model or ElasticModel(scene)
        self.gdim = scene.gdim
        self.estimated = scene.estimated()
        self.clamped = self.model.clamped_dofs(scene.fixed)
        self.clamped_boundary = self.model.clamped_dofs(scene.fixed + scene.loaded)
        self.loaded = self.model.node_set(scene.loaded, exclude_groups=scene.fixed)
        self.matched = self.model.node_set(scene.matched, vertices_only=scene.match_vertices_only)
        self.matched_coords = self.matched.gather(self.matched.coords)
        self.target = load_target(scene, self.matched_coords, self.matched_groups()) if target is None else target
        self.forward_solves = 0
        self.adjoint_solves = 0

    @property
    def force_dofs(self) -> int:
        return self.loaded.total * self.gdim

    def matched_groups(self) -> np.ndarray:
        """Index into scene.matched of each matched node's (first) group, canonical order."""
        return self._groups_of(self.matched, self.scene.matched, self.scene.match_vertices_only)

    def loaded_groups(self) -> np.ndarray:
        """Index into scene.loaded of each loaded node's (first) group, canonical order."""
        return self._groups_of(self.loaded, self.scene.loaded)

    def _groups_of(self, nodes, groups, vertices_only=False) -> np.ndarray:
        group = np.full(len(nodes), -1)
        for i, name in reversed(list(enumerate(groups))):
            group[np.isin(nodes.blocks, self.model.boundary_blocks([name], vertices_only))] = i
        return nodes.gather(group)

    # --- parameters

    def materials(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(E, nu) of every region with the estimated entries taken from theta."""
        values = {"E": [m.E.value for m in self.scene.materials], "nu": [m.nu.value for m in self.scene.materials]}
        names = [m.name for m in self.scene.materials]
        for value, (material, key) in zip(np.atleast_1d(theta), self.estimated):
            values[key][names.index(material)] = float(value)
        return np.array(values["E"]), np.array(values["nu"])

    def initial_theta(self) -> np.ndarray:
        return np.array([getattr(self.scene.material(m), k).value for m, k in self.estimated])

    def bounds(self) -> list[tuple[float, float]]:
        return [getattr(self.scene.material(m), k).bounds for m, k in self.estimated]

    # --- solves

    def load(self, values: np.ndarray, nodes=None):
        """A Function holding per-node rows (global order) on ``nodes`` (default: loaded)."""
        nodes = nodes or self.loaded
        f = self.model.function("load")
        f.x.array.reshape(-1, self.model.bs)[nodes.blocks] = nodes.local(np.reshape(values, (-1, self.gdim)))
        return f

    def deformed_matched(self, u) -> np.ndarray:
        """Positions v_l + u_l of the matched nodes, global order, on every rank."""
        disp = u.x.array.reshape(-1, self.model.bs)[self.matched.blocks]
        return self.matched_coords + self.matched.gather(disp)

    def _misfit(self, u) -> Evaluation:
        residual = self.target.residual(self.deformed_matched(u))
        return Evaluation(0.5 * float(np.sum(residual**2)), u, residual)

    def _adjoint(self, theta, ev: Evaluation, clamped):
        """w with K w = Q^T r (zero on ``clamped``), and the Function holding Q^T r."""
        E, nu = self.materials(theta)
        self.adjoint_solves += 1
        r = self.load(ev.residual, self.matched)
        return self.model.solve(E, nu, clamped, r.x.petsc_vec), r

    def on_loaded(self, f) -> np.ndarray:
        """Rows of a Function at the loaded nodes, global order, flat."""
        return self.loaded.gather(f.x.array.reshape(-1, self.model.bs)[self.loaded.blocks]).ravel()

    # --- the paper's coordinates: nodal forces F

    def evaluate_forces(self, theta, forces, gradient: str = "") -> Evaluation:
        """Phi(theta, F) and, on request, dPhi/dF ("controls"), dPhi/dtheta ("theta"), or "both"."""
        E, nu = self.materials(theta)
        self.forward_solves += 1
        f = self.load(forces)
        ev = self._misfit(self.model.solve(E, nu, self.clamped, f.x.petsc_vec))
        if gradient:
            w, _ = self._adjoint(theta, ev, self.clamped)
            ev.grad_controls = self.on_loaded(w)  # P^T w
            ev.grad_theta = self.material_gradient(theta, ev.u, w)
        return ev

    # --- preconditioned coordinates: the loaded-boundary displacement d the forces produce

    def evaluate_displacement(self, theta, d, gradient: str = "") -> Evaluation:
        """Phi as a function of the loaded nodes' displacement d (a bijection with F at fixed theta).

        u solves K u = 0 with u = d on the loaded nodes; F = P^T K u. Optimising over d
        is optimising over F preconditioned by the boundary's Dirichlet-to-Neumann map:
        the same Phi*, far better conditioned. Gradients:
            dPhi/dd = (Q^T r)_B - (K w)_B,   K_D w = Q^T r (w = 0 on B)
            dPhi/dtheta_k = -w^T dK/dtheta_k u
        """
        E, nu = self.materials(theta)
        self.forward_solves += 1
        g = self.load(d)
        ev = self._misfit(self.model.solve(E, nu, self.clamped_boundary, None, prescribed=g))
        if gradient:
            w, r = self._adjoint(theta, ev, self.clamped_boundary)
            Kw = self.model.function("Kw")
            self.model.apply_stiffness(E, nu, w.x.petsc_vec, Kw.x.petsc_vec)
            ev.grad_controls = self.on_loaded(r) - self.on_loaded(Kw)
            ev.grad_theta = self.material_gradient(theta, ev.u, w)
        return ev

    def response(self, theta, basis: np.ndarray | None = None) -> np.ndarray:
        """J (n_matched, gdim, r): matched-node displacement per unit of each boundary mode."""
        return self.matched_rows(self.response_block(theta, basis))

    def response_block(self, theta, basis: np.ndarray | None = None) -> np.ndarray:
        """X (owned DOFs, r): the displacement field of each boundary mode.

        The loaded boundary moves by d = W q (W: force_dofs x r, orthonormal columns;
        None means the identity, the full space) and the interior follows from K_D u = 0,
        so the matched displacement is exactly J q. The r right-hand sides
        [-K W on free rows, W on the loaded rows] go through the one factorization of
        K_D as a dense block (MatMatSolve).
        """
        model = self.model
        E, nu = self.materials(theta)
        factor = model.factorize(E, nu, self.clamped_boundary)
        G = self.lift(basis)
        K = model.stiffness(E, nu)
        rhs = K.matMult(G)
        block = rhs.getDenseArray()
        block *= -1.0
        block[self.clamped_boundary] = G.getDenseArray()[self.clamped_boundary]
        X = model.dense(G.getSize()[1])
        factor.solve_many(rhs, X)
        out = X.getDenseArray().copy()
        for M in (G, K, rhs, X):
            M.destroy()
        return out

    def lift(self, basis: np.ndarray | None = None) -> PETSc.Mat:
        """The boundary modes as fields: W on the loaded DOFs, zero elsewhere (dense, owned rows)."""
        W = np.eye(self.force_dofs) if basis is None else basis
        r = W.shape[1]
        G = self.model.dense(r)
        rows = self.loaded.dofs(self.model.bs).ravel()
        G.getDenseArray()[rows] = self.loaded.local(W.reshape(self.loaded.total, self.gdim * r)).reshape(-1, r)
        return G

    def matched_rows(self, X: np.ndarray) -> np.ndarray:
        """(n_matched, gdim, k) global: the matched nodes' rows of owned-DOF columns X."""
        rows = self.matched.dofs(self.model.bs).ravel()
        return self.matched.gather(X[rows].reshape(len(self.matched), self.gdim, -1))

    def reaction_forces(self, theta, u) -> np.ndarray:
        """F = P^T K(theta) u: the loaded-node forces that produce u."""
        E, nu = self.materials(theta)
        Ku = self.model.function("Ku")
        self.model.apply_stiffness(E, nu, u.x.petsc_vec, Ku.x.petsc_vec)
        return self.on_loaded(Ku)

    def stiffness_terms(self) -> list:
        """K(theta) = sum_j c_j M_j over M = (A_0, B_0, A_1, B_1, ...), the cached matrices."""
        A, B = self.model.material_matrices
        return [M for pair in zip(A, B) for M in pair]

    def stiffness_coefficients(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(c, dc/dtheta): c_j of ``stiffness_terms`` (mu_m, lambda_m interleaved), and
        their derivatives (n_estimated, 2 n_materials)."""
        E, nu = self.materials(theta)
        mu, lam = self.model.lame_parameters(E, nu)
        dmu_dE, dmu_dnu, dlam_dE, dlam_dnu = lame_jacobian(E, nu, self.scene.plane)
        names = [m.name for m in self.scene.materials]
        dc = np.zeros((len(self.estimated), 2 * len(names)))
        for k, (material, key) in enumerate(self.estimated):
            m = names.index(material)
            dc[k, 2 * m : 2 * m + 2] = (dmu_dE[m], dlam_dE[m]) if key == "E" else (dmu_dnu[m], dlam_dnu[m])
        return np.stack([mu, lam], axis=1).ravel(), dc

    def material_gradient(self, theta, u, w) -> np.ndarray:
        """-w^T dK/dtheta_k u for each estimated constant, from the cached matrices."""
        _, dc = self.stiffness_coefficients(theta)
        uv, wv = u.x.petsc_vec, w.x.petsc_vec
        tmp = uv.duplicate()
        products = []
        for M in self.stiffness_terms():
            M.mult(uv, tmp)
            products.append(wv.dot(tmp))
        tmp.destroy()
        return -dc @ np.array(products)

    def surface_distance(self, residual: np.ndarray) -> dict:
        d = np.linalg.norm(residual, axis=1)
        if self.target.landmark_nodes is not None:
            d = d[self.target.landmark_nodes]
        return {"rms": float(np.sqrt(np.mean(d**2))), "max": float(d.max()), "mean": float(d.mean())}
