"""The BBSplat and Textured Gaussians baselines (docs/baselines.md): their method names and stage-2
render settings, their shared stage 1, and the Gaussian alpha textures billboards start from."""

from __future__ import annotations

import numpy as np
import pytest

from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, render_jit
from patexgs_jax.render import LAMBDA_MIP_DEFAULT
from patexgs_jax.textures.billboard_alpha import gaussian_alpha, with_gaussian_alpha
from patexgs_jax.training.config import METHODS, Method, TrainConfig, stage1_key
from patexgs_jax.viewer.frames import MODES, mode_config, own_mode

BILLBOARDS = ("bbsplat", "bbsplat+mip", "bbsplat+adaptive")


@pytest.mark.parametrize("name", BILLBOARDS + ("textured-gaussians",))
def test_methods_are_registered(name):
    spec = Method.from_name(name)
    assert spec is METHODS[name]
    rc = TrainConfig(method=name, iters_tex=100, warmup_tex=10).render_config()
    assert rc.coverage == ("lowpass" if name == "textured-gaussians" else "billboard")
    assert rc.mip == ("nearest" if name == "bbsplat+mip" else "none")
    assert spec.grows == (name == "bbsplat+adaptive")
    assert spec.size == {"bbsplat": 16, "bbsplat+mip": 16, "bbsplat+adaptive": None, "textured-gaussians": 8}[name]


def test_textured_gaussians_is_textured_fixed_8():
    assert Method.from_name("textured-gaussians") == Method.from_name("textured-fixed-8")


@pytest.mark.parametrize("name", BILLBOARDS + ("textured-gaussians",))
def test_stage1_is_shared_with_2dgs(name):
    """The table protocol: every method starts its texture stage from the same 2DGS checkpoint."""
    assert stage1_key(TrainConfig(method=name)) == stage1_key(TrainConfig(method="2dgs"))


def test_billboard_lambda_mip_is_the_paper_value_in_bbsplat_units():
    """lambda 0.4 (the paper's, used for BBSplat + our_mipmap) with BBSplat's textures over 2 of its
    scale units: a texture over 6 of ours, so lambda n D is the same for 0.4 / 3."""
    assert RenderConfig(coverage="billboard").lambda_mip == pytest.approx(0.4 / 3.0, rel=1e-12)
    assert LAMBDA_MIP_DEFAULT["billboard"] == pytest.approx(0.4 / 3.0, rel=1e-12)


def test_gaussian_alpha():
    a = gaussian_alpha(16)
    assert a.shape == (16, 16) and a.dtype == np.float32
    np.testing.assert_allclose(a, a.T, atol=0, rtol=0)
    np.testing.assert_allclose(a, a[::-1, ::-1], atol=1e-7, rtol=0)
    np.testing.assert_allclose(a[0, 0], np.exp(-9.0), rtol=1e-6, atol=0)
    np.testing.assert_allclose(gaussian_alpha(5)[2, 2], 1.0, rtol=0, atol=1e-7)
    # The 1 x 1 constant is the Gaussian's mean over the square: its integrated alpha.
    x = np.linspace(-3, 3, 6001)
    mean = np.trapezoid(np.exp(-0.5 * x * x), x) / 6.0
    np.testing.assert_allclose(gaussian_alpha(1)[0, 0], mean ** 2, rtol=1e-6, atol=0)


def test_with_gaussian_alpha_fills_the_used_block_only():
    sizes = [16, 5, 3, 0, 16, 5]
    sc = Scene.from_arrays(np.zeros((6, 3)), np.full((6, 2), 0.1), np.tile([1.0, 0, 0, 0], (6, 1)), np.full(6, 0.5),
                           np.zeros((6, 1, 3)), alpha_textures=[None if n == 0 else np.ones((n, n)) for n in sizes])
    active = np.array([1, 1, 1, 1, 0, 1], np.float32)
    out = with_gaussian_alpha(sc, active)
    for i, n in enumerate(sizes):
        t = out.alpha.texture(i)
        if n == 0:
            assert t is None
            continue
        want = gaussian_alpha(n) if active[i] else np.ones((n, n), np.float32)
        np.testing.assert_allclose(t[..., 0], want, atol=0, rtol=0)
    for b_old, b_new in zip(sc.alpha.buckets, out.alpha.buckets):  # the slots' padding stays zero
        pad_old = np.asarray(b_old) == 0
        assert np.all(np.asarray(b_new)[pad_old] == 0) or b_new.shape[1] == 1


@pytest.mark.parametrize("n", [16, 5])
def test_billboard_with_gaussian_alpha_renders_the_2dgs_splat(n):
    """The stage-2 start of the bbsplat methods: a billboard whose alpha texture is the sampled
    Gaussian renders the 2DGS splat it replaces, up to the bilinear interpolation between texels
    (and the 2DGS low-pass, which a resolved splat does not reach)."""
    cam = Camera.from_intrinsics([100.0, 100.0, 32.0, 24.0], look_at((0.0, -0.3, -2.0), (0.0, 0.0, 0.0)), 64, 48)
    quat = [np.cos(0.2), 0.1, 0.15, 0.05]
    args = ([[0.05, 0.02, 0.0]], [[0.12, 0.08]], [quat], [0.9], np.full((1, 1, 3), 0.5))
    gauss = Scene.from_arrays(*args, capacity=4)
    bb = with_gaussian_alpha(Scene.from_arrays(*args, alpha_textures=[np.ones((n, n))], capacity=4))
    cap = Capacity(pairs=1024)
    a = np.asarray(render_jit(gauss, cam, config=RenderConfig(mip="none"), capacity=cap).alpha)
    b = np.asarray(render_jit(bb, cam, config=RenderConfig(mip="none", coverage="billboard"), capacity=cap).alpha)
    # Bilinear interpolation of exp(-u^2 / 2) exp(-v^2 / 2) between texels h = 6 / (n - 1) apart is
    # off by at most h^2 / 8 max|f''| <= h^2 / 8 per axis: 0.036 (n = 16) and 0.51 (n = 5) at opacity 0.9.
    h = 6.0 / (n - 1)
    assert a.max() > 0.85
    np.testing.assert_allclose(b, a, atol=0.9 * h * h / 4.0, rtol=0)
    np.testing.assert_allclose(b.sum(), a.sum(), rtol={16: 0.02, 5: 0.05}[n], atol=0)


@pytest.mark.parametrize("name", ["bbsplat", "bbsplat+mip"])
def test_viewer_keeps_billboards_in_every_mode(name):
    """The viewer's coverage modes switch a billboard run's mip levels, never its coverage."""
    base = TrainConfig(method=name).render_config()
    for mode in MODES:
        rc = mode_config(base, mode)
        assert rc.coverage == "billboard" and rc.lambda_mip == base.lambda_mip
        assert rc.mip == ("none" if mode == "mip-off" else "nearest")
    assert mode_config(base, own_mode(base)).mip == base.mip
