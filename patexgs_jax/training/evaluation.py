"""Which views can be trained on or scored, and the mean PSNR / SSIM a run reports."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import buckets, compiled
from ..rendering import RenderConfig
from ..scene import Scene

__all__ = ["camera_problem", "evaluate", "image_problem", "view_problem"]


def image_problem(image) -> str | None:
    """Why an image cannot be trained on (empty or non-finite), or None."""
    if image is None or np.size(image) == 0 or not np.all(np.isfinite(image)):
        return "image is empty or not finite"
    return None


def camera_problem(camera) -> str | None:
    """Why a camera cannot be trained on (non-finite), or None."""
    if not (np.all(np.isfinite(np.asarray(camera.K))) and np.all(np.isfinite(np.asarray(camera.world_to_camera)))):
        return "camera is not finite"
    return None


def view_problem(camera, image) -> str | None:
    """Why a view cannot be used (empty or non-finite image, non-finite camera), or None."""
    return image_problem(image) or camera_problem(camera)


def evaluate(scene: Scene, views, render_config: RenderConfig) -> dict:
    """Mean PSNR and SSIM over views, renders clipped to [0, 1]. Views are rendered at their size
    buckets (:class:`patexgs_jax.buckets.ViewRenderer`: a few programs, released at the end)."""
    from ..metrics import psnr, ssim

    ps, ss = [], []
    # as in training: empty or non-finite images and cameras are left out
    views = [v for v in views if view_problem(v.camera, v.image) is None]
    with buckets.ViewRenderer(scene, render_config) as renderer:
        renderer.prepare([v.camera for v in views])
        for v in views:
            img = renderer.image(v.camera)
            ps.append(float(psnr(img, v.image)))
            ss.append(float(ssim(jnp.asarray(img), jnp.asarray(v.image))))
            # SSIM compiles per image size and cannot be padded: bound what it keeps
            compiled.trim_programs(ssim)
    return dict(psnr=float(np.mean(ps)) if ps else None, ssim=float(np.mean(ss)) if ss else None)
