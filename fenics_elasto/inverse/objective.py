"""The misfit Phi(theta, controls) and its hand-derived adjoint gradients (docs/method.md §3-4).

    forward:  K u = P F                   adjoint:  K w = O^T w_r r
    dPhi/dF = P^T w                       dPhi/dtheta_k = -w^T (dK/dtheta_k) u

K is symmetric, so one factorization serves both solves. ``InverseProblem`` glues the
forward model (forward.py), where it is observed (observation.py) and the misfit to the
target (misfit.py) -- as hIPPYlib's Model glues PDE and Misfit -- and counts the solves.
theta are the estimated constants in the order of ``Scene.estimated()``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from collections.abc import Sequence
from typing import Literal
from functools import cached_property

import numpy as np

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.util.errors import require
from fenics_elasto.model.forward import BoundaryForward
from fenics_elasto.inverse.displacement_field import observed_samples
from fenics_elasto.inverse.states import States
from fenics_elasto.inverse.misfit import Misfit, TargetData, build_misfit, read_targets, stacked
from fenics_elasto.model.observation import Observation, Samples
from fenics_elasto.model.scene import Scene
from fenics_elasto.model.responses import response_block


@dataclass
class Evaluation:
    phi: float  # the data misfit
    u: object  # dolfinx Function (the first state's)
    y: np.ndarray  # (S n_obs, gdim) observed positions
    residual: np.ndarray  # (n_obs, gdim) unweighted r
    grad_controls: np.ndarray | None = None  # dPhi/dF or dPhi/dd
    grad_theta: np.ndarray | None = None
    fields: list = field(default_factory=list)  # every state's u (dolfinx Functions)


def _sampled(scene: Scene, mesh, data: TargetData) -> TargetData:
    """The target with its displacement field as observed (displacement_field.py)."""
    if data.displacement is None:
        return data
    correlation = (data.spec or scene.config["target"] or {}).get("displacement_correlation")
    return replace(data, displacement=observed_samples(data.displacement, mesh, correlation))


class InverseProblem:
    """A scene's forward model, its observation and the misfit to its target."""

    def __init__(self, scene: Scene, model: ElasticModel | None = None,
                 target: TargetData | Sequence[tuple[str, TargetData]] | Misfit | Literal[False] | None = None):
        """``target``: a target in memory (TargetData), several states' ((name,
        TargetData) pairs), a Misfit (no landmarks), None to read the scene's [target] or
        [[states]] files, False for none (training)."""
        require(scene.matched, f"{scene.path}: boundary.matched is empty: nothing to compare with the target")
        self.scene = scene
        self.forward = BoundaryForward(scene, model)
        self.model = self.forward.model
        self.params = self.forward.params
        self.gdim = scene.gdim
        if target is False or isinstance(target, Misfit):
            self.states = States([""], [target] if target else [], [scene.config["target"] or {}])
            self.observation = Observation(self.model, scene, None)
            self._misfit = target or None
            return
        targets = read_targets(scene) if target is None else [("", target)] if isinstance(target, TargetData) \
            else list(target)
        targets = [(name, _sampled(scene, self.model.dofs.V.mesh, data)) for name, data in targets]
        own = [data.observed_inside() or Samples.single(np.zeros((0, self.gdim))) for _, data in targets]
        counts = [len(p.points) for p in own]
        self.observation = Observation(self.model, scene, Samples.joined(own) if sum(counts) else None)
        groups = self.node_groups()
        misfits = [build_misfit(scene, groups, data, before=sum(counts[:i]), after=sum(counts[i + 1:]))
                   for i, (_, data) in enumerate(targets)]
        self.states = States([name for name, _ in targets], misfits,
                             [data.spec or scene.config["target"] or {} for _, data in targets])
        self._misfit = stacked(misfits, self.states.weights)

    # --- several states (states.py): rows and controls one state after another

    @property
    def points(self) -> np.ndarray:
        """The undeformed observed positions of every state's rows (the observation's, repeated)."""
        return np.tile(self.observation.points, (self.states.count, 1))

    def field_rows(self, theta, evaluation: Evaluation) -> np.ndarray:
        """(S n, gdim, n_theta): the observed positions' derivative in theta at fixed
        controls, each state's from its own field (n_theta back-solves each)."""
        return np.concatenate([self.observation.rows(self.forward.field_derivative(theta, u))
                               for u in evaluation.fields])

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
        return self.misfit.residual(self.points)

    def _evaluate(self, theta, fields: list, boundary: bool, gradient: bool) -> Evaluation:
        y = np.concatenate([self.observation.positions(u) for u in fields])
        residual = self.misfit.residual(y)
        ev = Evaluation(self.misfit.cost(residual), fields[0], y, residual, fields=fields)
        if gradient:
            pulled = [self.pull_back(theta, g, boundary) for g in self.states.split(self.misfit.gradient(residual))]
            ev.grad_controls = np.concatenate([controls for controls, _ in pulled])
            ev.grad_theta = np.sum([self.forward.material_gradient(theta, u, w) for u, (_, w) in zip(fields, pulled)],
                                   axis=0)
        return ev

    def pull_back(self, theta, g: np.ndarray, boundary: bool = True) -> tuple[np.ndarray, object]:
        """(dPhi/dcontrols, w) of one state for dPhi/dy = g (n_obs, gdim): one adjoint solve.
        Linear in g: with boundary motion as the controls it is the transpose of
        ``observed_motion``."""
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
        """Phi of fields solved elsewhere (the surrogate's: profile.Profile), no gradients:
        ``u`` one Function per state (or one Function)."""
        return self._evaluate(theta, u if isinstance(u, list) else [u], True, False)

    def evaluate_forces(self, theta, forces, gradient: bool = False) -> Evaluation:
        """Phi(theta, F) -- the paper's coordinates -- and on request its gradients."""
        return self._evaluate(theta, [self.forward.from_forces(theta, f) for f in self.states.split(forces)], False, gradient)

    def evaluate_displacement(self, theta, d, gradient: bool = False) -> Evaluation:
        """Phi as a function of the loaded nodes' displacement d (a bijection with F at
        fixed theta; the forces preconditioned by the Dirichlet-to-Neumann map).

            dPhi/dd = (O^T g)_B - (K w)_B,   K_D w = O^T g (w = 0 on B),   g = dPhi/dy
            dPhi/dtheta_k = -w^T dK/dtheta_k u
        """
        return self._evaluate(theta, [self.forward.from_boundary(theta, ds) for ds in self.states.split(d)], True, gradient)

    def response(self, theta, basis: np.ndarray | None = None, rtol: float | None = None) -> np.ndarray:
        """J (n_obs, gdim, r): observed displacement per unit of each boundary mode
        (``rtol``: see forward.response_block)."""
        return self.states.stack_controls(self.observation.rows(response_block(self.forward, theta, basis, rtol)))

    def distances(self, residual: np.ndarray) -> dict:
        return self.misfit.distances(residual, self.scene.matched)
