"""Checks of an estimate's set-up and answer that need no optimisation: a target that does
not overlap the source or is in other units, a full force space that fits any material,
and a final fit worse than the target can resolve.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.inverse.displacement_field import correlated_over
from fenics_elasto.inverse.inner import InnerResult
from fenics_elasto.inverse.misfit import FieldTerm, PointTerm, credited_noise
from fenics_elasto.geometry.surface import Surface
from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.inverse.options import Options


OVERLAP = 0.25  # a target farther (rms) from its nodes than this share of their extent does not overlap them


def check_overlap(problem: InverseProblem) -> float:
    """Refuse a target that does not lie on the observed surface -- as a whole, or one
    group's (another group's surface, a swapped file) -- or that covers only part of its
    group, naming the file; return Phi at u = 0."""
    y = problem.points
    residual = problem.residual_at_rest
    observed = problem.misfit.weights > 0
    size = float(np.linalg.norm(np.ptp(y, axis=0)))
    distance = float(np.sqrt(np.mean(np.sum(residual[observed] ** 2, axis=1)))) if observed.any() else 0.0
    for kind, key in ((FieldTerm, "displacement"), (PointTerm, "landmarks")):  # each blamed on its own file
        rows = np.setdiff1d(problem.misfit.rows_of(kind), problem.misfit.rows_of(FieldTerm) if kind is PointTerm else [])
        moved = float(np.sqrt(np.mean(np.sum(residual[rows] ** 2, axis=1)))) if len(rows) else 0.0
        require(moved < OVERLAP * size, f"{_point_files(problem, key)}: moves the body by {moved:.3g} rms, against its "
                                        f"size {size:.3g}; is it in the same units and frame as the mesh?")
    targets = sorted(_group_targets(problem), key=lambda t: -t.rms)
    require(distance < OVERLAP * size,
            f"{targets[0].where if targets else problem.scene.path}: the target does not overlap the matched surface "
            f"(rms distance {distance:.3g} vs matched size {size:.3g}); is it in the same units and frame?")
    for t in targets:
        require(t.rms < OVERLAP * t.extent, f"{t.where}: does not overlap {t.group} (rms distance {t.rms:.3g} vs the "
                f"group's size {t.extent:.3g}): is it another group's surface, or in other units?")
    check_covered(targets)
    return problem.misfit.cost(residual)


@dataclass
class GroupTarget:
    """One matched group's target surface in one state, its nodes, their distances to
    it and where it came from."""

    surface: Surface
    x: np.ndarray  # the group's matched nodes at rest
    distance: np.ndarray  # ... and each one's distance to the surface
    group: str
    where: str  # the file, as _target_file names it
    state: str = ""

    @cached_property
    def rim(self) -> np.ndarray:
        """Whether each node's closest point lies on the target's rim (Surface.on_rim)."""
        return self.surface.on_rim(self.x) if len(self.x) else np.zeros(0, bool)

    @property
    def motion(self) -> float:
        """How far the nodes the target covers lie from it (their 95th percentile)."""
        covered = self.distance[~self.rim]
        return float(np.percentile(covered, 95)) if len(covered) else 0.0

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.distance**2))) if len(self.x) else 0.0

    @property
    def extent(self) -> float:
        return float(np.linalg.norm(np.ptp(self.x, axis=0))) if len(self.x) else 0.0


def _group_targets(problem: InverseProblem) -> list[GroupTarget]:
    """Every state's target surface per matched group (one for them all with ``surface``)."""
    x, groups, out = problem.matched_coords, problem.node_groups(), []
    for state, misfit, spec in zip(problem.states.names, problem.states.misfits, problem.states.specs):
        term = misfit.terms[0]
        if not isinstance(term, SurfaceTerm):
            continue
        one = len(term.surfaces) == 1  # ``surface``: one file for every group, each group checked against it
        for g, group in enumerate(problem.scene.matched):
            surface, mine = term.surfaces[0 if one else g], x[(groups if one else term.surface_of) == g]
            distance = np.linalg.norm(mine - surface.closest(mine), axis=1)
            out.append(GroupTarget(surface, mine, distance, group, _target_file(spec, "the matched groups" if one
                                                                                 else group, state), state))
    return out


# A matched group's target must cover the whole group: where it covers a part, the rest
# of the group has only the target's edge to go to, and the fit pulls it there (a new
# user's box with its sides' target cropped at a sixth of their length: E at its bound,
# 0.2 for 4, the interval spanning every value). Refused when more than UNCOVERED of a
# group's nodes lie beyond its target's edge, farther from it than BEYOND_EDGE times the
# distance the nodes covered lie from their target (its 95th percentile: the motion) --
# the largest such motion of the state's matched groups: a bar's loaded end face, bent
# and twisted, moves mostly in its own plane, where no distance to it shows the motion
# and its rim overhangs the target by all of it (a user's bar: 7 % of the face's nodes
# 0.275 beyond, the face itself within 0.044; the sides within ~0.27).
UNCOVERED = 0.05
BEYOND_EDGE = 5.0


def check_covered(targets: list[GroupTarget]) -> None:
    """Each group's target covers the whole group, against the motion its state's groups
    show (BEYOND_EDGE)."""
    motion: dict[str, float] = {}
    for t in targets:
        motion[t.state] = max(motion.get(t.state, 0.0), t.motion)
    for t in targets:
        _check_covered(t, motion[t.state])


def _check_covered(t: GroupTarget, motion: float) -> None:
    """Refuse a target surface that covers only part of its matched group: one line
    naming the group, its file and the share left out (``motion``: the state's)."""
    if len(t.x) == 0:
        return
    beyond = t.rim & (t.distance > BEYOND_EDGE * motion)
    if beyond.mean() > UNCOVERED:
        raise UserError(f"{t.where}: covers only part of {t.group}: {100 * beyond.mean():.0f} % of its nodes lie "
                        f"beyond the target's edge, up to {t.distance[beyond].max():.3g} from it (the nodes its targets "
                        f"cover lie within {motion:.3g}); give the group's whole surface, or match the part it covers as "
                        "a group of its own")


def _point_files(problem: InverseProblem, key: str) -> str:
    """The [target] ``key`` files (displacement, landmarks) of every state that has one."""
    files = [f"{_target_table(name)} {key} ({spec[key]})"
             for name, spec in zip(problem.states.names, problem.states.specs) if spec.get(key)]
    return ", ".join(files) or f"{problem.scene.path}: the {key}"


def _target_table(state: str) -> str:
    """The table a target is given in: a state's, or [target]."""
    return f"[[states]] {state}: target" if state else "[target]"


def _target_file(spec: dict, group: str, state: str) -> str:
    """Where a group's target came from, for the error line."""
    where = _target_table(state)
    for key in ("surfaces", "labels"):
        table = spec.get(key) or {}
        if group in table:
            return f"{where} {key}.{group} ({table[group]})" if key == "surfaces" else f"{where} labels.{group}"
    return f"{where} surface ({spec.get('surface')})" if spec.get("surface") else where


def check_determined(problem: InverseProblem, basis, options: Options, inner: str) -> str | None:
    """Refuse a full force space that can fit the data for any material; None if fine.

    Only for the L-BFGS inner solvers: with Gauss-Newton the linearisation after the
    scan tells (``Estimator.check_identifiable``), and counting is too strict where
    elasticity smooths a few more boundary directions than constraints away. Counting,
    generically: the loaded nodes' displacements are the controls; each
    matched surface point asks one (normal) constraint, each landmark gdim. A loaded
    node that is itself matched meets its own constraint, leaving gdim - 1 free
    directions; every other loaded node leaves gdim. When the free directions are at
    least the remaining constraints plus the materials, the target is fitted exactly
    whatever the materials are (walls sliding along their target, forces scaling).
    """
    if basis is not None or inner == "gauss-newton":
        return None
    misfit, observation = problem.misfit, problem.observation
    surface = misfit.surface_rows()
    surface = surface[misfit.weights[surface] > 0]
    node_is_loaded = _nodes_in(problem, observation.nodes, problem.loaded)
    own = int(np.sum(node_is_loaded[surface[surface < observation.node_count]]))
    free = problem.force_dofs - own
    constraints = len(surface) - own + problem.gdim * len(misfit.landmark_rows()) + len(problem.params)
    if free < constraints:
        return None
    message = (f"{problem.scene.path}: the full force space cannot determine {', '.join(problem.params.labels)}: "
               f"its {free} free boundary directions exceed the {constraints} the target constrains, so every "
               f"material fits it exactly; give reduced bases ([reduction], e.g. from `fenics-elasto train "
               f"{problem.scene.path.name} --synthetic 40 --rank 20 --out bases.npz`) or landmarks inside the body "
               f"([target] landmarks), or set optimizer.allow_undetermined = true")
    if not options.allow_undetermined:
        raise UserError(message)
    return "undetermined set-up (allow_undetermined = true): " + message.split(": ", 1)[1].split("; give")[0]


def _nodes_in(problem, nodes, other) -> np.ndarray:
    """For each node of ``nodes`` (canonical order): is it a node of ``other``?"""
    tree = cKDTree(other.gather(other.coords)) if other.total else None
    points = nodes.gather(nodes.coords)
    if tree is None or not len(points):
        return np.zeros(len(points), bool)
    gap, _ = tree.query(points)
    return gap < 1e-12 * max(1.0, float(np.ptp(points)))


EXTENT_RATIO = 1.5  # a target this much larger or smaller than the surface it matches is suspect
UNITS_RATIO = 3.0  # ... and this much larger is never right (mm against cm is 10x): refused
NOISE_RATIO = 3.0  # a final rms distance above this x [target] noise fits badly
# target_warnings: states with no noise stated whose final rms surface distances differ
# by more than this are named (the inclusion with one outline displaced by 0.02: 31x
# weighed alike, E dragged to its bound; 186x weighed by their residuals, E within 0.1 %;
# two clean outlines: within 2x)
STATES_SPREAD = 10.0
# A field image whose voxels inside the body fill less than this share of it is said: most
# of the image fell outside, as where its affine is wrong.
FIELD_COVERAGE = 0.5


def check_extent(problem: InverseProblem) -> list[str]:
    """A target that overlaps the source (check_overlap) can still be wrong: in other
    units (10x larger) or of another part. Compare each target surface's extent with
    the matched nodes it is compared with: more than UNITS_RATIO x larger is refused
    (no elasticity turns a surface into one three times its size), beyond EXTENT_RATIO
    either way is a warning (a partial segmentation is smaller and may be right)."""
    out = []
    for misfit, spec in zip(problem.states.misfits, problem.states.specs):
        out += _extent_warnings(problem, misfit, spec)
    return out


def _extent_warnings(problem: InverseProblem, misfit, spec: dict) -> list[str]:
    out, matched = [], problem.scene.matched
    for rows, term in zip(misfit.slices, misfit.terms):
        if not isinstance(term, SurfaceTerm):
            continue
        for i, surface in enumerate(term.surfaces):
            labels = spec.get("labels") or {}
            name = (f"target.surface ({spec['surface']})" if spec.get("surface") else
                    f"target.labels.{matched[i]} ({labels.get('image')})" if labels else
                    f"target.surfaces.{matched[i]} ({(spec.get('surfaces') or {}).get(matched[i])})")
            own = problem.observation.points[rows][term.surface_of == i]
            size = float(np.linalg.norm(np.ptp(own, axis=0))) if len(own) else 0.0
            if size <= 0:
                continue
            ratio = surface.extent / size
            message = (f"{name} spans {ratio:.3g} x the matched surface it is compared with "
                       f"({surface.extent:.3g} vs {size:.3g}): in other units, or of another part?")
            require(ratio <= UNITS_RATIO, message)
            if not 1 / EXTENT_RATIO < ratio < EXTENT_RATIO:
                out.append(message)
    return out


def target_warnings(problem: InverseProblem, best: InnerResult, state_noise: str = "residual") -> list[str]:
    """Each state's final rms distance against what its target can resolve: NOISE_RATIO x
    its target.noise if given, else the target's mean edge length; then the states
    against each other (their fits' spread, the same data twice); ``state_noise``: how
    states with no noise stated were weighed ([optimizer] state_noise)."""
    states = problem.states
    distances = states.distances(best.evaluation.residual)
    out = []
    for name, misfit, spec, rows in zip(states.names, states.misfits, states.specs,
                                        states.split(best.evaluation.residual)):
        state = f"state {name}: " if states.count > 1 else ""
        stray = stray_group(misfit, rows, problem.scene.matched)
        out += [state + line for line in _distance_warnings(misfit, spec, distances[name]) + _field_warnings(misfit, rows)
                + _drowned_surfaces(misfit, spec, distances[name]) + ([stray] if stray else [])]
    return out + _unequal_states(problem, distances, state_noise) + _repeated_states(problem)


# One matched group fitting its target this many times worse than every other group does:
# its target (a stale file, another state's scan, a frame slip) is the first suspect, the
# set-up beside it the second (a user's exact outer surface fitted 11x worse than the
# organs' where their patch planes clamped a strip of wall the truth had left free).
STRAY_GROUP = 10.0


def stray_group(misfit, residual: np.ndarray, groups: list[str], always: bool = False) -> str | None:
    """A sentence naming the matched group that fits its target STRAY_GROUP times worse
    than every other group; None where none does, unless ``always``: then each group's
    fit, the worst first (where the targets give one surface per group)."""
    fits = misfit.group_distances(residual, groups)
    if len(fits) < 2:
        return None
    order = sorted(fits, key=fits.__getitem__, reverse=True)
    worst, others = order[0], fits[order[1]]
    if fits[worst] > STRAY_GROUP * others:
        return (f"{worst} fits its target {fits[worst] / max(others, 1e-300):.3g}x worse than every other group (rms "
                f"{fits[worst]:.3g}, the others within {others:.3g}): check its target (its file, its state, its frame) "
                "and the set-up beside it (what is clamped or loaded there that the body did not have)")
    if not always:
        return None
    return "rms distance per group, the worst first: " + worst_first(fits)


def worst_first(fits: dict[str, float]) -> str:
    """``group rms, ...`` for each group's rms distance (``misfit.group_distances``), the worst first."""
    return ", ".join(f"{g} {fits[g]:.3g}" for g in sorted(fits, key=fits.__getitem__, reverse=True))


# Surfaces that fit this much closer than the noise they were weighed with beside landmarks
# or a field of stated noise: their unstated noise cost them their say.
DROWNED = 0.1


def _drowned_surfaces(misfit, spec: dict, distances: dict) -> list[str]:
    """Surfaces with no stated noise, weighed beside landmarks or a field of stated noise
    as if their noise were their roughness or a tenth of their edge (misfit.credited_noise),
    that fit far closer than that: they counted for little, and the answer with them. A
    user's bar: exact surfaces (rms 5e-5) with a field of noise 1e-3 gave 2.87 for 4,
    surfaces alone 4.12; with target.noise = 5e-5 stated, 4.30."""
    stated = [key for key in ("landmark_noise", "displacement_noise") if spec.get(key) is not None]
    surfaces = misfit.surfaces
    if spec.get("noise") is not None or not stated or not surfaces or "surface" not in distances:
        return []
    weighed = credited_noise(surfaces)
    rms = distances["surface"]["rms"]
    if rms >= DROWNED * weighed:
        return []
    return [f"the target surfaces fit within {rms:.2g} rms but, with no target.noise stated, were weighed as if their "
            f"noise were {weighed:.2g} beside the {' and '.join(stated)} stated: they counted for little; state "
            "target.noise if they are known better"]


def _field_warnings(misfit, residual: np.ndarray) -> list[str]:
    """A displacement field whose residual at the answer is one error over cubes wider
    than the cells its samples were counted in (displacement_field.correlated_over)."""
    out = []
    for rows, term in zip(misfit.slices, misfit.terms):
        if not isinstance(term, FieldTerm) or term.cell <= 0:
            continue
        if term.coverage is not None and term.coverage < FIELD_COVERAGE:
            out.append(f"the displacement field image's voxels inside the body fill {100 * term.coverage:.2g} % of it: "
                       "is its affine right (an LPS/RAS slip negates x and y) and does it cover the body?")
        length = correlated_over(term.points, residual[rows], term.cell)
        if length is not None:
            out.append(f"the displacement field's residual is shared over cubes of {length:.3g} ({length / term.cell:.0f}x "
                       f"the cells of {term.cell:.3g} each counted as one independent observation): a smooth error -- "
                       "the field's own, as a registration's often is, or the model's -- counted that often can make "
                       "the interval too narrow; if the field's error is smooth, set [target] displacement_correlation "
                       f"to its correlation length (at least {length:.3g})")
    return out


def _unequal_states(problem: InverseProblem, distances: dict[str, dict], state_noise: str) -> list[str]:
    """States with no noise stated whose surfaces fit more than STATES_SPREAD times apart:
    weighed alike, the worse one's error counts as much as the other's data; weighed by
    their residuals, the worse one counts little, and its target may be off."""
    if problem.states.count < 2 or problem.states.noise is not None:
        return []
    rms = {name: d["surface"]["rms"] for name, d in distances.items() if "surface" in d}
    if len(rms) < 2 or min(rms.values()) <= 0 or max(rms.values()) <= STATES_SPREAD * min(rms.values()):
        return []
    listed = ", ".join(f"{name} {value:.3g}" for name, value in rms.items())
    spread = f"the states' final rms surface distances differ {max(rms.values()) / min(rms.values()):.0f}x ({listed})"
    if state_noise == "residual":  # weighed by their levels, or found within REWEIGH_SETTLED of alike
        return [f"{spread}: each state was weighed by its own residual's level, so the worse one counts little; "
                "is its target off (segmentation, frame, time point)? State each target.noise if they are known"]
    return [f"{spread} and they are weighed alike: state each state's target.noise to weigh them by it, "
            "or let their residuals weigh them (optimizer.state_noise = \"residual\")"]


def _repeated_states(problem: InverseProblem) -> list[str]:
    """States whose targets hold the very same data (a copied state, or two names for one
    scan): counted twice, one scan narrows the interval as a second one would (a user's
    pair of one scan: 4.61-5.37 against 4.47-5.56 alone)."""
    seen: dict[bytes, str] = {}
    out = []
    for name, misfit in zip(problem.states.names, problem.states.misfits):
        key = _fingerprint(misfit)
        if key in seen:
            out.append(f"states {seen[key]} and {name} observe the same data: counted twice, one scan narrows the "
                       "interval as if it were two; give each state its own scan")
        seen.setdefault(key, name)
    return out


def _fingerprint(misfit) -> bytes:
    """A digest of every surface's and point's coordinates a state's misfit compares with."""
    digest = hashlib.sha1()
    for term in misfit.terms:
        for surface in getattr(term, "surfaces", []):
            digest.update(surface.points.tobytes())
        if isinstance(term, PointTerm):
            digest.update(term.points.tobytes())
    return digest.digest()


def _distance_warnings(misfit, spec: dict, distances: dict) -> list[str]:
    """One state's ``distances`` (Misfit.distances) against its target's resolution."""
    out = []
    surfaces = [s for term in misfit.terms for s in getattr(term, "surfaces", [])]
    for kind, distance in distances.items():
        hint = "check its units, frame and the set-up"
        # each kind against its own stated noise: the landmarks' against landmark_noise, not the surfaces'
        own = {"field": "displacement_noise", "landmarks": "landmark_noise"}.get(kind, "noise")
        stated = own if spec.get(own) else "noise" if spec.get("noise") else None
        if stated is not None:
            scale = NOISE_RATIO * spec[stated]
            what = f"{NOISE_RATIO:g} x target.{stated} ({NOISE_RATIO:g} x {spec[stated]:.3g})"
            hint = FIELD_HINT if kind == "field" else hint
        elif kind == "surface" and surfaces:
            scale = float(np.mean([s.mean_edge for s in surfaces]))
            what = f"the target's mean edge length ({scale:.3g})"
        else:
            continue
        if distance["rms"] > scale:
            out.append(f"the final rms {kind} distance {distance['rms']:.3g} is above {what}: "
                       f"the model does not fit the target; {hint}")
    return out


# A field read in the wrong frame fits at many times its noise (a NIfTI field from
# SimpleITK read as RAS: 16x, and E at its bound): what to look at first.
FIELD_HINT = ("are the field's vectors in the mesh's frame and unit? (ITK, SimpleITK, ANTs and elastix write a NIfTI "
              "field's vectors in LPS: set [target] displacement_frame = \"itk\"); or is its noise stated too small?")
