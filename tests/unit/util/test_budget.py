"""What a mesh will cost, before it is made: the estimated cell counts against gmsh's
own, the refusal and the warning; and the phantom meshed at sizes that used to fail."""

import numpy as np
import pytest

from fenics_elasto.util import budget
from fenics_elasto.app.cli import main
from fenics_elasto.util.errors import UserError
from fenics_elasto.mesh.builtin import ORGAN_SIZE, PHANTOM_HALF, PROSTATE_SIZE, _phantom_cells, phantom_organs
from fenics_elasto.mesh.gmsh_models import fresh_gmsh_model


def cells_in(msh, dim: int) -> int:
    gmsh = fresh_gmsh_model("count")
    gmsh.merge(str(msh))
    count = sum(len(tags) for tags in gmsh.model.mesh.getElements(dim)[1])
    gmsh.clear()
    return count


def test_phantom_estimate_is_gmsh_count(scenes):
    """The size field integrated over the phantom's volume vs the tetrahedra gmsh made."""
    made = cells_in(scenes["prostate-phantom"].parent / "phantom.msh", 3)
    expected = _phantom_cells(phantom_organs(0), PHANTOM_HALF, 1.6, ORGAN_SIZE, PROSTATE_SIZE)
    assert 0.8 < expected / made < 1.25, (expected, made)


def test_letter_estimate_is_gmsh_count(scenes):
    """The letter A's area from its .geo corners (shoelace) over h^2 vs gmsh's triangles."""
    def area(corners):
        x, y = np.array(corners, float).T
        return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))

    letter = area([(0, 0), (1.6, 0), (2.32, 2.4), (5.68, 2.4), (6.4, 0), (8, 0), (5, 10), (3, 10)])
    letter -= area([(2.68, 3.6), (4, 8), (5.32, 3.6)])
    made = cells_in(scenes["letter-a"].parent / "letter_a.msh", 2)
    assert 0.8 < letter / 0.4**2 * budget.CELLS_PER_VOLUME[2] / made < 1.25


def test_a_mesh_that_cannot_fit_is_refused_with_the_size_that_would(caplog):
    with pytest.raises(UserError, match=r"x --size 0.1: about 1e\+07 tetrahedra .* use a size >= 0.5"):
        budget.check_mesh_cost("x --size 0.1", 1e7, 3, 0.1, available=budget.BASE_BYTES + 8e4 * budget.BYTES_PER_CELL[3])
    budget.check_mesh_cost("y --size 1", 1e3, 3, 1.0, available=1e12)
    assert not caplog.records


def test_a_long_mesh_is_warned_about_with_its_time_and_memory(monkeypatch, capfd, tmp_path):
    monkeypatch.setattr(budget, "WARN_SECONDS", 0.0)  # every mesh is "long"
    assert main(["mesh", "letter-a", "--out", str(tmp_path / "a")]) == 0
    warning = [line for line in capfd.readouterr().err.splitlines() if line.startswith("warning: ")]
    assert len(warning) == 1 and "letter-a --size 0.4" in warning[0] and "meshing takes" in warning[0], warning


@pytest.mark.slow
@pytest.mark.parametrize("seed, size", [(18, 1.6), (0, 1.8), (9, 2.0)])
def test_phantom_sizes_where_gmsh_failed_on_the_bones(tmp_path, seed, size):
    """gmsh's surface mesh of the thin bones overlapped itself here (volume left empty,
    exit 0, then "Duplicate mesh entity" in simulate); the bones are now meshed again finer."""
    from fenics_elasto.model.scene import load_scene

    assert main(["mesh", "prostate-phantom", "--out", str(tmp_path), "--size", str(size), "--seed", str(seed)]) == 0
    scene = load_scene(tmp_path / "problem.toml", command="simulate")
    assert scene.mesh.topology.index_map(3).size_global > 1000
