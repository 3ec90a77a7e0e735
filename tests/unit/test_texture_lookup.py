"""Texture lookups: the mip pyramid and its transpose, the mip level's effect (invariance under a
constant texture, level 0 under magnification), and the bookkeeping of the lookups done in passes
over the pairs that can contribute. Minification against a supersampled truth, and the passes'
images and gradients against looking up every pair, are in tests/integration/test_render_sweeps.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import Capacity, RenderConfig
from patexgs_jax.rendering import texture_lookup
from render_cases import (
    camera,
    single_splat_scene,
    tile_render,
)

# ---------------------------------------------------------------------------------------------
# Mipmap properties
# ---------------------------------------------------------------------------------------------


def test_pyramid_levels_and_their_transpose_match_numpy():
    """Each bucket's levels are ``D X D^T`` of the level above (the first with each slot's own
    filter for its size), and the backward is the transpose ``D^T G D``: checked in float64 against
    numpy, for the unrolled filters and the einsum (the first level of a 32-texel slot)."""
    from patexgs_jax.textures import atlas as tx

    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        for b in (1, 3, 5):  # slots of 2 and 8 (unrolled), 32 (an einsum to level 1, unrolled below)
            P = 1 << b
            sizes = np.arange(P // 2 + 1, P + 1)
            X = np.zeros((sizes.size, P, P, 2))
            for k, n in enumerate(sizes):
                X[k, :n, :n] = rng.normal(size=(n, n, 2))
            levels, vjp = jax.vjp(jax.jit(lambda x, sizes=sizes, b=b: tx._pyramid(x, jnp.asarray(sizes), b)),
                                  jnp.asarray(X))
            G = [rng.normal(size=lev.shape) for lev in levels]
            want_levels, want_grad = [X], G[-1]
            Ds = []
            for k in range(1, b + 1):
                if k == 1:  # the level-1 filters are tabulated in float32, zero past each size
                    D = tx._first_level_table(P)[sizes - (P // 2 + 1)].astype(np.float64)
                    np.testing.assert_allclose(D[-1], tx.downsample_matrix(P, P // 2), rtol=1e-6)
                else:
                    D = np.stack([tx.downsample_matrix(P >> (k - 1), P >> k)] * sizes.size)
                Ds.append(D)
                want_levels.append(np.einsum("kip,kpqc,kjq->kijc", Ds[-1], want_levels[-1], Ds[-1]))
            for k in range(b, 0, -1):  # the transpose, coarsest level first
                want_grad = G[k - 1] + np.einsum("kip,kijc,kjq->kpqc", Ds[k - 1], want_grad, Ds[k - 1])
            for got, want in zip(levels, want_levels):
                np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-12)
            np.testing.assert_allclose(np.asarray(vjp([jnp.asarray(g) for g in G])[0]), want_grad,
                                       rtol=0, atol=1e-12)


def test_level_addresses_are_the_pyramid_layout():
    """Level l of a block of bucket side P starts at sum_{k<l} (P >> k)^2 = (4/3)(P^2 - (P >> l)^2),
    with row stride and side P >> l (level 0: stride P, side the texture's own n), for every
    bucket side up to 4096 and level, under jit as the renderer computes it."""
    from patexgs_jax import textures as tx

    sides, levels, want = [], [], []
    for b in range(13):
        for lev in range(b + 1):
            sides.append(1 << b)
            levels.append(lev)
            want.append(sum(((1 << b) >> k) ** 2 for k in range(lev)))
    P, L = jnp.asarray(sides, jnp.int32), jnp.asarray(levels, jnp.int32)
    n = jnp.maximum(P - 1, 1)
    off, stride, side = jax.jit(tx.level_address)(P, n, L)
    np.testing.assert_array_equal(np.asarray(off), want)
    np.testing.assert_array_equal(np.asarray(stride), np.where(L == 0, P, P >> L))
    np.testing.assert_array_equal(np.asarray(side), np.where(L == 0, n, P >> L))


def test_constant_texture_is_mip_invariant():
    rgb = np.full((9, 9, 3), 0.25)
    alpha = np.full((6, 6), 0.8)
    sc = single_splat_scene(rgb, alpha)
    cam = camera(eye=(0.0, 0.0, -12.0), f=30.0)  # strong minification: high levels are chosen
    base = tile_render(sc, cam, RenderConfig(mip="none"), capacity=Capacity(1024))
    for cfg in (RenderConfig(mip="nearest"), RenderConfig(mip="trilinear")):
        out = tile_render(sc, cam, cfg, capacity=Capacity(1024))
        np.testing.assert_allclose(out.rgb, base.rgb, atol=2e-6)
        np.testing.assert_allclose(out.alpha, base.alpha, atol=2e-6)


def test_magnification_picks_level_zero():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(-0.5, 0.5, (8, 8, 3))
    alpha = rng.uniform(0.2, 1.0, (8, 8))
    sc = single_splat_scene(rgb, alpha, scale=0.5)
    cam = camera(eye=(0.0, 0.0, -2.0), f=80.0)  # ~20 px per unit of scale: D ~ 0.05, 0.4*8*D < 1
    base = tile_render(sc, cam, RenderConfig(mip="none"), capacity=Capacity(1024))
    out = tile_render(sc, cam, RenderConfig(mip="nearest"), capacity=Capacity(1024))
    # Same texels, same level: equal up to float32 rounding of a different fusion of the lookups.
    np.testing.assert_allclose(out.rgb, base.rgb, atol=1e-6, rtol=0)
    np.testing.assert_allclose(out.alpha, base.alpha, atol=1e-6, rtol=0)
    assert base.alpha.max() > 0.5


# ---------------------------------------------------------------------------------------------
# Texture lookups only where a pair can contribute, in passes
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("c", [32, 7, 45])
def test_pass_pairs_list_the_marked_pairs_in_order(c):
    """The passes' pairs, read in order, are exactly the marked slots of the block in row-major order,
    then the "none" index: for a chunk of 32 slots (one word per row), fewer (a partial word) and
    more (two words, the second partial), with passes that end inside a row."""
    rng = np.random.default_rng(c)
    B, P = 3, 20
    take = rng.random((B, P, c)) < 0.2
    take[1, 5] = True  # a full row
    take[2] = False    # a tile with no marks
    N = take.size
    K = 13
    passes = texture_lookup._mark_passes(jnp.asarray(take), K)
    want = np.flatnonzero(take.reshape(-1))
    assert int(passes.count) == want.size
    got = []
    j = 0
    while bool(texture_lookup._more_passes(passes, j)):
        got.append(np.asarray(texture_lookup._pass_pairs(passes, j)))
        j += 1
    assert j == -(-want.size // K)
    got = np.concatenate(got)
    np.testing.assert_array_equal(got[:want.size], want)
    assert np.all(got[want.size:] == N)


@pytest.mark.parametrize("shape, share", [((1, 4096, 4095), 1.0), ((1, 4096, 4096), 0.3)])
def test_pass_running_counts_are_exact(shape, share):
    """The rows' running counts of marks are exact integers: by float32 matmuls while the block has
    fewer than 2**24 slots (here every slot marked, the last count 16,773,120, just below), by an
    integer cumsum from 2**24 slots on."""
    rng = np.random.default_rng(shape[-1])
    take = rng.random(shape) < share
    passes = texture_lookup._mark_passes(jnp.asarray(take), 64)
    nw = -(-shape[-1] // 32)
    padded = np.zeros(shape[:-1] + (nw * 32,), bool)
    padded[..., :shape[-1]] = take
    want = np.cumsum(padded.reshape(-1, 32).sum(axis=1))
    np.testing.assert_array_equal(np.asarray(passes.ends), want)
    assert int(passes.count) == int(take.sum())


@pytest.mark.parametrize("K", [1, 5, 64, 1000])
def test_rows_of_ranks_match_searchsorted(K):
    """The rows of a pass's consecutive ranks, from a histogram and running sums, equal
    ``np.searchsorted(ends, rank, side="right")``: for running counts with empty rows (repeated
    ends), passes starting before the first end, inside a row, and past the last end."""
    rng = np.random.default_rng(K)
    counts = rng.integers(0, 4, 300) * (rng.random(300) < 0.6)
    ends = np.cumsum(counts).astype(np.int32)
    for start in [0, 1, int(ends[40]), int(ends[-1]) - K // 2, int(ends[-1]) + 3]:
        got = np.asarray(texture_lookup._rows_of_ranks(jnp.asarray(ends), jnp.int32(start), K))
        want = np.searchsorted(ends, start + np.arange(K), side="right")
        np.testing.assert_array_equal(got, want, err_msg=f"start {start}")
