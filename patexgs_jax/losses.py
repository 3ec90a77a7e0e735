"""Training losses: photometric (L1 + D-SSIM) and the 2DGS geometric regularisers.

All take (H, W, ...) images of one view and return scalars; jit-friendly and differentiable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .math import safe_normalize
from .metrics import ssim


def photometric(rgb, target, lambda_dssim: float = 0.2):
    """``(1 - lambda) L1 + lambda (1 - SSIM)`` (3DGS), with (H, W, 3) images; also returns L1."""
    l1 = jnp.mean(jnp.abs(rgb - target))
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(rgb, target)), l1


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


def normal_consistency(rendered_normal, depth, alpha, K):
    """2DGS normal consistency: mean of ``1 - <n_rendered, alpha * n_from_depth>``.

    ``rendered_normal`` is the renderer's alpha-weighted normal; the depth normal is weighted by the
    (gradient-stopped) alpha as 2DGS does, so empty pixels add a constant 1 and no gradient.
    """
    surf = depth_to_normal(depth, K) * jax.lax.stop_gradient(alpha)[..., None]
    return jnp.mean(1.0 - jnp.sum(rendered_normal * surf, axis=-1))


def distortion(dist_map):
    """Mean of the renderer's per-pixel 2DGS depth-distortion term."""
    return jnp.mean(dist_map)
