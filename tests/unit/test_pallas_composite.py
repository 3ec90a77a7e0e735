"""The Pallas compositor (``RenderConfig(compositor="pallas")``, :mod:`patexgs_jax.rendering.pallas_composite`),
quick checks: its configuration, one shared case against the XLA compositor in Pallas's interpret
mode (values and gradients; on a GPU, which the device check runs this file on, the compiled
kernel), and its forward and backward lowered for CUDA (Triton) on a machine without a GPU. The
other cases are in tests/integration/test_pallas_untextured.py and test_pallas_textures.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

from pallas_cases import compare
from patexgs_jax import RenderConfig
from patexgs_jax.rendering import pallas_composite
from patexgs_jax.rendering.chunks import CompositeInputs, Static
from patexgs_jax.rendering.config import resolve_compositor
from patexgs_jax.rendering.projection import COLS
from render_cases import CAP, CONFIGS, camera, scene


def test_config():
    assert RenderConfig().compositor is None
    assert resolve_compositor(RenderConfig()) == "xla"  # None: XLA off a GPU
    assert resolve_compositor(RenderConfig(compositor="pallas")) == "pallas"
    # Off a GPU the kernel runs in Pallas's interpreter; on one (the device check) compiled.
    assert pallas_composite._interpret() == (jax.default_backend() != "gpu")
    with pytest.raises(ValueError, match="compositor"):
        RenderConfig(compositor="triton")
    with pytest.raises(ValueError, match="power-of-two"):
        RenderConfig(compositor="pallas", tile_size=12)
    RenderConfig(compositor="xla", tile_size=12)  # the XLA compositor takes any tile size


def test_matches_xla_compositor():
    """Outputs and the gradients of the scene and screen_offset, 2DGS (lowpass) coverage."""
    _, degree, cfg = CONFIGS["2dgs"]
    compare(scene(4, False, degree), camera(), cfg, CAP)


@pytest.mark.parametrize("coverage,textured,mip", [("lowpass", False, "none"), ("prefilter", False, "none"),
                                                  ("lowpass", True, "nearest"), ("prefilter", True, "trilinear")])
def test_lowers_for_cuda(coverage, textured, mip):
    """The kernel's forward and backward lower for the GPU (Triton) on a machine without one: a
    change that the GPU lowering rejects (a primitive Triton has no rule for, a vector that is not
    a power of two) fails here. jax 0.10 lowers Triton kernels for "cuda" without a device (taking
    compute capability 9.0 where none is present); compiling the Triton IR to PTX happens in XLA's
    GPU compiler, on the GPU machine."""
    cfg = RenderConfig(mip=mip, coverage=coverage, compositor="pallas")
    st = Static(config=cfg, tiles_x=3, num_tiles=6, rgb=textured, alpha=textured)
    width = COLS.width_prefilter if st.prefilter else COLS.width
    sd = jax.ShapeDtypeStruct
    ctx = CompositeInputs(ids_sorted=sd((1024,), jnp.int32), tile_start=sd((6,), jnp.int32),
                          binned=sd((6,), jnp.int32), peak=sd((48,), jnp.float32), flag=sd((), jnp.bool_))
    texels = (None, None)
    if textured:
        ctx = ctx._replace(tex_meta=sd((48, 8), jnp.int32), rgb_has=sd((48,), jnp.bool_),
                           alpha_has=sd((48,), jnp.bool_))
        texels = (sd((4000, 3), jnp.float32), sd((3000, 1), jnp.float32))

    def loss(packed, texels, ctx):
        acc, t_final, _ = pallas_composite.composite_tiles(st, packed, *texels, ctx, interpret=False)
        return jnp.sum(acc) + jnp.sum(t_final)

    args = (sd((48, width), jnp.float32), texels, ctx)
    lowered = jax.jit(jax.value_and_grad(loss, argnums=(0, 1))).trace(*args).lower(lowering_platforms=("cuda",))
    text = lowered.as_text()
    assert text.count("__gpu$xla.gpu.triton") == 2  # the forward kernel and the backward kernel
