"""COLMAP model files: finding a scene's model folder, reading it (``.bin`` or ``.txt``) and writing one.

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

import re
import struct
from collections.abc import Iterator
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
    "find_sparse_dir",
    "model_points",
    "quaternion_from_rotation",
    "read_model",
    "rotation_from_quaternion",
    "validate_binary_model",
    "validate_text_model",
    "write_binary_model",
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


def _read_rigs_frames_binary(folder: Path) -> _RigsFrames | None:
    if not _has_rigs_frames(folder, ".bin"):
        return None
    rigs: dict[int, dict[tuple[int, int], np.ndarray | None]] = {}
    r = _Reader(folder / "rigs.bin")
    for _ in range(r.count("<Q", 8, "rigs")):
        rig_id, nsensors = r.unpack("<II", "a rig record")
        sensors: dict[tuple[int, int], np.ndarray | None] = {}
        if nsensors > 0:
            sensors[r.unpack("<iI", f"the reference sensor of rig {rig_id}")] = _REFERENCE
        for _ in range(max(0, nsensors - 1)):
            stype, sid, has_pose = r.unpack("<iIB", f"a sensor of rig {rig_id}")
            sensors[(stype, sid)] = None
            if has_pose:
                pose = _pose(r.unpack("<7d", f"a sensor pose of rig {rig_id}"))
                sensors[(stype, sid)] = _check_sensor_pose(r.path, rig_id, pose)
        if rig_id in rigs:
            r.fail(f"rig {rig_id} is defined twice")
        rigs[rig_id] = sensors
    r.finish()
    frames = {}
    r = _Reader(folder / "frames.bin")
    for _ in range(r.count("<Q", 68, "frames")):
        frame_id, rig_id, *qt = r.unpack("<II7d", "a frame record")
        ndata = r.count("<I", 16, f"data ids of frame {frame_id}")
        cams = []
        for _ in range(ndata):
            stype, sid, data_id = r.unpack("<iIQ", f"the data ids of frame {frame_id}")
            if stype == _CAMERA:
                cams.append((sid, data_id))
        if frame_id in frames:
            r.fail(f"frame {frame_id} is defined twice")
        frames[frame_id] = (rig_id, _pose(qt), cams)
    r.finish()
    return _RigsFrames(folder / "rigs.bin", folder / "frames.bin", rigs, frames)


# ----------------------------------------------------------------------------------------------------
# Binary files
# ----------------------------------------------------------------------------------------------------


class _Reader:
    """A binary file read front to back; every read checks that the bytes are there."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except OSError as e:
            raise DatasetError(f"Cannot read COLMAP file {path}: {e}.") from None
        self.off = 0

    def fail(self, what: str) -> NoReturn:
        raise DatasetError(
            f"COLMAP file {self.path} is corrupt or truncated ({what}, at byte {self.off} of "
            f"{len(self.buf)}). Re-export the model (colmap model_converter) or re-copy the file.")

    def unpack(self, fmt: str, what: str):
        size = struct.calcsize(fmt)
        if self.off + size > len(self.buf):
            self.fail(f"file ends inside {what}")
        out = struct.unpack_from(fmt, self.buf, self.off)
        self.off += size
        return out

    def take(self, nbytes: int, what: str) -> bytes:
        if nbytes < 0 or self.off + nbytes > len(self.buf):
            self.fail(f"file ends inside {what}")
        out = self.buf[self.off:self.off + nbytes]
        self.off += nbytes
        return out

    def count(self, fmt: str, min_record: int, what: str) -> int:
        (n,) = self.unpack(fmt, f"the {what} count")
        if n * min_record > len(self.buf) - self.off:
            self.fail(f"it declares {n} {what} but only {len(self.buf) - self.off} bytes follow")
        return n

    def finish(self):
        if self.off != len(self.buf):
            self.fail(f"{len(self.buf) - self.off} unexpected trailing bytes")


# Ids are kept as int64 (COLMAP's are unsigned; none comes near 2**63).
_ID_LIMIT = 1 << 63

# A keypoint in images.bin: x, y (float64), the id of its 3D point (uint64, all ones for none: -1 as int64).
_POINT2D = np.dtype([("xy", "<f8", (2,)), ("point3D_id", "<i8")])
# The fixed part of a 3D point in points3D.bin (then track_length (image id, keypoint index) uint32 pairs).
_POINT3D = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"),
                     ("track_length", "<u8")])


def _read_binary(folder: Path) -> ColmapModel:
    cameras: dict[int, ColmapCamera] = {}
    r = _Reader(folder / "cameras.bin")
    for _ in range(r.count("<Q", 24, "cameras")):
        cam_id, model_id, width, height = r.unpack("<IiQQ", "a camera record")
        model = CAMERA_MODELS.get(model_id)
        if model is None:
            r.fail(f"camera {cam_id} has unknown camera model id {model_id}")
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            r.fail(f"camera {cam_id} has implausible size {width}x{height}")
        params = np.array(r.unpack(f"<{model.num_params}d", f"the parameters of camera {cam_id}"), np.float64)
        cam = ColmapCamera(cam_id, model, width, height, params)
        _check_camera(r.path, cam, cameras)
        cameras[cam_id] = cam
    r.finish()

    rigs_frames = _read_rigs_frames_binary(folder)
    entries = {}
    r = _Reader(folder / "images.bin")
    for _ in range(r.count("<Q", 64 + 1 + 8, "images")):
        image_id, *qt, camera_id = r.unpack("<I7dI", "an image record")
        end = r.buf.find(b"\0", r.off)
        if end < 0:
            r.fail(f"the name of image {image_id} is not terminated")
        try:
            name = r.buf[r.off:end].decode("utf-8")
        except UnicodeDecodeError:
            r.fail(f"the name of image {image_id} is not valid UTF-8")
        r.off = end + 1
        npts = r.count("<Q", _POINT2D.itemsize, f"2D points of image {image_id}")
        kp = np.frombuffer(r.take(_POINT2D.itemsize * npts, f"the 2D points of image {image_id}"), _POINT2D)
        if image_id in entries:
            r.fail(f"image {image_id} is defined twice")
        if camera_id not in cameras:
            _bad_model(r.path, f"image {image_id} ({name}) uses camera {camera_id}, which cameras.bin does not define")
        entries[image_id] = (name, camera_id, qt, kp)
    r.finish()
    images = _images(folder / "images.bin", entries, rigs_frames)

    points = _read_points_binary(_Reader(folder / "points3D.bin"))
    return ColmapModel(folder, ".bin", cameras, images, points)


def _read_points_binary(r: _Reader) -> ColmapPoints:
    """``points3D.bin``: a light Python loop finds where each record starts (tracks make them vary in
    size), then numpy gathers the fields of all records at once (unpacking each record in Python
    would cost seconds for a few 100k points)."""
    n = r.count("<Q", _POINT3D.itemsize, "3D points")
    buf, off, size = r.buf, r.off, len(r.buf)
    track_length_at = struct.Struct("<Q").unpack_from
    starts, lengths = [], []
    for _ in range(n):
        if off + _POINT3D.itemsize > size:
            r.off = off
            r.fail("file ends inside a 3D point record")
        (track_len,) = track_length_at(buf, off + _POINT3D.itemsize - 8)
        starts.append(off)
        lengths.append(track_len)
        off += _POINT3D.itemsize + 8 * track_len
        if off > size:
            r.off = starts[-1] + _POINT3D.itemsize
            r.fail(f"file ends inside the track of 3D point {track_length_at(buf, starts[-1])[0]}")
    r.off = off
    r.finish()
    raw = np.frombuffer(buf, np.uint8)
    first = np.asarray(starts, np.int64)
    rec = _gather(raw, first, _POINT3D.itemsize).view(_POINT3D).reshape(n)
    too_large = np.nonzero(rec["id"] >= _ID_LIMIT)[0]
    if too_large.size:
        r.off = int(first[too_large[0]])
        r.fail(f"implausible 3D point id {rec['id'][too_large[0]]}")
    length = np.asarray(lengths, np.int64)
    # Byte offset of each track element: its point's first element, then 8 bytes apart.
    element = np.arange(int(length.sum())) - np.repeat(np.cumsum(length) - length, length)
    at = np.repeat(first + _POINT3D.itemsize, length) + 8 * element
    tracks = _gather(raw, at, 8).view("<u4").reshape(-1, 2).astype(np.int64)
    return _points(r.path, rec["id"], rec["xyz"], rec["rgb"], rec["error"], length, tracks)


def _gather(raw: np.ndarray, offsets: np.ndarray, nbytes: int, chunk: int = 1 << 16) -> np.ndarray:
    """(len(offsets), nbytes) uint8: the ``nbytes`` bytes of ``raw`` from each offset (a chunk of
    offsets at a time, so that the byte indices stay small)."""
    out = np.empty((offsets.size, nbytes), np.uint8)
    for k in range(0, offsets.size, chunk):
        out[k:k + chunk] = raw[offsets[k:k + chunk, None] + np.arange(nbytes)]
    return out


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


def validate_binary_model(folder: Path) -> dict[str, int]:
    """Reads COLMAP ``.bin`` files (cameras, images, points3D, and rigs/frames if present), checking
    that every record is complete, consistent and finite and that the files end exactly after the last
    record.

    Args:
      folder: a folder with ``cameras.bin``, ``images.bin``, ``points3D.bin``.

    Returns:
      ``{"cameras": n, "images": n, "points3D": n}``.

    Raises:
      DatasetError naming the corrupt file (truncated, trailing bytes, unknown camera model id,
      implausible sizes, missing cameras or frames, non-finite values).
    """
    model = _read_binary(Path(folder))
    return {"cameras": len(model.cameras), "images": len(model.images), "points3D": len(model.points)}


# ----------------------------------------------------------------------------------------------------
# Text files
# ----------------------------------------------------------------------------------------------------


class _TextFile:
    """A COLMAP text file's lines, and its data lines (:meth:`records`: comments and blank lines
    skipped)."""

    def __init__(self, path: Path):
        self.path = path
        try:
            with open(path, encoding="utf-8") as fh:
                self.lines = list(enumerate(fh, start=1))
        except (OSError, UnicodeDecodeError) as e:
            raise DatasetError(f"Cannot read COLMAP file {path}: {e}.") from None

    def fail(self, lineno: int, what: str) -> NoReturn:
        raise DatasetError(f"COLMAP file {self.path} is corrupt or truncated at line {lineno} ({what}). "
                           "Re-export the model (colmap model_converter) or re-copy the file.")

    def records(self) -> Iterator[tuple[int, list[str]]]:
        for lineno, line in self.lines:
            t = line.split()
            if t and not t[0].startswith("#"):
                yield lineno, t

    def ints(self, lineno: int, tokens) -> list[int]:
        try:
            out = [int(t) for t in tokens]
        except ValueError:
            self.fail(lineno, "an id or size is not an integer")
        if any(not -_ID_LIMIT <= v < _ID_LIMIT for v in out):
            self.fail(lineno, "an id or size is out of range")
        return out

    def floats(self, lineno: int, tokens) -> list[float]:
        try:
            return [float(t) for t in tokens]
        except ValueError:
            self.fail(lineno, "a field is not a number")

    def sensor(self, lineno: int, name: str) -> int:
        if name not in _SENSOR_TYPE_IDS:
            self.fail(lineno, f"unknown sensor type {name!r}")
        return _SENSOR_TYPE_IDS[name]

    def declared(self) -> int | None:
        """The count declared in the header ('# Number of images: 71, ...'), if any."""
        for _, line in self.lines:
            if not line.startswith("#"):
                break
            m = re.match(r"#\s*Number of (?:cameras|images|points|rigs|frames)\s*:\s*(\d+)", line)
            if m:
                return int(m.group(1))
        return None

    def check_declared(self, got: int) -> None:
        n = self.declared()
        if n is not None and n != got:
            raise DatasetError(f"COLMAP file {self.path} declares {n} entries in its header but holds {got}: "
                               "it is truncated; re-export the model.")


def _read_rigs_frames_text(folder: Path) -> _RigsFrames | None:
    if not _has_rigs_frames(folder, ".txt"):
        return None
    rigs: dict[int, dict[tuple[int, int], np.ndarray | None]] = {}
    f = _TextFile(folder / "rigs.txt")
    for lineno, t in f.records():
        if len(t) < 2:
            f.fail(lineno, "expected RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID SENSORS[]")
        rig_id, nsensors = f.ints(lineno, t[:2])
        sensors: dict[tuple[int, int], np.ndarray | None] = {}
        k = 2
        for s in range(nsensors):
            if len(t) < k + (2 if s == 0 else 3):
                f.fail(lineno, f"rig {rig_id} declares {nsensors} sensors but lists fewer")
            key = (f.sensor(lineno, t[k]), f.ints(lineno, t[k + 1:k + 2])[0])
            if s == 0:
                sensors[key] = _REFERENCE
                k += 2
                continue
            (has_pose,) = f.ints(lineno, t[k + 2:k + 3])
            k += 3
            sensors[key] = None
            if has_pose:
                if len(t) < k + 7:
                    f.fail(lineno, f"a sensor pose of rig {rig_id} is cut short")
                sensors[key] = _check_sensor_pose(f.path, rig_id, _pose(f.floats(lineno, t[k:k + 7])))
                k += 7
        if k != len(t):
            f.fail(lineno, f"{len(t) - k} unexpected fields after the sensors of rig {rig_id}")
        if rig_id in rigs:
            f.fail(lineno, f"rig {rig_id} is defined twice")
        rigs[rig_id] = sensors
    f.check_declared(len(rigs))
    frames = {}
    f = _TextFile(folder / "frames.txt")
    for lineno, t in f.records():
        if len(t) < 10:
            f.fail(lineno, "expected FRAME_ID RIG_ID QW QX QY QZ TX TY TZ NUM_DATA_IDS DATA_IDS[]")
        frame_id, rig_id = f.ints(lineno, t[:2])
        qt = f.floats(lineno, t[2:9])
        (ndata,) = f.ints(lineno, t[9:10])
        if len(t) != 10 + 3 * ndata:
            f.fail(lineno, f"frame {frame_id} declares {ndata} data ids as (SENSOR_TYPE, SENSOR_ID, DATA_ID) "
                   f"but has {len(t) - 10} fields for them")
        cams = []
        for k in range(10, len(t), 3):
            stype = f.sensor(lineno, t[k])
            sid, data_id = f.ints(lineno, t[k + 1:k + 3])
            if stype == _CAMERA:
                cams.append((sid, data_id))
        if frame_id in frames:
            f.fail(lineno, f"frame {frame_id} is defined twice")
        frames[frame_id] = (rig_id, _pose(qt), cams)
    f.check_declared(len(frames))
    return _RigsFrames(folder / "rigs.txt", folder / "frames.txt", rigs, frames)


def _read_text(folder: Path) -> ColmapModel:
    cameras: dict[int, ColmapCamera] = {}
    f = _TextFile(folder / "cameras.txt")
    for lineno, t in f.records():
        if len(t) < 4 or t[1] not in CAMERA_MODELS_BY_NAME:
            f.fail(lineno, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] with one of COLMAP's models")
        model = CAMERA_MODELS_BY_NAME[t[1]]
        if len(t) != 4 + model.num_params:
            f.fail(lineno, f"model {t[1]} needs {model.num_params} parameters, found {len(t) - 4}")
        cam_id, width, height = f.ints(lineno, [t[0], t[2], t[3]])
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            f.fail(lineno, f"camera {cam_id} has implausible size {width}x{height}")
        cam = ColmapCamera(cam_id, model, width, height, np.array(f.floats(lineno, t[4:]), np.float64))
        _check_camera(f.path, cam, cameras)
        cameras[cam_id] = cam
    f.check_declared(len(cameras))

    rigs_frames = _read_rigs_frames_text(folder)
    entries = {}
    f = _TextFile(folder / "images.txt")
    k = 0
    while k < len(f.lines):
        lineno, line = f.lines[k]
        k += 1
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        if len(t) < 10:
            f.fail(lineno, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        (image_id,) = f.ints(lineno, t[:1])
        qt = f.floats(lineno, t[1:8])
        (camera_id,) = f.ints(lineno, t[8:9])
        name = t[9]
        # The keypoint line is the next line of the file, blank when the image has none.
        if k >= len(f.lines):
            f.fail(lineno + 1, "the POINTS2D line of the last image is missing")
        kp_lineno, kp_line = f.lines[k]
        k += 1
        pts = kp_line.split()
        if len(pts) % 3:
            f.fail(kp_lineno, "POINTS2D must be (X, Y, POINT3D_ID) triplets")
        kp = np.zeros(len(pts) // 3, _POINT2D)
        kp["xy"] = np.array(f.floats(kp_lineno, pts), np.float64).reshape(-1, 3)[:, :2]
        kp["point3D_id"] = f.ints(kp_lineno, pts[2::3])
        if image_id in entries:
            f.fail(lineno, f"image {image_id} is defined twice")
        if camera_id not in cameras:
            _bad_model(f.path, f"image {image_id} ({name}) uses camera {camera_id}, which cameras.txt does not define")
        entries[image_id] = (name, camera_id, qt, kp)
    f.check_declared(len(entries))
    images = _images(f.path, entries, rigs_frames)

    f = _TextFile(folder / "points3D.txt")
    ids, xyz, rgb, error, lengths, tracks = [], [], [], [], [], []
    for lineno, t in f.records():
        if len(t) < 8 or (len(t) - 8) % 2:
            f.fail(lineno, "expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)")
        (pid,) = f.ints(lineno, t[:1])
        x, y, z = f.floats(lineno, t[1:4])
        col = f.ints(lineno, t[4:7])
        if not all(0 <= c <= 255 for c in col):
            f.fail(lineno, f"the colour of 3D point {pid} is not in 0..255")
        (err,) = f.floats(lineno, t[7:8])
        track = f.ints(lineno, t[8:])
        ids.append(pid)
        xyz.append((x, y, z))
        rgb.append(col)
        error.append(err)
        lengths.append(len(track) // 2)
        tracks.extend(track)
    f.check_declared(len(ids))
    points = _points(f.path, ids, xyz, rgb, error, lengths, tracks)
    return ColmapModel(folder, ".txt", cameras, images, points)


def validate_text_model(folder: Path) -> None:
    """Reads COLMAP ``cameras.txt``, ``images.txt`` and ``points3D.txt`` (and rigs/frames if present),
    checking each line's fields, the model's consistency and the counts the headers declare, so that
    a damaged file is reported with its name and line number.

    Raises:
      DatasetError naming the file and line.
    """
    _read_text(Path(folder))


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
    return _read_binary(folder) if ext == ".bin" else _read_text(folder)


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


# ----------------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------------


def write_binary_model(folder: Path, cameras, images, points: ColmapPoints) -> None:
    """Writes ``cameras.bin``, ``images.bin`` and ``points3D.bin`` into ``folder`` (the three-file
    layout, which every COLMAP version reads; COLMAP 3.12+ gives each camera a trivial rig and each
    image a frame of its own).

    Args:
      cameras: :class:`ColmapCamera` s.
      images: :class:`ColmapImage` s, with their keypoints and the 3D points they observe.
      points: :class:`ColmapPoints`, tracks included.
    """
    folder = Path(folder)
    out = [struct.pack("<Q", len(cameras))]
    for cam in cameras:
        params = np.asarray(cam.params, "<f8").reshape(-1)
        if params.size != cam.model.num_params:
            raise ValueError(f"camera {cam.camera_id}: {cam.model.name} has {cam.model.num_params} parameters, "
                             f"got {params.size}.")
        out += [struct.pack("<IiQQ", cam.camera_id, cam.model.model_id, cam.width, cam.height), params.tobytes()]
    (folder / "cameras.bin").write_bytes(b"".join(out))

    out = [struct.pack("<Q", len(images))]
    for im in images:
        pose = np.asarray(im.cam_from_world, np.float64)
        kp = np.zeros(len(im.points2D), _POINT2D)
        kp["xy"] = im.points2D
        kp["point3D_id"] = im.point3D_ids
        out += [struct.pack("<I7dI", im.image_id, *quaternion_from_rotation(pose[:, :3]), *pose[:, 3], im.camera_id),
                im.name.encode("utf-8") + b"\0", struct.pack("<Q", len(kp)), kp.tobytes()]
    (folder / "images.bin").write_bytes(b"".join(out))

    out = [struct.pack("<Q", len(points))]
    starts = np.concatenate([[0], np.cumsum(points.track_length)])
    tracks = np.asarray(points.tracks, "<u4").reshape(-1, 2)
    for k in range(len(points)):
        out += [struct.pack("<Q3d3BdQ", int(points.ids[k]), *points.xyz[k], *points.rgb[k], float(points.error[k]),
                            int(points.track_length[k])), tracks[starts[k]:starts[k + 1]].tobytes()]
    (folder / "points3D.bin").write_bytes(b"".join(out))
