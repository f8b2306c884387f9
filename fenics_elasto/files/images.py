"""Label-map images (segmentations) -> integer voxel labels and their index-to-world affine.

Readers, chosen for telling world coordinates exactly as each format defines them:

- NIfTI (``.nii``, ``.nii.gz``): nibabel (MIT), the reference Python reader of the
  format. ``img.affine`` is the sform where its code is set, else the qform, applied to
  (i, j, k) with no axis flips -- the RAS+ frame that 3D Slicer and TotalSegmentator
  write. (ITK reads NIfTI into LPS, negating x and y, which is why it is not used here.)
- NRRD (``.nrrd``, ``.nhdr``) and MetaImage (``.mha``, ``.mhd``): SimpleITK (Apache-2),
  ITK's own readers of both, with detached headers, compression and every pixel type:
  world = origin + direction @ diag(spacing) @ (i, j, k). One library for both formats
  (pynrrd reads NRRD only). A NRRD written in a RAS space is read back by ITK in LPS; its
  header's own frame is restored here, so the coordinates are the header's.

Both give a ``LabelImage``: labels indexed [i, j, k] (the first index varies along the
first axis of the header) and the 4 x 4 affine taking (i, j, k, 1) to world (x, y, z, 1).
Bad input -- no file, an unknown suffix, an unreadable file, not 3D, not integer labels,
no voxel spacing, nothing labelled -- is one line (UserError).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.logs import log

NIFTI = (".nii", ".nii.gz")
ITK = (".nrrd", ".nhdr", ".mha", ".mhd")


@dataclass
class LabelImage:
    """Integer labels per voxel, indexed [i, j, k], and the index-to-world affine (4 x 4)."""

    labels: np.ndarray
    affine: np.ndarray

    @property
    def spacing(self) -> np.ndarray:
        """The voxel's edge lengths along i, j, k (the affine's column norms)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def world(self, ijk: np.ndarray) -> np.ndarray:
        """World coordinates of (fractional) voxel indices, one row each."""
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]


def _suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def is_image(path) -> bool:
    """Is ``path`` named as an image this module reads (by its suffix)?"""
    return _suffix(Path(path)) in NIFTI + ITK


def read_label_image(path, label: str) -> LabelImage:
    """The label map in ``path`` (NIfTI, NRRD or MetaImage), checked; ``label`` names it
    in error lines (e.g. 'labels.image (seg.nii.gz)')."""
    path = Path(path)
    require(path.is_file(), f"{label}: no such file {path}")
    suffix = _suffix(path)
    require(suffix in NIFTI + ITK, f"{label}: not a label-map image: expected {', '.join(NIFTI + ITK)}, got {path.name}")
    try:
        data, affine = _read_nifti(path) if suffix in NIFTI else _read_itk(path)
    except UserError:
        raise
    except Exception as err:  # readers raise anything from OSError to their own exception types
        cause = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        raise UserError(f"{label}: cannot read it as an image ({cause[:200]})") from None
    return _checked(data, affine, label)


def _read_nifti(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import nibabel as nib

    image: Any = nib.load(str(path))  # a Nifti1Image (or Nifti2Image) for these suffixes
    affine = np.asarray(image.affine, dtype=float)
    _say_if_qform_differs(image, affine, path)
    return np.asanyarray(image.dataobj), affine


def _say_if_qform_differs(image: Any, affine: np.ndarray, path: Path) -> None:
    """A header whose sform and qform both hold a frame, and disagree by more than half a
    voxel somewhere in the image, is said: the sform is used (as nibabel, 3D Slicer and
    ITK do), and a tool that read the qform would put the labels elsewhere."""
    qform, code = image.get_qform(coded=True)
    if qform is None or not code or not image.get_sform(coded=True)[1]:
        return
    corners = np.array([[i, j, k, 1.0] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) * np.r_[image.shape[:3], 1]
    apart = float(np.max(np.linalg.norm((corners @ (affine - qform).T)[:, :3], axis=1)))
    voxel = float(np.min(np.linalg.norm(affine[:3, :3], axis=0)))
    if apart > 0.5 * voxel:
        log.warning(f"{path.name}: its sform and qform disagree by up to {apart:.3g} (image units); the sform is "
                    "used, as nibabel, 3D Slicer and ITK do")


RAS_SPACES = ("right-anterior-superior", "RAS")


def _read_itk(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import SimpleITK as sitk

    image = sitk.ReadImage(str(path))
    require(image.GetDimension() == 3, f"not a 3D image: {image.GetDimension()} dimensions")
    require(image.GetNumberOfComponentsPerPixel() == 1, f"{image.GetNumberOfComponentsPerPixel()} values per voxel")
    data = sitk.GetArrayFromImage(image).transpose(2, 1, 0)  # ITK's array is [k, j, i]
    direction = np.array(image.GetDirection(), dtype=float).reshape(3, 3)
    affine = np.eye(4)
    affine[:3, :3] = direction * np.array(image.GetSpacing(), dtype=float)
    affine[:3, 3] = image.GetOrigin()
    if image.HasMetaDataKey("NRRD_space") and image.GetMetaData("NRRD_space") in RAS_SPACES:
        affine[:2] *= -1  # ITK turned the header's RAS into LPS; back to the header's frame
    return data, affine


def _checked(data: np.ndarray, affine: np.ndarray, label: str) -> LabelImage:
    """Integer labels on a 3D grid with a usable affine, and something labelled."""
    data = np.asarray(data)
    if data.ndim > 3 and all(n == 1 for n in data.shape[3:]):  # NIfTI may store a 3D map as 1 x 1 volumes
        data = data.reshape(data.shape[:3])
    require(data.ndim == 3, f"{label}: not a 3D label map (shape {data.shape})")
    require(data.size > 0, f"{label}: the image has no voxels")
    if not np.issubdtype(data.dtype, np.integer):
        require(np.issubdtype(data.dtype, np.floating) and np.isfinite(data).all() and (data == np.round(data)).all(),
                f"{label}: not a label map: its voxels hold non-integer values ({data.dtype}, e.g. "
                f"{_non_integer(data)}); a segmentation's labels are integers")
    require(np.isfinite(affine).all(), f"{label}: the header's spacing or orientation is not finite")
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    require((spacing > 0).all() and abs(np.linalg.det(affine[:3, :3])) > 1e-12 * spacing.prod(),
            f"{label}: no voxel spacing in its header (spacings {', '.join(f'{s:g}' for s in spacing)})")
    labels = data.astype(np.int64)
    require(labels.any(), f"{label}: the image is empty (every voxel is 0, the background)")
    return LabelImage(labels, affine)


def _non_integer(data: np.ndarray) -> str:
    finite = data[np.isfinite(data)]
    odd = finite[finite != np.round(finite)]
    return f"{odd.flat[0]:g}" if odd.size else "NaN"


def check_off_border(labelled: np.ndarray, label: str) -> None:
    """One line where labelled voxels (non-zero) lie on the image's border: the
    segmentation was cut off there (a rest map for ``scene``, a deformed one for a target:
    a user's map cropped through the body was refused as 'the data do not determine')."""
    for axis, name in enumerate("ijk"):
        for end in (0, labelled.shape[axis] - 1):
            face = np.take(labelled, end, axis=axis)
            require(not face.any(), f"{label}: labelled voxels on the image border ({name} = {end}): the "
                    "segmentation is cut off there; pad the image or crop less")
