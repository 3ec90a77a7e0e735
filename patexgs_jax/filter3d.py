"""Mip-Splatting's 3D smoothing filter (Yu et al., CVPR 2024, Sec. 5.1): per 3D Gaussian, the highest
sampling rate at which any training view sees it bounds the frequencies it may represent.

For Gaussian k the sampling rate in view n is ``focal_n / depth_n`` (pixels per world unit at its
centre's camera z), counted in the views whose frustum holds the centre (depth above
:data:`MIN_DEPTH`, and the projected centre within the image widened by :data:`FRUSTUM_MARGIN`
of its size on each side, as the reference code); ``nu_k`` is the largest. The filter is an
isotropic Gaussian of variance ``FILTER_SCALE / nu_k^2`` (world units^2) convolved with the
Gaussian: ``Sigma + f I``, the opacity times ``sqrt(det Sigma / det(Sigma + f I))`` so the integral
is kept (:mod:`patexgs_jax.rendering.gaussian3d` applies it from ``Scene.filter3d``). A Gaussian no
view sees gets the lowest rate of those seen, as the reference code.

2D splats (``patexgs+filter3d``) take the same f in their plane: a surfel has no extent along its
normal, so its Gaussian's scales become sqrt(s^2 + f) and its opacity is scaled by
prod_i s_i / sqrt(s_i^2 + f). Untextured (its 2DGS stage 1), the splat is drawn with those scales
(:func:`patexgs_jax.rendering.projection.filtered_log_scales`); textured, only with the prefiltered
coverage, which folds the filter into its kernel while the textures keep their extent of +-3
scales (:func:`patexgs_jax.rendering.projection.plane_filter`). As in Mip-Splatting the filter acts
from the first step, so such a method trains its own stage 1.

The reference code (autonomousvision/mip-splatting, ``compute_3D_filter``) takes the smallest depth
over the views and divides by the largest focal length of all of them; here the rate is the
largest focal / depth over the views, the paper's definition (the same for views of one focal
length). The filter is recomputed after every densification and, after densification stops, every
densification interval (100 steps at the paper's scale, as the reference) up to one interval before
the end (:class:`patexgs_jax.training.strategies.SmoothingFilter`).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np

from .camera import Camera
from .scene import Scene

__all__ = ["FILTER_SCALE", "FRUSTUM_MARGIN", "MIN_DEPTH", "bake", "filter_variance", "opacity_factor"]

#: Mip-Splatting's filter scale s: the filter's variance is s / nu^2 (nu the sampling rate).
FILTER_SCALE = 0.2
#: Views count for a Gaussian only where its centre's camera z exceeds this (the reference's 0.2).
MIN_DEPTH = 0.2
#: ... and its projected centre lies within the image widened by this share of its size per side.
FRUSTUM_MARGIN = 0.15


def filter_variance(means, cameras: Sequence[Camera]) -> np.ndarray:
    """(C,) float32 the 3D filter's variance of Gaussians at ``means`` (C, 3) for the training
    ``cameras`` (module docstring); zeros if no view sees any of them."""
    means = np.asarray(means, np.float64)
    rate = np.zeros(means.shape[0])
    seen = np.zeros(means.shape[0], bool)
    for cam in cameras:
        K = np.asarray(cam.K, np.float64)
        w2c = np.asarray(cam.world_to_camera, np.float64)
        p = means @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.maximum(p[:, 2], 1e-3)
        q = p @ K.T
        x, y = q[:, 0] / z, q[:, 1] / z
        mx, my = FRUSTUM_MARGIN * cam.width, FRUSTUM_MARGIN * cam.height
        ok = ((p[:, 2] > MIN_DEPTH) & (x >= -mx) & (x <= cam.width + mx) & (y >= -my)
              & (y <= cam.height + my))
        rate = np.where(ok, np.maximum(rate, max(K[0, 0], K[1, 1]) / z), rate)
        seen |= ok
    if not seen.any():
        return np.zeros(means.shape[0], np.float32)
    rate = np.where(seen, rate, rate[seen].min())
    return (FILTER_SCALE / np.square(rate)).astype(np.float32)


def opacity_factor(log_scales, filter3d) -> np.ndarray:
    """(C,) float64 ``sqrt(det Sigma / det(Sigma + f I))`` = prod_i s_i / sqrt(s_i^2 + f) (host side;
    log scales (C, 3), or (C, 2) for 2D splats: the factor in their plane)."""
    ls = np.asarray(log_scales, np.float64)
    return np.exp(np.sum(ls - _filtered(ls, filter3d), axis=-1))


def _filtered(ls: np.ndarray, filter3d) -> np.ndarray:
    """log sqrt(s^2 + f) of log scales ``ls`` (C, 3) or (C, 2) (ls itself where f is 0)."""
    f = np.asarray(filter3d, np.float64)[:, None]
    return np.where(f > 0, 0.5 * np.logaddexp(2.0 * ls, np.log(np.where(f > 0, f, 1.0))), ls)


def with_filter(scene: Scene, cameras: Sequence[Camera]) -> Scene:
    """``scene`` with its 3D filter recomputed from its means and the training ``cameras``."""
    return scene.replace(filter3d=jax.device_put(filter_variance(scene.means, cameras)))


def bake(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The (C, 3) log scales and (C,) opacity logits of a 3D scene with its 3D filter folded in
    (scales sqrt(s^2 + f), opacity times :func:`opacity_factor`), as Mip-Splatting's fused PLY holds
    them; the scene's own where it has no filter."""
    ls = np.asarray(scene.log_scales, np.float64)
    logits = np.asarray(scene.opacity_logits, np.float64)
    if scene.filter3d is None:
        return ls.astype(np.float32), logits.astype(np.float32)
    ls_f = _filtered(ls, scene.filter3d)
    op = 1.0 / (1.0 + np.exp(-logits)) * opacity_factor(ls, scene.filter3d)
    op = np.clip(op, 1e-7, 1 - 1e-7)
    return ls_f.astype(np.float32), (np.log(op) - np.log1p(-op)).astype(np.float32)
