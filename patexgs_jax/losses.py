"""Training losses: photometric (L1 + D-SSIM) and the 2DGS geometric regularisers.

All take (H, W, ...) images of one view and return scalars; jit-friendly and differentiable.
``valid`` (optional (H, W) bool, a top-left block) marks the pixels of a view rendered at a padded
size (:mod:`patexgs_jax.padding`): the loss is then the loss of the cropped images, the padding
taking no part (the same values up to the order of the sums).

The SSIM and normal-consistency terms filter the image: they are summed over strips of rows
(:func:`patexgs_jax.metrics.sum_over_row_strips`), each recomputed for the gradient, so the step's
memory holds a strip's intermediates rather than whole-image ones (tens of times the image for
SSIM's five filtered moments and their gradients).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from .math import safe_normalize
from .metrics import ssim_sum, strip_rows, sum_over_row_strips


def masked_mean(x, valid=None):
    """Mean of (H, W, ...) ``x`` over the pixels where ``valid`` ((H, W) bool); the plain mean
    without a mask."""
    if valid is None:
        return jnp.mean(x)
    per_pixel = x.size // (x.shape[0] * x.shape[1])
    m = valid.reshape(valid.shape + (1,) * (x.ndim - 2))
    return jnp.sum(jnp.where(m, x, 0.0)) / (jnp.sum(valid) * per_pixel).astype(x.dtype)


def photometric(rgb, target, lambda_dssim: float = 0.2, valid=None):
    """``(1 - lambda) L1 + lambda (1 - SSIM)`` (3DGS), with (H, W, 3) images; also returns L1.

    With ``valid``, both images are zeroed outside it, so SSIM's windows at the valid block's edge
    see zeros there exactly as its zero-padded border does on the cropped images. SSIM is summed
    strip by strip (:func:`patexgs_jax.metrics.ssim_sum`)."""
    if valid is None:
        l1 = jnp.mean(jnp.abs(rgb - target))
        s = ssim_sum(rgb, target) / rgb.size
        return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s), l1
    m = valid[..., None]
    rgb, target = jnp.where(m, rgb, 0.0), jnp.where(m, target, 0.0)
    l1 = masked_mean(jnp.abs(rgb - target), valid)
    count = (jnp.sum(valid) * rgb.shape[-1]).astype(rgb.dtype)
    s = ssim_sum(rgb, target, weight=valid) / count
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s), l1


def depth_to_normal(depth, K):
    """Camera-frame surface normals of a depth map, facing the camera.

    Args:
      depth: (H, W) camera z per pixel (pixel centres at j + 0.5, i + 0.5).
      K: (3, 3) intrinsics.
    Returns:
      (H, W, 3) unit normals from central differences of the back-projected points (zero on the
      one-pixel border and where the depth is zero).
    """
    H, W = depth.shape
    x = (jnp.arange(W, dtype=depth.dtype) + 0.5 - K[0, 2]) / K[0, 0]
    y = (jnp.arange(H, dtype=depth.dtype) + 0.5 - K[1, 2]) / K[1, 1]
    pts = jnp.stack([x[None, :] * depth, y[:, None] * depth, depth], axis=-1)
    dx = pts[1:-1, 2:] - pts[1:-1, :-2]
    dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
    n = safe_normalize(jnp.cross(dy, dx))  # x right, y down, z forward: faces the camera
    valid = (depth[1:-1, 1:-1] > 0)[..., None]
    return jnp.pad(jnp.where(valid, n, 0.0), ((1, 1), (1, 1), (0, 0)))


def normal_consistency(rendered_normal, depth, alpha, K, valid=None):
    """2DGS normal consistency: mean of ``1 - <n_rendered, alpha * n_from_depth>``.

    ``rendered_normal`` (H, W, 3) is the renderer's alpha-weighted normal; the depth normal
    (:func:`depth_to_normal` of ``depth`` (H, W)) is weighted by the (gradient-stopped) ``alpha``
    (H, W) as 2DGS does, so empty pixels add a constant 1 and no gradient. With ``valid`` the depth
    normal is zero on the valid block's one-pixel border, as on the cropped map. Summed strip by
    strip (:func:`patexgs_jax.metrics.sum_over_row_strips`).
    """
    H, W = depth.shape
    if valid is None:
        valid = jnp.ones((H, W), bool)
    dt = depth.dtype
    x = (jnp.arange(W, dtype=dt) + 0.5 - K[0, 2]) / K[0, 0]
    cols = jnp.arange(W)

    def strip(xs, row0):
        n_r, d, a, v = xs  # (R + 2, W, ...): one row of context each side
        d = jnp.where(v, d, 0.0)
        rows = row0 + jnp.arange(d.shape[0])
        y = (rows.astype(dt) + 0.5 - K[1, 2]) / K[1, 1]
        pts = jnp.stack([x[None, :] * d, y[:, None] * d, d], axis=-1)
        dx = pts[1:-1, 2:] - pts[1:-1, :-2]
        dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
        n = safe_normalize(jnp.cross(dy, dx))  # x right, y down, z forward: faces the camera
        n = jnp.where((d[1:-1, 1:-1] > 0)[..., None], n, 0.0)
        n = jnp.pad(n, ((0, 0), (1, 1), (0, 0)))
        # the depth normal needs both neighbours: zero on the image's and the valid block's border
        right = jnp.pad(v[1:-1, 1:], ((0, 0), (0, 1)))
        inner = (v[1:-1] & v[2:] & right & (rows[1:-1] >= 1)[:, None] & (cols >= 1)[None, :]
                 & (cols <= W - 2)[None, :])
        surf = jnp.where(inner[..., None], n * lax.stop_gradient(a[1:-1])[..., None], 0.0)
        per_pixel = 1.0 - jnp.sum(n_r[1:-1] * surf, axis=-1)
        return jnp.sum(jnp.where(v[1:-1], per_pixel, 0.0))

    total = sum_over_row_strips(strip, (rendered_normal, depth, alpha, valid), rows=strip_rows(W), halo=1)
    return total / jnp.sum(valid).astype(dt)


def distortion(dist_map, valid=None):
    """Mean of the renderer's per-pixel 2DGS depth-distortion term."""
    return masked_mean(dist_map, valid)
