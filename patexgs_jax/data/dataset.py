"""Format-independent pieces of the dataset loaders.

Everything here is host-side numpy (jax is only touched to build :class:`~patexgs_jax.camera.Camera`).

* :class:`View` -- one posed image: a :class:`Camera`, a name and a lazily loaded ``(H, W, 3)`` float32
  image in [0, 1] (read on first access of ``view.image`` and kept in a bounded LRU :class:`ImageCache`:
  at most a set number of images and of bytes).
* :class:`Dataset` -- train/test views, an initial point cloud and the :class:`SceneNormalization`.
* helpers shared by the format loaders: image reading (RGBA compositing), box downsampling, the 3DGS
  train/test split, the 3DGS scene normalisation, random initial points, cache-folder selection and
  atomic cache writes.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import os
import shutil
import stat
import sys
import threading
import time
import uuid
import warnings
import zlib  # noqa: F401  -- load the system zlib before pycolmap can be imported (see data/__init__.py)
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import PIL.Image  # noqa: F401  -- same reason: PIL (and its zlib) must be loaded before pycolmap

from ..camera import Camera

__all__ = [
    "DatasetError",
    "DatasetWarning",
    "ImageCache",
    "View",
    "Dataset",
    "SceneNormalization",
    "read_image",
    "box_downsample",
    "area_resize",
    "split_indices",
    "compute_normalization",
    "random_points_in_box",
    "random_points_in_frustums",
    "zoom_out_views",
    "resolve_cache_dir",
    "IMAGE_EXTENSIONS",
    "DEFAULT_IMAGE_CACHE_SIZE",
    "DEFAULT_IMAGE_CACHE_BYTES",
    "DEFAULT_NUM_RANDOM_POINTS",
]

#: File extensions (lower case) recognised as images when listing folders.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
#: Default number of decoded images kept in memory per dataset.
DEFAULT_IMAGE_CACHE_SIZE = 64
#: Default bound on the bytes of the decoded images kept in memory per dataset (2 GiB).
DEFAULT_IMAGE_CACHE_BYTES = 2 << 30
#: Default number of random initial points when a scene has no point cloud (3DGS uses 100k for Blender).
DEFAULT_NUM_RANDOM_POINTS = 100_000


class DatasetError(ValueError):
    """A dataset cannot be loaded; the message names the offending file and how to fix it."""


class DatasetWarning(UserWarning):
    """Something in a dataset is unusual but was worked around (e.g. an empty point cloud)."""


# ----------------------------------------------------------------------------------------------------
# Images
# ----------------------------------------------------------------------------------------------------


def read_image(path, background=(1.0, 1.0, 1.0), size: tuple[int, int] | None = None) -> np.ndarray:
    """Reads an image file as RGB float32 in [0, 1].

    Args:
      path: image file (anything Pillow reads: PNG, JPEG, TIFF, ...).
      background: (3,) RGB in [0, 1] on which images with an alpha channel (RGBA, LA, palette with
        transparency) are composited: ``rgb * alpha + background * (1 - alpha)``.
      size: optional ``(width, height)`` to resize to with an area filter (:func:`area_resize`),
        a block of rows at a time: besides the decoded file, memory holds the output and one block.

    Returns:
      (H, W, 3) float32 array in [0, 1]. 16-bit grey images are scaled by 1/65535; grey images are
      replicated to three channels. EXIF orientation is *not* applied (COLMAP does not apply it either).

    Raises:
      DatasetError: the file is missing or cannot be decoded (message names the file).
    """
    path = Path(path)
    try:
        with PIL.Image.open(path) as im:
            im.load()
            if size is None:
                return _pil_to_float(im, background)
            W, H = im.size
            w, h = int(size[0]), int(size[1])
            if not (1 <= w <= W and 1 <= h <= H):
                raise ValueError(f"cannot area-resize a {W}x{H} image to {w}x{h} (only downscaling)")
            cols = _area_weights(W, w)
            rows = [_resize_axis(_pil_to_float(im.crop((0, r, W, min(H, r + _RESIZE_BLOCK))), background), cols, 1)
                    for r in range(0, H, _RESIZE_BLOCK)]
    except FileNotFoundError:
        raise DatasetError(f"Image file {path} does not exist; restore it, or load with "
                           "skip_missing=True to drop the views whose images are missing.") from None
    except (PIL.UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise DatasetError(f"Image file {path} cannot be decoded ({type(e).__name__}: {e}); the file is "
                           "corrupt or truncated: re-export or re-copy it, or load with skip_missing=True "
                           "(which only drops images unreadable at load time).") from None
    return _resize_axis(np.concatenate(rows), _area_weights(H, h), 0)


#: Rows of a full-size image converted to float at a time by :func:`read_image`'s resize.
_RESIZE_BLOCK = 256


def _area_weights(n_in: int, n_out: int):
    """Area-filter taps along one axis as an (n_out, n_in) float32 sparse matrix: output pixel j
    averages the input interval ``[j s, (j + 1) s)``, s = n_in / n_out, each input pixel weighted
    by its overlap with it (at most ceil(s) + 1 taps a row)."""
    import scipy.sparse

    s = n_in / n_out
    lo = np.arange(n_out) * s
    hi = lo + s
    k = int(np.ceil(s)) + 1
    idx = np.floor(lo).astype(np.int64)[:, None] + np.arange(k)
    w = np.clip(np.minimum(hi[:, None], idx + 1) - np.maximum(lo[:, None], idx), 0.0, None) / s
    keep = (w > 0) & (idx < n_in)
    rows = np.broadcast_to(np.arange(n_out)[:, None], idx.shape)
    return scipy.sparse.csr_matrix((w[keep].astype(np.float32), (rows[keep], idx[keep])), shape=(n_out, n_in))


def _resize_axis(x: np.ndarray, taps, axis: int) -> np.ndarray:
    """Applies :func:`_area_weights` taps along ``axis`` (0 or 1) of an (H, W, C) float32 array."""
    if axis == 0:
        return np.asarray(taps @ x.reshape(x.shape[0], -1), np.float32).reshape((taps.shape[0],) + x.shape[1:])
    t = np.ascontiguousarray(x.transpose(1, 0, 2))  # the sparse product runs along the first axis
    out = np.asarray(taps @ t.reshape(t.shape[0], -1), np.float32).reshape((taps.shape[0],) + t.shape[1:])
    return np.ascontiguousarray(out.transpose(1, 0, 2))


def area_resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Downscales an (H, W, C) image to (height, width, C) float32 with an area filter.

    Output pixel (i, j) is the mean of the image over the rectangle
    ``[j W / width, (j + 1) W / width) x [i H / height, (i + 1) H / height)`` (partly covered pixels
    weighted by their covered area), so pixel centres map as ``(j + 0.5) W / width`` and the
    intrinsics scale by ``width / W`` and ``height / H`` (an integer factor is :func:`box_downsample`).
    """
    x = np.asarray(image, np.float32)
    H, W = x.shape[:2]
    if not (1 <= width <= W and 1 <= height <= H):
        raise ValueError(f"area_resize only downscales: {W}x{H} to {width}x{height}.")
    squeeze = x.ndim == 2
    x = x[..., None] if squeeze else x
    out = _resize_axis(_resize_axis(x, _area_weights(W, width), 1), _area_weights(H, height), 0)
    return out[..., 0] if squeeze else out


def _pil_to_float(im: PIL.Image.Image, background) -> np.ndarray:
    bg = np.asarray(background, np.float32).reshape(3)
    mode = im.mode
    if mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
        mode = im.mode
    if mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        a = np.asarray(im, dtype=np.float32) / 65535.0
        return np.repeat(a[..., None], 3, axis=-1)
    if mode == "I":
        a = np.asarray(im, dtype=np.float64)
        a = a / (65535.0 if a.max(initial=0) > 255 else 255.0)
        return np.repeat(a[..., None], 3, axis=-1).astype(np.float32)
    if mode == "F":
        return np.repeat(np.clip(np.asarray(im, np.float32), 0.0, 1.0)[..., None], 3, axis=-1)
    if mode in ("LA", "La", "PA", "RGBa"):
        im = im.convert("RGBA")
        mode = "RGBA"
    if mode == "L" or mode == "1":
        a = np.asarray(im.convert("L"), dtype=np.float32) / 255.0
        return np.repeat(a[..., None], 3, axis=-1)
    if mode == "RGBA":
        a = np.asarray(im, dtype=np.float32) / 255.0
        alpha = a[..., 3:4]
        return (a[..., :3] * alpha + bg * (1.0 - alpha)).astype(np.float32)
    if mode != "RGB":
        im = im.convert("RGB")
    return _to_unit_float(np.asarray(im))


def _to_unit_float(a: np.ndarray) -> np.ndarray:
    """uint8 -> float32 / 255 into one new array (no float32 temporary of the same size)."""
    out = np.empty(a.shape, np.float32)
    np.divide(a, np.float32(255.0), out=out)
    return out


def image_size(path) -> tuple[int, int]:
    """(width, height) of an image file from its header only (no decoding).

    Raises:
      FileNotFoundError: the file does not exist.
      DatasetError: the header cannot be read.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    try:
        with PIL.Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (PIL.UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise DatasetError(f"Image file {path} is not a readable image ({type(e).__name__}: {e}); "
                           "re-export or re-copy it, or load with skip_missing=True to drop it.") from None


def probe_image(path) -> tuple[tuple[int, int] | None, str | None]:
    """Reads only an image header: ``((width, height), None)``, or ``(None, reason)`` if the file is
    missing or not a readable image."""
    if path is None or not Path(path).is_file():
        return None, "does not exist"
    try:
        with PIL.Image.open(path) as im:
            return (int(im.size[0]), int(im.size[1])), None
    except (PIL.UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        return None, f"is not a readable image ({type(e).__name__})"


def handle_unreadable(problems: list[tuple[str, str]], total: int, source: str, skip_missing: bool) -> list[str]:
    """Raises (or, with ``skip_missing``, prints and returns the skipped names) for missing/unreadable images.

    Args:
      problems: ``(path or name, reason)`` for each bad image.
      total: number of images the source lists.
      source: what lists them (e.g. the COLMAP model folder), for the message.
    """
    if not problems:
        return []
    listed = "; ".join(f"{p} {why}" for p, why in problems[:5]) + ("; ..." if len(problems) > 5 else "")
    if not skip_missing:
        raise DatasetError(f"{len(problems)} of {total} images listed by {source} are missing or unreadable: {listed}. "
                           "Restore them, or load with skip_missing=True to drop those views.")
    print(f"[patexgs_jax] skip_missing: skipped {len(problems)} of {total} images listed by {source} "
          f"(missing or unreadable): {listed}", file=sys.stderr, flush=True)
    return [str(p) for p, _ in problems]


def image_loader(path, factor: int, background, size: tuple[int, int] | None = None):
    """A zero-argument function that reads ``path`` (RGBA composited on ``background``) and
    box-downsamples it by ``factor``, or resizes it to ``size`` = (width, height) with an area
    filter (see :func:`read_image`): the lazy loader a :class:`View` holds."""
    if size is not None:
        return lambda: read_image(path, background, size=size)
    return lambda: box_downsample(read_image(path, background), factor)


def fit_records_to_width(records: list[dict], max_width: int | None, background,
                         verbose: bool) -> tuple[list[dict], float]:
    """Applies the default resolution rule to loader records (see :func:`finish_dataset`): the
    images wider than ``max_width`` are resized to ``max_width`` pixels wide (height
    ``H * max_width // W``) with an area filter, their intrinsics scaled per axis, and one line says
    so. Returns the records and the largest downscaling ratio applied (1.0 when none).
    """
    if max_width is None:
        return records, 1.0
    wide = [r for r in records if r["width"] > max_width]
    if not wide:
        return records, 1.0
    out = []
    for r in records:
        if r["width"] <= max_width:
            out.append(r)
            continue
        w, h = int(max_width), max(1, r["height"] * int(max_width) // r["width"])
        K = np.diag([w / r["width"], h / r["height"], 1.0]) @ np.asarray(r["K"], np.float64)
        out.append(dict(r, K=K, width=w, height=h, load=image_loader(r["image_path"], 1, background, size=(w, h)),
                        full_size=(r["width"], r["height"])))
    big = max(wide, key=lambda r: r["width"])
    ratio = big["width"] / max_width
    if verbose:
        small = next(r for r in out if r["name"] == big["name"])
        print(f"[patexgs_jax] {len(wide)} of {len(records)} images are wider than {max_width} px (up to "
              f"{big['width']}x{big['height']}): training at {small['width']}x{small['height']}, downscaled "
              f"{ratio:.3g}x with an area filter, as 3DGS does; --factor 1 (factor=1) keeps the full size.",
              file=sys.stderr, flush=True)
    return out, ratio


def box_downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Box (area) downsampling by an integer factor, matching :meth:`Camera.scaled`.

    The image is cropped to a multiple of ``factor`` (the partial last row/column block is dropped) and
    each ``factor x factor`` block is averaged, so output pixel (i, j) covers input pixels
    ``[f*i, f*(i+1)) x [f*j, f*(j+1))`` and continuous coordinates are simply divided by ``factor``.

    Args:
      image: (H, W) or (H, W, C) array.
      factor: positive integer.

    Returns:
      (H // factor, W // factor[, C]) float32 array (the input itself, as float32, when factor == 1).
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"downsampling factor must be a positive integer, got {factor}.")
    image = np.asarray(image)
    if factor == 1:
        return image.astype(np.float32, copy=False)
    h, w = image.shape[0] // factor, image.shape[1] // factor
    if h < 1 or w < 1:
        raise ValueError(f"factor {factor} leaves no pixel of a {image.shape[1]}x{image.shape[0]} image.")
    x = image[: h * factor, : w * factor].astype(np.float32, copy=False)
    x = x.reshape((h, factor, w, factor) + image.shape[2:])
    return x.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


class ImageCache:
    """A thread-safe, bounded least-recently-used cache of decoded images.

    Holds at most ``maxsize`` images and at most ``max_bytes`` of them: a 24 MP image is 288 MB as
    float32, so the byte bound is what keeps a large capture's cache in memory (with the defaults,
    64 images of 1600 x 1200, or 7 of 24 MP). An image larger than ``max_bytes`` on its own is
    returned without being kept.

    Args:
      maxsize: maximum number of images held (``0`` disables caching: every access re-reads).
      max_bytes: maximum total bytes of the images held (None: no byte bound).

    Attributes:
      hits, misses: access counters (a miss is one call of the loader).
      nbytes: bytes of the images held now.
    """

    def __init__(self, maxsize: int = DEFAULT_IMAGE_CACHE_SIZE, max_bytes: int | None = DEFAULT_IMAGE_CACHE_BYTES):
        maxsize = int(maxsize)
        if maxsize < 0:
            raise ValueError(f"image cache size must be >= 0, got {maxsize}.")
        if max_bytes is not None and max_bytes < 0:
            raise ValueError(f"image cache bytes must be >= 0 or None, got {max_bytes}.")
        self.maxsize = maxsize
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self._items: collections.OrderedDict[object, np.ndarray] = collections.OrderedDict()
        self._lock = threading.Lock()
        self.nbytes = 0
        self.hits = 0
        self.misses = 0

    def _over(self) -> bool:
        return len(self._items) > self.maxsize or (self.max_bytes is not None and self.nbytes > self.max_bytes)

    def get(self, key, loader: Callable[[], np.ndarray]) -> np.ndarray:
        """Returns the cached array for ``key``, calling ``loader()`` (and caching) on a miss.

        The returned array is read-only (it is shared by every later access).
        """
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                self.hits += 1
                return self._items[key]
            self.misses += 1
        value = loader()
        value.setflags(write=False)
        if self.maxsize:
            with self._lock:
                old = self._items.pop(key, None)  # another thread loaded it meanwhile
                if old is not None:
                    self.nbytes -= old.nbytes
                self._items[key] = value
                self.nbytes += value.nbytes
                while self._items and self._over():
                    self.nbytes -= self._items.popitem(last=False)[1].nbytes
        return value

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key) -> bool:
        return key in self._items

    def clear(self) -> None:
        """Drops every cached image."""
        with self._lock:
            self._items.clear()
            self.nbytes = 0


# ----------------------------------------------------------------------------------------------------
# Views
# ----------------------------------------------------------------------------------------------------


class View:
    """One posed image of a dataset.

    Attributes:
      camera: the :class:`Camera` (OpenCV axes, K in continuous pixel coordinates).
      name: image name as in the source (e.g. the COLMAP image name ``"0001.jpg"``); scaled views
        keep the name of the view they come from.
      scale: integer zoom-out factor relative to the loaded view (1 for views of a :class:`Dataset`).
      image_path: the file the pixels come from (after undistortion / ``images_N`` selection), or None.
      near, far: optional depth bounds (LLFF ``poses_bounds.npy``), else None.
      image: (H, W, 3) float32 in [0, 1] with (H, W) = (camera.height, camera.width); loaded on access
        and held in the dataset's bounded LRU cache. Read-only.
    """

    __slots__ = ("camera", "name", "scale", "image_path", "near", "far", "_load", "_cache", "_key")

    def __init__(self, camera: Camera, name: str, load: Callable[[], np.ndarray], *, cache: ImageCache,
                 key=None, scale: int = 1, image_path=None, near=None, far=None):
        self.camera = camera
        self.name = str(name)
        self.scale = int(scale)
        self.image_path = None if image_path is None else Path(image_path)
        self.near = None if near is None else float(near)
        self.far = None if far is None else float(far)
        self._load = load
        self._cache = cache
        self._key = key if key is not None else (id(self), self.scale)

    @property
    def image(self) -> np.ndarray:
        """(H, W, 3) float32 image in [0, 1], loaded lazily (LRU-cached, read-only)."""
        return self._cache.get(self._key, self._checked_load)

    def _checked_load(self) -> np.ndarray:
        img = np.asarray(self._load(), dtype=np.float32)
        want = (self.camera.height, self.camera.width, 3)
        if img.shape != want:
            src = self.image_path if self.image_path is not None else self.name
            raise DatasetError(f"Image {src} decoded to shape {img.shape} but its camera expects {want}; "
                               "the file changed after loading the dataset: reload it.")
        return img

    def scaled(self, factor: int) -> View:
        """The zoom-out view: image box-downsampled by ``factor`` and ``camera.scaled(factor)``.

        The image is cropped to a multiple of ``factor`` and averaged over ``factor x factor`` blocks,
        which is exactly consistent with :meth:`Camera.scaled` (continuous coordinates divided by
        ``factor``). The result shares this view's image cache.

        Args:
          factor: positive integer.

        Returns:
          a :class:`View` of size (height // factor, width // factor) with ``scale = self.scale * factor``.
        """
        factor = int(factor)
        if factor == 1:
            return self
        camera = self.camera.scaled(factor)
        parent = self
        return View(camera, self.name, lambda: box_downsample(parent.image, factor), cache=self._cache,
                    key=(self._key, factor), scale=self.scale * factor, image_path=self.image_path,
                    near=self.near, far=self.far)

    def __repr__(self) -> str:
        return (f"View(name={self.name!r}, {self.camera.width}x{self.camera.height}, scale={self.scale}, "
                f"image_path={str(self.image_path) if self.image_path else None!r})")


def zoom_out_views(views: Sequence[View], factors: Iterable[int] = (2, 4, 8)) -> dict[int, list[View]]:
    """For each factor, the zoom-out (box-downsampled) version of every view.

    Args:
      views: sequence of N views (typically ``dataset.test_views``).
      factors: positive integer zoom-out factors.

    Returns:
      ``{factor: [views[0].scaled(factor), ..., views[N-1].scaled(factor)]}`` (lists aligned with
      ``views``; images load lazily).
    """
    return {int(f): [v.scaled(int(f)) for v in views] for f in factors}


# ----------------------------------------------------------------------------------------------------
# Scene normalisation
# ----------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SceneNormalization:
    """The 3DGS scene normalisation and the similarity (if any) applied to the loaded scene.

    Attributes:
      center: (3,) float64 mean centre of the training cameras (all cameras if there is no training
        view), in the *dataset's* (returned) coordinates.
      radius: 1.1 x the largest distance of those camera centres from ``center`` (dataset
        coordinates); 3DGS's ``cameras_extent``.
      transform: (4, 4) float64 similarity mapping original (file) world coordinates to dataset
        coordinates, ``x_dataset = s * R x_original + t`` (identity unless ``normalize=True``).
      original_center, original_radius: the same statistics in the original coordinates.
    """

    center: np.ndarray
    radius: float
    transform: np.ndarray
    original_center: np.ndarray
    original_radius: float

    @property
    def applied(self) -> bool:
        """Whether the cameras and points were transformed (``normalize=True``)."""
        return not np.allclose(self.transform, np.eye(4))

    @property
    def scale(self) -> float:
        """Scale ``s`` of :attr:`transform` (dataset length = s * original length)."""
        return float(np.cbrt(np.linalg.det(self.transform[:3, :3])))

    def to_original_points(self, points) -> np.ndarray:
        """Maps (..., 3) dataset-coordinate points to original coordinates; returns float64."""
        inv = np.linalg.inv(self.transform)
        p = np.asarray(points, np.float64)
        return p @ inv[:3, :3].T + inv[:3, 3]

    def from_original_points(self, points) -> np.ndarray:
        """Maps (..., 3) original-coordinate points to dataset coordinates; returns float64."""
        p = np.asarray(points, np.float64)
        return p @ self.transform[:3, :3].T + self.transform[:3, 3]

    def to_original_length(self, length):
        """Converts lengths (e.g. Gaussian scales, depths) from dataset to original units (``/ s``)."""
        return np.asarray(length, np.float64) / self.scale

    def to_original_world_to_camera(self, world_to_camera) -> np.ndarray:
        """(4, 4) world-to-camera of the original scene for a dataset-coordinate (4, 4) world-to-camera.

        Camera-space lengths are in original units (the similarity's scale is undone).
        """
        w2c = np.asarray(world_to_camera, np.float64) @ self.transform
        out = np.eye(4)
        out[:3, :] = w2c[:3, :] / self.scale
        return out

    def from_original_world_to_camera(self, world_to_camera) -> np.ndarray:
        """(4, 4) dataset-coordinate world-to-camera for an original-coordinate (4, 4) world-to-camera."""
        w2c = np.asarray(world_to_camera, np.float64) @ np.linalg.inv(self.transform)
        out = np.eye(4)
        out[:3, :] = w2c[:3, :] * self.scale
        return out


def compute_normalization(camera_centers, normalize: bool = False) -> SceneNormalization:
    """The 3DGS normalisation of a set of camera centres.

    ``center`` = mean camera centre, ``radius`` = 1.1 * max distance of a centre from it (the loaders
    pass the training cameras, as 3DGS does, or all cameras when there is no training view; a single
    camera gives radius 1.1 * 1, so the radius is never 0, as in 3DGS when all centres coincide).

    Args:
      camera_centers: (N, 3) camera centres in original world coordinates (N >= 1).
      normalize: if True the recorded transform maps ``x -> (x - center) / radius`` (so the normalised
        scene has centre 0 and radius 1); otherwise it is the identity.

    Returns:
      a :class:`SceneNormalization`.
    """
    c = np.asarray(camera_centers, np.float64).reshape(-1, 3)
    center = c.mean(axis=0)
    dist = np.linalg.norm(c - center, axis=1).max()
    radius = float(1.1 * dist) if dist > 0 else 1.1
    transform = np.eye(4)
    if normalize:
        transform[:3, :3] /= radius
        transform[:3, 3] = -center / radius
        return SceneNormalization(center=np.zeros(3), radius=1.0, transform=transform,
                                  original_center=center, original_radius=radius)
    return SceneNormalization(center=center, radius=radius, transform=transform,
                              original_center=center, original_radius=radius)


# ----------------------------------------------------------------------------------------------------
# Dataset
# ----------------------------------------------------------------------------------------------------


@dataclasses.dataclass(eq=False)
class Dataset:
    """A loaded scene.

    Attributes:
      train_views, test_views: tuples of :class:`View` (sorted by name within each split).
      points: (M, 3) float32 initial point cloud (dataset coordinates).
      colors: (M, 3) float32 in [0, 1], or None when the points carry no colour.
      points_source: ``"sfm"`` (COLMAP points3D), ``"ply"`` (a PLY named by transforms.json) or
        ``"random"`` (seeded random points; see the format loaders for the region).
      normalization: the :class:`SceneNormalization` (centre, radius, and the applied similarity).
      format: ``"colmap"``, ``"llff"`` or ``"nerf"``.
      path: the scene folder (or transforms file) that was loaded.
      factor: the image downsampling factor that was applied (1 = full resolution; with the default
        resolution rule, images wider than 1600 px resized to 1600 wide, the largest ratio, e.g. 2.52).
      image_cache: the shared :class:`ImageCache` of decoded images.
      info: free-form details (e.g. ``{"undistorted_from": ..., "skipped": [...]}``).
    """

    train_views: tuple
    test_views: tuple
    points: np.ndarray
    colors: np.ndarray | None
    points_source: str
    normalization: SceneNormalization
    format: str
    path: Path
    factor: float
    image_cache: ImageCache
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def views(self) -> tuple:
        """All views (train then test)."""
        return tuple(self.train_views) + tuple(self.test_views)

    def zoom_out_views(self, factors: Iterable[int] = (2, 4, 8)) -> dict[int, list[View]]:
        """``{factor: [test_view.scaled(factor) for each test view]}``; see :func:`zoom_out_views`."""
        return zoom_out_views(self.test_views, factors)

    def __repr__(self) -> str:
        n = self.normalization
        return (f"Dataset(format={self.format!r}, path={str(self.path)!r}, factor={self.factor}, "
                f"train={len(self.train_views)}, test={len(self.test_views)}, points={len(self.points)} "
                f"({self.points_source}), center={np.round(n.center, 4).tolist()}, radius={n.radius:.4g})")


def split_indices(n: int, test_every: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The 3DGS / Mip-NeRF 360 hold-out split of ``n`` name-sorted images.

    Image ``i`` is a test image iff ``i % test_every == 0`` (so images 0, 8, 16, ... with the default
    8). ``test_every`` of 0 or None means no test split.

    Returns:
      (train_indices, test_indices), int64 arrays.
    """
    idx = np.arange(int(n))
    if not test_every:
        return idx, idx[:0]
    test_every = int(test_every)
    if test_every < 0:
        raise ValueError(f"test_every must be >= 0 or None, got {test_every}.")
    is_test = idx % test_every == 0
    return idx[~is_test], idx[is_test]


def finish_dataset(records: list[dict], *, fmt: str, path: Path, factor: float, test_every, normalize: bool,
                   points, colors, points_source: str, cache: ImageCache, info: dict | None = None,
                   splits: tuple[list[int], list[int]] | None = None, random_points=None) -> Dataset:
    """Builds a :class:`Dataset` from per-view records (internal helper shared by the loaders).

    Each record is a dict with ``name``, ``K`` (3, 3) float64, ``w2c`` (4, 4) float64 (original
    coordinates), ``width``, ``height``, ``load`` (callable returning the (H, W, 3) image), optionally
    ``image_path``, ``near``, ``far``. Records are sorted by name; ``splits`` (indices into the *given*
    order) overrides ``test_every``. ``random_points`` is a callable ``(normalization) -> (points,
    colors)`` used when ``points`` is None.
    """
    if not records:
        raise DatasetError(f"No usable views in {path}.")
    order = sorted(range(len(records)), key=lambda i: records[i]["name"])
    if splits is not None:
        train_idx = sorted(splits[0], key=lambda i: records[i]["name"])
        test_idx = sorted(splits[1], key=lambda i: records[i]["name"])
    else:
        tr, te = split_indices(len(order), test_every)
        train_idx = [order[k] for k in tr]
        test_idx = [order[k] for k in te]
    # 3DGS normalises with the training cameras (all cameras if there is no training view).
    centers = np.stack([-r["w2c"][:3, :3].T @ r["w2c"][:3, 3] for r in (
        [records[i] for i in train_idx] if train_idx else records)])
    norm = compute_normalization(centers, normalize=normalize)
    if points is None:
        if random_points is None:
            raise ValueError("finish_dataset needs points or random_points.")
        points, colors = random_points(norm)
    T = norm.transform
    s = norm.scale
    views = {}
    for i in order:
        r = records[i]
        w2c = r["w2c"]
        if normalize:
            w2c = norm.from_original_world_to_camera(w2c)
        try:
            cam = Camera.from_intrinsics(r["K"], w2c, r["width"], r["height"])
        except ValueError as e:
            raise DatasetError(f"{path}: invalid camera for view {r['name']!r}: {e}") from None
        near, far = r.get("near"), r.get("far")
        if normalize and near is not None:
            near, far = near * s, None if far is None else far * s
        views[i] = View(cam, r["name"], r["load"], cache=cache, key=(i, 1), image_path=r.get("image_path"),
                        near=near, far=far)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if normalize:
        points = points @ T[:3, :3].T + T[:3, 3]
    return Dataset(train_views=tuple(views[i] for i in train_idx), test_views=tuple(views[i] for i in test_idx),
                   points=points.astype(np.float32),
                   colors=None if colors is None else np.asarray(colors, np.float32).reshape(-1, 3),
                   points_source=points_source, normalization=norm, format=fmt, path=Path(path),
                   factor=factor if isinstance(factor, float) else int(factor), image_cache=cache,
                   info=dict(info or {}))


# ----------------------------------------------------------------------------------------------------
# Random initial points
# ----------------------------------------------------------------------------------------------------


def random_points_in_box(center, half_extent: float, count: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0):
    """Uniform random points in an axis-aligned cube, with uniform random colours (as 3DGS's Blender init).

    Args:
      center: (3,) cube centre.
      half_extent: half the cube's side.
      count: number of points.
      seed: numpy Generator seed (deterministic).

    Returns:
      (points (count, 3) float64, colors (count, 3) float32 in [0, 1]).
    """
    rng = np.random.default_rng(seed)
    pts = np.asarray(center, np.float64) + rng.uniform(-half_extent, half_extent, size=(int(count), 3))
    cols = rng.uniform(0.0, 1.0, size=(int(count), 3)).astype(np.float32)
    return pts, cols


def random_points_in_frustums(cameras: Sequence[tuple[np.ndarray, np.ndarray, int, int, float, float]],
                              count: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0):
    """Uniform-in-image random points between near and far depth bounds of random cameras.

    Args:
      cameras: sequence of ``(K (3, 3), w2c (4, 4), width, height, near, far)``.
      count: number of points.
      seed: numpy Generator seed.

    Returns:
      (points (count, 3) float64 world coordinates, colors (count, 3) float32 uniform in [0, 1]).
    """
    rng = np.random.default_rng(seed)
    count = int(count)
    which = rng.integers(0, len(cameras), size=count)
    pts = np.empty((count, 3))
    u, v, t = rng.uniform(size=(3, count))
    for c, (K, w2c, w, h, near, far) in enumerate(cameras):
        m = which == c
        if not m.any():
            continue
        pix = np.stack([u[m] * w, v[m] * h, np.ones(m.sum())], axis=-1)
        rays = pix @ np.linalg.inv(K).T
        depth = near + t[m] * (far - near)
        p_cam = rays * depth[:, None]
        c2w = np.linalg.inv(w2c)
        pts[m] = p_cam @ c2w[:3, :3].T + c2w[:3, 3]
    cols = rng.uniform(0.0, 1.0, size=(count, 3)).astype(np.float32)
    return pts, cols


# ----------------------------------------------------------------------------------------------------
# Cache folders
# ----------------------------------------------------------------------------------------------------

_CACHE_ENV = "PATEXGS_CACHE"
_SCENE_CACHE_NAME = ".patexgs_cache"


def _is_writable_dir(path: Path) -> bool:
    """Writable by permission bits *and* by access check (root ignores bits; we do not)."""
    try:
        st = path.stat()
    except OSError:
        return False
    if not stat.S_ISDIR(st.st_mode):
        return False
    if not st.st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH):
        return False
    return os.access(path, os.W_OK)


def _user_cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "patexgs_jax"


def resolve_cache_dir(scene: Path, cache_dir=None) -> Path:
    """The folder where derived data (undistorted images) of ``scene`` is cached.

    In order of precedence:

    1. ``cache_dir`` (argument) -> ``<cache_dir>/<scene name>-<hash of the absolute scene path>``;
    2. the ``PATEXGS_CACHE`` environment variable, used the same way;
    3. ``<scene>/.patexgs_cache`` when the scene folder is writable (by its permission bits too: a
       read-only dataset folder is never written, even by root);
    4. ``$XDG_CACHE_HOME/patexgs_jax/<scene name>-<hash>`` (default ``~/.cache/patexgs_jax/...``).

    The folder is not created here.
    """
    scene = Path(scene).resolve()
    key = f"{scene.name}-{hashlib.sha1(str(scene).encode()).hexdigest()[:12]}"
    if cache_dir is not None:
        return Path(cache_dir).expanduser().resolve() / key
    env = os.environ.get(_CACHE_ENV)
    if env:
        return Path(env).expanduser().resolve() / key
    own = scene / _SCENE_CACHE_NAME
    if own.is_dir() and _is_writable_dir(own):
        return own
    if not own.exists() and _is_writable_dir(scene):
        return own
    return _user_cache_root() / key


def atomic_build_dir(final: Path, build: Callable[[Path], None]) -> Path:
    """Creates folder ``final`` by running ``build(tmp)`` into a temporary sibling, then renaming.

    Nothing partial is left at ``final`` if ``build`` fails or the process is interrupted (a stray
    ``.tmp-*`` sibling may remain after a hard kill; it is ignored and removed by later builds).
    If another process created ``final`` first, its result is kept.

    Returns:
      ``final``.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    for stale in final.parent.glob(f".tmp-{final.name}-*"):
        # Remove leftovers of interrupted builds that are older than an hour (others may be live).
        try:
            if time.time() - stale.stat().st_mtime > 3600:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:
            pass
    tmp = final.parent / f".tmp-{final.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        build(tmp)
        (tmp / "COMPLETE").write_text("ok\n")
        try:
            os.rename(tmp, final)
        except OSError:
            if (final / "COMPLETE").is_file():  # lost a race: keep the other result
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def is_complete_dir(path: Path) -> bool:
    """Whether ``path`` is a finished :func:`atomic_build_dir` result."""
    return (Path(path) / "COMPLETE").is_file()


def fingerprint(*parts) -> str:
    """Short stable hash of strings / paths (files contribute name, size and mtime)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, Path):
            try:
                st = p.stat()
                h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
            except OSError:
                h.update(f"{p}|missing".encode())
        else:
            h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()[:16]


# ----------------------------------------------------------------------------------------------------
# Small shared helpers for the loaders
# ----------------------------------------------------------------------------------------------------


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder`` (by extension, case-insensitive), sorted by name."""
    return sorted((p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                   and not p.name.startswith(".")), key=lambda p: p.name)


def check_size_against_camera(path: Path, file_size: tuple[int, int], cam_size: tuple[float, float],
                              folder_factor: int, what: str) -> tuple[float, float]:
    """Checks an image's (w, h) against its full-resolution camera size divided by ``folder_factor``.

    Mip-NeRF 360's ``images_N`` folders round the size (not floor), so any size within one pixel of
    ``camera_size / N`` is accepted; the returned per-axis ratios ``(w / W, h / H)`` are what the
    intrinsics must be scaled by. With ``folder_factor == 1`` the sizes must match exactly.

    Raises:
      DatasetError naming the file, both sizes and the fix.
    """
    w, h = file_size
    W, H = cam_size
    f = int(folder_factor)
    if f == 1:
        ok = abs(w - W) < 0.5 and abs(h - H) < 0.5
    else:
        ok = abs(w * f - W) < f and abs(h * f - H) < f
    if not ok:
        expect = f"{W:g}x{H:g}" if f == 1 else f"about {W / f:g}x{H / f:g} (= {W:g}x{H:g} / {f})"
        raise DatasetError(
            f"Image {path} is {w}x{h} but {what} expects {expect}. The image does not belong to this "
            f"camera model (wrong folder, rotated/resized image?): replace it with the original, or fix "
            f"the camera model.")
    return w / W, h / H


def orthonormalize_pose(c2w: np.ndarray, source: str) -> np.ndarray:
    """Projects the rotation block of a (4, 4) camera-to-world onto SO(3) (float32 rounding in files).

    Raises:
      DatasetError if the block is far from a rotation (scaled / sheared / reflected pose).
    """
    c2w = np.array(c2w, np.float64)
    R = c2w[:3, :3]
    U, S, Vt = np.linalg.svd(R)
    if not np.all(np.isfinite(c2w)) or np.abs(S - 1).max() > 1e-2 or np.linalg.det(R) < 0:
        raise DatasetError(f"{source}: the camera rotation is not a rotation matrix (singular values "
                           f"{np.round(S, 4).tolist()}, det {np.linalg.det(R):.3g}); poses must be rigid "
                           "camera-to-world transforms.")
    c2w[:3, :3] = U @ Vt
    c2w[3] = [0.0, 0.0, 0.0, 1.0]
    return c2w


def warn(msg: str) -> None:
    """Emits a :class:`DatasetWarning`."""
    warnings.warn(msg, DatasetWarning, stacklevel=3)
