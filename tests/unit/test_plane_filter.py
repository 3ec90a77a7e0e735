"""Mip-Splatting's 3D smoothing filter on 2D splats (``Scene.filter3d`` of a 2D scene, the
``patexgs+filter3d`` method): the renderer against the float64 reference (prefiltered, textured or
not, and under the 2DGS low-pass untextured), the integral kept, a zero filter changing nothing,
gradients, the settings that refuse it, its PLY round trip and the method's own stage 1.

Scenes and camera are tests/render_cases.py's (capacity 48, 44x36), so compiled renderers are shared.
"""

from __future__ import annotations

import types

import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import Camera, RenderConfig, look_at, random_scene
from patexgs_jax.densify import DensifyStats
from patexgs_jax.export import export_ply, load_ply, sidecar_path
from patexgs_jax.filter3d import filter_variance
from patexgs_jax.rendering.projection import plane_filter
from patexgs_jax.schedule import TrainState
from patexgs_jax.training import TrainConfig
from patexgs_jax.training.strategies import SmoothingFilter
from render_cases import C, camera, directional_fd_check, ref_render, scene, single_splat_scene, tile_render

PREFILTER = TrainConfig(method="patexgs+filter3d").render_config()


def _filtered(sc, seed=0, scale=0.12):
    """``sc`` with filters from 0 (a fifth of the splats) to about its splats' own variances
    (scales 0.08-0.45), so the widening ranges from nothing to doubling."""
    rng = np.random.default_rng(seed)
    f = (scale * rng.uniform(0.0, 1.5, C)) ** 2
    f[rng.uniform(size=C) < 0.2] = 0.0
    return sc.replace(filter3d=jnp.asarray(f, jnp.float32))


@pytest.mark.parametrize("textured,coverage", [(True, "prefilter"), (False, "prefilter"), (False, "lowpass")])
def test_matches_float64_reference(textured, coverage):
    """The reference convolves each splat in its plane (covariance diag(1 + f / s^2) in units of the
    scales) and adds the pixel filter, inverted directly, or (the 2DGS low-pass, untextured) draws
    the splat with scales sqrt(s^2 + f): the renderer, which folds the filter into the screen
    Jacobian, agrees to rounding in float64 and within the 2DGS renderer's float32 bounds."""
    sc = _filtered(scene(11, textured, 1))
    cam = camera()
    cfg = RenderConfig(mip="nearest" if textured else "none", coverage=coverage,
                       min_var=0.25 if coverage == "prefilter" else 0.0)
    ref = ref_render(sc, cam, cfg)
    plain = ref_render(sc.replace(filter3d=None), cam, cfg)
    assert np.abs(ref["rgb"] - plain["rgb"]).max() > 0.05, "the filter should change the image"
    out64 = tile_render(sc, cam, cfg, jnp.float64)
    np.testing.assert_allclose(out64.rgb, ref["rgb"], atol=1e-7, rtol=0)
    np.testing.assert_allclose(out64.alpha, ref["alpha"], atol=1e-7, rtol=0)
    np.testing.assert_allclose(out64.depth, ref["depth"], atol=1e-6, rtol=0)
    out32 = tile_render(sc, cam, cfg)
    err = np.abs(out32.rgb - ref["rgb"]).max(axis=-1)
    assert np.mean(err > 2e-4) <= 0.005, (err.max(), np.mean(err > 2e-4))
    assert np.median(err) < 2e-5


def test_zero_filter_is_no_filter():
    """A filter of zeros widens nothing (d = 1 exactly, however small the splat) and renders as no
    filter up to float32 rounding (another compiled program: XLA may contract differently)."""
    sc = scene(5, True, 1)
    zero = sc.replace(filter3d=jnp.zeros(C, jnp.float32),
                      log_scales=sc.log_scales.at[0].set(-40.0))  # (exp(-2 log s) overflows float32)
    np.testing.assert_array_equal(np.asarray(plane_filter(zero)), 1.0)
    cam = camera()
    a = tile_render(sc, cam, PREFILTER)
    b = tile_render(sc.replace(filter3d=jnp.zeros(C, jnp.float32)), cam, PREFILTER)
    # Two programs' float32 roundings differ by up to 1.5e-6 in a normal's component (unit vectors
    # summed over many pairs) and 1.1e-5 of a depth (values ~2-3) with the suite's codegen
    # (tests/conftest.py); 2e-6 of a depth with an AMD EPYC's default one.
    for name in ("rgb", "alpha", "normal"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=3e-6, rtol=1e-5)
    np.testing.assert_allclose(a.depth, b.depth, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("scale_px", [0.2, 1.0, 4.0])
def test_filtered_splat_is_the_convolved_gaussian(scale_px):
    """A splat of ``scale_px`` px facing the camera (an affine projection) at opacity 0.3 with a
    filter of 1 px standard deviation: the image is opacity s^2 / v exp(-|d|^2 / 2v), v = s^2 + 1 +
    the pixel filter's variance (0.1), within the cut-off (pairs below 1/255 of the coverage); its summed
    alpha, the integral, equals the unfiltered splat's within 3% (a 0.2 px splat becomes a ~1 px one)."""
    f_px, F, Z = 1.0, 40.0, 2.6
    cam = Camera.from_intrinsics([F, F, 22.0, 18.0], look_at((0.0, 0.0, -Z), (0.0, 0.0, 0.0)), 44, 36)
    sc = single_splat_scene(None, None, scale=scale_px * Z / F)
    sc = sc.replace(opacity_logits=sc.opacity_logits.at[0].set(float(np.log(0.3 / 0.7))))
    filt = sc.replace(filter3d=jnp.zeros(C, jnp.float32).at[0].set((f_px * Z / F) ** 2))
    a = tile_render(sc, cam, PREFILTER).alpha
    b = tile_render(filt, cam, PREFILTER).alpha
    v = scale_px ** 2 + f_px ** 2 + PREFILTER.pixel_var
    assert v > PREFILTER.min_var  # (so the pixel filter is pixel_var)
    x, y = np.meshgrid(np.arange(44) + 0.5 - 22.0, np.arange(36) + 0.5 - 18.0)
    want = 0.3 * scale_px ** 2 / v * np.exp(-0.5 * (x * x + y * y) / v)
    np.testing.assert_allclose(b, want, atol=1.01 * scale_px ** 2 / v / 255, rtol=0)  # (the coverage / 255 cut)
    assert abs(float(b.sum()) / float(a.sum()) - 1) < 0.03


def test_gradients_match_finite_differences():
    """float64 directional derivative through the filtered kernel (the scales' gradient includes the
    filter's dependence on them; the filter itself is not trained). Untextured: the filter does not
    touch the texture lookups, whose gradients the prefilter's own check covers."""
    sc = _filtered(scene(7, False, 1), seed=1)
    # (h 1e-7, as the prefilter's own check: a step of 1e-6 moves some faint pair across alpha 1/255)
    directional_fd_check(sc, camera(), RenderConfig(mip="none", coverage="prefilter"), seed=2, h=1e-7)


@pytest.mark.parametrize("textured,coverage", [(True, "lowpass"), (False, "billboard")])
def test_textures_and_billboards_need_the_prefilter(textured, coverage):
    """Textures span +-3 of the unfiltered scales, a billboard has no Gaussian: only the prefilter
    folds the filter in, and the others say so."""
    sc = _filtered(scene(3, textured, 0))
    with pytest.raises(ValueError, match="coverage 'prefilter'"):
        tile_render(sc, camera(), RenderConfig(mip="none", coverage=coverage))


def test_ply_stores_the_filter_and_renders_the_same(tmp_path):
    """A 2D scene's filter cannot be baked (its textures span +-3 scales): the PLY carries its
    deviation as ``filter_3D`` after ``rot_3`` and loads back into a scene that renders the same; a
    3D file with ``filter_3D`` (Mip-Splatting's unfused PLY) loads with its filter."""
    sc = _filtered(scene(9, True, 1))
    path = export_ply(sc, tmp_path / "f.ply")
    head = path.read_bytes().split(b"end_header\n")[0].decode("ascii").splitlines()
    props = [ln.split()[-1] for ln in head if ln.startswith("property")]
    assert props[-5:] == ["rot_0", "rot_1", "rot_2", "rot_3", "filter_3D"]
    back = load_ply(path, capacity=C)
    assert back.filter3d is not None and not back.is_3d
    keep = np.asarray(sc.active) > 0
    # (stored as the deviation sqrt(f), as Mip-Splatting does: back to the variance within rounding)
    np.testing.assert_allclose(np.asarray(back.filter3d)[:keep.sum()], np.asarray(sc.filter3d)[keep], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(back.log_scales)[:keep.sum()], np.asarray(sc.log_scales)[keep])
    ref = tile_render(sc, camera(), PREFILTER)
    out = tile_render(back, camera(), PREFILTER)
    np.testing.assert_allclose(out.rgb, ref.rgb, atol=2e-5, rtol=0)

    g3 = random_scene(3, 5, sh_degree=0, scale_dims=3)
    path = export_ply(g3, tmp_path / "g3.ply")  # (no filter: the 3DGS layout) + a filter_3D column
    head, body = path.read_bytes().split(b"end_header\n")
    rows = np.frombuffer(body, "<f4").reshape(5, -1)
    dev = np.linspace(0.01, 0.05, 5, dtype="<f4")[:, None]
    head = head.replace(b"property float rot_3\n", b"property float rot_3\nproperty float filter_3D\n")
    path.write_bytes(head + b"end_header\n" + np.concatenate([rows, dev], 1).astype("<f4").tobytes())
    assert not sidecar_path(path).exists()  # (an untextured scene has none)
    back = load_ply(path)
    assert back.is_3d
    np.testing.assert_allclose(np.asarray(back.filter3d), np.square(dev[:, 0]), rtol=1e-6)


def test_method_has_its_own_stage1():
    """As in Mip-Splatting the filter acts from the first step (the 2DGS stage under the low-pass
    too), so ``patexgs+filter3d`` does not share the 2DGS stage 1; its scene carries the filter from
    the start, recomputed at the 3D method's steps."""
    from patexgs_jax.training.config import stage1_key
    from patexgs_jax.training.trainer import init_scene

    cfg = TrainConfig(method="patexgs+filter3d", iters_2dgs=1000, iters_tex=400, warmup_tex=40)
    assert stage1_key(cfg) != stage1_key(TrainConfig(method="2dgs", iters_2dgs=1000))
    assert cfg.render_config(stage=1) == TrainConfig(method="2dgs").render_config()
    assert cfg.render_config().coverage == "prefilter"
    sc = init_scene(np.random.default_rng(0).uniform(-1, 1, (20, 3)), None, cfg)
    assert not sc.is_3d and np.all(np.asarray(sc.filter3d) == 0)
    view = types.SimpleNamespace(camera=camera())
    f = SmoothingFilter(cfg, [view])
    st = f.before_step(TrainState(sc, None, DensifyStats.zeros(sc.capacity)), 0)  # pyright: ignore[reportArgumentType]
    np.testing.assert_array_equal(np.asarray(st.scene.filter3d), filter_variance(sc.means, [view.camera]))
    steps = [t for t in range(1, cfg.total_steps + 1) if f.recomputes_at(t)]
    first = next(t for t in range(1, cfg.iters_2dgs) if cfg.densify.densify_at(t))
    assert steps[0] == first and steps[-1] == 1200 and 1100 in steps  # (the texture stage's too)
