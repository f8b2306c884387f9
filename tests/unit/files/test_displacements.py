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
    with pytest.raises(UserError, match="one vector array on the points, found 2"):
        read_displacement(tmp_path / "two.vtp", 3)


def test_a_label_map_is_not_a_displacement_field(tmp_path):
    lm.write_nifti(tmp_path / "seg.nii.gz", lm.label_map())
    with pytest.raises(UserError, match="not a displacement field: expected 3 values per voxel"):
        read_displacement(tmp_path / "seg.nii.gz", 3)
