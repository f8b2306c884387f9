"""What the API's calls return: a simulation and an estimate, each with its field, its
record (result.json's) and what a user reads off it."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from dolfinx import fem

from fenics_elasto.files.outputs import to_json
from fenics_elasto.inverse.report import offset_lines, widened_note
from fenics_elasto.files.writers import surface as group_surface
from fenics_elasto.model.scene import Scene
from fenics_elasto.util.errors import require

if TYPE_CHECKING:
    import pyvista as pv

    from fenics_elasto.inverse.estimator import EstimateResult
    from fenics_elasto.inverse.objective import InverseProblem


class Solution:
    """A displacement field on a scene, and the surfaces of its groups."""

    def __init__(self, scene: Scene, u: fem.Function, record: dict) -> None:
        self.scene = scene
        self.u = u  #: the displacement (a dolfinx Function on the scene's mesh)
        self.record = record  #: what result.json holds of this solve

    def surface(self, group: str, deformed: bool = True) -> pv.PolyData | None:
        """The facet group ``group`` as a pyvista mesh (lines in 2D, triangles in 3D),
        moved by ``u`` unless ``deformed`` is False, with point data "displacement" and
        "|u|". Usable as a target. Collective; the mesh on rank 0, None elsewhere."""
        have = sorted(self.scene.facet_groups)
        require(group in self.scene.facet_groups, f"surface: unknown facet group {group!r} (have {have})")
        return group_surface(self.u, self.scene.facet_groups[group], deformed)

    def to_json(self) -> str:
        """The record as result.json's text."""
        return to_json(self.record)


class Simulation(Solution):
    """A forward solve (``simulate``): ``u``, ``record`` (materials, max_displacement,
    dofs, factorizations, wall_time_s, ...) and ``surface(group)``."""

    def __str__(self) -> str:
        materials = ", ".join(f"{name}: E = {m['E']:.4g}, nu = {m['nu']:.4g}" for name, m in self.record["materials"].items())
        return (f"simulation: {self.record['dofs']} dofs, max |u| {self.record['max_displacement']:.4g}, "
                f"{self.record['wall_time_s']:.2f} s ({materials})")


class Estimate(Solution):
    """An estimate's answer (``estimate``).

    ``values``, ``std`` and ``ci95`` are keyed "region.param" (e.g. "inclusion.E") over
    the estimated constants; ``std`` is NaN and ``ci95`` (NaN, NaN) where no uncertainty
    was computed (a run interrupted while it was being worked out, or one whose inner
    solver keeps no response of the controls; a run interrupted earlier has the Laplace
    interval at its best value); ``parts`` splits each std by its sources. ``materials``
    holds every region's E and nu, ``forces`` the recovered nodal forces of the loaded
    nodes (flat), ``warnings`` what the estimate found worth a warning, ``record`` all of
    result.json.
    """

    def __init__(self, scene: Scene, outcome: EstimateResult, problem: InverseProblem,
                 basis: np.ndarray | None = None) -> None:
        super().__init__(scene, outcome.u, outcome.record)
        self.outcome = outcome  #: the estimator's own result (theta, evaluation, ...)
        self.problem = problem  #: the inverse problem it solved (forward model, observation, misfit)
        self.basis = basis  #: the reduced bases W used, or None (the full force space)

    @property
    def values(self) -> dict[str, float]:
        """The estimated constants, "region.param" -> value."""
        return self.outcome.estimated

    @property
    def std(self) -> dict[str, float]:
        """Each estimated constant's standard deviation (NaN if not computed)."""
        return {label: float(self._uncertainty(label).get("std", math.nan)) for label in self.values}

    @property
    def ci95(self) -> dict[str, tuple[float, float]]:
        """Each estimated constant's 95 % interval (low, high); (NaN, NaN) if not computed."""
        out = {}
        for label in self.values:
            low, high = self._uncertainty(label).get("ci95", (math.nan, math.nan))
            out[label] = (float(low), float(high))
        return out

    @property
    def parts(self) -> dict[str, dict[str, float]]:
        """Each estimated constant's sigma by its sources ("noise", "mesh", "bases",
        "target_offset", "voxels", ...: result.json's ``parts``); empty if not computed."""
        return {label: {part: float(v) for part, v in self._uncertainty(label).get("parts", {}).items()}
                for label in self.values}

    def _uncertainty(self, label: str) -> dict[str, Any]:
        entry = (self.record.get("uncertainty") or {}).get(label)
        return entry if isinstance(entry, dict) else {}

    @property
    def materials(self) -> dict[str, dict[str, float]]:
        """Every region's E and nu, estimated or fixed."""
        return self.record["materials"]

    @property
    def warnings(self) -> list[str]:
        """What the estimate found worth a warning, one line each."""
        return list(self.record["warnings"])

    @property
    def forces(self) -> np.ndarray:
        """The recovered nodal forces of the loaded nodes, flat (node by node)."""
        return self.outcome.forces

    @property
    def interrupted(self) -> bool:
        """Stopped by Ctrl-C: the answer is the best so far."""
        return bool(self.record["interrupted"])

    def __str__(self) -> str:
        lines = ["estimate" + (" (interrupted: the best so far)" if self.interrupted else "")]
        for label, value in self.values.items():
            sd, (low, high) = self.std[label], self.ci95[label]
            sure = f" ± {sd:.2g} (95 %: {low:.4g} to {high:.4g})" if np.isfinite(sd) else ""
            uncertainty = self.record.get("uncertainty") or {}
            parts = uncertainty.get(label, {}).get("parts", {})
            if sure and any(v > 0 for name, v in parts.items() if name != "noise"):
                sure += "; parts of sigma: " + ", ".join(f"{name} {v:.2g}" for name, v in parts.items())
            if sure:
                sure += widened_note((uncertainty.get("widened") or {}).get(label, 1.0))
            lines.append(f"  {label} = {value:.5g}{sure}")
        lines += self._offset_lines()
        distance = self.record.get("surface_distance") or {}
        if "rms" in distance:
            lines.append(f"  rms distance to the target {distance['rms']:.3g} (max {distance['max']:.3g})")
        lines.append(f"  {self.record['dofs']} dofs, {self.record['factorizations']} factorizations, "
                     f"{self.record['wall_time_s']:.1f} s")
        lines += [f"  warning: {text}" for text in self.warnings]
        return "\n".join(lines)

    def _offset_lines(self) -> list[str]:
        """What a target bigger all round would do (report.describe_offset, from result.json)."""
        offset = (self.record.get("uncertainty") or {}).get("target_offset")
        if not offset:
            return []
        # result.json holds the shifts in units (relative for E); offset_lines takes them in s = (log E, nu)
        shifts = [(label, np.log(max(1.0 + shift, 1e-300)) if label.endswith(".E") else shift, label.endswith(".E"))
                  for label, shift in offset["shift"].items() if shift is not None]
        return ["  " + line for line in offset_lines(offset["offset"], shifts)]
