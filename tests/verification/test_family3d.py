"""3D estimates on meshes users have: the pelvis phantom meshed by plain gmsh (order 1,
straight-sided, and order 2), never by this package; the truth from scikit-fem on its
own finer curved mesh with wall motion no affine map has (tests/independent.py); the
organ surfaces and 4 fiducials inside the prostate observed. The README's workflow:
`train --synthetic 120 --rank 80`, then `estimate` at default settings.

benchmarks/family3d.py runs the whole family (two geometries, E 25 / 50 / 75).
"""

import json

import numpy as np
import pytest

import independent as ind
from fenics_elasto.app.cli import main

TRUE_E = 50.0
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("family3d")]  # one worker: the truth is made once


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """The scikit-fem truth at prostate E = 50 and the folder for the sources."""
    out = tmp_path_factory.mktemp("family3d")
    return out, ind.phantom(out / "truth", TRUE_E)


def _estimate(problem, bases, out) -> dict:
    assert main(["estimate", str(problem), "--out", str(out), "--set", f"reduction={{bases='{bases}'}}"]) == 0
    return json.loads((out / "result.json").read_text())


def _source(family, order: int):
    """A plain gmsh source of the phantom, its bases, and a problem observing the organ
    surfaces and the fiducials. (The surfaces alone, benchmarks/family3d.py --data
    surfaces: at default weight the 4 fiducials narrowed the order-1 interval by 1 %
    only, 9.80 -> 9.67.)"""
    out, truth = family
    problem = ind.plain_source(out / "sources", order)
    bases = problem.parent / "bases.npz"
    if not bases.is_file():
        assert main(["train", str(problem), "--synthetic", "120", "--rank", "80", "--out", str(bases)]) == 0
    surfaces = {g: truth[g] for g in ("bladder", "prostate_surface", "rectum")}
    return ind.retarget(problem, {"surfaces": surfaces, "landmarks": truth["fiducials"]}), bases


# |E / truth - 1| at most: measured -0.27 % (order 1, curved on load; -3.9 % before its
# bones were read from their CAD faces) and +0.24 % (order 2); #31's goal is 3 %.
BOUND = 0.03


@pytest.mark.parametrize("order", [1, 2])
def test_prostate_E_on_a_plain_gmsh_source(family, tmp_path, order):
    """(a) order 1: straight-sided, curved on load; (b) order 2: gmsh's own curved mesh.
    Within 3 % of the truth, the interval holding it; (c) the noise-free target's error
    is no larger than the model's own part of sigma (mesh and bases) says (measured:
    0.13 against 1.44 on order 1, 0.12 against 1.54 on order 2), whose bases part holds
    half the answer's move at half the rank."""
    result = _estimate(*_source(family, order), tmp_path / "out")
    E = result["materials"]["prostate"]["E"]
    u = result["uncertainty"]["prostate.E"]
    low, high = u["ci95"]
    parts = u["parts"]
    print(f"plain gmsh order {order}: E = {E:.3f} ({100 * (E / TRUE_E - 1):+.2f} %), [{low:.2f}, {high:.2f}], "
          f"parts {parts}, mesh shift {result['uncertainty'].get('mesh_shift')}")
    assert abs(E / TRUE_E - 1) < BOUND, E
    assert low < TRUE_E < high, (low, high)
    assert parts["mesh"] > 0 and "mesh_shift" in result["uncertainty"], result["uncertainty"]
    assert np.hypot(parts["mesh"], parts["bases"]) >= abs(E - TRUE_E), parts
    half = result["bases_fit"]["shift_at_half_rank"]["prostate.E"]  # half of it is in the bases part (measured +2.0 %)
    assert abs(half) > 0.005 and parts["bases"] >= (1 - 1e-9) * 0.5 * abs(np.log1p(half)) * E, (half, parts)
