"""The label maps' own error in the answer: the voxel staircase a segmentation leaves.

A surface made from a label map (SurfaceNets, smoothed: geometry/label_surfaces.py)
lies off the organ by a share of its voxels, and that error is correlated over about a
voxel: a residual cannot see it, and the noise part of sigma, which takes the residual's
rows as independent, counts it hundreds of times too small. On a user's kidney with a
stiff tumour (r = 11 mm) segmented at 1 x 1 x 3 mm, the tumour's E came out 30-76 % high
with 95 % intervals that missed the truth in 3 of 7 grids (docs: validation).

Measured on a sphere of radius 11 voxelised at 0.5 x 0.5 x 1, 0.8 x 0.8 x 2, 1 x 1 x 1.5
and 1 x 1 x 3 mm, the grid turned 0-17 degrees (``tests/unit/inverse/test_voxel_error.py``):
a point with unit normal n lies off by an rms of 0.07-0.11 x |n . h| (h: the voxel's
three edges, |n . h| = sqrt(sum_a (n . h_a)^2)), hence VOXEL_SHARE; two points one
largest edge apart share 0.3-0.7 of it, 1.5 edges apart 0.1-0.3, two edges ~0.1: a
Gaussian of CORRELATION_SHARE x the largest edge. A face a few degrees off the grid
steps far less often, and its terraces are longer than the smoothing reaches: there the
error is larger and reaches further (``staircase``, measured on boxes).

Both segmentations count, independently: the source's (a scene ``fenics-elasto scene``
made from a label map writes ``[uncertainty] source_voxels``; the same error field in
every state, at the rest positions) and the target's (``target.labels``: the image's
voxels; each state its own). The answer's linearisation maps such a field to a shift of
s (the controls following, as for ``target_offset``); its std is the ``voxels`` part.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.inverse.uncertainty.posterior import offset_matrix

VOXEL_SHARE = 0.1
CORRELATION_SHARE = 0.8
REACH = 3.0  # correlation lengths beyond which two points are taken as independent (exp(-4.5) = 0.01)
# Faces along the grid. The model above was measured on spheres, whose staircase steps
# every voxel or two. A face at an angle t to a voxel plane steps only every
# period = depth / tan t (depth: the voxel's extent across that plane), and the smoothing
# takes out only short periods: a box's faces 2.5-5.6 degrees off a 0.8 x 0.8 x 1.5 mm
# grid lay off by 2.2x what the spheres' model says, over terraces of 8-17 mm. So a point
# lies off by the larger of the spheres' share and STEP_SHARE of the depth (a sawtooth:
# 1 / sqrt(12)) times the share of its period the smoothing lets through,
# 1 / (1 + (SMOOTHED_PERIOD x the in-plane edge / period)^4), correlated over a sixth of
# the period (at least the spheres' length, at most TERRACE_CAP largest edges).
# Measured on boxes at 3-20 degrees on three grids: 0.43-1.13 of this (test_voxel_error.py).
# Along the grid (within ALIGNED_DEGREES) a face's whole offset is one unknown of up to half
# a voxel, which no correlation length here spans: that is said (grid_aligned_warnings).
STEP_SHARE = 0.3
SMOOTHED_PERIOD = 9.0
TERRACE_CAP = 5.0
ALIGNED_DEGREES = 2.0
ALIGNED_SHARE = 0.25


def voxel_edges(value) -> np.ndarray | None:
    """(3, 3) the voxel's edges as columns, from ``[uncertainty] source_voxels``: a
    3-vector of spacings along x, y, z, or three rows, each an edge in world coordinates
    (the image affine's columns); None where not given."""
    if value is None:
        return None
    edges = np.asarray(value, float)
    return np.diag(edges) if edges.ndim == 1 else edges.T


def normal_std(normals: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The segmentation's rms error along each unit normal for voxels of these edges (a 2D
    scene: the edges in its plane)."""
    gdim = normals.shape[1]
    return VOXEL_SHARE * np.linalg.norm(normals @ edges[:gdim, :gdim], axis=1)


def staircase(normals: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per unit normal: the segmentation's rms error along it and its correlation length,
    for voxels of these edges (the spheres' model, or a long terrace's; see above)."""
    gdim = normals.shape[1]
    edges = edges[:gdim, :gdim]
    duals = np.linalg.inv(edges)  # rows: normals of the voxel planes, over their spacing
    depth = 1.0 / np.linalg.norm(duals, axis=1)
    cosine = np.abs(normals @ (duals * depth[:, None]).T)
    plane = np.argmax(cosine, axis=1)
    c = np.clip(cosine[np.arange(len(plane)), plane], 1e-12, 1.0)
    period = depth[plane] * c / np.maximum(np.sqrt(1.0 - c**2), 1e-12)
    lengths = np.linalg.norm(edges, axis=0)
    in_plane = np.sqrt((np.sum(lengths**2) - lengths**2) / max(gdim - 1, 1))[plane]
    passed = 1.0 / (1.0 + (SMOOTHED_PERIOD * in_plane / period) ** 4)
    std = np.maximum(normal_std(normals, edges), STEP_SHARE * depth[plane] * passed)
    return std, np.clip(period / 6.0, CORRELATION_SHARE * lengths.max(), TERRACE_CAP * lengths.max())


def correlated_sums(weights: np.ndarray, positions: np.ndarray, length) -> np.ndarray:
    """Per row w of ``weights``: sum_ij w_i w_j rho_ij, rho the Gaussian of each point's
    correlation ``length`` (one for all, or one each: Gibbs' kernel,
    (2 l_i l_j / s)^(d/2) exp(-|x_i - x_j|^2 / s), s = l_i^2 + l_j^2, in d dimensions: a
    covariance), the pairs beyond REACH of the longest left out and found once for all rows."""
    lengths = np.broadcast_to(np.asarray(length, float), weights.shape[1:])
    total = np.sum(weights**2, axis=1)
    pairs = cKDTree(positions).query_pairs(REACH * float(lengths.max(initial=0.0)), output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        s = lengths[i] ** 2 + lengths[j] ** 2
        rho = (2.0 * lengths[i] * lengths[j] / s) ** (positions.shape[1] / 2)
        rho *= np.exp(-np.sum((positions[i] - positions[j]) ** 2, axis=1) / s)
        total += 2.0 * (weights[:, i] * weights[:, j]) @ rho
    return total


def target_edges(problem) -> list[np.ndarray | None]:
    """Per row of the stacked misfit, the voxel edges of the label map its target surface
    came from (None for other rows)."""
    out: list[np.ndarray | None] = []
    for misfit in problem.states.misfits:
        rows: list[np.ndarray | None] = [None] * misfit.count
        for span, term in zip(misfit.slices, misfit.terms):
            if isinstance(term, SurfaceTerm):
                for local, which in enumerate(term.surface_of):
                    rows[span.start + local] = term.surfaces[which].voxels
        out += rows
    return out


def _label_maps(problem) -> tuple[np.ndarray, np.ndarray | None, list[np.ndarray | None]]:
    """(the surface rows, the source's voxel edges, each row's target voxel edges); no
    rows where neither the source nor any target came from a label map."""
    surface = problem.misfit.surface_rows()
    source = voxel_edges((problem.scene.config.get("uncertainty") or {}).get("source_voxels"))
    targets = target_edges(problem)
    if source is None and all(targets[row] is None for row in surface):
        surface = surface[:0]
    return surface, source, targets


def voxel_std(problem, lin, evaluation) -> np.ndarray | None:
    """The ``voxels`` part of sigma in s (one std per constant), or None where neither
    the source nor the targets came from a label map."""
    misfit = problem.misfit
    surface, source, targets = _label_maps(problem)
    if not len(surface):
        return None
    rows = misfit.statistical_rows(evaluation.y, evaluation.residual)
    gdim = rows.shape[1]
    scale = np.linalg.norm(rows[surface, 0], axis=1)  # sqrt(w): the weighted residual's change per unit along n
    normals = rows[surface, 0] / np.maximum(scale, 1e-300)[:, None]
    pull = offset_matrix(lin)[:, surface * gdim] * scale  # ds per unit of normal error at each surface row
    variance = np.zeros(pull.shape[0])
    if source is not None:  # one field, at the rest positions: a node's rows in every state move together
        variance += _variance(pull, normals, problem.points[surface], source)
    count = len(problem.observation.points)
    for state in range(problem.states.count):
        mine = [i for i, row in enumerate(surface) if row // count == state and targets[row] is not None]
        # one field per target surface: each surface holds an array of its own (misfit.label_map_targets)
        for edges in {id(targets[surface[i]]): targets[surface[i]] for i in mine}.values():
            same = [i for i in mine if targets[surface[i]] is edges]
            variance += _variance(pull[:, same], normals[same], evaluation.y[surface[same]], edges)
    return np.sqrt(variance)


def _variance(pull: np.ndarray, normals: np.ndarray, positions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    stds, lengths = staircase(normals, edges)
    return correlated_sums(pull * stds, positions, lengths)


def aligned_share(normals: np.ndarray, edges: np.ndarray) -> float:
    """The share of these unit normals within ALIGNED_DEGREES of a voxel plane's normal
    (the rows of edges^-1: the grid's dual directions)."""
    gdim = normals.shape[1]
    planes = np.linalg.inv(edges[:gdim, :gdim])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    return float(np.mean(np.abs(normals @ planes.T).max(axis=1) >= np.cos(np.radians(ALIGNED_DEGREES))))


def grid_aligned_warnings(problem, y: np.ndarray) -> list[str]:
    """One line for the source's label map, and one for the targets' on each voxel grid,
    whose surfaces lie along that grid at over ALIGNED_SHARE of the matched points (y: the
    model's positions, where the targets' normals are taken): the voxels part of sigma
    undercounts their staircase there."""
    misfit = problem.misfit
    surface, source, targets = _label_maps(problem)
    if not len(surface):
        return []  # no label map: no closest-point queries for the normals either
    outward = misfit.offset_residual(y)
    if outward is None:
        return []
    normals = -outward[surface]
    closed = np.linalg.norm(normals, axis=1) > 0.5  # rows of closed surfaces (an outline has none)
    maps: dict[bytes, tuple[str, np.ndarray, list[int]]] = {}
    if source is not None:
        maps[b"source"] = ("the source's label map", source, list(np.flatnonzero(closed)))
    for i in np.flatnonzero(closed):
        edges = targets[surface[i]]
        if edges is not None:  # the targets' maps on one grid together
            maps.setdefault(edges.tobytes(), ("the target label map", edges, []))[2].append(int(i))
    return [_aligned_line(name, share, edges) for name, edges, rows in maps.values()
            if rows and (share := aligned_share(normals[rows], edges)) >= ALIGNED_SHARE]


def mixed_source_warnings(problem) -> list[str]:
    """One line where the source came from a label map and some matched target surfaces
    from surface files: a segmentation's rounded edges and terraces against exact faces
    are one shape error, the same in every fit, which the voxels part (a random staircase)
    does not count. A prostate MR user's box: the rest map against the exact deformed
    surfaces put the gland 11-14 % high, both intervals 1 % short; the same map against
    the deformed map, and exact rest surfaces against either target, held (docs: limits)."""
    surface, source, targets = _label_maps(problem)
    if source is None or all(targets[row] is not None for row in surface):
        return []
    return ["the source came from a label map and the target from surface files: where those surfaces were not "
            "segmented the same way (exact or drawn faces against a label map's rounded edges and terraces), their "
            "shapes differ by one error the voxels part of sigma does not count -- the answer may be off by more than "
            "its interval (a box phantom: E 11-14 % high, its interval 1 % short); targets from the deformed state's "
            "label map ([target.labels]) would hold it"]


def _aligned_line(name: str, share: float, edges: np.ndarray) -> str:
    sizes = " x ".join(f"{v:.2g}" for v in np.linalg.norm(edges, axis=0))
    return (f"{name}'s surfaces lie along its voxel grid ({sizes}; within {ALIGNED_DEGREES:g} degrees) at {share:.0%} "
            "of the matched points: such a face's place is known only to within a voxel, the same unknown over all of "
            "it, which the voxels part of sigma does not count -- the answer may be off by more than its interval; a "
            "grid turned a few degrees against those faces, or surface files, would hold it")
