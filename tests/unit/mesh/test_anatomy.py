"""Scenes from surface files (`fenics-elasto scene`): groups, areas and volumes against
the analytic shapes the surfaces sample; each repair of a defective surface; each
refusal as one line + exit 2; the real prostate; and a scene that `simulate` runs."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import ufl
from scipy.spatial import cKDTree

import dolfinx
from conftest import logged, run_cli
from fenics_elasto.mesh.anatomy import build_scene_from_spec
from fenics_elasto.mesh.builtin import PROSTATE_STL
from fenics_elasto.mesh.repair import closed_shells, enclosed_volume
from fenics_elasto.app.cli import main
from fenics_elasto.model.scene import load_scene

PROSTATE = PROSTATE_STL


def sphere(center, radius, nsub=4) -> pv.PolyData:
    """Icosphere: every vertex on the sphere (nsub 4: 5,120 triangles, area 0.1 % short)."""
    return pv.Icosphere(radius=radius, center=center, nsub=nsub)


def ellipsoid(center, radii, nsub=4) -> pv.PolyData:
    surface = pv.Icosphere(radius=1.0, nsub=nsub)
    surface.points = np.asarray(surface.points) * radii + np.asarray(center)
    return surface


def write(folder: Path, files: dict, spec: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, surface in files.items():
        surface.save(folder / name)
    (folder / "spec.toml").write_text(spec)
    return folder / "spec.toml"


def measures(problem: Path) -> tuple[dict, dict, object]:
    """Area of every facet group (1 ds + 1 dS) and volume of every cell group (1 dx),
    assembled on the DOLFINx mesh the scene loader reads."""
    scene = load_scene(problem)
    mesh = scene.mesh
    areas = {}
    for name, facets in scene.facet_groups.items():
        tags = dolfinx.mesh.meshtags(mesh, 2, np.sort(facets), np.ones(len(facets), np.int32))
        areas[name] = sum(dolfinx.fem.assemble_scalar(dolfinx.fem.form(
            1.0 * measure(domain=mesh, subdomain_data=tags, subdomain_id=1))) for measure in (ufl.ds, ufl.dS))
    volumes = {m.name: dolfinx.fem.assemble_scalar(dolfinx.fem.form(
        1.0 * ufl.dx(domain=mesh, subdomain_data=scene.cell_tags, subdomain_id=m.tag))) for m in scene.materials}
    return areas, volumes, scene


def facet_corners(scene, group: str) -> np.ndarray:
    """(facets, 3, 3) the corner points of a facet group's (curved) triangles."""
    mesh = scene.mesh
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 2, scene.facet_groups[group])
    return mesh.geometry.x[nodes[:, :3]]


def flat_area(corners: np.ndarray) -> float:
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()


def expect_error(capsys, argv, *words):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    for word in words:
        assert word in err, (word, err)




# --------------------------------------------------------------------------- analytic scenes


@pytest.fixture(scope="module")
def sphere_in_box(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sphere_in_box")
    spec = write(folder, {"ball.stl": sphere((0, 0, 0), 10.0, nsub=5)}, """
units = "mm"
size = 6.0
organ_size = 2.5
[body]
box = { margin = 8.0 }
[regions.ball]
surface = "ball.stl"
[patches.bottom]
side = { point = [0.0, -15.0, 0.0], normal = [0.0, -1.0, 0.0] }
""")
    return build_scene_from_spec(spec, folder / "out")


def test_sphere_in_box_groups_areas_and_volumes(sphere_in_box):
    areas, volumes, scene = measures(sphere_in_box)
    r, half = 10.0, 18.0  # the box is the sphere's bounding box (poles are vertices) grown by the margin
    assert set(areas) == {"outer", "ball_surface", "bottom"} and set(volumes) == {"tissue", "ball"}
    assert areas["outer"] == pytest.approx(6 * (2 * half) ** 2, rel=1e-9)
    assert areas["bottom"] == pytest.approx((2 * half) ** 2 + 4 * (2 * half) * 3.0, rel=1e-9)  # face + 3-wide strips
    assert areas["ball_surface"] == pytest.approx(4 * math.pi * r**2, rel=2e-3)
    assert volumes["ball"] == pytest.approx(4 / 3 * math.pi * r**3, rel=2e-3)
    assert volumes["tissue"] + volumes["ball"] == pytest.approx((2 * half) ** 3, rel=1e-9)


def test_curved_surfaces_are_much_closer_than_flat_facets(sphere_in_box):
    areas, _, scene = measures(sphere_in_box)
    exact = 4 * math.pi * 10.0**2
    flat = flat_area(facet_corners(scene, "ball_surface"))
    assert abs(flat - exact) / exact > 5e-3  # flat facets cut the sphere's curvature
    assert abs(areas["ball_surface"] - exact) < abs(flat - exact) / 10


def test_patch_is_the_half_space_of_facet_centroids(sphere_in_box):
    _, _, scene = measures(sphere_in_box)
    side = lambda group: facet_corners(scene, group).mean(axis=1) @ [0.0, -1.0, 0.0] - 15.0  # noqa: E731
    assert (side("bottom") > 0).all()
    outer_only = np.setdiff1d(scene.facet_groups["outer"], scene.facet_groups["bottom"])
    nodes = dolfinx.mesh.entities_to_geometry(scene.mesh, 2, outer_only)
    assert (scene.mesh.geometry.x[nodes[:, :3]].mean(axis=1) @ [0.0, -1.0, 0.0] - 15.0 <= 0).all()


def test_two_spheres_in_one_file_make_one_region(tmp_path):
    pair = sphere((-8, 0, 0), 5.0) + sphere((8, 0, 0), 5.0)
    spec = write(tmp_path, {"pair.stl": pair}, """
units = "cm"
size = 5.0
organ_size = 2.0
[body]
box = { margin = 6.0 }
[regions.pair]
surface = "pair.stl"
""")
    lines = []
    with logged(lines):
        problem = build_scene_from_spec(spec, tmp_path / "out")
    areas, volumes, _ = measures(problem)
    assert "2 closed piece(s)" in lines[0] and lines[0].endswith("26 x 10 x 10 cm")
    assert 'units = "cm"' in problem.read_text()
    assert set(volumes) == {"tissue", "pair"} and set(areas) == {"outer", "pair_surface"}
    assert areas["pair_surface"] == pytest.approx(2 * 4 * math.pi * 25, rel=3e-3)
    assert volumes["pair"] == pytest.approx(2 * 4 / 3 * math.pi * 125, rel=3e-3)
    assert volumes["tissue"] + volumes["pair"] == pytest.approx(38 * 22 * 22, rel=1e-9)


def test_body_surface_with_a_cap_patch(tmp_path):
    """A spherical body (a user surface) clamped on a cap: the patch is the cap, its rim
    on the cut plane (curved edges along the cut, not bulging across it)."""
    spec = write(tmp_path, {"body.stl": sphere((0, 0, 0), 12.0, nsub=5), "ball.stl": sphere((0, 0, 0), 5.0)}, """
size = 3.0
organ_size = 2.0
[body]
surface = "body.stl"
[regions.ball]
surface = "ball.stl"
[patches.cap]
side = { point = [-8.0, 0.0, 0.0], normal = [-1.0, 0.0, 0.0] }
""")
    areas, volumes, scene = measures(build_scene_from_spec(spec, tmp_path / "out"))
    assert set(areas) == {"outer", "cap", "ball_surface"}
    assert areas["outer"] == pytest.approx(4 * math.pi * 144, rel=2e-3)
    assert areas["cap"] == pytest.approx(2 * math.pi * 12 * 4, rel=2e-3)  # 2 pi R h
    assert (facet_corners(scene, "cap")[:, :, 0] <= -8.0 + 1e-9).all()
    assert volumes["tissue"] + volumes["ball"] == pytest.approx(4 / 3 * math.pi * 12**3, rel=2e-3)


def test_region_inside_a_region(tmp_path):
    """A tumour inside a gland: the gland's volume is the shell between the two."""
    spec = write(tmp_path, {"gland.stl": sphere((0, 0, 0), 8.0), "tumour.stl": sphere((2, 0, 0), 3.0)}, """
size = 5.0
organ_size = 2.0
[body]
box = { margin = 5.0 }
[regions.gland]
surface = "gland.stl"
[regions.tumour]
surface = "tumour.stl"
""")
    areas, volumes, _ = measures(build_scene_from_spec(spec, tmp_path / "out"))
    # (a tumour of radius 3 meshed at 2: ~0.5 % short; a gland without its hole would be 6 % over)
    assert volumes["tumour"] == pytest.approx(4 / 3 * math.pi * 27, rel=1e-2)
    assert volumes["gland"] == pytest.approx(4 / 3 * math.pi * (512 - 27), rel=1e-2)
    assert areas["tumour_surface"] == pytest.approx(4 * math.pi * 9, rel=1e-2)


@pytest.mark.slow
def test_cavity_and_region_in_an_ellipsoid_body(tmp_path):
    spec = write(tmp_path, {"ball.stl": sphere((-9, 0, 0), 6.0, nsub=5), "hole.stl": sphere((9, 0, 0), 5.0, nsub=5)}, """
size = 5.0
organ_size = 2.0
[body]
ellipsoid = { margin = 6.0 }
material = "fat"
[regions.ball]
surface = "ball.stl"
[cavities.hole]
surface = "hole.stl"
""")
    problem = build_scene_from_spec(spec, tmp_path / "out")
    areas, volumes, scene = measures(problem)
    assert set(volumes) == {"fat", "ball"} and set(areas) == {"outer", "ball_surface", "hole"}
    assert areas["ball_surface"] == pytest.approx(4 * math.pi * 36, rel=2e-3)
    assert areas["hole"] == pytest.approx(4 * math.pi * 25, rel=2e-3)
    assert volumes["ball"] == pytest.approx(4 / 3 * math.pi * 216, rel=2e-3)
    # The outer boundary is an ellipsoid about the centre of the organs' box: fit its semi-axes.
    points = facet_corners(scene, "outer").reshape(-1, 3) - [-0.5, 0.0, 0.0]
    inverse_squares, *_ = np.linalg.lstsq(points**2, np.ones(len(points)), rcond=None)
    a, b, c = 1 / np.sqrt(inverse_squares)
    assert np.abs((points**2) @ inverse_squares - 1).max() < 2e-3
    assert b == pytest.approx(c, rel=1e-3) and a > b  # shaped like the organs' box, grown
    enclosed = 4 / 3 * math.pi * a * b * c
    assert volumes["fat"] + volumes["ball"] == pytest.approx(enclosed - 4 / 3 * math.pi * 125, rel=2e-3)
    # every organ point keeps the margin from the outer boundary
    organ = np.vstack([sphere((-8.5, 0, 0), 6.0).points, sphere((9.5, 0, 0), 5.0).points])
    assert cKDTree(points).query(organ)[0].min() > 0.95 * 6.0
    text = problem.read_text()
    assert 'loaded  = ["hole"]' in text and "[materials.fat]" in text and "[boundary.displacement.hole]" in text


# --------------------------------------------------------------------------- repairs


def shells_of(tmp_path, surface, lines, name="organ.vtk"):
    surface.save(tmp_path / name)
    with logged(lines):
        return closed_shells(tmp_path / name, name, "region", "organ")


def test_specks_are_dropped_and_reported(tmp_path):
    specks = [sphere((30 + 3 * k, 0, 0), 0.05, nsub=0) for k in range(3)]
    lines = []
    shells = shells_of(tmp_path, sphere((0, 0, 0), 10.0).merge(specks), lines)
    assert len(shells) == 1 and len(shells[0].triangles) == 5120
    assert any("dropped 3 stray piece(s) (20 triangles each" in line for line in lines), lines


def test_small_hole_is_filled_and_reported(tmp_path):
    ball = sphere((0, 0, 0), 10.0)
    top = np.asarray(ball.cell_centers().points)[:, 2] > 9.9  # a cap of radius ~1.4
    lines = []
    shells = shells_of(tmp_path, ball.extract_cells(np.flatnonzero(~top)).extract_surface(algorithm=None), lines)
    assert any("filled 1 hole(s)" in line for line in lines), lines
    assert len(shells) == 1
    assert shells[0].volume == pytest.approx(ball.volume, rel=1e-3)


def test_flipped_normals_are_turned_outward_and_reported(tmp_path):
    ball = sphere((0, 0, 0), 10.0)
    faces = ball.regular_faces.copy()
    lines = []
    inward = shells_of(tmp_path, pv.PolyData.from_regular_faces(ball.points, faces[:, ::-1]), lines, "in.vtk")
    assert any("turned the inward-facing normals of 1 component(s) outward" in line for line in lines), lines
    assert inward[0].volume == pytest.approx(ball.volume, rel=1e-9)
    some = np.random.default_rng(0).random(len(faces)) < 0.1
    faces[some] = faces[some][:, ::-1]
    lines = []
    mixed = shells_of(tmp_path, pv.PolyData.from_regular_faces(ball.points, faces), lines, "mixed.vtk")
    assert any(f"re-oriented {some.sum()} triangles" in line for line in lines), lines
    assert mixed[0].volume == pytest.approx(ball.volume, rel=1e-9)


def test_duplicated_points_and_triangles_are_merged_and_reported(tmp_path):
    ball = sphere((0, 0, 0), 10.0)
    faces = ball.regular_faces
    soup = np.asarray(ball.points)[faces].reshape(-1, 3)  # every triangle with its own corners
    triangles = np.arange(len(soup)).reshape(-1, 3)
    triangles = np.vstack([triangles, triangles[:7]])  # and 7 triangles twice
    lines = []
    shells = shells_of(tmp_path, pv.PolyData.from_regular_faces(soup, triangles), lines)
    assert any(f"merged {len(soup) - ball.n_points} duplicated points" in line for line in lines), lines
    assert any("dropped 7 duplicated triangles" in line for line in lines), lines
    assert len(shells[0].triangles) == len(faces)
    assert shells[0].volume == pytest.approx(ball.volume, rel=1e-9)


def test_nested_pieces_of_one_file_are_not_a_self_intersection(tmp_path):
    """A hollow organ's outer and inner wall in one file: two outward pieces, the inner
    one inside the outer (winding number 2 inside it, which is no defect)."""
    lines = []
    shells = shells_of(tmp_path, sphere((0, 0, 0), 10.0) + sphere((1, 0, 0), 6.0), lines)
    assert lines == [] and len(shells) == 2
    assert sorted(s.volume for s in shells) == pytest.approx([sphere((0, 0, 0), r).volume for r in (6.0, 10.0)])


def test_a_clean_surface_needs_no_repair(tmp_path):
    lines = []
    shells = shells_of(tmp_path, sphere((0, 0, 0), 10.0), lines)
    assert lines == [] and enclosed_volume(shells[0].points, shells[0].triangles) > 0


# --------------------------------------------------------------------------- refusals


BOX_BODY = """
[body]
box = { margin = 5.0 }
[regions.a]
surface = "a.stl"
"""
BOX_SPEC = "size = 5.0\n" + BOX_BODY


def test_refusals_of_bad_surfaces(tmp_path, capsys):
    ball = sphere((0, 0, 0), 10.0)
    half = ball.extract_cells(np.flatnonzero(np.asarray(ball.cell_centers().points)[:, 2] > 0)).extract_surface(algorithm=None)
    cases = {
        "open": ("a.stl", half, ["a.stl", "opening of radius", "is a guess"]),
        "lines": ("a.vtk", pv.Circle(radius=5.0).extract_feature_edges(), ["a.vtk", "only lines"]),
    }
    for case, (name, surface, words) in cases.items():
        spec = write(tmp_path / case, {name: surface}, BOX_SPEC.replace("a.stl", name))
        expect_error(capsys, ["scene", spec, "--out", tmp_path / case / "out"], *words)
    spec = write(tmp_path / "empty", {}, BOX_SPEC)
    (tmp_path / "empty" / "a.stl").write_bytes(b"")
    expect_error(capsys, ["scene", spec, "--out", tmp_path / "out"], "a.stl", "empty")
    (tmp_path / "empty" / "a.stl").unlink()
    expect_error(capsys, ["scene", spec, "--out", tmp_path / "out"], "a.stl", "no such file")


def test_non_manifold_and_self_intersecting_surfaces_are_rebuilt(tmp_path, capsys):
    """#34 item 2: a fin on an edge (non-manifold) and two blobs of one organ passing
    through each other get through, rebuilt from what they enclose, each with one line
    saying what changed: the ball keeps its volume, the blobs make their union."""
    ball = sphere((0, 0, 0), 10.0)
    edge = ball.regular_faces[0, :2]
    fin = pv.PolyData.from_regular_faces(np.vstack([ball.points, [[0, 0, 30.0]]]),
                                         np.vstack([ball.regular_faces, [[edge[0], edge[1], ball.n_points]]]))
    spec = write(tmp_path / "fin", {"a.stl": fin}, BOX_SPEC)
    assert main(["scene", str(spec), "--out", str(tmp_path / "fin" / "out")]) == 0
    out = capsys.readouterr().out
    assert "non-manifold" in out and "rebuilt from what it encloses" in out and "Hausdorff distance" in out, out
    _, volumes, _ = measures(tmp_path / "fin" / "out" / "problem.toml")
    assert volumes["a"] == pytest.approx(4 / 3 * np.pi * 10.0**3, rel=0.01)
    blobs = sphere((-4, 0, 0), 6.0).merge(sphere((4, 0, 0), 6.0))  # one organ exported as two overlapping blobs
    spec = write(tmp_path / "blobs", {"a.stl": blobs}, BOX_SPEC)
    assert main(["scene", str(spec), "--out", str(tmp_path / "blobs" / "out")]) == 0
    out = capsys.readouterr().out
    assert "pass through each other" in out and "rebuilt from what it encloses" in out, out
    _, volumes, _ = measures(tmp_path / "blobs" / "out" / "problem.toml")
    lens = 2 * np.pi * (6.0 - 4.0) ** 2 * (2 * 6.0 + 4.0) / 3  # two caps of height 2: the overlap
    assert volumes["a"] == pytest.approx(2 * 4 / 3 * np.pi * 6.0**3 - lens, rel=0.01)


def test_pieces_touching_at_a_vertex_are_rebuilt_as_one():
    """Two balls of one file sharing one vertex (a bow-tie, as marching cubes and
    SurfaceNets make where diagonal voxels meet): each piece is closed but together they
    are no solid; rebuilt from what they enclose, one line saying why. It had been
    refused as "two of its pieces intersect"."""
    from fenics_elasto.mesh.repair import solid_shells

    ball = sphere((0, 0, 0), 5.0)
    tip = int(np.argmax(ball.points[:, 0]))
    mirrored = np.asarray(ball.points).copy()
    mirrored[:, 0] = 2 * ball.points[tip, 0] - mirrored[:, 0]  # the tip maps onto itself
    points = np.vstack([ball.points, mirrored])
    faces = ball.regular_faces
    triangles = np.vstack([faces, faces[:, ::-1] + ball.n_points])  # mirrored: turned to face outward again
    with logged([]) as lines:
        shells = solid_shells(points, triangles, "a.stl", "region", "a")
    assert any("touch at 1 vertices" in line and "rebuilt from what it encloses" in line for line in lines), lines
    assert len(shells) == 1 and shells[0].volume == pytest.approx(2 * ball.volume, rel=0.02)


def test_a_voxel_staircase_surface_is_smoothed_and_meshed(tmp_path, capsys):
    """A body exported with its smoothing off (SurfaceNets' voxel faces on the test
    kidney's oblique 1 x 1.2 x 1.8 mm grid): smoothed as a label map's surfaces are, one
    line saying so, and meshed. Cut by two patches' planes as it was, it had been left
    open ("please report"); a user's such body had failed inside gmsh. Its volume stays
    within 2 % of the voxels'; a smooth surface is not touched
    (test_a_clean_surface_needs_no_repair)."""
    import labelmaps as lm

    image = pv.ImageData(dimensions=lm.label_map().shape, spacing=lm.SPACING)
    image.point_data["inside"] = (lm.label_map() > 0).astype(np.int32).ravel(order="F")
    steps = image.contour_labels("all", smoothing=False, output_mesh_type="triangles")
    world = np.asarray(steps.points) / lm.SPACING @ lm.affine()[:3, :3].T + lm.affine()[:3, 3]
    staircase = pv.PolyData.from_regular_faces(world, steps.regular_faces)
    centre, axis = lm.world_centre(), lm.rotation()[:, 0]
    ends = "".join(f"[patches.{name}]\nside = {{ point = {[float(v) for v in centre + 15 * sign * axis]}, "
                   f"normal = {[float(v) for v in sign * axis]} }}\n" for name, sign in (("top", 1), ("bottom", -1)))
    spec = write(tmp_path, {"body.stl": staircase, "a.stl": sphere(centre, 5.0)},
                 'size = 8.0\norgan_size = 2.5\n[body]\nsurface = "body.stl"\nmaterial = "tissue"\n'
                 '[regions.a]\nsurface = "a.stl"\n' + ends)
    assert main(["scene", str(spec), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "body (body.stl): a voxel staircase (its faces point" in out, out
    _, volumes, _ = measures(tmp_path / "out" / "problem.toml")
    assert sum(volumes.values()) == pytest.approx(staircase.volume, rel=0.02)
    with logged([]) as lines:  # a box faces six ways too, and keeps its edges
        closed_shells(write(tmp_path / "box", {"box.stl": pv.Box(level=10).triangulate()}, "")
                      .parent / "box.stl", "box.stl", "body", "tissue")
    assert not any("staircase" in line for line in lines), lines


def _real_prostate() -> pv.PolyData:
    return pv.read(PROSTATE).connectivity("largest").extract_surface(algorithm=None).clean()


@pytest.mark.parametrize("defect", ["fin", "hole"])
def test_a_broken_real_prostate_is_rebuilt_faithfully(defect):
    """The real prostate segmentation with a fin on an edge, or a hole of radius 6 mm
    (10 % of its size, twice what is filled in place): rebuilt within 1 % of its volume."""
    from fenics_elasto.mesh.repair import solid_shells

    organ = _real_prostate()
    points, triangles = np.asarray(organ.points), organ.regular_faces
    if defect == "fin":
        edge = triangles[0, :2]
        points = np.vstack([points, points[edge].mean(axis=0) + [0.0, 0.0, 15.0]])
        triangles = np.vstack([triangles, [[edge[0], edge[1], len(points) - 1]]])
    else:
        centres = points[triangles].mean(axis=1)
        triangles = triangles[np.linalg.norm(centres - points[np.argmax(points[:, 2])], axis=1) > 6.0]
    shells = solid_shells(points, triangles, "prostate.stl", "region", "prostate")
    assert len(shells) == 1 and shells[0].volume == pytest.approx(organ.volume, rel=0.01)


def test_what_encloses_nothing_or_would_be_a_guess_is_refused(tmp_path, capsys):
    sheet = pv.Plane(i_size=20, j_size=20).triangulate()
    spec = write(tmp_path / "sheet", {"a.stl": sheet}, BOX_SPEC)
    expect_error(capsys, ["scene", spec, "--out", tmp_path / "out"], "a.stl", "encloses no volume")


@pytest.mark.slow
def test_a_fine_real_prostate_is_decimated_and_meshed(tmp_path, capsys):
    """The real prostate refined to 1.3e5 triangles (an export finer than any organ
    size): decimated before gmsh sees it, one line saying so with the volume change and
    the Hausdorff distance, and the region keeps its volume."""
    fine = _real_prostate().subdivide(2, "loop")
    assert fine.n_cells > 1e5
    spec = write(tmp_path, {"p.stl": fine}, 'organ_size = 3.0\n[body]\nbox = { margin = 10.0 }\n'
                                             '[regions.prostate]\nsurface = "p.stl"\n')
    assert main(["scene", str(spec), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert f"{fine.n_cells} -> " in out and "Hausdorff distance to the input" in out, out
    _, volumes, _ = measures(tmp_path / "out" / "problem.toml")
    assert volumes["prostate"] == pytest.approx(fine.volume, rel=0.01)


@pytest.mark.slow
def test_a_fine_body_surface_is_decimated_too(tmp_path, capsys):
    """A body exported at 0.1 mm (327,680 triangles) is decimated like a region's surface:
    gmsh had meshed every triangle (56 s) and made another mesh than the coarse body's."""
    fine = ellipsoid((0, 0, 0), (25.0, 20.0, 18.0), nsub=7)
    assert fine.n_cells == 327_680
    spec = write(tmp_path, {"body.stl": fine, "a.stl": sphere((0, 0, 0), 6.0)},
                 'size = 8.0\norgan_size = 2.5\n[body]\nsurface = "body.stl"\nmaterial = "tissue"\n'
                 '[regions.a]\nsurface = "a.stl"\n')
    assert main(["scene", str(spec), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "body (body.stl): 327680 -> " in out, out
    _, volumes, _ = measures(tmp_path / "out" / "problem.toml")
    assert sum(volumes.values()) == pytest.approx(fine.volume, rel=0.01)


def test_refusals_of_organs_that_do_not_nest(tmp_path, capsys):
    two = """
organ_size = 1.0
[body]
surface = "body.stl"
[regions.a]
surface = "a.stl"
[{kind}.b]
surface = "b.stl"
"""
    body = sphere((0, 0, 0), 20.0)
    cases = {
        "crossing": ({"a.stl": sphere((-3, 0, 0), 5.0), "b.stl": sphere((3, 0, 0), 5.0)}, "regions",
                     ["regions.a (a.stl)", "regions.b (b.stl)", "intersect"]),
        "touching": ({"a.stl": sphere((-5.03, 0, 0), 5.0), "b.stl": sphere((5.03, 0, 0), 5.0)}, "regions",
                     ["a.stl", "b.stl", "touch"]),
        "leaking": ({"a.stl": sphere((0, 0, 0), 5.0), "b.stl": sphere((18, 0, 0), 5.0)}, "regions",
                    ["regions.b (b.stl) leaks out of the body", "body.stl"]),
        "outside": ({"a.stl": sphere((0, 0, 0), 5.0), "b.stl": sphere((40, 0, 0), 5.0)}, "regions",
                    ["regions.b (b.stl) lies outside the body (body.stl)"]),
        "cavity_in_region": ({"a.stl": sphere((0, 0, 0), 10.0), "b.stl": sphere((0, 0, 0), 4.0)}, "cavities",
                             ["cavities.b (b.stl) lies inside regions.a (a.stl)", "surrounded by the body"]),
    }
    for case, (files, kind, words) in cases.items():
        spec = write(tmp_path / case, {"body.stl": body, **files}, two.format(kind=kind))
        expect_error(capsys, ["scene", spec, "--out", tmp_path / case / "out"], *words)


def test_gmsh_failure_is_one_line_naming_a_file(tmp_path):
    """Surfaces that cross (the checks before meshing bypassed): gmsh's own error, with
    the file behind the surface it names, as a UserError."""
    from fenics_elasto.mesh.anatomy import box_shell, mesh_shells
    from fenics_elasto.mesh.repair import Shell
    from fenics_elasto.util.errors import UserError

    def shell(centre, role, name):
        s = sphere(centre, 5.0, nsub=3)
        return Shell(role, name, f"{name}.stl", np.asarray(s.points), s.regular_faces.astype(np.int64))

    body = box_shell(np.array([-12.0, -10, -10]), np.array([12.0, 10, 10]), "tissue")
    with pytest.raises(UserError, match=r"gmsh could not mesh the scene near (a|b)\.stl .*intersection"):
        mesh_shells([body, shell((-2, 0, 0), "region", "a"), shell((2, 0, 0), "cavity", "b")], [None, 0, 0], [],
                    4.0, 1.5, tmp_path / "x.msh")


@pytest.mark.parametrize("text, words", [
    ("organ_sise = 2.0", ["organ_sise", "did you mean organ_size?"]),
    ("size = 'big'", ["size", "expected a number > 0", '"big"']),
    ("units = 'inch'", ["units", '"mm", "cm", "m"']),
    ("[patches.bones]\nside = { point = [0, 0], normal = [0, 1, 0] }", ["patches.bones.side.point", "3-vector"]),
    ("[patches.bones]\nside = { point = [0, -99, 0], normal = [0, -1, 0] }",
     ["patches.bones", "no part of the outer", "the body spans ["]),
    ("[patches.bones]\nside = { point = [0, -99, 0], normal = [0, 1, 0] }",  # a frame or unit slip: all of it
     ["patches.bones", "every part of the outer", "the body spans ["]),
    ("[cavities.a_surface]\nsurface = 'a.stl'", ["a_surface", "clashes"]),
    ("organ_size = 9.0\nsize = 5.0", ["organ_size 9 is larger than size 5"]),
    ("[regions.b]\nsurfce = 'b.stl'", ["regions.b", "did you mean surface?"]),
])
def test_refusals_of_bad_spec_keys(tmp_path, capsys, text, words):
    spec = write(tmp_path, {"a.stl": sphere((0, 0, 0), 5.0)}, BOX_SPEC + text + "\n" if text.startswith("[")
                 else text + "\n" + BOX_BODY)
    expect_error(capsys, ["scene", spec, "--out", tmp_path / "out"], *words)


# --------------------------------------------------------------------------- real data and the CLI


def pelvis(folder: Path, size: float) -> Path:
    """The real prostate with a bladder above and a rectum behind it (ellipsoids)."""
    return write(folder, {"bladder.stl": ellipsoid((0.7, -2.0, 64.3), (25, 20, 15)),
                          "rectum.stl": ellipsoid((0.7, 29.2, 25.0), (10, 10, 30))}, f"""
units = "mm"
size = {size}
[body]
box = {{ margin = 15.0 }}
[regions.prostate]
surface = "{PROSTATE}"
[cavities.bladder]
surface = "bladder.stl"
[cavities.rectum]
surface = "rectum.stl"
[patches.bones]
side = {{ point = [0.0, -25.0, 0.0], normal = [0.0, -1.0, 0.0] }}
""")


@pytest.mark.slow
def test_real_prostate_scene(tmp_path, capsys):
    spec = pelvis(tmp_path, 14.0)
    assert main(["scene", str(spec), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "regions.prostate" in out and "dropped 4 stray piece(s) (8 triangles each" in out
    areas, volumes, _ = measures(tmp_path / "out" / "problem.toml")
    assert set(areas) == {"outer", "bones", "bladder", "rectum", "prostate_surface"}
    # the organ as segmented: the largest connected piece of the file
    organ = pv.read(PROSTATE).connectivity("largest").extract_surface(algorithm=None)
    assert volumes["prostate"] == pytest.approx(organ.volume, rel=5e-3)
    assert areas["bladder"] == pytest.approx(ellipsoid((0, 0, 0), (25, 20, 15)).area, rel=3e-3)


@pytest.mark.slow
def test_scene_from_surfaces_runs_simulate(tmp_path):
    spec = write(tmp_path, {"ball.stl": sphere((-7, 0, 0), 5.0), "hole.stl": sphere((7, 0, 0), 4.0)}, """
organ_size = 2.5
[body]
box = { margin = 8.0 }
[regions.ball]
surface = "ball.stl"
[cavities.hole]
surface = "hole.stl"
""")
    proc = run_cli("scene", spec, "--out", tmp_path / "scene", "--size", 6)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert "element size 6 mm in the body, 2.5 mm at the organs" in proc.stdout
    proc = run_cli("simulate", tmp_path / "scene" / "problem.toml", "--out", tmp_path / "result")
    assert proc.returncode == 0, proc.stderr
    result = json.loads((tmp_path / "result" / "result.json").read_text())
    # the hole's wall is inflated by 5 % of its radius; the clamped box holds the rest
    assert result["max_displacement"] == pytest.approx(0.05 * 4.0, rel=2e-2)
    assert set(result["materials"]) == {"ball", "tissue"}


@pytest.mark.slow
def test_scene_under_mpi(tmp_path):
    spec = write(tmp_path, {"a.stl": sphere((0, 0, 0), 5.0)}, BOX_SPEC)
    proc = run_cli("scene", spec, "--out", tmp_path / "out", mpi=2)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("wrote ") == 1
    bad = write(tmp_path / "bad", {"a.stl": sphere((0, 0, 0), 5.0)}, BOX_SPEC.replace("size", "sise"))
    proc = run_cli("scene", bad, "--out", tmp_path / "out2", mpi=2)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0 and "sise" in proc.stderr


# --------------------------------------------------------------------------- the same phantom by both doors


def test_a_box_from_a_surface_file_keeps_its_edges(tmp_path, capsys):
    """A box given as an STL (a phantom's, a machined part's) was meshed as one smooth
    surface: elements of 8 mm cut its edges off up to 2 mm deep, and the model's body was
    not the user's. Its sharp edges are now the mesh's edges: every outer facet lies on
    one face, and the areas and volume are the box's. The patch's side walls are said."""
    box = pv.Box(bounds=(-20.0, 16.0, -15.0, 15.0, -12.0, 18.0), level=6, quads=False).clean()
    spec = write(tmp_path, {"box.stl": box, "ball.stl": sphere((0, 0, 2), 6.0)}, """
size = 8.0
organ_size = 2.5
[body]
surface = "box.stl"
[regions.ball]
surface = "ball.stl"
[patches.bottom]
side = { point = [0.0, -13.0, 0.0], normal = [0.0, -1.0, 0.0] }
[patches.top]
side = { point = [0.0, 13.0, 0.0], normal = [0.0, 3.0, 0.0] }
""")
    assert main(["scene", str(spec), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "body (box.stl): its sharp edges" in out
    assert "patches.bottom: 1344 mm^2, 20% of it side walls reaching 2 mm past its plane" in out, out  # 2 (36 + 30) 2
    assert "patches.top: 1344 mm^2, 20% of it side walls reaching 2 mm past its plane" in out, out  # a normal of length 3
    areas, volumes, scene = measures(tmp_path / "out" / "problem.toml")
    a, b, c = 36.0, 30.0, 30.0
    assert areas["outer"] == pytest.approx(2 * (a * b + b * c + c * a), rel=1e-9)
    assert areas["bottom"] == pytest.approx(a * c + 2 * (a + c) * 2.0, rel=1e-9)  # face + 2-wide strips
    assert volumes["tissue"] + volumes["ball"] == pytest.approx(a * b * c, rel=1e-9)
    corners = facet_corners(scene, "outer")
    faces = np.array([[-20.0, -15.0, -12.0], [16.0, 15.0, 18.0]])
    on_face = np.isclose(corners[:, :, None, :], faces[None, None], atol=1e-9)  # (facet, corner, low/high, axis)
    assert on_face.all(axis=1).any(axis=(1, 2)).all()  # every facet's three corners share a face


def test_sharp_edges_are_kept_only_where_they_part_faces():
    """A box's twelve edges are features, also once decimated (as a fine export or a
    label map's surface is); a bumpy organ's stray sharp edges are not."""
    from fenics_elasto.mesh.labelmaps import coarsen
    from fenics_elasto.mesh.repair import feature_edges, featured, shells_of

    length = lambda shell: np.linalg.norm(np.subtract(*shell.points[shell.features.T]), axis=1).sum()  # noqa: E731
    box = pv.Box(bounds=(0.0, 30.0, 0.0, 20.0, 0.0, 10.0), level=20, quads=False).clean()
    shell = featured(shells_of(np.asarray(box.points), box.faces.reshape(-1, 4)[:, 1:], "box", "body", "tissue")[0])
    decimated = coarsen([shell], 6.0)[0]
    assert len(decimated.triangles) < len(shell.triangles) / 3
    for kept in (shell, decimated):
        assert length(kept) == pytest.approx(4 * (30 + 20 + 10))
    bumpy = sphere((0, 0, 0), 10.0, nsub=3)
    rng = np.random.default_rng(0)
    spikes = rng.choice(bumpy.n_points, 20, replace=False)
    bumpy.points[spikes] *= 1.6  # twenty spikes: sharp edges around each, parting only specks
    from fenics_elasto.mesh.repair import sharp_edges

    triangles = bumpy.faces.reshape(-1, 4)[:, 1:]
    assert len(sharp_edges(np.asarray(bumpy.points), triangles)) > 60
    assert len(feature_edges(np.asarray(bumpy.points), triangles)) == 0


def phantom_files(folder: Path) -> Path:
    """The built-in phantom's shapes (phantom_organs(0), its 12 x 10 x 10 cm box) written as
    surface files, and a spec that makes them a scene: prostate a region; bladder, rectum
    and both bones cavities."""
    from fenics_elasto.mesh.builtin import FAR_SIZE, ORGAN_SIZE, PHANTOM_HALF, phantom_organs
    from fenics_elasto.app.study import SIZE

    organs = phantom_organs(0)

    def cylinder(organ, axis):
        centre, direction = np.asarray(organ["center"], float), np.eye(3)[axis]
        return pv.Cylinder(center=centre + 0.5 * organ["length"] * direction, direction=direction, radius=organ["radius"],
                           height=organ["length"], resolution=96).triangulate().subdivide_adaptive(max_edge_len=0.3).clean()

    half = np.asarray(PHANTOM_HALF)
    box = pv.Box(bounds=(-half[0], half[0], -half[1], half[1], -half[2], half[2]), level=8, quads=False).clean()
    files = {"body.stl": box, "rectum.stl": cylinder(organs["rectum"], 2), "pubis.stl": cylinder(organs["pubis"], 0),
             "sacrum.stl": cylinder(organs["sacrum"], 0)}
    files.update({f"{name}.stl": ellipsoid(organs[name]["center"], organs[name]["radii"], nsub=5)
                  for name in ("prostate", "bladder")})
    spec = f'units = "cm"\nsize = {FAR_SIZE * SIZE}\norgan_size = {ORGAN_SIZE * SIZE}\n'
    spec += '[body]\nsurface = "body.stl"\nmaterial = "tissue"\n[regions.prostate]\nsurface = "prostate.stl"\n'
    spec += "".join(f'[cavities.{name}]\nsurface = "{name}.stl"\n' for name in ("bladder", "rectum", "pubis", "sacrum"))
    return write(folder, files, spec)


@pytest.mark.slow
def test_phantom_from_surface_files_gives_the_built_in_phantoms_E(tmp_path):
    """The prostate phantom through `scene` from its CAD shapes written as STL files,
    with the built-in problem, trained as `mesh prostate-phantom` is in the demo (12
    example scans), estimating prostate E = 50 from one held-out target on a finer
    built-in mesh. Its answer rests on a flat Phi*: sigma is 8.5 % of E, and the mesh's
    node numbering alone moved it by about one sigma (49.58 with gmsh's numbering, 50.54
    with some loads read from the mesh's parallel copy, 46.42 +- 4.24 [39.0, 55.9] with
    every load from it; 51.59 through the built-in door, which test_prostate_demo_quick
    and test_reduction.py run; with the box's and the cylinders' edges kept as edges of the
    mesh, 50.97 [48.3, 53.8], against 49.90 [46.5, 53.6] smoothed over). So the check is
    the interval's, and a bound of 10 % that a wrongly routed scene (groups, regions,
    units) would miss by far."""
    from fenics_elasto.mesh.builtin import build_scene as build_builtin
    from fenics_elasto.inverse.objective import InverseProblem
    from fenics_elasto.inverse.reduction.bases import train_bases
    from fenics_elasto.app.study import FINE, SIZE, recovered, run_case, simulate_examples, simulate_targets

    builtin = build_builtin("prostate-phantom", tmp_path / "builtin", size=SIZE)  # its problem.toml only
    build_scene_from_spec(phantom_files(tmp_path / "files"), tmp_path / "scene")
    routed = tmp_path / "scene" / "problem.toml"  # the built-in problem on the scene's mesh (bones: two groups)
    routed.write_text(builtin.read_text().replace('"phantom.msh"', '"scene.msh"').replace('["bones"]', '["pubis", "sacrum"]'))
    target = simulate_targets(tmp_path / "targets", (50.0,), FINE)[50.0].settings(landmarks=False)
    examples = simulate_examples(routed, tmp_path / "scene" / "examples", 12)
    bases = train_bases(InverseProblem(load_scene(routed), target=False), examples, rank=12)
    result = run_case(routed, target, bases.W)
    E = recovered(result)
    low, high = result["uncertainty"]["prostate.E"]["ci95"]
    print("prostate E = 50 through `scene`:", E, [low, high])
    assert low < 50.0 < high and abs(E - 50.0) / 50.0 < 0.10, (E, low, high)


KIDNEY = Path(__file__).resolve().parents[3] / "meshes" / "kidney"


@pytest.mark.slow
def test_the_published_kidney_gets_through(tmp_path, capsys):
    """#34: scikit-surgeryvtk's kidney and tumours as published (non-manifold, specks,
    duplicates) were refused, and after MeshFix gmsh failed on them. Both are rebuilt
    from what they enclose, each saying so, and meshed: the tumours keep their 4.7 cm³
    within 1 % (the two tumours of 2.6 and 2.1 cm³), the kidney its volume."""
    spec = tmp_path / "kidney.toml"
    spec.write_text(f'units = "mm"\nsize = 7.0\norgan_size = 2.5\n[body]\nsurface = "{KIDNEY / "kidney.vtk"}"\n'
                    f'material = "kidney"\n[regions.tumour]\nsurface = "{KIDNEY / "tumors.vtk"}"\n')
    assert main(["scene", str(spec), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert out.count("rebuilt from what it encloses") == 2 and "29 edges are shared" in out, out
    _, volumes, _ = measures(tmp_path / "out" / "problem.toml")
    assert volumes["tumour"] == pytest.approx(2600.0 + 2100.0, rel=0.015)  # the 2.6 and 2.1 cm3
    whole = pv.read(KIDNEY / "kidney.vtk").connectivity("largest").extract_surface(algorithm=None)
    assert volumes["kidney"] + volumes["tumour"] == pytest.approx(whole.volume, rel=0.01)


def test_a_patch_plane_a_hair_off_a_face_is_refused():
    """A plane 1e-6 above a block's bottom face cuts its sides into a strip gmsh cannot
    mesh: a user's scene ran at 100 % CPU past ten minutes, deaf to Ctrl-C. Refused in
    one line, not moved (it would cut a band along the face); a plane 1 off the face is
    kept as given."""
    from fenics_elasto.mesh.anatomy import Patch, _clear_of_slivers, box_shell
    from fenics_elasto.util.errors import UserError

    body = box_shell(np.array([-12.0, -10, -10]), np.array([12.0, 10, 10]), "tissue")
    down = np.array([0.0, 0.0, -1.0])
    kept = Patch("bottom", np.array([0.0, 0.0, -9.0]), down)
    assert _clear_of_slivers(body, kept, "spec: patches.bottom", "mm") is kept
    with pytest.raises(UserError, match=r"spec: patches.bottom: its plane passes 1e-06 mm from .* too thin to mesh"):
        _clear_of_slivers(body, Patch("bottom", np.array([0.0, 0.0, -10 + 1e-6]), down), "spec: patches.bottom", "mm")


def test_a_patch_plane_crossing_a_hair_from_a_point_is_moved_clear():
    """A plane across a ball that passes 1e-6 of an edge from one of its points (a label
    map's smoothed staircase did so on 1 voxel grid in 10 of a user's, and was refused)
    is moved along its normal by a hundredth of an edge or a few, said in one line, and
    then clears every point it cuts past by a thousandth of an edge."""
    import pyvista as pv

    from fenics_elasto.mesh.anatomy import NUDGE_CLEAR, NUDGE_SHARE, NUDGE_STEPS, Patch, _clear_of_slivers, _closest_corner
    from fenics_elasto.mesh.repair import Shell

    ball = pv.Icosphere(radius=10.0, nsub=3)
    body = Shell("body", "tissue", "body", np.asarray(ball.points, float), ball.regular_faces.astype(np.int64))
    edge = float(np.linalg.norm(body.points[body.triangles[0, 0]] - body.points[body.triangles[0, 1]]))
    normal = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
    vertex = body.points[np.argmin(np.abs(body.points @ normal - 3.0))]  # well inside the ball's span
    given = Patch("side", vertex + 1e-6 * edge * normal, normal)
    lines: list[str] = []
    with logged(lines):
        moved = _clear_of_slivers(body, given, "spec: patches.side", "mm")
    shift = float((moved.point - given.point) @ normal)
    assert 0 < abs(shift) <= NUDGE_STEPS * NUDGE_SHARE * 1.5 * edge, shift
    assert _closest_corner(body, moved.point, normal)[0] >= NUDGE_CLEAR
    assert any(line.startswith("note: spec: patches.side: its plane passed") and "moved" in line for line in lines), lines


def test_a_loaded_patch_is_loaded_matched_beside_the_outer_surface_and_pushed_by_simulate(tmp_path):
    """``[patches.probe] loaded = true``: problem.toml loads it (clamping the other patch),
    matches the free outer surface beside the organs, and gives ``simulate`` a push along
    its normal -- a probe pressing an organ without a --set for every list (an outside
    user needed three on every command)."""
    surfaces = {"body.stl": sphere((0, 0, 0), 12.0, nsub=4), "ball.stl": sphere((2, 0, 0), 4.0)}
    spec = write(tmp_path, surfaces, """
size = 4.0
organ_size = 2.5
[body]
surface = "body.stl"
[regions.ball]
surface = "ball.stl"
[patches.back]
side = { point = [0.0, -9.0, 0.0], normal = [0.0, -1.0, 0.0] }
[patches.probe]
side = { point = [0.0, 9.0, 0.0], normal = [0.0, 2.0, 0.0] }
loaded = true
""")
    problem = build_scene_from_spec(spec, tmp_path / "scene")
    text = problem.read_text()
    assert 'fixed   = ["back"]' in text and 'loaded  = ["probe"]' in text
    assert 'matched = ["ball_surface", "outer"]' in text
    push = 0.03 * np.linalg.norm(np.ptp(pv.read(tmp_path / "body.stl").points, axis=0))  # 3 % of the body's size
    assert "[boundary.displacement.probe]" in text and f"value = [0, {-push:.6g}, 0]" in text
    assert main(["simulate", str(problem), "--out", str(tmp_path / "result")]) == 0
    result = json.loads((tmp_path / "result" / "result.json").read_text())
    assert result["max_displacement"] == pytest.approx(push, rel=2e-2)
    # no patch holding the body: the rest of the outer surface is clamped, so not matched
    held = "[patches.back]\nside = { point = [0.0, -9.0, 0.0], normal = [0.0, -1.0, 0.0] }\n"
    assert held in spec.read_text()
    alone = write(tmp_path / "alone", surfaces, spec.read_text().replace(held, ""))
    text = build_scene_from_spec(alone, tmp_path / "alone" / "scene").read_text()
    assert 'fixed   = ["outer"]' in text and 'loaded  = ["probe"]' in text and 'matched = ["ball_surface"]' in text
