"""The demos run end to end and meet their stated accuracy."""

import re
import subprocess
import sys

import pytest

from conftest import ROOT, assert_picture


def run_demo(script: str, *args, timeout=1200) -> str:
    proc = subprocess.run([sys.executable, str(ROOT / "demos" / script), *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.slow
def test_letter_a_poisson_demo_beats_the_paper(tmp_path):
    """The paper: ~10 % error and ~4 s per case; the issue asks for < 2 % and < 2 s."""
    stdout = run_demo("letter_a_poisson.py", "--out", tmp_path)
    rows = re.findall(r"^\| (0\.\d+) \| (0\.\d+) \| ([\d.]+) \| ([\d.]+) \|", stdout, re.M)
    assert len(rows) == 4, stdout
    for true, found, error, _seconds in rows:
        assert float(error) < 2.0, (true, found, error)
    assert_picture(tmp_path / "letter_a_poisson.png")


@pytest.mark.slow
def test_prostate_demo_quick(tmp_path):
    stdout = run_demo("prostate_elastography.py", "--quick", "--out", tmp_path)
    assert "Table 1" in stdout
    index = (tmp_path / "index.md").read_text()
    assert "fig8_rank.png" in index and "fig7_bases.png" in index
    for picture in ("fig8_rank.png", "fig7_bases.png"):
        assert_picture(tmp_path / picture)
    row = re.search(r"^\| 50 \| ([\d.]+) \| ([\d.]+) \|", index, re.M)
    assert row and float(row.group(2)) < 15.0, index  # reduced rank 6 on a coarse phantom; see README


QUICK_BOUND = 10.0  # % on the E ratio (see the README's real-prostate table)


@pytest.mark.slow
def test_real_prostate_demo_quick(tmp_path):
    """Surface files -> scene -> simulate -> image-like targets -> train -> estimate, on
    the real prostate, through the command line. The bound is loose on purpose (see
    the demo's README section): the quick run's coarse source mesh and rank-40 bases
    leave a misfit floor that moves E by up to ~BOUND %, and the point is that every
    kind of target -- clean, noisy, voxelised -- lands near the truth, not far off
    (a wrong set-up, or targets in the wrong place, miss by far more)."""
    import json

    run_demo("real_prostate.py", "--quick", "--out", tmp_path, timeout=2400)
    rows = json.loads((tmp_path / "table.json").read_text())
    assert {r["target"] for r in rows} == {"noise 0.5 mm", "voxels 1 mm"}
    index = (tmp_path / "index.md").read_text()
    assert "| true E ratio | target |" in index
    for r in rows:
        assert abs(r["error_percent"]) < QUICK_BOUND, r  # set from the measured quick run
        assert r["bases_fit"] > 0.95, r
    for picture in ("truth.png", "targets.png", "estimate_voxels_1_mm.png", "bases.png"):
        assert picture in index
        assert_picture(tmp_path / picture)
