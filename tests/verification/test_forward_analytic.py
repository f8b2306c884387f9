"""Forward model against analytic solutions: convergence rates, patch test, Lame sphere."""

import numpy as np
import pytest
import ufl

import dolfinx
from dolfinx import fem

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.loads import assemble_load
from fenics_elasto.mesh.gmsh_models import GmshModel
from fenics_elasto.mesh.builtin import build_cantilever
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values, prescribed_function, simulate

from analytic import C, E, L, P, cantilever_errors


def solve_cantilever(tmp_path, h, degree):
    return cantilever_errors(build_cantilever(tmp_path / f"c{h}", size=h, length=L, half_height=C), degree)


@pytest.mark.parametrize("degree, rate", [(1, 2.0), (2, 3.0)])
def test_cantilever_convergence(tmp_path, degree, rate):
    """L2 error rate (least-squares slope against the mean cell size) and tip deflection."""
    results = [solve_cantilever(tmp_path, h, degree) for h in (0.5, 0.25, 0.125, 0.0625)]
    errors, tips, sizes = map(np.array, zip(*results))
    slope = np.polyfit(np.log(sizes), np.log(errors), 1)[0]
    exact_tip = P * L**3 / (3 * E * 2 * C**3 / 3)
    tip_errors = np.abs(tips - exact_tip) / exact_tip
    print(f"P{degree} L2 errors {errors}, sizes {sizes}, rate {slope:.2f}, tip errors {tip_errors}")
    assert abs(slope - rate) < 0.3, slope
    assert tip_errors[-1] < tip_errors[0]
    assert tip_errors[-1] < (2e-3 if degree == 1 else 1e-6)


@pytest.mark.parametrize("degree", [1, 2])
def test_patch_linear_field_reproduced(scenes, degree):
    """An affine displacement prescribed on the whole outline is reproduced inside."""
    gradient = [[0.02, -0.05], [0.03, 0.01]]
    scene = load_scene(scenes["letter-a"], [f"degree={degree}", "boundary.fixed=[]", "boundary.loaded=[]",
                                            f"boundary.displacement.outline={{value=[0.1, -0.2], gradient={gradient}}}"])
    sim = simulate(scene)
    coords = sim.model.dofs.dof_coords
    expected = np.array([0.1, -0.2]) + coords @ np.array(gradient).T
    assert np.abs(sim.u.x.array.reshape(-1, 2) - expected).max() < 1e-12


def hollow_sphere(path, h, a=1.0, b=2.0):
    with GmshModel("sphere") as gmsh:
        _sphere(gmsh, path, h, a, b)
    (path / "problem.toml").write_text('mesh = "sphere.msh"\n[materials.shell]\nE = 100.0\nnu = 0.3\n'
                                       '[boundary]\nfixed = []\n[boundary.displacement.outer]\nscale = 0.0\n')
    return path / "problem.toml"


def _sphere(gmsh, path, h, a, b):
    outer = gmsh.model.occ.addSphere(0, 0, 0, b)
    inner = gmsh.model.occ.addSphere(0, 0, 0, a)
    gmsh.model.occ.cut([(3, outer)], [(3, inner)])
    gmsh.model.occ.synchronize()
    vol = gmsh.model.getEntities(3)[0][1]
    faces = [t for _, t in gmsh.model.getBoundary([(3, vol)], oriented=False)]
    areas = {f: gmsh.model.occ.getMass(2, f) for f in faces}
    gmsh.model.addPhysicalGroup(3, [vol], name="shell")
    gmsh.model.addPhysicalGroup(2, [f for f in faces if areas[f] < 2 * np.pi * a * a * 2.5], name="inner")
    gmsh.model.addPhysicalGroup(2, [f for f in faces if areas[f] > 2 * np.pi * a * a * 2.5], name="outer")
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)
    gmsh.model.mesh.generate(3)
    gmsh.write(str(path / "sphere.msh"))


@pytest.mark.slow
def test_lame_sphere_internal_pressure(tmp_path):
    """Thick-walled sphere: pressure p inside, exact radial displacement on the outside."""
    a, b, p, E_, nu = 1.0, 2.0, 1.0, 100.0, 0.3

    def u_r(r):
        return p * a**3 / (E_ * (b**3 - a**3)) * ((1 - 2 * nu) * r + (1 + nu) * b**3 / (2 * r**2))

    errors = []
    for h in (0.6, 0.3):
        problem = hollow_sphere(tmp_path, h)
        scene = load_scene(problem, [f"boundary.displacement.outer.scale={u_r(b) / b}"])
        model = ElasticModel(scene)
        mesh = scene.mesh
        inner = scene.facet_groups["inner"]
        tags = dolfinx.mesh.meshtags(mesh, 2, np.sort(inner), np.ones(len(inner), np.int32))
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
        n = ufl.FacetNormal(mesh)
        rhs = assemble_load(-p * ufl.inner(n, ufl.TestFunction(model.dofs.V)) * ds(1))
        clamped = model.dofs.clamped_dofs(["outer"])
        c = model.stiffness.coefficients(*material_values(scene))
        u = model.solve(c, clamped, rhs, prescribed_function(model, scene.displacement))
        x = ufl.SpatialCoordinate(mesh)
        r = ufl.sqrt(ufl.dot(x, x))
        diff = u - u_r(r) * x / r
        err = np.sqrt(fem.assemble_scalar(fem.form(ufl.inner(diff, diff) * ufl.dx)))
        norm = np.sqrt(fem.assemble_scalar(fem.form(u_r(r) ** 2 * ufl.dx)))
        errors.append(err / norm)
    print("Lame sphere relative L2 errors", errors)
    assert errors[-1] < 2.5e-2  # h = 0.3 on a sphere of radius 1..2
    assert np.log2(errors[0] / errors[1]) > 1.7  # P2 on an affine (faceted) sphere: geometry limits to ~2
