"""The 3D-Gaussian renderer tests' shared scenes and configurations (tests/unit/test_gaussian3d.py,
tests/integration/test_gaussian3d_render.py), in the shapes of render_cases (C = 48, 44 x 36 images)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from patexgs_jax import RenderConfig, Scene, random_scene
from render_cases import C
from render_reference import reference_render_3d, scene_to_reference

CONFIGS = {
    "3dgs": (False, RenderConfig(mip="none", background=(0.1, 0.2, 0.3))),
    "mip2d": (False, RenderConfig(mip="none", coverage="prefilter")),
    "mip2d+3d": (True, RenderConfig(mip="none", coverage="prefilter", pixel_var=0.2)),
}


def scene3d(seed, filter3d=False, sh_degree=1):
    sc = random_scene(seed, C, sh_degree=sh_degree, extent=0.8, scale_range=(0.03, 0.35), scale_dims=3)
    if filter3d:  # a filter of about a pixel's footprint at the camera's distance (0.02 world units)
        f = np.random.default_rng(seed).uniform(0.0, 0.03, C) ** 2
        sc = sc.replace(filter3d=jnp.asarray(f, jnp.float32))
    return sc


def ref3d(sc, cam, cfg):
    return reference_render_3d(scene_to_reference(sc), np.asarray(cam.K, np.float64),
                               np.asarray(cam.world_to_camera, np.float64), cam.width, cam.height,
                               background=cfg.background, near=cfg.near, coverage=cfg.coverage,
                               pixel_var=cfg.pixel_var)


HARD = ["edge_on_flat", "near_plane", "sub_pixel", "huge", "degenerate"]


def hard_scene3d(case):
    """Eight 3D Gaussians in front of a camera at z = -3 looking along +z."""
    rng = np.random.default_rng(1)
    n = 8
    means = rng.uniform(-0.3, 0.3, (n, 3))
    scales = np.full((n, 3), 0.2)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) + rng.normal(0, 0.1, (n, 4))
    filt = np.zeros(n)  # (a zero 3D filter is none: every case has one, so they share compiled programs)
    if case == "edge_on_flat":  # flat along x (scale 1e-7), seen edge-on by the camera looking along +z
        scales[:, 0] = 1e-7
        quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        quats[1:] += rng.normal(0, 1e-7, (n - 1, 4))
    elif case == "near_plane":
        means[:, 2] = np.linspace(-3.2, -2.9, n)  # behind, on, just past the near plane
        scales[:] = 1.0
    elif case == "sub_pixel":
        scales[:] = np.exp(rng.uniform(np.log(1e-6), np.log(1e-3), (n, 3)))
        filt = np.zeros(n)
        filt[::2] = 1e-4
    elif case == "huge":
        scales[:] = np.exp(rng.uniform(np.log(1.0), np.log(1e3), (n, 3)))
    elif case == "degenerate":  # needles, discs and points mixed, some with a 3D filter of 0
        scales = np.exp(rng.choice([-30.0, -8.0, 0.0, 5.0], (n, 3)))
        filt = np.where(rng.uniform(size=n) < 0.5, 0.0, 1e-3)
    return Scene.from_arrays(means, scales, quats, np.full(n, 0.8), rng.normal(0, 1, (n, 4, 3)), capacity=n,
                             filter3d=filt)
