"""Image files: reading (RGBA compositing), area resizing, box downsampling, header probes, writing,
and the bounded LRU cache of decoded images that a dataset's views share.

Host-side numpy and Pillow only. Images are (H, W, 3) float32 in [0, 1] once read.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt
import PIL.Image

from .errors import DatasetError

__all__ = [
    "IMAGE_EXTENSIONS",
    "DEFAULT_IMAGE_CACHE_SIZE",
    "DEFAULT_IMAGE_CACHE_BYTES",
    "ImageCache",
    "area_resize",
    "box_downsample",
    "decode_problem",
    "image_loader",
    "image_size",
    "list_images",
    "probe_image",
    "read_image",
    "save_image",
]

#: File extensions (lower case) recognised as images when listing folders.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
#: Default number of decoded images kept in memory per dataset.
DEFAULT_IMAGE_CACHE_SIZE = 64
#: Default bound on the bytes of the decoded images kept in memory per dataset (2 GiB).
DEFAULT_IMAGE_CACHE_BYTES = 2 << 30


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


def decode_problem(path) -> str | None:
    """Why the image file at ``path`` cannot be decoded (missing, corrupt or truncated), or None.

    Decodes the whole file, which a header probe does not: a truncated JPEG has a valid header.
    JPEGs decode at 1/8 of their size (libjpeg's DCT scaling still reads every entropy-coded byte,
    so truncation and corrupt data are found) to keep the check of a large capture to seconds."""
    path = Path(path)
    if not path.is_file():
        return "does not exist"
    try:
        with PIL.Image.open(path) as im:
            if im.format == "JPEG":
                im.draft("RGB", (max(1, im.size[0] // 8), max(1, im.size[1] // 8)))
            im.load()
    except (PIL.UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        return f"cannot be decoded ({type(e).__name__}: {e})"
    return None


def image_loader(path, factor: int, background, size: tuple[int, int] | None = None):
    """A zero-argument function that reads ``path`` (RGBA composited on ``background``) and
    box-downsamples it by ``factor``, or resizes it to ``size`` = (width, height) with an area
    filter (see :func:`read_image`): the lazy loader a :class:`View` holds."""
    if size is not None:
        return lambda: read_image(path, background, size=size)
    return lambda: box_downsample(read_image(path, background), factor)


def box_downsample(image: np.ndarray, factor: int, dtype: npt.DTypeLike = np.float32) -> np.ndarray:
    """Box (area) downsampling by an integer factor, matching :meth:`Camera.scaled`.

    The image is cropped to a multiple of ``factor`` (the partial last row/column block is dropped) and
    each ``factor x factor`` block is averaged, so output pixel (i, j) covers input pixels
    ``[f*i, f*(i+1)) x [f*j, f*(j+1))`` and continuous coordinates are simply divided by ``factor``.

    Args:
      image: (H, W) or (H, W, C) array.
      factor: positive integer.
      dtype: of the result: float32 (what views hold), or e.g. uint8 (rounded to nearest) for files.

    Returns:
      (H // factor, W // factor[, C]) array of ``dtype`` (the input itself, as ``dtype``, when
      factor == 1).
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"downsampling factor must be a positive integer, got {factor}.")
    image = np.asarray(image)
    dtype = np.dtype(dtype)
    if factor == 1:
        return image.astype(dtype, copy=False)
    h, w = image.shape[0] // factor, image.shape[1] // factor
    if h < 1 or w < 1:
        raise ValueError(f"factor {factor} leaves no pixel of a {image.shape[1]}x{image.shape[0]} image.")
    # float32 blocks for float32 results (a quarter of the float64 copy); sums in float64 either way
    x = image[: h * factor, : w * factor].astype(np.float32 if dtype == np.float32 else np.float64, copy=False)
    mean = x.reshape((h, factor, w, factor) + image.shape[2:]).mean(axis=(1, 3), dtype=np.float64)
    if dtype == np.uint8:
        mean = np.clip(np.round(mean), 0, 255)
    return mean.astype(dtype)


def save_image(image: np.ndarray, path, jpeg_quality: int = 95) -> None:
    """Saves an (H, W, 3) uint8 image; the format follows the suffix (PNG or JPEG)."""
    path = Path(path)
    im = PIL.Image.fromarray(np.asarray(image, np.uint8))
    if path.suffix.lower() in (".jpg", ".jpeg"):
        im.save(path, quality=jpeg_quality)
    else:
        im.save(path)


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


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder`` (by extension, case-insensitive), sorted by name."""
    return sorted((p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                   and not p.name.startswith(".")), key=lambda p: p.name)
