"""The misfit between observed positions and the target (docs/method.md §3).

    Phi(y) = 1/2 sum_l w_l |r_l(y)|^2,   r_l = y_l - target_l(y_l)

over the observation rows (observation.py): a matched node's target is the closest
point of its target surface, a landmark's its observed position. Almost everywhere
dPhi/dy_l = w_l r_l, and the Gauss-Newton curvature of 1/2 |r_l|^2 is spanned by the
directions ``Surface.curvature_directions`` gives (the normal of a face, the two
directions across an edge, all at a vertex; all for a landmark) -- exact for a
piecewise-linear target, but only inside each feature's Voronoi region, a thin wedge
at the edges and vertices of a finely faceted smooth surface: the inner fits also try
the smooth surface's there (``gauss_newton_rows(smooth=True)``; inner.GaussNewton says why).

Weights: surface rows 1; landmark rows ``landmark_weight`` (see ``landmark_weight``: from
``[target] landmark_noise`` beside the surfaces' noise, by maximum likelihood).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from fenics_elasto.config.schema import suggestion
from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.logs import log
from fenics_elasto.geometry.phong import finer_where_faceted
from fenics_elasto.geometry.surface import Surface
from fenics_elasto.files.images import check_off_border, read_label_image
from fenics_elasto.inverse.displacement_field import DisplacementField
from fenics_elasto.model.observation import Samples
from fenics_elasto.files.readers import read_landmarks, read_surface
from fenics_elasto.geometry.label_surfaces import label_surface
from fenics_elasto.mesh.repair import without_specks
from fenics_elasto.geometry.smoothing import is_rough, noise, roughness, smoothed
from fenics_elasto.geometry.targets import SurfaceTerm


@dataclass
class PointTerm:
    """Rows with a fixed target point each (landmarks). ``noise``: their stated
    localisation std (``[target] landmark_noise``), None where unstated."""

    points: np.ndarray
    noise: float | None = None

    def closest(self, y: np.ndarray) -> np.ndarray:
        return self.points

    def curvature_directions(self, y: np.ndarray, smooth: bool = False) -> np.ndarray:
        return np.broadcast_to(np.eye(y.shape[1]), y.shape + (y.shape[1],)).copy()


@dataclass
class FieldTerm(PointTerm):
    """Rows of a displacement field's samples: each observed where it moved to, each
    standing for a cube of side ``cell`` (displacement_field.observed_samples)."""

    cell: float = 0.0
    coverage: float | None = None  # an image's: the share of the body its kept voxels fill


class Unobserved:
    """Rows that carry no data (the matched nodes of a landmark-only target)."""

    def closest(self, y: np.ndarray) -> np.ndarray:
        return y

    def curvature_directions(self, y: np.ndarray, smooth: bool = False) -> np.ndarray:
        return np.zeros(y.shape + (y.shape[1],))


class Term(Protocol):
    """What the misfit asks of a block of rows' target."""

    def closest(self, y: np.ndarray) -> np.ndarray: ...

    def curvature_directions(self, y: np.ndarray, smooth: bool = False) -> np.ndarray: ...


class Misfit:
    """Phi over consecutive blocks of observation rows, each with its term and weight."""

    def __init__(self, blocks: Sequence[tuple[int, Term, float]]):
        """``blocks``: (row count, SurfaceTerm | PointTerm, weight) in row order."""
        self.terms = [term for _, term, _ in blocks]
        bounds = np.cumsum([0] + [count for count, _, _ in blocks])
        self.slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        self.weights = np.concatenate([np.full(count, weight, float) for count, _, weight in blocks] or [np.zeros(0)])
        self._roughness: float | None = None

    @property
    def count(self) -> int:
        return len(self.weights)

    def closest(self, y: np.ndarray) -> np.ndarray:
        out = np.empty_like(y)
        for rows, term in zip(self.slices, self.terms):
            out[rows] = term.closest(y[rows])
        return out

    def residual(self, y: np.ndarray) -> np.ndarray:
        """r_l = y_l - target_l(y_l), unweighted (a distance per row)."""
        return y - self.closest(y)

    def cost(self, residual: np.ndarray) -> float:
        return 0.5 * float(np.sum(self.weights[:, None] * residual**2))

    def gradient(self, residual: np.ndarray) -> np.ndarray:
        """dPhi/dy = w r."""
        return self.weights[:, None] * residual

    def gauss_newton_rows(self, y: np.ndarray, smooth: bool = False) -> np.ndarray:
        """(n, gdim, gdim) sqrt(w) C_l: the Gauss-Newton curvature is sum_l J_l^T C_l^T C_l J_l w_l
        (``smooth``: the smooth surfaces' curvature at their facets' edges and vertices,
        Surface.curvature_directions)."""
        out = np.zeros(y.shape + (y.shape[1],))
        for rows, term in zip(self.slices, self.terms):
            out[rows] = term.curvature_directions(y[rows], smooth)
        return np.sqrt(self.weights)[:, None, None] * out

    @property
    def surfaces(self) -> list[Surface]:
        """The target surfaces of every surface term."""
        return [s for t in self.terms if isinstance(t, SurfaceTerm) for s in t.surfaces]

    def smoothing(self) -> dict | None:
        """The rough targets smoothed before matching: their noise before and after (the
        largest over the surfaces), or None when none was."""
        done = [s for s in self.surfaces if s.smoothed_from is not None]
        if not done:
            return None
        return {"surfaces": len(done), "noise_before": max(float(s.smoothed_from or 0.0) for s in done),
                "noise_after": max(noise(s) for s in done)}

    def rough(self) -> bool:
        """A surface target rougher than its sampling (Surface.is_rough) as matched: then
        Phi* is jagged in the materials (the closest point is the nearest spike)."""
        return any(is_rough(s) for s in self.surfaces)

    def roughness(self) -> float:
        """The surface targets' own noise (0 without surfaces): the posterior's noise floor."""
        if self._roughness is None:  # a pass over every target vertex: once
            self._roughness = max([t.roughness() for t in self.terms if isinstance(t, SurfaceTerm)], default=0.0)
        return float(self._roughness)

    def stated_floor(self) -> float:
        """The least noise std, on the rows' common scale, that leaves no landmark credited
        better than its stated ``landmark_noise`` (0 without one): a landmark row of weight
        w and stated std n needs the scale at least n sqrt(w). The weights assume the
        surfaces' noise (landmark_weight), and a residual led by near-exact surfaces would
        else make six noisy fiducials ten times surer than stated (a user's 3D ball: E
        3.736, 95 % 3.623-3.853, for 4)."""
        return max([term.noise * float(np.sqrt(self.weights[rows.start])) for rows, term in zip(self.slices, self.terms)
                    if type(term) is PointTerm and term.noise is not None and rows.stop > rows.start], default=0.0)

    def statistical_rows(self, y: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """(n, gdim, gdim) sqrt(w) C_l of the noise model the posterior uses: a surface point
        is measured along the surface's normal only (one component: the unit residual, the
        normal of a face; the curvature's first row where the residual vanishes); a
        landmark in every direction. Unlike the exact closest-feature curvature
        (gauss_newton_rows), a point whose closest feature is a vertex or an edge -- common
        on a rough, noisy target -- does not claim to know where it sits along the surface."""
        out = self.gauss_newton_rows(y)
        rows = self.surface_rows()
        if len(rows):
            d = np.linalg.norm(residual[rows], axis=1)
            moved = d > 1e-12 * max(float(d.max()), 1e-300)
            normal = out[rows, 0] / np.maximum(np.linalg.norm(out[rows, 0], axis=1, keepdims=True), 1e-300)
            normal[moved] = residual[rows][moved] / d[moved, None]
            out[rows] = 0.0
            out[rows, 0] = np.sqrt(self.weights[rows])[:, None] * normal
        return out

    def offset_residual(self, y: np.ndarray) -> np.ndarray | None:
        """d r / d delta when every closed target surface moves out along its normal by
        delta (an over-segmentation): -outward normal at its rows, zero elsewhere; None
        when no row has a closed surface."""
        out = np.zeros_like(y)
        for rows, term in zip(self.slices, self.terms):
            if isinstance(term, SurfaceTerm):
                out[rows] = -term.outward(y[rows])
        return out if out.any() else None

    def rows_of(self, kind: type) -> np.ndarray:
        """Indices of the rows whose term is a ``kind``."""
        rows = [np.arange(s.start, s.stop) for s, t in zip(self.slices, self.terms) if isinstance(t, kind)]
        return np.concatenate(rows) if rows else np.zeros(0, int)

    def landmark_rows(self) -> np.ndarray:
        """Indices of the rows with a fixed target point (landmarks, a field's samples)."""
        return self.rows_of(PointTerm)

    def surface_rows(self) -> np.ndarray:
        return self.rows_of(SurfaceTerm)

    def distances(self, residual: np.ndarray, groups: list[str] | None = None) -> dict:
        """rms / max / mean distance of the surface rows and of the landmark rows; with the
        scene's matched ``groups``, the surface's also per group (``group_distances``)."""
        out: dict = {}
        field = self.rows_of(FieldTerm)
        landmarks = np.setdiff1d(self.landmark_rows(), field)
        for name, rows in (("surface", self.surface_rows()), ("landmarks", landmarks), ("field", field)):
            if len(rows):
                d = np.linalg.norm(residual[rows], axis=1)
                out[name] = {"rms": float(np.sqrt(np.mean(d**2))), "max": float(d.max()), "mean": float(d.mean())}
        by_group = self.group_distances(residual, groups) if groups else {}
        if by_group and "surface" in out:
            out["surface"]["groups"] = by_group
        return out

    def group_distances(self, residual: np.ndarray, groups: list[str]) -> dict[str, float]:
        """Each matched group's rms distance to its own target surface (``groups``: the
        scene's matched groups, in order), where the targets give one surface per group."""
        squares, counts = dict.fromkeys(groups, 0.0), dict.fromkeys(groups, 0)
        for rows, term in zip(self.slices, self.terms):
            if isinstance(term, SurfaceTerm) and len(term.surfaces) == len(groups) > 1:
                d2 = np.sum(residual[rows] ** 2, axis=1)
                for i, group in enumerate(groups):
                    mine = term.surface_of == i
                    squares[group] += float(d2[mine].sum())
                    counts[group] += int(mine.sum())
        return {g: float(np.sqrt(squares[g] / counts[g])) for g in groups if counts[g]}


# --------------------------------------------------------------------------- from [target]


@dataclass
class TargetData:
    """A target in memory: ``surface`` (one for every matched group) or ``surfaces`` (one
    per matched group), and/or ``landmarks`` (source points, observed points); ``source``
    names it in error lines."""

    surface: Surface | None = None
    surfaces: dict[str, Surface] | None = None
    landmarks: tuple[np.ndarray, np.ndarray] | None = None
    displacement: DisplacementField | None = None
    source: str = "target"
    spec: dict | None = None  # its [target] table (weights, noise); None: the scene's

    def observed_inside(self) -> Samples | None:
        """The rows observed inside the body: the landmarks', then the field's (its cubes'
        means: displacement_field.observed_samples)."""
        field = self.displacement
        parts = [p for p in (None if self.landmarks is None else Samples.single(self.landmarks[0]),
                             None if field is None else field.samples or Samples.single(field.points)) if p is not None]
        return Samples.joined(parts) if parts else None


def read_target(scene, spec: dict | None = None, where: str | None = None) -> TargetData:
    """The scene's [target] files (or another target table ``spec``, e.g. a state's,
    named ``where`` in messages) read, paths relative to the problem file, the rough 3D
    surfaces smoothed (``smooth``)."""
    spec = scene.config["target"] if spec is None else spec
    where = where or f"{scene.path}: [target]"
    require(spec is not None, f"{where}: missing; give surface, surfaces, landmarks and/or displacement")
    base = scene.path.parent
    read = lambda name: target_surface(base / name, scene.gdim, spec["smooth"])  # noqa: E731
    if spec["surfaces"] is not None:  # the names first: a file of a group not matched is not read
        check_surface_groups(scene.matched, spec["surfaces"], f"{where}.surfaces")
    surfaces = {g: read(f) for g, f in spec["surfaces"].items()} if spec["surfaces"] is not None else None
    if spec.get("labels") is not None:
        surfaces = label_map_targets(scene, spec["labels"], f"{where}.labels")
    landmarks = None if spec.get("landmarks") is None else read_landmarks(base / spec["landmarks"], scene.gdim)
    return TargetData(surface=read(spec["surface"]) if spec["surface"] is not None else None, surfaces=surfaces,
                      landmarks=landmarks, displacement=read_target_field(scene, spec), source=where, spec=spec)


def read_targets(scene) -> list[tuple[str, TargetData]]:
    """(state name, target) of every state of the scene: [[states]], or the one [target] ("")."""
    if scene.config.get("states") is None:
        return [("", read_target(scene))]
    return [(state["name"], read_target(scene, state["target"], f"{scene.path}: [[states]] {state['name']}: target"))
            for state in scene.config["states"]]


def read_target_field(scene, spec: dict) -> DisplacementField | None:
    """A target table's displacement: the field's samples as read (not yet sampled), or None."""
    if spec.get("displacement") is None:
        return None
    return DisplacementField.read(scene.path.parent / spec["displacement"], scene.gdim,
                                  spec.get("displacement_frame") or "world")


def label_map_targets(scene, table: dict, where: str) -> dict[str, Surface]:
    """``[target.labels]``: per matched group the boundary of its labels' union in the
    deformed state's label map (SurfaceNets, smoothed; world coordinates as the image's
    header gives them)."""
    groups = {g: labels for g, labels in table.items() if g != "image"}
    check_surface_groups(scene.matched, groups, where, noun="labels")
    image = read_label_image(scene.path.parent / table["image"], f"{where} image")
    present = set(np.unique(image.labels).tolist())
    named = sorted({v for labels in groups.values() for v in labels})
    check_off_border(np.isin(image.labels, named), f"{where} image ({table['image']})")
    out = {}
    for group, labels in groups.items():
        absent = sorted(set(labels) - present)
        require(not absent, f"{where} {group}: label(s) {absent} not in {table['image']}")
        # stray voxels of the labels (a segmentation's specks) dropped, as `scene` drops the rest map's: one
        # voxel 20 mm from a user's tumour made its target "1.55 x the matched surface"
        out[group] = Surface(*without_specks(*label_surface(image.labels, image.affine, labels), f"{where} {group}"))
        out[group].voxels = np.asarray(image.affine, float)[:3, :3]  # its segmentation's error: uncertainty/voxels.py
    return out


def landmark_weight(spec: dict, surfaces: list[Surface]) -> float:
    """The weight of a landmark row beside a surface row's 1: ``[target] landmark_weight``
    if given; else with ``landmark_noise`` (the markers' localisation std) the maximum-
    likelihood ratio (sigma_surface / landmark_noise)^2, sigma_surface being ``[target]
    noise`` if given, else the noise the target surfaces show (their roughness), but at
    least SURFACE_FLOOR of their mean edge -- a surface is not known better than a tenth of
    its own sampling however smooth it looks; else 1: a landmark as certain as a surface
    point."""
    if spec.get("landmark_weight") is not None:
        return float(spec["landmark_weight"])
    return _noise_weight(spec, surfaces, spec.get("landmark_noise"))


def field_weight(spec: dict, surfaces: list[Surface]) -> float:
    """The weight of a displacement field's sample (one per correlation cell) beside a
    surface row's 1: (sigma_reference / displacement_noise)^2 by maximum likelihood, the
    reference being the surfaces' noise (as for landmarks), else the landmarks' noise;
    1 without ``displacement_noise``."""
    return _noise_weight(spec, surfaces, spec.get("displacement_noise"), spec.get("landmark_noise"))


def _noise_weight(spec: dict, surfaces: list[Surface], own: float | None, fallback: float | None = None) -> float:
    if own is None:
        return 1.0
    sigma = spec.get("noise")
    if sigma is None and surfaces:
        sigma = credited_noise(surfaces)
    if sigma is None:  # no surface: the other point data's noise, else the rows' own scale
        sigma = fallback if fallback is not None else own
    return float((sigma / own) ** 2)


SURFACE_FLOOR = 0.1  # landmark_weight: the least noise a target surface is credited with, in its mean edges


def credited_noise(surfaces: list[Surface]) -> float:
    """The noise target surfaces with none stated are weighed with beside landmarks or a
    field of stated noise: the noise they show (their roughness), but at least
    SURFACE_FLOOR of their mean edge."""
    return max(max(noise(s) for s in surfaces), SURFACE_FLOOR * float(np.mean([s.mean_edge for s in surfaces])))


def target_surface(path: Path, gdim: int, smooth: str) -> Surface:
    """A target surface file, smoothed first when it is rough (``smooth_if_rough``)."""
    return smooth_if_rough(read_surface(path, gdim), path.name, smooth)


def smooth_if_rough(surface: Surface, name: str, smooth: str) -> Surface:
    """A target surface, smoothed first when it is rough (``smooth = "auto"``): the
    closest point to a noisy, finely sampled surface is its nearest spike, so the misfit
    is jagged in the materials and the optimiser lands in one of its many local minima
    (phantom, 0.08 mm of noise on organs sampled every 0.3 mm: E +4 %, +29 %, +10 % with
    sigmas of 0.7 %, 0.006 %, 0.002 %; smoothed: within 2 %, intervals holding the truth).
    3D only: organs are smooth, while 2D outlines have corners that a noisy polyline
    cannot tell from its noise -- smoothing rounded the letter A's and moved its nu by
    -3 % (0.5 % noise, 30 draws: -3.7 % against -0.6 % unsmoothed)."""
    if smooth == "auto" and surface.dim == 3 and is_rough(surface):
        smooth_surface = smoothed(surface)
        log.info(f"note: {name}: rough (noise ~{roughness(surface):.3g}, mean edge {surface.mean_edge:.3g}): "
                 f"smoothed before matching (noise left ~{noise(smooth_surface):.3g}); [target] smooth = \"off\" keeps it")
        out = finer_where_faceted(smooth_surface, name)
    else:  # a rough surface's own normals are its noise: no smooth surface to lift it onto
        out = surface if is_rough(surface) else finer_where_faceted(surface, name)
    out.voxels = surface.voxels
    return out


def check_surface_groups(matched: list[str], given, where: str, noun: str = "surface") -> None:
    """One target (a surface, or its labels) per matched group, and none for another group;
    ``where``: the table that gives them."""
    missing = [g for g in matched if g not in given]
    unknown = [g for g in given if g not in matched]
    if missing and unknown:  # a misspelt group: name it, and what it may have meant
        guesses = [f"{g!r} (did you mean {guess!r}?)" if guess else repr(g)
                   for g, guess in ((g, suggestion(g, missing)) for g in unknown)]
        raise UserError(f"{where}: no {noun} for matched group(s) {missing}; given for {', '.join(guesses)}, "
                        f"which boundary.matched does not name")
    require(not missing, f"{where}: no {noun} for matched group(s) {missing}")
    require(not unknown, f"{where}: {unknown} not in boundary.matched")


def build_misfit(scene, node_groups: np.ndarray, target: TargetData, before: int = 0, after: int = 0) -> Misfit:
    """A target as a Misfit over the scene's observation rows (weights from its [target]).

    ``node_groups``: index into ``scene.matched`` of each matched node (canonical order);
    the target's own observed points (landmarks, then field samples) follow the nodes',
    after ``before`` rows of other states' points and before ``after`` more: rows this
    target does not observe.
    """
    spec = target.spec or scene.config["target"] or {"landmark_weight": None}
    where = target.source
    require(any(x is not None for x in (target.surface, target.surfaces, target.landmarks, target.displacement)),
            f"{where}: missing; give surface, surfaces, landmarks and/or displacement")
    blocks: list[tuple[int, Term, float]] = []
    if target.surface is not None:
        blocks.append((len(node_groups), SurfaceTerm([target.surface], np.zeros(len(node_groups), int)), 1.0))
    elif target.surfaces is not None:
        check_surface_groups(scene.matched, target.surfaces, f"{where}.surfaces")
        blocks.append((len(node_groups), SurfaceTerm([target.surfaces[g] for g in scene.matched], node_groups), 1.0))
    else:  # no surfaces: the matched nodes observe nothing
        blocks.append((len(node_groups), Unobserved(), 0.0))
    surfaces = blocks[0][1].surfaces if isinstance(blocks[0][1], SurfaceTerm) else []
    if before:
        blocks.append((before, Unobserved(), 0.0))
    if target.landmarks is not None:
        observed = target.landmarks[1]
        noise = spec.get("landmark_noise")
        blocks.append((len(observed), PointTerm(observed, None if noise is None else float(noise)),
                       landmark_weight(spec, surfaces)))
    if target.displacement is not None:
        field = target.displacement
        blocks.append((len(field.points), FieldTerm(field.points + field.vectors, cell=field.cell, coverage=field.coverage),
                       field_weight(spec, surfaces)))
    if after:
        blocks.append((after, Unobserved(), 0.0))
    return Misfit(blocks)


def stacked(misfits: Sequence[Misfit], weights: Sequence[float] | np.ndarray | None = None) -> Misfit:
    """One Misfit over the states' rows one after another (each over the same observation),
    each state's rows weighed by its entry of ``weights`` too (states.States.weights)."""
    weights = np.ones(len(misfits)) if weights is None else np.asarray(weights, float)
    if len(misfits) == 1 and weights[0] == 1.0:
        return misfits[0]
    return Misfit([(s.stop - s.start, term, w * float(m.weights[s.start]) if s.stop > s.start else 0.0)
                   for m, w in zip(misfits, weights) for s, term in zip(m.slices, m.terms)])
