"""COLMAP's binary model files (``cameras.bin``, ``images.bin``, ``points3D.bin``, and ``rigs.bin`` /
``frames.bin`` from COLMAP 3.12): read record by record and checked as they are read (see
:mod:`.colmap_records`), and written (the three-file layout every COLMAP version reads).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import NoReturn

import numpy as np

from .colmap_records import (
    _CAMERA,
    _ID_LIMIT,
    _POINT2D,
    _REFERENCE,
    CAMERA_MODELS,
    ColmapCamera,
    ColmapModel,
    ColmapPoints,
    _bad_model,
    _check_camera,
    _check_sensor_pose,
    _has_rigs_frames,
    _images,
    _points,
    _pose,
    _RigsFrames,
    quaternion_from_rotation,
)
from .errors import DatasetError

__all__ = ["read_binary_model", "validate_binary_model", "write_binary_model"]


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


# The fixed part of a 3D point in points3D.bin (then track_length (image id, keypoint index) uint32 pairs).
_POINT3D = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"),
                     ("track_length", "<u8")])


def read_binary_model(folder: Path) -> ColmapModel:
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
    model = read_binary_model(Path(folder))
    return {"cameras": len(model.cameras), "images": len(model.images), "points3D": len(model.points)}


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
