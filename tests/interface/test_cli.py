"""Command line: mesh -> simulate for every built-in scene, and bad input -> exit 2."""

import json

import pytest

from conftest import assert_picture, run_cli
from fenics_elasto.app.cli import main


@pytest.mark.slow
@pytest.mark.parametrize("name, size", [("letter-a", None), ("cantilever", None), ("prostate-phantom", 1.6)])
def test_mesh_then_simulate(tmp_path, name, size):
    args = ["mesh", name, "--out", tmp_path / "scene"] + (["--size", size] if size else [])
    assert run_cli(*args).returncode == 0
    proc = run_cli("simulate", tmp_path / "scene" / "problem.toml", "--out", tmp_path / "result")
    assert proc.returncode == 0, proc.stderr
    result = json.loads((tmp_path / "result" / "result.json").read_text())
    assert result["dofs"] > 1000 and result["factorizations"] == 1
    assert result["max_displacement"] > 0.01
    for produced in ("screenshot.png", "surface.vtp", "displacement.bp"):
        assert (tmp_path / "result" / produced).exists(), produced
    assert_picture(tmp_path / "result" / "screenshot.png", 0.05)
    proc = run_cli("render", tmp_path / "result", "--out", tmp_path / "again.png")
    assert proc.returncode == 0
    assert_picture(tmp_path / "again.png")


def _problem(tmp_path, scenes, name, edit=lambda text: text):
    """A copy of a built-in scene's problem.toml next to its mesh, edited."""
    source = scenes[name]
    path = source.parent / f"edited_{tmp_path.name}.toml"
    path.write_text(edit(source.read_text()))
    return path


def _expect_user_error(capsys, argv, *words):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    for word in words:
        assert word in err, err
    return err


BAD_SETTINGS = [
    ("materials.letter.nu=0.5", "Poisson"),
    ("materials.letter.E=0.0", "Young"),
    ("materials.letter.E=-3.0", "Young"),
    ("boundary.fixed=['nope']", "nope"),
    ("boundary.matched=['outline', 'hole']", "hole"),
    ("boundary.fixed=[]", "boundary.fixed"),
    ("boundary.loaded=['outline']", "share"),
    ("degree=3", "degree"),
    ("plane='membrane'", "plane"),
    ("materials.letter.nu={estimate=true, initial=0.3, bounds=[0.1, 0.6]}", "Poisson"),
    ("materials.letter.nu={estimate=true, initial=0.3, bounds=[0.35, 0.4]}", "outside bounds"),
]


@pytest.mark.parametrize("setting, word", BAD_SETTINGS)
def test_bad_values_exit_2_naming_the_culprit(scenes, tmp_path, capsys, setting, word):
    argv = ["simulate", scenes["letter-a"], "--out", tmp_path, "--set", setting]
    if setting.startswith("boundary.fixed=[]"):
        argv += ["--set", "boundary.displacement={}", "--set", "boundary.load={top=[0.0, -1.0]}"]
    _expect_user_error(capsys, argv, word)


def test_unknown_material_group(scenes, tmp_path, capsys):
    problem = _problem(tmp_path, scenes, "letter-a", lambda t: t + "\n[materials.bone]\nE = 1.0\nnu = 0.3\n")
    _expect_user_error(capsys, ["simulate", problem, "--out", tmp_path], "materials.bone")


def test_missing_files(tmp_path, scenes, capsys):
    _expect_user_error(capsys, ["simulate", tmp_path / "absent.toml", "--out", tmp_path], "absent.toml")
    problem = _problem(tmp_path, scenes, "letter-a", lambda t: t.replace("letter_a.msh", "gone.msh"))
    _expect_user_error(capsys, ["simulate", problem, "--out", tmp_path], "gone.msh")


def test_corrupt_mesh_and_toml(tmp_path, capsys):
    (tmp_path / "bad.msh").write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\ngarbage\n")
    (tmp_path / "p.toml").write_text('mesh = "bad.msh"\n[materials.a]\nE = 1.0\nnu = 0.3\n[boundary]\nfixed = ["b"]\n'
                                     '[boundary.load]\nb = [0.0, 1.0]\n')
    _expect_user_error(capsys, ["simulate", tmp_path / "p.toml", "--out", tmp_path], "bad.msh")
    (tmp_path / "q.toml").write_text('mesh = "bad.msh\n')
    _expect_user_error(capsys, ["simulate", tmp_path / "q.toml", "--out", tmp_path], "q.toml", "TOML")


def test_nan_coordinates(scenes, tmp_path, capsys):
    source = scenes["cantilever"].parent / "cantilever.msh"
    lines = source.read_text().splitlines()
    start = lines.index("$Nodes")
    # the first coordinate line after the first entity block header
    for i in range(start + 2, len(lines)):
        if len(lines[i].split()) == 3 and "." in lines[i]:
            lines[i] = "nan 0 0"
            break
    (tmp_path / "nan.msh").write_text("\n".join(lines) + "\n")
    (tmp_path / "p.toml").write_text(scenes["cantilever"].read_text().replace("cantilever.msh", "nan.msh"))
    _expect_user_error(capsys, ["simulate", tmp_path / "p.toml", "--out", tmp_path], "NaN")


def test_unknown_scene_and_bad_override(tmp_path, capsys):
    _expect_user_error(capsys, ["mesh", "teapot", "--out", tmp_path], "teapot")
    _expect_user_error(capsys, ["mesh", "letter-a", "--out", tmp_path, "--size", "-1"], "--size")
    _expect_user_error(capsys, ["mesh", "letter-a", "--out", tmp_path, "--organ-size", "0.2"], "--organ-size")
    _expect_user_error(capsys, ["mesh", "prostate-phantom", "--out", tmp_path, "--prostate-size", "0"], "--prostate-size")


def test_phantom_organ_detail(tmp_path, scenes):
    """--organ-size refines the bladder and rectum walls (the loaded boundary)."""
    from fenics_elasto.mesh.gmsh_models import read_surfaces

    assert main(["mesh", "prostate-phantom", "--out", str(tmp_path), "--size", "1.6", "--organ-size", "0.25"]) == 0
    finer = read_surfaces(tmp_path / "phantom.msh")
    default = read_surfaces(scenes["prostate-phantom"].parent / "phantom.msh")
    for group in ("bladder", "rectum"):
        assert len(finer[group][1]) > 1.5 * len(default[group][1]), group
    assert abs(len(finer["prostate_surface"][1]) / len(default["prostate_surface"][1]) - 1) < 0.2


def test_mesh_around_an_atlas(tmp_path, capsys):
    """A patient meshed around the atlas's organs has the atlas's loaded surfaces;
    an atlas for a scene that takes none, or a missing atlas file, exits 2."""
    from fenics_elasto.mesh.atlas import atlas_surfaces

    assert main(["mesh", "prostate-phantom", "--out", str(tmp_path / "atlas"), "--size", "1.6"]) == 0
    atlas = tmp_path / "atlas" / "phantom.msh"
    assert main(["mesh", "prostate-phantom", "--out", str(tmp_path / "p3"), "--size", "1.6", "--seed", "3",
                 "--atlas", str(atlas)]) == 0
    mine, theirs = atlas_surfaces(tmp_path / "p3" / "phantom.msh"), atlas_surfaces(atlas)
    for g in ("bladder", "rectum"):
        assert mine[g][1].shape == theirs[g][1].shape and mine[g][0].shape == theirs[g][0].shape
    _expect_user_error(capsys, ["mesh", "letter-a", "--out", tmp_path / "a", "--atlas", atlas], "--atlas")
    _expect_user_error(capsys, ["mesh", "prostate-phantom", "--out", tmp_path / "b", "--atlas", tmp_path / "no.msh"],
                       "no.msh")


def test_no_traceback_from_the_console_script(tmp_path):
    proc = run_cli("simulate", tmp_path / "absent.toml", "--out", tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.strip().startswith("error:")


def test_train_arguments_that_cannot_work(tmp_path, capsys, scenes):
    """Several training scenes without their shared atlas, a scene without examples,
    examples without a scene: one-line errors before any work."""
    p = scenes["cantilever"]
    _expect_user_error(capsys, ["train", "--rank", 2, "--out", tmp_path / "b.npz"], "--patient")
    _expect_user_error(capsys, ["train", p, "--examples", tmp_path, "--patient", p, tmp_path, "--rank", 2,
                                "--out", tmp_path / "b.npz"], "--atlas")
    _expect_user_error(capsys, ["train", "--atlas", tmp_path / "a.msh", "--patient", p, "--rank", 2,
                                "--out", tmp_path / "b.npz"], "no examples", p.name)
    _expect_user_error(capsys, ["train", "--examples", tmp_path, "--patient", p, tmp_path, "--rank", 2,
                                "--out", tmp_path / "b.npz"], "--examples")
    _expect_user_error(capsys, ["train", "--atlas", tmp_path / "a.msh", "--patient", p, tmp_path, "--rank", 2,
                                "--out", tmp_path / "b.npz"], "a.msh")
