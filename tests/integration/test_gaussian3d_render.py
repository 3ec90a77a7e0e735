"""3D Gaussians in the renderer, the slower checks (the rest: tests/unit/test_gaussian3d.py): the
hard scenes of test_hard_cases (hard_scenes.build, property-based) made 3D, with finite values and
gradients and float32 against the float64 reference; the tile cull keeps every pair a Gaussian's
kernel reaches; the screen-offset gradient (the densification statistic) is the gradient of the
projected centre."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import hard_scenes as hs
from gaussian3d_cases import CONFIGS, hard_scene3d, scene3d
from patexgs_jax import Capacity, RenderConfig, render_jit
from patexgs_jax.render import ALPHA_MIN
from patexgs_jax.rendering import binning, chunks, kernel
from patexgs_jax.rendering.gaussian3d import project3d
from patexgs_jax.rendering.projection import COLS, FOOTPRINT
from patexgs_jax.scene import Scene
from render_cases import C, H, W, camera
from render_reference import reference_render_3d

#: hard_scenes' cases but the two about textures (3D Gaussians have none).
CASES3D = [c for c in hs.CASES if c not in ("clamp_textures", "mip_range")]
HS_CFGS = {cov: RenderConfig(mip="none", coverage=cov, background=(0.2, 0.5, 0.8), near=hs.NEAR)
           for cov in ("lowpass", "prefilter")}
TOL, FLIP_FRACTION = 2e-4, 0.03


def to_3d(scene, seed):
    """A hard_scenes scene made 3D: a third scale from 1e-7 (flat) to 10 times the first, a 3D
    filter on about half of the Gaussians (zero on the others), no textures."""
    rng = np.random.default_rng(seed + 7)
    ls = np.asarray(scene.log_scales)
    third = ls[:, :1] + np.log(10.0) * rng.uniform(-7.0, 1.0, (ls.shape[0], 1))
    f = np.where(rng.uniform(size=ls.shape[0]) < 0.5, 0.0, 10.0 ** rng.uniform(-4.0, -1.0, ls.shape[0])) ** 2
    return Scene(means=scene.means, log_scales=jnp.asarray(np.concatenate([ls, third], 1), jnp.float32),
                 quats=scene.quats, opacity_logits=scene.opacity_logits, sh=scene.sh, active=scene.active,
                 filter3d=jnp.asarray(f, jnp.float32))


@functools.partial(jax.jit, static_argnames="cfg")
def render_and_grad(scene, cam, cfg):
    def loss(s):
        out = render_jit(s, cam, config=cfg, capacity=Capacity(pairs=8192))
        return (jnp.sum(out.rgb) + jnp.sum(out.alpha) + 0.1 * jnp.sum(out.depth) + jnp.sum(out.normal)
                + jnp.sum(out.distortion)), out

    (val, out), grad = jax.value_and_grad(loss, has_aux=True)(scene)
    return val, out, grad


@given(case=st.sampled_from(CASES3D), seed=st.integers(0, 10_000), knob=st.floats(0.0, 1.0),
       cov=st.sampled_from(["lowpass", "prefilter"]))
def test_hard_scenes_3d(case, seed, knob, cov):
    scene2, cam, info = hs.build(case, seed, knob)
    sc, n, cfg = to_3d(scene2, seed), info["n"], HS_CFGS[cov]
    val, out, grad = render_and_grad(sc, cam, cfg)
    assert np.isfinite(float(val)) and not bool(out.overflow)
    for path, leaf in jax.tree_util.tree_leaves_with_path(grad):
        assert np.all(np.isfinite(np.asarray(leaf))), (case, cov, jax.tree_util.keystr(path))
    alpha = np.asarray(out.alpha)
    assert np.all(np.isfinite(np.asarray(out.rgb))) and np.all((alpha >= 0) & (alpha <= 1))
    if info["ill_conditioned"] == "near_plane":
        return  # centres within float32 rounding of the near plane: culled or not by rounding
    act = np.asarray(sc.active[:n]) > 0
    q32 = np.asarray(sc.quats, np.float32)[:n]
    g = dict(means=np.asarray(sc.means[:n], np.float64), scales=np.exp(np.asarray(sc.log_scales[:n], np.float64)),
             # the renderer's convention: a quaternion of float32 squared norm below 1e-24 is the identity
             quats=np.where((np.sum(q32 * q32, axis=1) < 1e-24)[:, None], [1.0, 0.0, 0.0, 0.0], q32),
             opacities=np.where(act, 1 / (1 + np.exp(-np.asarray(sc.opacity_logits[:n], np.float64))), 0.0),
             sh=np.asarray(sc.sh[:n], np.float64), filter3d=np.asarray(sc.filter3d[:n], np.float64))
    ref = reference_render_3d(g, np.asarray(cam.K, np.float64), np.asarray(cam.world_to_camera, np.float64),
                              cam.width, cam.height, background=cfg.background, near=cfg.near, coverage=cov,
                              pixel_var=cfg.pixel_var)
    worst = np.maximum(np.abs(np.asarray(out.rgb) - ref["rgb"]).max(-1), np.abs(alpha - ref["alpha"]))
    assert np.mean(worst > TOL) <= FLIP_FRACTION, (case, seed, knob, cov, np.mean(worst > TOL), worst.max())


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


@functools.partial(jax.jit, static_argnames=("config",))
def _screen_boxes3d(sc, cam, config):
    """The Gaussians' tile ranges (tx0, tx1, ty0, ty1, ok), each (C,), as the renderer bins them (one
    program, not one per operation)."""
    proj = project3d(sc, cam, config, None, None)
    ts = config.tile_size
    return binning.tile_ranges(proj.bounds, proj.visible, ts, -(-cam.width // ts), -(-cam.height // ts))


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
        tx0, tx1, ty0, ty1, ok = (np.asarray(a) for a in _screen_boxes3d(sc, cam, cfg))
        pairs = [(i, x, y) for i in np.flatnonzero(ok) for y in range(ty0[i], ty1[i]) for x in range(tx0[i], tx1[i])]
        assert 0 < len(pairs) <= 1024
        g, px, py = (np.pad(np.asarray(v, np.int32), (0, 1024 - len(pairs))) for v in zip(*pairs))
        keep, reach = (np.asarray(a)[:len(pairs)] for a in cull_check3d(sc, cam, cfg, g, px, py))
        assert not np.any(reach & ~keep), (case, cov)
        if case == "random":  # ellipses that are not axis-aligned leave corner tiles of their boxes
            assert np.mean(keep) < 1.0, "the cull should leave some pairs out"
