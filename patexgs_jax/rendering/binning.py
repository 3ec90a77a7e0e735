"""Binning: each splat's screen box to a range of tiles, and the (splat, tile) pairs sorted into
depth-ordered per-tile lists with one stable sort of 32-bit tile keys (pairs are generated in depth
order, so a stable sort by tile keeps each tile's list front to back)."""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax


def tile_ranges(bounds, visible, tile_size, tiles_x, tiles_y):
    """The tiles each splat's screen box ``bounds`` (xmin, xmax, ymin, ymax, each (C,), pixels)
    overlaps: (tx0, tx1, ty0, ty1, ok), each (C,), the half-open ranges [tx0, tx1) x [ty0, ty1) of
    tile columns and rows (int32) whose pixel centres the box may reach, and ok, ``visible`` with a
    non-empty range."""
    xmin, xmax, ymin, ymax = bounds

    def rng(lo, hi, n):
        lo = jnp.floor(jnp.clip((lo - 0.5) / tile_size, -1.0, n + 1.0))
        hi = jnp.floor(jnp.clip((hi - 0.5) / tile_size, -1.0, n + 1.0)) + 1
        lo = jnp.where(jnp.isnan(lo), 0.0, lo)
        hi = jnp.where(jnp.isnan(hi), float(n), hi)
        return jnp.clip(lo, 0, n).astype(jnp.int32), jnp.clip(hi, 0, n).astype(jnp.int32)

    tx0, tx1 = rng(xmin, xmax, tiles_x)
    ty0, ty1 = rng(ymin, ymax, tiles_y)
    ok = visible & (tx1 > tx0) & (ty1 > ty0)
    return tx0, tx1, ty0, ty1, ok


def tile_histogram(tx0, tx1, ty0, ty1, ok, tiles_x, tiles_y):
    """Exact number of splats per tile, by a 2D difference array: O(C + tiles)."""
    one = ok.astype(jnp.int32)
    diff = jnp.zeros((tiles_y + 1, tiles_x + 1), jnp.int32)
    diff = diff.at[ty0, tx0].add(one).at[ty0, tx1].add(-one)
    diff = diff.at[ty1, tx0].add(-one).at[ty1, tx1].add(one)
    return jnp.cumsum(jnp.cumsum(diff, axis=0), axis=1)[:tiles_y, :tiles_x].reshape(-1)


def bin_pairs(depth, tx0, tx1, ty0, ty1, ok, tiles_x, num_tiles, pair_capacity):
    """Depth-ordered per-tile lists.

    Returns (sorted_ids (P,), tile_start (T,), tile_count_binned (T,)): the splat ids of pairs
    sorted by tile, each tile's run in front-to-back order.
    """
    C = depth.shape[0]
    counts = jnp.where(ok, (tx1 - tx0) * (ty1 - ty0), 0)
    key = jnp.where(ok, depth, jnp.inf)
    order = jnp.argsort(key, stable=True).astype(jnp.int32)
    counts_s = counts[order]
    ends = jnp.cumsum(counts_s)
    starts = ends - counts_s
    total = ends[-1]
    p = jnp.arange(pair_capacity, dtype=jnp.int32)
    mark = jnp.full((pair_capacity,), -1, jnp.int32)
    mark = mark.at[jnp.where(counts_s > 0, starts, pair_capacity)].max(
        jnp.arange(C, dtype=jnp.int32), mode="drop")
    rank = jnp.maximum(lax.cummax(mark), 0)
    g = order[rank]
    k = p - starts[rank]
    w = jnp.maximum(tx1[g] - tx0[g], 1)
    tile = (ty0[g] + k // w) * tiles_x + tx0[g] + k % w
    valid = (p < total) & (k >= 0)
    tile = jnp.where(valid, tile, num_tiles)
    tile_sorted, ids_sorted = lax.sort((tile, g), num_keys=1, is_stable=True)
    binned = jnp.zeros((num_tiles + 1,), jnp.int32).at[tile].add(1)[:num_tiles]
    tile_start = jnp.cumsum(binned) - binned
    return ids_sorted, tile_start, binned


def pair_count(tx0, tx1, ty0, ty1, ok):
    """() float32: the (splat, tile) pairs of the ranges of :func:`tile_ranges`."""
    return jnp.sum(jnp.where(ok, (tx1 - tx0) * (ty1 - ty0), 0).astype(jnp.float32))
