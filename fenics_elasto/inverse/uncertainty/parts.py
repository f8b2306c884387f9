"""The model's own error beside the noise: the parts of sigma.

Noise is not the only error in an answer. The source mesh has its own (``mesh``:
how far the answer would move with elements one degree higher, mesh_error.py), and
reduced bases that cannot represent the wall motion
have theirs (``bases``: how far the answer moves when the bases may also use the wall
motion surface matching finds and they miss -- reduction.missing_wall_motion -- and half
of how far it moves when they are cut to half their rank, report.half_rank_shift), and so do
surfaces segmented from label maps (``voxels``: their staircase, voxels.py). All
are added to the noise's std in quadrature; the interval widens with them and the
printed line names the largest part and the lever that shrinks it.
"""

from __future__ import annotations

import numpy as np

from fenics_elasto.inverse.checks import worst_first
from fenics_elasto.inverse.uncertainty.mesh_error import HigherDegreeModel, mesh_error_wanted, mesh_shift
from fenics_elasto.inverse.uncertainty.posterior import Posterior
from fenics_elasto.inverse.uncertainty.voxels import voxel_std

# What the bases still leave at their rank r, as a std: half of how far the answer moves
# between r/2 and r. Where the answer converges in the rank that overstates it (the
# pelvis phantom's filled state: 50.0 at rank 80, its truth, after a 1.5-sigma move);
# where it does not, the move is the only measure there is: on a prostate MR user's
# nested scene at rank 48 (ten runs, gland and nodule), 7 of 20 intervals missed without
# this share, the gland up to 14 % high with the move 2-14 % the other way; 2 missed with
# it, by 1 % (docs: validation).
RANK_PART = 0.5

LEVERS = {"mesh": "a finer source mesh at the organs (about 4x smaller per halving of the element size, P2)",
          "bases": "bases with more examples and a higher rank (train --synthetic N --rank R)",
          "voxels": "label maps of finer voxels (thinner slices) for the source or the target"}


def add_model_error(problem, post: Posterior, theta, evaluation, lin, fit: dict | None,
                    prepared: HigherDegreeModel | None = None) -> None:
    """Sets ``post.model_parts_s``: the mesh's and the bases' first-order shifts of the
    answer, as stds (the bases' with half their half-rank move: ``bases_part``, whose share
    ``post.rank_part_s`` keeps), and the voxels' staircase where a label map is in play.
    None is applied as a correction: on the pelvis phantom's
    straight-sided gmsh source (curved on load, rippled wall motion) the degree-3 shift
    was -3 % where the answer was 4 % low already -- the geometry's error and the wall
    motion's, which a higher degree on the same cells cannot see, were larger.
    ``prepared``: the degree-3 solve's set-up made ahead (HigherDegreeModel.ahead), used up here."""
    bases, post.rank_part_s = bases_part(fit, len(post.labels))
    parts = {"mesh": np.zeros(len(post.labels)), "bases": bases}
    if mesh_error_wanted(problem):
        ds, moved, motion = mesh_shift(problem, lin, theta, evaluation, prepared)
        parts["mesh"] = np.where(np.isfinite(ds), np.abs(ds), 0.0)
        post.mesh_shift_s = np.asarray(ds, float)
        post.mesh_moves = (moved, motion)
    voxels = voxel_std(problem, lin, evaluation)
    if voxels is not None:
        parts["voxels"] = np.where(np.isfinite(voxels), voxels, 0.0)
    post.model_parts_s = parts


def bases_part(fit: dict | None, count: int) -> tuple[np.ndarray, np.ndarray | None]:
    """(the bases part of sigma in s, the half-rank move's share of it or None where not
    measured): the first-order shift of the wall motion they miss and RANK_PART of the
    half-rank move, in quadrature (``fit``: result.json's bases_fit)."""
    fit = fit or {}
    missed = np.abs(np.asarray(fit.get("shift_if_enriched_s", np.zeros(count)), float))
    if "shift_at_half_rank_s" not in fit:
        return missed, None
    rank = RANK_PART * np.abs(np.asarray(fit["shift_at_half_rank_s"], float))
    return np.hypot(missed, rank), rank


UNRESOLVED = 0.5  # a degree-3 solve that moves the observed points this share of their motion or more


def unresolved_warnings(post: Posterior | None) -> list[str]:
    """A degree-3 solve at the answer that moves the observed points by UNRESOLVED of
    their own motion or more: the source mesh does not resolve the recovered forces, and
    the answer's linearisation (the mesh part of sigma) cannot be trusted to say how far
    that moves it. A user's create_box with its loaded top unmatched, in the full force
    space: moved 0.753 against 0.867 at the answer (the truth's motion ~0.06), E 0.645
    for 4 (interval missing)."""
    if post is None or post.mesh_moves is None:
        return []
    moved, motion = post.mesh_moves
    if moved < UNRESOLVED * motion:
        return []
    return [f"a degree-3 solve at the answer moves the observed points by {moved:.3g}, {moved / max(motion, 1e-300):.2g}x "
            f"their largest displacement ({motion:.3g}): the source mesh does not resolve the recovered boundary forces, "
            "and the answer and its interval may be far off -- give reduced bases (`fenics-elasto train`), match the "
            "loaded groups too, or add landmarks"]


# A noise part widened this much is mostly a structured residual: where the model misses
# the target's shape, not its noise. An outside check (a probe pressing a liver with a
# tumour, exact targets by scikit-fem): a 4 mm source STL of the 10 mm tumour fitted 4x
# worse than the body, widened the noise part 8.2x and gave E 31.6 (13.2-50.6) for 30,
# its largest part "noise"; the tumour's surface at 1.5 mm gave 32.5 (27.2-39.1), 1.0x.
STRUCTURED_LEVER = 3.0


def largest_part(post: Posterior, group_fits: dict[str, float] | None = None) -> list[str]:
    """Per constant: ``largest part: mesh (the lever)`` where a part other than the noise
    leads, else ``largest part: noise`` -- and where a structured residual widened the
    noise part STRUCTURED_LEVER times or more, that lever: the fit, each matched group's
    rms distance (``group_fits``) the worst first."""
    out = []
    parts = post.parts_s()
    for i, label in enumerate(post.labels):
        name = max(parts, key=lambda key: parts[key][i])
        lever = "" if name == "noise" else f"; it shrinks with {LEVERS[name]}"
        if name == "noise" and post.widening[i] >= STRUCTURED_LEVER:
            lever = _structured_lever(group_fits or {})
        out.append(f"{label}: largest part of sigma: {name}{lever}")
    return out


def _structured_lever(group_fits: dict[str, float]) -> str:
    fits = f" (rms distance per group: {worst_first(group_fits)})" if len(group_fits) > 1 else ""
    return (f", most of it a structured residual (the widening): the model misses the target's shape more than its "
            f"noise{fits}; it shrinks with a finer source surface or mesh, or a truer target, where the fit is worst")
