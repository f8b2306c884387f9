"""The parallel copy of a scene's .msh (model/mesh_copy.py): the first load writes what
it made, later loads -- on any number of ranks -- read the same mesh from it, without
gmsh; an edited .msh gets a new copy."""

import json
from pathlib import Path

import pytest

import fenics_elasto  # noqa: F401  (dolfinx_solver first)
from conftest import TESTS, logged, run_mpi_script
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.mesh.gmsh_models import GmshModel, write_msh
from fenics_elasto.model import scene as scene_module
from fenics_elasto.model.mesh_copy import folder_of
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate
from mpi.mesh_copy import mesh_summary


def _without_gmsh(monkeypatch) -> None:
    def refuse(*args):
        raise AssertionError("the .msh was opened although its copy is current")

    monkeypatch.setattr(scene_module, "_open_checked", refuse)


def _ball_in_box(path: Path, size: float) -> None:
    """A straight-sided (order 1) box with a ball region, as plain gmsh writes it."""
    with GmshModel("ball") as gmsh:
        occ = gmsh.model.occ
        box, ball = occ.addBox(-2, -2, -2, 4, 4, 4), occ.addSphere(0, 0, 0, 1.0)
        occ.fragment([(3, box)], [(3, ball)])
        occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [ball], name="ball")
        gmsh.model.addPhysicalGroup(3, [t for _, t in gmsh.model.getEntities(3) if t != ball], name="tissue")
        sphere = [t for _, t in gmsh.model.getBoundary([(3, ball)], oriented=False)]
        gmsh.model.addPhysicalGroup(2, sphere, name="ball_surface")
        gmsh.model.addPhysicalGroup(2, [t for _, t in gmsh.model.getEntities(2) if t not in sphere], name="skin")
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        write_msh(gmsh, path, 3)


def test_the_copy_gives_what_the_msh_gives(tmp_path, monkeypatch):
    """The letter A's overlapping groups (feet inside outline) survive the copy, and a
    simulation on the copy's mesh is the .msh's to rounding."""
    problem = build_scene("letter-a", tmp_path / "letter")
    msh = problem.parent / "letter_a.msh"
    first_u = simulate(load_scene(problem)).u.x.array  # the first load: gmsh, then the copy written
    assert (folder_of(msh) / "copy.json").exists()
    first = mesh_summary(msh, curve=True)  # as load_scene reads a P2 scene (a 2D one is never curved)
    _without_gmsh(monkeypatch)
    assert mesh_summary(msh, curve=True) == first
    assert first["facets"]["feet"] < first["facets"]["outline"]
    # The first load reads its copy back: the same DOF order, so the same array exactly
    assert (simulate(load_scene(problem)).u.x.array == first_u).all()


def test_a_curved_copy_keeps_the_curving_and_says_so(tmp_path, monkeypatch):
    """A straight-sided 3D mesh is curved once, on its first load; the copy holds the
    curved geometry and its later loads repeat the curving's line."""
    msh = tmp_path / "ball.msh"
    _ball_in_box(msh, 0.8)
    lines: list = []
    with logged(lines):
        first = mesh_summary(msh, curve=True)
    assert first["degree"] == 2 and any("curved on load" in line for line in lines)
    with monkeypatch.context() as patched:
        _without_gmsh(patched)
        lines.clear()
        with logged(lines):
            assert mesh_summary(msh, curve=True) == first
        assert any("curved on load" in line and "parallel copy" in line for line in lines)
    straight = mesh_summary(msh, curve=False)  # another setting: the .msh again, and another copy
    assert straight["degree"] == 1 and straight["moment"] != first["moment"]


def test_an_edited_msh_gets_a_new_copy(tmp_path):
    msh = tmp_path / "ball.msh"
    _ball_in_box(msh, 0.8)
    coarse = mesh_summary(msh, curve=False)
    _ball_in_box(msh, 0.6)
    fine = mesh_summary(msh, curve=False)
    assert fine["cells"] > coarse["cells"]
    assert json.loads((folder_of(msh) / "copy.json").read_text())["key"]["size"] == msh.stat().st_size


def test_two_ranks_read_the_copy_as_one_does(tmp_path):
    """The copy written by one rank, read by two (each a slice: no rank holds the whole
    mesh), gives the same mesh, and a copy written by two ranks reads back in one."""
    msh = tmp_path / "ball.msh"
    _ball_in_box(msh, 0.8)
    serial = mesh_summary(msh, curve=True)
    run_mpi_script(TESTS / "mpi" / "mesh_copy.py", 2, msh, tmp_path / "two.json")
    two = json.loads((tmp_path / "two.json").read_text())
    assert two.pop("moment") == pytest.approx(serial.pop("moment"), rel=1e-12)
    assert two == json.loads(json.dumps(serial))
    other = tmp_path / "written_by_two" / "ball.msh"
    other.parent.mkdir()
    other.write_bytes(msh.read_bytes())
    run_mpi_script(TESTS / "mpi" / "mesh_copy.py", 2, other, tmp_path / "written.json")
    assert (folder_of(other) / "copy.json").exists()
    assert mesh_summary(other, curve=True)["cells"] == serial["cells"]

