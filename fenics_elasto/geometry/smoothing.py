"""A measured surface's own noise, and Taubin smoothing of a rough one.

A target surface from a segmentation or a scan carries noise that the fit's residual
cannot see (the closest point to a rough surface is its nearest spike); its vertices
show it against their neighbours (``roughness``). A target rougher than its own
sampling makes the misfit jagged in the materials, so it is smoothed first (``smoothed``).
"""

from __future__ import annotations

import weakref

import numpy as np

from fenics_elasto.geometry.meshes import rings
from fenics_elasto.geometry.surface import Surface

ROUGH_SHARE = 0.1  # a target rougher than this share of its mean edge is smoothed before matching
TAUBIN_STEPS = (0.5, -0.5)  # lambda, mu of smoothed()
TAUBIN_PASSES = 20  # noise falls ~13x on the phantom's organs; a clean organ moves < 1e-5 of its size
_ROUGHNESS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # a pass over every vertex: once per surface


def is_rough(surface: Surface) -> bool:
    """Noisier than its own sampling resolves: roughness above ROUGH_SHARE of the mean
    edge (clean simulated and segmented targets measure 0.0001-0.03 of it; 0.25 % noise
    on the phantom's finely sampled organs 0.27)."""
    return roughness(surface) > ROUGH_SHARE * surface.mean_edge


def smoothed(surface: Surface, passes: int = TAUBIN_PASSES) -> Surface:
    """Taubin's lambda|mu smoothing (a shrink step lambda = 0.5, then an inflate step
    mu = -0.5 of the umbrella Laplacian, ``passes`` times): a low-pass filter that
    removes noise at the sampling's wavelength (an eigenvalue k of the Laplacian is
    damped by (1 - k^2 / 4)^passes) while a smooth shape, k ~ 0, moves only to second
    order -- a plain Laplacian shrinks it, Taubin's mu = -0.53 inflated the phantom's
    organs by 1.4e-4 cm, worth ~1 % of E. Rim vertices stay put."""
    adjacency, valence, rim = rings(surface.cells, len(surface.points), surface.dim)
    n = len(surface.points)
    inner = ~rim & (valence >= 2)
    # The filter is linear and acts on each column alike: a column of unit white noise
    # beside the coordinates measures how much of the target's noise it lets through.
    probe = np.random.default_rng(0).standard_normal(n)
    columns = np.c_[surface.points, probe]
    for _ in range(passes):
        for factor in TAUBIN_STEPS:
            umbrella = adjacency @ columns / np.maximum(valence, 1)[:, None] - columns
            columns += factor * inner[:, None] * umbrella
    out = Surface(columns[:, :-1], surface.cells)
    out.smoothed_from = roughness(surface)
    out.noise_gain = float(np.std(columns[inner, -1])) if inner.any() else 1.0
    return out


def noise(surface: Surface) -> float:
    """The noise a point matched to this surface sees: its roughness; once smoothed,
    the noise it had times the filter's gain -- the roughness left measures only the
    highest frequencies, while the filtered noise keeps wiggles a few samples long
    (the letter at 1 % noise: roughness 0.092 -> 0.006, filtered noise ~0.4 x 0.092)."""
    if surface.smoothed_from is None:
        return roughness(surface)
    return surface.noise_gain * surface.smoothed_from


def roughness(surface: Surface) -> float:
    """The noise a measured surface carries, from the surface alone: each vertex's offset
    along the normal from the mean of its neighbours (the umbrella Laplacian), whose
    variance is (1 + 1/m) x the noise's for m neighbours; the median over interior
    vertices, so that corners and feature edges (a few vertices each) do not count, and
    a smooth surface sampled finely (a simulated target) gives ~0 (curvature adds ~edge^2 /
    radius: 0.02 for 0.6-long edges on a sphere of radius 20). A fit's residual
    cannot see this noise -- the closest point to a rough surface is its nearest spike,
    so residuals run at 0.4-0.7x the noise."""
    if surface in _ROUGHNESS:
        return _ROUGHNESS[surface]
    points, cells = surface.points, surface.cells
    adjacency, valence, rim = rings(cells, len(points), surface.dim)
    inner = ~rim & (valence >= 2)
    if inner.sum() < 10:
        _ROUGHNESS[surface] = 0.0
        return 0.0
    offset = points - adjacency @ points / np.maximum(valence, 1)[:, None]
    normal = np.zeros_like(points)  # area-weighted vertex normals (2D: of the two segments)
    for column in range(cells.shape[1]):
        np.add.at(normal, cells[:, column], surface.area_normals)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    height = np.einsum("nd,nd->n", offset, normal)[inner]
    m = valence[inner]
    _ROUGHNESS[surface] = float(np.sqrt(np.median(height**2 / (1 + 1 / m)) / 0.454936))  # median of chi2(1): 0.4549
    return _ROUGHNESS[surface]
