"""The renderer's 3D Gaussians (rendering/gaussian3d.py: 3DGS's dilation, Mip-Splatting's 2D and 3D
filters) against their float64 brute-force reference, float64 finite differences, and hard cases
with every value and gradient finite. The tile cull and the densification's screen-offset gradient
of 3D Gaussians: tests/integration/test_gaussian3d_render.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gaussian3d_cases import CONFIGS, HARD, hard_scene3d, ref3d, scene3d
from patexgs_jax import Capacity, RenderConfig, Scene, random_scene, render_jit
from render_cases import C, camera, directional_fd_check, tile_render


@pytest.mark.parametrize("name", list(CONFIGS))
def test_matches_reference(name):
    filt, cfg = CONFIGS[name]
    sc = scene3d(7, filt)
    cam = camera()
    ref = ref3d(sc, cam, cfg)
    assert ref["alpha"].mean() > 0.2, "the test scene should cover much of the image"
    out64 = tile_render(sc, cam, cfg, jnp.float64)
    for k, atol in (("rgb", 1e-7), ("alpha", 1e-7), ("depth", 1e-6), ("normal", 1e-7), ("distortion", 1e-9)):
        np.testing.assert_allclose(getattr(out64, k), ref[k], atol=atol, rtol=1e-6, err_msg=k)
    best = ref["best"].ravel()
    np.testing.assert_array_equal(out64.max_contrib_count, np.bincount(best[best >= 0], minlength=C))
    out32 = tile_render(sc, cam, cfg)
    err = np.abs(out32.rgb - ref["rgb"]).max(axis=-1)
    assert np.mean(err > 2e-4) <= 0.005, (err.max(), np.mean(err > 2e-4))
    assert np.median(err) < 2e-5


@pytest.mark.parametrize("name", ["3dgs", "mip2d+3d"])
def test_gradients_match_finite_differences(name):
    filt, cfg = CONFIGS[name]
    sc = scene3d(21, filt)
    for seed in range(2):
        directional_fd_check(sc, camera(), cfg, seed, h=1e-7 if cfg.coverage == "prefilter" else 1e-6)


@pytest.mark.parametrize("case", HARD)
def test_hard_cases_finite(case):
    sc = hard_scene3d(case)
    cam = camera(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 1.0))
    for cov in ("lowpass", "prefilter"):
        cfg = RenderConfig(mip="none", coverage=cov)

        def loss(s, cfg=cfg):
            out = render_jit(s, cam, config=cfg, capacity=Capacity(pairs=1024))
            return (jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.normal) + jnp.sum(out.alpha)
                    + jnp.sum(out.distortion))

        val, g = jax.value_and_grad(loss)(sc)
        assert np.isfinite(float(val)), (case, cov)
        for path, leaf in jax.tree_util.tree_leaves_with_path(g):
            assert np.all(np.isfinite(np.asarray(leaf))), (case, cov, jax.tree_util.keystr(path))


def test_flat_gaussian_matches_reference_and_fades_with_the_mip_filter():
    """A Gaussian flattened to 1e-7 along an axis across the view (seen edge-on) keeps a
    0.3 px^2 line under 3DGS's dilation; Mip-Splatting's 2D filter scales its opacity by
    sqrt(det / det filtered), so it vanishes. Both as the float64 reference says."""
    sc = Scene.from_arrays([[0.0, 0.0, 0.0]], [[1e-7, 0.3, 0.3]], [[1.0, 0.0, 0.0, 0.0]], [0.9],
                           np.full((1, 1, 3), 1.0), capacity=C)
    cam = camera(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 1.0))
    sums = {}
    for cov, name in (("lowpass", "3dgs"), ("prefilter", "mip2d")):
        cfg = CONFIGS[name][1]  # (the programs of test_matches_reference)
        ref = ref3d(sc, cam, cfg)
        out = tile_render(sc, cam, cfg)
        np.testing.assert_allclose(out.rgb, ref["rgb"], atol=2e-4, rtol=0)
        sums[cov] = float(ref["alpha"].sum())
    assert sums["lowpass"] > 1.0 and sums["prefilter"] < 1e-3, sums


def test_textures_are_refused_on_3d_gaussians():
    sc = random_scene(0, 4, rgb_sizes=[2, 0, 0, 0])
    sc3 = sc.replace(log_scales=jnp.zeros((4, 3), jnp.float32))
    with pytest.raises(ValueError, match="textures are not supported on 3D Gaussians"):
        render_jit(sc3, camera(), config=RenderConfig(), capacity=Capacity(1024))
    with pytest.raises(ValueError, match="take no textures"):
        Scene.from_arrays(np.zeros((1, 3)), np.ones((1, 3)), [[1.0, 0, 0, 0]], [0.5], np.zeros((1, 3)),
                          rgb_textures=[None])
