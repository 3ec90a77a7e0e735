"""The Pallas compositor (``RenderConfig(compositor="pallas")``, :mod:`patexgs_jax.rendering.pallas_composite`),
quick checks: its configuration, one shared case against the XLA compositor in Pallas's interpret
mode (values and gradients), and its forward and backward lowered for CUDA (Triton) on this CPU
machine. The other cases are in tests/integration/test_pallas_composite.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest
from pallas_cases import compare

from patexgs_jax import RenderConfig, render_jit
from patexgs_jax.rendering import pallas_composite
from patexgs_jax.rendering.chunks import Static
from patexgs_jax.rendering.projection import COLS
from render_cases import CAP, CONFIGS, camera, scene


def test_config():
    assert RenderConfig().compositor is None
    assert pallas_composite.resolve_compositor(RenderConfig()) == "xla"  # None: XLA off a GPU
    assert pallas_composite.resolve_compositor(RenderConfig(compositor="pallas")) == "pallas"
    assert pallas_composite._interpret()  # off a GPU the kernel runs in Pallas's interpreter
    with pytest.raises(ValueError, match="compositor"):
        RenderConfig(compositor="triton")
    with pytest.raises(ValueError, match="power-of-two"):
        RenderConfig(compositor="pallas", tile_size=12)
    RenderConfig(compositor="xla", tile_size=12)  # the XLA compositor takes any tile size


def test_textured_scene_raises():
    cfg = RenderConfig(mip="none", compositor="pallas")
    with pytest.raises(NotImplementedError, match="untextured"):
        render_jit(scene(1, textured=True), camera(), config=cfg, capacity=CAP)


def test_matches_xla_compositor():
    """Outputs and the gradients of the scene and screen_offset, 2DGS (lowpass) coverage."""
    _, degree, cfg = CONFIGS["2dgs"]
    compare(scene(4, False, degree), camera(), cfg, CAP)


@pytest.mark.parametrize("coverage", ["lowpass", "prefilter"])
def test_lowers_for_cuda(coverage):
    """The kernel's forward and backward lower for the GPU (Triton) on a machine without one: a
    change that the GPU lowering rejects (a primitive Triton has no rule for, a vector that is not
    a power of two) fails here. jax 0.10 lowers Triton kernels for "cuda" without a device;
    compiling the Triton IR to PTX happens in XLA's GPU compiler, on the GPU machine."""
    cfg = RenderConfig(mip="none", coverage=coverage, compositor="pallas")
    st = Static(config=cfg, tiles_x=3, num_tiles=6, rgb=False, alpha=False)
    width = COLS.width_prefilter if st.prefilter else COLS.width
    packed = jax.ShapeDtypeStruct((48, width), jnp.float32)
    ctx = {k: jax.ShapeDtypeStruct((n,), jnp.int32)
           for k, n in (("tile_start", 6), ("binned", 6), ("ids_sorted", 1024))}

    def loss(packed, ctx):
        acc, t_final, _ = pallas_composite.composite_tiles(st, packed, None, None, ctx, interpret=False)
        return jnp.sum(acc) + jnp.sum(t_final)

    lowered = jax.jit(jax.value_and_grad(loss)).trace(packed, ctx).lower(lowering_platforms=("cuda",))
    text = lowered.as_text()
    assert text.count("__gpu$xla.gpu.triton") == 2  # the forward kernel and the backward kernel
    assert "input_output_alias" in text or "tf.aliasing_output" in text or "output_operand_alias" in text

