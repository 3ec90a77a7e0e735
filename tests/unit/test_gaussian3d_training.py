"""The 3D methods' host-side pieces: the ``3dgs`` / ``mip-splatting`` configs and their own stage 1,
3DGS's split in three axes, Mip-Splatting's 3D filter (its sampling rates, schedule, filtered opacity
reset) and the initial scene. Host-side numpy: no renderer compile."""

from __future__ import annotations

import math
import types

import jax
import numpy as np
import pytest

from patexgs_jax import Camera, Scene, look_at
from patexgs_jax import densify as dens
from patexgs_jax.filter3d import FILTER_SCALE, bake, filter_variance, opacity_factor
from patexgs_jax.math import quat_to_rotmat
from patexgs_jax.schedule import TrainState
from patexgs_jax.training.config import Method, TrainConfig, preset_config, stage1_key
from patexgs_jax.training.strategies import Densification, SmoothingFilter
from patexgs_jax.training.trainer import init_scene


def test_methods_and_their_own_stage1():
    for name, cov in (("3dgs", "lowpass"), ("mip-splatting", "prefilter")):
        spec = Method.from_name(name)
        assert spec.primitive == "3d" and spec.textures is None and spec.filter3d == (name == "mip-splatting")
        cfg = preset_config("tiny", method=name, continue_2dgs=200)
        assert cfg.total_steps == cfg.iters_2dgs + 200 == preset_config("tiny", method="2dgs",
                                                                        continue_2dgs=200).total_steps
        assert cfg.render_config(stage=1) == cfg.render_config(stage=2)
        assert cfg.render_config().coverage == cov and cfg.render_config().mip == "none"
        assert Densification(cfg, 1.0).config.prune_opacity == 0.005  # 3DGS's, not 2DGS's 0.05
    assert Densification(preset_config("tiny", method="2dgs"), 1.0).config.prune_opacity == 0.05
    keys = [stage1_key(preset_config("tiny", method=m)) for m in ("2dgs", "patexgs", "3dgs", "mip-splatting")]
    assert keys[0] == keys[1] and keys[2] != keys[0] and keys[3] != keys[0] and keys[3] != keys[2]
    # a 3D run shares its stage 1 with runs of the same method that differ after it
    assert keys[2] == stage1_key(preset_config("tiny", method="3dgs", continue_2dgs=7, iters_tex=50))
    with pytest.raises(ValueError, match="untextured"):
        TrainConfig(method="patexgs", continue_2dgs=10)


def test_init_scene_is_isotropic_3d():
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    for name in ("3dgs", "mip-splatting"):
        sc = init_scene(pts, None, preset_config("tiny", method=name))
        ls = np.asarray(sc.log_scales)[:50]
        assert sc.is_3d and sc.rgb is None and np.all(ls == ls[:, :1])
        assert (sc.filter3d is not None) == (name == "mip-splatting")
    assert not init_scene(pts, None, preset_config("tiny", method="2dgs")).is_3d


def test_split_samples_a_3d_gaussian_in_all_three_axes():
    """3DGS's split: children drawn from the parent's 3D Gaussian, scales divided by 0.8 N."""
    n = 400
    q = np.random.default_rng(3).normal(size=4)
    sc = Scene.from_arrays([[0.1, 0.2, 0.3]], [[0.3, 0.1, 0.02]], [q], [0.5], np.zeros((1, 1, 3)))
    stats = dens.DensifyStats(*(jax.device_put(np.asarray([v], np.float32)) for v in (1e-3, 1.0, 0.0)))
    cfg = dens.DensifyConfig(split_count=n, max_world_scale=None)
    s2, _, _, info = dens.densify_and_prune(sc, None, stats, cfg, 1.0, 1)
    assert info.split == 1 and s2.num_active() == n
    R = np.asarray(quat_to_rotmat(sc.quats[0]), np.float64)
    local = (np.asarray(s2.means, np.float64)[:n] - [0.1, 0.2, 0.3]) @ R
    np.testing.assert_allclose(local.std(axis=0), [0.3, 0.1, 0.02], rtol=0.15)
    np.testing.assert_allclose(np.asarray(s2.log_scales)[:n],
                               np.broadcast_to(np.log([0.3, 0.1, 0.02]) - math.log(0.8 * n), (n, 3)), atol=1e-5)


def cam(eye, f=100.0, w=64, h=48):
    return Camera.from_intrinsics([f, f, w / 2, h / 2], look_at(eye, (0.0, 0.0, 0.0)), w, h)


def test_filter_variance_takes_the_highest_sampling_rate_in_the_frusta():
    a, b = cam((0.0, 0.0, -4.0)), cam((0.0, 0.0, -2.0), f=60.0)
    means = np.array([[0.0, 0.0, 0.0],      # both: rates 100 / 4 = 25 and 60 / 2 = 30
                      [0.0, 0.0, 1.0],      # both: 100 / 5 = 20, 60 / 3 = 20
                      [1.5, 0.0, 0.0],      # b: pixel 77 > 64 + 0.15 * 64; a: 69.5, in its margin: 25
                      [0.0, 0.0, -10.0],    # behind both: the lowest rate seen (20)
                      [0.0, 0.0, -1.9]])    # b: z 0.1 <= 0.2, not counted; a: 100 / 2.1
    f = filter_variance(means, [a, b])
    rates = np.array([30.0, 20.0, 25.0, 20.0, 100 / 2.1])
    np.testing.assert_allclose(f, FILTER_SCALE / rates ** 2, rtol=1e-5)
    assert np.all(filter_variance(means[3:4], [a, b]) == 0)  # nothing seen: no filter


def test_filter_opacity_factor_bake_and_reset():
    ls = np.log(np.array([[0.1, 0.2, 0.3], [1e-20, 1.0, 1.0]]))
    f = np.array([0.01, 0.0])
    det = np.prod(np.exp(ls[0]) ** 2)
    np.testing.assert_allclose(opacity_factor(ls, f), [np.sqrt(det / np.prod(np.exp(ls[0]) ** 2 + 0.01)), 1.0],
                               rtol=1e-9)
    sc = Scene.from_arrays(np.zeros((2, 3)), np.exp(ls), [[1.0, 0, 0, 0]] * 2, [0.9, 0.005], np.zeros((2, 1, 3)),
                           filter3d=f)
    ls_b, logit_b = bake(sc)
    np.testing.assert_allclose(np.exp(2 * ls_b[0].astype(np.float64)), np.exp(ls[0]) ** 2 + 0.01, rtol=1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-logit_b.astype(np.float64))), [0.9 * opacity_factor(ls, f)[0], 0.005],
                               rtol=1e-5)
    s2, _ = dens.reset_opacity(sc, None, 0.01)  # Mip-Splatting: the filtered opacity is capped
    filtered = np.asarray(s2.opacities, np.float64) * opacity_factor(np.asarray(sc.log_scales), f)
    np.testing.assert_allclose(filtered, [0.01, 0.005], rtol=1e-5)


def test_smoothing_filter_schedule_and_recompute():
    """The reference's steps at the paper's scale: after each densification (600 .. 14,900), then
    every 100 steps after densification stops, not in the last 100 steps."""
    view = types.SimpleNamespace(camera=cam((0.0, 0.0, -4.0)))
    f = SmoothingFilter(TrainConfig(method="mip-splatting", continue_2dgs=30_000), [view])
    steps = [t for t in range(1, 60_001) if f.recomputes_at(t)]
    assert steps[:2] == [600, 700] and 14_900 in steps and 15_000 not in steps and 15_100 in steps
    assert steps[-1] == 59_800 and all(t % 100 == 0 for t in steps)
    sc = init_scene(np.random.default_rng(0).uniform(-1, 1, (20, 3)), None, TrainConfig(method="mip-splatting"))
    assert np.all(np.asarray(sc.filter3d) == 0)
    st = f.before_step(TrainState(sc, None, None), 0)
    np.testing.assert_array_equal(np.asarray(st.scene.filter3d), filter_variance(sc.means, f.cameras))
    assert np.all(np.asarray(st.scene.filter3d)[:20] > 0)
    off = SmoothingFilter(TrainConfig(method="3dgs"), [view])
    assert off.before_step(TrainState(sc, None, None), 0).scene is sc
