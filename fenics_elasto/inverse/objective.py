"""The misfit Phi(theta, controls) and its hand-derived adjoint gradients (docs/method.md §3-4).

    forward:  K u = P F                   adjoint:  K w = O^T w_r r
    dPhi/dF = P^T w                       dPhi/dtheta_k = -w^T (dK/dtheta_k) u

K is symmetric, so one factorization serves both solves. ``InverseProblem`` glues the
forward model (forward.py), where it is observed (observation.py) and the misfit to the
target (misfit.py) -- as hIPPYlib's Model glues PDE and Misfit -- and counts the solves.
theta are the estimated constants in the order of ``Scene.estimated()``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal
from functools import cached_property

import numpy as np

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.util.errors import require
from fenics_elasto.model.forward import BoundaryForward
from fenics_elasto.inverse.displacement_field import observed_samples
from fenics_elasto.inverse.misfit import Misfit, TargetData, build_misfit, read_target
from fenics_elasto.model.observation import Observation
from fenics_elasto.model.scene import Scene
from fenics_elasto.model.responses import response_block


@dataclass
class Evaluation:
    phi: float  # the data misfit
    u: object  # dolfinx Function
    y: np.ndarray  # (n_obs, gdim) observed positions
    residual: np.ndarray  # (n_obs, gdim) unweighted r
    grad_controls: np.ndarray | None = None  # dPhi/dF or dPhi/dd
    grad_theta: np.ndarray | None = None


class InverseProblem:
    """A scene's forward model, its observation and the misfit to its target."""

    def __init__(self, scene: Scene, model: ElasticModel | None = None,
                 target: TargetData | Misfit | Literal[False] | None = None):
        """``target``: a target in memory (TargetData), a Misfit (no landmarks), None to
        read the scene's [target] files, False for none (training)."""
        require(scene.matched, f"{scene.path}: boundary.matched is empty: nothing to compare with the target")
        self.scene = scene
        self.forward = BoundaryForward(scene, model)
        self.model = self.forward.model
        self.params = self.forward.params
        self.gdim = scene.gdim
        data = read_target(scene) if target is None else target
        if isinstance(data, TargetData) and data.displacement is not None:
            correlation = (scene.config["target"] or {}).get("displacement_correlation")
            data = replace(data, displacement=observed_samples(data.displacement, self.model.dofs.V.mesh, correlation))
        points = data.observed_points() if isinstance(data, TargetData) else None
        self.observation = Observation(self.model, scene, points)
        self._misfit = build_misfit(scene, self.node_groups(), data) if isinstance(data, TargetData) else data or None

    @property
    def misfit(self) -> Misfit:
        """The misfit to the target (a problem made for training, ``target=False``, has none)."""
        if self._misfit is None:
            raise ValueError("this InverseProblem was made without a target (target=False)")
        return self._misfit

    @property
    def has_target(self) -> bool:
        return self._misfit is not None

    # --- sizes and groups

    @property
    def force_dofs(self) -> int:
        return self.forward.force_dofs

    @property
    def loaded(self):
        return self.forward.loaded

    @property
    def matched_coords(self) -> np.ndarray:
        """Reference positions of the matched nodes (canonical order)."""
        return self.observation.node_points

    def node_groups(self) -> np.ndarray:
        """Index into scene.matched of each matched node's (first) group, canonical order."""
        return self._groups_of(self.observation.nodes, self.scene.matched, self.observation.vertices_only)

    def matched_on_loaded(self) -> np.ndarray:
        """Mask over the matched nodes (canonical order): those on a loaded group."""
        return self._groups_of(self.observation.nodes, self.scene.loaded, self.observation.vertices_only) >= 0

    def loaded_groups(self) -> np.ndarray:
        """Index into scene.loaded of each loaded node's (first) group, canonical order."""
        return self._groups_of(self.loaded, self.scene.loaded)

    def _groups_of(self, nodes, groups, vertices_only=False) -> np.ndarray:
        group = np.full(len(nodes), -1)
        for i, name in reversed(list(enumerate(groups))):
            group[np.isin(nodes.blocks, self.model.dofs.boundary_blocks([name], vertices_only))] = i
        return nodes.gather(group)

    # --- Phi and its gradients

    @cached_property
    def residual_at_rest(self) -> np.ndarray:
        """The misfit's residual of the undeformed observed points (u = 0): the target's
        overlap check and the scale of Phi at rest (estimate.py) both read it."""
        return self.misfit.residual(self.observation.points)

    def _evaluate(self, theta, u, boundary: bool, gradient: bool) -> Evaluation:
        y = self.observation.positions(u)
        residual = self.misfit.residual(y)
        ev = Evaluation(self.misfit.cost(residual), u, y, residual)
        if gradient:
            ev.grad_controls, w = self.pull_back(theta, self.misfit.gradient(residual), boundary)
            ev.grad_theta = self.forward.material_gradient(theta, u, w)
        return ev

    def pull_back(self, theta, g: np.ndarray, boundary: bool = True) -> tuple[np.ndarray, object]:
        """(dPhi/dcontrols, w) for dPhi/dy = g (n_obs, gdim): one adjoint solve. Linear in
        g: with boundary motion as the controls it is the transpose of ``observed_motion``."""
        load = self.observation.transpose(g)
        w = self.forward.adjoint(theta, load, boundary)
        if not boundary:  # dPhi/dF = P^T w
            return self.forward.on_loaded(w), w
        Kw = self.model.dofs.function("Kw")  # dPhi/dd = (O^T g)_B - (K w)_B
        self.model.stiffness.apply(self.forward.coefficients(theta)[0], w.x.petsc_vec, Kw.x.petsc_vec)
        return self.forward.on_loaded(load) - self.forward.on_loaded(Kw), w

    def observed_motion(self, theta, d: np.ndarray) -> np.ndarray:
        """(n_obs, gdim) O u of the loaded boundary's motion d: one solve, linear in d."""
        return self.observation.values(self.forward.from_boundary(theta, d))

    def evaluate_field(self, theta, u) -> Evaluation:
        """Phi of a field u solved elsewhere (the surrogate's: functional.Profile), no gradients."""
        return self._evaluate(theta, u, True, False)

    def evaluate_forces(self, theta, forces, gradient: bool = False) -> Evaluation:
        """Phi(theta, F) -- the paper's coordinates -- and on request its gradients."""
        return self._evaluate(theta, self.forward.from_forces(theta, forces), False, gradient)

    def evaluate_displacement(self, theta, d, gradient: bool = False) -> Evaluation:
        """Phi as a function of the loaded nodes' displacement d (a bijection with F at
        fixed theta; the forces preconditioned by the Dirichlet-to-Neumann map).

            dPhi/dd = (O^T g)_B - (K w)_B,   K_D w = O^T g (w = 0 on B),   g = dPhi/dy
            dPhi/dtheta_k = -w^T dK/dtheta_k u
        """
        return self._evaluate(theta, self.forward.from_boundary(theta, d), True, gradient)

    def response(self, theta, basis: np.ndarray | None = None, rtol: float | None = None) -> np.ndarray:
        """J (n_obs, gdim, r): observed displacement per unit of each boundary mode
        (``rtol``: see forward.response_block)."""
        return self.observation.rows(response_block(self.forward, theta, basis, rtol))

    def distances(self, residual: np.ndarray) -> dict:
        return self.misfit.distances(residual)
