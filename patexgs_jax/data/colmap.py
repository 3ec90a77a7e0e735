"""COLMAP scenes: ``sparse/0`` (or ``sparse/``) + ``images/`` (+ Mip-NeRF 360 ``images_2/4/8``).

Models are read with pycolmap (``.bin`` or ``.txt``). Binary files are first walked by
:func:`validate_binary_model` because pycolmap 4.2.1 hangs or silently accepts truncated binary files
(e.g. an ``images.bin`` cut to 4 bytes never returns; one cut by a byte loads "fine").

Distorted camera models are undistorted once with ``pycolmap.undistort_images`` into the cache folder
(see :func:`~patexgs_jax.data.dataset.resolve_cache_dir`), written atomically and reused afterwards.
"""

from __future__ import annotations

import re
import shutil
import struct
import sys
import time
import zlib  # noqa: F401  -- must be loaded before pycolmap (heap corruption otherwise, see data/__init__)
from pathlib import Path
from typing import NoReturn

import numpy as np
import PIL.Image  # noqa: F401  -- must be loaded before pycolmap (see data/__init__)

from .._pycolmap import pycolmap
from .dataset import (
    DEFAULT_IMAGE_CACHE_BYTES,
    DEFAULT_IMAGE_CACHE_SIZE,
    DEFAULT_NUM_RANDOM_POINTS,
    IMAGE_EXTENSIONS,
    Dataset,
    DatasetError,
    ImageCache,
    atomic_build_dir,
    check_size_against_camera,
    fingerprint,
    finish_dataset,
    fit_records_to_width,
    handle_unreadable,
    image_loader,
    image_size,
    is_complete_dir,
    list_images,
    probe_image,
    random_points_in_box,
    resolve_cache_dir,
    warn,
)

__all__ = [
    "load_colmap",
    "find_sparse_dir",
    "read_model",
    "validate_binary_model",
    "validate_text_model",
    "default_factor",
    "default_resolution",
    "DEFAULT_MAX_WIDTH",
    "MIPNERF360_FACTORS",
    "PINHOLE_MODELS",
]

#: Default downsampling factors of the Mip-NeRF 360 scenes (3DGS / Mip-NeRF 360 evaluation protocol).
MIPNERF360_FACTORS = {
    **{s: 4 for s in ("bicycle", "flowers", "garden", "stump", "treehill")},
    **{s: 2 for s in ("room", "counter", "kitchen", "bonsai")},
}
#: Camera models used as they are (no distortion).
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_MODEL_FILES = ("cameras", "images", "points3D")


#: Without a factor, images wider than this many pixels are resized to this width (the 3DGS rule).
DEFAULT_MAX_WIDTH = 1600


def default_resolution(scene: Path, factor: int | None) -> tuple[int, int | None]:
    """``(factor, max_width)`` of a scene loaded with ``factor``: an explicit factor as it is (no
    width limit); None -> the Mip-NeRF 360 factor for those scene names (:func:`default_factor`),
    else factor 1 with images wider than :data:`DEFAULT_MAX_WIDTH` resized to that width."""
    if factor is not None:
        return int(factor), None
    named = default_factor(scene)
    return (named, None) if named != 1 else (1, DEFAULT_MAX_WIDTH)


def default_factor(scene: Path) -> int:
    """Default image downsampling factor for a scene folder: 4 for the Mip-NeRF 360 outdoor scenes
    (bicycle, flowers, garden, stump, treehill), 2 for the indoor ones (room, counter, kitchen, bonsai),
    1 otherwise (decided by the folder name)."""
    return MIPNERF360_FACTORS.get(Path(scene).resolve().name, 1)


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


def _num_params_by_model_id() -> dict[int, tuple[str, int]]:
    table = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if int(mid.value) < 0:
            continue
        cam = pycolmap.Camera.create_from_model_id(1, mid, 1.0, 1, 1)
        table[int(mid.value)] = (name, len(cam.params))
    return table


_MODEL_TABLE = _num_params_by_model_id()


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
        if model_id not in _MODEL_TABLE:
            r.fail(f"camera {cam_id} has unknown camera model id {model_id}")
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            r.fail(f"camera {cam_id} has implausible size {width}x{height}")
        r.skip(8 * _MODEL_TABLE[model_id][1], f"the parameters of camera {cam_id}")
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
    names = {name: mid for mid, (name, _) in _MODEL_TABLE.items()}

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
        nparams = _MODEL_TABLE[names[t[1]]][1]
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


# ----------------------------------------------------------------------------------------------------
# Loader
# ----------------------------------------------------------------------------------------------------


def _intrinsics(cam) -> np.ndarray:
    p = np.asarray(cam.params, np.float64)
    name = cam.model.name
    if name == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif name == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    else:  # pragma: no cover - guarded by the callers
        raise DatasetError(f"internal: camera model {name} is not a pinhole model.")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _resolve_image_files(names: list[str], folder: Path, base_folder: Path) -> dict[str, Path | None]:
    """Maps image names to files in ``folder``: exact name, else same stem with another image
    extension, else (when ``folder`` has exactly as many images as ``base_folder``) by sorted order."""
    out: dict[str, Path | None] = {}
    missing = []
    for n in names:
        p = folder / n
        if p.is_file():
            out[n] = p
            continue
        alt = [q for q in (p.with_suffix(e) for e in IMAGE_EXTENSIONS + tuple(x.upper() for x in IMAGE_EXTENSIONS))
               if q.is_file()]
        out[n] = alt[0] if alt else None
        if not alt:
            missing.append(n)
    if missing and folder != base_folder and base_folder.is_dir():
        base = [p.name for p in list_images(base_folder)]
        files = list_images(folder)
        if len(base) == len(files) and len(files) > 0:
            by_order = dict(zip(base, files))
            for n in missing:
                out[n] = by_order.get(n)
    return out


def load_colmap(path, factor: int | None = None, test_every: int | None = 8, skip_missing: bool = False, *,
                normalize: bool = False, cache_dir=None, image_cache_size: int = DEFAULT_IMAGE_CACHE_SIZE,
              image_cache_bytes: int | None = DEFAULT_IMAGE_CACHE_BYTES,
                background=(1.0, 1.0, 1.0), num_random_points: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0,
                images: str = "images", verbose: bool = True) -> Dataset:
    """Loads a COLMAP scene folder.

    Layout: ``<scene>/sparse/0/`` (or ``<scene>/sparse/``) with cameras/images/points3D ``.bin`` or
    ``.txt``; images in ``<scene>/images/`` named as in the model; optional ``images_N/`` (Mip-NeRF 360
    downsampled copies, same names, or the same count of files matched by sorted order).

    Args:
      path: scene folder.
      factor: image downsampling factor; None -> :func:`default_resolution` (the Mip-NeRF 360 factors
        for those scene names, else full size with images wider than 1600 px resized to 1600 wide
        with an area filter and K scaled per axis, as 3DGS).
        If ``images_<factor>`` exists it is used and K is scaled per axis by the actual size ratio
        (``w_N / W``, ``h_N / H``); otherwise ``images/`` is box-downsampled to ``W // f x H // f`` and K
        divided by ``f`` (pixel-centre consistent, like :meth:`Camera.scaled`).
      test_every: every ``test_every``-th name-sorted image is a test view (0 / None: no test views).
      skip_missing: drop views whose image is missing or unreadable (printing how many) instead of
        raising.
      normalize: apply the 3DGS similarity (centre -> 0, radius -> 1) to cameras and points; the
        mapping back is recorded in ``dataset.normalization``.
      cache_dir: root folder for derived data (undistorted images); see ``resolve_cache_dir``.
      image_cache_size, image_cache_bytes: at most this many decoded images, and bytes of them, are
        kept in memory (LRU; defaults 64 and 2 GiB; None: no byte bound).
      background: (3,) RGB in [0, 1] for compositing images with alpha.
      num_random_points, seed: used only if the model has no 3D points (a :class:`DatasetWarning` is
        emitted and random points fill the cube of half-side 0.5 x the largest camera distance around
        the mean camera centre).
      images: name of the full-resolution image folder.
      verbose: print a message when undistorting / skipping.

    Returns:
      a :class:`Dataset` (``format="colmap"``); cameras are PINHOLE (distorted models are undistorted
      with pycolmap and cached).

    Raises:
      DatasetError: no model, unreadable / corrupt model, no registered images, missing image folder,
        missing / unreadable images (unless ``skip_missing``), image size that disagrees with its camera,
        camera model that cannot be undistorted.
    """
    scene = Path(path)
    sparse = find_sparse_dir(scene)
    if sparse is None:
        raise DatasetError(f"No COLMAP model in {scene}: expected sparse/0/ or sparse/ with cameras, images "
                           "and points3D (.bin or .txt).")
    rec = read_model(sparse)
    point_ids, pts, cols = model_points(rec, sparse)  # before undistorting, which keeps the points as they are
    reg = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not reg:
        raise DatasetError(f"The COLMAP model in {sparse} has no registered images ({len(rec.images)} images, "
                           "none with a pose): the reconstruction failed; re-run COLMAP mapping.")
    factor, max_width = default_resolution(scene, factor)
    if factor < 1:
        raise DatasetError(f"factor must be a positive integer, got {factor}.")

    base_folder = scene / images
    folder, folder_factor = base_folder, 1
    if factor > 1 and (scene / f"{images}_{factor}").is_dir():
        folder, folder_factor = scene / f"{images}_{factor}", factor
    post = factor // folder_factor
    if not folder.is_dir():
        raise DatasetError(f"Image folder {folder} not found: a COLMAP scene needs its images in "
                           f"{scene}/{images}/ with the names used in {sparse}.")

    # Resolve files, check headers and sizes.
    files = _resolve_image_files([im.name for im in reg], folder, base_folder)
    kept, problems, ratios = [], [], {}
    for im in reg:
        f = files[im.name]
        size, why = probe_image(f)
        if size is None or f is None:
            problems.append((f if f is not None else folder / im.name, why))
            continue
        cam = rec.cameras[im.camera_id]
        ratios[im.name] = check_size_against_camera(
            f, size, (cam.width, cam.height), folder_factor,
            f"its camera {im.camera_id} ({cam.model.name} {cam.width}x{cam.height}) in {sparse}")
        kept.append(im)
    skipped = handle_unreadable(problems, len(reg), f"the COLMAP model {sparse} (images in {folder})", skip_missing)
    if not kept:
        raise DatasetError(f"None of the {len(reg)} registered images of {sparse} could be read from {folder}.")

    info = {"sparse": str(sparse), "image_folder": str(folder), "skipped": skipped}
    models = sorted({rec.cameras[im.camera_id].model.name for im in kept})
    distorted = [m for m in models if m not in PINHOLE_MODELS]
    undistorted_dir = None
    if distorted:
        for m in distorted:
            cam = next(rec.cameras[im.camera_id] for im in kept if rec.cameras[im.camera_id].model.name == m)
            if not cam.is_perspective():
                raise DatasetError(f"Camera model {m} (in {sparse}) is not a perspective model and cannot be "
                                   "undistorted to a pinhole camera; convert the capture to perspective images "
                                   "(e.g. cube maps) and re-run COLMAP.")
        undistorted_dir = _undistort(scene, sparse, rec, kept, files, ratios, folder, cache_dir, distorted, verbose)
        info["undistorted_from"] = models
        info["undistorted_dir"] = str(undistorted_dir)
        rec = read_model(undistorted_dir / "sparse")
        by_name = {im.name: im for im in rec.images.values()}
        und_images = undistorted_dir / "images"
        new_kept = []
        for im in kept:
            uim = by_name.get(im.name)
            f = und_images / im.name
            if uim is None or not f.is_file():
                if not skip_missing:
                    raise DatasetError(f"pycolmap could not undistort {files[im.name]} (no output in {und_images}); "
                                       "the image is probably corrupt: replace it or use skip_missing=True.")
                skipped.append(im.name)
                continue
            files[im.name] = f
            cam = rec.cameras[uim.camera_id]
            ratios[im.name] = check_size_against_camera(
                f, image_size(f), (cam.width, cam.height), 1, f"its undistorted camera in {undistorted_dir}")
            new_kept.append(uim)
        kept = new_kept

    records = []
    for im in kept:
        cam = rec.cameras[im.camera_id]
        rx, ry = ratios[im.name]
        K = _intrinsics(cam)
        K = np.diag([rx, ry, 1.0]) @ K  # images_N: per-axis ratio of actual size (exact 1 otherwise)
        w_file = int(round(cam.width * rx))
        h_file = int(round(cam.height * ry))
        if post > 1:
            K = np.diag([1.0 / post, 1.0 / post, 1.0]) @ K
        w, h = w_file // post, h_file // post
        if w < 1 or h < 1:
            raise DatasetError(f"factor {factor} leaves no pixel of the {w_file}x{h_file} image {files[im.name]}.")
        w2c = np.eye(4)
        w2c[:3, :] = im.cam_from_world().matrix()
        records.append(dict(name=im.name, K=K, w2c=w2c, width=w, height=h, image_path=files[im.name],
                            load=image_loader(files[im.name], post, background)))
    records, ratio = fit_records_to_width(records, max_width, background, verbose)
    applied: float = ratio if ratio > 1 else factor

    if point_ids.size:
        source = "sfm"
    else:
        warn(f"The COLMAP model in {sparse} has no 3D points; using {num_random_points} random points "
             "(seeded) around the cameras instead. Re-run COLMAP triangulation for a better initialisation.")
        pts = cols = None
        source = "random"

    def rand(norm):
        half = 0.5 * norm.original_radius / 1.1
        return random_points_in_box(norm.original_center, half, num_random_points, seed)

    return finish_dataset(records, fmt="colmap", path=scene, factor=applied, test_every=test_every,
                          normalize=normalize, points=pts, colors=cols, points_source=source,
                          cache=ImageCache(image_cache_size, image_cache_bytes), info=info, random_points=rand)



def _undistort(scene, sparse, rec, kept, files, ratios, folder, cache_dir, distorted, verbose) -> Path:
    """Undistorts the kept images once into the cache (atomically); returns the folder holding
    ``images/`` and ``sparse/`` of the undistorted (PINHOLE) model."""
    names = [im.name for im in kept]
    rescale = {}
    for im in kept:
        cam = rec.cameras[im.camera_id]
        rx, ry = ratios[im.name]
        if abs(rx - 1) > 1e-12 or abs(ry - 1) > 1e-12:
            rescale[im.camera_id] = (int(round(cam.width * rx)), int(round(cam.height * ry)))
    # Files whose names differ from the model's (images_N matched by order) need renaming: link them.
    renamed = {n: files[n] for n in names
               if files[n].name != Path(n).name or files[n].parent != folder / Path(n).parent}
    sparse_files = sorted(p for p in sparse.iterdir() if p.is_file())
    key = fingerprint("undistort-v1", *sparse_files, folder.resolve(), names, sorted(rescale.items()),
                      *[files[n] for n in names])
    root = resolve_cache_dir(scene, cache_dir) / "undistorted"
    final = root / f"{folder.name}-{key}"
    if is_complete_dir(final):
        return final

    def build(tmp: Path):
        src_model = sparse
        src_images = folder
        if rescale or renamed:
            r2 = pycolmap.Reconstruction(rec)
            for cid, (w, h) in rescale.items():
                cam = r2.cameras[cid]
                cam.rescale(w, h)
                r2.cameras[cid] = cam
            src_model = tmp / "input_model"
            src_model.mkdir()
            r2.write_binary(str(src_model))
        if renamed:
            src_images = tmp / "input_images"
            for n in names:
                dst = src_images / n
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.symlink_to(files[n].resolve())
        out = tmp / "out"
        if verbose:
            print(f"[patexgs_jax] {scene}: {len(names)} images use distorted camera models "
                  f"({', '.join(distorted)}); undistorting them once with pycolmap into {final} "
                  "(reused on later loads) ...", file=sys.stderr, flush=True)
        t0 = time.time()
        old = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = max(old, 2)
        try:
            pycolmap.undistort_images(str(out), str(src_model), str(src_images), image_names=names,
                                      jpeg_quality=100)
        except Exception as e:
            raise DatasetError(
                f"pycolmap failed to undistort the images of {scene} ({type(e).__name__}: {e}).") from None
        finally:
            pycolmap.logging.minloglevel = old
        (out / "images").rename(tmp / "images")
        (out / "sparse").rename(tmp / "sparse")
        for extra in ("out", "input_model", "input_images"):
            _rmtree(tmp / extra)
        if verbose:
            print(f"[patexgs_jax] undistortion done in {time.time() - t0:.1f} s.", file=sys.stderr, flush=True)

    try:
        return atomic_build_dir(final, build)
    except OSError as e:
        raise DatasetError(f"Cannot write the undistortion cache {final} ({e}); pass cache_dir= or set "
                           "PATEXGS_CACHE to a writable folder.") from None


def _rmtree(p: Path):
    if p.is_symlink() or p.is_file():
        p.unlink()
    elif p.exists():
        shutil.rmtree(p)
