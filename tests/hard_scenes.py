"""Builders of numerically hard scenes for tests/integration/test_hard_cases.py.

Every scene has the same shapes (capacity ``C``, the texture sizes of ``RGB_SIZES`` / ``ALPHA_SIZES`` on
the first ``NTEX`` slots) and every camera the same image size, so one compiled renderer serves them
all; only values change. A scene is a deterministic function of ``(case, seed, knob)``: hypothesis
draws those three, and a failing example is kept as an explicit ``@example(case, seed, knob)``.
"""

from __future__ import annotations

import numpy as np

from patexgs_jax import Camera, Scene, look_at
from patexgs_jax.data.colmap_model import quaternion_from_rotation

C = 2048            # slots: room for the "thousands of splats on one pixel" case; others use NTEX
NTEX = 16           # slots that may carry textures (and that the ordinary cases use)
W, H = 32, 24       # 2 x 2 tiles of 16 px, a partial tile row
NEAR = 0.01
# Texture sides of the first NTEX slots (0: none). 32 has a 6-level pyramid, so mip levels span 0..5.
RGB_SIZES = [1, 2, 3, 4, 5, 8, 16, 0, 2, 4, 0, 7, 1, 0, 9, 32]
ALPHA_SIZES = [4, 0, 2, 8, 1, 3, 16, 5, 0, 6, 2, 0, 12, 4, 1, 32]
SH_C0 = 0.28209479177387814

CASES = ("edge_on", "needle", "tiny_huge", "near_plane", "far", "coincident", "opacity_extremes",
         "tiny_quat", "focal", "clamp_textures", "mip_range")


def frame_with_normal(n: np.ndarray, rng) -> np.ndarray:
    """A rotation matrix whose third column is the unit vector ``n``."""
    n = n / np.linalg.norm(n)
    a = np.cross(n, rng.normal(size=3))
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    return np.stack([a, b, n], axis=1)


def _unit(v):
    return v / np.linalg.norm(v)


def build(case: str, seed: int, knob: float):
    """(scene, camera, info) of one hard case; ``knob`` in [0, 1] picks the extreme within the case.

    ``info``: dict with ``n`` (slots used) and ``ill_conditioned``: None, "near_plane" (splat centres
    within float32 rounding of the near plane) or "alpha_tie" (alpha textures that clamp alpha at 0.99
    on many pixels); see tests/integration/test_hard_cases.py for what each means.
    """
    rng = np.random.default_rng(seed)
    n = NTEX
    f = 40.0
    eye = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), -3.0])
    target = np.zeros(3)
    means = rng.uniform(-0.6, 0.6, (n, 3))
    scales = np.exp(rng.uniform(np.log(0.1), np.log(0.6), (n, 2)))
    quats = rng.normal(size=(n, 4))
    opac = rng.uniform(0.2, 0.95, n)
    sh = np.zeros((n, 4, 3))
    sh[:, 0] = (rng.uniform(0.1, 0.9, (n, 3)) - 0.5) / SH_C0
    sh[:, 1:] = rng.normal(0, 0.1, (n, 3, 3))
    rgb = [None if s == 0 else rng.uniform(-0.2, 0.2, (s, s, 3)) for s in RGB_SIZES]
    alpha = [None if s == 0 else rng.uniform(0.3, 1.2, (s, s)) for s in ALPHA_SIZES]
    ill = None
    w2c = look_at(eye, target)
    R_cam, fwd = w2c[:3, :3], w2c[2, :3]
    k = 1 + int(knob * (n - 1))  # how many splats are made extreme (at least one)
    pick = rng.permutation(n)[:k]

    def at_depth(z, lateral=0.3):
        off = R_cam.T @ np.array([rng.uniform(-lateral, lateral) * z / 3, rng.uniform(-lateral, lateral) * z / 3, 0])
        return eye + z * fwd + off

    if case == "edge_on":
        # Normal perpendicular to the ray through the mean, up to an angle of at most 1e-7.
        for i in pick:
            d = _unit(means[i] - eye)
            nrm = _unit(np.cross(d, rng.normal(size=3)))
            nrm = _unit(nrm + rng.uniform(-1e-7, 1e-7) * d)
            quats[i] = quaternion_from_rotation(frame_with_normal(nrm, rng))
    elif case == "needle":
        s = 10.0 ** rng.uniform(-5, -3, k)
        scales[pick] = np.stack([s, s * 1e6], axis=1)[:, rng.permutation(2)]
    elif case == "tiny_huge":
        scales[pick] = np.where(rng.random((k, 2)) < 0.5, 1e-7, 1e4)
    elif case == "near_plane":
        depths = np.array([-1.0, 0.0, NEAR - 1e-6, NEAR, NEAR + 1e-6, NEAR + 1e-3, 0.05, 0.2])
        for j, i in enumerate(pick):
            means[i] = at_depth(depths[j % len(depths)], lateral=0.0)
            scales[i] = rng.uniform(0.05, 1.0, 2)
        ill = "near_plane"
    elif case == "far":
        for i in pick:
            z = 1e6 * rng.uniform(0.5, 1.0)
            means[i] = at_depth(z)
            scales[i] = z * rng.choice([0.02, 0.1, 1e-4]) * np.ones(2)
    elif case == "coincident":
        m = means[pick[0]]
        for i in pick:
            means[i] = m  # identical centres: equal depths (ties keep slot order in both renderers)
    elif case == "opacity_extremes":
        opac[pick] = rng.choice([0.0, 1.0], k)
    elif case == "tiny_quat":
        quats[pick] = _normed(quats[pick]) * 10.0 ** -rng.choice([3.0, 6.0, 9.0, 11.0, 13.0], (k, 1))
    elif case == "focal":
        f = float(10.0 ** (-2 + 7 * knob))  # 0.01 (everything in a pixel) .. 1e5 (a 0.3 mrad view)
    elif case == "clamp_textures":
        for i in pick:
            if alpha[i] is not None:
                alpha[i] = rng.choice([0.0, 50.0], alpha[i].shape)   # alpha 0 and min(0.99, 50 o G)
            if rgb[i] is not None:
                rgb[i] = rng.choice([-3.0, 0.0, 3.0], rgb[i].shape)
            sh[i, 0] = rng.choice([-40.0, 40.0], 3)                   # SH colour clamped at 0, or large
        ill = "alpha_tie"
    elif case == "mip_range":
        dist = 10.0 ** (-0.3 + 2.3 * knob)                            # 0.5 .. 100: level 0 .. coarsest
        eye = eye / np.linalg.norm(eye) * dist
        f = 40.0 * dist / 3.0 * rng.uniform(0.5, 1.5)                  # keeps the scene in view
        rgb = [None if s == 0 else rng.uniform(-0.3, 0.3, (s, s, 3)) for s in RGB_SIZES]
    else:
        raise ValueError(case)
    w2c = look_at(eye, target)
    cam = Camera.from_intrinsics([f, f * 1.03, W / 2 + 0.3, H / 2 - 0.2], w2c, W, H)
    scene = Scene.from_arrays(means, scales, quats, opac, sh, rgb_textures=rgb, alpha_textures=alpha, capacity=C)
    return scene, cam, dict(ill_conditioned=ill, n=n)


def _normed(q):
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def pile_on_one_pixel(seed: int, n: int):
    """``n`` (up to C) small splats stacked along the ray of one pixel, textures on the first NTEX."""
    rng = np.random.default_rng(seed)
    eye = np.array([0.0, 0.0, -2.0])
    means = np.zeros((n, 3))
    means[:, 2] = rng.uniform(0.0, 2.0, n)
    means[:, :2] = rng.normal(0, 1e-3, (n, 2))
    scales = np.full((n, 2), 0.01) * rng.uniform(0.8, 1.2, (n, 1))
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) + rng.normal(0, 0.05, (n, 4))
    opac = rng.uniform(0.01, 0.1, n)
    sh = np.zeros((n, 4, 3))
    sh[:, 0] = (rng.uniform(0.1, 0.9, (n, 3)) - 0.5) / SH_C0
    rgb = [None] * n
    alpha = [None] * n
    for i in range(min(n, NTEX)):
        rgb[i] = None if RGB_SIZES[i] == 0 else rng.uniform(-0.1, 0.1, (RGB_SIZES[i],) * 2 + (3,))
        alpha[i] = None if ALPHA_SIZES[i] == 0 else rng.uniform(0.5, 1.0, (ALPHA_SIZES[i],) * 2)
    # Keep the bucket shapes of the other scenes: the first NTEX slots always hold the textures.
    cam = Camera.from_intrinsics([50.0, 50.0, 8.0, 8.0], look_at(eye, (0.0, 0.0, 0.0)), W, H)
    scene = Scene.from_arrays(means, scales, quats, opac, sh, rgb_textures=rgb, alpha_textures=alpha, capacity=C)
    return scene, cam
