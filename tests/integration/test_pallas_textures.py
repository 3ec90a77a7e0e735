"""The Pallas compositor's textured renderer (RGBA lookups with per-pixel mipmaps, nearest and
trilinear, both coverages; interpreted on the CPU) against the XLA compositor: every output, and
the gradients of the scene (texels included) and of screen_offset on the shared cases; outputs and
the texel gradients on the hard cases (tests/pallas_cases.py says to what tolerance and why). The
untextured cases are in tests/integration/test_pallas_untextured.py."""

from __future__ import annotations

import pytest
from pallas_cases import compare

import hard_scenes as hs
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


@pytest.mark.parametrize("case", hs.CASES)
def test_hard_cases(case):
    """The PATexGS renderer (prefilter coverage, nearest mipmaps) on every hard case: outputs, and
    the texture gradients (the others are ill-conditioned there: see
    tests/integration/test_pallas_untextured.py, which checks the compositor's own gradients)."""
    cfg = RenderConfig(mip="nearest", coverage="prefilter", background=(0.2, 0.5, 0.8), near=hs.NEAR)
    sc, cam, _ = hs.build(case, 3, 0.3)
    compare(sc, cam, cfg, Capacity(pairs=8192), level="texels")
