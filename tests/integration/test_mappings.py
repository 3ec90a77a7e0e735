"""Memory mappings stay bounded (patexgs_jax.memory_maps, patexgs_jax.padding): views of many sizes are
rendered at a few padded sizes with unchanged pixels, compiled programs of retired layouts are
released, and a run near the cap checkpoints and stops with a clear message instead of crashing."""

from __future__ import annotations

import functools
import types

import jax
import numpy as np
import pytest

from patexgs_jax import Camera, RenderConfig, look_at, memory_maps, padding, random_scene
from patexgs_jax import checkpoint as ckpt
from patexgs_jax.data import load
from patexgs_jax.data.synthetic import generate
from patexgs_jax.densify import DensifyConfig
from patexgs_jax.render import TRACE_COUNTS, Capacity, count_pairs, render_jit
from patexgs_jax.textures.rebucket import resize_textures
from patexgs_jax.training.config import TrainConfig
from patexgs_jax.training.run import train
from patexgs_jax.training.step import STEP_TRACES, view_loss_and_grads
from patexgs_jax.training.trainer import Trainer

needs_proc = pytest.mark.skipif(memory_maps.memory_maps() is None, reason="needs /proc (Linux)")


def test_padded_sides():
    for steps in (None, 1, 4, 8):
        prev = 0
        for side in range(1, 2000):
            b = padding.padded_side(side, 16, steps)
            assert b >= side and b % 16 == 0 and b >= prev, (side, steps, b)
            tiles = -(-side // 16)
            if steps is None or tiles <= steps:
                assert b == 16 * tiles  # the renderer's own tile grid
            else:
                assert b / 16 <= tiles * (1 + 1 / steps), (side, steps, b)
            prev = b
        sides = {padding.padded_side(s, 16, steps) for s in range(257, 2049)}  # three octaves
        assert steps is None or len(sides) <= 3 * steps
    with pytest.raises(ValueError, match="positive"):
        padding.padded_side(0)


# ------------------------------------------------------------------------------------------------
# Evaluation renders
# ------------------------------------------------------------------------------------------------
CFG = RenderConfig(mip="nearest", coverage="prefilter")
SIZES = [(33 + k, 17 + 2 * k) for k in range(8)]  # 8 sizes, one tile grid: 48 x 32 (3 x 2 tiles)


def _scene(rgb_side=2):
    return random_scene(1, 40, sh_degree=1, extent=0.8, scale_range=(0.08, 0.4),
                        rgb_sizes=[rgb_side] * 40, alpha_sizes=[3] * 40)


def _camera(w, h):
    return Camera.from_intrinsics([30.0, 31.0, 20.3, 12.1], look_at((0.3, -0.4, -2.6), (0.0, 0.0, 0.0)), w, h)


def _unpadded(scene, cam):
    needed, _ = count_pairs(scene, cam, CFG)
    return render_jit(scene, cam, config=CFG, capacity=Capacity.fit(float(needed)))


FIELDS = ("rgb", "alpha", "depth", "normal", "distortion", "dominant", "max_contrib_count")


def test_padded_render_equals_the_unpadded_one():
    scene = _scene()
    for (w, h), steps in (((37, 22), None), ((37, 22), 1)):
        cam = _camera(w, h)
        ref = _unpadded(scene, cam)
        renderer = padding.ViewRenderer(scene, CFG, steps_per_octave=steps)
        out = renderer(cam)
        padded = renderer.camera(cam)
        assert (padded.height, padded.width) == ((32, 48) if steps is None else (32, 64))
        for f in FIELDS:
            a, b = np.asarray(getattr(out, f)), np.asarray(getattr(ref, f))
            assert a.shape == b.shape, f
            if steps is None or f in ("dominant", "max_contrib_count"):
                # The tile grid is the unpadded one: the same computation.
                np.testing.assert_array_equal(a, b, err_msg=f)
            else:
                # More tiles, batched differently by the renderer: equal up to float rounding.
                np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6, err_msg=f)
        if steps is None:
            for f in ("visible", "radius_px", "pairs_needed"):
                np.testing.assert_array_equal(np.asarray(getattr(out, f)), np.asarray(getattr(ref, f)), err_msg=f)
    padding.release_scene_programs()


@needs_proc
def test_evaluation_compiles_one_program_per_bucket_and_mappings_stay_bounded(monkeypatch):
    """8 view sizes in one bucket, over 3 texture layouts (growth events): one renderer program per
    layout, released when done in a process past memory_maps.KEEP_SHARE of its cap (simulated: 0), so
    the mapping count comes back to where it was; below it, kept for the next evaluation."""
    scene = _scene(rgb_side=1)
    memory_maps.release_compiled_code(threshold=0)
    # Below the share (the real one; the suite's processes stay far under it): a second evaluation
    # of the same scene takes the first's programs, tracing nothing.
    cams = [_camera(w, h) for w, h in SIZES]
    with padding.ViewRenderer(scene, CFG) as renderer:
        renderer.prepare(cams)
        first = renderer.image(cams[0])
    traces = sum(TRACE_COUNTS.values())
    with padding.ViewRenderer(scene, CFG) as renderer:
        renderer.prepare(cams)
        np.testing.assert_array_equal(renderer.image(cams[0]), first)
    assert sum(TRACE_COUNTS.values()) == traces
    monkeypatch.setattr(memory_maps, "KEEP_SHARE", 0.0)
    memory_maps.release_compiled_code(threshold=0)
    base = memory_maps.memory_maps()[0]
    peaks = []
    for side in (1, 3, 6):  # each growth changes the texture buckets: a new layout, new programs
        if side > 1:
            n = scene.capacity
            scene, _, info = resize_textures(scene, None, np.full(n, side), np.full(n, 3))
        traces = sum(TRACE_COUNTS.values())
        with padding.ViewRenderer(scene, CFG) as renderer:
            cams = [_camera(w, h) for w, h in SIZES]
            renderer.prepare(cams)
            for cam in cams:
                img = renderer.image(cam)
                assert img.shape == (cam.height, cam.width, 3) and np.isfinite(img).all()
            assert len(renderer.capacities) == 1
            peaks.append(memory_maps.memory_maps()[0] - base)
        assert sum(TRACE_COUNTS.values()) - traces == 1  # 8 sizes, 1 bucket: 1 program
    after = memory_maps.memory_maps()[0] - base
    # One layout's programs (renderer, counter, SSIM-free) at a time: no growth from layout to layout.
    assert max(peaks) < 2500, peaks
    assert peaks[-1] < peaks[0] + 500, peaks
    assert after < 0.3 * max(peaks) + 100, (peaks, after)


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mixed_sizes(tmp_path_factory):
    """A synthetic capture whose 8 training views are crops of 6 sizes (as undistortion leaves
    them), in 2 tile grids (3 x 2 and 3 x 3 tiles); the crops keep K, so pixels stay where they were."""
    root = tmp_path_factory.mktemp("mixed")
    ds = load(generate(root / "scene", seed=0, num_views=10, width=48, height=40, num_points=300), factor=1,
              test_every=5, cache_dir=root / "cache", verbose=False)
    sizes = [(48, 32), (45, 30), (47, 31), (48, 40), (46, 36), (44, 33), (48, 32), (45, 30)]

    def crop(v, w, h):
        cam = Camera(K=v.camera.K, world_to_camera=v.camera.world_to_camera, width=w, height=h)
        return types.SimpleNamespace(camera=cam, image=np.asarray(v.image)[:h, :w], name=v.name)

    train = [crop(v, w, h) for v, (w, h) in zip(ds.train_views, sizes)]
    test = [crop(v, 43, 29) for v in ds.test_views]
    return types.SimpleNamespace(train_views=train, test_views=test, points=ds.points, colors=ds.colors,
                                 normalization=ds.normalization)


class _Simulated(memory_maps.MapGuard):
    """A guard whose mapping count crosses its cap once ``trigger()`` says so."""

    def __init__(self, trigger):
        super().__init__(release_share=0.5, stop_share=0.9, limit=1000)
        self.trigger = trigger
        self.released = 0

    def counts(self):
        return (950 if self.trigger() else 10), 1000


def test_training_compiles_per_tile_grid_and_stops_near_the_map_limit(mixed_sizes, tmp_path, monkeypatch):
    cfg = TrainConfig(method="2dgs", iters_2dgs=12, sh_interval=4, normal_from=2, checkpoint_every=100,
                        log_every=100, densify=DensifyConfig(start=10_000, stop=10_001, opacity_reset_interval=10_000))
    start = sum(STEP_TRACES.values())
    # Stop once both tile grids compiled (the check after a compile sees it).
    guard = _Simulated(lambda: sum(STEP_TRACES.values()) - start >= 2)
    out = tmp_path / "run"
    with pytest.raises(memory_maps.MapLimitReached) as err:
        train(mixed_sizes, cfg, out, verbose=False, map_guard=guard)
    msg = str(err.value)
    for words in ("950 memory mappings", "limit of 1,000", "vm.max_map_count", "--resume", "resume=True",
                  "sysctl -w vm.max_map_count", str(out / "checkpoints")):
        assert words in msg, (words, msg)
    assert sum(STEP_TRACES.values()) - start == 2  # 6 sizes, 2 tile grids: 2 programs
    stopped = ckpt.read_metadata(ckpt.latest_checkpoint(out / "checkpoints"))["step"]
    assert 2 <= stopped < cfg.total_steps
    # Resumed in a fresh guard's care, the run completes; the stopped run's steps are kept.
    mid = sum(STEP_TRACES.values())
    result = train(mixed_sizes, cfg, out, resume=True, verbose=False)
    assert result.summary["steps"] == cfg.total_steps and result.summary["skipped_steps"] == 0
    assert np.isfinite(result.summary["test_psnr"])
    assert sum(STEP_TRACES.values()) - mid <= 2


@pytest.mark.parametrize("size", [None, (48, 64)], ids=["own-grid", "one-size"])
def test_padded_step_matches_the_cropped_loss(mixed_sizes, size):
    """The loss and gradients of a view padded to its tile grid, or to a larger padded size (the
    "one" padding: the renderer bins the view's own tiles only), are those of the view itself (the
    densification statistic, the screen-offset gradient, included)."""
    import jax.numpy as jnp

    cfg = TrainConfig(method="2dgs", iters_2dgs=4)
    run = Trainer(mixed_sizes, cfg, None, verbose=False)
    run.fresh()
    v = mixed_sizes.train_views[1]  # 45 x 30 in a 48 x 32 bucket
    cam = padding.train_camera(v.camera, 16, size)
    grads = jax.jit(functools.partial(view_loss_and_grads, render_config=cfg.render_config(1),
                                      capacity=Capacity.fit(4096), lambda_dssim=0.2, lambda_dist=0.1))
    args = (jnp.int32(1), jnp.float32(0.05))
    (want, (_, l1_want, mse_want)), (g_want, off_want) = grads(run.scene, v.camera, jnp.asarray(v.image), *args)
    (loss, (out, l1, mse)), (g, off) = grads(
        run.scene, cam, jnp.asarray(padding.pad_image(v.image, cam.height, cam.width)), *args,
        valid_hw=jnp.asarray([v.camera.height, v.camera.width]))
    own = render_jit(run.scene, v.camera, config=cfg.render_config(1), capacity=Capacity.fit(4096))
    np.testing.assert_array_equal(np.asarray(out.visible), np.asarray(own.visible))
    assert float(out.pairs_needed) == float(own.pairs_needed)
    for a, b in ((loss, want), (l1, l1_want), (mse, mse_want)):
        assert float(a) == pytest.approx(float(b), rel=1e-5)
    pairs = ((off, off_want), (g.means, g_want.means), (g.sh, g_want.sh), (g.opacity_logits, g_want.opacity_logits))
    # Each entry sums per-pixel terms, here in another order (tile grid, SSIM's windows): an entry
    # far below its leaf's largest keeps an absolute float32 error of a fraction of that largest
    # (1.7e-4 of it on 9 of 1,024 screen-offset entries with XLA's older CPU emitters, 1e-7 with
    # its default ones). A pixel lost or counted twice would move entries by their own size.
    for a, b in pairs:
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=5e-4 * float(np.max(np.abs(b))))


def test_one_padding_compiles_the_step_once(mixed_sizes):
    """With ``padding="one"`` the 8 views of 6 sizes (2 tile grids: 2 programs per-size, see
    test_training_compiles_per_tile_grid_and_stops_near_the_map_limit) train with one program,
    and summary.json counts it."""
    from patexgs_jax.training.steps import PROCESS

    cfg = TrainConfig(method="2dgs", iters_2dgs=10, sh_interval=4, normal_from=2, padding="one",
                      densify=DensifyConfig(start=10_000, stop=10_001, opacity_reset_interval=10_000))
    PROCESS.release_steps()  # (a step of this layout shared by an earlier run would hide the count)
    start = sum(STEP_TRACES.values())
    summary = train(mixed_sizes, cfg, None, verbose=False).summary
    assert sum(STEP_TRACES.values()) - start == 1
    assert summary["compiles"]["step_programs"] == summary["recompiles"] == 1
    assert summary["compiles"]["step_seconds"] > 0 and summary["compiles"]["xla_programs"] >= 1
    pad = summary["padding"]
    assert (pad["policy"], pad["sizes"], pad["one_size"], pad["headroom"]) == ("one", 2, [48, 48], 2.0)
    # (heights 30-32: 2 tile rows; 33-40: 3)
    assert pad["one_over_per_size"] == pytest.approx(8 * 48 * 48 / (5 * 48 * 32 + 3 * 48 * 48) - 1)
