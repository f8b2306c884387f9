"""Displacement fields read from files: points with one vector array, and vector images
in the label maps' world frame (files/displacements.py)."""

from __future__ import annotations

import numpy as np
import pytest

import labelmaps as lm
from fenics_elasto.files.displacements import read_displacement
from fenics_elasto.util.errors import UserError

GRADIENT = np.array([[0.01, 0.002, 0.0], [0.0, -0.02, 0.005], [0.003, 0.0, 0.015]])


def field_at(points: np.ndarray) -> np.ndarray:
    """A known affine field in world coordinates."""
    return (points - lm.world_centre()) @ GRADIENT.T + [0.1, -0.2, 0.3]


def voxel_centres() -> np.ndarray:
    ijk = np.indices(lm.SHAPE).reshape(3, -1).T
    return ijk @ lm.affine()[:3, :3].T + lm.affine()[:3, 3]


def test_a_nifti_vector_image_gives_world_points_and_vectors(tmp_path):
    """NIfTI's vector intent (X Y Z 1 3), rotated anisotropic voxels: every voxel centre
    at its world position (the header's affine), its vector as stored."""
    import nibabel as nib

    points = voxel_centres()
    data = field_at(points).reshape(*lm.SHAPE, 1, 3)
    image = nib.Nifti1Image(data.astype(np.float32), lm.affine())
    image.header.set_intent("vector")
    nib.save(image, str(tmp_path / "u.nii.gz"))
    read_points, vectors = read_displacement(tmp_path / "u.nii.gz", 3)
    assert np.abs(read_points - points).max() < 1e-4
    assert np.abs(vectors - field_at(points)).max() < 1e-5


def test_a_metaimage_vector_field_gives_the_same(tmp_path):
    import SimpleITK as sitk

    points = voxel_centres()
    data = field_at(points).reshape(*lm.SHAPE, 3).transpose(2, 1, 0, 3)  # ITK's array is [k, j, i, component]
    image = sitk.GetImageFromArray(data.copy(), isVector=True)
    image.SetSpacing(lm.SPACING.tolist())
    image.SetOrigin(lm.OFFSET.tolist())
    image.SetDirection(lm.rotation().ravel().tolist())
    sitk.WriteImage(image, str(tmp_path / "u.mha"))
    read_points, vectors = read_displacement(tmp_path / "u.mha", 3)
    assert np.abs(read_points - points).max() < 1e-9
    assert np.abs(vectors - field_at(points)).max() < 1e-12


def test_points_with_one_vector_array(tmp_path):
    import pyvista as pv

    points = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    cloud = pv.PolyData(points)
    cloud["u"] = field_at(points)
    cloud["pressure"] = np.ones(50)  # a scalar array beside it is fine
    cloud.save(tmp_path / "u.vtp")
    read_points, vectors = read_displacement(tmp_path / "u.vtp", 3)
    assert np.allclose(read_points, points) and np.allclose(vectors, field_at(points))
    cloud["v"] = field_at(points)  # two vector arrays: which one?
    cloud.save(tmp_path / "two.vtp")
    with pytest.raises(UserError, match=r"one vector array \(2 or 3 components\) on the points, found 2"):
        read_displacement(tmp_path / "two.vtp", 3)


def test_a_label_map_is_not_a_displacement_field(tmp_path):
    lm.write_nifti(tmp_path / "seg.nii.gz", lm.label_map())
    with pytest.raises(UserError, match="not a displacement field: expected 3 values per voxel"):
        read_displacement(tmp_path / "seg.nii.gz", 3)


LPS = np.diag([-1.0, -1.0, 1.0])  # ITK's physical frame from the RAS world, and back


def test_a_nifti_field_written_by_itk_is_read_in_the_ras_world(tmp_path):
    """SimpleITK (as ITK, ANTs, elastix) writes a NIfTI field's header in RAS but its
    vectors in LPS. Read as they stand ("world") x and y come out negated -- the box of a
    new user's test then gave E at its bound -- and with displacement_frame = "itk" they
    are the world's vectors. A point file has no such split: "itk" is refused for it."""
    import SimpleITK as sitk

    points = voxel_centres()
    lps_vectors = field_at(points) @ LPS
    data = lps_vectors.reshape(*lm.SHAPE, 3).transpose(2, 1, 0, 3)  # ITK's array is [k, j, i, component]
    image = sitk.GetImageFromArray(data.copy(), isVector=True)
    image.SetSpacing(lm.SPACING.tolist())
    image.SetOrigin((LPS @ lm.OFFSET).tolist())
    image.SetDirection((LPS @ lm.rotation()).ravel().tolist())
    sitk.WriteImage(image, str(tmp_path / "u.nii.gz"))
    as_stored, vectors = read_displacement(tmp_path / "u.nii.gz", 3)
    assert np.abs(as_stored - points).max() < 1e-4  # the header: RAS, as nibabel reads it
    assert np.abs(vectors - lps_vectors).max() < 1e-5
    read_points, vectors = read_displacement(tmp_path / "u.nii.gz", 3, frame="itk")
    assert np.abs(read_points - points).max() < 1e-4 and np.abs(vectors - field_at(points)).max() < 1e-5
    import pyvista as pv

    cloud = pv.PolyData(points[:20])
    cloud["u"] = field_at(points[:20])
    cloud.save(tmp_path / "u.vtp")
    with pytest.raises(UserError, match="displacement_frame = \"itk\" is for NIfTI images"):
        read_displacement(tmp_path / "u.vtp", 3, frame="itk")


def test_a_field_fitting_far_above_its_noise_says_where_to_look():
    """The wrong frame's field fitted at 16x its stated noise with no word; now a warning
    names the frame (and the unit, and the noise itself)."""
    from types import SimpleNamespace

    from fenics_elasto.inverse.checks import _distance_warnings

    misfit = SimpleNamespace(terms=[])
    spec = {"displacement_noise": 0.002}
    (warning,) = _distance_warnings(misfit, spec, {"field": {"rms": 0.0327}})
    assert "above 3 x target.displacement_noise (3 x 0.002)" in warning and 'displacement_frame = "itk"' in warning
    assert _distance_warnings(misfit, spec, {"field": {"rms": 0.0027}}) == []  # the right frame: 1.35x its noise


def test_landmarks_are_judged_by_their_own_noise():
    """A user's fiducials fitted at 0.0027 with landmark_noise 0.002 were said not to fit
    against 3 x target.noise (0.0004, the surfaces'); against their own noise they fit."""
    from types import SimpleNamespace

    from fenics_elasto.inverse.checks import _distance_warnings

    misfit = SimpleNamespace(terms=[])
    spec = {"noise": 0.0004, "landmark_noise": 0.002}
    assert _distance_warnings(misfit, spec, {"landmarks": {"rms": 0.0027}}) == []
    (warning,) = _distance_warnings(misfit, spec, {"landmarks": {"rms": 0.0081}})
    assert "above 3 x target.landmark_noise (3 x 0.002)" in warning


def test_a_first_order_shift_past_a_factor_e_gives_the_offset_that_moves_it_10_percent():
    """'would move core.E by -1e+02 %' said nothing, and 'by a factor 0.0018' no more (a
    user's inclusions made a tenth of that offset bigger moved E -80 %): past a factor e
    the line gives the offset that moves it 10 %, first order (0.001 x ln 1.1 / 8)."""
    from fenics_elasto.inverse.report import offset_lines

    (line,) = offset_lines(0.001, [("core.E", -8.0, True), ("rubber.E", 0.5, True), ("rubber.nu", 0.01, False)])
    assert "core.E beyond first order (1.2e-05 bigger would move it 10 %)" in line, line
    assert "rubber.E by +65 %" in line and "rubber.nu by +0.01" in line
