"""Synthetic label maps for the label-map tests: an ellipsoid "kidney" (label 1) holding a
ball "tumour" (label 2), on anisotropic voxels, with an affine that rotates and shifts."""

from __future__ import annotations

import numpy as np

SHAPE = (44, 38, 26)
SPACING = np.array([1.0, 1.2, 1.8])  # mm: anisotropic, as CT is
AXES = np.array([18.0, 14.0, 16.0])  # the ellipsoid's semi-axes along i, j, k (mm)
RADIUS = 6.0  # the ball's
OFFSET = np.array([-30.0, 12.5, -845.0])  # world position of voxel (0, 0, 0)


def rotation() -> np.ndarray:
    """A rotation about a tilted axis (no axis-aligned shortcut survives it)."""
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    angle = np.radians(30.0)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def affine() -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = rotation() * SPACING
    a[:3, 3] = OFFSET
    return a


def centre_mm() -> np.ndarray:
    """The shapes' centre in scaled index space (mm along i, j, k)."""
    return (np.array(SHAPE) - 1) * SPACING / 2


def label_map(scale: float = 1.0) -> np.ndarray:
    """The kidney (1) with the tumour (2) in it; ``scale`` grows both about the centre."""
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij"), axis=-1) * SPACING - centre_mm()
    return _labels(grid, scale)


def labels_at(x: np.ndarray) -> np.ndarray:
    """The exact shapes' label (0, 1 or 2) at world points x (n, 3)."""
    return _labels((x - OFFSET) @ rotation() - centre_mm(), 1.0)


def _labels(offsets: np.ndarray, scale: float) -> np.ndarray:
    """Labels at offsets from the centre along the image's axes, in mm (..., 3)."""
    labels = np.zeros(offsets.shape[:-1], np.int16)
    labels[((offsets / (scale * AXES)) ** 2).sum(axis=-1) <= 1] = 1
    labels[(offsets**2).sum(axis=-1) <= (scale * RADIUS) ** 2] = 2
    return labels


def world_ellipsoid_bounds(scale: float = 1.0) -> np.ndarray:
    """The bounding box of the affine-mapped ellipsoid: along world axis r the half-width
    is |row r of (R diag(axes))|."""
    m = rotation() * (scale * AXES)
    centre = rotation() @ centre_mm() + OFFSET
    half = np.linalg.norm(m, axis=1)
    return np.array([centre - half, centre + half])


def world_centre() -> np.ndarray:
    return rotation() @ centre_mm() + OFFSET


def write_nifti(path, labels: np.ndarray) -> None:
    import nibabel as nib

    image = nib.Nifti1Image(labels, affine())
    image.set_sform(affine(), code=1)
    nib.save(image, str(path))


def write_itk(path, labels: np.ndarray) -> None:
    """NRRD or MetaImage (by the suffix) with the same world frame as write_nifti."""
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(labels.transpose(2, 1, 0).copy())
    image.SetSpacing(SPACING.tolist())
    image.SetOrigin(OFFSET.tolist())
    image.SetDirection(rotation().ravel().tolist())
    sitk.WriteImage(image, str(path))


def kidney_spec(image: str, organ_size: float = 2.5, patches: dict | None = None) -> str:
    """A scene spec (interface.md, "Scenes from label maps") of a kidney label map: the
    body labels 1 and 2, the tumour region label 2, and ``patches`` (name -> (point,
    normal), world coordinates) cut from its surface by planes."""
    text = (f'units = "mm"\nsize = 8.0\norgan_size = {organ_size:g}\n[labels]\nimage = "{image}"\n'
            '[body]\nlabel = [1, 2]\nmaterial = "kidney"\n[regions.tumour]\nlabel = 2\n')
    for name, (point, normal) in (patches or {}).items():
        listed = [[float(x) for x in v] for v in (point, normal)]
        text += f"[patches.{name}]\nside = {{ point = {listed[0]}, normal = {listed[1]} }}\n"
    return text
