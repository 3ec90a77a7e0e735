"""The renderer's 3D Gaussians (rendering/gaussian3d.py: 3DGS's dilation, Mip-Splatting's 2D and 3D
filters) against their float64 brute-force reference, float64 finite differences, and hard cases
with every value and gradient finite."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import Capacity, RenderConfig, Scene, random_scene, render_jit
from patexgs_jax.rendering import ALPHA_MIN, binning, chunks, kernel
from patexgs_jax.rendering.gaussian3d import project3d
from patexgs_jax.rendering.projection import COLS, FOOTPRINT
from render_cases import C, H, W, camera, directional_fd_check, tile_render
from render_reference import reference_render_3d, scene_to_reference_3d

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
    return reference_render_3d(scene_to_reference_3d(sc), np.asarray(cam.K, np.float64),
                               np.asarray(cam.world_to_camera, np.float64), cam.width, cam.height,
                               background=cfg.background, near=cfg.near, coverage=cfg.coverage,
                               pixel_var=cfg.pixel_var)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_matches_reference(name):
    filt, cfg = CONFIGS[name]
    sc = scene3d(7, filt)
    cam = camera()
    ref = ref3d(sc, cam, cfg)
    assert ref["alpha"].mean() > 0.2, "the test scene should cover much of the image"
    out64 = tile_render(sc, cam, cfg, jnp.float64)
    for k, atol in (("rgb", 1e-7), ("alpha", 1e-7), ("depth", 1e-6), ("normal", 1e-7), ("distortion", 1e-9)):
        np.testing.assert_allclose(getattr(out64, k), ref[k], atol=atol, rtol=1e-6, err_msg=k)
    best = ref["best"].ravel()
    np.testing.assert_array_equal(out64.max_contrib_count, np.bincount(best[best >= 0], minlength=C))
    out32 = tile_render(sc, cam, cfg)
    err = np.abs(out32.rgb - ref["rgb"]).max(axis=-1)
    assert np.mean(err > 2e-4) <= 0.005, (err.max(), np.mean(err > 2e-4))
    assert np.median(err) < 2e-5


@pytest.mark.parametrize("name", ["3dgs", "mip2d+3d"])
def test_gradients_match_finite_differences(name):
    filt, cfg = CONFIGS[name]
    sc = scene3d(21, filt)
    for seed in range(2):
        directional_fd_check(sc, camera(), cfg, seed, h=1e-7 if cfg.coverage == "prefilter" else 1e-6)


def test_screen_offset_gradient_is_the_centre_gradient():
    """The densification statistic: the screen_offset gradient equals the gradient of a shift of
    the projected centre, by float64 finite differences on one Gaussian's offset."""
    cfg = CONFIGS["3dgs"][1]
    cam = camera()
    with jax.enable_x64(True):
        sc = scene3d(4).astype(jnp.float64)
        wts = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (H, W, 3)))

        def loss(off):
            out = render_jit(sc, cam, config=cfg, capacity=Capacity(4096), screen_offset=off)
            return jnp.sum(out.rgb * wts)

        off = jnp.zeros((C, 2), jnp.float64)
        g = np.asarray(jax.grad(loss)(off))
        i = int(np.argmax(np.linalg.norm(g, axis=1)))
        h = 1e-6
        for j in range(2):
            e = jnp.zeros((C, 2), jnp.float64).at[i, j].set(h)
            fd = (float(loss(e)) - float(loss(-e))) / (2 * h)
            assert abs(g[i, j] - fd) <= 2e-4 * abs(fd) + 1e-6, (g[i, j], fd)


HARD = ["edge_on_flat", "near_plane", "sub_pixel", "huge", "degenerate"]


def hard_scene3d(case):
    """Eight 3D Gaussians in front of a camera at z = -3 looking along +z."""
    rng = np.random.default_rng(1)
    n = 8
    means = rng.uniform(-0.3, 0.3, (n, 3))
    scales = np.full((n, 3), 0.2)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) + rng.normal(0, 0.1, (n, 4))
    filt = None
    if case == "edge_on_flat":  # flat along z, seen edge-on from the camera's side: z-scale 1e-7
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


@pytest.mark.parametrize("case", HARD)
def test_hard_cases_finite(case):
    sc = hard_scene3d(case)
    cam = camera(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 1.0))
    for cov in ("lowpass", "prefilter"):
        cfg = RenderConfig(mip="none", coverage=cov)

        def loss(s, cfg=cfg):
            out = render_jit(s, cam, config=cfg, capacity=Capacity(pairs=1024))
            return (jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.normal) + jnp.sum(out.alpha)
                    + jnp.sum(out.distortion))

        val, g = jax.value_and_grad(loss)(sc)
        assert np.isfinite(float(val)), (case, cov)
        for path, leaf in jax.tree_util.tree_leaves_with_path(g):
            assert np.all(np.isfinite(np.asarray(leaf))), (case, cov, jax.tree_util.keystr(path))


def test_flat_gaussian_matches_reference_and_fades_with_the_mip_filter():
    """A Gaussian flattened to 1e-7 along an axis across the view (seen edge-on) keeps a
    0.3 px^2 line under 3DGS's dilation; Mip-Splatting's 2D filter scales its opacity by
    sqrt(det / det filtered), so it vanishes. Both as the float64 reference says."""
    sc = Scene.from_arrays([[0.0, 0.0, 0.0]], [[1e-7, 0.3, 0.3]], [[1.0, 0.0, 0.0, 0.0]], [0.9],
                           np.full((1, 1, 3), 1.0), capacity=C)
    cam = camera(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 1.0))
    sums = {}
    for cov, name in (("lowpass", "3dgs"), ("prefilter", "mip2d")):
        cfg = CONFIGS[name][1]  # (the programs of test_matches_reference)
        ref = ref3d(sc, cam, cfg)
        out = tile_render(sc, cam, cfg)
        np.testing.assert_allclose(out.rgb, ref["rgb"], atol=2e-4, rtol=0)
        sums[cov] = float(ref["alpha"].sum())
    assert sums["lowpass"] > 1.0 and sums["prefilter"] < 1e-3, sums


def test_textures_are_refused_on_3d_gaussians():
    sc = random_scene(0, 4, rgb_sizes=[2, 0, 0, 0])
    sc3 = sc.replace(log_scales=jnp.zeros((4, 3), jnp.float32))
    with pytest.raises(ValueError, match="textures are not supported on 3D Gaussians"):
        render_jit(sc3, camera(), config=RenderConfig(), capacity=Capacity(1024))
    with pytest.raises(ValueError, match="take no textures"):
        Scene.from_arrays(np.zeros((1, 3)), np.ones((1, 3)), [[1.0, 0, 0, 0]], [0.5], np.zeros((1, 3)),
                          rgb_textures=[None])


@functools.partial(jax.jit, static_argnames=("config",))
def cull_check3d(sc, cam, config, g, px, py):
    """For (Gaussian g, tile (px, py)) pairs: whether binning.tile_touches keeps each, and whether
    the compositor's own kernel reaches alpha 1/255 at a pixel of the tile in front of the near plane."""
    ts = config.tile_size
    proj = project3d(sc, cam, config, None, None)
    keep = binning.tile_touches([proj.footprint[:, i][g] for i in range(FOOTPRINT.width)], px, py, ts, False)
    pk = proj.packed[g][:, None, :]
    iy, ix = jnp.divmod(jnp.arange(ts * ts), ts)
    x = (px[:, None] * ts + ix).astype(jnp.float32) + 0.5
    y = (py[:, None] * ts + iy).astype(jnp.float32) + 0.5
    G, z = kernel.chunk_geometry(pk, x, y, True)
    alpha = chunks.cols(pk)[COLS.opacity] * G
    return keep, jnp.any((alpha >= ALPHA_MIN) & (z > config.near), axis=(0, 2))


@pytest.mark.parametrize("case", ["random", "edge_on_flat", "huge", "near_plane", "degenerate"])
def test_tile_cull_keeps_every_pair(case):
    """No (Gaussian, tile) pair of a screen box that the tile cull leaves out reaches alpha 1/255 at a
    pixel of its tile, by the compositor's float32 kernel, under both coverage modes."""
    if case == "random":
        sc, cam = scene3d(9, True), camera()
    else:
        sc, cam = hard_scene3d(case), camera(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 1.0))
    for cov in ("lowpass", "prefilter"):
        cfg = RenderConfig(mip="none", coverage=cov)
        proj = project3d(sc, cam, cfg, None, None)
        ts = cfg.tile_size
        tx0, tx1, ty0, ty1, ok = (np.asarray(a) for a in binning.tile_ranges(
            proj.bounds, proj.visible, ts, -(-cam.width // ts), -(-cam.height // ts)))
        pairs = [(i, x, y) for i in np.flatnonzero(ok) for y in range(ty0[i], ty1[i]) for x in range(tx0[i], tx1[i])]
        assert 0 < len(pairs) <= 1024
        g, px, py = (np.pad(np.asarray(v, np.int32), (0, 1024 - len(pairs))) for v in zip(*pairs))
        keep, reach = (np.asarray(a)[:len(pairs)] for a in cull_check3d(sc, cam, cfg, g, px, py))
        assert not np.any(reach & ~keep), (case, cov)
        if case == "random":  # ellipses that are not axis-aligned leave corner tiles of their boxes
            assert np.mean(keep) < 1.0, "the cull should leave some pairs out"
