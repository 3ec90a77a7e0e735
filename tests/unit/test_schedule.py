"""Adaptive texture sizes (:mod:`patexgs_jax.adaptive`: Eqs. 7-10, budgets, schedule state) and
re-bucketing with moments (:mod:`patexgs_jax.rebucket`).

Everything but one test is host-side numpy; the rendering-invariance test compiles the renderer
once (one small camera, one scene shape: the resize there keeps every bucket shape).
"""

from __future__ import annotations

import dataclasses
import io

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from patexgs_jax import Camera, Capacity, RenderConfig, adaptive, look_at, random_scene
from patexgs_jax.adaptive import (
    ContributionCounts,
    GrowthSchedule,
    TextureScheduleState,
    contribution_sizes,
    default_sigma,
    grow_sizes,
    initial_texture_sizes,
    pixel_share_sigma,
    side_of,
    solve_sigma_for_budget,
    total_texels,
)
from patexgs_jax.metrics import mb_to_texels, storage_mb, texels_to_mb
from patexgs_jax.optim import adam_moments, make_optimizer
from patexgs_jax.render import _render
from patexgs_jax.textures import rebucket as rb
from patexgs_jax.textures.rebucket import add_textures, resample_matrix, resize_textures

BANKS = ("rgb", "alpha")
NEUTRAL = {"rgb": 0.0, "alpha": 1.0}


# ----------------------------------------------------------------------------------- helpers
def ref_area_weights(n: int, m: int, samples: int = 20_000) -> np.ndarray:
    """(m, n) weights of the mean of the bilinear interpolant over each new texel's cell, by the
    midpoint rule on ``samples`` points a cell (independent of the closed form)."""
    last = n - 1.0
    if m == 1:
        cells = [(0.0, last)]
    else:
        h = last / (m - 1)
        cells = [(max(j * h - h / 2, 0.0), min(j * h + h / 2, last)) for j in range(m)]
    W = np.zeros((m, n))
    for j, (lo, hi) in enumerate(cells):
        t = lo + (np.arange(samples) + 0.5) * (hi - lo) / samples
        W[j] = np.maximum(0.0, 1.0 - np.abs(t[:, None] - np.arange(n)[None, :])).mean(axis=0)
    return W


def ref_resample(tex: np.ndarray, m: int) -> np.ndarray:
    """Independent reference. Growing: the renderer's bilinear lookup (textures.corners, in
    float64) at the new texel positions -3 + 6 j / (m - 1), one texel at a time. Shrinking: the
    interpolant's mean over each new texel's cell (:func:`ref_area_weights`, separably: the
    interpolant is a tensor product)."""
    n = tex.shape[0]
    tex = tex.astype(np.float64)
    if m < n:
        W = ref_area_weights(n, m)
        return np.einsum("ma,abc,nb->mnc", W, tex, W)
    pos = -3.0 + 6.0 * np.arange(m) / (m - 1) if m > 1 else np.array([0.0])

    def lookup(u, v):
        last = max(n - 1.0, 0.0)
        ta = min(max((u + 3.0) / 6.0 * last, 0.0), last)
        tb = min(max((v + 3.0) / 6.0 * last, 0.0), last)
        a0 = min(np.floor(ta), max(last - 1.0, 0.0))
        b0 = min(np.floor(tb), max(last - 1.0, 0.0))
        fa, fb = ta - a0, tb - b0
        a0, b0 = int(a0), int(b0)
        a1, b1 = min(a0 + 1, n - 1), min(b0 + 1, n - 1)
        return ((1 - fa) * ((1 - fb) * tex[a0, b0] + fb * tex[a0, b1])
                + fa * ((1 - fb) * tex[a1, b0] + fb * tex[a1, b1]))

    return np.array([[lookup(u, v) for v in pos] for u in pos])


def interpolant_mean(tex: np.ndarray) -> np.ndarray:
    """(ch,) mean of a texture's bilinear interpolant over [-3, 3]^2 (trapezoid weights)."""
    n = tex.shape[0]
    w = np.ones(n) if n == 1 else np.r_[0.5, np.ones(n - 2), 0.5] / (n - 1)
    return np.einsum("a,abc,b->c", w, tex.astype(np.float64), w)


def slot_of(bank, i):
    return int(bank.bucket[i]), int(bank.slot[i]), int(bank.size[i])


def tex_of(data_bank, index_bank, i):
    """Gaussian i's used block in ``data_bank`` (params or a moment tree), located by ``index_bank``."""
    b, s, n = slot_of(index_bank, i)
    return None if b < 0 else np.asarray(data_bank.buckets[b][s, :n, :n])


def randomise_moments(scene, opt_state, rng):
    """Distinct random mu (normal) and nu (positive) per texel of used blocks; padding stays zero."""
    def fill(m, positive):
        kw = {}
        for name in BANKS:
            bank, mb = getattr(scene, name), getattr(m, name)
            new = [np.zeros(d.shape, np.float32) for d in mb.buckets]
            for i in range(scene.capacity):
                b, s, n = slot_of(bank, i)
                if b >= 0:
                    shape = (n, n, bank.channels)
                    new[b][s, :n, :n] = rng.uniform(0.1, 2.0, shape) if positive else rng.normal(size=shape)
            kw[name] = dataclasses.replace(mb, buckets=tuple(jnp.asarray(x) for x in new))
        return m.replace(**kw)

    adam, group = opt_state
    return (adam._replace(mu=fill(adam.mu, False), nu=fill(adam.nu, True)), group)


def check_bank_layout(bank, data=None):
    """Unique in-range slots, zero padding and zero free slots, power-of-two capacities; ``data``
    (a moment tree laid out by ``bank``) is checked for the padding and free slots instead."""
    data = bank if data is None else data
    C = bank.size.shape[0]
    seen = set()
    used = [np.zeros(d.shape[0], bool) for d in bank.buckets]
    for i in range(C):
        b, s, n = slot_of(bank, i)
        if b < 0:
            assert n == 0 and int(bank.slot[i]) == 0
            continue
        assert b == (n - 1).bit_length() and 0 <= s < bank.buckets[b].shape[0]
        assert (b, s) not in seen
        seen.add((b, s))
        used[b][s] = True
    for b, d in enumerate(data.buckets):
        cap = d.shape[0]
        assert cap == 0 or cap & (cap - 1) == 0
        d = np.asarray(d)
        assert not np.any(d[~used[b]])
    for i in range(C):
        b, s, n = slot_of(bank, i)
        if b >= 0:
            block = np.asarray(data.buckets[b][s]).copy()
            block[:n, :n] = 0
            assert not np.any(block)


# ------------------------------------------------------------------------- property: resize
SIDES = [0, 1, 2, 3, 4, 5, 7, 8, 9]
C_PROP = 5


@settings(max_examples=25)
@given(data=st.data(), seed=st.integers(0, 2**16))
def test_resize_sequence_resamples_texels_and_moments(data, seed):
    rng = np.random.default_rng(seed)
    init = {name: data.draw(st.lists(st.sampled_from(SIDES), min_size=C_PROP, max_size=C_PROP))
            for name in BANKS}
    scene = random_scene(seed, C_PROP, rgb_sizes=init["rgb"], alpha_sizes=init["alpha"])
    opt = make_optimizer(1.0)
    state = randomise_moments(scene, opt.init(scene), rng)
    num_steps = data.draw(st.integers(1, 4))
    for _ in range(num_steps):
        requests = {}
        for name in BANKS:
            cur = np.asarray(getattr(scene, name).size).astype(int)
            mode = data.draw(st.sampled_from(["new", "new", "same", "none"]))
            if mode == "none":
                requests[name] = None
            elif mode == "same":
                requests[name] = cur.copy()
            else:  # mix of keep / shrink / grow / 0 <-> n per Gaussian
                requests[name] = np.array([c if data.draw(st.booleans()) else data.draw(st.sampled_from(SIDES))
                                           for c in cur])
        min_cap = data.draw(st.sampled_from([1, 1, 4]))
        new_scene, new_state, info = resize_textures(scene, state, requests["rgb"], requests["alpha"],
                                                     min_capacity=min_cap)
        (mu0, nu0), (mu1, nu1) = adam_moments(state), adam_moments(new_state)
        assert int(new_state[0].count) == int(state[0].count)
        for leaf in ("means", "log_scales", "quats", "opacity_logits", "sh", "active"):
            assert getattr(new_scene, leaf) is getattr(scene, leaf)
            assert getattr(mu1, leaf) is getattr(mu0, leaf)
        for name in BANKS:
            old_b, new_b = getattr(scene, name), getattr(new_scene, name)
            req = requests[name]
            if req is None:
                assert new_b is old_b and getattr(mu1, name) is getattr(mu0, name)
                assert info.changed[name] == 0
                continue
            check_bank_layout(new_b)
            assert len(new_b.buckets) >= len(old_b.buckets)
            # The layout is kept while every bucket holds its textures, else sized afresh.
            counts = np.bincount([(int(n) - 1).bit_length() for n in req if n > 0], minlength=len(new_b.buckets))
            relaid = new_b.capacities != old_b.capacities
            fits = all(c <= cap for c, cap in zip(counts, old_b.capacities + (0,) * len(counts)))
            assert relaid == (not fits)
            if relaid:  # the buckets that overflow sized afresh; those that fit kept unless mostly emptied
                fresh = [0 if c == 0 else 1 << (max(int(c), min_cap) - 1).bit_length() for c in counts]
                olds = old_b.capacities + (0,) * (len(counts) - len(old_b.capacities))
                assert new_b.capacities == tuple(o if c <= o <= rb.KEEP_WITHIN * f else f
                                                 for c, o, f in zip(counts, olds, fresh))
            for mtree in (getattr(mu1, name), getattr(nu1, name)):
                assert tuple(x.shape for x in mtree.buckets) == tuple(x.shape for x in new_b.buckets)
                for leaf in (mtree.bucket, mtree.slot, mtree.size):
                    assert not np.any(np.asarray(leaf))
                check_bank_layout(new_b, data=mtree)
            assert np.all(np.asarray(new_b.size).astype(int) == req)
            old_sizes = np.asarray(old_b.size).astype(int)
            assert info.changed[name] == int(np.sum(old_sizes != req))
            assert info.texels_before[name] == int(np.sum(old_sizes**2))
            assert info.texels_after[name] == int(np.sum(req**2)) == new_b.texel_count()
            assert info.capacities_after[name] == new_b.capacities
            for i in range(C_PROP):
                n, m = old_sizes[i], req[i]
                trees = [(old_b, new_b), (getattr(mu0, name), getattr(mu1, name)),
                         (getattr(nu0, name), getattr(nu1, name))]
                for k, (t_old, t_new) in enumerate(trees):
                    before, after = tex_of(t_old, old_b, i), tex_of(t_new, new_b, i)
                    if m == 0:
                        assert after is None
                    elif m == n:
                        if not relaid:
                            assert slot_of(new_b, i) == slot_of(old_b, i)  # stable slot
                        (b, s, _), (_, s_old, _) = slot_of(new_b, i), slot_of(old_b, i)
                        # The block is copied bit-exactly, padding included.
                        assert np.array_equal(np.asarray(t_new.buckets[b][s]), np.asarray(t_old.buckets[b][s_old]))
                    elif n == 0:
                        assert np.all(after == (NEUTRAL[name] if k == 0 else 0.0))
                    else:
                        np.testing.assert_allclose(after, ref_resample(before, m), rtol=1e-6, atol=1e-6)
                        if k == 2:
                            assert np.all(after >= 0)
        total_changed = sum(info.changed.values())
        assert info.num_changed == total_changed
        new_shapes = [tuple(x.shape for x in getattr(new_scene, nm).buckets) for nm in BANKS]
        old_shapes = [tuple(x.shape for x in getattr(scene, nm).buckets) for nm in BANKS]
        assert info.shapes_changed == (new_shapes != old_shapes)
        scene, state = new_scene, new_state


def test_resample_matrix_properties():
    for n in range(1, 7):
        for m in range(1, 10):
            R = resample_matrix(n, m)
            assert R.shape == (m, n) and np.all(R >= 0)
            np.testing.assert_allclose(R.sum(axis=1), 1.0, atol=1e-15)
            if 1 < m < n:
                np.testing.assert_allclose(R, ref_area_weights(n, m), atol=1e-8)
    assert np.array_equal(resample_matrix(4, 4), np.eye(4))
    np.testing.assert_allclose(resample_matrix(3, 1), [[0.25, 0.5, 0.25]], atol=1e-15)  # m = 1: the mean
    np.testing.assert_allclose(resample_matrix(2, 1), [[0.5, 0.5]], atol=1e-15)
    np.testing.assert_allclose(resample_matrix(5, 2), [[0.25, 0.5, 0.25, 0, 0], [0, 0, 0.25, 0.5, 0.25]],
                               atol=1e-15)  # every texel of the 5x5 warm-up texture counts
    np.testing.assert_array_equal(resample_matrix(1, 3), [[1.0], [1.0], [1.0]])
    np.testing.assert_array_equal(resample_matrix(2, 3), [[1, 0], [0.5, 0.5], [0, 1]])


@settings(max_examples=25)
@given(sides=st.lists(st.integers(1, 12), min_size=2, max_size=6), seed=st.integers(0, 2**16))
def test_shrinking_keeps_the_mean(sides, seed):
    """Any sequence of shrinks keeps the interpolant's mean; a growth keeps it where it is exact."""
    tex = np.random.default_rng(seed).normal(size=(sides[0], sides[0], 3))
    mean = interpolant_mean(tex)
    for m in sides[1:]:
        n = tex.shape[0]
        tex = np.einsum("ma,abc,nb->mnc", resample_matrix(n, m), tex, resample_matrix(n, m))
        if m < n or n == 1 or (m - 1) % (n - 1) == 0:
            np.testing.assert_allclose(interpolant_mean(tex), mean, rtol=1e-12, atol=1e-12)
        else:
            mean = interpolant_mean(tex)


def test_slots_are_reused_and_overflowing_buckets_sized_afresh():
    scene = random_scene(0, 4, rgb_sizes=[2, 2, 0, 0], alpha_sizes=None)
    assert scene.rgb.capacities == (0, 2)
    # Swap: 0 leaves bucket 1, 2 arrives; capacity unchanged and the freed slot is reused.
    s1, _, info = resize_textures(scene, None, [0, 2, 2, 0], None)
    assert not info.shapes_changed and s1.rgb.capacities == (0, 2)
    assert int(s1.rgb.slot[1]) == int(scene.rgb.slot[1]) and int(s1.rgb.slot[2]) == int(scene.rgb.slot[0])
    # Three in bucket 1: it grows to 4; a new bucket 3 starts at min_capacity rounded up.
    s2, _, info = resize_textures(s1, None, [2, 2, 2, 6], None, min_capacity=3)
    assert info.shapes_changed and s2.rgb.capacities == (0, 4, 0, 4)
    # Shrinking everything that fits keeps the layout (no recompile) ...
    s3, _, info = resize_textures(s2, None, [0, 0, 0, 0], None)
    assert s3.rgb.capacities == (0, 4, 0, 4) and not info.shapes_changed
    assert info.texels_before["rgb"] == 4 * 3 + 36 and info.texels_after["rgb"] == 0
    # ... and an overflow (a new bucket here) sizes afresh the buckets that overflow, keeps those
    # that fit (bucket 3: 2 textures in 4 slots) and shrinks the emptied ones; none is removed.
    s4, _, info = resize_textures(s2, None, [9, 0, 5, 6], None)
    assert info.shapes_changed and s4.rgb.capacities == (0, 0, 0, 4, 1)
    assert [s4.rgb.texture(i) is None for i in range(4)] == [False, True, False, False]
    np.testing.assert_array_equal(s4.rgb.texture(3), s2.rgb.texture(3))


def test_headroom_keeps_the_layout_through_small_moves():
    """A bucket sized afresh gets max(headroom * count, min_spare) free slots (a power of two in
    all, at most the scene's capacity), so the next few moves into it keep the shapes."""
    sides = [1] * 20 + [2] * 12
    scene = random_scene(0, 32, rgb_sizes=[0] * 32, alpha_sizes=None)
    scene, _, info = resize_textures(scene, None, sides, None, headroom=0.5, min_spare=4)
    assert scene.rgb.capacities == (32, 32)  # 20 + 10 -> 32; 12 + 6 -> 32 (the scene's capacity)
    grown = list(sides)
    for i in range(8):  # eight textures move from bucket 0 to bucket 1, one resize at a time
        grown[i] = 2
        scene, _, info = resize_textures(scene, None, grown, None, headroom=0.5, min_spare=4)
        assert not info.shapes_changed
    small = random_scene(0, 32, rgb_sizes=[0] * 32, alpha_sizes=None)
    small, _, _ = resize_textures(small, None, [3] + [0] * 31, None, headroom=0.5, min_spare=4)
    assert small.rgb.capacities == (0, 0, 8)  # 1 + max(0.5, 4) -> 8
    with pytest.raises(ValueError, match="headroom"):
        resize_textures(small, None, [3] + [0] * 31, None, headroom=-1)


def test_resize_rejects_bad_inputs():
    scene = random_scene(1, 3, rgb_sizes=[1, 2, 3], alpha_sizes=None)
    with pytest.raises(ValueError, match="shape"):
        resize_textures(scene, None, [1, 2], None)
    with pytest.raises(ValueError, match=">= 0"):
        resize_textures(scene, None, [1, -2, 3], None)
    with pytest.raises(ValueError, match="max_size"):
        resize_textures(scene, None, [1, 2, 40], None, max_size=32)
    with pytest.raises(ValueError, match="integer"):
        resize_textures(scene, None, [1, 2.5, 3], None)
    with pytest.raises(ValueError, match="add_textures"):
        resize_textures(scene, None, None, [1, 1, 1])
    with pytest.raises(ValueError, match="already has"):
        add_textures(scene, None, None, [1, 1, 1], None)
    opt = make_optimizer(1.0)
    other = random_scene(1, 3, rgb_sizes=[4, 4, 4], alpha_sizes=None)
    with pytest.raises(ValueError, match="moments"):
        resize_textures(scene, opt.init(other), [1, 1, 1], None)


# ------------------------------------------------------------------------ rendering invariance
def test_exact_growth_leaves_the_render_unchanged():
    """n -> m with (m - 1) a multiple of (n - 1) (1 -> any, 2 -> any, 3 -> 5) keeps the bilinear
    interpolant, so the image (mip off) is unchanged. Two inactive dummies swap sizes with the
    active splats so every bucket keeps its shape: one compile."""
    C = 4
    scene = random_scene(3, C, extent=0.25, scale_range=(0.25, 0.5), opacity_range=(0.5, 0.9),
                         rgb_sizes=[2, 1, 3, 4], alpha_sizes=[2, 3, 5, 5])
    scene = scene.replace(active=jnp.asarray([1.0, 1.0, 0.0, 0.0]))
    grown, _, info = resize_textures(scene, None, [3, 4, 2, 1], [5, 5, 2, 3])
    assert not info.shapes_changed and info.changed == {"rgb": 4, "alpha": 4}
    cam = Camera.from_intrinsics([40.0, 40.0, 16.0, 16.0], look_at((0.2, -0.1, -2.0), (0, 0, 0)), 32, 32)
    cfg, cap = RenderConfig(mip="none"), Capacity(pairs=256)
    # The renderer traced at most once for the three scenes below (a second trace raises).
    render_once = jax.jit(chex.assert_max_traces(_render, n=1), static_argnames=("config", "capacity"))
    outs = [render_once(s, cam, config=cfg, capacity=cap) for s in (scene, grown)]
    assert not any(bool(o.overflow) for o in outs)
    np.testing.assert_allclose(np.asarray(outs[1].rgb), np.asarray(outs[0].rgb), atol=2e-5)
    np.testing.assert_allclose(np.asarray(outs[1].alpha), np.asarray(outs[0].alpha), atol=2e-5)
    # Not vacuous: the textures do show (same shapes, no recompile).
    flat = scene.replace(rgb=dataclasses.replace(
        scene.rgb, buckets=tuple(jnp.zeros_like(b) for b in scene.rgb.buckets)))
    plain = render_once(flat, cam, config=cfg, capacity=cap)
    assert np.max(np.abs(np.asarray(plain.rgb) - np.asarray(outs[0].rgb))) > 1e-2


# --------------------------------------------------------------------------------------- Eq. 7
def test_eq7_hand_computed():
    S = np.array([[0, 3, 100, 0], [1, 1, 50, 0]])
    # T = [log2(1) + log2(2), log2(4) + log2(2), log2(101) + log2(51), 0] = [1, 3, 12.33, 0]
    np.testing.assert_array_equal(initial_texture_sizes(S, 1.0), [1, 3, 12, 1])
    np.testing.assert_array_equal(initial_texture_sizes(S, 1.0, max_size=8), [1, 3, 8, 1])
    np.testing.assert_array_equal(initial_texture_sizes(S, 1.0, active=[1, 1, 0, 1]), [1, 3, 0, 1])
    # sigma = 3: [log2(4/3)... ] = [0 + 0.415, 1 + 0.415, 5.11 + 4.19, 0] -> [1 (min), 1, 9, 1]
    np.testing.assert_array_equal(initial_texture_sizes(S, 3.0), [1, 1, 9, 1])
    np.testing.assert_array_equal(side_of([0.0, 0.2, 1.49, 1.5, 2.5, 40.0]), [0, 1, 1, 2, 3, 32])
    assert default_sigma(800, 1000) == 80.0
    # The scale-free default equals the paper's at its scale (200 views, 10^6 Gaussians) ...
    assert pixel_share_sigma(200 * 800 * 1000, 10**6) == pytest.approx(default_sigma(800, 1000))
    # ... and gives about the same T to a Gaussian that dominates the same share (here all) of its fair
    # share of the pixel-views, spread over its views, at a far smaller scale (21 views, 3,900 Gaussians).

    small = pixel_share_sigma(21 * 96 * 128, 3900)
    S_paper = np.full((200, 1), 800 * 1000 / 10**6)
    S_small = np.full((21, 1), 96 * 128 / 3900)
    T_paper, T_small = contribution_sizes(S_paper, default_sigma(800, 1000)), contribution_sizes(S_small, small)
    np.testing.assert_allclose(T_small, T_paper, rtol=0.05)  # (the log costs 4% at 21 views)
    assert 2.5 < T_paper[0] < 3.0  # (about 2 / ln 2 = 2.9)
    with pytest.raises(ValueError, match="num_gaussians"):
        pixel_share_sigma(1000, 0)
    with pytest.raises(ValueError):
        initial_texture_sizes(S[0], 1.0)
    with pytest.raises(ValueError):
        initial_texture_sizes(-S, 1.0)
    with pytest.raises(ValueError):
        initial_texture_sizes(S, 0.0)


# ----------------------------------------------------------------------------------- Eqs. 8-10
def test_eq8_10_hand_computed():
    sch = GrowthSchedule(t0=100, t_final=300, interval=50, tau_preset=1e-5, max_size=32)
    T = np.array([2.0, 2.0, 2.0, 2.0, 2.0, 0.0, 2.0, 32.0])
    g = np.array([9.5e-6, 0.12, 0.95, 1.0, 1e-7, 0.5, 7.0, 0.95])
    active = np.array([1, 1, 1, 1, 1, 1, 0, 1])  # 6: inactive (its huge gradient is ignored)

    # t = t0: tau_high = tau_preset, tau_low = 0.9 tau_preset; only g = 9.5e-6 is in range.
    new, sel, lo, hi = grow_sizes(T, g, 100, sch, active=active)
    assert hi == pytest.approx(1e-5) and lo == pytest.approx(9e-6)
    np.testing.assert_array_equal(sel, [1, 0, 0, 0, 0, 0, 0, 0])
    assert new[0] == pytest.approx(2.0 + np.sqrt(9.5e-6 / 9e-6))

    # t = 200: r = 1/2, tau_high = 1e-5 + (1/8)(1 - 1e-5) (tau_max = 1.0 among active, textured).
    new, sel, lo, hi = grow_sizes(T, g, 200, sch, active=active)
    assert hi == pytest.approx(1e-5 + 0.125 * (1.0 - 1e-5)) and lo == pytest.approx(0.9 * hi)
    np.testing.assert_array_equal(sel, [0, 1, 0, 0, 0, 0, 0, 0])
    assert new[1] == pytest.approx(2.0 + np.sqrt(0.12 / lo))
    np.testing.assert_array_equal(np.delete(new, 1), np.delete(T, 1))

    # t = t_final: (0.9, 1.0); 1.0 itself is excluded (strict), the side-32 Gaussian is at max size,
    # Gaussian 5 has no texture.
    new, sel, lo, hi = grow_sizes(T, g, 300, sch, active=active)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(0.9)
    np.testing.assert_array_equal(sel, [0, 0, 1, 0, 0, 0, 0, 0])
    assert new[2] == pytest.approx(2.0 + np.sqrt(0.95 / 0.9))
    assert side_of(new)[2] == 3

    # (C, 2) gradients use the norm; bad inputs raise.
    g2 = np.stack([g, np.zeros_like(g)], axis=1)
    assert np.array_equal(grow_sizes(T, g2, 300, sch, active=active)[0], new)
    with pytest.raises(ValueError):
        grow_sizes(T, -g, 300, sch)
    with pytest.raises(ValueError):
        grow_sizes(T, g[:3], 300, sch)
    with pytest.raises(ValueError):
        GrowthSchedule(t0=10, t_final=10)


def test_growth_budget_takes_largest_gradients_first():
    sch = GrowthSchedule(t0=0, t_final=100, interval=1)
    T = np.full(5, 2.0)  # 5 x 4 = 20 texels
    g = np.array([0.93, 0.99, 0.95, 0.91, 1.0])  # at t_final range (0.9, 1.0): 0..3 selected
    new_free, sel_free, _, _ = grow_sizes(T, g, 100, sch)
    np.testing.assert_array_equal(sel_free, [1, 1, 1, 1, 0])
    grown = side_of(new_free)**2 - 4
    # Room for exactly the two largest (Gaussians 1 and 2), not for the third.
    budget = 20 + grown[1] + grown[2]
    new, sel, _, _ = grow_sizes(T, g, 100, sch, texel_budget=budget)
    np.testing.assert_array_equal(sel, [0, 1, 1, 0, 0])
    assert total_texels(side_of(new)) == budget
    np.testing.assert_array_equal(new[[0, 3, 4]], T[[0, 3, 4]])
    assert not grow_sizes(T, g, 100, sch, texel_budget=19)[1].any()


def test_schedule_state_steps_and_round_trips():
    sch = GrowthSchedule(t0=10, t_final=50, interval=20)
    state = TextureScheduleState.create(np.array([1, 3, 0, 5]))
    g = np.array([0.95, 0.5, 0.97, 1.0])
    same, sides, sel = state.step(g, 20, sch)  # not a growth step
    assert same is state and not sel.any()
    np.testing.assert_array_equal(sides, [1, 3, 0, 5])
    new, sides, sel = state.step(g, 50, sch)
    np.testing.assert_array_equal(sel, [1, 0, 0, 0])
    assert new.last_growth_step == 50 and new.num_growth_events == 1 and new.num_grown == 1
    assert sides[0] == side_of(1 + np.sqrt(0.95 / 0.9))
    buf = io.BytesIO()
    np.savez(buf, **new.to_dict())
    buf.seek(0)
    with np.load(buf) as f:
        back = TextureScheduleState.from_dict(dict(f))
    assert back == new and back.sizes.dtype == np.float64


# -------------------------------------------------------------------------------------- budgets
def test_mb_to_texels_matches_storage_mb():
    assert mb_to_texels(1.0) == 2**20 // 16
    for mb in (0.5, 3.7, 42.2):
        t = mb_to_texels(mb)
        assert storage_mb(0, 0, t, t) <= mb < storage_mb(0, 0, t + 1, t + 1)
        assert texels_to_mb(t) == storage_mb(0, 0, t, t)
        t3 = mb_to_texels(mb, floats_per_texel=3)
        assert storage_mb(0, 0, t3, 0) <= mb < storage_mb(0, 0, t3 + 1, 0)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_solve_sigma_hits_budget(seed):
    rng = np.random.default_rng(seed)
    J, C = 6, 400  # one shape: the bisection compiles once
    visible = rng.uniform(size=(J, C)) < rng.uniform(0.2, 0.9)
    S = (rng.poisson(rng.lognormal(3.0, 1.5, (1, C)), (J, C)) * visible).astype(float)
    S[:, :5] = 0  # a few Gaussians that are never the top contributor
    sides_lo = initial_texture_sizes(S, 1e9)
    sides_hi = initial_texture_sizes(S, 1e-9)
    lo, hi = total_texels(sides_lo), total_texels(sides_hi)
    target = int(np.exp(rng.uniform(np.log(lo * 1.5), np.log(hi * 0.7))))
    sigma = solve_sigma_for_budget(S, target)
    got = total_texels(initial_texture_sizes(S, sigma))
    assert abs(got - target) <= 0.01 * target, (got, target)
    with pytest.raises(ValueError, match="unreachable"):
        solve_sigma_for_budget(S, hi * 2)
    with pytest.raises(ValueError, match="unreachable"):
        solve_sigma_for_budget(S, lo // 2)


def _sparse_counts(rng, J, C, seen=0.3):
    visible = rng.uniform(size=(J, C)) < seen
    return (rng.poisson(rng.lognormal(3.0, 1.5, (1, C)), (J, C)) * visible).astype(np.float64)


def test_contribution_counts_keep_only_nonzeros_and_match_the_dense_sums():
    rng = np.random.default_rng(0)
    S = _sparse_counts(rng, 7, 500)
    S[:, :9] = 0  # never the top contributor
    sp = ContributionCounts.from_dense(S)
    assert sp.values.size == np.count_nonzero(S) and sp.num_views == 7 and sp.capacity == 500
    streamed = ContributionCounts.from_views((row.astype(np.int32) for row in S), 500)
    for sigma in (0.3, 17.0, 4e3):
        want = np.sum(np.log2(1.0 + S / sigma), axis=0)  # Eq. 7 written out, dense, float64
        np.testing.assert_allclose(sp.sizes(sigma), want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(streamed.sizes(sigma), want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(contribution_sizes(sp, sigma), contribution_sizes(S, sigma), rtol=1e-12)
        np.testing.assert_array_equal(initial_texture_sizes(sp, sigma), initial_texture_sizes(S, sigma))
    np.testing.assert_array_equal(sp.column_max(), S.max(axis=0))
    np.testing.assert_allclose(sp.column_sum(), S.sum(axis=0))
    keep = np.array([3, 10, 11, 400])
    np.testing.assert_allclose(sp.columns(keep).sizes(5.0), np.sum(np.log2(1 + S[:, keep] / 5.0), axis=0))
    S[-2:] = 0  # views where no kept Gaussian (or none at all) contributes
    sub = ContributionCounts.from_dense(S).columns(keep)
    np.testing.assert_array_equal(sub.column_max(), S[:, keep].max(axis=0))
    assert sub.num_views == 7 and sub.offsets[-1] == np.count_nonzero(S[:, keep])
    # Whole counts go through a table of logarithms, the others one by one: the same numbers.
    capped = ContributionCounts.from_dense(np.minimum(S, 50))  # (the largest below the number of counts)
    assert capped._whole_counts is not None
    direct = np.bincount(capped.index, weights=np.log2(1.0 + capped.values.astype(np.float64) / 17.0), minlength=500)
    np.testing.assert_array_equal(capped.sizes(17.0), direct)
    for odd in (S + 0.25, S * 1000.0):  # fractional counts; a largest count past the number of counts
        S_odd = ContributionCounts.from_dense(odd)
        assert S_odd._whole_counts is None
        np.testing.assert_allclose(S_odd.sizes(17.0), np.sum(np.log2(1.0 + odd / 17.0), axis=0), rtol=1e-12)
    with pytest.raises(ValueError, match="non-negative"):
        ContributionCounts.from_views([np.array([1.0, -2.0])])
    with pytest.raises(ValueError, match=r"shape \(C,\)"):
        ContributionCounts.from_views([np.zeros(3), np.zeros(4)])
    with pytest.raises(ValueError, match="num_images, C"):
        ContributionCounts.from_dense(np.zeros(5))


def test_solve_sigma_on_a_sample_then_checked_on_every_gaussian(monkeypatch):
    """A scene larger than the bisection's sample: its sigma still holds the budget on all Gaussians
    (the sample's root is checked on all of them and, where it misses, refined there)."""
    monkeypatch.setattr(adaptive, "SOLVE_SAMPLE", 256)
    rng = np.random.default_rng(5)
    S = _sparse_counts(rng, 6, 6000)
    act = rng.uniform(size=6000) < 0.95
    lo = total_texels(initial_texture_sizes(S, 1e9, active=act))
    hi = total_texels(initial_texture_sizes(S, 1e-9, active=act))
    for target in (int(lo * 1.3), int(np.sqrt(lo * hi)), int(hi * 0.5)):
        sigma = solve_sigma_for_budget(ContributionCounts.from_dense(S), target, active=act)
        got = total_texels(initial_texture_sizes(S, sigma, active=act))
        assert abs(got - target) <= 0.01 * target, (got, target)


def test_solve_sigma_reports_unreachable_tolerance():
    S = np.array([[1000.0, 0.0]])  # one contributing Gaussian: totals 1 + k^2 only
    with pytest.raises(ValueError, match="within"):
        solve_sigma_for_budget(S, 1 + 30, max_size=32)  # between 1 + 25 and 1 + 36


# ----------------------------------------------------------------------------------- add_textures
def test_add_textures_then_update_step():
    C = 6
    scene = random_scene(5, C)  # no textures (stage-1 2DGS)
    opt = make_optimizer(2.0)
    update = jax.jit(opt.update)  # one program per tree layout, not one per operation
    state = opt.init(scene)
    rng = np.random.default_rng(0)

    def random_like(tree):
        return jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape), x.dtype), tree)

    updates, state = update(random_like(scene), state, scene)
    scene = optax.apply_updates(scene, updates)
    mu_old, nu_old = adam_moments(state)

    s2, st2, info = add_textures(scene, state, opt, np.ones(C, int), np.full(C, 5))
    assert info.shapes_changed and info.texels_after == {"rgb": C, "alpha": 25 * C}
    assert s2.rgb.capacities == (8,) and s2.alpha.capacities == (0, 0, 0, 8)
    for i in range(C):
        assert np.all(s2.rgb.texture(i) == 0.0) and np.all(s2.alpha.texture(i) == 1.0)
    mu, nu = adam_moments(st2)
    assert int(st2[0].count) == 1 and int(st2[1].count) == 1
    for leaf in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(np.asarray(getattr(mu, leaf)), np.asarray(getattr(mu_old, leaf)))
        assert np.array_equal(np.asarray(getattr(nu, leaf)), np.asarray(getattr(nu_old, leaf)))
    for bank in (mu.rgb, mu.alpha, nu.rgb, nu.alpha):
        assert all(not np.any(np.asarray(x)) for x in jax.tree_util.tree_leaves(bank))

    grads = random_like(s2)
    updates, st3 = update(grads, st2, s2)
    s3 = optax.apply_updates(s2, updates)
    assert int(st3[0].count) == 2
    assert np.array_equal(np.asarray(s3.alpha.size), np.asarray(s2.alpha.size))  # frozen indices
    assert not np.allclose(s3.rgb.texture(0), 0.0) and not np.allclose(s3.alpha.texture(0), 1.0)
    mu3 = adam_moments(st3)[0]
    np.testing.assert_allclose(np.asarray(mu3.means), 0.9 * np.asarray(mu_old.means)
                               + 0.1 * np.asarray(grads.means), rtol=1e-5, atol=1e-7)

    # The textured state keeps going through a resize.
    s4, st4, _ = resize_textures(s3, st3, np.full(C, 3), None)
    np.testing.assert_allclose(s4.rgb.texture(0), np.broadcast_to(s3.rgb.texture(0), (3, 3, 3)))
    nu3, nu4 = adam_moments(st3)[1].rgb, adam_moments(st4)[1].rgb
    assert np.any(tex_of(nu3, s3.rgb, 0))
    np.testing.assert_allclose(tex_of(nu4, s4.rgb, 0), np.broadcast_to(tex_of(nu3, s3.rgb, 0), (3, 3, 3)))

    # Without an optimizer the new moments are zeros too; without a state only the scene changes.
    s5, st5, _ = add_textures(scene, state, None, None, np.full(C, 5))
    assert s5.rgb is None and not np.any(np.asarray(adam_moments(st5)[0].alpha.buckets[3]))
    assert add_textures(scene, None, None, np.ones(C, int), None)[1] is None


def test_new_texels_have_their_own_bias_correction():
    """A texture that appears late is corrected with its own age (its first update is the nominal
    learning rate, not 3.2x it); a resize carries each texture's age; other groups use the count;
    an optax state from an older checkpoint upgrades to the same structure."""
    from patexgs_jax.optim import AdamState, LearningRates, upgrade_state

    C = 4
    scene = random_scene(6, C)
    opt = make_optimizer(1.0)
    update = jax.jit(opt.update)  # one program per tree layout, not one per operation
    state = opt.init(scene)
    rng = np.random.default_rng(1)

    def random_like(tree):
        return jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape), x.dtype), tree)

    for _ in range(20):  # a 2DGS stage: the global count reaches 20
        updates, state = update(random_like(scene), state, scene)
        scene = optax.apply_updates(scene, updates)
    s2, st2, _ = add_textures(scene, state, opt, np.array([1, 2, 0, 1]), np.array([5, 5, 0, 5]))
    assert int(st2[0].count) == 20
    grads = random_like(s2)
    updates, st3 = update(grads, st2, s2)
    lr = LearningRates()
    for i in (0, 1, 3):
        np.testing.assert_allclose(tex_of(updates.rgb, s2.rgb, i),
                                   -lr.texture_rgb * np.sign(tex_of(grads.rgb, s2.rgb, i)), rtol=1e-5)
        np.testing.assert_allclose(tex_of(updates.alpha, s2.alpha, i),
                                   -lr.texture_alpha * np.sign(tex_of(grads.alpha, s2.alpha, i)), rtol=1e-5)
    age = st3[0].age
    for i in (0, 1, 3):
        assert np.all(tex_of(age.rgb, s2.rgb, i) == 1.0) and np.all(tex_of(age.alpha, s2.alpha, i) == 1.0)
    for leaf in ("means", "log_scales", "quats", "opacity_logits", "sh", "active"):
        assert not np.any(np.asarray(getattr(age, leaf)))  # the count corrects these
    for bank in (age.rgb, age.alpha):
        assert not np.any(np.asarray(bank.bucket)) and not np.any(np.asarray(bank.size))
    # Two more steps, then a resize: grown and shrunk textures keep their age 3, a new one starts at 0.
    s3 = optax.apply_updates(s2, updates)
    for _ in range(2):
        updates, st3 = update(random_like(s3), st3, s3)
        s3 = optax.apply_updates(s3, updates)
    s4, st4, _ = resize_textures(s3, st3, np.array([3, 1, 2, 1]), np.array([2, 5, 3, 5]))
    age4 = st4[0].age
    for i in (0, 1, 3):
        np.testing.assert_allclose(tex_of(age4.rgb, s4.rgb, i), 3.0, rtol=1e-6)
        np.testing.assert_allclose(tex_of(age4.alpha, s4.alpha, i), 3.0, rtol=1e-6)
    assert np.all(tex_of(age4.rgb, s4.rgb, 2) == 0.0) and np.all(tex_of(age4.alpha, s4.alpha, 2) == 0.0)
    # The next step gives every texel of a slot its first texel's age + 1, exactly (a checkpoint
    # stores one age per slot).
    _, st5 = update(random_like(s4), st4, s4)
    for bank, bank4 in ((st5[0].age.rgb, age4.rgb), (st5[0].age.alpha, age4.alpha)):
        for a, a4 in zip(bank.buckets, bank4.buckets):
            a, a4 = np.asarray(a), np.asarray(a4)
            assert np.array_equal(a, np.broadcast_to(a4[:, :1, :1, :1] + np.float32(1.0), a.shape))
    # An optax Adam state (no ages) upgrades with every texel's age at the count.
    adam = st4[0]
    old = (optax.ScaleByAdamState(count=adam.count, mu=adam.mu, nu=adam.nu), st4[1])
    new = upgrade_state(old)
    assert isinstance(new[0], AdamState)
    assert jax.tree_util.tree_structure(new) == jax.tree_util.tree_structure(st4)
    assert np.all(tex_of(new[0].age.rgb, s4.rgb, 2) == 23.0) and not np.any(np.asarray(new[0].age.means))
    assert upgrade_state(st4) is st4
    # A checkpoint stores one age per slot; broadcast back, the state trains exactly as the one saved.
    from patexgs_jax.optim import ages_per_slot

    stored = ages_per_slot(st5)
    assert all(np.shape(a)[1:] == (1, 1, 1) for a in stored[0].age.rgb.buckets + stored[0].age.alpha.buckets)
    back = upgrade_state(stored)
    assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(st5)
    assert all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
               zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(st5)))
