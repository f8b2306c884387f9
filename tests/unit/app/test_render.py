"""Pictures: the distance they colour by, the titles they carry, and that they draw."""

import numpy as np
import pytest
import pyvista as pv
from PIL import Image

from conftest import assert_picture
from fenics_elasto.app.render import caption, distance_to, render


def moved_sphere(center, radius, shift):
    sphere = pv.Icosphere(radius=radius, center=center, nsub=4)
    sphere.point_data["displacement"] = np.tile(shift, (sphere.n_points, 1))
    sphere.point_data["|u|"] = np.full(sphere.n_points, np.linalg.norm(shift))
    sphere.points = sphere.points + np.asarray(shift)
    return sphere


def test_distance_to_a_sphere():
    """Points on rays from the centre: their distance to a fine sphere is |r - R| up to
    the facets' sag (R (1 - cos(edge / 2R)) ~ 1e-3 R here)."""
    sphere = pv.Icosphere(radius=2.0, nsub=5)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    r = rng.uniform(0.5, 4.0, 200)
    assert distance_to(sphere, directions * r[:, None]) == pytest.approx(np.abs(r - 2.0), abs=3e-3)


ESTIMATE = {"materials": {"prostate": {"E": 36.63, "nu": 0.4}, "tissue": {"E": 10.0, "nu": 0.4}},
            "estimated": ["prostate.E"], "surface_distance": {"rms": 0.0362, "max": 0.8}}


def test_caption_names_the_case_and_the_answer():
    assert caption(ESTIMATE, "noise_1mm", "mm") == (
        "estimate: noise_1mm\nprostate E = 36.63 (3.66 x tissue); rms distance to target 0.0362 mm")
    sure = {**ESTIMATE, "uncertainty": {"prostate.E": {"std": 0.91, "ci95": [35.0, 38.4]}, "noise_std": 0.03}}
    assert "prostate E = 36.63 (95 %: 35-38.4) (3.66 x tissue)" in caption(sure)
    # a one-sided interval is the interval, not +- sigma (3.16 +- 4.2 about 0.84-161)
    weak = {**ESTIMATE, "uncertainty": {"prostate.E": {"std": 4.2, "ci95": [0.8421, 160.9]}}}
    assert "= 36.63 (95 %: 0.8421-160.9)" in caption(weak) and "±" not in caption(weak)
    no_interval = {**ESTIMATE, "uncertainty": {"prostate.E": {"std": 0.91}}}
    assert "prostate E = 36.63 ± 0.91 (3.66 x tissue)" in caption(no_interval)
    not_computed = {**ESTIMATE, "uncertainty": {"note": "not computed"}}
    assert "±" not in caption(not_computed) and "95 %" not in caption(not_computed)
    simulated = {"materials": {"tissue": {"E": 10.0, "nu": 0.4}, "prostate": {"E": 30.0, "nu": 0.4}},
                 "max_displacement": 8.07}
    assert caption(simulated, "truth", "mm") == ("simulate: truth\ntissue E = 10, prostate E = 30; "
                                                 "largest displacement 8.07 mm")


@pytest.mark.parametrize("with_target", [False, True])
def test_3d_picture(tmp_path, with_target):
    """Organs, a clamped plate, the body; with a target surface a second panel (the fit)."""
    groups = {"bladder": moved_sphere((0, 0, 3), 1.5, (0, 0, 0.3)),
              "prostate_surface": moved_sphere((0, 0, 0), 1.0, (0, 0, 0.1)),
              "bones": pv.Plane(center=(0, 0, -2), i_size=6, j_size=6).triangulate()}
    groups["bones"].point_data["|u|"] = np.zeros(groups["bones"].n_points)
    body = pv.Box(bounds=(-4, 4, -4, 4, -3, 6), level=2, quads=False)
    target = pv.merge([pv.Icosphere(radius=1.55, center=(0, 0, 3.3), nsub=4),
                       pv.Icosphere(radius=1.0, center=(0, 0, 0.1), nsub=4)])
    path = render(tmp_path / "picture.png", groups, context=body, target=target if with_target else None,
                  title="estimate: toy\nprostate E = 30", fixed=["bones"], units="mm")
    assert_picture(path, 0.05)
    assert Image.open(path).size == ((2000, 1000) if with_target else (1400, 1000))
    if with_target:  # the bladder is 0.05 off its target, the prostate on it
        assert groups["bladder"].point_data["distance"] == pytest.approx(0.05, abs=1e-3)
        assert groups["prostate_surface"].point_data["distance"] == pytest.approx(0.0, abs=1e-3)


def test_a_group_without_a_target_is_not_coloured_by_anothers(tmp_path):
    """A bar's loaded end, moved in its own plane and not matched, was coloured by its
    distance to the sides' target (0.25, the panel's top): only matched groups are."""
    groups = {"end": moved_sphere((0, 0, 3), 1.0, (0, 0, 0.3)), "sides": moved_sphere((0, 0, 0), 1.0, (0, 0, 0.1))}
    target = pv.Icosphere(radius=1.0, center=(0, 0, 0.1), nsub=4)
    path = render(tmp_path / "picture.png", groups, target=target, title="estimate", matched=["sides"])
    assert_picture(path, 0.05)
    assert "distance" not in groups["end"].point_data
    assert groups["sides"].point_data["distance"] == pytest.approx(0.0, abs=1e-3)


def test_2d_picture(tmp_path):
    circle = pv.Circle(radius=1.0, resolution=60)
    cells = circle.triangulate()
    cells.point_data["|u|"] = np.linalg.norm(cells.points, axis=1)
    outline = cells.extract_feature_edges(boundary_edges=True, feature_edges=False, manifold_edges=False)
    outline.point_data["|u|"] = np.ones(outline.n_points)
    path = render(tmp_path / "flat.png", {"outline": outline}, {"outline": outline}, cells, outline.scale(1.05),
                  "estimate: disk", dim=2)
    assert_picture(path, 0.05)


def test_a_group_around_others_is_see_through(tmp_path):
    """A prostate MR user's nodule sat hidden inside the gland and the matched outer
    surface, both drawn opaque: a group whose box holds another's is see-through."""
    from fenics_elasto.app.render import SHELL_OPACITY, picture

    groups = {"outer": moved_sphere((0, 0, 0), 3.0, (0, 0, 0.1)), "gland": moved_sphere((0, 0, 0), 1.5, (0, 0, 0.1)),
              "nodule": moved_sphere((0.5, 0, 0), 0.4, (0, 0, 0.1))}
    plotter = picture(groups, title="estimate")
    drawn = [(pv.wrap(actor.GetMapper().GetInput()), actor.GetProperty().GetOpacity())
             for actor in plotter.renderers[1].actors.values() if hasattr(actor.GetMapper(), "GetInput")]
    plotter.close()
    opacity = {name: [o for mesh, o in drawn if mesh is not None and np.allclose(mesh.bounds, surface.bounds)]
               for name, surface in groups.items()}
    assert opacity == {"outer": [SHELL_OPACITY], "gland": [SHELL_OPACITY], "nodule": [1.0]}
