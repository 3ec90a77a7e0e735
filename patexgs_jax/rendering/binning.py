"""Binning: each splat's screen box to a range of tiles, and the (splat, tile) pairs sorted into
depth-ordered per-tile lists with one stable sort of 32-bit tile keys (pairs are generated in depth
order, so a stable sort by tile keeps each tile's list front to back). Pairs of a box's tiles that
the splat cannot reach alpha 1/255 in are left out (:func:`tile_touches`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from .billboard import square_touches
from .projection import FOOTPRINT

#: tile_touches tests each tile grown by this many pixels a side, and accepts quadratic forms down
#: to -TOUCH_EPS (their terms normalised to 1): margins for float32 rounding, so that a pixel the
#: compositor keeps is never in a tile left out.
TOUCH_GROW = 1.0
TOUCH_EPS = 1e-4


def tile_ranges(bounds, visible, tile_size, tiles_x, tiles_y, limit=None):
    """The tiles each splat's screen box ``bounds`` (xmin, xmax, ymin, ymax, each (C,), pixels)
    overlaps: (tx0, tx1, ty0, ty1, ok), each (C,), the half-open ranges [tx0, tx1) x [ty0, ty1) of
    tile columns and rows (int32) whose pixel centres the box may reach, and ok, ``visible`` with a
    non-empty range. ``limit``: None, or (columns, rows) of tiles (() int32 each, may be traced, at
    most tiles_x and tiles_y) that exist: the ranges are cut to them, so that a view rendered on a
    larger padded grid bins the splats of its own tiles only."""
    xmin, xmax, ymin, ymax = bounds
    lim_x, lim_y = (tiles_x, tiles_y) if limit is None else limit

    def rng(lo, hi, n, lim):
        lo = jnp.floor(jnp.clip((lo - 0.5) / tile_size, -1.0, n + 1.0))
        hi = jnp.floor(jnp.clip((hi - 0.5) / tile_size, -1.0, n + 1.0)) + 1
        lo = jnp.where(jnp.isnan(lo), 0.0, lo)
        hi = jnp.where(jnp.isnan(hi), float(n), hi)
        return jnp.clip(lo, 0, lim).astype(jnp.int32), jnp.clip(hi, 0, lim).astype(jnp.int32)

    tx0, tx1 = rng(xmin, xmax, tiles_x, lim_x)
    ty0, ty1 = rng(ymin, ymax, tiles_y, lim_y)
    ok = visible & (tx1 > tx0) & (ty1 > ty0)
    return tx0, tx1, ty0, ty1, ok


def tile_histogram(tx0, tx1, ty0, ty1, ok, tiles_x, tiles_y):
    """Exact number of splats per tile, by a 2D difference array: O(C + tiles)."""
    one = ok.astype(jnp.int32)
    diff = jnp.zeros((tiles_y + 1, tiles_x + 1), jnp.int32)
    diff = diff.at[ty0, tx0].add(one).at[ty0, tx1].add(-one)
    diff = diff.at[ty1, tx0].add(-one).at[ty1, tx1].add(one)
    return jnp.cumsum(jnp.cumsum(diff, axis=0), axis=1)[:tiles_y, :tiles_x].reshape(-1)


def tile_touches(fp, tx, ty, tile_size: int, lowpass: bool):
    """Whether the splats of footprint rows ``fp`` (one per pair, a list of :data:`FOOTPRINT`'s 16
    columns, each (N,)) can reach alpha 1/255 at a pixel centre of tile (tx, ty) (each (N,) int32):
    False only where none can (up to the margins :data:`TOUCH_GROW`, :data:`TOUCH_EPS`).

    The ray through pixel (x, y) meets the plane at the homogeneous point s = x A + y B + C (u =
    s0 / s2, v = s1 / s2), in front of the camera where ``side * s2 > 0``, and inside the region
    ``h^T P h <= r2`` where ``Phi(s) = r2 s2^2 - s01^T P s01 >= 0``: the region's rays form one nappe
    of a quadratic cone in s, which is convex, and the tile's rays the convex cone spanned by the
    rays of its four corners. They meet iff a corner's ray is in the nappe, or the nappe's axis (the
    splat's centre, always in front) falls in the tile, or a side of the tile (the cone over a
    segment between corners) crosses the nappe: where the segment is in front, the maximum of Phi, a
    quadratic along it, is at its ends or its vertex. An unbounded footprint (the region crosses the
    plane of the camera centre parallel to the image) is bounded here by its front half.
    Without the prefilter (``lowpass``), the low-pass disc ``2 |d|^2 <= r2`` counts too. The
    prefilter's screen support is not tested (the box of :func:`projection.project` has it).
    """
    F = FOOTPRINT
    A, B, C = fp[F.a], fp[F.b], fp[F.c]
    p, r, t = fp[F.conic]
    r2, side = fp[F.r2], fp[F.side]
    mx, my = fp[F.mu]
    dt = r2.dtype
    x0 = (tx * tile_size).astype(dt) + (0.5 - TOUCH_GROW)
    y0 = (ty * tile_size).astype(dt) + (0.5 - TOUCH_GROW)
    x1 = x0 + (tile_size - 1 + 2 * TOUCH_GROW)
    y1 = y0 + (tile_size - 1 + 2 * TOUCH_GROW)
    inside = (mx >= x0) & (mx <= x1) & (my >= y0) & (my <= y1)

    def corner(x, y):  # s at a corner, scaled to unit norm under r2 s2^2 + s01^T P s01 (a positive scale)
        s = [x * A[i] + y * B[i] + C[i] for i in range(3)]
        n = r2 * s[2] * s[2] + (p * s[0] + 2.0 * r * s[1]) * s[0] + t * s[1] * s[1]
        k = lax.rsqrt(n + 1e-20)
        return [si * k for si in s]

    def phi(a, b):  # the bilinear form of Phi
        return r2 * a[2] * b[2] - (p * a[0] * b[0] + r * (a[0] * b[1] + a[1] * b[0]) + t * a[1] * b[1])

    s = [corner(x0, y0), corner(x1, y0), corner(x1, y1), corner(x0, y1)]
    front = [side * q[2] for q in s]
    pp = [phi(q, q) for q in s]
    hit = inside
    for k in range(4):
        hit = hit | ((front[k] > 0) & (pp[k] >= -TOUCH_EPS))
    for k in range(4):  # the side from corner k (alpha = 1) to corner j (alpha = 0)
        j = (k + 1) % 4
        pij = phi(s[k], s[j])
        c2 = pp[k] - 2.0 * pij + pp[j]
        c1 = 2.0 * (pij - pp[j])
        fk, fj = front[k], front[j]
        d = fj - fk
        cross = jnp.clip(fj / jnp.where(d == 0, 1.0, d), 0.0, 1.0)  # where the front changes sign
        lo = jnp.where(fj >= 0, 0.0, cross)
        hi = jnp.where(fk >= 0, 1.0, cross)
        vertex = jnp.clip(-c1 / jnp.where(c2 == 0, 1.0, 2.0 * c2), lo, hi)
        some = (fk >= 0) | (fj >= 0)
        for a in (lo, hi, vertex):
            hit = hit | (some & ((c2 * a + c1) * a + pp[j] >= -TOUCH_EPS))
    if lowpass:
        dx = jnp.clip(mx, x0, x1) - mx
        dy = jnp.clip(my, y0, y1) - my
        hit = hit | (2.0 * (dx * dx + dy * dy) <= r2)
    return hit | (side == 0)


#: bin_pairs tests the pairs' tiles in this many blocks of slots and skips the blocks past the box
#: pairs: a capacity is a power of two, with headroom in the viewer (twice a view's pairs), so that
#: many of its slots are empty. Neither the cull's blocks nor the sort's prefixes (below) go under
#: _MIN_BLOCK slots (a smaller capacity is tested and sorted whole).
_CULL_BLOCKS = 16
_MIN_BLOCK = 4096


def _touches_in_blocks(footprint, g, tx, ty, total, tile_size: int, lowpass: bool, billboard: bool = False):
    """:func:`tile_touches` (with ``billboard``, :func:`billboard.square_touches`) of the slots'
    splats ``g`` and tiles (tx, ty) (each (N,)), computed only for the blocks of slots that hold a
    pair (slot < ``total``); False in the others."""
    N = g.shape[0]

    def block(args):
        gb, txb, tyb = args
        rows = footprint[gb]
        fp = [rows[:, i] for i in range(FOOTPRINT.width)]
        if billboard:
            F = FOOTPRINT
            return square_touches(fp[F.a], fp[F.b], fp[F.c], fp[F.side], txb, tyb, tile_size, TOUCH_GROW)
        return tile_touches(fp, txb, tyb, tile_size, lowpass)

    if N % _CULL_BLOCKS or N // _CULL_BLOCKS < _MIN_BLOCK:
        return block((g, tx, ty))
    n = N // _CULL_BLOCKS

    def one(args):
        i, rest = args
        return lax.cond(i * n < total, block, lambda a: jnp.zeros(a[0].shape, bool), rest)

    blocks = jax.tree.map(lambda a: a.reshape(_CULL_BLOCKS, n), (g, tx, ty))
    return lax.map(one, (jnp.arange(_CULL_BLOCKS), blocks)).reshape(N)


#: bin_pairs sorts the shortest prefix of the slots, of 1/2**k of them (k < this), that holds every
#: box pair: pairs fill the slots from the first, and the tiles' lists read only the kept pairs.
_SORT_PREFIXES = 4


def _sort_prefix(tile, g, total):
    """The splat ids ``g`` (N,) stably sorted by ``tile`` (N,), where only the first ``total`` slots
    can hold pairs (the others have the largest key): only the shortest prefix of N / 2**k slots
    that holds them is sorted (a branch per prefix length); the output's other slots are 0."""
    N = g.shape[0]
    sizes = [N] + [N >> k for k in range(1, _SORT_PREFIXES) if (N >> k) >= _MIN_BLOCK and (N >> k) << k == N]

    def branch(n):
        def run(args):
            t, ids = args
            out = lax.sort((t[:n], ids[:n]), num_keys=1, is_stable=True)[1]
            return out if n == N else jnp.concatenate([out, jnp.zeros((N - n,), out.dtype)])
        return run

    if len(sizes) == 1:
        return branch(N)((tile, g))
    index = jnp.sum(jnp.asarray(sizes[1:], jnp.int32) >= total)  # sizes decrease
    return lax.switch(index, [branch(n) for n in sizes], (tile, g))


def bin_pairs(depth, tx0, tx1, ty0, ty1, ok, tiles_x, num_tiles, pair_capacity, footprint=None,
              tile_size: int = 16, lowpass: bool = False, billboard: bool = False):
    """Depth-ordered per-tile lists.

    With ``footprint`` ((C, 16), :attr:`projection.Projection.footprint`), a box's tiles that
    :func:`tile_touches` (``billboard``: :func:`billboard.square_touches`) rules out are left out.

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
    if footprint is not None:
        valid = valid & _touches_in_blocks(footprint, g, tx0[g] + k % w, ty0[g] + k // w, total, tile_size, lowpass,
                                           billboard)
    tile = jnp.where(valid, tile, num_tiles)
    ids_sorted = _sort_prefix(tile, g, total)
    binned = jnp.zeros((num_tiles + 1,), jnp.int32).at[tile].add(1)[:num_tiles]
    tile_start = jnp.cumsum(binned) - binned
    return ids_sorted, tile_start, binned


def bin_projection(proj, ranges, tiles_x: int, num_tiles: int, pair_capacity: int, config):
    """:func:`bin_pairs` of a view's :class:`projection.Projection` ``proj`` and its
    :func:`tile_ranges` ``ranges``, with ``config``'s tile size, tile cull and coverage mode."""
    tx0, tx1, ty0, ty1, ok = ranges
    return bin_pairs(proj.depth, tx0, tx1, ty0, ty1, ok, tiles_x, num_tiles, pair_capacity,
                     footprint=proj.footprint if config.tile_cull else None, tile_size=config.tile_size,
                     lowpass=config.coverage in ("lowpass", "object"),  # (object: within the low-pass's bounds)
                     billboard=config.coverage in ("billboard", "texel-grid"))


def pair_count(tx0, tx1, ty0, ty1, ok):
    """() float32: the (splat, tile) pairs of the ranges of :func:`tile_ranges`."""
    return jnp.sum(jnp.where(ok, (tx1 - tx0) * (ty1 - ty0), 0).astype(jnp.float32))
