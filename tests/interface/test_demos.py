"""The demos run end to end and meet their stated accuracy."""

import re
import subprocess
import sys

import pytest

from conftest import ROOT, assert_picture


def run_demo(script: str, *args, timeout=1200, cwd=None) -> str:
    proc = subprocess.run([sys.executable, str(ROOT / "demos" / script), *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.slow
def test_letter_a_poisson_demo_beats_the_paper(tmp_path):
    """The paper: ~10 % error and ~4 s per case; the issue asks for < 2 % and < 2 s. The demo
    is a literate script without options (docs/demos): it writes to out/letter_a of its folder."""
    stdout = run_demo("letter_a_poisson.py", cwd=tmp_path)
    rows = re.findall(r"^\| (0\.\d+) \| (0\.\d+) \| ([\d.]+) \| ([\d.]+) \|", stdout, re.M)
    assert len(rows) == 4, stdout
    for true, found, error, _seconds in rows:
        assert float(error) < 2.0, (true, found, error)
    assert_picture(tmp_path / "out" / "letter_a" / "letter_a_poisson.png")


@pytest.mark.slow
def test_prostate_demo_quick(tmp_path):
    """The literate prostate demo (docs/demos) reads --quick and --out from the command line
    (make demo-quick): one target E, no full-space comparison, ranks 1 and 12, no atlas study
    (test_reduction.py's held-out patient runs the atlas through the command line)."""
    stdout = run_demo("prostate_elastography.py", "--quick", "--out", tmp_path)
    assert "Table 1" in stdout
    index = (tmp_path / "index.md").read_text()
    assert "fig8_rank.png" in index and "fig7_bases.png" in index
    for picture in ("fig8_rank.png", "fig7_bases.png"):
        assert_picture(tmp_path / picture)
    row = re.search(r"^\| 50 \| ([\d.]+) \| ([\d.]+) \|", index, re.M)
    assert row and float(row.group(2)) < 15.0, index  # reduced rank 6 on a coarse phantom; see docs/validation.md


@pytest.mark.slow
def test_real_prostate_chain(tmp_path):
    """The real prostate from STL files to an estimate through the command line (`--ci`:
    coarse meshes, rank 40 of 60 synthetic examples, one voxelised target; ~2 min).
    The chain is what is checked here: every command succeeds, the bases explain the
    wall motion, the result carries its interval, the pictures are drawn, and the
    prostate comes out stiffer than the tissue and within a factor 2 of the truth. It
    is not an accuracy test: on these coarse meshes E is off by +52 % (rank 40) or
    +13 % (rank 80), with an interval that states noise only; docs/validation.md's table of the
    quick and full runs (+5 % and better) is the accuracy claim."""
    import json

    run_demo("real_prostate.py", "--ci", "--out", tmp_path, timeout=1200)
    rows = json.loads((tmp_path / "table.json").read_text())
    assert [r["target"] for r in rows] == ["voxels 1 mm"]
    row = rows[0]
    assert 1.5 < row["ratio"] < 6.0, row  # truth 3
    assert row["bases_fit"] > 0.95 and row["sigma"] > 0, row
    index = (tmp_path / "index.md").read_text()
    for picture in ("truth.png", "targets.png", "estimate_voxels_1_mm.png", "bases.png"):
        assert picture in index
        assert_picture(tmp_path / picture)


QUICK_BOUND = 7.0  # % on the E ratio: the quick run measured +4.9 % (noise) and +5.9 % (voxels)


@pytest.mark.slow
@pytest.mark.demo
def test_real_prostate_demo_quick(tmp_path):
    """Surface files -> scene -> simulate -> image-like targets -> train -> estimate, on
    the real prostate, through the command line (`make test-demo`, ~13 min). The quick
    run's coarse source mesh (16 mm, 5.3 mm at the organs) leaves a bias of ~5 %
    (measured +4.9 % noisy, +5.9 % voxelised); the bound keeps that and no more."""
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
