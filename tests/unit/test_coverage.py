"""The prefiltered coverage (``RenderConfig(coverage="prefilter")``, the patexgs methods' mode):
integrated coverage, edge-on and near-edge-on splats, the mip level rule, and the literal (2DGS
low-pass) mode's images kept bit for bit. Zoom-out consistency with a supersampled render is in
tests/integration/test_render_sweeps.py.

Every render here has capacity 48 and a few image sizes, so compiled renderers are shared.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from locations import TEST_DATA
from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, render_jit
from patexgs_jax.data.images import box_downsample
from patexgs_jax.training import TrainConfig
from render_reference import tent_down

C = 48
CAP = Capacity(pairs=8192)
PREFILTER = TrainConfig(method="patexgs").render_config()
LITERAL = TrainConfig(method="patexgs-literal").render_config()


def _render(sc, cam, cfg):
    out = render_jit(sc, cam, config=cfg, capacity=CAP)
    assert not bool(out.overflow)
    return out


def test_method_modes():
    """The patexgs family prefilters; the baselines and patexgs-literal keep the 2DGS low-pass and
    the paper's lambda_mip; stage 1 is the 2DGS renderer for every method."""
    assert PREFILTER.coverage == "prefilter" and PREFILTER.mip == "nearest"
    assert LITERAL.coverage == "lowpass" and LITERAL.lambda_mip == 0.4
    for m in ("2dgs", "textured-fixed-8"):
        assert TrainConfig(method=m).render_config().coverage == "lowpass"
    for m in ("patexgs-no-mip", "patexgs-trilinear", "patexgs-no-adaptive"):
        assert TrainConfig(method=m).render_config().coverage == "prefilter"
    stage1 = {TrainConfig(method=m).render_config(stage=1) for m in ("2dgs", "patexgs", "textured-fixed-4")}
    assert stage1 == {TrainConfig(method="2dgs").render_config()}


# ---------------------------------------------------------------------------------------------
# Coverage: a splat's summed alpha is its integrated coverage, whatever its size
# ---------------------------------------------------------------------------------------------
F, Z, SIDE = 100.0, 4.0, 48
CAM = Camera.from_intrinsics([F, F, SIDE / 2, SIDE / 2], look_at((0.0, 0.0, -Z), (0.0, 0.0, 0.0)), SIDE, SIDE)


def _splat(scale_px, offset_px, opacity, aspect=0.7):
    """One untextured splat facing the camera, rotated in its plane, ``scale_px`` x ``aspect``
    scale_px pixels of standard deviation, its centre ``offset_px`` from the image centre."""
    s = scale_px * Z / F
    mean = [[offset_px[0] * Z / F, offset_px[1] * Z / F, 0.0]]
    q = [[np.cos(0.3), 0.0, 0.0, np.sin(0.3)]]
    return Scene.from_arrays(mean, [[s, aspect * s]], q, [opacity], np.zeros((1, 1, 3)) + 0.3, capacity=C)


@pytest.mark.parametrize("scale_px", [0.1, 0.3, 1.0, 3.0, 10.0])
def test_summed_alpha_is_integrated_coverage(scale_px):
    """Opacity 0.3 (far from the 0.99 cap): sum of alpha over the image = opacity x 2 pi x the
    product of the screen standard deviations, within 5%, at sub-pixel positions between pixel
    centres and on one. (The low-pass widens a 0.1-pixel splat to a pixel: tens of times more.)"""
    rng = np.random.default_rng(int(scale_px * 10))
    want = 0.3 * 2 * np.pi * scale_px * scale_px * 0.7
    for offset in [(0.0, 0.0), (0.5, 0.5)] + [tuple(rng.uniform(0, 1, 2)) for _ in range(2)]:
        got = float(np.sum(_render(_splat(scale_px, offset, 0.3), CAM, PREFILTER).alpha))
        assert abs(got / want - 1) < 0.05, (offset, got / want)
    if scale_px <= 0.3:
        lowpass = float(np.sum(_render(_splat(scale_px, (0.0, 0.0), 0.3), CAM, LITERAL).alpha))
        assert lowpass > 5 * want


def _projected_integral(sc, cam, n=801):
    """The integral over the screen (px^2) of splat 0's Gaussian, by quadrature over its plane:
    exp(-|h|^2 / 2) times the area element |det H| / w(h)^3 of the plane-to-image homography H
    (w its third row), exact under perspective."""
    from render_reference import quat_rot

    R = quat_rot(np.asarray(sc.quats[0], np.float64))
    s = np.exp(np.asarray(sc.log_scales[0], np.float64))
    w2c = np.asarray(cam.world_to_camera, np.float64)
    cols = [w2c[:3, :3] @ (R[:, 0] * s[0]), w2c[:3, :3] @ (R[:, 1] * s[1]),
            w2c[:3, :3] @ np.asarray(sc.means[0], np.float64) + w2c[:3, 3]]
    Hm = np.asarray(cam.K, np.float64) @ np.stack(cols, axis=1)
    h = np.linspace(-6, 6, n)
    u, v = np.meshgrid(h, h)
    w = Hm[2, 0] * u + Hm[2, 1] * v + Hm[2, 2]
    dA = (h[1] - h[0]) ** 2
    return float(np.sum(np.exp(-0.5 * (u * u + v * v)) * abs(np.linalg.det(Hm)) / np.abs(w) ** 3) * dA)


def test_edge_on_splat_has_no_coverage_and_finite_gradient():
    """A splat seen exactly edge-on covers nothing (a line has no area); tilted slightly, it covers
    what its projected area says."""
    import jax

    for tilt in (0.0, 0.05):
        q = [[np.cos(np.pi / 4 - tilt / 2), np.sin(np.pi / 4 - tilt / 2), 0.0, 0.0]]   # about x
        sc = Scene.from_arrays([[0.0, 0.0, 0.0]], [[0.2, 0.2]], q, [0.5], np.zeros((1, 1, 3)) + 0.3, capacity=C)
        out = _render(sc, CAM, PREFILTER)
        area = 0.5 * _projected_integral(sc, CAM)
        got = float(np.sum(out.alpha))
        if tilt == 0:
            assert got < 1e-4, got
        else:
            assert abs(got / area - 1) < 0.05, got / area
        g = jax.grad(lambda s: jnp.sum(render_jit(s, CAM, config=PREFILTER, capacity=CAP).rgb))(sc)
        for leaf in jax.tree_util.tree_leaves(g):
            assert np.all(np.isfinite(np.asarray(leaf)))


@pytest.mark.parametrize("tilt", [0.003, 0.01])
def test_near_edge_on_splat_stays_on_its_screen_footprint(tilt):
    """Within 0.6 degrees of edge-on, the prefiltered ellipse in the splat's plane reaches behind the
    camera (on screen it is unbounded: such a splat was listed in all 256 tiles of this image). The
    kernel is cut to twice its affine screen footprint: a few tiles around the splat's line, and
    nothing beyond a few pixels of it."""
    from patexgs_jax.render import count_pairs

    side = 256
    cam = Camera.from_intrinsics([F, F, side / 2, side / 2], look_at((0.0, 0.0, -Z), (0.0, 0.0, 0.0)), side, side)
    q = [[np.cos(np.pi / 4 - tilt / 2), np.sin(np.pi / 4 - tilt / 2), 0.0, 0.0]]
    sc = Scene.from_arrays([[0.0, 0.0, 0.0]], [[0.2, 0.2]], q, [0.9], np.zeros((1, 1, 3)) + 0.3, capacity=C)
    pairs, _ = count_pairs(sc, cam, PREFILTER)
    assert int(pairs) <= 12, int(pairs)
    alpha = np.asarray(_render(sc, cam, PREFILTER).alpha)
    ys, xs = np.nonzero(alpha > 0)
    assert alpha.sum() > 1 and ys.min() >= side / 2 - 5 and ys.max() <= side / 2 + 5, (ys.min(), ys.max())


def test_wall_of_small_opaque_splats_stays_nearly_opaque():
    """A wall tiled by opaque splats (0.98), each smaller than a pixel zoomed out: compositing k
    splats of coverage c leaves (1 - c)^k of the background where the supersampled render has
    none, so the prefiltered wall is somewhat see-through. Bound: within 0.1 of the supersampled
    alpha at 1/4 and 1/8 (measured: 0.90-0.92 against 0.96; the low-pass gives 1.0)."""
    n, side = 24, 96
    g = (np.arange(n) + 0.5) / n * 2 - 1
    X, Y = np.meshgrid(g, g)
    means = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], 1)
    sc = Scene.from_arrays(means, np.full((n * n, 2), 0.6 * 2 / n), np.tile([1.0, 0, 0, 0], (n * n, 1)),
                           np.full(n * n, 0.98), np.zeros((n * n, 1, 3)) + 1.0, capacity=n * n)
    cam = Camera.from_intrinsics([0.9 * side] * 2 + [side / 2] * 2, look_at((0, 0, -3.0), (0, 0, 0)), side, side)
    cap = Capacity(pairs=1 << 14)
    full = np.asarray(render_jit(sc, cam, config=PREFILTER, capacity=cap).alpha)
    for f in (4, 8):
        small = np.asarray(render_jit(sc, cam.scaled(f), config=PREFILTER, capacity=cap).alpha)
        ref = box_downsample(full[..., None], f)[..., 0]
        c = slice(small.shape[0] // 2 - small.shape[0] // 8, small.shape[0] // 2 + small.shape[0] // 8)
        assert ref[c, c].mean() > 0.95
        assert small[c, c].mean() > ref[c, c].mean() - 0.1, (f, small[c, c].mean(), ref[c, c].mean())


# ---------------------------------------------------------------------------------------------
# Mip levels: level floor(log2(n D / 6)) (texels per pixel), level 0 under magnification
# ---------------------------------------------------------------------------------------------
def _textured_splat(tex, scale):
    q = [[1.0, 0.0, 0.0, 0.0]]
    sh = np.zeros((1, 1, 3)) + 0.2
    return Scene.from_arrays([[0.0, 0.0, 0.0]], [[scale, scale]], q, [0.9], sh, rgb_textures=[tex], capacity=C)


@pytest.mark.parametrize("texels_per_pixel, level", [(0.5, 0), (1.9, 0), (2.1, 1), (3.8, 1), (4.3, 2)])
def test_mip_level_follows_texels_per_pixel(texels_per_pixel, level):
    """A 16 x 16 texture on a splat facing the camera, D scale units per pixel: the prefilter
    samples level floor(log2(lambda n D)), lambda = 1/6 (n D / 6 texels per pixel). The render
    equals, to rounding, the same splat carrying that level as its (mip-less) texture."""
    n = 16
    tex = np.random.default_rng(0).uniform(-0.3, 0.3, (n, n, 3))
    D = texels_per_pixel * 6 / n                       # scale units per pixel
    scale = Z / (F * D)                                # D = (Z / F) / scale at the centre
    levels = [tex]
    while len(levels) <= level:
        levels.append(tent_down(levels[-1], levels[-1].shape[0] // 2))
    got = _render(_textured_splat(tex, scale), CAM, PREFILTER)
    want = _render(_textured_splat(levels[level], scale), CAM, RenderConfig(coverage="prefilter", mip="none"))
    np.testing.assert_allclose(got.rgb, want.rgb, atol=2e-6, rtol=0)
    assert got.alpha.max() > 0.4


# ---------------------------------------------------------------------------------------------
# The literal mode: today's images, unchanged
# ---------------------------------------------------------------------------------------------
def test_literal_mode_reproduces_the_low_pass_renderer():
    """``patexgs-literal`` (and ``2dgs``) render the images of the renderer before the prefilter
    existed (commit b7ee7fa, stored in tests/data): the 44 x 36 textured scene of tests/render_cases.py
    with nearest and trilinear mipmaps, and untextured."""
    from render_cases import CAP as RCAP
    from render_cases import camera, scene

    gold = np.load(TEST_DATA / "literal_mode_b7ee7fa.npz")
    cases = {"nearest": (LITERAL, True),
             "trilinear": (RenderConfig(mip="trilinear", lambda_mip=0.4), True),
             "2dgs": (TrainConfig(method="2dgs").render_config(), False)}
    # Equal up to float32 rounding: another CPU (vector width) or XLA optimisation level sums in
    # another order, which moves depths of ~2 by up to 1.3e-5 and colours by up to 5e-6 (measured on
    # an AMD EPYC against the Intel Xeon that wrote the file). Any real change is far larger: lambda
    # 0.41 for 0.4 moves colours by 0.04, a background of 0.001 by 0.001.
    for name, (cfg, textured) in cases.items():
        out = render_jit(scene(7, textured, 1), camera(), config=cfg, capacity=RCAP)
        for k in ("rgb", "alpha", "depth"):
            np.testing.assert_allclose(np.asarray(getattr(out, k)), gold[f"{name}_{k}"], rtol=5e-5, atol=5e-6,
                                       err_msg=f"{name} {k}")
