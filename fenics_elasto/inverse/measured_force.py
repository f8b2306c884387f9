"""A measured total force: the scale that unknown forces leave open (docs/method.md §10).

With unknown boundary forces, scaling every E and the forces together leaves u
unchanged, so surfaces, landmarks and fields determine only the ratios of E and the
boundary motion. A force F_g measured on a loaded group g (a probe's load cell) fixes
the scale. The estimate runs with one E as the reference, as without a force; at its
answer the loaded nodes' forces summed over each group give the predicted F_g(1), and
every E and force is multiplied by the scale s minimising

    sum_g |s F_g(1) - F_g|^2 / noise_g^2,   s = sum_g F_g(1).F_g / noise_g^2 / sum_g |F_g(1)|^2 / noise_g^2,

exact for the joint problem where the data other than the force do not see s (they do
not: u is unchanged), and with var(s) = 1 / sum_g |F_g(1)|^2 / noise_g^2. An E's
absolute variance adds its ratio's, scaled, and the scale's: var(s E) = s^2 var(E) +
E^2 var(s) (independent: the ratios come from the motion, the scale from the force).
A predicted force that points elsewhere than the measured one (chi^2 beyond its
degrees of freedom) is said: the motion and the force disagree.

When every E is marked estimated, the first region's E is held at its initial value as
the reference while the motion is fitted, and reported, scaled, as estimated.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fenics_elasto.inverse.uncertainty.profile_interval import Z95
from fenics_elasto.util.errors import UserError
from fenics_elasto.util.logs import log


@dataclass
class MeasuredForce:
    group: str
    value: np.ndarray
    noise: float
    state: str = ""  # with [[states]]: the state it was measured in

    @property
    def label(self) -> str:
        return f"{self.state}.{self.group}" if self.state else self.group

    @property
    def key(self) -> str:
        """Where it was given, for messages."""
        return f"[[states]] {self.state}: measured_force.{self.group}" if self.state else \
            f"boundary.measured_force.{self.group}"


def measured_forces(scene) -> list[MeasuredForce]:
    """[boundary.measured_force], or each [[states]] entry's measured_force (groups
    checked loaded by the schema); every one scales the same E."""
    tables = [("", scene.config["boundary"].get("measured_force") or {})]
    tables += [(state["name"], state.get("measured_force") or {}) for state in scene.config.get("states") or []]
    return [MeasuredForce(g, np.asarray(f["value"], float), float(f["noise"]), state)
            for state, table in tables for g, f in table.items()]


def with_force_reference(scene):
    """The scene to fit the motion on: as given, unless a force is measured and every E
    is estimated -- then the first region's E is the fitting's reference (module docstring)."""
    if not measured_forces(scene) or any(not m.E.estimate for m in scene.materials):
        return scene
    first = scene.materials[0]
    held = replace(first, E=replace(first.E, estimate=False))
    log.info(f"every E is estimated and a force is measured: {first.name}.E is held at {first.E.value:g} while the "
             "motion is fitted, then every E is scaled by the force")
    return replace(scene, materials=[held, *scene.materials[1:]], force_reference=first.name)


def group_forces(problem, forces: np.ndarray) -> dict[str, np.ndarray]:
    """The total force through each loaded group: its nodes' forces summed (a node on
    two loaded groups counts for the first)."""
    nodal = forces.reshape(-1, problem.gdim)
    group = problem.loaded_groups()
    return {name: nodal[group == i].sum(axis=0) for i, name in enumerate(problem.scene.loaded)}


def predicted_force_covariances(problem, basis, theta, lin, noise_std: float,
                                measured: list[MeasuredForce]) -> dict[str, np.ndarray]:
    """How well the fitted motion determines each measured group's predicted force: its
    covariance (gdim x gdim, in the fit's units) from the controls' posterior given the
    materials, noise_std^2 (A_q^T A_q + alpha I)^-1 (linearisation.py). The force
    through group g along e_j is t_j . R d, R the loaded nodes' stiffness (symmetric) and
    t_j the group's unit translation, so its row in the controls q (d = W q) is
    (R t_j)^T W: one solve per direction. Where the surfaces cannot see a motion -- a
    tube's wall sliding along itself -- the prior alone holds it and the force's part
    that rests on it is uncertain: weighed so in ``force_scale``. The pelvis phantom's
    rectum force: its push on the wall gave the scale within 0.1 %, the parts along and
    around the tube's axis 4 % off, and unweighted the scale came out 4 % high."""
    H = lin.A_q.T @ lin.A_q + lin.prior * np.eye(lin.A_q.shape[1])
    states = problem.states
    width = H.shape[0] // states.count  # each state's controls, stacked
    rows = {group: force_rows(problem, theta, group) for group in {m.group for m in measured}}  # states share them
    out = {}
    for m in measured:
        state = states.names.index(m.state) if m.state else 0
        J = np.zeros((problem.gdim, H.shape[0]))
        J[:, state * width:(state + 1) * width] = rows[m.group] if basis is None else rows[m.group] @ basis
        out[m.label] = noise_std**2 * J @ np.linalg.solve(H, J.T)
    return out


def force_rows(problem, theta, group: str) -> np.ndarray:
    """(gdim, force_dofs): the total force through ``group`` as rows acting on the loaded
    nodes' displacement d (other walls held, no other load): row j is R t_j, the loaded
    nodes' forces when the group alone is moved by a unit step along e_j."""
    forward, gdim = problem.forward, problem.gdim
    on_group = problem.loaded_groups() == problem.scene.loaded.index(group)
    rows = []
    for j in range(gdim):
        translation = np.zeros((len(on_group), gdim))
        translation[on_group, j] = 1.0
        rows.append(forward.reaction_forces(theta, forward.from_boundary(theta, translation.ravel())))
    return np.array(rows)


@dataclass
class Scale:
    value: float
    std: float
    chi2: float
    dof: int


def force_scale(predicted: dict[str, np.ndarray], measured: list[MeasuredForce],
                covariance: dict[str, np.ndarray] | None = None) -> Scale:
    """The least-squares scale s of the predicted forces (by MeasuredForce.label) onto the
    measured ones, each weighed by its noise and, where given, by how uncertain the
    prediction is (``covariance``, in the fit's units: s^2 of it once scaled; a few
    fixed-point rounds, s moving little)."""
    covariance = covariance or {}
    s, a = 1.0, 1.0
    for _ in range(FORCE_SCALE_ROUNDS):
        weights = {m.label: np.linalg.inv(m.noise**2 * np.eye(len(m.value))
                                          + s**2 * covariance.get(m.label, np.zeros((len(m.value),) * 2)))
                   for m in measured}
        a = sum(float(predicted[m.label] @ weights[m.label] @ predicted[m.label]) for m in measured)
        s = sum(float(predicted[m.label] @ weights[m.label] @ m.value) for m in measured) / a
        if not covariance:
            break
    chi2 = sum(float((s * predicted[m.label] - m.value) @ weights[m.label] @ (s * predicted[m.label] - m.value))
               for m in measured)
    return Scale(s, float(1.0 / np.sqrt(a)), chi2, sum(len(m.value) for m in measured) - 1)


FORCE_SCALE_ROUNDS = 4  # force_scale's rounds of weights at the last scale (s moves by % a round)


def apply_measured_force(problem, result, measured: list[MeasuredForce]) -> None:
    """Scale the estimate's E and forces by the measured force (in place: theta, forces,
    result.json's materials, uncertainty and ``measured_force``; its ``history`` stays the
    fit's, in the reference's units)."""
    record = result.record
    predicted = {}
    for m in measured:  # each measured force against its state's forces
        forces = result.state_forces[m.state] if m.state else result.forces
        predicted[m.label] = group_forces(problem, forces)[m.group]
    scale = force_scale(predicted, measured, result.force_covariance)
    s = scale.value
    _check_direction(problem, predicted, measured, s)
    is_E = problem.params.is_E
    ratio_std = {label: entry["std"] for label, entry in record.get("uncertainty", {}).items()
                 if isinstance(entry, dict) and "std" in entry}
    result.theta = np.where(is_E, result.theta * s, result.theta)
    result.forces = result.forces * s
    result.state_forces = {name: forces * s for name, forces in result.state_forces.items()}
    for name, values in record["materials"].items():
        values["E"] = float(values["E"] * s)
        label = f"{name}.E"
        E = values["E"]
        if label in ratio_std or name == problem.scene.force_reference:
            by_force = E * scale.std / s
            entry = record.setdefault("uncertainty", {}).setdefault(label, {"ci95": [E / s, E / s]})
            low, high = (s * end for end in entry["ci95"])  # the ratio's interval (profiled: maybe asymmetric)
            entry["std"] = float(np.hypot(s * ratio_std.get(label, 0.0), by_force))
            entry["ci95"] = [E - float(np.hypot(E - low, Z95 * by_force)), E + float(np.hypot(high - E, Z95 * by_force))]
            parts = entry.setdefault("parts", {})
            parts.update({part: s * value for part, value in parts.items()})  # the ratio's parts, in E's units now
            parts["force"] = by_force
    _scale_stds(record.get("uncertainty", {}), s)
    reference = problem.scene.force_reference
    if reference:  # reported as estimated: the force determined it
        result.labels = [f"{reference}.E", *result.labels]
        result.theta = np.concatenate([[record["materials"][reference]["E"]], result.theta])
    record["measured_force"] = {
        "scale": s, "scale_std": scale.std, "chi2": scale.chi2, "dof": scale.dof, "reference": reference,
        "groups": {m.label: {"measured": m.value.tolist(), "predicted": (s * predicted[m.label]).tolist(),
                             "noise": m.noise} for m in measured}}
    log.info(f"measured force: every E and force scaled by {s:.4g} ± {scale.std:.2g} "
             f"(chi2 {scale.chi2:.3g} on {scale.dof} dof); the lines above were relative to the reference, now:")
    for line in scaled_lines(record):
        log.info(line)
    for text in _outside_bounds(problem, record):
        log.warning(text)
        record.setdefault("warnings", []).append(text)
    if scale.dof > 0 and scale.chi2 > scale.dof + 3.0 * np.sqrt(2.0 * scale.dof) + 9.0:
        text = (f"the measured force and the fitted motion disagree (chi2 {scale.chi2:.3g} on {scale.dof} dof): the "
                "predicted force points elsewhere; check the force's frame and group, or its noise")
        log.warning(text)
        record.setdefault("warnings", []).append(text)


def _check_direction(problem, predicted: dict[str, np.ndarray], measured: list[MeasuredForce], s: float) -> None:
    """Refuse a scale <= 0: the measured force points against the force the fitted motion
    needs, which no positive E gives -- most often the reaction on the probe given for
    the force on the body (every E came out negative, with no warning)."""
    if s > 0:
        return
    against = [m for m in measured if float(predicted[m.label] @ m.value) < 0] or measured
    m = against[0]
    need = predicted[m.label]
    cosine = float(need @ m.value) / max(float(np.linalg.norm(need) * np.linalg.norm(m.value)), 1e-300)
    if cosine < -PERPENDICULAR:
        how, advice = "points against", "give the force the group applies to the body, not its reaction on the probe"
    else:  # a zero force, or one across the motion: a frame, an axis order or a group slip, not a sign
        how, advice = "is zero or across", "check the force's frame, axis order and group"
    raise UserError(f"{problem.scene.path}: {m.key}: the measured force {_vector(m.value)} {how} the force the fitted "
                    f"motion needs through {m.group} ({_vector(need)} at the reference's E; scale {s:.3g}): {advice}")


# _check_direction: a measured force within this cosine of perpendicular to the force the
# fitted motion needs is "across" it (a user's force turned 90 degrees read "points against")
PERPENDICULAR = 0.5


def _vector(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.3g}" for x in v) + "]"


# result.json's uncertainty entries in E's units that a scale multiplies (``widened`` is a ratio)
SCALED_ENTRIES = ("noise_only_std", "patch_std", "mesh_shift")


def _scale_stds(uncertainty: dict, s: float) -> None:
    """The per-E entries of result.json's uncertainty that are in E's units, scaled."""
    for key in SCALED_ENTRIES:
        for label, value in (uncertainty.get(key) or {}).items():
            if label.endswith(".E") and value is not None:
                uncertainty[key][label] = s * value


def scaled_lines(record: dict) -> list[str]:
    """``inclusion.E = 3.107 ± 0.94 (95 %: 1.71-5.626)`` per E, after the force's scale."""
    out = []
    for name, values in record["materials"].items():
        entry = record.get("uncertainty", {}).get(f"{name}.E")
        if isinstance(entry, dict) and "ci95" in entry:
            low, high = entry["ci95"]
            out.append(f"{name}.E = {values['E']:.4g} ± {entry['std']:.2g} (95 %: {low:.4g}-{high:.4g})")
    return out


def _outside_bounds(problem, record: dict) -> list[str]:
    """Warnings for each E the force scaled outside its bounds: the force's unit or size
    (E x length^2) is the usual cause (x100 put both of a box's E 10x past them, unsaid)."""
    out = []
    for material in problem.scene.materials:
        bounds, E = material.E.bounds, record["materials"][material.name]["E"]
        if bounds and not bounds[0] <= E <= bounds[1]:
            out.append(f"{material.name}.E = {E:.4g} after the measured force's scale, outside its bounds "
                       f"[{bounds[0]:g}, {bounds[1]:g}]: check the force's unit (E x length^2) and size")
    return out
