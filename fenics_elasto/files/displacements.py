"""Displacement fields (image registration's output) -> (points, vectors) in the world frame.

Two kinds of file:

- points with one vector array (``.vtu``, ``.vtp``, ``.vtk``: anything pyvista reads):
  the field's samples where the registration placed them;
- a displacement-field image -- NIfTI (nibabel) or NRRD / MetaImage (SimpleITK), the
  readers and world frame of label maps (images.py) -- with gdim values per voxel:
  the samples are the voxel centres, the vectors the voxel values in that frame.

The vectors are read in the points' frame (``frame = "world"``). ITK, SimpleITK, ANTs
and elastix write a NIfTI displacement field's vectors in ITK's LPS frame while its
header's affine (as nibabel reads it) is RAS: ``frame = "itk"`` turns such vectors into
the RAS world (x and y negated). A MetaImage or NRRD field is read in ITK's frame
already, points and vectors alike; a point file's vectors are its points' own.

Bad input (no file, no vector array or several, a scalar image, non-finite values) is
one line (UserError).
"""


from __future__ import annotations

from pathlib import Path

import numpy as np

from fenics_elasto.files.images import NIFTI, RAS_SPACES, _suffix, is_image
from fenics_elasto.util.errors import UserError, require


def read_displacement(path, gdim: int, frame: str = "world") -> tuple[np.ndarray, np.ndarray]:
    """(points (n, gdim), vectors (n, gdim)) of the displacement field in ``path``, its
    vectors in ``frame`` (module docstring)."""
    path = Path(path)
    require(path.is_file(), f"{path}: no such displacement field file")
    suffix = _suffix(path)
    if is_image(path):
        require(gdim == 3, f"{path}: a displacement-field image needs a 3D scene")
        points, vectors = _image_field(path, suffix)
        if frame == "itk" and suffix in NIFTI:  # ITK's LPS vectors into the header's RAS world
            vectors[:, :2] *= -1.0
    else:
        require(frame == "world", f"{path}: displacement_frame = \"itk\" is for NIfTI images written by ITK "
                                  "(LPS vectors); a point file's vectors are read in its points' frame")
        points, vectors = _point_field(path, gdim)
    require(len(points) > 0, f"{path}: the displacement field has no points")
    # An image's NaN may be a registration's masked background, dropped with the voxels
    # outside the body (displacement_field.observed_samples refuses one inside it).
    require(np.isfinite(points).all() and (is_image(path) or np.isfinite(vectors).all()),
            f"{path}: the displacement field holds NaN or infinite values")
    return points, vectors


def _point_field(path: Path, gdim: int) -> tuple[np.ndarray, np.ndarray]:
    from fenics_elasto.files.readers import quiet_vtk

    import pyvista as pv

    try:
        with quiet_vtk(raise_errors=True):
            mesh = pv.read(str(path))
    except Exception as err:  # noqa: BLE001 (pyvista raises many kinds; all mean "cannot read")
        raise UserError(f"{path}: cannot read a displacement field ({type(err).__name__})") from None
    arrays = {name: np.asarray(mesh.point_data[name]) for name in mesh.point_data.keys()}
    vectors = {name: a for name, a in arrays.items() if a.ndim == 2 and a.shape[1] in (2, 3)}
    others = ", ".join(f"{name} of {a.shape[1] if a.ndim == 2 else 1} component(s)" for name, a in arrays.items())
    require(len(vectors) == 1, f"{path}: expected one vector array (2 or 3 components) on the points, found "
            + (f"{len(vectors)} ({', '.join(vectors)})" if vectors else f"none ({others or 'no arrays'})"))
    (values,) = vectors.values()
    flat = values.shape[1] >= gdim and not np.any(values[:, gdim:])  # 2D fields may carry a zero z
    require(flat, f"{path}: its vectors have {values.shape[1]} components, the scene is {gdim}D")
    points = np.asarray(mesh.points, float)
    off = np.abs(points[:, gdim:]).max(initial=0.0)
    require(off <= 1e-9 * max(float(np.ptp(points, axis=0).max(initial=0.0)), 1e-300),
            f"{path}: its points lie up to {off:.3g} off the 2D scene's plane z = 0 (a slice from another plane?)")
    return points[:, :gdim], values[:, :gdim].astype(float)


def _image_field(path: Path, suffix: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        data, affine = _read_nifti_vectors(path) if suffix in NIFTI else _read_itk_vectors(path)
    except UserError:
        raise
    except Exception as err:  # noqa: BLE001 (the readers' own errors: an unreadable file)
        raise UserError(f"{path}: cannot read a displacement-field image ({type(err).__name__})") from None
    require(data.ndim == 4 and data.shape[3] == 3,
            f"{path}: not a displacement field: expected 3 values per voxel, got shape {data.shape}")
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    require(np.isfinite(affine).all() and (spacing > 0).all(), f"{path}: no voxel spacing in its header")
    ijk = np.indices(data.shape[:3]).reshape(3, -1).T.astype(float)
    points = ijk @ affine[:3, :3].T + affine[:3, 3]
    return points, data.reshape(-1, 3).astype(float)


def _read_nifti_vectors(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """NIfTI stores a vector per voxel along its 5th axis (intent "vector", shape X Y Z 1 3)."""
    import nibabel as nib

    image = nib.load(str(path))
    data = np.asanyarray(image.dataobj)  # type: ignore[attr-defined]
    if data.ndim == 5 and data.shape[3] == 1:
        data = data[:, :, :, 0, :]
    return data, np.asarray(image.affine, float)  # type: ignore[attr-defined]


def _read_itk_vectors(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ITK's displacement fields are in its LPS frame; a header written in RAS is restored
    to its own frame, points and vectors alike (as label maps: images.py)."""
    import SimpleITK as sitk

    image = sitk.ReadImage(str(path))
    require(image.GetDimension() == 3, f"{path}: not a 3D image")
    data = sitk.GetArrayFromImage(image)  # [k, j, i, component]
    require(data.ndim == 4, f"{path}: not a displacement field: one value per voxel")
    data = data.transpose(2, 1, 0, 3).astype(float)
    affine = np.eye(4)
    affine[:3, :3] = np.array(image.GetDirection(), float).reshape(3, 3) * np.array(image.GetSpacing(), float)
    affine[:3, 3] = image.GetOrigin()
    if image.HasMetaDataKey("NRRD_space") and image.GetMetaData("NRRD_space") in RAS_SPACES:
        affine[:2] *= -1
        data[..., :2] *= -1
    return data, affine
