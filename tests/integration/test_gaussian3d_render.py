"""3D Gaussians in the renderer, the slower checks (the rest: tests/unit/test_gaussian3d.py): the
tile cull keeps every pair a Gaussian's kernel reaches, and the screen-offset gradient (the
densification statistic) is the gradient of the projected centre."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gaussian3d_cases import CONFIGS, hard_scene3d, scene3d

from patexgs_jax import Capacity, RenderConfig, render_jit
from patexgs_jax.rendering import ALPHA_MIN, binning, chunks, kernel
from patexgs_jax.rendering.gaussian3d import project3d
from patexgs_jax.rendering.projection import COLS, FOOTPRINT
from render_cases import C, H, W, camera


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
