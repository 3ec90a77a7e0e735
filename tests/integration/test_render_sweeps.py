"""The renderer over more configurations and scales than tests/unit runs: the float64 reference and
finite differences for every other configuration, hard-case gradients with trilinear mipmaps, mip
minification and zoom-out against supersampled renders, and the texture lookups in passes against
looking up every pair. Each compiles several renderers of its own, hence this tier.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hard_scenes as hs
from patexgs_jax import Camera, Capacity, RenderConfig, look_at, random_scene, render, render_jit
from patexgs_jax.data import box_downsample
from patexgs_jax.render import _render as render_unjitted
from patexgs_jax.render import scene_textures
from patexgs_jax.training import TrainConfig
from render_cases import (
    CAP,
    CONFIGS,
    HARD_CASES,
    C,
    H,
    W,
    camera,
    check_gradients_match_finite_differences,
    check_hard_case_gradients_finite,
    check_matches_reference,
    check_tile_cull_keeps_every_pair,
    scene,
    single_splat_scene,
    tile_render,
)

PREFILTER = TrainConfig(method="patexgs").render_config()
LITERAL = TrainConfig(method="patexgs-literal").render_config()


@pytest.mark.parametrize("name", ["none", "trilinear", "no-rgb-mip", "prefilter-2dgs"])
def test_matches_reference(name):
    check_matches_reference(name)


@pytest.mark.parametrize("name", ["2dgs", "trilinear"])
def test_gradients_match_finite_differences(name):
    check_gradients_match_finite_differences(name)


@pytest.mark.parametrize("case", [c for c in hs.CASES if c not in ("edge_on", "near_plane")])
def test_tile_cull_keeps_every_pair_that_can_contribute(case):
    check_tile_cull_keeps_every_pair(case)


@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_case_gradients_finite_trilinear(case):
    check_hard_case_gradients_finite(case, "trilinear")


@pytest.mark.parametrize("channel", ["rgb", "alpha"])
def test_minification_is_closer_to_supersampled_truth(channel):
    n = 32
    checker = ((np.add.outer(np.arange(n), np.arange(n)) % 2) * 2 - 1).astype(np.float64)
    if channel == "rgb":
        sc = single_splat_scene(0.4 * checker[..., None].repeat(3, -1), None, scale=1.0)
    else:
        sc = single_splat_scene(None, 0.5 + 0.5 * checker, scale=1.0)
    sc = sc.replace(sh=sc.sh.at[0, 0].set(0.5 / 0.28209479177387814 * 0.3))
    # Small view: the 6x6 texture square spans about 16 px, so 32 texels alias badly.
    cam_small = camera(eye=(0.0, 0.0, -10.0), target=(0.0, 0.0, 0.0), f=27.0, w=W, h=H)
    factor = 8
    K_big = np.asarray(cam_small.K, np.float64) * np.array([[factor], [factor], [1]])
    cam_big = Camera.from_intrinsics(K_big, np.asarray(cam_small.world_to_camera), W * factor, H * factor)
    truth = render(sc, cam_big, RenderConfig(mip="none"))
    truth = np.asarray(truth.rgb).reshape(H, factor, W, factor, 3).mean(axis=(1, 3))
    errs = {}
    for mip in ("none", "nearest", "trilinear"):
        out = render(sc, cam_small, RenderConfig(mip=mip))
        errs[mip] = float(np.sqrt(np.mean((np.asarray(out.rgb) - truth) ** 2)))
    assert errs["nearest"] < 0.7 * errs["none"], errs
    assert errs["trilinear"] < 0.7 * errs["none"], errs


@pytest.mark.parametrize("name", ["nearest", "trilinear"])
def test_texture_passes_do_not_change_the_result(name):
    """Looking textures up only for the pairs that can reach alpha 1/255, in many small passes, gives
    the image and gradients of looking up every pair. (At 1/512 a pass holds 80 of the 40,960 pairs
    of a chunk step here, far fewer than contribute. The default share, about one pass per step, is
    what the float64 reference tests above render with.)"""
    textured, degree, cfg = CONFIGS[name]
    sc = scene(31, textured, degree)
    cam = camera()
    cfgs = [dataclasses.replace(cfg, texture_pairs=t) for t in (1.0, 1 / 512)]

    def loss(s, c):  # the image and the gradient from one compiled function per configuration
        out = render_unjitted(s, cam, c, CAP)
        return jnp.mean(jnp.abs(out.rgb - 0.3)) + 0.1 * jnp.mean(out.alpha * out.depth), out

    with jax.enable_x64(True):
        sc64 = sc.astype(jnp.float64)
        res = []
        for c in cfgs:
            (_, out), g = jax.jit(jax.value_and_grad(lambda s, c=c: loss(s, c), has_aux=True))(sc64)
            res.append(jax.tree_util.tree_map(np.asarray, (out, g)))
    (out_d, g_d) = res[0]
    assert out_d.alpha.mean() > 0.2
    for out, g in res[1:]:
        for a, b in [(out.rgb, out_d.rgb), (out.alpha, out_d.alpha), (out.depth, out_d.depth),
                     (out.normal, out_d.normal), (out.distortion, out_d.distortion)]:
            np.testing.assert_allclose(a, b, atol=1e-12, rtol=0)
        np.testing.assert_array_equal(out.max_contrib_count, out_d.max_contrib_count)
        for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(g_d)):
            scale = float(np.abs(b).max()) if b.size else 0.0
            np.testing.assert_allclose(a, b, atol=1e-10 * max(scale, 1.0), rtol=0)


# ---------------------------------------------------------------------------------------------
# Zoom-out: the render at 1/s is close to the box-downsampled full-resolution render
# ---------------------------------------------------------------------------------------------
ZW, ZH = 64, 48
ZOOM_CAP = Capacity(pairs=8192)


def _render(sc, cam, cfg):
    out = render_jit(sc, cam, config=cfg, capacity=ZOOM_CAP)
    assert not bool(out.overflow)
    return out


def _psnr(a, b):
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2)))


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), factor=st.sampled_from([2, 4]), textured=st.booleans())
def test_zoom_out_matches_supersampled_render(seed, factor, textured):
    """Random scenes whose splats span 0.3 to 3 pixels at full resolution (0.1 to 1.5 pixels zoomed
    out): the prefiltered render at 1/s is within 28 dB PSNR of the full-resolution render
    box-downsampled by s (what a perfectly anti-aliased renderer shows), and at least as close as
    the low-pass's."""
    sizes = [0, 1, 2, 4, 8, 16] * 8
    sc = random_scene(seed, C, sh_degree=0, extent=0.8, scale_range=(0.004, 0.04),
                      rgb_sizes=sizes if textured else None, alpha_sizes=sizes[::-1] if textured else None)
    rng = np.random.default_rng(seed)
    eye = (rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), -2.5)
    cam = Camera.from_intrinsics([60.0, 60.0, ZW / 2, ZH / 2], look_at(eye, (0.0, 0.0, 0.0)), ZW, ZH)
    small = cam.scaled(factor)
    got = {}
    for name, cfg in (("prefilter", PREFILTER), ("lowpass", LITERAL)):
        full = np.asarray(_render(sc, cam, cfg).rgb)
        zoomed = np.asarray(_render(sc, small, cfg).rgb)
        got[name] = _psnr(zoomed, box_downsample(full, factor))
    assert got["prefilter"] >= 28.0, got
    assert got["prefilter"] >= got["lowpass"] - 0.5, got


def test_prepared_textures_render_the_same_image_and_must_match_the_config():
    """render_jit with the scene's scene_textures (built once, as the viewer reuses them) gives the
    render that builds them itself, to float32 rounding (the same arithmetic in two programs, which
    XLA may fuse differently: bit-equal with its default CPU code generation, 74 of 4,752 values
    6e-8 apart with its older emitters) and the same dominant splats; textures prepared for other
    mip settings or a scene without textures are refused with a line that names the fix."""
    sc, cam = scene(3), camera()
    cfg = RenderConfig(mip="nearest", coverage="prefilter")
    tx = scene_textures(sc, config=cfg)
    own = tile_render(sc, cam, cfg)
    out = jax.tree_util.tree_map(np.asarray, render_jit(sc, cam, config=cfg, capacity=CAP, textures=tx))
    for name in ("rgb", "alpha", "depth", "normal"):  # (a few ulps)
        np.testing.assert_allclose(getattr(out, name), getattr(own, name), rtol=5e-7, atol=5e-7, err_msg=name)
    np.testing.assert_array_equal(out.dominant, own.dominant)
    with pytest.raises(ValueError, match="scene_textures"):
        render_jit(sc, cam, config=dataclasses.replace(cfg, mip="none"), capacity=CAP, textures=tx)
    with pytest.raises(ValueError, match="scene_textures"):
        render_jit(scene(3, textured=False), cam, config=cfg, capacity=CAP, textures=tx)
