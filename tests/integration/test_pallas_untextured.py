"""The Pallas compositor (``RenderConfig(compositor="pallas")``, interpreted on the CPU) against the
XLA compositor on the renderer's shared cases and the hard cases, without textures: every output,
and the gradients (tests/pallas_cases.py says to what tolerance and why). The quick checks are in
tests/unit/test_pallas_composite.py, the textured renderer in test_pallas_textures.py."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hard_scenes as hs
from pallas_cases import compare, render_and_grad
from patexgs_jax import Capacity, RenderConfig
from render_cases import CAP, CONFIGS, camera, scene

HARD_CFG = RenderConfig(mip="none", background=(0.2, 0.5, 0.8), near=hs.NEAR)
HARD_CAP = Capacity(pairs=8192)


@pytest.mark.parametrize("name", ["prefilter-2dgs"])
def test_shared_cases(name):
    """Outputs and the gradients of the scene and screen_offset (the unit test has "2dgs", the
    textured cases are in test_pallas_textures.py)."""
    _, degree, cfg = CONFIGS[name]
    compare(scene(7 + len(name), False, degree), camera(), dataclasses.replace(cfg, mip="none"), CAP)


def test_float64_same_maths():
    """In float64 the kernel and the XLA compositor agree to rounding: the same formulas (float32
    differences are the order of sums and products only)."""
    _, degree, cfg = CONFIGS["2dgs"]
    with jax.enable_x64(True):
        sc = scene(5, False, degree).astype(jnp.float64)
        runs = [jax.tree_util.tree_map(np.asarray, render_and_grad(
            sc, camera(), dataclasses.replace(cfg, compositor=c), CAP)) for c in ("xla", "pallas")]
    (out_x, g_x), (out_p, g_p) = runs
    for f in ("rgb", "alpha", "depth", "normal", "distortion"):
        np.testing.assert_allclose(getattr(out_p, f), getattr(out_x, f), rtol=1e-9, atol=1e-11, err_msg=f)
    np.testing.assert_array_equal(out_p.dominant, out_x.dominant)
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g_x), jax.tree_util.tree_leaves(g_p), strict=True):
        if np.issubdtype(a.dtype, np.floating) and a.size:
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * float(np.abs(a).max()) + 1e-12,
                                       err_msg=jax.tree_util.keystr(path))


@pytest.mark.parametrize("coverage", ["lowpass", "prefilter"])
@pytest.mark.parametrize("case", hs.CASES)
def test_hard_cases(case, coverage):
    """Every hard case (tests/hard_scenes.py) at two seeds and knobs, textures left out. Gradients
    at the compositor's own level (the packed splat columns); ill-conditioned cases (splat centres
    within rounding of the near plane) to 1e-2 of each column's range."""
    cfg = dataclasses.replace(HARD_CFG, coverage=coverage)
    for seed, knob in ((0, 0.1), (1, 0.5)):
        sc, cam, info = hs.build(case, seed, knob)
        rtol = 1e-2 if info["ill_conditioned"] else None
        compare(sc.replace(rgb=None, alpha=None), cam, cfg, HARD_CAP, level="packed", packed_rtol=rtol)


@pytest.mark.parametrize("coverage", ["lowpass", "prefilter"])
@pytest.mark.parametrize("n,seed", [(600, 1), (hs.C, 2)])
def test_splats_piled_on_one_pixel(n, seed, coverage):
    """Hundreds to thousands of splats along one pixel's ray: the kernel's long lists and its stop."""
    sc, cam = hs.pile_on_one_pixel(seed, n)
    compare(sc.replace(rgb=None, alpha=None), cam, dataclasses.replace(HARD_CFG, coverage=coverage), HARD_CAP,
            level="packed")


@pytest.mark.parametrize("coverage", ["lowpass", "prefilter"])
def test_3d_gaussians(coverage):
    """3D Gaussians (3DGS's dilation, Mip-Splatting's 2D filter) composite through the same
    screen-space kernel: the Pallas compositor matches the XLA one, outputs and scene gradients."""
    from patexgs_jax import random_scene

    sc = random_scene(3, 60, scale_dims=3)
    compare(sc, camera(), RenderConfig(coverage=coverage, mip="none"), CAP)


def test_billboards_are_refused():
    """The kernel has no billboard square: asking for it names the fix."""
    with pytest.raises(ValueError, match="compositor='xla'"):
        RenderConfig(coverage="billboard", compositor="pallas")
