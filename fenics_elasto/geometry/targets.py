"""Target surfaces of groups of points: each point's closest point on its own surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fenics_elasto.geometry.smoothing import noise
from fenics_elasto.geometry.surface import Surface


@dataclass
class SurfaceTerm:
    """Rows matched to surfaces: ``surface_of[l]`` indexes ``surfaces``."""

    surfaces: list[Surface]
    surface_of: np.ndarray

    def residual(self, y: np.ndarray) -> np.ndarray:
        return y - self.closest(y)

    def closest(self, y: np.ndarray) -> np.ndarray:
        out = np.empty_like(y)
        for i, surface in enumerate(self.surfaces):
            rows = np.flatnonzero(self.surface_of == i)
            out[rows] = surface.closest(y[rows])
        return out

    def roughness(self) -> float:
        """The targets' own noise (Surface.noise), rms over the rows matched to each."""
        counts = np.bincount(self.surface_of, minlength=len(self.surfaces))
        variance = sum(float(c) * noise(s) ** 2 for c, s in zip(counts, self.surfaces) if c)
        return float(np.sqrt(variance / max(int(counts.sum()), 1)))

    def outward(self, y: np.ndarray) -> np.ndarray:
        """(n, gdim) the outward normal of each row's closed target surface at its closest
        point; zero rows for outlines and open surfaces."""
        out = np.zeros_like(y)
        for i, surface in enumerate(self.surfaces):
            rows = np.flatnonzero(self.surface_of == i)
            normal = surface.outward(y[rows]) if len(rows) else None
            if normal is not None:
                out[rows] = normal
        return out

    def curvature_directions(self, y: np.ndarray, smooth: bool = False) -> np.ndarray:
        out = np.zeros(y.shape + (y.shape[1],))
        for i, surface in enumerate(self.surfaces):
            rows = np.flatnonzero(self.surface_of == i)
            out[rows] = surface.curvature_directions(y[rows], smooth)
        return out
