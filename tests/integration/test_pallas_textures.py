"""The Pallas compositor's textured renderer (RGBA lookups with per-pixel mipmaps, nearest and
trilinear, both coverages; interpreted on the CPU) against the XLA compositor: every output, and
the gradients of the scene (texels included) and of screen_offset on the shared cases; outputs and
the texel gradients on the hard cases (tests/pallas_cases.py says to what tolerance and why). The
untextured cases are in tests/integration/test_pallas_untextured.py."""

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


@pytest.mark.parametrize("name", ["trilinear"])
def test_shared_cases(name):
    """Trilinear mipmaps with the 2DGS coverage (the level blend's gradient through the footprint);
    the hard cases below take the other coverage and mip mode. Each configuration is a compile of
    both renderers and their gradients: about 50 s here."""
    textured, degree, cfg = CONFIGS[name]
    assert textured
    compare(scene(11 + len(name), True, degree), camera(), cfg, CAP)


def test_float64_same_maths():
    """In float64 the kernel's textured renderer and the XLA compositor's agree to rounding: its
    hand-derived backward (texels, (u, v), the trilinear level through the footprint) is the same
    derivative as autodiff's of the XLA lookups."""
    _, degree, cfg = CONFIGS["trilinear"]
    with jax.enable_x64(True):
        sc = scene(6, True, degree).astype(jnp.float64)
        runs = [jax.tree_util.tree_map(np.asarray, render_and_grad(
            sc, camera(), dataclasses.replace(cfg, compositor=c), CAP)) for c in ("xla", "pallas")]
    (out_x, g_x), (out_p, g_p) = runs
    for f in ("rgb", "alpha", "depth", "normal", "distortion"):
        np.testing.assert_allclose(getattr(out_p, f), getattr(out_x, f), rtol=1e-9, atol=1e-11, err_msg=f)
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g_x), jax.tree_util.tree_leaves(g_p), strict=True):
        if np.issubdtype(a.dtype, np.floating) and a.size:
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * float(np.abs(a).max()) + 1e-12,
                                       err_msg=jax.tree_util.keystr(path))


@pytest.mark.parametrize("case", hs.CASES)
def test_hard_cases(case):
    """The PATexGS renderer (prefilter coverage, nearest mipmaps) on every hard case: outputs, and
    the texture gradients (the others are ill-conditioned there: see
    tests/integration/test_pallas_untextured.py, which checks the compositor's own gradients)."""
    cfg = RenderConfig(mip="nearest", coverage="prefilter", background=(0.2, 0.5, 0.8), near=hs.NEAR)
    sc, cam, _ = hs.build(case, 3, 0.3)
    compare(sc, cam, cfg, Capacity(pairs=8192), level="texels")
