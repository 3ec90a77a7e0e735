"""Training under stress: the optimiser state and the learning-rate schedule stay finite
when every Gaussian is pruned and when the capacity grows several times; the output directory is
checked before any training step. (Bad batches - NaN pixels, empty images, corrupt poses - are
covered by tests/integration/test_train.py::test_bad_views_are_skipped; kills by tests/integration/test_kill.py.)

Host-side and eager: no renderer compile.
"""

from __future__ import annotations

from types import SimpleNamespace

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from patexgs_jax import Camera, random_scene
from patexgs_jax import checkpoint as ckpt
from patexgs_jax.densify import DensifyConfig, DensifyStats, densify_and_prune, prune_gaussians
from patexgs_jax.optim import LearningRates, adam_moments, make_optimizer, step_rates
from patexgs_jax.training.config import TrainConfig
from patexgs_jax.training.run import train
from patexgs_jax.training.trainer import Trainer

RADIUS = 2.0
LR = LearningRates(means_steps=5)


def random_grads(scene, rng, scale=1.0):
    """Random gradients on the active rows (inactive ones are never rendered: zero gradient)."""
    act = np.asarray(scene.active) > 0

    def g(x):
        v = rng.normal(0, scale, np.shape(x))
        if np.ndim(x) and np.shape(x)[0] == act.size:
            v[~act] = 0.0
        return jnp.asarray(v, x.dtype)

    return jax.tree_util.tree_map(g, scene)


def zero_grads(scene):
    return jax.tree_util.tree_map(jnp.zeros_like, scene)


_JIT = {}


def steps(opt, scene, state, grads_fn, n):
    """n optimiser steps (jitted per optimiser: eager optax compiles every primitive per shape)."""
    if id(opt) not in _JIT:
        def one(g, st, sc):
            updates, st = opt.update(g, st, sc)
            return updates, optax.apply_updates(sc, updates), st

        _JIT[id(opt)] = (opt, jax.jit(one))
    fn = _JIT[id(opt)][1]
    for _ in range(n):
        updates, scene, state = fn(grads_fn(scene), state, scene)
        for path, u in jax.tree_util.tree_leaves_with_path(updates):
            assert np.all(np.isfinite(np.asarray(u))), jax.tree_util.keystr(path)
    return scene, state


def assert_finite_state(scene, state, what):
    for name, tree in (("scene", scene), ("opt_state", state)):
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            assert np.all(np.isfinite(np.asarray(leaf))), f"{what}: {name}{jax.tree_util.keystr(path)}"
    mu, nu = adam_moments(state)
    inactive = np.asarray(scene.active) == 0
    for m in (mu, nu):
        assert m.means.shape == scene.means.shape, what
        assert np.all(np.asarray(m.means)[inactive] == 0), f"{what}: moments left on inactive slots"
    assert np.all(np.asarray(nu.means) >= 0), what


def test_prune_to_zero_keeps_optimizer_finite():
    rng = np.random.default_rng(0)
    opt = make_optimizer(RADIUS, LR)
    scene = random_scene(0, 6, sh_degree=1, capacity=8)
    state = opt.init(scene)
    scene, state = steps(opt, scene, state, lambda s: random_grads(s, rng), 3)
    # Densification whose opacity threshold prunes everything.
    cfg = DensifyConfig(prune_opacity=1.0, max_screen_radius=None, max_world_scale=None)
    scene, state, stats, info = densify_and_prune(scene, state, DensifyStats.zeros(8), cfg, RADIUS, 0)
    assert info.num_active_after == 0 and info.pruned == 6 and scene.num_active() == 0
    assert_finite_state(scene, state, "after pruning everything")
    # An empty scene renders the background: zero gradients. Adam (eps 1e-15) must give zero,
    # finite updates for many steps, across the end of the means' learning-rate decay.
    before = jax.tree_util.tree_map(np.asarray, scene)
    scene, state = steps(opt, scene, state, zero_grads, 8)
    assert_finite_state(scene, state, "steps on an empty scene")
    chex.assert_trees_all_equal(scene, before)
    assert int(state[0].count) == int(state[1].count) == 11
    # Pruning an already empty scene again is a no-op, and the statistics stay consistent.
    scene2, state2, stats2, n = prune_gaussians(scene, state, stats, np.ones(8, bool))
    assert n == 0 and stats2.capacity == 8
    assert_finite_state(scene2, state2, "pruning an empty scene")


def test_capacity_growth_several_times_keeps_optimizer_finite():
    rng = np.random.default_rng(1)
    opt = make_optimizer(RADIUS, LR)
    scene = random_scene(1, 2, sh_degree=2, scale_range=(0.001, 0.002), capacity=2)  # full: no free slot
    state = opt.init(scene)
    cfg = DensifyConfig(grad_threshold=0.0, percent_dense=0.01, prune_opacity=0.0, max_screen_radius=None,
                        max_world_scale=None)
    caps = [scene.capacity]
    for k in range(4):
        scene, state = steps(opt, scene, state, lambda s, k=k: random_grads(s, rng, scale=10.0 ** (3 * k - 4)), 2)
        C = scene.capacity
        stats = DensifyStats(grad_sum=jnp.ones(C), count=jnp.ones(C), max_radius=jnp.zeros(C))
        scene, state, _, info = densify_and_prune(scene, state, stats, cfg, RADIUS, k)
        assert info.cloned == info.num_active_before > 0  # every active one cloned: the capacity doubles
        caps.append(scene.capacity)
        assert_finite_state(scene, state, f"growth {k}")
    assert caps == [2, 4, 8, 16, 32] and scene.num_active() == 32
    scene, state = steps(opt, scene, state, lambda s: random_grads(s, rng, scale=1e8), 3)
    assert_finite_state(scene, state, "after growth")
    assert int(state[0].count) == 11


@pytest.mark.parametrize("count", [0, 4, 5, 6, 10**6, 2**31 - 2, 2**31 - 1])
def test_learning_rate_schedule_finite_at_any_step_count(count):
    opt = make_optimizer(RADIUS, LR, step_offset=3)
    scene = random_scene(2, 3, capacity=4)
    adam, group = opt.init(scene)
    state = (adam._replace(count=jnp.asarray(count, jnp.int32)), group._replace(count=jnp.asarray(count, jnp.int32)))
    grads = random_grads(scene, np.random.default_rng(2))
    updates, state = jax.jit(opt.update)(grads, state, scene)
    u = np.asarray(updates.means)
    assert np.all(np.isfinite(u)) and np.any(u != 0)
    # From zero moments, Adam's bias-corrected step |m_hat / sqrt(v_hat)| is at most
    # 0.1 / sqrt(0.001) < 3.2 per entry, times the decayed means learning rate (x radius).
    t = min((count + 3) / LR.means_steps, 1.0)
    lr_now = RADIUS * np.exp((1 - t) * np.log(LR.means_init) + t * np.log(LR.means_final))
    assert np.max(np.abs(u)) <= 3.2 * lr_now * (1 + 1e-5)
    assert int(state[1].count) == min(count + 1, 2**31 - 1)  # saturates instead of wrapping
    # (near 2^31 the decay used to restart: count + step_offset wrapped around in int32.)


@pytest.mark.parametrize("count", [0, 4, 7, 1000])
def test_rates_as_arguments_update_as_the_constants_do(count):
    """The training step passes the learning rates as arguments (``step_rates``: one program for
    every scene radius, schedule and rate, shared between runs): an update with another run's
    rates equals that run's own optimiser's bit for bit, before, during and after the means'
    decay, texels and SH bands included, and the jitted update traced once serves both runs."""
    scene = random_scene(3, 6, sh_degree=1, capacity=8, rgb_sizes=[0, 2, 4, 2, 0, 3], alpha_sizes=[2, 0, 2, 0, 0, 1])
    runs = [(RADIUS, LR, 3), (0.37, LearningRates(means_init=3e-4, means_steps=9, scales=1e-2, sh_dc=1e-3,
                                                  sh_rest_divisor=7.0, texture_rgb=4e-3, texture_alpha=6e-4), 0)]
    third = make_optimizer(5.0)  # (a third run's optimiser: only its structure is used)
    traces = []

    def update(g, st, sc, rates):
        traces.append(1)
        return third.update(g, st, sc, rates=rates)

    shared = jax.jit(update)
    grads = random_grads(scene, np.random.default_rng(count))
    for radius, lr, offset in runs:
        own = make_optimizer(radius, lr, step_offset=offset)
        adam, group = own.init(scene)
        c = jnp.asarray(count, jnp.int32)
        state = (adam._replace(count=c), group._replace(count=c))
        want, want_state = jax.jit(own.update)(grads, state, scene)
        got, got_state = shared(grads, state, scene, step_rates(lr, radius, offset))
        chex.assert_trees_all_equal(got, want)
        chex.assert_trees_all_equal(got_state, want_state)
        assert np.any(np.asarray(got.means) != 0) and any(np.any(np.asarray(b) != 0) for b in got.rgb.buckets)
    assert len(traces) == 1


# ------------------------------------------------------------------------------------------------
class TinyData:
    """Just enough of a dataset for train() to build its initial state."""

    def __init__(self):
        rng = np.random.default_rng(0)
        self.points = rng.uniform(-1, 1, (300, 3)).astype(np.float32)
        self.colors = rng.uniform(0, 1, (300, 3)).astype(np.float32)
        # One view with a camera (the trainer reads the views' sizes for their padding); never rendered.
        camera = Camera(K=np.array([[50.0, 0, 24], [0, 50.0, 16], [0, 0, 1]], np.float32),
                        world_to_camera=np.eye(4, dtype=np.float32), width=48, height=32)
        self.train_views = (SimpleNamespace(camera=camera),)
        self.test_views = ()

        class Norm:
            radius = 1.0

        self.normalization = Norm()


def _never_run(monkeypatch):
    calls = []
    monkeypatch.setattr(Trainer, "run", lambda self: calls.append("run"))
    return calls


@pytest.mark.parametrize("errno,msg", [(28, "No space left on device"), (30, "Read-only file system")])
def test_unwritable_output_fails_before_training(tmp_path, monkeypatch, errno, msg):
    calls = _never_run(monkeypatch)

    def fail(*a, **k):
        raise OSError(errno, msg)

    # A full disk fails the probe's write/fsync; a read-only one its creation.
    monkeypatch.setattr(ckpt.os, "fsync", fail) if errno == 28 else monkeypatch.setattr(ckpt.tempfile, "mkstemp", fail)
    with pytest.raises(ckpt.CheckpointError, match=f"not writable: {msg}"):
        train(TinyData(), TrainConfig(method="2dgs", iters_2dgs=5), tmp_path / "out", verbose=False)
    assert calls == []


def test_too_little_space_for_checkpoints_fails_before_training(tmp_path, monkeypatch):
    """A disk with room for the 4 KiB write probe but not for the checkpoints is refused up front
    (it used to be found at the first checkpoint, checkpoint_every steps into the run)."""
    calls = _never_run(monkeypatch)
    real = ckpt.shutil.disk_usage
    monkeypatch.setattr(ckpt.shutil, "disk_usage", lambda p: real(p)._replace(free=64 * 1024))
    with pytest.raises(ckpt.CheckpointError, match=r"MiB free.*MiB are needed"):
        train(TinyData(), TrainConfig(method="2dgs", iters_2dgs=5), tmp_path / "out", verbose=False)
    assert calls == []


def test_compile_ahead_prepares_again_only_when_the_capacity_changed():
    """After densification stops, the texture stage's first step is compiled ahead once; a 100-step
    refit that keeps the tile capacity leaves that program valid (it depends on shapes and capacity
    only), so only a capacity change prepares it again (seen at the step after the refit: compiling
    ahead is the last strategy, the trainer refits after the strategies)."""
    from types import SimpleNamespace

    from patexgs_jax.render import Capacity
    from patexgs_jax.training.compile_ahead import CompileAhead

    ahead = object.__new__(CompileAhead)
    ahead.cfg, ahead._last_densify, ahead._prepared_own = SimpleNamespace(iters_2dgs=1000), 500, None
    ahead.tiles = SimpleNamespace(current=None)
    prepared, at = [], []
    ahead.prepare = lambda config, state, capacity, predict_allocation=True: (prepared.append(capacity),
                                                                              at.append(step))
    state = SimpleNamespace(scene=SimpleNamespace(rgb=None))
    for step in range(1, 1000):
        if step == 501:
            ahead.tiles.current = Capacity(1 << 16)  # fitted at the first step after densification
        if step == 801:
            ahead.tiles.current = Capacity(1 << 17)  # the refit after step 800 grew it
        assert ahead.after_step(state, step) is state
    assert prepared == [Capacity(1 << 16), Capacity(1 << 17)]
    assert at == [501, 801]
