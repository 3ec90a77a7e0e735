"""Adaptive density control: clone / split / prune counts, slot and moment bookkeeping, capacity
growth, the Gaussian budget, split geometry, opacity reset and textured pruning; the device path
(capacity kept: rows written in place) against the host path, bit for bit, and its compile count.

Host-side numpy and the small jitted row writes (no renderer compile)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from patexgs_jax import Scene, random_scene
from patexgs_jax.densify import (
    DensifyConfig,
    DensifyStats,
    accumulate,
    densify_and_prune,
    prune_gaussians,
    reset_opacity,
    resize_capacity,
    resize_opt_state,
)
from patexgs_jax.math import quat_to_rotmat
from patexgs_jax.optim import AdamState, GroupLRState, adam_moments, make_optimizer


def tagged_scene(scales, opacities, capacity, seed=0, sh_degree=1):
    """Scene whose row i is recognisable: SH DC = i + 1 (copied by clones and splits).

    Built directly with device_put (Scene.from_arrays' jnp.asarray compiles once per new shape)."""
    n = len(scales)
    rng = np.random.default_rng(seed)
    sc = np.asarray(scales, np.float64)
    sc = np.stack([sc, sc * 0.7], axis=1)
    K = (sh_degree + 1) ** 2
    sh = rng.normal(0, 0.1, (n, K, 3))
    sh[:, 0, 0] = np.arange(n) + 1.0
    op = np.asarray(opacities, np.float64)

    def pad(a, fill=0.0):
        out = np.empty((capacity,) + a.shape[1:], np.float32)
        out[:] = fill
        out[:n] = a
        return jax.device_put(out)

    return Scene(means=pad(rng.uniform(-1, 1, (n, 3))), log_scales=pad(np.log(sc)),
                 quats=pad(rng.normal(size=(n, 4)), np.array([1.0, 0, 0, 0])),
                 opacity_logits=pad(np.log(op) - np.log1p(-op), -20.0), sh=pad(sh),
                 active=pad(np.ones(n)))


def tagged_state(scene):
    """An optimiser state whose moments at active row i hold i + 1 (mu) and 1000 + i (nu) in every
    leaf (inactive rows: 0)."""
    C = scene.capacity
    act = np.asarray(scene.active)

    def fill(base):
        def f(path, x):
            if path[0].name == "active":
                return np.zeros(x.shape, np.float32)
            r = ((np.arange(C) + base) * act).reshape((C,) + (1,) * (x.ndim - 1))
            return np.broadcast_to(r, x.shape).astype(np.float32)
        return jax.tree_util.tree_map_with_path(f, scene)

    # The structure make_optimizer(...).init(scene) has (built directly: no per-shape compiles).
    return (AdamState(count=np.zeros([], np.int32), mu=fill(1.0), nu=fill(1000.0), age=fill(2000.0)),
            GroupLRState(count=np.zeros([], np.int32)))


def stats_of(grads, radii=None, C=None):
    g = np.asarray(grads, np.float32)
    C = C or g.shape[0]
    out = np.zeros(C, np.float32)
    out[: g.shape[0]] = g
    r = np.zeros(C, np.float32)
    if radii is not None:
        r[: len(radii)] = radii
    return DensifyStats(grad_sum=jnp.asarray(out), count=jnp.asarray((out > 0).astype(np.float32)),
                        max_radius=jnp.asarray(r))


def tag(scene):
    return np.round(np.asarray(scene.sh)[:, 0, 0]).astype(int) - 1  # row id of origin, -1 if none


HI, LO = 1e-3, 1e-5


def test_accumulate_pixel_to_ndc():
    s = DensifyStats.zeros(3)
    g = np.array([[1e-4, 0.0], [0.0, 1e-4], [3e-4, 4e-4]], np.float32)
    s = accumulate(s, g, np.array([True, True, False]), np.array([3.0, 7.0, 50.0]), 20, 10)
    s = accumulate(s, g, np.array([True, False, False]), np.array([5.0, 9.0, 1.0]), 20, 10)
    np.testing.assert_allclose(np.asarray(s.grad_sum), [2e-3, 5e-4, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(s.count), [2, 1, 0])
    np.testing.assert_array_equal(np.asarray(s.max_radius), [5.0, 7.0, 0.0])
    np.testing.assert_allclose(s.mean_grad(), [1e-3, 5e-4, 0.0], rtol=1e-6)
    # jit-compatible
    s2 = jax.jit(accumulate, static_argnums=(4, 5))(s, g, np.ones(3, bool), np.ones(3), 20, 10)
    assert float(s2.count[2]) == 1.0


def test_hand_built_clone_split_prune():
    # 0 clone, 1 split, 2 untouched (low grad), 3 low opacity, 4 too big in world, 5 too big on screen.
    scales = [0.005, 0.05, 0.05, 0.05, 0.2, 0.05]
    opac = [0.5, 0.5, 0.5, 0.01, 0.5, 0.5]
    scene = tagged_scene(scales, opac, capacity=8)
    state = tagged_state(scene)
    stats = stats_of([HI, HI, LO, LO, LO, LO], radii=[1, 1, 1, 1, 1, 30], C=8)
    cfg = DensifyConfig()
    s2, st2, stats2, info = densify_and_prune(scene, state, stats, cfg, 1.0, np.random.default_rng(0))
    assert (info.cloned, info.split, info.pruned) == (1, 1, 3)
    assert (info.capacity_before, info.capacity_after, info.shapes_changed) == (8, 8, False)
    assert info.num_active_before == 6 and info.num_active_after == 5 == s2.num_active()
    assert list(np.asarray(s2.active)) == [1, 1, 1, 0, 0, 0, 1, 1]
    assert list(tag(s2)[[0, 1, 2, 6, 7]]) == [0, 1, 2, 0, 1]   # clone in slot 6, split child in 7
    # Pruned rows are reset to the inactive fill.
    for r in (3, 4, 5):
        assert float(s2.opacity_logits[r]) == -20.0
        np.testing.assert_array_equal(np.asarray(s2.quats[r]), [1, 0, 0, 0])
        np.testing.assert_array_equal(np.asarray(s2.means[r]), 0)
    # Split children: scales / 1.6, clone exact copy.
    np.testing.assert_allclose(np.asarray(s2.log_scales)[[1, 7]],
                               np.repeat(np.asarray(scene.log_scales[1:2]) - math.log(1.6), 2, 0), atol=1e-6)
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(np.asarray(getattr(s2, f)[6]), np.asarray(getattr(scene, f)[0]))
    # Moments: untouched rows keep theirs, new / split / pruned rows are zero, count kept.
    mu, nu = adam_moments(st2)
    for m, base in ((mu, 1.0), (nu, 1000.0), (st2[0].age, 2000.0)):  # every tree of Adam's state follows
        got = np.asarray(m.means)[:, 0]
        np.testing.assert_array_equal(got, [base + 0, 0, base + 2, 0, 0, 0, 0, 0])
        np.testing.assert_array_equal(np.asarray(m.opacity_logits), got)
    assert int(st2[0].count) == int(state[0].count)
    assert stats2.capacity == 8 and float(np.sum(np.asarray(stats2.grad_sum))) == 0.0

    # Without size pruning only the low-opacity Gaussian goes.
    s3, _, _, info3 = densify_and_prune(scene, state, stats, cfg, 1.0, 0, prune_large=False)
    assert (info3.cloned, info3.split, info3.pruned) == (1, 1, 1)
    # A clone's parent that is too big on screen goes; its fresh clone (no radius yet) stays.
    big = stats_of([HI, HI, LO, LO, LO, LO], radii=[30, 1, 1, 1, 1, 1], C=8)
    s5, _, _, info5 = densify_and_prune(scene, state, big, cfg, 1.0, 0)
    assert info5.pruned == 3 and list(np.asarray(s5.active)[[0, 6]]) == [0, 1] and tag(s5)[6] == 0
    # Copying clone moments instead.
    cfg_copy = DensifyConfig(copy_clone_moments=True)
    _, st4, _, _ = densify_and_prune(scene, state, stats, cfg_copy, 1.0, 0)
    assert float(adam_moments(st4)[0].means[6, 0]) == 1.0


def test_schedule_helpers():
    cfg = DensifyConfig()
    assert not cfg.densify_at(500) and cfg.densify_at(600) and not cfg.densify_at(15000)
    assert cfg.reset_opacity_at(3000) and not cfg.reset_opacity_at(0) and not cfg.reset_opacity_at(15000)
    assert not cfg.prune_large(3000) and cfg.prune_large(3100)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 12), st.integers(0, 6), st.sampled_from([1, 2, 3]),
       st.booleans())
def test_moments_follow_gaussians(seed, n, spare, split_count, reset_all):
    rng = np.random.default_rng(seed)
    C = n + spare
    hot = rng.random(n) < 0.5
    small = rng.random(n) < 0.5
    low = rng.random(n) < 0.3
    scales = np.where(small, 0.005, 0.05)
    opac = np.where(low, 0.01, 0.5)
    scene = tagged_scene(scales, opac, capacity=C, seed=seed)
    state = tagged_state(scene)
    stats = stats_of(np.where(hot, HI, LO), radii=np.ones(n), C=C)
    cfg = DensifyConfig(split_count=split_count, reset_all_stats=reset_all)
    s2, st2, stats2, info = densify_and_prune(scene, state, stats, cfg, 1.0, rng, prune_large=False)
    mu, nu = adam_moments(st2)
    C2 = s2.capacity
    assert C2 == info.capacity_after and C2 >= C and (C2 == C or C2 % C == 0)
    for tree in (mu, nu, stats2):
        assert all(np.shape(x)[0] == C2 for x in jax.tree_util.tree_leaves(tree))

    act = np.asarray(s2.active) > 0
    origin = tag(s2)
    assert info.cloned == int(np.sum(hot & small)) and info.split == int(np.sum(hot & ~small))
    assert info.num_active_after == int(act.sum())
    assert np.all(np.asarray(s2.opacity_logits)[act] >= math.log(cfg.prune_opacity / (1 - cfg.prune_opacity)))
    mu_means, nu_means = np.asarray(mu.means)[:, 0], np.asarray(nu.means)[:, 0]
    for i in range(n):
        copies = np.flatnonzero(act & (origin == i))
        if low[i]:
            assert copies.size == 0
        elif not hot[i]:
            assert list(copies) == [i]
            assert mu_means[i] == i + 1 and nu_means[i] == 1000 + i
            for f in ("means", "log_scales", "quats", "sh"):
                np.testing.assert_array_equal(np.asarray(getattr(s2, f)[i]), np.asarray(getattr(scene, f)[i]))
        elif small[i]:
            assert copies.size == 2 and i in copies
            other = copies[copies != i][0]
            assert mu_means[i] == i + 1 and mu_means[other] == 0 and nu_means[other] == 0
        else:
            assert copies.size == split_count and i in copies
            assert np.all(mu_means[copies] == 0) and np.all(nu_means[copies] == 0)
    g2 = np.asarray(stats2.grad_sum)
    if reset_all:
        assert np.all(g2 == 0)
    else:   # untouched rows keep their statistics, new / split / pruned rows restart
        keep = np.zeros(C2, bool)
        keep[:n] = ~hot & ~low
        np.testing.assert_array_equal(g2[keep], np.asarray(stats.grad_sum)[:n][keep[:n]])
        assert np.all(g2[~keep] == 0)
    # Every other row is inactive with zero moments.
    dead = ~act
    assert np.all(np.asarray(s2.opacity_logits)[dead & (np.arange(C2) >= n)] == -20.0)
    assert np.all(mu_means[dead] == 0) and np.all(nu_means[dead] == 0)
    assert np.all(np.asarray(mu.quats)[dead] == 0)


def test_tagged_state_matches_optimizer_structure():
    scene = tagged_scene([0.05] * 3, [0.5] * 3, capacity=4)
    assert (jax.tree_util.tree_structure(tagged_state(scene))
            == jax.tree_util.tree_structure(make_optimizer(1.0).init(scene)))


def test_capacity_doubling():
    scene = tagged_scene([0.005] * 4, [0.5] * 4, capacity=4)
    state = tagged_state(scene)
    s2, st2, stats2, info = densify_and_prune(scene, state, stats_of([HI] * 4), DensifyConfig(), 1.0, 0)
    assert (info.capacity_before, info.capacity_after, info.shapes_changed) == (4, 8, True)
    assert s2.num_active() == 8 and s2.capacity == 8 and stats2.capacity == 8
    # Splitting 4 into 3 children each needs 8 new slots: 4 -> 8 -> 16.
    scene = tagged_scene([0.05] * 4, [0.5] * 4, capacity=4)
    s3, st3, _, info = densify_and_prune(scene, tagged_state(scene), stats_of([HI] * 4),
                                         DensifyConfig(split_count=3), 1.0, 0)
    assert info.capacity_after == 16 and s3.num_active() == 12
    assert adam_moments(st3)[0].sh.shape == (16, 4, 3)


def test_cap_honoured_highest_gradient_first():
    grads = [2.5e-4, 9e-4, 5e-4, 7e-4, 3e-4, LO]
    scene = tagged_scene([0.005, 0.005, 0.05, 0.005, 0.05, 0.005], [0.5] * 6, capacity=16)
    cfg = DensifyConfig(max_gaussians=8)
    s2, _, _, info = densify_and_prune(scene, None, stats_of(grads, C=16), cfg, 1.0, 0)
    assert s2.num_active() == 8 and info.dropped_by_cap == 3
    assert info.cloned == 2 and info.split == 0                 # rows 1 and 3 (highest gradients)
    assert sorted(tag(s2)[np.asarray(s2.active) > 0]) == [0, 1, 1, 2, 3, 3, 4, 5]
    # Already at the cap: nothing grows.
    _, _, _, info = densify_and_prune(scene, None, stats_of(grads, C=16), DensifyConfig(max_gaussians=6),
                                      1.0, 0)
    assert info.cloned == info.split == 0 and info.num_active_after == 6


def test_split_samples_in_tangent_plane():
    n_children = 400
    scene = tagged_scene([0.3], [0.5], capacity=1, seed=5)
    cfg = DensifyConfig(split_count=n_children, max_world_scale=None)
    s2, _, _, info = densify_and_prune(scene, None, stats_of([HI]), cfg, 1.0, 1)
    assert info.split == 1 and s2.num_active() == n_children
    R = np.asarray(quat_to_rotmat(scene.quats[0]), np.float64)
    d = np.asarray(s2.means, np.float64)[: n_children] - np.asarray(scene.means[0], np.float64)
    local = d @ R                                    # (u, v, normal) coordinates
    assert np.max(np.abs(local[:, 2])) < 1e-5
    s = np.exp(np.asarray(scene.log_scales[0], np.float64))
    np.testing.assert_allclose(local[:, :2].std(axis=0), s, rtol=0.15)
    np.testing.assert_allclose(np.asarray(s2.log_scales)[: n_children],
                               np.broadcast_to(np.log(s) - math.log(0.8 * n_children), (n_children, 2)),
                               atol=1e-5)


def test_reset_opacity():
    scene = tagged_scene([0.05] * 3, [0.005, 0.5, 0.9], capacity=4)
    state = tagged_state(scene)
    s2, st2 = reset_opacity(scene, state, 0.01)
    np.testing.assert_allclose(np.asarray(s2.opacities)[:3], [0.005, 0.01, 0.01], rtol=1e-5)
    assert float(s2.opacity_logits[3]) == -20.0
    mu, nu = adam_moments(st2)
    assert np.all(np.asarray(mu.opacity_logits) == 0) and np.all(np.asarray(nu.opacity_logits) == 0)
    np.testing.assert_array_equal(np.asarray(mu.means), np.asarray(adam_moments(state)[0].means))


def test_resize_capacity():
    scene = tagged_scene([0.05] * 3, [0.5] * 3, capacity=3)
    big = resize_capacity(scene, 5)
    assert big.capacity == 5 and big.num_active() == 3
    np.testing.assert_array_equal(np.asarray(big.quats[3:]), [[1, 0, 0, 0]] * 2)
    assert np.all(np.asarray(big.opacity_logits[3:]) == -20.0)
    state = resize_opt_state(tagged_state(scene), 5)
    mu, _ = adam_moments(state)
    assert mu.quats.shape == (5, 4) and np.all(np.asarray(mu.quats[3:]) == 0)
    assert resize_capacity(big, 3).capacity == 3
    with pytest.raises(ValueError, match="shrink"):
        resize_capacity(scene, 2)
    assert resize_capacity(DensifyStats.zeros(3), 6).capacity == 6


def test_textured_prune_and_clone_refused():
    scene = random_scene(1, 6, rgb_sizes=[2, 0, 3, 4, 1, 2], alpha_sizes=[0, 2, 2, 0, 5, 1], capacity=8)
    state = make_optimizer(1.0).init(scene)
    state = (state[0]._replace(mu=jax.tree_util.tree_map(jnp.ones_like, state[0].mu)), state[1])
    mask = np.array([False, True, True, False, False, False, False, False])
    s2, st2, _, n = prune_gaussians(scene, state, DensifyStats.zeros(8), mask)
    assert n == 2 and s2.num_active() == 4
    for bank_name in ("rgb", "alpha"):
        b0, b2 = getattr(scene, bank_name), getattr(s2, bank_name)
        assert b2.capacities == b0.capacities
        for i in range(6):
            if mask[i]:
                assert b2.texture(i) is None
                b, sl = int(b0.bucket[i]), int(b0.slot[i])
                if b >= 0:   # texels and their moments zeroed
                    assert np.all(np.asarray(b2.buckets[b][sl]) == 0)
                    assert np.all(np.asarray(getattr(adam_moments(st2)[0], bank_name).buckets[b][sl]) == 0)
            else:
                t0, t2 = b0.texture(i), b2.texture(i)
                assert (t0 is None and t2 is None) or np.array_equal(t0, t2)
    # densify_and_prune prunes textured scenes (grow=False) and refuses to clone them.
    op = np.asarray(scene.opacity_logits).copy()
    op[4] = -10.0
    low = scene.replace(opacity_logits=jnp.asarray(op))
    hot = stats_of([HI] * 6, C=8)
    _, _, _, info = densify_and_prune(low, state, hot, DensifyConfig(), 1.0, 0, grow=False,
                                      prune_large=False)
    assert info.pruned == 1 and info.cloned == 0
    with pytest.raises(NotImplementedError, match="grow=False"):
        densify_and_prune(low, state, hot, DensifyConfig(), 1.0, 0)


# ------------------------------------------------------------------------------------------------
# The device path (capacity kept: rows written in place) against the host path, bit for bit.
def _device_copy(tree):
    return jax.tree_util.tree_map(lambda x: jax.device_put(np.array(x)), tree)


def random_state(seed, C, n_active, dims=2, filter3d=False):
    """A scene with ``n_active`` active rows scattered over C slots (garbage in the inactive ones,
    which the device path must leave alone as the host path copies them), scales straddling the
    clone / split and world-prune thresholds, some low opacities; random Adam moments (mu, nu, age)."""
    rng = np.random.default_rng(seed)
    act = np.zeros(C, np.float32)
    act[rng.choice(C, n_active, replace=False)] = 1.0
    f = np.float32
    scale = np.exp(rng.uniform(np.log(0.003), np.log(0.15), C))  # a third cloned, a tenth too large
    scene = Scene(means=jax.device_put(rng.uniform(-1, 1, (C, 3)).astype(f)),
                  log_scales=jax.device_put(np.log(scale[:, None] * rng.uniform(0.6, 1.0, (C, dims))).astype(f)),
                  quats=jax.device_put(rng.normal(size=(C, 4)).astype(f)),
                  opacity_logits=jax.device_put(rng.normal(1.0, 2.5, C).astype(f)),
                  sh=jax.device_put(rng.normal(size=(C, 4, 3)).astype(f)), active=jax.device_put(act),
                  filter3d=jax.device_put(rng.uniform(0, 1e-3, C).astype(f)) if filter3d else None)
    return scene, random_moments(scene, rng)


def random_moments(scene, rng):
    def tree():
        return jax.tree_util.tree_map(lambda x: jax.device_put(rng.normal(size=np.shape(x)).astype(np.float32)),
                                      scene)
    return (AdamState(count=jnp.asarray(7, jnp.int32), mu=tree(), nu=tree(), age=tree()),
            GroupLRState(count=jnp.asarray(7, jnp.int32)))


def random_stats(seed, scene):
    rng = np.random.default_rng(seed + 1)
    C = scene.capacity
    act = np.asarray(scene.active) > 0
    g = np.where(act & (rng.random(C) < 0.3), HI, LO).astype(np.float32) * rng.uniform(1, 3, C).astype(np.float32)
    cnt = np.where(act, rng.integers(1, 4, C), 0).astype(np.float32)
    return DensifyStats(grad_sum=jax.device_put(g * cnt), count=jax.device_put(cnt),
                        max_radius=jax.device_put(rng.uniform(0, 24, C).astype(np.float32)))


def assert_same_result(a, b):
    (sa, sta, sta_s, ia), (sb, stb, stb_s, ib) = a, b
    assert ia == ib
    for x, y in ((sa, sb), (sta, stb), (sta_s, stb_s)):
        la, ta = jax.tree_util.tree_flatten_with_path(x)
        lb, tb = jax.tree_util.tree_flatten_with_path(y)
        assert ta == tb
        for (path, u), (_, v) in zip(la, lb, strict=True):
            u, v = np.asarray(u), np.asarray(v)
            assert u.dtype == v.dtype and u.shape == v.shape, jax.tree_util.keystr(path)
            assert np.array_equal(u, v), jax.tree_util.keystr(path)   # bit for bit (no NaNs here)


CASES = [dict(), dict(split_count=1), dict(split_count=3), dict(copy_clone_moments=True),
         dict(reset_all_stats=False), dict(max_gaussians=44), dict(max_gaussians=46, split_count=3),
         dict(prune_large=False), dict(grow=False), dict(dims=3), dict(filter3d=True),
         dict(dims=3, filter3d=True, copy_clone_moments=True, reset_all_stats=False)]


@pytest.mark.parametrize("case", CASES, ids=[",".join(f"{k}={v}" for k, v in c.items()) or "default"
                                             for c in CASES])
def test_device_path_matches_host_path(case):
    from patexgs_jax.densify import _densify_and_prune

    case = dict(case)
    dims, f3 = case.pop("dims", 2), case.pop("filter3d", False)
    kw = dict(prune_large=case.pop("prune_large", True), grow=case.pop("grow", True))
    cfg = DensifyConfig(**case)
    for seed in range(3):   # C = 64 for every case: one padded shape
        scene, state = random_state(seed, 64, 40, dims, f3)
        stats = random_stats(seed, scene)
        host = _densify_and_prune(_device_copy(scene), _device_copy(state), stats, cfg, 1.0, seed,
                                  in_place=False, donate=False, **kw)
        assert host[3].capacity_after == 64
        old_means = scene.means
        dev = densify_and_prune(scene, state, stats, cfg, 1.0, seed, donate=True, **kw)
        assert_same_result(host, dev)
        if host[3].pruned or host[3].cloned or host[3].split:
            assert old_means.is_deleted()   # donated: written in place
        # Without donation the inputs stay usable and the result is the same.
        scene, state = random_state(seed, 64, 40, dims, f3)
        assert_same_result(host, densify_and_prune(scene, state, stats, cfg, 1.0, seed, **kw))
        assert not scene.means.is_deleted()


def test_device_path_matches_host_path_textured_prune():
    from patexgs_jax.densify import _densify_and_prune

    rng = np.random.default_rng(3)
    n = 12
    scene = random_scene(1, n, rgb_sizes=rng.integers(0, 5, n), alpha_sizes=rng.integers(0, 4, n), capacity=16)
    op = np.asarray(scene.opacity_logits).copy()
    op[[1, 4, 5, 9]] = -10.0                   # pruned: textured and untextured rows
    scene = scene.replace(opacity_logits=jax.device_put(op))
    state = random_moments(scene, rng)
    stats = stats_of([HI] * n, radii=rng.uniform(0, 30, n), C=16)
    host = _densify_and_prune(_device_copy(scene), _device_copy(state), stats, DensifyConfig(), 1.0, 0,
                              prune_large=True, grow=False, in_place=False, donate=False)
    assert host[3].pruned >= 4
    assert_same_result(host, densify_and_prune(scene, state, stats, DensifyConfig(), 1.0, 0, grow=False,
                                               donate=True))


def test_device_path_compiles_a_few_times():
    """Densification events at one capacity with different numbers of changed rows compile the row
    writes once per padded size (powers of 8), not once an event."""
    compiles = []

    def listen(event, seconds, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(event)

    C = 8192
    scene, state = random_state(11, C, 2000)
    cfg = DensifyConfig(max_screen_radius=None, max_world_scale=None)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        per_event = []
        for k, n_hot in enumerate([3, 20, 50, 300, 9, 200, 35]):
            act = np.asarray(scene.active) > 0
            rows = np.flatnonzero(act)[:n_hot]
            g = np.zeros(C, np.float32)
            g[rows] = HI
            stats = DensifyStats(grad_sum=jax.device_put(g), count=jax.device_put(act.astype(np.float32)),
                                 max_radius=jax.device_put(np.zeros(C, np.float32)))
            before = len(compiles)
            scene, state, _, info = densify_and_prune(scene, state, stats, cfg, 1.0, k, donate=True)
            jax.block_until_ready((scene, state))
            assert info.capacity_after == C and info.cloned + info.split == n_hot
            per_event.append(len(compiles) - before)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    # The changed rows (the first event's low-opacity prunes, then 2 a split) pad to 64, 512 or 4096
    # rows and the split rows to 64 or 512: per padded size the parameter write and the moment write
    # (one program for mu, nu and age) compile once, and the split-row gather once: 8 programs.
    assert sum(per_event) <= 9, per_event
    assert per_event[4:] == [0, 0, 0], per_event
