"""Two readings of the paper's Eq. 13 as coverage modes: ``"object"`` (Eq. 2's object-space G as
written, no screen-space low-pass) and ``"texel-grid"`` (G x A on the texel grid, in the alpha
pyramid, under the billboard square). docs/zoom_out.md measures them on trained models."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, render_jit

C, CAP = 4, Capacity(pairs=4096)
F, Z, SIDE = 100.0, 4.0, 48
CAM = Camera.from_intrinsics([F, F, SIDE / 2, SIDE / 2], look_at((0.0, 0.0, -Z), (0.0, 0.0, 0.0)), SIDE, SIDE)
OBJECT, LOWPASS = RenderConfig(coverage="object", mip="none"), RenderConfig(coverage="lowpass", mip="none")


def _splat(scale_px, offset_px=(0.0, 0.0), alpha=None):
    s = scale_px * Z / F
    mean = [[offset_px[0] * Z / F, offset_px[1] * Z / F, 0.0]]
    tex = {} if alpha is None else dict(rgb_textures=[None], alpha_textures=[alpha])
    return Scene.from_arrays(mean, [[s, 0.7 * s]], [[np.cos(0.3), 0.0, 0.0, np.sin(0.3)]], [0.5],
                             np.zeros((1, 1, 3)) + 0.3, capacity=C, **tex)


def _alpha(sc, cfg):
    out = render_jit(sc, CAM, config=cfg, capacity=CAP)
    assert not bool(out.overflow)
    return np.asarray(out.alpha)


def test_object_is_the_lowpass_where_the_splat_is_resolved_and_drops_a_sub_pixel_one():
    big = _splat(8.0)
    np.testing.assert_allclose(_alpha(big, OBJECT), _alpha(big, LOWPASS), atol=1e-5)
    # A 0.1-pixel splat on a pixel corner: no pixel centre within 7 of its standard deviations.
    tiny = _splat(0.1)
    assert _alpha(tiny, OBJECT).sum() < 1e-6 and _alpha(tiny, LOWPASS).sum() > 0.1


def test_texel_grid_at_level_0_is_eq_13_with_the_gaussian_sampled_on_the_texels():
    """An all-ones 32 x 32 alpha texture: G on the texel grid, interpolated bilinearly, is Eq. 2's G
    within the interpolation's error (h^2 / 8 max |G''| = 0.005 at the grid's spacing 6 / 31), and 0
    outside the texture's square (where G < 0.011)."""
    sc = _splat(6.0, alpha=np.ones((32, 32, 1), np.float32))
    grid = _alpha(sc, RenderConfig(coverage="texel-grid", mip="none"))
    np.testing.assert_allclose(grid, _alpha(sc, OBJECT), atol=0.5 * 0.012)
    assert grid.max() > 0.4


def test_texel_grid_coarsest_level_holds_the_pyramids_mean_of_g_times_a():
    """Zoomed out to the 1 x 1 level, every pixel centre the square holds gets the opacity times the
    pyramid's filtered G x A (A = 1): the texel grid's G through the bank's downsampling, 8 -> 4 -> 2 -> 1."""
    from patexgs_jax.textures.bank import downsample_matrix

    x = np.linspace(-3.0, 3.0, 8)
    mean = (downsample_matrix(2, 1) @ downsample_matrix(4, 2) @ downsample_matrix(8, 4) @ np.exp(-0.5 * x * x))[0]
    sc = _splat(0.5, alpha=np.ones((8, 8, 1), np.float32))
    a = _alpha(sc, RenderConfig(coverage="texel-grid", mip="nearest", lambda_mip=4.0))
    hit = a[a > 0]
    assert hit.size >= 1
    np.testing.assert_allclose(hit, 0.5 * mean**2, rtol=1e-5)


@pytest.mark.parametrize("coverage", ["object", "texel-grid"])
def test_readings_have_finite_gradients(coverage):
    sc = _splat(3.0, alpha=np.full((4, 4, 1), 0.8, np.float32))
    cfg = RenderConfig(coverage=coverage, mip="nearest")

    def loss(means):
        return jnp.sum(render_jit(sc.replace(means=means), CAM, config=cfg, capacity=CAP).rgb)

    g = np.asarray(jax.grad(loss)(sc.means))
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0


def test_texel_grid_refuses_an_untextured_scene_and_pallas_refuses_both():
    with pytest.raises(ValueError, match="texel-grid.*has none"):
        _alpha(_splat(2.0), RenderConfig(coverage="texel-grid"))
    for cov in ("object", "texel-grid"):
        with pytest.raises(ValueError, match="pallas"):
            RenderConfig(coverage=cov, compositor="pallas")
