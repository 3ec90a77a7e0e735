"""The renderer tests' shared scenes, camera and configurations (tests/unit/test_render.py,
test_render_gradients.py, test_texture_lookup.py, test_coverage.py).

Compiles are the expensive part on CPU: every scene here has one capacity (C=48), every camera one
image size (44x36, a partial tile on each edge), every render one Capacity, so compiled renderers are
shared across tests (one per configuration and dtype).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, random_scene, render_jit
from render_reference import reference_render, scene_to_reference

C = 48
W, H = 44, 36
CAP = Capacity(pairs=4096)
# Texture sides per Gaussian, fixed so every textured scene has the same bucket layout (shapes).
RGB_SIZES = [0, 1, 2, 3, 4, 5, 7, 8, 9, 16] * 4 + [0] * 8
ALPHA_SIZES = [5, 0, 1, 3, 4, 6, 8, 2, 9, 12] * 4 + [5] * 8


def camera(eye=(0.3, -0.4, -2.6), target=(0.0, 0.0, 0.0), f=40.0, w=W, h=H) -> Camera:
    return Camera.from_intrinsics([f, f * 1.05, w / 2 + 0.3, h / 2 - 0.2], look_at(eye, target), w, h)


def scene(seed, textured=True, sh_degree=1) -> Scene:
    return random_scene(seed, C, sh_degree=sh_degree, extent=0.8, scale_range=(0.08, 0.45),
                        rgb_sizes=RGB_SIZES if textured else None,
                        alpha_sizes=ALPHA_SIZES if textured else None)


def tile_render(sc, cam, cfg, dtype=jnp.float32, capacity=CAP):
    if dtype == jnp.float64:
        with jax.enable_x64(True):
            out = render_jit(sc.astype(jnp.float64), cam, config=cfg, capacity=capacity)
            assert not bool(out.overflow)
            return jax.tree_util.tree_map(np.asarray, out)
    out = render_jit(sc, cam, config=cfg, capacity=capacity)
    assert not bool(out.overflow)
    return jax.tree_util.tree_map(np.asarray, out)


def ref_render(sc, cam, cfg):
    return reference_render(scene_to_reference(sc), np.asarray(cam.K, np.float64),
                            np.asarray(cam.world_to_camera, np.float64), cam.width, cam.height,
                            mip=cfg.mip, lam=cfg.lambda_mip, rgb_mip=cfg.rgb_mip,
                            alpha_mip=cfg.alpha_mip, background=cfg.background, near=cfg.near,
                            coverage=cfg.coverage, pixel_var=cfg.pixel_var, min_var=cfg.min_var)


CONFIGS = {
    "2dgs": (False, 3, RenderConfig(mip="none", background=(0.1, 0.2, 0.3))),
    "none": (True, 1, RenderConfig(mip="none")),
    "nearest": (True, 1, RenderConfig(mip="nearest")),
    "trilinear": (True, 2, RenderConfig(mip="trilinear", lambda_mip=1.5)),
    "no-rgb-mip": (True, 0, RenderConfig(mip="nearest", rgb_mip=False, lambda_mip=2.0)),
    "prefilter": (True, 1, RenderConfig(mip="nearest", coverage="prefilter", min_var=0.25)),
    "prefilter-2dgs": (False, 2, RenderConfig(mip="none", coverage="prefilter", pixel_var=0.3)),
}


def single_splat_scene(tex_rgb, tex_alpha=None, scale=1.0, n_pad=C):
    """One splat facing the camera (normal along z) at the origin, padded to capacity C."""
    q = [1.0, 0.0, 0.0, 0.0]
    sh = np.zeros((1, 1, 3))
    return Scene.from_arrays([[0.0, 0.0, 0.0]], [[scale, scale]], [q], [1.0], sh,
                             rgb_textures=[tex_rgb], alpha_textures=[tex_alpha], capacity=n_pad)
