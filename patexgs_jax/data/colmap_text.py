"""COLMAP's text model files (``cameras.txt``, ``images.txt``, ``points3D.txt``, and ``rigs.txt`` /
``frames.txt`` from COLMAP 3.12): read line by line and checked as they are read (see
:mod:`.colmap_records`); a header's declared count catches a file truncated at a line boundary.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import NoReturn

import numpy as np

from . import colmap_records as cm
from .colmap_records import (
    _CAMERA,
    _ID_LIMIT,
    _POINT2D,
    _REFERENCE,
    _SENSOR_TYPE_IDS,
    CAMERA_MODELS_BY_NAME,
    ColmapCamera,
    ColmapModel,
)
from .errors import DatasetError

__all__ = ["read_text_model", "validate_text_model"]


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


def _read_rigs_frames_text(folder: Path) -> cm._RigsFrames | None:
    if not cm._has_rigs_frames(folder, ".txt"):
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
                sensors[key] = cm._check_sensor_pose(f.path, rig_id, cm._pose(f.floats(lineno, t[k:k + 7])))
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
        frames[frame_id] = (rig_id, cm._pose(qt), cams)
    f.check_declared(len(frames))
    return cm._RigsFrames(folder / "rigs.txt", folder / "frames.txt", rigs, frames)


def read_text_model(folder: Path) -> ColmapModel:
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
        cm._check_camera(f.path, cam, cameras)
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
            cm._bad_model(f.path, f"image {image_id} ({name}) uses camera {camera_id}, which cameras.txt does "
                          "not define")
        entries[image_id] = (name, camera_id, qt, kp)
    f.check_declared(len(entries))
    images = cm._images(f.path, entries, rigs_frames)

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
    points = cm._points(f.path, ids, xyz, rgb, error, lengths, tracks)
    return ColmapModel(folder, ".txt", cameras, images, points)


def validate_text_model(folder: Path) -> None:
    """Reads COLMAP ``cameras.txt``, ``images.txt`` and ``points3D.txt`` (and rigs/frames if present),
    checking each line's fields, the model's consistency and the counts the headers declare, so that
    a damaged file is reported with its name and line number.

    Raises:
      DatasetError naming the file and line.
    """
    read_text_model(Path(folder))
