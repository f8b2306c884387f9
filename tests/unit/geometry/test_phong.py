"""Targets refined onto the smooth surface through their vertices (geometry/phong.py).

Independent truths: the sphere and the circle the faceted targets were sampled from
(their closest points' distance from the centre), and a box, whose flat faces are its
own."""

import numpy as np
import pytest
import pyvista as pv

from fenics_elasto.geometry.phong import FACETED, MAX_LEVELS, faceting, finer_where_faceted
from fenics_elasto.geometry.surface import Surface


def _sphere(resolution: int) -> Surface:
    mesh = pv.Sphere(radius=1.0, theta_resolution=resolution, phi_resolution=resolution).triangulate().clean()
    return Surface(np.asarray(mesh.points), mesh.faces.reshape(-1, 4)[:, 1:])


def _radial_bias(surface: Surface, directions: np.ndarray) -> float:
    """The mean distance from the unit sphere (or circle) of the closest points to points just outside it."""
    return float(np.mean(np.linalg.norm(surface.closest(1.05 * directions), axis=1) - 1.0))


@pytest.mark.parametrize("resolution", [20, 40])
def test_a_faceted_sphere_is_refined_onto_it(resolution):
    """The flat faces lie inside the sphere (e^2 / 12 R on average); each level of lifted
    subdivision cuts that about fourfold (measured 12x in two levels, 15x in one and two),
    until the faces cut under FACETED of an edge, and the faces' order does not matter:
    half of them turned gives the same points."""
    flat = _sphere(resolution)
    directions = np.random.default_rng(0).normal(size=(5000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    finer = finer_where_faceted(flat, "sphere")
    levels = round(np.log(len(finer.cells) / len(flat.cells)) / np.log(4))
    assert levels >= 1 and len(finer.cells) == 4**levels * len(flat.cells)
    assert faceting(finer) <= FACETED or levels == MAX_LEVELS
    before, after = _radial_bias(flat, directions), _radial_bias(finer, directions)
    assert before < 0 and abs(after) < abs(before) / 3**levels, (before, after, levels)
    turned = flat.cells.copy()
    turned[::2] = turned[::2, ::-1]
    again = finer_where_faceted(Surface(flat.points, turned), "sphere")
    assert np.allclose(np.sort(again.points, axis=0), np.sort(finer.points, axis=0), atol=1e-12)


def test_a_box_and_a_fine_surface_are_kept():
    """A box's faces are its shape (its edges are creases): nothing to lift. A gently
    curved sheet (z = 0.01 r^2 over a unit square in 20 x 20 squares) is below FACETED."""
    box = pv.Box().triangulate().subdivide(2)
    surface = Surface(np.asarray(box.points), box.faces.reshape(-1, 4)[:, 1:])
    assert faceting(surface) == 0.0 and finer_where_faceted(surface, "box") is surface
    sheet = pv.Plane(i_resolution=20, j_resolution=20).triangulate()
    points = np.asarray(sheet.points).copy()
    points[:, 2] = 0.01 * (points[:, 0] ** 2 + points[:, 1] ** 2)
    gentle = Surface(points, sheet.faces.reshape(-1, 4)[:, 1:])
    assert 0 < faceting(gentle) < FACETED and finer_where_faceted(gentle, "sheet") is gentle


def test_a_coarse_circle_outline_is_refined_onto_it():
    """2D: a 60-gon's segments lie inside its circle; refined twice, 15x closer (measured)."""
    angle = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    outline = Surface(np.c_[np.cos(angle), np.sin(angle)], np.c_[np.arange(60), (np.arange(60) + 1) % 60])
    finer = finer_where_faceted(outline, "circle")
    probe = np.random.default_rng(1).uniform(0, 2 * np.pi, 2000)
    directions = np.c_[np.cos(probe), np.sin(probe)]
    before, after = _radial_bias(outline, directions), _radial_bias(finer, directions)
    assert len(finer.cells) == 4 * len(outline.cells) and abs(after) < abs(before) / 10, (before, after)


def test_a_coarse_interface_target_gives_the_inclusion_E(tmp_path):
    """scikit-fem's inclusion on its own finer mesh (tests/independent.py), its interface
    target sampled every 0.15 (51 segments on a circle of radius 1.2, cutting its corners
    by 1.5 % of an edge on average): refined, E 39.84 for 40 (95 % 39.58-40.11); with
    the flat segments it was 37.56 (34.64-40.90)."""
    import json

    from independent import inclusion
    from fenics_elasto.app.cli import main

    case = inclusion(tmp_path / "case", 4.0, source_size=0.2, spacing=0.15)
    assert main(["estimate", str(case["problem"]), "--out", str(tmp_path / "out")]) == 0
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    E, (low, high) = result["materials"]["inclusion"]["E"], result["uncertainty"]["inclusion.E"]["ci95"]
    assert abs(E / 40.0 - 1) < 0.015 and low < 40.0 < high, (E, low, high)
