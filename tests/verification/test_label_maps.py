"""A tumour's stiffness from two label maps, against a truth the toolkit did not make:
tests/independent.py's kidney (scikit-fem P2 on its own curved gmsh mesh, the hilum
clamped, a rounded probe pressing, dragging and rippling one side), imaged at rest and
pressed on 1 x 1 x 1.5 mm voxels in a rotated frame. The user's chain: `scene` of the
rest map, `train --synthetic 60 --rank 24`, `estimate` from the pressed map.

benchmarks/kidney_labelmaps.py runs the E ratios 2 / 4 / 8 at two pushes on a finer
truth (within -11 to -3 %, every interval holding; the exact surfaces instead of the
pressed map: -6 to +10 %)."""

import pytest

import independent as ind

pytestmark = pytest.mark.slow


def test_tumour_E_from_two_label_maps(tmp_path):
    """E ratio 4 pressed by 10 mm, the truth at element sizes 2 / 4.5 mm (45k DOFs: made
    in ~30 s with its images) and the source at organ_size 4: measured 35.3 for 40 (the
    truth's own coarseness: 37.7 against the finer one), 95 % 23.3-53.9 (26.3-47.7 before
    the voxels part counted the flattest parts' long terraces, stop 68). Before the
    label surfaces were smoothed (the Taubin pass had been a no-op) such chains gave
    +60 to +150 %, two intervals in six missing."""
    truth = ind.kidney(tmp_path / "truth", 4.0, push=10.0, tumour_size=2.0, far=4.5)
    result = ind.kidney_chain(truth, tmp_path / "chain", organ_size=4.0)
    E = result["materials"]["tumour"]["E"]
    low, high = result["uncertainty"]["tumour.E"]["ci95"]
    assert E == pytest.approx(40.0, rel=0.2)
    assert low <= 40.0 <= high
    assert high / low < 2.5  # the maps determine E: before the fix the interval spanned 4x and more
    parts = result["uncertainty"]["tumour.E"]["parts"]
    assert 0.2 * parts["noise"] < parts["voxels"] < 5 * parts["noise"]  # both maps' staircase, counted (voxels.py)
    assert not any("voxel grid" in line for line in result["warnings"])  # a curved kidney: the model holds there
