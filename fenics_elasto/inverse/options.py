"""The optimiser's settings: problem.toml's [optimizer] table, checked by config/problem.py."""

from __future__ import annotations

from dataclasses import dataclass


# A Gauss-Newton fit stops at this share of inner_tol (it was inner_tol squared, 1e-12).
# Its tail is long where points slide across the target's facets: the default phantom's
# rank-240 start fit took 326 iterations, 7 to come within 1e-7 of its end and 319 for
# the last 5e-9. At 1e-10 it takes 77; E moved 4e-8 (relative) and sigma 3e-7
# (docs/performance.md, "The rank table").
GAUSS_NEWTON_SHARE = 1e-4


@dataclass
class Options:
    inner: str = "auto"
    inner_maxiter: int = 400
    outer_maxiter: int = 40
    outer_xtol: float = 1e-3  # the outer loop stops once a step moves log E by less (nu: a tenth of it);
    # on the surrogate also within a share of the noise std (Estimator.settled_within)
    scan: int = 5  # material values per estimated constant in the initial scan (1: the initial values only)
    inner_tol: float = 1e-6  # relative decrease of Phi that ends an L-BFGS inner loop (Gauss-Newton: ``gauss_newton_tol``)
    full_gn_limit: int = 1500  # largest full force space for which "auto" picks Gauss-Newton
    anchor: float = 1e-4  # Gauss-Newton prior towards the surface-matched start, relative to the data curvature
    surrogate: bool = True  # reduced bases: outer loop on the reduced-basis response in the materials
    matched_motion: str = "auto"  # reduced bases: the states' matched wall motions join them (auto: no measured force)
    allow_undetermined: bool = False  # run a set-up the data cannot determine (with a warning)
    state_noise: str = "residual"  # several states, no target.noise: weighed by their residuals' levels, or "alike"

    @property
    def gauss_newton_tol(self) -> float:
        """The relative decrease of Phi that ends a Gauss-Newton fit: GAUSS_NEWTON_SHARE of
        ``inner_tol`` (1e-10 at the default)."""
        return GAUSS_NEWTON_SHARE * self.inner_tol

    @classmethod
    def from_scene(cls, scene) -> Options:
        """The scene's [optimizer] table (checked and completed by config.py)."""
        return cls(**scene.config["optimizer"])
