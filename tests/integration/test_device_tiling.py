"""The device-chosen tile schedule, the compiling half of its checks (tests/unit/test_device_path.py
has the rule): a whole image in one batch (a GPU's schedule) gives the CPU schedule's image, and the
memory bound the rule assumes holds for the heaviest render."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from patexgs_jax import Capacity, RenderConfig, random_scene, render_jit
from patexgs_jax.rendering import tiling
from render_cases import CAP, camera, scene

P, CHUNK = 16 * 16, 32


def test_whole_image_batch_renders_the_same_image(monkeypatch):
    """Every tile in one batch (a GPU's schedule) gives the CPU schedule's image."""
    monkeypatch.delenv(tiling.ENV_TILE_BATCH, raising=False)
    sc, cam = scene(2), camera()
    outs = [render_jit(sc, cam, config=RenderConfig(mip="nearest", coverage="prefilter", tile_batch=tb), capacity=CAP)
            for tb in (8, 10_000)]
    np.testing.assert_allclose(np.asarray(outs[0].rgb), np.asarray(outs[1].rgb), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(outs[0].alpha), np.asarray(outs[1].alpha), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(outs[0].dominant), np.asarray(outs[1].dominant))


def test_memory_bound_covers_the_heaviest_render():
    """PAIR_BYTES bounds the working memory a tile adds to the forward and backward of the heaviest
    configuration (trilinear mipmaps of RGB and alpha textures, the prefilter), as XLA's memory
    analysis of the compiled program reports it."""
    sizes = [4, 8, 16, 32] * 50
    sc = random_scene(0, 200, sh_degree=3, extent=0.8, scale_range=(0.02, 0.2), rgb_sizes=sizes, alpha_sizes=sizes)
    cam = camera(w=128, h=64, f=80.0)  # 32 tiles
    temp = {}
    for tb in (4, 32):
        cfg = RenderConfig(mip="trilinear", coverage="prefilter", tile_batch=tb)

        def loss(s, cfg=cfg):
            out = render_jit(s, cam, config=cfg, capacity=Capacity(1 << 14))
            return jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.normal)

        temp[tb] = jax.jit(jax.grad(loss)).lower(sc).compile().memory_analysis().temp_size_in_bytes
    per_tile = (temp[32] - temp[4]) / 28
    assert 0 < per_tile <= P * CHUNK * tiling.PAIR_BYTES, (per_tile, P * CHUNK * tiling.PAIR_BYTES)
