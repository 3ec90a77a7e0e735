"""COLMAP model files: finding a scene's model folder and reading it (``.bin`` by :mod:`.colmap_binary`,
which also writes one, ``.txt`` by :mod:`.colmap_text`); what a model holds is :mod:`.colmap_records`,
re-exported here.

The reader is ours (numpy and :mod:`struct`), so that a COLMAP scene loads without pycolmap. It walks
every record and checks it as it goes: a truncated or padded binary file, a damaged text line, an
unknown camera model, an image whose camera or frame is missing and a non-finite camera parameter or
pose are :class:`DatasetError` naming the file and the record (byte offset or line number). The
undistortion hands a model to pycolmap only after this reader accepted it: pycolmap (4.2.1) hangs on
some truncated binary files, silently accepts others and reads NaN poses without complaint.

Conventions (COLMAP's): a pose ``cam_from_world`` maps world to camera coordinates, ``x_cam = R x + t``,
stored as a unit quaternion ``(qw, qx, qy, qz)`` and a translation. Models written by COLMAP 3.12 and
later also hold ``rigs`` and ``frames``: a frame's ``rig_from_world`` and its sensor's
``sensor_from_rig`` then give an image's pose (the pose written beside the image is not used, as
COLMAP does not use it either); older models have only the three files and the pose beside each image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .colmap_binary import read_binary_model
from .colmap_records import (
    CAMERA_MODELS,
    CAMERA_MODELS_BY_NAME,
    CameraModel,
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    ColmapPoints,
    quaternion_from_rotation,
    rotation_from_quaternion,
)
from .colmap_text import read_text_model
from .errors import DatasetError

__all__ = [
    "CAMERA_MODELS",
    "CAMERA_MODELS_BY_NAME",
    "CameraModel",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "ColmapPoints",
    "find_sparse_dir",
    "model_points",
    "quaternion_from_rotation",
    "read_model",
    "rotation_from_quaternion",
]

_MODEL_FILES = ("cameras", "images", "points3D")


def find_sparse_dir(scene: Path) -> Path | None:
    """The COLMAP model folder of a scene: ``sparse/0`` if it holds a model, else ``sparse``, else None.

    A folder holds a model if it has ``cameras``, ``images`` and ``points3D`` all as ``.bin`` or all as
    ``.txt``.
    """
    for cand in (Path(scene) / "sparse" / "0", Path(scene) / "sparse"):
        if _model_ext(cand) is not None:
            return cand
    return None


def _model_ext(folder: Path) -> str | None:
    for ext in (".bin", ".txt"):
        if all((folder / f"{n}{ext}").is_file() for n in _MODEL_FILES):
            return ext
    return None


# ----------------------------------------------------------------------------------------------------
# Reading a model folder
# ----------------------------------------------------------------------------------------------------


def read_model(folder: Path) -> ColmapModel:
    """Reads a COLMAP model folder (``.bin``, else ``.txt``; see the module docstring).

    Text files whose header declares a count (``# Number of points: N``) are checked against what was
    read, which catches files truncated at a line boundary.

    Raises:
      DatasetError naming the folder / file and the problem.
    """
    folder = Path(folder)
    ext = _model_ext(folder)
    if ext is None:
        raise DatasetError(f"{folder} does not hold a COLMAP model (cameras, images and points3D as .bin "
                           "or .txt).")
    return read_binary_model(folder) if ext == ".bin" else read_text_model(folder)


def model_points(model: ColmapModel):
    """(ids (M,) int64 sorted, xyz (M, 3) float64, colours (M, 3) float32 in [0, 1]) of a model's 3D
    points; a non-finite point is a :class:`DatasetError` naming the file and the ids (it would have
    become a NaN Gaussian)."""
    pts = model.points
    cols = pts.rgb.astype(np.float32) / 255.0
    bad = pts.ids[~np.all(np.isfinite(pts.xyz), axis=1)]
    if bad.size:
        raise DatasetError(f"COLMAP file {model.file('points3D')}: {bad.size} of {pts.ids.size} "
                           f"points have non-finite coordinates (ids {bad[:5].tolist()}"
                           f"{' ...' if bad.size > 5 else ''}); re-run COLMAP triangulation or delete those points.")
    return pts.ids.copy(), pts.xyz.copy(), cols
