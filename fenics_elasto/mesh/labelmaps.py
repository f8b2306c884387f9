"""Scenes from a label-map image: the spec's labels -> the closed shells anatomy.py meshes.

A spec with ``[labels] image = ...`` names label values instead of surface files
(interface.md, "Scenes from label maps"): the body is the union of ``body.label`` (with
its cavities and any unlabelled voxels it encloses), a region or a cavity is the union of
its ``label``. ``label_shells``:

1. reads the image (files/images.py: world coordinates as its header gives them) and
   checks that every label named is in it;
2. relabels it compactly -- 0 outside the body, 1 the body's own material, then one label
   per region and per cavity -- and runs SurfaceNets once on that (geometry/
   label_surfaces.py), anisotropic voxels as they are;
3. checks from the interfaces' two sides that the labels nest as a scene must: no region
   or cavity on the body's outer boundary, none touching another unless held wholly
   inside it (a region in a region: a nodule in a gland), the body off the image
   border -- one line each, naming the spec keys and labels;
4. smooths each closed surface without shrinking it and hands it to the surface-file
   path's own checks and repairs (repair.solid_shells: where two voxels touch by an edge
   only, the surface is pinched there and is rebuilt from what it encloses), so the
   nesting, meshing and curving that follow are the surface files' (anatomy.py).

``coarsen`` then brings each shell down to about organ_size / 2 edges once the sizes
are known (SurfaceNets gives about one vertex per boundary voxel).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fenics_elasto.files.images import LabelImage, check_off_border, read_label_image
from fenics_elasto.geometry.label_surfaces import Interfaces, coarsened, smoothed, surface_nets
from fenics_elasto.mesh.repair import NotClosed, Shell, enclosed_volume, featured, shells_of, solid_shells
from fenics_elasto.util.errors import require
from fenics_elasto.util.logs import log

OUTSIDE, BODY = 0, 1


@dataclass
class Part:
    """One shape of the spec as labels: its role, name, spec key and label values."""

    role: str  # "region" or "cavity"
    name: str
    key: str  # 'regions.tumour'
    labels: list[int]

    def describe(self) -> str:
        return f"{self.key} (label {', '.join(map(str, self.labels))})"


def _parts(spec: dict) -> list[Part]:
    parts = [Part("region", n, f"regions.{n}", r["label"]) for n, r in spec["regions"].items()]
    return parts + [Part("cavity", n, f"cavities.{n}", c["label"]) for n, c in spec["cavities"].items()]


def _check_present(image: LabelImage, spec: dict, parts: list[Part], label: str) -> None:
    present = set(np.unique(image.labels).tolist()) - {0}
    named = [("body", v) for v in spec["body"]["label"] or []] + [(p.key, v) for p in parts for v in p.labels]
    for key, value in named:
        require(value in present, f"{label}: {key}: label {value} is not in the image "
                f"(its labels: {', '.join(map(str, sorted(present)))})")


def compact_labels(image: LabelImage, spec: dict, parts: list[Part]) -> np.ndarray:
    """0 outside the body, 1 the body's material, 2 + k the k-th part (regions, then
    cavities). With a box or ellipsoid body, 0 is everything but the parts."""
    from scipy.ndimage import binary_fill_holes

    compact = np.zeros(image.labels.shape, np.int32)
    if spec["body"]["label"] is not None:
        solid = np.isin(image.labels, spec["body"]["label"] + [v for p in parts if p.role == "cavity" for v in p.labels])
        compact[binary_fill_holes(solid)] = BODY
    for k, part in enumerate(parts):
        compact[np.isin(image.labels, part.labels)] = 2 + k
    return compact


def _check_nesting(sides: np.ndarray, parts: list[Part], has_body: bool, label: str) -> dict[int, int]:
    """Every part wrapped in body material or held wholly inside a region (a nodule in a
    gland): no part on the outer boundary (with a label body), no two parts touching
    otherwise. Returns each region held inside another: its index -> the other's."""
    pairs = {tuple(p) for p in np.unique(sides, axis=0).tolist()}
    inside = _held_inside(pairs, parts)
    for a, b in sorted(pairs):
        if a == OUTSIDE and b >= 2 and has_body:
            part = parts[b - 2]
            where = "leaks out of the body: it reaches the body's outer boundary" if part.role == "region" else \
                "opens to the outside of the body"
            require(False, f"{label}: {part.describe()} {where}; it must be wrapped in the body's material")
        if a >= 2 and inside.get(a - 2) != b - 2 and inside.get(b - 2) != a - 2:
            require(False, f"{label}: {parts[a - 2].describe()} and {parts[b - 2].describe()} touch; the scene "
                    "needs the body's material between them, or one held wholly inside the other")
    return inside


def _held_inside(pairs: set, parts: list[Part]) -> dict[int, int]:
    """The regions each held wholly inside another region: part index -> the other's. A
    region is held inside another where that one is all it borders, the regions held
    inside itself aside (found from the innermost out)."""
    borders: dict[int, set[int]] = {k: set() for k in range(len(parts))}
    for a, b in pairs:
        for x, y in ((a, b), (b, a)):
            if x >= 2:
                borders[x - 2].add(y)
    inside: dict[int, int] = {}
    found = True
    while found:
        found = False
        for k in set(borders) - set(inside):
            outer = borders[k] - {2 + c for c, p in inside.items() if p == k}
            if len(outer) == 1 and (o := next(iter(outer)) - 2) >= 0 and parts[k].role == parts[o].role == "region":
                inside[k], found = o, True
    return inside


def _within(k: int, inside: dict[int, int]) -> list[int]:
    """Part k and every part held inside it, at any depth."""
    held = [c for c, p in inside.items() if p == k]
    return [k] + [d for c in held for d in _within(c, inside)]


def _shells(interfaces: Interfaces, inside: list[int], label: str, role: str, name: str) -> list[Shell]:
    points, triangles = interfaces.boundary_of(inside)
    points = smoothed(points, triangles)
    if enclosed_volume(points, triangles) < 0:  # SurfaceNets orients by label order: outward here, not a repair
        triangles = triangles[:, [0, 2, 1]]
    return solid_shells(points, triangles, label, role, name)


def label_shells(spec: dict, folder: Path) -> tuple[Shell | None, list[Shell], np.ndarray]:
    """The body's shell (None when the spec puts a box or an ellipsoid around the
    organs), the regions' and cavities' shells, from the spec's label-map image, and its
    voxel's edges (columns, world coordinates: the segmentation's error, uncertainty/voxels.py)."""
    file = spec["labels"]["image"]
    label = f"labels.image ({file})"
    image = read_label_image(folder / file, label)
    parts = _parts(spec)
    _check_present(image, spec, parts, label)
    compact = compact_labels(image, spec, parts)
    has_body = spec["body"]["label"] is not None
    check_off_border(compact, label)
    interfaces = surface_nets(compact, image.affine)
    inside = _check_nesting(interfaces.sides, parts, has_body, label)
    spacing = " x ".join(f"{s:.3g}" for s in image.spacing)
    log.info(f"{label}: {' x '.join(map(str, compact.shape))} voxels of {spacing} {spec['units']}")
    # a region's shell encloses the regions held inside it: its surface is its outer one
    organs = [s for k, p in enumerate(parts)
              for s in _shells(interfaces, [2 + j for j in _within(k, inside)], f"{p.describe()} of {file}", p.role, p.name)]
    edges = np.asarray(image.affine, float)[:3, :3]
    if not has_body:
        return None, organs, edges
    body = _shells(interfaces, list(range(1, 2 + len(parts))), f"body (label {spec['body']['label']}) of {file}", "body",
                   spec["body"]["material"])
    require(len(body) == 1, f"{label}: body.label {spec['body']['label']}: {len(body)} separate pieces; the body must be one")
    return body[0], organs, edges


# Quadric decimation can fold a triangle through its neighbours (a real kidney's tumour,
# 3,596 -> 2,380 triangles: one); such a try is made again at twice the triangles, at most
# this many times, before the shell is kept as it was.
COARSEN_TRIES = 3


def coarsen(shells: list[Shell], organ_size: float, beyond: float = 1.5) -> list[Shell]:
    """Each shell decimated to about organ_size / 2 edges where it has more than
    ``beyond`` times the triangles that takes, checked again; one line each says what
    changed (volume, Hausdorff distance to the input)."""
    return [_coarsened_shell(shell, organ_size, beyond) for shell in shells]


def _coarsened_shell(shell: Shell, organ_size: float, beyond: float) -> Shell:
    """``coarsen`` for one shell: a decimation that fails the surface checks is tried
    again with edges sqrt(2) shorter, COARSEN_TRIES times in all; then the shell as it was."""
    size, failed = organ_size, None
    for _ in range(COARSEN_TRIES):
        points, triangles = coarsened(shell.points, shell.triangles, size, beyond)
        if len(triangles) == len(shell.triangles):
            break
        try:
            pieces = shells_of(points, triangles, shell.label, shell.role, shell.name)
        except NotClosed as error:
            failed = f"decimated to {len(triangles)} triangles, {error.defect}"
            log.info(f"{shell.label}: {failed}; trying again with twice the triangles")
            size /= np.sqrt(2)
            continue
        require(len(pieces) == 1, f"{shell.label}: split into {len(pieces)} pieces when coarsened; try a smaller organ_size")
        _say_what_changed(shell, pieces[0])
        return featured(pieces[0]) if len(shell.features) else pieces[0]  # a box's edges stay edges
    if failed:
        log.info(f"{shell.label}: kept its {len(shell.triangles)} triangles")
    return shell


def _say_what_changed(before: Shell, after: Shell) -> None:
    import igl

    change = enclosed_volume(after.points, after.triangles) / before.volume - 1
    distance = float(igl.hausdorff(before.points, before.triangles, np.ascontiguousarray(after.points),
                                   np.ascontiguousarray(after.triangles)))
    log.info(f"{before.label}: {len(before.triangles)} -> {len(after.triangles)} triangles (edges ~ organ_size / 2): "
             f"volume {100 * change:+.2f} %, Hausdorff distance to the input {distance:.3g}")
