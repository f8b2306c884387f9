"""Synthetic targets for the inverse tests, always made on a different, finer mesh; and
the Taylor test's rates, which the gradient tests share."""

from pathlib import Path

from fenics_elasto.files.writers import write_matched_surfaces
from fenics_elasto.inverse.verification import taylor_test
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate, write_landmarks_for


def fine_simulation(name: str, folder: Path, size: float, settings=()):
    """Simulate a built-in scene on a fine mesh; write its matched surfaces."""
    problem = build_scene(name, folder, size=size)
    scene = load_scene(problem, list(settings))
    sim = simulate(scene)
    write_matched_surfaces(folder / "target", scene, sim.u)
    return scene, sim


def inclusion_ratio_4_target(folder: Path, *extra: str) -> str:
    """The inclusion at E ratio 4 (top moved by (0.3, -0.6), plus ``extra`` settings)
    simulated at h = 0.25; the --set value that makes its outline and interface the target."""
    fine_simulation("inclusion", folder, 0.25,
                    ["materials.inclusion.E=40.0", "boundary.displacement.top.value=[0.3, -0.6]", *extra])
    targets = ", ".join(f"{g}='{folder / 'target' / f'surface_{g}.vtp'}'" for g in ("outline", "interface"))
    return f"target.surfaces={{{targets}}}"


def letter_case(base: Path, fine_size: float, nu: float):
    """A letter-A source (h = 0.4) and its outline target simulated at nu on a finer mesh."""
    fine_simulation("letter-a", base / "fine", fine_size, [f"materials.letter.nu={nu}"])
    return build_scene("letter-a", base / "source"), base / "fine" / "target" / "surface.vtp"


def landmarks_for(source_problem: Path, sim, path: Path, noise: float = 0.0, seed: int = 0) -> Path:
    """Exact node correspondence: the fine solution probed at the source's matched nodes."""
    return write_landmarks_for(load_scene(source_problem), sim.u, path, noise, seed)


def taylor_rates(phi, x, direction, gradient, eps0):
    """Rates of |phi(x + e d) - phi(x) - e g.d| as e halves (2 for a correct gradient)."""
    result = taylor_test(phi, x, direction, gradient, eps0)
    assert not result.at_roundoff, result
    return result.rates, result.remainders
