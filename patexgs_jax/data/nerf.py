"""NeRF-style ``transforms.json`` scenes (NeRF Blender synthetic, instant-ngp, nerfstudio).

Supported keys (top level = shared by all frames; the same keys inside a frame override them):

* intrinsics: ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, or ``camera_angle_x`` (and optional
  ``camera_angle_y``) -- focal = 0.5 * size / tan(0.5 * angle); ``fl_y`` defaults to ``fl_x``, the
  principal point to the image centre, ``w``/``h`` to the image file's size;
* distortion: ``k1``, ``k2``, ``k3``, ``p1``, ``p2`` (OpenCV model), or with ``camera_model:
  "OPENCV_FISHEYE"`` / ``is_fisheye: true`` the fisheye ``k1..k4``; distorted images are undistorted
  once (numpy remap with the OpenCV equations, output camera chosen by ``pycolmap.undistort_camera``
  so that no blank pixels remain) into the cache folder;
* per frame: ``file_path`` (relative to the json file, with or without extension) and
  ``transform_matrix`` (camera-to-world, OpenGL axes: x right, y up, z backwards; converted to OpenCV
  by flipping the y and z camera axes);
* ``ply_file_path`` (nerfstudio): an initial point cloud in PLY format.

Splits: ``transforms_train.json`` / ``transforms_test.json`` define the split when present
(``transforms_val.json`` is ignored); otherwise ``transforms.json`` is split with ``test_every``.
Images with alpha are composited on ``background`` (white by default).
"""

from __future__ import annotations

import functools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import PIL.Image

from .cache import atomic_build_dir, fingerprint, is_complete_dir, resolve_cache_dir
from .colmap import default_resolution
from .dataset import Dataset
from .errors import DatasetError, pycolmap_module
from .images import DEFAULT_IMAGE_CACHE_BYTES, DEFAULT_IMAGE_CACHE_SIZE, ImageCache, image_loader, probe_image
from .records import (
    DEFAULT_NUM_RANDOM_POINTS,
    check_size_against_camera,
    finish_dataset,
    fit_records_to_width,
    handle_unreadable,
    orthonormalize_pose,
    random_points_in_box,
)

__all__ = ["load_nerf", "find_transforms", "distort_normalized", "undistort_image", "read_ply_points",
           "OPENGL_TO_OPENCV"]

#: Right-multiplying an OpenGL camera-to-world by this gives the OpenCV camera-to-world.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".webp", ".tif", ".tiff", ".bmp")


def find_transforms(path) -> dict[str, Path] | None:
    """The transforms files of a scene: ``{"train": ..., "test": ...}`` when split files exist,
    ``{"all": transforms.json}`` otherwise, None when there is none. ``path`` may be the json file."""
    p = Path(path)
    if p.is_file() and p.suffix == ".json":
        return {"all": p}
    if (p / "transforms_train.json").is_file():
        out = {"train": p / "transforms_train.json"}
        if (p / "transforms_test.json").is_file():
            out["test"] = p / "transforms_test.json"
        return out
    if (p / "transforms.json").is_file():
        return {"all": p / "transforms.json"}
    return None


def _read_json(path: Path) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path} is not valid JSON ({e}); fix or regenerate it.") from None
    except OSError as e:
        raise DatasetError(f"Cannot read {path}: {e}.") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise DatasetError(f"{path} has no 'frames' list; it is not a NeRF transforms file.")
    return data


def _resolve_file(base: Path, file_path: str) -> Path | None:
    p = base / file_path
    if p.is_file():
        return p
    for ext in _EXTS:
        q = p.parent / (p.name + ext)
        if q.is_file():
            return q
    return None


# ----------------------------------------------------------------------------------------------------
# Distortion (OpenCV equations) and undistortion
# ----------------------------------------------------------------------------------------------------


def _coefficients(params: dict) -> dict[str, float]:
    """k1..k4, p1, p2 of a distortion ``params`` dict as floats (missing or null: 0)."""
    return {k: float(params.get(k, 0.0) or 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}


def distort_normalized(x, y, params: dict, fisheye: bool = False):
    """Applies lens distortion to normalised camera coordinates (x = X/Z, y = Y/Z).

    OpenCV model: ``r2 = x^2 + y^2``, ``radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3``,
    ``xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)``, ``yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y``.
    Fisheye (OpenCV fisheye / COLMAP OPENCV_FISHEYE): ``theta = atan(r)``,
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, scaled by ``theta_d / r``.

    Args:
      x, y: arrays of the same shape (float64 recommended).
      params: dict with any of k1, k2, k3, k4, p1, p2 (missing = 0).
      fisheye: use the fisheye model.

    Returns:
      (xd, yd) arrays of the input shape.
    """
    c = _coefficients(params)
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if fisheye:
        r = np.hypot(x, y)
        th = np.arctan(r)
        t2 = th * th
        thd = th * (1 + t2 * (c["k1"] + t2 * (c["k2"] + t2 * (c["k3"] + t2 * c["k4"]))))
        s = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
        return x * s, y * s
    k1, k2, k3, p1, p2 = c["k1"], c["k2"], c["k3"], c["p1"], c["p2"]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Samples (H, W, C) ``img`` at continuous coordinates (pixel centres at +0.5), clamping at edges."""
    H, W = img.shape[:2]
    x = np.clip(u - 0.5, 0.0, W - 1.0)
    y = np.clip(v - 0.5, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2 if W > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2 if H > 1 else 0)
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def undistort_image(image: np.ndarray, K: np.ndarray, params: dict, K_new: np.ndarray, width: int, height: int,
                    fisheye: bool = False) -> np.ndarray:
    """Resamples a distorted image into a pinhole camera (bilinear, edge-clamped).

    For each output pixel centre ``(j + 0.5, i + 0.5)`` the ray ``K_new^-1 [u, v, 1]`` is distorted with
    :func:`distort_normalized` and projected with ``K``; the input is sampled there. Colour channels of
    RGBA input are interpolated premultiplied by alpha.

    Args:
      image: (H, W, C) float array (C = 3 or 4, values in [0, 1]).
      K: (3, 3) intrinsics of the distorted camera.
      params: distortion coefficients (see :func:`distort_normalized`).
      K_new: (3, 3) intrinsics of the output pinhole camera.
      width, height: output size.

    Returns:
      (height, width, C) float32.
    """
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (jj - K_new[0, 2]) / K_new[0, 0]
    y = (ii - K_new[1, 2]) / K_new[1, 1]
    xd, yd = distort_normalized(x, y, params, fisheye)
    u = K[0, 0] * xd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    img = np.asarray(image, np.float64)
    if img.shape[-1] == 4:
        pm = np.concatenate([img[..., :3] * img[..., 3:], img[..., 3:]], axis=-1)
        out = _bilinear(pm, u, v)
        a = out[..., 3:]
        rgb = np.where(a > 1e-8, out[..., :3] / np.maximum(a, 1e-8), 0.0)
        return np.concatenate([np.clip(rgb, 0, 1), a], axis=-1).astype(np.float32)
    return _bilinear(img, u, v).astype(np.float32)


def _pycolmap_camera(pycolmap, K, params, fisheye, width, height):
    c = _coefficients(params)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fisheye:
        model, p = "OPENCV_FISHEYE", [fx, fy, cx, cy, c["k1"], c["k2"], c["k3"], c["k4"]]
    elif c["k3"] != 0.0:
        model, p = "FULL_OPENCV", [fx, fy, cx, cy, c["k1"], c["k2"], c["p1"], c["p2"], c["k3"], 0.0, 0.0, 0.0]
    else:
        model, p = "OPENCV", [fx, fy, cx, cy, c["k1"], c["k2"], c["p1"], c["p2"]]
    cam = pycolmap.Camera.create_from_model_name(1, model, float(fx), int(width), int(height))
    cam.params = p
    return cam


def _read_rgba_or_rgb(path: Path) -> np.ndarray:
    try:
        with PIL.Image.open(path) as im:
            im.load()
            has_alpha = im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or (im.mode == "P" and "transparency" in im.info)
            im = im.convert("RGBA" if has_alpha else "RGB")
            return np.asarray(im, np.float32) / 255.0
    except (PIL.UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise DatasetError(f"Image file {path} cannot be decoded ({type(e).__name__}: {e}); re-export it.") from None


# ----------------------------------------------------------------------------------------------------
# PLY (nerfstudio ply_file_path)
# ----------------------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply_points(path) -> tuple[np.ndarray, np.ndarray | None]:
    """Reads the vertices of a PLY file (ascii or binary, vertex element first, no list properties).

    Returns:
      (points (M, 3) float64, colors (M, 3) float32 in [0, 1] from red/green/blue, or None).

    Raises:
      DatasetError on a malformed or truncated file.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DatasetError(f"Cannot read point cloud {path}: {e}.") from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path} is not a PLY file (no 'ply' magic / end_header).")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body = raw[raw.index(b"\n", end) + 1:]
    fmt, count, props, in_vertex, first = None, None, [], False, True
    for line in header:
        t = line.split()
        if not t:
            continue
        if t[0] == "format":
            fmt = t[1]
        elif t[0] == "element":
            in_vertex = t[1] == "vertex"
            if in_vertex:
                if not first:
                    raise DatasetError(f"{path}: the vertex element must come first.")
                count = int(t[2])
            first = False
        elif t[0] == "property" and in_vertex:
            if t[1] == "list" or t[1] not in _PLY_TYPES:
                raise DatasetError(f"{path}: unsupported vertex property {' '.join(t[1:])}.")
            props.append((t[2], _PLY_TYPES[t[1]]))
    names = [p[0] for p in props]
    if count is None or not all(k in names for k in "xyz"):
        raise DatasetError(f"{path}: no vertex element with x, y, z.")
    try:
        if fmt == "ascii":
            rows = body.decode("ascii").split("\n")
            vals = np.array([r.split() for r in rows[:count]], dtype=np.float64)
            if vals.shape != (count, len(props)):
                raise ValueError("short")
            table = {n: vals[:, i] for i, n in enumerate(names)}
        elif fmt in ("binary_little_endian", "binary_big_endian"):
            order = "<" if fmt == "binary_little_endian" else ">"
            dt = np.dtype([(n, order + t) for n, t in props])
            if len(body) < dt.itemsize * count:
                raise ValueError("short")
            arr = np.frombuffer(body, dtype=dt, count=count)
            table = {n: arr[n].astype(np.float64) for n in names}
        else:
            raise DatasetError(f"{path}: unsupported PLY format {fmt!r}.")
    except ValueError:
        raise DatasetError(f"{path} is truncated or malformed (expected {count} vertices).") from None
    pts = np.stack([table["x"], table["y"], table["z"]], axis=-1)
    cols = None
    if all(k in table for k in ("red", "green", "blue")):
        cols = np.stack([table["red"], table["green"], table["blue"]], axis=-1).astype(np.float32)
    for what, a in (("coordinates", pts), ("colours", cols)):
        if a is not None and not np.all(np.isfinite(a)):
            bad = int(np.sum(~np.all(np.isfinite(a), axis=1)))
            raise DatasetError(f"{path}: {bad} of {count} vertices have non-finite {what}; "
                               "delete them or regenerate the point cloud.")
    if cols is not None:
        cols = cols / (255.0 if cols.max(initial=0) > 1.0 or dict(props)["red"] == "u1" else 1.0)
    return pts, cols


# ----------------------------------------------------------------------------------------------------
# Loader
# ----------------------------------------------------------------------------------------------------


def _frame_value(frame: dict, top: dict, key: str, default=None):
    """A frame's value of ``key``, else the file's top-level one, else ``default``."""
    return frame.get(key, top.get(key, default))


def _frame_number(frame: dict, top: dict, where: str, key: str, default=None):
    """A finite number, or ``default`` when absent / null; a clear error for anything else."""
    v = _frame_value(frame, top, key)
    if v is None:
        return default
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {key} must be a number, got {v!r}.") from None
    if not math.isfinite(x):  # NaN distortion made NaN sample positions and an IndexError
        raise DatasetError(f"{where}: {key} must be a finite number, got {v!r}; fix or remove it.")
    return x


def load_nerf(path, factor: int | None = None, test_every: int | None = 8, skip_missing: bool = False, *,
              normalize: bool = False, cache_dir=None, image_cache_size: int = DEFAULT_IMAGE_CACHE_SIZE,
              image_cache_bytes: int | None = DEFAULT_IMAGE_CACHE_BYTES,
              background=(1.0, 1.0, 1.0), num_random_points: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0,
              verbose: bool = True) -> Dataset:
    """Loads a ``transforms.json`` scene (see the module docstring for the accepted keys).

    Args:
      path: scene folder (with ``transforms.json`` or ``transforms_train.json``) or a json file.
      factor: box-downsampling factor (None -> the Mip-NeRF 360 default for those scene names, else
        full size with images wider than 1600 px resized to 1600 wide, as 3DGS; see
        :func:`default_resolution`); image ``W x H`` becomes ``W // f x H // f`` and K is divided by ``f``.
      test_every: split of a single ``transforms.json`` (every ``test_every``-th name-sorted frame is a
        test view; 0 / None: none). Ignored when ``transforms_train.json`` defines the split.
      skip_missing: drop frames whose image is missing / unreadable (printing how many).
      normalize, cache_dir, image_cache_size, image_cache_bytes, verbose: as for :func:`load_colmap`.
      background: (3,) RGB in [0, 1] behind transparent pixels (default white, the NeRF convention).
      num_random_points, seed: without ``ply_file_path``, ``num_random_points`` (default 100,000)
        seeded uniform points with uniform random colours in the cube centred on the mean camera centre
        with half-side 0.5 x the largest camera distance from it (for the Blender scenes, about
        [-2, 2]^3).

    Returns:
      a :class:`Dataset` (``format="nerf"``); view names are the resolved file paths relative to the
      json folder (e.g. ``"train/r_0.png"``).

    Raises:
      DatasetError: invalid JSON, missing keys (no focal length / pose), missing or unreadable images
        (unless ``skip_missing``), image size that disagrees with ``w``/``h``, bad poses.
    """
    p = Path(path)
    found = find_transforms(p)
    if found is None:
        raise DatasetError(f"No transforms.json or transforms_train.json in {p}.")
    scene = p if p.is_dir() else p.parent
    factor, max_width = default_resolution(scene, factor)
    if factor < 1:
        raise DatasetError(f"factor must be a positive integer, got {factor}.")

    frames = []  # (split, frame dict, top dict, json path)
    tops = {}
    for split, jpath in found.items():
        data = _read_json(jpath)
        tops[split] = data
        for k, fr in enumerate(data["frames"]):
            if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
                raise DatasetError(f"{jpath}: frame {k} lacks 'file_path' or 'transform_matrix'.")
            frames.append((split, fr, data, jpath))
    if not frames:
        raise DatasetError(f"{', '.join(str(v) for v in found.values())} list no frames.")

    metas, problems = [], []
    for split, fr, top, jpath in frames:
        base = jpath.parent
        f = _resolve_file(base, str(fr["file_path"]))
        where = f"{jpath} (file_path {fr['file_path']!r})"
        size, why = probe_image(f)
        if size is None or f is None:
            if f is None:
                why = f"{why} (also tried appending .png, .jpg, .jpeg, ...)"
            problems.append((f if f is not None else base / str(fr["file_path"]), why))
            continue
        get = functools.partial(_frame_value, fr, top)
        num = functools.partial(_frame_number, fr, top, where)

        w, h = num("w"), num("h")
        if w is not None and h is not None:
            check_size_against_camera(f, size, (w, h), 1, f"w/h in {jpath}")
        w, h = size
        fx, fy, angle_x, angle_y = num("fl_x"), num("fl_y"), num("camera_angle_x"), num("camera_angle_y")
        if fx is None and angle_x is not None:
            fx = 0.5 * w / math.tan(0.5 * angle_x)
        if fx is None:
            raise DatasetError(f"{where}: no focal length (need fl_x or camera_angle_x).")
        if fy is None:
            fy = fx if angle_y is None else 0.5 * h / math.tan(0.5 * angle_y)
        cx = num("cx", 0.5 * w)
        cy = num("cy", 0.5 * h)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        fisheye = bool(get("is_fisheye", False)) or str(get("camera_model", "OPENCV")).upper() == "OPENCV_FISHEYE"
        model = str(get("camera_model", "OPENCV")).upper()
        if model not in ("OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE"):
            raise DatasetError(f"{jpath}: camera_model {model!r} is not supported (use OPENCV or OPENCV_FISHEYE).")
        dist = {k: num(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
        if not fisheye and dist["k4"] != 0.0:
            raise DatasetError(f"{where}: k4 is set but the camera is not fisheye; k4 of the OpenCV rational "
                               "model is not supported.")
        try:
            m = np.asarray(fr["transform_matrix"], np.float64)
        except (TypeError, ValueError):
            m = np.zeros((0,))
        if m.shape == (3, 4):
            m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
        if m.shape != (4, 4):
            raise DatasetError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {m.shape}.")
        c2w = orthonormalize_pose(m, where) @ OPENGL_TO_OPENCV
        name = f.relative_to(scene).as_posix() if f.is_relative_to(scene) else f.as_posix()
        metas.append(dict(split=split, name=name, file=f, K=K, w=w, h=h, dist=dist, fisheye=fisheye,
                          distorted=any(v != 0.0 for v in dist.values()), c2w=c2w))
    skipped = handle_unreadable(problems, len(frames), ", ".join(str(v) for v in found.values()), skip_missing)
    if not metas:
        raise DatasetError(f"No readable frame in {p}.")

    info = {"transforms": {k: str(v) for k, v in found.items()}, "skipped": skipped}
    if any(m["distorted"] for m in metas):
        _undistort_frames(scene, metas, cache_dir, verbose, info)

    records = []
    for m in metas:
        K, w, h = m["K"], m["w"], m["h"]
        if factor > 1:
            K = np.diag([1.0 / factor, 1.0 / factor, 1.0]) @ K
            w, h = w // factor, h // factor
            if w < 1 or h < 1:
                raise DatasetError(f"factor {factor} leaves no pixel of image {m['file']}.")
        records.append(dict(name=m["name"], K=K, w2c=np.linalg.inv(m["c2w"]), width=w, height=h,
                            image_path=m["file"], load=image_loader(m["file"], factor, background)))
    records, ratio = fit_records_to_width(records, max_width, background, verbose)
    applied: float = ratio if ratio > 1 else factor

    splits = None
    if "train" in found:
        splits = ([i for i, m in enumerate(metas) if m["split"] == "train"],
                  [i for i, m in enumerate(metas) if m["split"] == "test"])

    pts = cols = None
    source = "random"
    ply = None
    for top in tops.values():
        if top.get("ply_file_path"):
            ply = Path(found[next(iter(found))]).parent / str(top["ply_file_path"])
    if ply is not None:
        pts, cols = read_ply_points(ply)
        source = "ply"
        info["ply"] = str(ply)

    def rand(norm):
        half = 0.5 * norm.original_radius / 1.1
        return random_points_in_box(norm.original_center, half, num_random_points, seed)

    return finish_dataset(records, fmt="nerf", path=p, factor=applied, test_every=test_every, normalize=normalize,
                          points=pts, colors=cols, points_source=source,
                          cache=ImageCache(image_cache_size, image_cache_bytes),
                          info=info, splits=splits, random_points=rand)



def _undistort_frames(scene: Path, metas: list[dict], cache_dir, verbose: bool, info: dict) -> None:
    """Undistorts the distorted frames once into the cache (atomically) and updates ``metas`` in place
    (file, K, w, h) to the undistorted PNGs and their pinhole cameras."""
    todo = [m for m in metas if m["distorted"]]
    new_cams = []
    pycolmap = pycolmap_module("Undistorting the frames of a transforms.json scene")
    for m in todo:
        cam = _pycolmap_camera(pycolmap, m["K"], m["dist"], m["fisheye"], m["w"], m["h"])
        try:
            und = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
        except Exception as e:
            raise DatasetError(f"Cannot undistort the camera of {m['file']} ({e}); check its distortion "
                               "coefficients.") from None
        p = np.asarray(und.params, np.float64)
        K_new = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        new_cams.append((K_new, int(und.width), int(und.height)))
    key = fingerprint("nerf-undistort-v1", *[(m["name"], m["K"].tolist(), sorted(m["dist"].items()), m["fisheye"])
                                             for m in todo], *[m["file"] for m in todo])
    final = resolve_cache_dir(scene, cache_dir) / "undistorted" / f"nerf-{key}"
    out_names = [Path(m["name"]).with_suffix(".png").as_posix() for m in todo]

    def build(tmp: Path):
        if verbose:
            print(f"[patexgs_jax] {scene}: {len(todo)} frames have lens distortion; undistorting them once "
                  f"into {final} (reused on later loads) ...", file=sys.stderr, flush=True)
        t0 = time.time()
        for m, (K_new, w, h), rel in zip(todo, new_cams, out_names):
            img = _read_rgba_or_rgb(m["file"])
            out = undistort_image(img, m["K"], m["dist"], K_new, w, h, m["fisheye"])
            dst = tmp / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            arr = np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)
            PIL.Image.fromarray(arr, "RGBA" if arr.shape[-1] == 4 else "RGB").save(dst)
        if verbose:
            print(f"[patexgs_jax] undistortion done in {time.time() - t0:.1f} s.", file=sys.stderr, flush=True)

    if not is_complete_dir(final):
        try:
            atomic_build_dir(final, build)
        except OSError as e:
            raise DatasetError(f"Cannot write the undistortion cache {final} ({e}); pass cache_dir= or set "
                               "PATEXGS_CACHE to a writable folder.") from None
    for m, (K_new, w, h), rel in zip(todo, new_cams, out_names):
        m.update(file=final / rel, K=K_new, w=w, h=h, distorted=False)
    info["undistorted_dir"] = str(final)
