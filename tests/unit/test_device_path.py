"""The GPU path, checked on the CPU: the tile schedule chosen per device and its memory bound, and
float32 products at full precision in the programs lowered for CUDA (a GPU otherwise computes
float32 matmuls in TF32)."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import pytest
from jax import export

from patexgs_jax import RenderConfig, random_scene, render_jit
from patexgs_jax.densify import DensifyStats
from patexgs_jax.optim import make_optimizer
from patexgs_jax.render import scene_textures
from patexgs_jax.rendering import tiling
from patexgs_jax.training.step import single_view_step
from render_cases import CAP, camera, scene

GIB = 1 << 30
P, CHUNK = 16 * 16, 32


def _per_tile():
    return P * CHUNK * tiling.PAIR_BYTES


@pytest.mark.parametrize("num_tiles", [1, 7, 8, 9, 1200, 8160])
def test_cpu_keeps_its_tuned_batch(num_tiles):
    assert tiling.choose_tile_batch(num_tiles, backend="cpu", tile_size=16, chunk=CHUNK) == min(8, num_tiles)


@pytest.mark.parametrize("backend", ["gpu", "cuda", "rocm", "tpu"])
@pytest.mark.parametrize("num_tiles, memory, expected", [
    (1200, 80 * GIB, 1200),          # 640x480 on an H100: every tile at once
    (8160, 80 * GIB, 8160),          # 1920x1080 on an H100: every tile at once
    (32400, 80 * GIB, 20480),        # 3840x2160: as many as a quarter of 80 GiB holds
    (8160, 16 * GIB, 4096),          # 1080p on a 16 GiB card
    (8160, 1 << 20, 1),              # a device too small for one tile still advances one
    (1200, None, 1200),              # a device that does not report its memory: 8 GiB assumed
])
def test_accelerator_batches_as_many_tiles_as_fit(backend, num_tiles, memory, expected):
    b = tiling.choose_tile_batch(num_tiles, backend=backend, tile_size=16, chunk=CHUNK, memory_bytes=memory)
    assert b == expected
    mem = tiling.DEFAULT_DEVICE_MEMORY if memory is None else memory
    assert b == num_tiles or b * _per_tile() <= tiling.MEMORY_SHARE * mem < (b + 1) * _per_tile() or b == 1


def test_explicit_and_environment_overrides(monkeypatch):
    monkeypatch.delenv(tiling.ENV_TILE_BATCH, raising=False)
    assert tiling.resolve_tile_batch(3, 1200, tile_size=16, chunk=32, backend="gpu") == 3
    assert tiling.resolve_tile_batch(None, 1200, tile_size=16, chunk=32, backend="cpu") == 8
    monkeypatch.setenv(tiling.ENV_TILE_BATCH, "64")
    assert tiling.resolve_tile_batch(None, 1200, tile_size=16, chunk=32, backend="cpu") == 64
    assert tiling.resolve_tile_batch(5, 1200, tile_size=16, chunk=32, backend="cpu") == 5  # the config wins
    for bad in ("0", "-3", "many"):
        monkeypatch.setenv(tiling.ENV_TILE_BATCH, bad)
        with pytest.raises(ValueError, match="PATEXGS_TILE_BATCH"):
            tiling.resolve_tile_batch(None, 1200, tile_size=16, chunk=32, backend="cpu")
    with pytest.raises(ValueError, match="tile_batch"):
        RenderConfig(tile_batch=0)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the CPU's schedule (a GPU chooses its own)")
def test_cpu_default_is_todays_program(monkeypatch):
    """On the CPU the device-chosen schedule is the tuned one: the default config lowers to the same
    program as ``tile_batch=8`` (so the CPU path is exactly as fast as before)."""
    monkeypatch.delenv(tiling.ENV_TILE_BATCH, raising=False)
    sc, cam = scene(1), camera()
    texts = []
    for tb in (None, 8):
        cfg = RenderConfig(mip="nearest", coverage="prefilter", tile_batch=tb)
        lowered = jax.jit(lambda s, cfg=cfg: render_jit(s, cam, config=cfg, capacity=CAP).rgb).lower(sc)
        texts.append(re.sub(r"loc\(.*?\)|#loc\d*", "", lowered.as_text()))
    assert texts[0] == texts[1]


# ---------------------------------------------------------------------------------------------
# Full-precision products in the programs a GPU runs

_PRODUCT = re.compile(r"=\s*stablehlo\.(dot_general|dot|convolution)\b")
_PRECISION = re.compile(r"precision(?:_config)?\s*=\s*\[([^\]]*)\]")


def _full_precision(line: str) -> bool:
    """Whether a product's operands are both at HIGHEST (no attribute: the backend's default, TF32)."""
    m = _PRECISION.search(line)
    levels = re.findall(r"DEFAULT|HIGHEST|HIGH", m.group(1)) if m else []
    return len(levels) == 2 and all(level == "HIGHEST" for level in levels)


def _low_precision_products(fn, *args) -> tuple[int, list[str]]:
    """(products, those without HIGHEST precision) in ``fn`` lowered for CUDA."""
    text = export.export(jax.jit(fn), platforms=["cuda"])(*args).mlir_module()
    products = [line.strip() for line in text.splitlines() if _PRODUCT.search(line)]
    return len(products), [p[:240] for p in products if not _full_precision(p)]


# Bucket sides above textures.atlas._UNROLL_MAX take the einsum path of the mip pyramid.
_SIDES = [0, 1, 3, 5, 8, 12, 24, 40] * 6


@pytest.mark.parametrize("config", [
    RenderConfig(mip="none"),
    RenderConfig(mip="nearest", coverage="prefilter"),
    RenderConfig(mip="trilinear", coverage="lowpass"),
], ids=["2dgs", "patexgs", "trilinear-lowpass"])
def test_render_lowered_for_cuda_states_full_precision(config):
    textured = config.mip != "none"
    sc = random_scene(3, 48, sh_degree=3, extent=0.8, scale_range=(0.08, 0.45),
                      rgb_sizes=_SIDES if textured else None, alpha_sizes=_SIDES if textured else None)
    cam = camera()

    def loss(s):
        out = render_jit(s, cam, config=config, capacity=CAP)
        return jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.normal) + jnp.sum(out.distortion)

    counts = []
    for fn in (lambda s: render_jit(s, cam, config=config, capacity=CAP).rgb, jax.grad(loss),
               lambda s: scene_textures(s, config=config)):
        count, low = _low_precision_products(fn, sc)
        assert not low, f"{len(low)} of {count} products without precision=HIGHEST:\n" + "\n".join(low)
        counts.append(count)
    assert counts[0] > 0 and counts[1] > counts[0]  # the check saw the products (camera, SH, compositing)


def test_training_step_lowered_for_cuda_states_full_precision():
    """The whole training step: render, losses (L1, SSIM, normal consistency, distortion), gradients,
    densification statistics and Adam."""
    sc = random_scene(4, 48, sh_degree=3, extent=0.8, scale_range=(0.08, 0.45), rgb_sizes=_SIDES, alpha_sizes=_SIDES)
    cam = camera()
    opt = make_optimizer(1.0)
    config = RenderConfig(mip="nearest", coverage="prefilter")

    def step(s, o, st, img):
        return single_view_step(s, o, st, cam, img, jnp.array([cam.height, cam.width], jnp.int32), 3, 0.05,
                                optimizer=opt, render_config=config, capacity=CAP, lambda_dssim=0.2,
                                lambda_dist=100.0)

    img = jnp.zeros((cam.height, cam.width, 3), jnp.float32)
    count, low = _low_precision_products(step, sc, opt.init(sc), DensifyStats.zeros(sc.capacity), img)
    assert count > 0 and not low, f"{len(low)} of {count} products without precision=HIGHEST:\n" + "\n".join(low)


def test_metrics_lowered_for_cuda_state_full_precision():
    from patexgs_jax import metrics

    a = jnp.linspace(0, 1, 40 * 36 * 3, dtype=jnp.float32).reshape(36, 40, 3)
    for fn in (lambda x, y: metrics.ssim(x, y), lambda x, y: metrics.psnr(x, y)):
        _, low = _low_precision_products(fn, a, a[::-1])
        assert not low, low


def test_precision_parser():
    assert _full_precision("%1 = stablehlo.dot_general %a, %b, contracting_dims = [1] x [0], "
                           "precision = [HIGHEST, HIGHEST] : (tensor<4x3xf32>, ...)")
    assert _full_precision("%1 = stablehlo.dot_general %a, %b, precision_config = [#stablehlo<precision HIGHEST>, "
                           "#stablehlo<precision HIGHEST>] : ...")
    assert not _full_precision("%1 = stablehlo.dot_general %a, %b, contracting_dims = [1] x [0] : (tensor<4x3xf32>)")
    assert not _full_precision("%1 = stablehlo.dot_general %a, %b, precision = [DEFAULT, DEFAULT] : ...")
    assert not _full_precision("%1 = stablehlo.dot_general %a, %b, precision = [HIGH, HIGHEST] : ...")


def test_render_config_replace_keeps_resolved_fields():
    cfg = RenderConfig(coverage="prefilter")
    assert dataclasses.replace(cfg, tile_batch=4).lambda_mip == cfg.lambda_mip


def test_viewer_frames_take_the_device_schedule_off_the_cpu():
    from patexgs_jax.viewer import frames as vw

    assert vw.frame_schedule("cpu") == vw.FRAME_SCHEDULE
    assert vw.frame_schedule("gpu") == {} and vw.frame_schedule("tpu") == {}
