"""Meshing helpers (mesh/gmsh_models.py): folded curved cells straightened until none is left."""

from types import SimpleNamespace

import numpy as np

import fenics_elasto  # noqa: F401  (dolfinx_solver first)
from fenics_elasto.mesh import gmsh_models


def test_untangle_straightens_until_no_cell_folds(monkeypatch):
    """Straightening one cell's edges can fold a neighbour sharing them, and that one the
    next: a prostate label map's scene folded 79, 3, 1 and 1 cells in four rounds and was
    refused while three rounds were allowed. Here gmsh's optimisation leaves a chain of
    four cells that fold one after another as each is straightened: all four end with
    their midpoints on their chords."""
    positions = np.zeros((41, 3))
    positions[1:] = np.random.default_rng(0).normal(size=(40, 3))
    cells = np.arange(1, 41).reshape(4, 10)  # four 10-node tets, node tags 1-40
    straight = set()

    def folded(_gmsh):
        """The first cell not yet straightened folds, once its predecessors are straight."""
        left = [i for i in range(4) if i not in straight][:1]
        return np.array(left, np.int64), cells[left]

    def set_node(tag, point, _parametric):
        positions[tag] = point
        straight.add(int(np.flatnonzero(cells.ravel() == tag)[0]) // 10)  # its cell is straightened

    gmsh = SimpleNamespace(option=SimpleNamespace(setNumber=lambda *_: None),
                           model=SimpleNamespace(mesh=SimpleNamespace(optimize=lambda *_: None, setNode=set_node)))
    monkeypatch.setattr(gmsh_models, "folded_tetrahedra", folded)
    monkeypatch.setattr(gmsh_models, "node_positions", lambda _gmsh: positions.copy())

    assert gmsh_models.untangle(gmsh) == 4
    assert folded(gmsh)[0].size == 0
    for row in cells:
        for a, b, m in gmsh_models.TET10_EDGES:
            assert np.allclose(positions[row[m]], (positions[row[a]] + positions[row[b]]) / 2)


def test_a_mesh_of_its_own_it_cannot_use_names_the_sizes(monkeypatch, tmp_path):
    """The mesh check's advice for a folded cell names gmsh's options, which a user of
    `scene` does not have: a mesh the toolkit made is refused with the sizes as the lever."""
    import pytest

    from fenics_elasto.util.errors import UserError

    def refuse(_gmsh, label, _tdim):
        raise UserError(f"{label}: 1 curved cell(s) fold over; untangle them (gmsh: Mesh.HighOrderOptimize = 1)")

    monkeypatch.setattr(gmsh_models, "check_mesh", refuse)
    gmsh = SimpleNamespace(model=SimpleNamespace(getPhysicalGroups=lambda: [(3, 1)]))
    with pytest.raises(UserError, match=r"scene.msh as meshed: 1 curved cell.* a slightly different size or organ_size"):
        gmsh_models.save(gmsh, tmp_path / "scene.msh")
