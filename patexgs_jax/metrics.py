"""Image-quality metrics (PSNR, SSIM), the SSIM training loss and model-storage accounting.

Conventions, fixed for the whole package:

* Images are float arrays in ``[0, 1]`` with shape ``(H, W, 3)`` (one image) or ``(B, H, W, 3)``
  (a batch; every per-image metric then returns shape ``(B,)``). Nothing here clamps or quantises:
  3DGS evaluates 8-bit PNGs of renders clamped to ``[0, 1]``; do that before calling if you need to
  reproduce such numbers.
* **PSNR** is computed per image from the mean squared error over all pixels and channels, and a
  data set's PSNR is the mean of the per-image values (:func:`mean_psnr`, the 3DGS protocol), not the
  PSNR of the pooled MSE. A perfect match gives ``+inf`` (no cap), and so does any mean containing one.
* **SSIM** uses an 11x11 Gaussian window (sigma 1.5, normalised to sum 1), ``C1 = (0.01 L)^2``,
  ``C2 = (0.03 L)^2`` with ``L = max_val``, population (biased) local statistics, per channel, and
  the mean of the SSIM map over pixels and channels. Two border conventions:

  - ``border="zero_pad"`` (default): the 3DGS training/evaluation convention. The window sums are
    taken over the image zero-padded by ``window_size // 2`` on every side, so the map has the
    image's size and the border pixels (whose windows reach the zero padding) are averaged in.
  - ``border="crop"``: scikit-image's convention (``structural_similarity`` with
    ``gaussian_weights=True, sigma=1.5, use_sample_covariance=False``): only pixels whose whole
    window lies inside the image are averaged, i.e. the map is cropped by ``(window_size - 1) // 2``.
    (skimage filters with reflect padding and then crops, so the padding never reaches the kept
    pixels; the two agree to float rounding.)

  The Gaussian filter is separable and is applied as two 1-D passes written as a weighted sum of
  shifted slices, which XLA's CPU backend runs much faster than ``lax.conv_general_dilated`` with a
  depthwise kernel (docs/performance.md); zero padding of each 1-D pass is exactly the zero
  padding of the 2-D window.
* **Training loss.** 3DGS trains with ``(1 - lambda) * L1 + lambda * (1 - SSIM)`` and
  ``lambda = 0.2``, SSIM with the zero-pad border; :func:`dssim_loss` is that ``1 - SSIM`` term (not
  the ``(1 - SSIM) / 2`` that some papers call D-SSIM); the whole photometric loss, as the step
  computes it (SSIM summed in strips, optionally masked), is :func:`patexgs_jax.losses.photometric`.
* **Storage** is reported in MiB: ``1 MB = 2**20 bytes`` (what ``bytes / 1024 / 1024`` gives, as
  3DGS-compression papers compute model sizes). See :func:`storage_mb`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = [
    "BYTES_PER_MB",
    "FLOATS_PER_GAUSSIAN_BASE",
    "FLOATS_PER_RGBA_TEXEL",
    "STRIP_PIXELS",
    "psnr",
    "mean_psnr",
    "gaussian_window_1d",
    "ssim",
    "ssim_sum",
    "strip_rows",
    "sum_over_row_strips",
    "dssim_loss",
    "mb_to_texels",
    "scene_storage",
    "storage_mb",
    "texel_count",
    "texels_to_mb",
]

BYTES_PER_MB = 2**20
"""One "MB" in this package's storage numbers: a mebibyte."""

FLOATS_PER_GAUSSIAN_BASE = 3 + 2 + 4 + 1
"""Per-Gaussian floats besides colour: mean 3, scales 2 (2D Gaussians), rotation quaternion 4, opacity 1."""

FLOATS_PER_RGBA_TEXEL = 4
"""Floats per RGBA texel (3 RGB + 1 alpha); the unit of texel budgets (:mod:`patexgs_jax.adaptive`)."""


# --------------------------------------------------------------------------------------------- PSNR


def _is_jax(x) -> bool:
    return isinstance(x, jax.Array)


def _check_image_pair(img, ref) -> None:
    if img.shape != ref.shape:
        raise ValueError(f"Image shapes differ: {img.shape} vs {ref.shape}.")
    if img.ndim not in (3, 4):
        raise ValueError(f"Expected an image (H, W, C) or a batch (B, H, W, C), got shape {img.shape}.")


def psnr(img, ref, max_val: float = 1.0):
    """Peak signal-to-noise ratio in dB, per image.

    ``10 log10(max_val^2 / MSE)`` with the MSE over all pixels and channels of each image.

    Args:
      img, ref: ``(H, W, C)`` or ``(B, H, W, C)`` arrays of the same shape, float in ``[0, max_val]``.
      max_val: the peak value (data range).

    Returns:
      A scalar for one image, shape ``(B,)`` for a batch. With numpy inputs the computation is done in
      float64 and numpy values are returned; if either input is a jax array it is done with
      ``jax.numpy`` (jit/grad-friendly) in the inputs' float dtype. Identical images give ``+inf``.
    """
    if _is_jax(img) or _is_jax(ref):
        xp = jnp
        img, ref = jnp.asarray(img), jnp.asarray(ref)
        dtype = jnp.result_type(img.dtype, ref.dtype, jnp.float32)
        img, ref = img.astype(dtype), ref.astype(dtype)
    else:
        xp = np
        img, ref = np.asarray(img, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    _check_image_pair(img, ref)
    mse = xp.mean((img - ref) ** 2, axis=(-3, -2, -1))
    with np.errstate(divide="ignore"):
        return 10.0 * xp.log10(max_val**2 / mse)


def mean_psnr(pairs: Iterable[tuple[object, object]], max_val: float = 1.0) -> float:
    """Mean of per-image PSNR over ``(img, ref)`` pairs (each a single image or a batch), in float64.

    A batch contributes one value per image. Returns ``+inf`` if any image matches exactly.
    """
    values = [np.atleast_1d(psnr(np.asarray(a), np.asarray(b), max_val)) for a, b in pairs]
    if not values:
        raise ValueError("mean_psnr needs at least one image pair.")
    return float(np.mean(np.concatenate(values)))


# --------------------------------------------------------------------------------------------- SSIM


def gaussian_window_1d(window_size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """The normalised 1-D Gaussian ``g[k] ∝ exp(-(k - window_size // 2)^2 / (2 sigma^2))`` (float64).

    The 2-D SSIM window is ``outer(g, g)``.
    """
    if window_size < 1 or window_size % 2 != 1:
        raise ValueError(f"window_size must be a positive odd integer, got {window_size}.")
    k = np.arange(window_size, dtype=np.float64) - window_size // 2
    g = np.exp(-(k**2) / (2.0 * sigma**2))
    return g / g.sum()


def _filter_1d(x: jax.Array, g: np.ndarray, axis: int, pad: int) -> jax.Array:
    """Correlates ``x`` with the 1-D kernel ``g`` along ``axis``, zero-padding ``pad`` on both sides."""
    if pad:
        widths = [(0, 0)] * x.ndim
        widths[axis] = (pad, pad)
        x = jnp.pad(x, widths)
    n = x.shape[axis] - len(g) + 1
    out = lax.slice_in_dim(x, 0, n, axis=axis) * jnp.asarray(g[0], x.dtype)
    for k in range(1, len(g)):
        out = out + lax.slice_in_dim(x, k, k + n, axis=axis) * jnp.asarray(g[k], x.dtype)
    return out


#: Pixels per strip of the strip-wise SSIM and losses (:func:`sum_over_row_strips`): each strip's
#: filter intermediates and their gradients are a few tens of times its pixels, so whole-image
#: filters of a 12 MP image would hold gigabytes at once.
STRIP_PIXELS = 1 << 18


def strip_rows(width: int, pixels: int | None = None, min_rows: int = 16) -> int:
    """Rows per strip of an image ``width`` pixels wide: about ``pixels`` (default
    :data:`STRIP_PIXELS`) pixels a strip, at least ``min_rows`` rows."""
    pixels = STRIP_PIXELS if pixels is None else pixels
    return max(int(min_rows), -(-int(pixels) // max(int(width), 1)))


def sum_over_row_strips(fn, arrays, *, rows: int, halo: int):
    """``sum_s fn(strip_s, row0_s)`` over horizontal strips of images, one strip in memory at a time.

    Args:
      fn: ``fn(strips, row0) -> ()`` scalar, with ``strips`` a tuple of ``(rows + 2 halo, W, ...)``
        blocks (the strip's rows, ``halo`` rows above and below it, zeros beyond the image) and
        ``row0`` (() int32, traced) the image row of the block's first row (``-halo`` for the first).
      arrays: tuple of (H, W, ...) arrays of the same H.
      rows: rows per strip (>= halo; see :func:`strip_rows`).
      halo: rows of context each side of a strip.
    Returns:
      The sum, differentiable. With more than one strip, each strip is a ``jax.checkpoint``-ed
      step of a ``lax.map``: the gradient recomputes it, so memory holds the inputs, their
      cotangents and one strip's intermediates, whatever the image size.
    """
    H = arrays[0].shape[0]
    rows = int(rows)
    if rows < max(halo, 1):
        raise ValueError(f"strip rows ({rows}) must be at least the halo ({halo}) and 1.")
    S = -(-H // rows)

    def pad(x, top, bottom):  # rows only
        return jnp.pad(x, [(top, bottom)] + [(0, 0)] * (x.ndim - 1))

    if S == 1:
        return fn(tuple(pad(x, halo, halo) for x in arrays), jnp.int32(-halo))

    def strips(x):  # (H, W, ...) -> (S, rows + 2 halo, W, ...)
        main = pad(x, 0, S * rows - H).reshape((S, rows) + x.shape[1:])
        if not halo:
            return main
        zeros = jnp.zeros((1, halo) + x.shape[1:], x.dtype)
        top = jnp.concatenate([zeros, main[:-1, rows - halo:]], axis=0)
        bottom = jnp.concatenate([main[1:, :halo], zeros], axis=0)
        return jnp.concatenate([top, main, bottom], axis=1)

    row0 = jnp.arange(S, dtype=jnp.int32) * rows - halo
    body = jax.checkpoint(lambda xs: fn(xs[0], xs[1]))
    return jnp.sum(lax.map(body, (tuple(strips(x) for x in arrays), row0)))


def _ssim_map(img, ref, g, row_pad: int, col_pad: int, c1: float, c2: float):
    """The SSIM map of ``(..., H, W, C)`` images: the window sums over rows zero-padded by
    ``row_pad`` and columns by ``col_pad`` (the map has ``H + 2 row_pad - len(g) + 1`` rows)."""
    # One filtering pass for all five local moments: stack them on the channel axis.
    c = img.shape[-1]
    stacked = jnp.concatenate([img, ref, img * img, ref * ref, img * ref], axis=-1)
    blurred = _filter_1d(_filter_1d(stacked, g, axis=-3, pad=row_pad), g, axis=-2, pad=col_pad)
    mu_x, mu_y, e_xx, e_yy, e_xy = (blurred[..., i * c : (i + 1) * c] for i in range(5))
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov_xy = e_xy - mu_x * mu_y
    return ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / (
        (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    )


def ssim_sum(img, ref, weight=None, *, max_val: float = 1.0, window_size: int = 11, sigma: float = 1.5,
             k1: float = 0.01, k2: float = 0.03, rows: int | None = None):
    """Sum over pixels and channels of the zero-pad SSIM map (see :func:`ssim`), computed in strips
    of rows (:func:`sum_over_row_strips`), so that memory does not grow with the filters'
    whole-image intermediates.

    Args:
      img, ref: (H, W, C) float arrays in ``[0, max_val]``.
      weight: optional (H, W) per-pixel weight (bool or float) of the map.
      rows: rows per strip; default :func:`strip_rows` of the width.
    Returns:
      () the weighted sum (divide by ``C`` times the weights' sum, or by ``H W C``, for the mean).
    """
    img, ref = jnp.asarray(img), jnp.asarray(ref)
    _check_image_pair(img, ref)
    if img.ndim != 3:
        raise ValueError(f"ssim_sum takes one (H, W, C) image, got shape {img.shape}.")
    g = gaussian_window_1d(window_size, sigma)
    half = window_size // 2
    c1, c2 = (k1 * max_val) ** 2, (k2 * max_val) ** 2
    arrays = (img, ref) if weight is None else (img, ref, jnp.asarray(weight))

    H = img.shape[0]

    def strip(xs, row0):
        smap = _ssim_map(xs[0], xs[1], g, 0, half, c1, c2)
        if weight is None:  # rows past the image (the last strip's padding) are left out
            inside = row0 + half + jnp.arange(smap.shape[0]) < H
            return jnp.sum(jnp.where(inside[:, None, None], smap, 0.0))
        return jnp.sum(smap * xs[2][half:half + smap.shape[0], :, None].astype(smap.dtype))

    rows = strip_rows(img.shape[1]) if rows is None else rows
    return sum_over_row_strips(strip, arrays, rows=max(rows, half), halo=half)


@functools.partial(
    jax.jit, static_argnames=("border", "max_val", "window_size", "sigma", "k1", "k2", "return_map")
)
def ssim(
    img,
    ref,
    *,
    border: str = "zero_pad",
    max_val: float = 1.0,
    window_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    return_map: bool = False,
):
    """Structural similarity (Wang et al. 2004) with a Gaussian window, differentiable and jitted.

    Args:
      img, ref: ``(H, W, C)`` or ``(B, H, W, C)`` float arrays of the same shape in ``[0, max_val]``.
        Computed in float32 (float64 if the inputs are float64 and x64 is enabled).
      border: ``"zero_pad"`` (3DGS: zero padding by ``window_size // 2``, map of the image's size) or
        ``"crop"`` (scikit-image: only windows fully inside the image; needs ``H, W >= window_size``).
      max_val: data range ``L`` in ``C1 = (k1 L)^2, C2 = (k2 L)^2``.
      window_size, sigma: the Gaussian window (defaults 11 and 1.5).
      return_map: also return the SSIM map, shape ``(..., H', W', C)``.

    Returns:
      Mean SSIM over pixels and channels: a scalar for one image, ``(B,)`` for a batch (and the map if
      ``return_map``). One image with the zero-pad border and no map is computed in strips of
      rows (:func:`ssim_sum`), whose memory does not grow with the image's filter intermediates.
    """
    img, ref = jnp.asarray(img), jnp.asarray(ref)
    dtype = jnp.result_type(img.dtype, ref.dtype, jnp.float32)
    img, ref = img.astype(dtype), ref.astype(dtype)
    _check_image_pair(img, ref)
    if border not in ("zero_pad", "crop"):
        raise ValueError(f'border must be "zero_pad" or "crop", got {border!r}.')
    h, w = img.shape[-3], img.shape[-2]
    if border == "crop" and (h < window_size or w < window_size):
        raise ValueError(f"border='crop' needs images of at least {window_size}x{window_size}, got {h}x{w}.")
    if border == "zero_pad" and img.ndim == 3 and not return_map and h > strip_rows(w):
        total = ssim_sum(img, ref, max_val=max_val, window_size=window_size, sigma=sigma, k1=k1, k2=k2)
        return total / (h * w * img.shape[-1])

    g = gaussian_window_1d(window_size, sigma)
    pad = window_size // 2 if border == "zero_pad" else 0
    ssim_map = _ssim_map(img, ref, g, pad, pad, (k1 * max_val) ** 2, (k2 * max_val) ** 2)
    value = jnp.mean(ssim_map, axis=(-3, -2, -1))
    return (value, ssim_map) if return_map else value


def dssim_loss(img, ref, *, border: str = "zero_pad") -> jax.Array:
    """The 3DGS structural loss term ``1 - SSIM`` (zero-pad border), averaged over a batch."""
    return 1.0 - jnp.mean(ssim(img, ref, border=border))


# ------------------------------------------------------------------------------------------ storage


def texel_count(sizes) -> int:
    """Total number of texels of a list of per-Gaussian textures.

    Args:
      sizes: per-Gaussian texture sizes, either side lengths ``[s0, s1, ...]`` of square textures
        (``s * s`` texels each) or ``[(h0, w0), (h1, w1), ...]`` pairs (or an array of shape
        ``(N,)`` / ``(N, 2)``). A size of 0 means no texture. Mip levels derived at render time are
        not stored and not counted.
    """
    arr = np.asarray(sizes, dtype=np.int64)
    if arr.size == 0:
        return 0
    if np.any(arr < 0):
        raise ValueError("Texture sizes must be non-negative.")
    if arr.ndim == 1:
        return int(np.sum(arr * arr))
    if arr.ndim == 2 and arr.shape[1] == 2:
        return int(np.sum(arr[:, 0] * arr[:, 1]))
    raise ValueError(f"sizes must be a list of side lengths or of (h, w) pairs, got an array of shape {arr.shape}.")


def storage_mb(
    num_gaussians: int,
    sh_coeffs: int,
    texels_rgb: int,
    texels_alpha: int,
    bytes_per_value: int = 4,
) -> float:
    """Size in MiB (``2**20`` bytes) of the saved model's values.

    Counts, per Gaussian, ``3 + 2 + 4 + 1`` floats (mean, 2-D scales, rotation quaternion, opacity)
    plus ``3 * sh_coeffs`` colour floats (``sh_coeffs`` = SH coefficients per colour channel:
    1 for degree 0, 16 for degree 3), then 3 values per RGB texel and 1 per alpha texel, all at
    ``bytes_per_value`` bytes. Not counted: per-Gaussian texture-size metadata, file headers.

    Example: 100 000 Gaussians with degree-3 SH and no textures:
    ``100_000 * (10 + 48) * 4 / 2**20 = 22.125...`` MiB.
    """
    for name, v in (("num_gaussians", num_gaussians), ("sh_coeffs", sh_coeffs),
                    ("texels_rgb", texels_rgb), ("texels_alpha", texels_alpha)):
        if int(v) != v or v < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {v!r}.")
    if bytes_per_value <= 0:
        raise ValueError(f"bytes_per_value must be positive, got {bytes_per_value!r}.")
    values = int(num_gaussians) * (FLOATS_PER_GAUSSIAN_BASE + 3 * int(sh_coeffs))
    values += 3 * int(texels_rgb) + int(texels_alpha)
    return values * bytes_per_value / BYTES_PER_MB


def mb_to_texels(mb: float, floats_per_texel: int = FLOATS_PER_RGBA_TEXEL, bytes_per_value: int = 4) -> int:
    """Texels that fit in ``mb`` MiB (floor), consistent with :func:`storage_mb`.

    With the default 4 floats (RGBA) a texel costs 16 bytes, so ``storage_mb(0, 0, t, t) <= mb`` for
    ``t = mb_to_texels(mb)``.
    """
    if not mb >= 0 or floats_per_texel <= 0 or bytes_per_value <= 0:
        raise ValueError("mb must be >= 0 and floats_per_texel, bytes_per_value positive.")
    return int(math.floor(mb * BYTES_PER_MB / (floats_per_texel * bytes_per_value) + 1e-9))


def texels_to_mb(texels: int, floats_per_texel: int = FLOATS_PER_RGBA_TEXEL, bytes_per_value: int = 4) -> float:
    """MiB taken by ``texels`` texels of ``floats_per_texel`` floats (inverse of :func:`mb_to_texels`)."""
    return int(texels) * floats_per_texel * bytes_per_value / BYTES_PER_MB


def scene_storage(scene) -> dict:
    """What a scene stores, for its active Gaussians: ``{"gaussians", "texels_rgb", "texels_alpha",
    "texels", "storage_mb"}`` (texels as :meth:`patexgs_jax.Scene.texel_count`, storage as
    :func:`storage_mb`)."""
    n = scene.num_active()
    texels = scene.texel_count()
    return dict(gaussians=n, texels_rgb=texels["rgb"], texels_alpha=texels["alpha"],
                texels=texels["rgb"] + texels["alpha"],
                storage_mb=storage_mb(n, int(scene.sh.shape[1]), texels["rgb"], texels["alpha"]))
