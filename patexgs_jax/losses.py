"""Training losses: photometric (L1 + D-SSIM) and the 2DGS geometric regularisers.

All take (H, W, ...) images of one view and return scalars; jit-friendly and differentiable.
``valid`` (optional (H, W) bool, a top-left block) marks the pixels of a view rendered at a padded
size (:mod:`patexgs_jax.buckets`): the loss is then the loss of the cropped images, the padding
taking no part (the same values up to the order of the sums).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .math import safe_normalize
from .metrics import ssim


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
    see zeros there exactly as its zero-padded border does on the cropped images."""
    if valid is None:
        l1 = jnp.mean(jnp.abs(rgb - target))
        return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(rgb, target)), l1
    m = valid[..., None]
    rgb, target = jnp.where(m, rgb, 0.0), jnp.where(m, target, 0.0)
    l1 = masked_mean(jnp.abs(rgb - target), valid)
    _, ssim_map = ssim(rgb, target, return_map=True)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - masked_mean(ssim_map, valid)), l1


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

    ``rendered_normal`` is the renderer's alpha-weighted normal; the depth normal is weighted by the
    (gradient-stopped) alpha as 2DGS does, so empty pixels add a constant 1 and no gradient. With
    ``valid``, the depth normal is zero on the valid block's one-pixel border, as on the cropped map.
    """
    if valid is not None:
        depth = jnp.where(valid, depth, 0.0)
        inner = jnp.pad(valid[1:-1, 1:-1] & valid[2:, 1:-1] & valid[1:-1, 2:], ((1, 1), (1, 1)))
    surf = depth_to_normal(depth, K) * jax.lax.stop_gradient(alpha)[..., None]
    if valid is not None:
        surf = jnp.where(inner[..., None], surf, 0.0)
    return masked_mean(1.0 - jnp.sum(rendered_normal * surf, axis=-1), valid)


def distortion(dist_map, valid=None):
    """Mean of the renderer's per-pixel 2DGS depth-distortion term."""
    return masked_mean(dist_map, valid)
