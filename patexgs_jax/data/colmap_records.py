"""What a COLMAP model holds, shared by the two readers (:mod:`.colmap_binary`, :mod:`.colmap_text`)
and the model folder's entry point (:mod:`.colmap_model`): the camera model table, the records of a
model (cameras, images, points), the quaternion conventions, and the checks every reader runs on a
record as it reads it (each a :class:`DatasetError` naming the file and the record).

Conventions (COLMAP's): a pose ``cam_from_world`` maps world to camera coordinates, ``x_cam = R x + t``,
stored as a unit quaternion ``(qw, qx, qy, qz)`` and a translation. Models written by COLMAP 3.12 and
later also hold ``rigs`` and ``frames``: a frame's ``rig_from_world`` and its sensor's
``sensor_from_rig`` then give an image's pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np

from .errors import DatasetError

__all__ = [
    "CAMERA_MODELS",
    "CAMERA_MODELS_BY_NAME",
    "CameraModel",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "ColmapPoints",
    "quaternion_from_rotation",
    "rotation_from_quaternion",
]

# ----------------------------------------------------------------------------------------------------
# What a model holds
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraModel:
    """One of COLMAP's camera models: its id in binary files, its name in text files, its number of
    parameters, and whether it is a perspective (central, pinhole-like) projection that can be
    undistorted to a pinhole camera."""

    model_id: int
    name: str
    num_params: int
    perspective: bool = True


#: Every camera model COLMAP (4.x, as of pycolmap 4.2) defines, by id.
CAMERA_MODELS: dict[int, CameraModel] = {m.model_id: m for m in (
    CameraModel(0, "SIMPLE_PINHOLE", 3),
    CameraModel(1, "PINHOLE", 4),
    CameraModel(2, "SIMPLE_RADIAL", 4),
    CameraModel(3, "RADIAL", 5),
    CameraModel(4, "OPENCV", 8),
    CameraModel(5, "OPENCV_FISHEYE", 8),
    CameraModel(6, "FULL_OPENCV", 12),
    CameraModel(7, "FOV", 5),
    CameraModel(8, "SIMPLE_RADIAL_FISHEYE", 4),
    CameraModel(9, "RADIAL_FISHEYE", 5),
    CameraModel(10, "THIN_PRISM_FISHEYE", 12),
    CameraModel(11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
    CameraModel(12, "SIMPLE_DIVISION", 4),
    CameraModel(13, "DIVISION", 5),
    CameraModel(14, "SIMPLE_FISHEYE", 3),
    CameraModel(15, "FISHEYE", 4),
    CameraModel(16, "EUCM", 6),
    CameraModel(17, "EQUIRECTANGULAR", 2, perspective=False),
)}
#: The same, by name.
CAMERA_MODELS_BY_NAME: dict[str, CameraModel] = {m.name: m for m in CAMERA_MODELS.values()}

# Sensor types of rigs and frames (binary: the int, text: the name); images are CAMERA data.
_SENSOR_TYPES = {-1: "INVALID", 0: "CAMERA", 1: "IMU"}
_SENSOR_TYPE_IDS = {v: k for k, v in _SENSOR_TYPES.items()}
_CAMERA = 0
# Ids are kept as int64 (COLMAP's are unsigned; none comes near 2**63).
_ID_LIMIT = 1 << 63

# A keypoint of images.bin (and .txt): x, y (float64), its 3D point's id (uint64, all ones for none: -1 as int64).
_POINT2D = np.dtype([("xy", "<f8", (2,)), ("point3D_id", "<i8")])
# The pose of a rig's reference sensor in the rig (the identity; compared by identity, never composed).
_REFERENCE = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)


@dataclass(frozen=True, eq=False)
class ColmapCamera:
    """A camera (intrinsics shared by images): ``params`` (num_params,) float64 in COLMAP's order for
    its model (PINHOLE: fx, fy, cx, cy; SIMPLE_PINHOLE: f, cx, cy; ...), pixel sizes."""

    camera_id: int
    model: CameraModel
    width: int
    height: int
    params: np.ndarray


@dataclass(frozen=True, eq=False)
class ColmapImage:
    """An image of the model (COLMAP's files hold the registered images only, so each has a pose).

    ``cam_from_world``: (3, 4) float64 ``[R | t]`` world-to-camera. ``points2D``: (K, 2) float64
    keypoint positions in pixels (COLMAP: the top-left corner of the image at (0, 0), pixel centres at
    +0.5); ``point3D_ids``: (K,) int64, the 3D point each keypoint observes, -1 for none.
    """

    image_id: int
    name: str
    camera_id: int
    cam_from_world: np.ndarray
    points2D: np.ndarray
    point3D_ids: np.ndarray


@dataclass(frozen=True, eq=False)
class ColmapPoints:
    """The model's 3D points, in ascending id order: ``ids`` (M,) int64, ``xyz`` (M, 3) float64 world
    space, ``rgb`` (M, 3) uint8, ``error`` (M,) float64 mean reprojection error in pixels,
    ``track_length`` (M,) int64 observations per point, ``tracks`` (sum of track_length, 2) int64
    ``(image_id, point2D index)`` rows, point after point in ``ids`` order."""

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    track_length: np.ndarray
    tracks: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.size)


@dataclass(frozen=True, eq=False)
class ColmapModel:
    """A COLMAP model as read from ``folder`` (``ext`` ``.bin`` or ``.txt``): cameras and images by id,
    and the 3D points."""

    folder: Path
    ext: str
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: ColmapPoints

    def file(self, name: str) -> Path:
        """The path of one of the model's files, e.g. ``file("points3D")``."""
        return self.folder / f"{name}{self.ext}"


def _rotation_or_none(q) -> np.ndarray | None:
    """(3, 3) rotation of a quaternion ``(w, x, y, z)`` (normalised first); None if it is not finite or
    zero."""
    q = np.asarray(q, np.float64)
    n = float(np.sqrt(np.sum(q * q)))
    if not np.isfinite(n) or n == 0.0:
        return None
    w, x, y, z = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rotation_from_quaternion(q) -> np.ndarray:
    """(3, 3) float64 rotation of a quaternion ``q`` (4,) ``(w, x, y, z)``, normalised first.

    Raises:
      ValueError: ``q`` is zero or not finite.
    """
    R = _rotation_or_none(q)
    if R is None:
        raise ValueError(f"no rotation for the quaternion {np.asarray(q).tolist()}")
    return R


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(w, x, y, z)``, ``w >= 0``, of a (3, 3) rotation; the branch on the
    largest diagonal term keeps it accurate near 180 degree rotations."""
    m = np.asarray(R, np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _pose(qt) -> np.ndarray | None:
    """(3, 4) ``[R | t]`` of 7 numbers ``qw qx qy qz tx ty tz``; None if any is not finite (or the
    quaternion is zero)."""
    R = _rotation_or_none(qt[:4])
    t = np.asarray(qt[4:7], np.float64)
    if R is None or not np.all(np.isfinite(t)):
        return None
    return np.concatenate([R, t[:, None]], axis=1)


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The pose ``a o b`` of two (3, 4) poses (``b`` first)."""
    return np.concatenate([a[:, :3] @ b[:, :3], (a[:, :3] @ b[:, 3] + a[:, 3])[:, None]], axis=1)


def _bad_model(path: Path, what: str) -> NoReturn:
    raise DatasetError(f"COLMAP file {path}: {what}; the model is inconsistent: re-export it with COLMAP "
                       "(colmap model_converter) or re-copy it.")


def _non_finite(path: Path, what: str, fix: str) -> NoReturn:
    raise DatasetError(f"COLMAP file {path}: {what}; {fix}.")


def _check_camera(path: Path, cam: ColmapCamera, cameras: dict) -> None:
    if cam.camera_id in cameras:
        _bad_model(path, f"camera {cam.camera_id} is defined twice")
    if not np.all(np.isfinite(cam.params)):
        _non_finite(path, f"camera {cam.camera_id} ({cam.model.name}) has non-finite parameters "
                    f"{cam.params.tolist()}", "fix the calibration or re-export the model")


# ----------------------------------------------------------------------------------------------------
# Rigs and frames (COLMAP >= 3.12): image poses
# ----------------------------------------------------------------------------------------------------


@dataclass
class _RigsFrames:
    """What rigs and frames say about image poses: ``sensor_from_rig[rig_id][(type, id)]`` (the
    reference sensor: :data:`_REFERENCE`; None: a sensor whose pose in the rig is unknown) and per
    frame its rig, ``rig_from_world`` (None: not finite) and ``(camera_id, image_id)`` of its CAMERA
    data."""

    rigs_file: Path
    frames_file: Path
    sensor_from_rig: dict[int, dict[tuple[int, int], np.ndarray | None]]
    frames: dict[int, tuple[int, np.ndarray | None, list[tuple[int, int]]]]

    def poses(self, images: dict[int, tuple[str, int]]) -> dict[int, np.ndarray]:
        """``cam_from_world`` of each image ``{image_id: (name, camera_id)}``.

        Raises:
          DatasetError: an image in no frame or in two, a frame of an unknown rig, a frame holding a
          camera that its rig lacks or whose pose in the rig is unknown (COLMAP writes neither), a
          non-finite pose of a frame.
        """
        out: dict[int, np.ndarray] = {}
        for frame_id, (rig_id, rig_from_world, cams) in self.frames.items():
            rig = self.sensor_from_rig.get(rig_id)
            if rig is None:
                _bad_model(self.frames_file, f"frame {frame_id} belongs to rig {rig_id}, which {self.rigs_file.name} "
                           "does not define")
            for camera_id, image_id in cams:
                if image_id not in images:
                    _bad_model(self.frames_file, f"frame {frame_id} holds image {image_id}, which images"
                               f"{self.frames_file.suffix} does not define")
                if image_id in out:
                    _bad_model(self.frames_file, f"image {image_id} is in two frames")
                if camera_id != images[image_id][1]:
                    _bad_model(self.frames_file, f"frame {frame_id} holds image {image_id} as camera {camera_id}, "
                               f"but the image uses camera {images[image_id][1]}")
                if (_CAMERA, camera_id) not in rig:
                    _bad_model(self.frames_file, f"frame {frame_id} holds camera {camera_id}, which its rig "
                               f"{rig_id} does not have")
                sensor = rig[(_CAMERA, camera_id)]
                if sensor is None:
                    _bad_model(self.frames_file, f"frame {frame_id} holds camera {camera_id}, whose pose in rig "
                               f"{rig_id} is unknown ({self.rigs_file.name})")
                if rig_from_world is None:
                    _non_finite(self.frames_file, f"image {image_id} ({images[image_id][0]}) has a non-finite pose "
                                f"(its frame {frame_id})", "re-run COLMAP mapping or re-export the model")
                out[image_id] = rig_from_world if sensor is _REFERENCE else _compose(sensor, rig_from_world)
        for image_id, (name, _) in images.items():
            if image_id not in out:
                _bad_model(self.frames_file, f"image {image_id} ({name}) is in no frame")
        return out


def _check_sensor_pose(path: Path, rig_id: int, pose: np.ndarray | None) -> np.ndarray:
    if pose is None:
        _non_finite(path, f"rig {rig_id} has a sensor with a non-finite pose", "re-calibrate the rig or "
                    "re-export the model")
    return pose


def _has_rigs_frames(folder: Path, ext: str) -> bool:
    """Whether the model in ``folder`` has ``rigs`` and ``frames`` files (newer COLMAP); one without
    the other is an error naming the missing file."""
    present = [(folder / f"{name}{ext}").is_file() for name in ("rigs", "frames")]
    if present == [True, False] or present == [False, True]:
        have, missing = ("rigs", "frames") if present[0] else ("frames", "rigs")
        raise DatasetError(f"The COLMAP model in {folder} has {have}{ext} but no {missing}{ext}: re-export the "
                           "model (colmap model_converter) or re-copy it.")
    return all(present)


def _images(path: Path, entries: dict, rigs_frames: _RigsFrames | None) -> dict[int, ColmapImage]:
    """The images of ``entries`` ``{id: (name, camera_id, 7 pose numbers, keypoints)}``, posed by
    their frames where the model has frames, else by their own pose."""
    if rigs_frames is not None:
        poses = rigs_frames.poses({i: (e[0], e[1]) for i, e in entries.items()})
    else:
        poses = {}
        for image_id, (name, _, qt, _) in entries.items():
            pose = _pose(qt)
            if pose is None:
                _non_finite(path, f"image {image_id} ({name}) has a non-finite pose",
                            "re-run COLMAP mapping or re-export the model")
            poses[image_id] = pose
    return {i: ColmapImage(i, name, cid, poses[i], np.array(kp["xy"], np.float64).reshape(-1, 2),
                           np.array(kp["point3D_id"], np.int64).reshape(-1))
            for i, (name, cid, _, kp) in entries.items()}


def _points(path: Path, ids, xyz, rgb, error, lengths, tracks) -> ColmapPoints:
    ids = np.asarray(ids, np.int64).reshape(-1)
    unique, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        _bad_model(path, f"3D point {unique[counts > 1][0]} is defined twice")
    order = np.argsort(ids, kind="stable")
    lengths = np.asarray(lengths, np.int64).reshape(-1)
    # Track rows of the points in id order: each point's rows, moved from where the file had them.
    old_starts = np.cumsum(lengths) - lengths
    new_starts = np.cumsum(lengths[order]) - lengths[order]
    rows = np.repeat(old_starts[order] - new_starts, lengths[order]) + np.arange(int(lengths.sum()))
    return ColmapPoints(ids=ids[order], xyz=np.asarray(xyz, np.float64).reshape(-1, 3)[order],
                        rgb=np.asarray(rgb, np.uint8).reshape(-1, 3)[order],
                        error=np.asarray(error, np.float64).reshape(-1)[order], track_length=lengths[order],
                        tracks=np.asarray(tracks, np.int64).reshape(-1, 2)[rows])
