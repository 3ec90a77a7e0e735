"""COLMAP model files: finding a scene's model folder, checking its files, reading it with pycolmap.

Binary files are first walked by :func:`validate_binary_model` because pycolmap 4.2.1 hangs or
silently accepts truncated binary files (e.g. an ``images.bin`` cut to 4 bytes never returns; one
cut by a byte loads "fine"); text files are checked line by line (:func:`validate_text_model`).
Non-finite camera parameters, poses and points are errors naming the file and the entry.
"""

from __future__ import annotations

import functools
import re
import struct
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import numpy as np

from .errors import DatasetError, pycolmap_module

if TYPE_CHECKING:
    import pycolmap

__all__ = ["find_sparse_dir", "model_points", "read_model", "validate_binary_model", "validate_text_model"]

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
# Binary validation (pycolmap can hang or accept garbage on truncated files)
# ----------------------------------------------------------------------------------------------------


@functools.cache
def _model_table() -> dict[int, tuple[str, int]]:
    """COLMAP camera model id -> (name, number of parameters), as pycolmap defines them."""
    pycolmap = pycolmap_module("Reading a COLMAP model")
    table = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if int(mid.value) < 0:
            continue
        cam = pycolmap.Camera.create_from_model_id(1, mid, 1.0, 1, 1)
        table[int(mid.value)] = (name, len(cam.params))
    return table



class _Reader:
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

    def skip(self, nbytes: int, what: str):
        if nbytes < 0 or self.off + nbytes > len(self.buf):
            self.fail(f"file ends inside {what}")
        self.off += nbytes

    def count(self, fmt: str, min_record: int, what: str) -> int:
        (n,) = self.unpack(fmt, f"the {what} count")
        if n * min_record > len(self.buf) - self.off:
            self.fail(f"it declares {n} {what} but only {len(self.buf) - self.off} bytes follow")
        return n

    def finish(self):
        if self.off != len(self.buf):
            self.fail(f"{len(self.buf) - self.off} unexpected trailing bytes")


def validate_binary_model(folder: Path) -> dict[str, int]:
    """Walks COLMAP ``.bin`` files (cameras, images, points3D, and rigs/frames if present) and checks
    that every record is complete and the files end exactly after the last record.

    Args:
      folder: a folder with ``cameras.bin``, ``images.bin``, ``points3D.bin``.

    Returns:
      ``{"cameras": n, "images": n, "points3D": n}``.

    Raises:
      DatasetError naming the corrupt file (truncated, trailing bytes, unknown camera model id,
      implausible sizes).
    """
    folder = Path(folder)
    counts = {}

    r = _Reader(folder / "cameras.bin")
    n = r.count("<Q", 24, "cameras")
    for _ in range(n):
        cam_id, model_id, width, height = r.unpack("<IiQQ", "a camera record")
        if model_id not in _model_table():
            r.fail(f"camera {cam_id} has unknown camera model id {model_id}")
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            r.fail(f"camera {cam_id} has implausible size {width}x{height}")
        r.skip(8 * _model_table()[model_id][1], f"the parameters of camera {cam_id}")
    r.finish()
    counts["cameras"] = n

    r = _Reader(folder / "images.bin")
    n = r.count("<Q", 64 + 1 + 8, "images")
    for _ in range(n):
        image_id = r.unpack("<I7dI", "an image record")[0]
        end = r.buf.find(b"\0", r.off)
        if end < 0:
            r.fail(f"the name of image {image_id} is not terminated")
        try:
            r.buf[r.off:end].decode("utf-8")
        except UnicodeDecodeError:
            r.fail(f"the name of image {image_id} is not valid UTF-8")
        r.off = end + 1
        npts = r.count("<Q", 24, f"2D points of image {image_id}")
        r.skip(24 * npts, f"the 2D points of image {image_id}")
    r.finish()
    counts["images"] = n

    r = _Reader(folder / "points3D.bin")
    n = r.count("<Q", 51, "3D points")
    for _ in range(n):
        rec = r.unpack("<Q3d3BdQ", "a 3D point record")  # id, xyz, rgb, error, track length
        pid, track_len = rec[0], rec[-1]
        r.skip(8 * track_len, f"the track of 3D point {pid}")
    r.finish()
    counts["points3D"] = n

    if (folder / "rigs.bin").is_file():
        r = _Reader(folder / "rigs.bin")
        n = r.count("<Q", 8, "rigs")
        for _ in range(n):
            rig_id, nsensors = r.unpack("<II", "a rig record")
            if nsensors > 0:
                r.unpack("<iI", f"the reference sensor of rig {rig_id}")
            for _ in range(max(0, nsensors - 1)):
                _, _, has_pose = r.unpack("<iIB", f"a sensor of rig {rig_id}")
                if has_pose:
                    r.skip(56, f"a sensor pose of rig {rig_id}")
        r.finish()
    if (folder / "frames.bin").is_file():
        r = _Reader(folder / "frames.bin")
        n = r.count("<Q", 68, "frames")
        for _ in range(n):
            frame_id = r.unpack("<II7d", "a frame record")[0]
            ndata = r.count("<I", 16, f"data ids of frame {frame_id}")
            r.skip(16 * ndata, f"the data ids of frame {frame_id}")
        r.finish()
    return counts


def validate_text_model(folder: Path) -> None:
    """Checks the line structure of COLMAP ``cameras.txt``, ``images.txt`` and ``points3D.txt``
    (token counts and numbers), so that a damaged file is reported with its name and line number.

    Raises:
      DatasetError naming the file and line.
    """
    folder = Path(folder)
    names = {name: mid for mid, (name, _) in _model_table().items()}

    def fail(fname, lineno, what) -> NoReturn:
        raise DatasetError(f"COLMAP file {folder / fname} is corrupt or truncated at line {lineno} ({what}). "
                           "Re-export the model (colmap model_converter) or re-copy the file.")

    def numbers(fname, lineno, tokens):
        try:
            [float(t) for t in tokens]
        except ValueError:
            fail(fname, lineno, "a field is not a number")

    def lines(fname):
        try:
            with open(folder / fname, encoding="utf-8") as fh:
                yield from enumerate(fh, start=1)
        except (OSError, UnicodeDecodeError) as e:
            raise DatasetError(f"Cannot read COLMAP file {folder / fname}: {e}.") from None

    for lineno, line in lines("cameras.txt"):
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        if len(t) < 4 or t[1] not in names:
            fail("cameras.txt", lineno, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        nparams = _model_table()[names[t[1]]][1]
        if len(t) != 4 + nparams:
            fail("cameras.txt", lineno, f"model {t[1]} needs {nparams} parameters, found {len(t) - 4}")
        numbers("cameras.txt", lineno, [t[0]] + t[2:])

    it = lines("images.txt")
    for lineno, line in it:
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        if len(t) < 10:
            fail("images.txt", lineno, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        numbers("images.txt", lineno, t[:9])
        nxt = next(it, None)
        if nxt is None:
            fail("images.txt", lineno + 1, "the POINTS2D line of the last image is missing")
        pts = nxt[1].split()
        if len(pts) % 3:
            fail("images.txt", nxt[0], "POINTS2D must be (X, Y, POINT3D_ID) triplets")

    for lineno, line in lines("points3D.txt"):
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        if len(t) < 8 or (len(t) - 8) % 2:
            fail("points3D.txt", lineno, "expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)")
        numbers("points3D.txt", lineno, t[:8])


def _text_declared_counts(folder: Path) -> dict[str, int]:
    """Counts declared in COLMAP text headers ('# Number of images: 71, ...')."""
    out = {}
    for name in _MODEL_FILES:
        try:
            with open(folder / f"{name}.txt", encoding="utf-8", errors="replace") as fh:
                for line in fh:
                    if not line.startswith("#"):
                        break
                    m = re.match(r"#\s*Number of (?:cameras|images|points)\s*:\s*(\d+)", line)
                    if m:
                        out[name] = int(m.group(1))
        except OSError as e:
            raise DatasetError(f"Cannot read COLMAP file {folder / (name + '.txt')}: {e}.") from None
    return out


def read_model(folder: Path) -> pycolmap.Reconstruction:
    """Reads a COLMAP model folder (``.bin`` validated first, or ``.txt``) with pycolmap.

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
    if ext == ".bin":
        validate_binary_model(folder)
    else:
        validate_text_model(folder)
    pycolmap = pycolmap_module("Reading a COLMAP model")
    try:
        rec = pycolmap.Reconstruction()
        if ext == ".bin":
            rec.read_binary(str(folder))
        else:
            rec.read_text(str(folder))
    except Exception as e:  # pycolmap raises ValueError / IndexError / RuntimeError on bad models
        raise DatasetError(f"pycolmap cannot read the COLMAP model in {folder} ({type(e).__name__}: {e}). "
                           "The model files are inconsistent or corrupt: re-export them with COLMAP.") from None
    if ext == ".txt":
        declared = _text_declared_counts(folder)
        got = {"cameras": len(rec.cameras), "images": len(rec.images), "points3D": len(rec.points3D)}
        for name, n in declared.items():
            if got[name] != n:
                raise DatasetError(f"COLMAP file {folder / (name + '.txt')} declares {n} entries in its header "
                                   f"but holds {got[name]}: it is truncated; re-export the model.")
    _check_finite(rec, folder, ext)
    return rec


def _check_finite(rec, folder: Path, ext: str) -> None:
    """A NaN or infinite camera parameter or pose is a :class:`DatasetError` naming the file and the
    entry (3D points: :func:`model_points`). pycolmap reads them from binary models without complaint; a
    NaN distortion coefficient was undistorted into a camera of the wrong size."""
    for cid, cam in sorted(rec.cameras.items()):
        p = np.asarray(cam.params, np.float64)
        if not np.all(np.isfinite(p)):
            raise DatasetError(f"COLMAP file {folder / ('cameras' + ext)}: camera {cid} ({cam.model.name}) has "
                               f"non-finite parameters {p.tolist()}; fix the calibration or re-export the model.")
    poses = "frames" if (folder / f"frames{ext}").is_file() else "images"  # rig-aware models keep poses in frames
    for iid, im in sorted(rec.images.items()):
        if im.has_pose and not np.all(np.isfinite(im.cam_from_world().matrix())):
            raise DatasetError(f"COLMAP file {folder / (poses + ext)}: image {iid} ({im.name}) has a "
                               "non-finite pose; re-run COLMAP mapping or re-export the model.")


def model_points(rec, folder: Path):
    """(ids (M,) int64 sorted, xyz (M, 3) float64, colours (M, 3) float32 in [0, 1]) of a model's 3D
    points; a non-finite point is a :class:`DatasetError` naming the file and the ids (it would have
    become a NaN Gaussian)."""
    ids = np.array(sorted(rec.points3D.keys()), np.int64)
    xyz = np.array([rec.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    cols = np.array([rec.points3D[i].color for i in ids], np.float32).reshape(-1, 3) / 255.0
    bad = ids[~np.all(np.isfinite(xyz), axis=1)]
    if bad.size:
        points_file = folder / ("points3D" + (_model_ext(folder) or ""))
        raise DatasetError(f"COLMAP file {points_file}: {bad.size} of {ids.size} "
                           f"points have non-finite coordinates (ids {bad[:5].tolist()}"
                           f"{' ...' if bad.size > 5 else ''}); re-run COLMAP triangulation or delete those points.")
    return ids, xyz, cols
