"""The re-bucketing on the device (:mod:`patexgs_jax.textures.rebucket_device`), in a kept layout and
in one made afresh, against the host path that makes every bucket on the host
(:func:`patexgs_jax.textures.rebucket._apply_plan`), bit for bit, on random banks with random Adam
moments and ages."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from patexgs_jax import random_scene
from patexgs_jax.optim import make_optimizer
from patexgs_jax.scene import Scene
from patexgs_jax.textures import rebucket as rb
from patexgs_jax.textures import rebucket_device as rd

BANKS = ("rgb", "alpha")


def _trees(scene, state):
    return [scene] + [m for m in jax.tree_util.tree_leaves(state, is_leaf=lambda x: isinstance(x, Scene))
                      if isinstance(m, Scene)]


def _random_state(seed: int, C: int):
    """A scene with RGB and alpha textures in buckets with room (as the schedule's headroom gives),
    its Adam state, random values in every used slot (padding included) of every tree."""
    rng = np.random.default_rng(seed)
    sides = rng.choice([0, 1, 1, 1, 2, 3, 4, 5, 8, 9], size=C)
    scene = random_scene(seed, C)
    opt = make_optimizer(1.0)
    alpha = np.where(sides > 0, np.maximum(sides - 1, 1), 0)
    scene, state, _ = rb.add_textures(scene, opt.init(scene), opt, sides, alpha, headroom=1.0, min_spare=4)

    def noise(tree, positive):
        kw = {}
        for name in BANKS:
            bank, index = getattr(tree, name), getattr(scene, name)
            b_of, s_of = np.asarray(index.bucket).astype(int), np.asarray(index.slot).astype(int)
            new = []
            for b, x in enumerate(bank.buckets):
                v = np.zeros(x.shape, np.float32)
                used = s_of[b_of == b]
                shape = (used.size,) + x.shape[1:]
                v[used] = rng.uniform(0.1, 2.0, shape) if positive else rng.normal(size=shape)
                new.append(jax.device_put(v))
            kw[name] = dataclasses.replace(bank, buckets=tuple(new))
        return tree.replace(**kw)

    adam, group = state
    state = (adam._replace(mu=noise(adam.mu, False), nu=noise(adam.nu, True), age=noise(adam.age, True)), group)
    return noise(scene, False), state, rng


@pytest.mark.parametrize("donate", [False, True])
@pytest.mark.parametrize("chunk", [rd.CHUNK_TEXELS, 8])
def test_kept_layout_path_equals_the_host_path(monkeypatch, donate, chunk):
    """Grown, shrunk, appearing and vanishing textures within the headroom: every bucket of the
    parameters and of each moment tree equals the host path's, and slots of unchanged textures keep
    their whole block (garbage in the padding included); small chunks split the writes over calls."""
    monkeypatch.setattr(rd, "CHUNK_TEXELS", chunk)
    monkeypatch.setattr(rb, "DEVICE_MAX_SHARE", 1.0)  # (every resize below on the device)
    scene, state, rng = _random_state(3, 48)
    kept = 0
    for _ in range(4):
        new = {}
        for name in BANKS:
            cur = np.asarray(getattr(scene, name).size).astype(int)
            step = rng.choice([-1, 1, 1, 2], size=cur.size) * (rng.random(cur.size) < 0.15)
            appear = rng.choice([1, 3], size=cur.size) * (rng.random(cur.size) < 0.1)
            new[name] = np.clip(np.where(cur > 0, cur + step, appear), 0, 9)
        plans = {name: rb._plan(getattr(scene, name), new[name], 1, 1.0, 4) for name in BANKS}
        if not all(rb._layout_kept(plans[n], getattr(scene, n).buckets) for n in BANKS):
            continue  # (an overflow: the host path itself; not what this test is about)
        expect = []
        for i, tree in enumerate(_trees(scene, state)):
            fresh = {"rgb": rb.RGB_NEUTRAL, "alpha": rb.ALPHA_NEUTRAL} if i == 0 else {"rgb": 0.0, "alpha": 0.0}
            expect.append({n: rb._apply_plan(plans[n], [np.asarray(b) for b in getattr(tree, n).buckets], fresh[n])
                           for n in BANKS})
        scene, state, info = rb.resize_textures(scene, state, new["rgb"], new["alpha"], headroom=1.0, min_spare=4,
                                                donate=donate)
        assert not info.shapes_changed and info.num_changed > 0
        kept += 1
        for tree, want in zip(_trees(scene, state), expect):
            for n in BANKS:
                got = [np.asarray(b) for b in getattr(tree, n).buckets]
                assert len(got) == len(want[n])
                for g, w in zip(got, want[n]):
                    assert g.dtype == w.dtype and np.array_equal(g.view(np.uint32), w.view(np.uint32))
        for n in BANKS:
            assert np.array_equal(np.asarray(getattr(scene, n).size).astype(int), new[n])
    assert kept >= 2


def test_donated_buckets_are_reused_and_shared_ones_are_not_donated():
    scene, state, _ = _random_state(5, 16)
    sides = np.asarray(scene.rgb.size).astype(int)
    grown = sides.copy()
    grown[np.flatnonzero(sides == 1)[:2]] = 2
    old = scene.rgb.buckets
    s1, st1, info = rb.resize_textures(scene, state, grown, None, headroom=1.0, min_spare=4, donate=True)
    assert not info.shapes_changed
    assert all(b.is_deleted() for b in old if b.shape[0] > 0)
    # A tree whose buckets share a buffer with another's: nothing is donated.
    shared = (st1[0]._replace(nu=st1[0].mu), st1[1])
    again = grown.copy()
    again[np.flatnonzero(grown == 1)[:2]] = 2
    s2, _, info = rb.resize_textures(s1, shared, again, None, headroom=1.0, min_spare=4, donate=True)
    assert not info.shapes_changed
    assert not any(b.is_deleted() for b in s1.rgb.buckets)
    assert rd.can_donate(s2.rgb.buckets)


def test_prepared_programs_are_the_ones_used(monkeypatch):
    """prepare_growth compiles a layout's read and write programs ahead; the next growth event uses
    them (nothing compiled at the event) and writes what the host path writes."""
    scene, state, _ = _random_state(7, 32)
    rb.prepare_growth(scene)
    used = []
    program = rd._program
    monkeypatch.setattr(rd, "_program", lambda kind, donate, buckets: used.append(
        type(p := program(kind, donate, buckets)).__name__) or p)
    sides = np.asarray(scene.rgb.size).astype(int)
    grown = sides.copy()
    grown[np.flatnonzero(sides == 1)[:2]] = 2
    plan = rb._plan(scene.rgb, grown, 1, 1.0, 4)
    want = rb._apply_plan(plan, [np.asarray(b) for b in scene.rgb.buckets], rb.RGB_NEUTRAL)
    new, _, info = rb.resize_textures(scene, state, grown, None, headroom=1.0, min_spare=4, donate=True)
    assert not info.shapes_changed and used and set(used) == {"Compiled"}
    assert all(np.array_equal(np.asarray(g), w) for g, w in zip(new.rgb.buckets, want))
    _assert_uncommitted(scene.rgb.buckets, new)


def _assert_uncommitted(before, *trees):
    """A single-device run's arrays are uncommitted, and the training step's jit compiles again when
    some of its inputs are committed: what programs compiled ahead write comes back uncommitted."""
    assert not any(b.committed for b in before)
    committed = [x.shape for x in jax.tree_util.tree_leaves(trees) if isinstance(x, jax.Array) and x.committed]
    assert not committed, committed


def test_an_overflowing_event_runs_programs_compiled_ahead(monkeypatch):
    """prepare_growth also compiles, for every bucket, what an event that overflows it runs for it
    (the bucket made anew at the capacity it overflows to, its writes there); such an event keeps
    the other buckets' capacities, compiles nothing, and writes what the host path writes."""
    monkeypatch.setattr(rb, "DEVICE_MAX_SHARE", 1.0)  # (a few textures of 64 are over 5%)
    scene, state, _ = _random_state(17, 64)
    rb.prepare_growth(scene, headroom=1.0, min_spare=4)
    for fut in list(rd._ahead.values()):
        fut.result()
    used = []
    program, relayout_program = rd._program, rd._relayout_program
    monkeypatch.setattr(rd, "_program", lambda kind, donate, buckets: used.append(
        type(p := program(kind, donate, buckets)).__name__) or p)
    monkeypatch.setattr(rd, "_relayout_program", lambda *a: used.append(
        type(p := relayout_program(*a)).__name__) or p)
    sides = np.asarray(scene.rgb.size).astype(int)
    caps, counts = scene.rgb.capacities, np.bincount([(int(n) - 1).bit_length() for n in sides if n > 0])
    counts = np.concatenate([counts, np.zeros(len(caps) - counts.size, int)])
    # The bucket that the fewest textures grown by one texel from the bucket below overflow.
    b, need = min(((b, caps[b] - counts[b] + 1) for b in range(1, len(caps))
                   if caps[b] and np.count_nonzero(sides == 1 << (b - 1)) >= caps[b] - counts[b] + 1),
                  key=lambda x: x[1])
    grown = sides.copy()
    grown[np.flatnonzero(sides == 1 << (b - 1))[:need]] += 1
    host_scene, host_state, host_info = rb.resize_textures(_copy(scene), _copy(state), grown, None, headroom=1.0,
                                                           min_spare=4, on_device=False)
    new, new_state, info = rb.resize_textures(scene, state, grown, None, headroom=1.0, min_spare=4, donate=True)
    assert info == host_info and info.shapes_changed
    changed = [i for i, (x, y) in enumerate(zip(caps, new.rgb.capacities)) if x != y]
    assert changed == [b] and new.rgb.capacities[b] > caps[b]
    assert used and set(used) == {"Compiled"}, used
    _assert_uncommitted(host_scene.rgb.buckets, new, new_state)
    _assert_trees_equal((new, new_state), (host_scene, host_state))


def _copy(tree):
    return jax.tree_util.tree_map(lambda x: jax.device_put(np.array(x)) if isinstance(x, jax.Array) else x, tree)


def _assert_trees_equal(a, b):
    la, da = jax.tree_util.tree_flatten(a)
    lb, db = jax.tree_util.tree_flatten(b)
    assert da == db
    for x, y in zip(la, lb):
        x, y = np.atleast_1d(np.asarray(x)), np.atleast_1d(np.asarray(y))
        assert x.shape == y.shape and x.dtype == y.dtype
        assert np.array_equal(x.view(np.uint8), y.view(np.uint8))


@pytest.mark.parametrize("donate", [False, True])
@pytest.mark.parametrize("chunk", [rd.CHUNK_TEXELS, 8])
def test_new_layout_on_the_device_equals_the_host_path(monkeypatch, donate, chunk):
    """Events that overflow a bucket (every bucket sized afresh: grown, shrunk, new buckets, textures
    past a shrunk capacity moved): the device path's scene and optimiser state (parameters, moments,
    ages, index leaves) equal the host path's bit for bit, event after event."""
    monkeypatch.setattr(rd, "CHUNK_TEXELS", chunk)
    monkeypatch.setattr(rb, "DEVICE_MAX_SHARE", 1.0)  # (every resize below on the device)
    scene, state, rng = _random_state(11, 64)
    host_scene, host_state = _copy(scene), _copy(state)
    overflowed = shrunk = moved = 0
    for event in range(6):
        new = {}
        for name in BANKS:
            cur = np.asarray(getattr(scene, name).size).astype(int)
            # Many grow (buckets overflow; the largest side appears: a new bucket) while many shrink or
            # vanish (the layout made afresh shrinks their buckets; textures past the capacity move).
            u = rng.random(cur.size)
            step = np.where(u < 0.3, rng.choice([1, 2, 4, 8], size=cur.size),
                            np.where(u < 0.6 + 0.1 * (event % 2), -rng.choice([1, 3, 20], size=cur.size), 0))
            new[name] = np.clip(np.where(cur > 0, cur + step, rng.choice([0, 2], size=cur.size)), 0, 17)
        plans = {n: rb._plan(getattr(scene, n), new[n], 1, 0.25, 2) for n in BANKS}
        for n in BANKS:
            caps0 = getattr(scene, n).capacities
            shrunk += any(c < o for c, o in zip(plans[n].capacities, caps0))
            moved += sum(len(s) for s, _ in rb._moves(plans[n]).copies.values())
        host_scene, host_state, host_info = rb.resize_textures(host_scene, host_state, new["rgb"], new["alpha"],
                                                               headroom=0.25, min_spare=2, on_device=False)
        scene, state, info = rb.resize_textures(scene, state, new["rgb"], new["alpha"], headroom=0.25,
                                                min_spare=2, donate=donate)
        assert info == host_info
        overflowed += info.shapes_changed
        _assert_trees_equal((scene, state), (host_scene, host_state))
    assert overflowed >= 3 and shrunk >= 1 and moved >= 1


def test_resizes_that_change_most_textures_are_made_on_the_host(monkeypatch):
    """Above DEVICE_MAX_SHARE of a bank's textures changing in a new layout (the Eq. 7 allocation), the
    buckets are made on the host (no device reads or writes); the result is the same either way."""
    scene, state, _ = _random_state(13, 32)
    sides = np.asarray(scene.rgb.size).astype(int)
    most = np.where(sides > 0, 2 * sides + 1, 0)  # (a new bucket: the layout is made afresh)
    calls = []
    monkeypatch.setattr(rd, "write_slots", lambda *a, **k: calls.append(1))
    want, _, _ = rb.resize_textures(_copy(scene), _copy(state), most, None, on_device=False)
    got, _, _ = rb.resize_textures(scene, state, most, None)
    assert not calls
    _assert_trees_equal(got, want)
