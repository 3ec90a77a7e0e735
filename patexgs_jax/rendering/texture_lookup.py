"""Texture lookups of a chunk's (splat, pixel) pairs: the mip footprint (paper Eq. 11), the
addressing of the flat atlas, the gathers and their backward, and the passes that look up only the
pairs that can contribute.

Only the (pixel, splat) pairs of a chunk step that can reach alpha 1/255 (bounded by
``opacity * G * max(alpha texels)``) at pixels still compositing are looked up, gathered into passes
of ``RenderConfig.texture_pairs`` of the step's pairs; their texture values are spread back into the
dense (c, B, P) block, zero for the pairs skipped, which are not composited anyway. A bilinear lookup
is one gather of the four texels of a 2 x 2 block (see :mod:`patexgs_jax.textures`) per bank and mip
level read; the backward adds each lookup's texel cotangents to two rows of a paired (texel r,
texel r + 1) accumulator. The per-lookup address and weight arithmetic is computed once
(:func:`chunks.barrier`), not re-derived inside every per-texel and per-channel consumer.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .. import textures as tex
from ..math import safe_log2
from .chunks import CompositeInputs, Static, barrier, cols, per_slot, prefix_sum
from .config import RenderConfig
from .kernel import UV_LIMIT, alpha_min, uv
from .projection import COLS

_META = 4  # columns per bank of meta_table


def meta_table(*atlases):
    """(C, 4 x banks) int32: per splat, for each bank present (RGB first), its block's base row in
    the atlas, bucket side, texture side and top mip level: what a lookup reads per splat, in one
    row, so that a pass gathers it once instead of once per field and bank."""
    fields = [c for a in atlases if a is not None for c in (a.base, a.bucket_side, a.size, a.max_level)]
    return jnp.stack([c.astype(jnp.int32) for c in fields], axis=-1)


class _Lookup(NamedTuple):
    """A chunk's texture lookups in one bank, one entry per mip level read (1, or 2 for trilinear).

    base: (c,) int32 the splats' blocks in the atlas; row: (P, c) float rows within the blocks
    (exact integers, no gradient); stride: (P, c) int32 row strides of the levels read; fa, fb:
    (P, c) bilinear fractions; lw: level blend weights (P, c) for trilinear, else None.
    """

    base: jax.Array
    row: tuple
    stride: tuple
    fa: tuple
    fb: tuple
    lw: tuple | None

    def rows(self):
        """(atlas rows (P, c) int32 of each level read, their strides)."""
        return tuple(self.base + lax.stop_gradient(r).astype(jnp.int32) for r in self.row), self.stride


def _tex_lookups(m, u, v, log2_fp, config: RenderConfig, use_mip: bool) -> _Lookup:
    """Texture lookups of one bank at (u, v): ``m`` (..., 4) int32 the splats' rows of
    :func:`meta_table` for the bank, broadcasting against u, v; ``log2_fp``, log2 of the mip
    footprint (see :func:`_plane`), for mipmaps."""
    base, side_p, ni, L = m[..., 0], m[..., 1], m[..., 2], m[..., 3]
    n = ni.astype(u.dtype)
    lambda_mip = config.lambda_mip
    assert lambda_mip is not None  # RenderConfig sets its coverage mode's default

    def at_level(lev):
        off, stride, side = tex.level_address(side_p, ni, lev)
        return tex.corners(off, stride, side, u, v), jnp.broadcast_to(stride, u.shape)

    if not use_mip or config.mip == "none":
        (r, fa, fb), stride = at_level(jnp.int32(0))
        return _Lookup(base, (r,), (stride,), (fa,), (fb,), None)
    if config.mip == "nearest":
        lev = tex.mip_level_log2(log2_fp, n, L, lambda_mip, trilinear=False)
        (r, fa, fb), stride = at_level(lev)
        return _Lookup(base, (r,), (stride,), (fa,), (fb,), None)
    lev = tex.mip_level_log2(log2_fp, n, L, lambda_mip, trilinear=True)
    l0 = jnp.floor(lev)
    frac = lev - l0
    l0i = l0.astype(jnp.int32)
    (r0, fa0, fb0), s0 = at_level(l0i)
    (r1, fa1, fb1), s1 = at_level(jnp.minimum(l0i + 1, L))
    return _Lookup(base, (r0, r1), (s0, s1), (fa0, fa1), (fb0, fb1), (1.0 - frac, frac))


def _tex_value(vals, fa, fb, lw):
    """Texture values, a list of ch arrays (P, c), from the gathered texels ``vals`` (per level read, the
    4 ch arrays of :func:`textures.gather_corners`) and a :class:`_Lookup`'s fractions and level
    weights."""
    out = [tex.bilinear(t, a, b) for t, a, b in zip(vals, fa, fb)]
    if lw is not None:
        out = [[lw[0] * a + lw[1] * b for a, b in zip(*out)]]
    return out[0]


def _gather(texels, rows):
    """Texels of the lookups at ``rows`` (from :meth:`_Lookup.rows`) in the flat atlas ``texels``
    (M, ch): per level read, the 4 ch arrays of :func:`textures.gather_corners`."""
    return None if rows is None else tuple(tex.gather_corners(texels, i, s) for i, s in zip(*rows))


def _scatter(g_pairs, rows, g_vals):
    """Adds the cotangents ``g_vals`` of :func:`_gather` values to ``g_pairs`` (M, 2 ch), the
    cotangent of the flat atlas in pairs: row r holds that of texel r (first ch) and of texel r + 1
    (last ch; see :func:`unpair`). A lookup adds to two rows, r and r + stride."""
    ch = g_pairs.shape[-1] // 2
    for i, stride, g in zip(*rows, g_vals):
        idx = jnp.concatenate([i.reshape(-1), (i + stride).reshape(-1)])
        upd = jnp.concatenate([jnp.stack(g[2 * j * ch:2 * (j + 1) * ch], axis=-1).reshape(-1, 2 * ch)
                               for j in range(2)])
        g_pairs = g_pairs.at[idx].add(upd, mode="promise_in_bounds")
    return g_pairs


def unpair(g_pairs):
    """(M, 2 ch) paired cotangents (:func:`_scatter`) -> (M, ch) cotangents of the flat atlas."""
    ch = g_pairs.shape[-1] // 2
    return g_pairs[:, :ch] + jnp.pad(g_pairs[:-1, ch:], ((1, 0), (0, 0)))


def _rays(pk, x, y):
    """The homogeneous ray-plane products s_i = A_i x + B_i y + C_i (i = 0, 1, 2) of pixel centres
    x, y with the splats' planes pk (..., >= 9), broadcast against each other; (u, v) = (s0, s1) / s2
    (:func:`uv`)."""
    A, B, Cc = pk[..., COLS.a], pk[..., COLS.b], pk[..., COLS.c]
    return [x * A[..., i] + y * B[..., i] + Cc[..., i] for i in range(3)]


def _plane(pk, x, y, need_footprint: bool):
    """Where the rays of pixel centres x, y meet the splats' planes: pk (..., >= 9) packed splats
    (only the plane-equation columns A, B, C are read), x, y broadcast against them.

    Returns u, v, whether the ray meets the plane, and log2 of the mip footprint max(D12, D13)
    (log2 1e4 where a ray misses the plane, the coarsest level) or None, all of the broadcast shape.
    """
    s = _rays(pk, x, y)
    u, v, ok, _ = uv(*s)
    log2_fp = None
    if need_footprint:
        def neighbour(d):
            """(u, v) of the ray one pixel over ((0, 0) where it misses the plane) and whether it
            meets the plane. The miss is folded into one reciprocal, not a select per coordinate:
            fewer selects let XLA fuse more of this."""
            t = [s[i] + d[..., i] for i in range(3)]
            hit = jnp.abs(t[2]) * UV_LIMIT > jnp.maximum(jnp.abs(t[0]), jnp.abs(t[1]))
            inv = jnp.where(hit, 1.0 / jnp.where(hit, t[2], 1.0), 0.0)
            return t[0] * inv, t[1] * inv, hit

        ux, vx, okx = neighbour(pk[..., COLS.a])
        uy, vy, oky = neighbour(pk[..., COLS.b])
        # log2 max(D12, D13) = 0.5 log2 max(D12^2, D13^2): no square roots, and the banks share it.
        d2 = jnp.maximum((ux - u) ** 2 + (vx - v) ** 2, (uy - u) ** 2 + (vy - v) ** 2)
        log2_fp = jnp.where(ok & okx & oky, 0.5 * safe_log2(d2), math.log2(UV_LIMIT))
    return u, v, ok, log2_fp


class _Passes(NamedTuple):
    """Which (splat, tile, pixel) pairs of a batch's chunk get texture lookups, and in how many passes.

    The (c, B, P) block is cut into rows of at most 32 slots along its last axis (32 pixels of a
    splat's tile); ``bits`` (R,) uint32 marks the pairs of each row that may reach alpha 1/255
    at a pixel still compositing; ``ends`` (R,) int32 is the inclusive running count of marked pairs
    over the rows; count: () int32 how many in all; K: static pass size; shape: static (c, B, P).
    Pass j looks up the marked pairs of ranks ``j K`` to ``(j + 1) K - 1`` in block order.
    """

    bits: jax.Array
    ends: jax.Array
    count: jax.Array
    K: int
    shape: tuple


_WORD = 32  # slots per row of _Passes: one uint32 bit each


def _row_bits(take):
    """(..., c) bool -> (..., ceil(c / 32)) uint32: the marks of each run of 32 slots as the bits of
    one word (slot w 32 + i of the last axis is bit i of word w)."""
    c = take.shape[-1]
    nw = -(-c // _WORD)
    take = jnp.pad(take, [(0, 0)] * (take.ndim - 1) + [(0, nw * _WORD - c)])
    take = take.reshape(take.shape[:-1] + (nw, _WORD))
    weights = jnp.left_shift(jnp.uint32(1), jnp.arange(_WORD, dtype=jnp.uint32))
    return jnp.sum(jnp.where(take, weights, jnp.uint32(0)), axis=-1, dtype=jnp.uint32)


def _nth_bit(bits, n):
    """Position (int32) of the bit of rank ``n`` (0-based, from the least significant) set in
    ``bits`` (uint32), elementwise; ``n`` must be below the number of set bits. A binary search on
    population counts: 5 halvings of the 32-bit word."""
    pos = jnp.zeros(bits.shape, jnp.uint32)
    n = n.astype(jnp.uint32)
    for width in (16, 8, 4, 2, 1):
        low = lax.population_count(jnp.right_shift(bits, pos) & jnp.uint32((1 << width) - 1))
        up = n >= low
        n = jnp.where(up, n - low, n)
        pos = jnp.where(up, pos + jnp.uint32(width), pos)
    return pos.astype(jnp.int32)


def texture_passes(st: Static, ctx: CompositeInputs, pk, gid, valid, G, done):
    """The :class:`_Passes` of a batch's chunk, or None when every pair is looked up
    (``config.texture_pairs`` 1).

    A pair whose bound ``opacity * G * max(alpha texels)`` is below 1/255 (with a 1e-3 margin for
    rounding) has alpha < 1/255 whatever its texture holds, and a pixel that stopped compositing
    takes nothing more: neither needs a lookup, and their texture values are never read (the pair
    is skipped). Textures then cost in proportion to the pairs that contribute (a few percent to a
    few tens of percent of a chunk's pairs), not to the whole (pixels x splats) block.

    The marks are packed into 32-bit words, one per 32-slot row, and counted with a running sum over
    the rows; each pass finds its pairs from those counts (:func:`_pass_pairs`,
    :func:`_rows_of_ranks`). Nothing block-sized is written, only the words (one per 32 pairs): no
    per-pair index array; the one scatter adds the rows' ends into a pass-sized histogram.
    """
    N = G.size
    K = min(N, max(1, math.ceil(st.config.texture_pairs * N)))
    if K >= N:
        return None
    bound = cols(pk)[COLS.opacity] * per_slot(ctx.peak[gid]) * G
    take = per_slot(valid & ctx.need("tex_has")[gid]) & ~done & (bound >= alpha_min(st, pk) * (1.0 - 1e-3))
    return _mark_passes(take, K)


def _mark_passes(take, K: int) -> _Passes:
    """The :class:`_Passes` of passes of K pairs over the pairs marked in ``take`` (..., n) bool (rows
    of 32 slots along the last axis)."""
    bits = _row_bits(take).reshape(-1)
    counts = lax.population_count(bits).astype(jnp.int32)
    if take.size < 2 ** 24:  # running counts exact in float32: two small matmuls, not reduce-windows
        ends = _running_sum(counts.astype(jnp.float32)).astype(jnp.int32)
    else:
        ends = jnp.cumsum(counts)
    return _Passes(bits, ends, ends[-1], K, take.shape)


def _more_passes(passes: _Passes, j):
    """Whether pass j has pairs (the condition of the pass loops)."""
    return j * passes.K < passes.count


def _rows_of_ranks(ends, start, K: int):
    """(K,) int32: for the ranks ``start`` .. ``start + K - 1``, the row holding each, i.e. how many
    of the inclusive running counts ``ends`` (R,) int32 (nondecreasing) are at most the rank
    (``searchsorted(ends, rank, side="right")``). The ranks are consecutive, so this is the number of
    rows ending before ``start`` plus a running sum of a histogram of where the others end: one
    scatter of R ones and two small matmuls (:func:`_running_sum`), where a binary search would
    gather ``log2 R`` times."""
    before = jnp.sum((ends < start).astype(jnp.int32))
    at = ends - start
    hist = jnp.zeros((K,), jnp.float32).at[jnp.where((at >= 0) & (at < K), at, K)].add(1.0, mode="drop")
    return before + _running_sum(hist).astype(jnp.int32)


def _running_sum(x):
    """Inclusive running sum of a (K,) float32 vector of small integer counts (exact below 2**24), as
    a prefix sum within blocks of w (a power of two, about sqrt K) and one over the blocks' totals:
    two triangular matmuls, where XLA's CPU cumsum is a reduce-window of K^2 adds."""
    K = x.shape[0]
    w = 1 << max(0, math.ceil(math.log2(math.sqrt(K))))
    nb = -(-K // w)
    blocks = prefix_sum(jnp.pad(x, (0, nb * w - K)).reshape(nb, w))
    offsets = prefix_sum(blocks[:, -1]) - blocks[:, -1]
    return (blocks + offsets[:, None]).reshape(-1)[:K]


def _pass_pairs(passes: _Passes, j):
    """(K,) int32 flat indices into the block (``passes.shape``) of the pairs of pass j, in block
    order; the block's size for unused slots."""
    n = passes.shape[-1]
    nw = -(-n // _WORD)
    start = j * passes.K
    rank = start + jnp.arange(passes.K, dtype=jnp.int32)
    row = jnp.minimum(_rows_of_ranks(passes.ends, start, passes.K), passes.ends.shape[0] - 1)
    word = passes.bits[row]
    first = passes.ends[row] - lax.population_count(word).astype(jnp.int32)
    bit = _nth_bit(word, rank - first)
    pair = (row // nw) * n + (row % nw) * _WORD + bit
    return jnp.where(rank < passes.count, pair, math.prod(passes.shape))


def _select(pk, gid, x, y, sel):
    """Splats' plane equations (the first ``COLS.plane`` columns of pk (B, c, F), all a lookup reads),
    splat ids and pixel centres of the looked-up pairs: with ``sel`` None the whole block,
    broadcasting ((c, B, 1, 9), (c, B, 1), (B, P), (B, P)); else of the pairs of
    :func:`_pair_rows` ``sel``: (K, 9), (K,), (K,), (K,). The columns are cut before the gather,
    so the gather's transpose scatters into (B c, 9); cut from the gathered (K, F) rows instead,
    each column read would be a (K, F) pad in the backward, summed."""
    pk = pk[..., :COLS.plane]
    if sel is None:
        return jnp.swapaxes(pk, 0, 1)[:, :, None], per_slot(gid), x, y
    _, splat, pixel = sel
    B, c, F = pk.shape
    return pk.reshape(B * c, F)[splat], gid.reshape(-1)[splat], x.reshape(-1)[pixel], y.reshape(-1)[pixel]


def _pair_rows(ctx: CompositeInputs, passes: _Passes, j):
    """(idx, splat, pixel), each (K,) int32: the pairs of pass j (:func:`_pass_pairs`, flat into
    ``passes.shape`` = (c, B, P), N for none), and the rows of their splats in the (B c) chunk slots
    and of their pixels in the (B P) pixels. Through :func:`barrier`, so that the pass's pair
    search is done once, not again in every gather that reads it (XLA would fuse it into each and
    redo it for every gathered element, the columns of a splat row included)."""
    c, B, P = passes.shape
    idx = _pass_pairs(passes, j)
    i = jnp.minimum(idx, c * B * P - 1)
    k, r = i // (B * P), i % (B * P)
    return barrier((idx, (r // P) * c + k, r), ctx.flag)


def _lookups(st: Static, ctx: CompositeInputs, pk, gid, x, y, sel):
    """Texture lookups of a batch's chunk (all pairs, ``sel`` None) or of the pairs ``sel``
    (:func:`_pair_rows`).

    Args:
      pk: (B, c, F) packed splats; gid (B, c); x, y (B, P) pixel centres; sel: see
        :func:`_select`.
    Returns:
      (rgb weights, alpha weights), differentiable in pk: per bank None or (fa, fb, lw) of its
      :class:`_Lookup`; and (rgb rows, alpha rows), None or :meth:`_Lookup.rows`.
    """
    pk, gid, x, y = _select(pk, gid, x, y, sel)
    u, v, _, fp = _plane(pk, x, y, st.need_footprint)
    # Each per-lookup quantity is computed once (see barrier): (u, v), the footprint and the splats'
    # texture addressing (one row gathered per lookup), which every lookup reads, then the lookups'
    # rows and weights, which the gathers and products read per texel.
    u, v, fp, m = barrier((u, v, fp, ctx.need("tex_meta")[gid]), ctx.flag)
    cfg = st.config
    lr = _tex_lookups(m[..., :_META], u, v, fp, cfg, st.rgb_mip) if st.rgb else None
    la = _tex_lookups(m[..., -_META:], u, v, fp, cfg, st.alpha_mip) if st.alpha else None
    lr, la = barrier((lr, la), ctx.flag)
    def weights(lk):
        return None if lk is None else (lk.fa, lk.fb, lk.lw)

    def rows(lk):
        return None if lk is None else lk.rows()

    return (weights(lr), weights(la)), (rows(lr), rows(la))


def _values(ctx: CompositeInputs, weights, vals):
    """Texture values of lookups: (RGB offsets, a list of 3, or None; alpha or None), each of the
    lookups' shape, from their weights (:func:`_lookups`) and gathered texels ``vals`` (per bank None
    or :func:`_gather`'s). Through :func:`barrier`, so their cotangents are computed once, not
    per texel."""
    (wr, wa), (vr, va) = weights, vals
    return barrier((None if wr is None else _tex_value(vr, *wr),
                    None if wa is None else _tex_value(va, *wa)[0]), ctx.flag)


def _pick(dense, idx):
    """(c, B, P) arrays -> their values at the pairs ``idx`` (K,), zero for unused slots."""
    return jax.tree.map(lambda q: q.reshape(-1).at[idx].get(mode="fill", fill_value=0), dense)


def texture_fwd(st: Static, ctx: CompositeInputs, pk, gid, x, y, passes: _Passes | None, shape):
    """Texture values (RGB offsets list of 3 or None, alpha or None), each (c, B, P), of a batch's
    chunk: every pair (``passes`` None) or the pairs of :func:`texture_passes`, zero elsewhere."""
    def look(sel):
        w, rows = _lookups(st, ctx, pk, gid, x, y, sel)
        return _values(ctx, w, (_gather(ctx.rgb_texels, rows[0]), _gather(ctx.alpha_texels, rows[1])))

    if passes is None:
        return look(None)
    N = math.prod(shape)
    dt = pk.dtype
    init = (None if not st.rgb else [jnp.zeros((N,), dt)] * 3, None if not st.alpha else jnp.zeros((N,), dt))

    def body(state):
        j, dense = state
        sel = _pair_rows(ctx, passes, j)
        idx = sel[0]
        vals = look(sel)
        return j + 1, jax.tree.map(lambda d, q: d.at[idx].set(q, mode="drop"), dense, vals)

    _, dense = lax.while_loop(lambda state: _more_passes(passes, state[0]), body, (jnp.int32(0), init))
    return jax.tree.map(lambda d: d.reshape(shape), dense)


def texture_bwd(st: Static, ctx: CompositeInputs, pk, gid, x, y, passes: _Passes | None, shape, ct, g_rt, g_at):
    """The backward of :func:`texture_fwd` for cotangents ``ct`` of its output. Each pass's lookups
    are computed again here, under ``jax.vjp``, rather than kept from the :func:`texture_fwd` call
    of :func:`composite._chunk_bwd` that produced the values: the number of passes is known only at
    run time, so their residuals have no static size. This is work done twice, and not small (see
    docs/performance.md).

    Returns (g_pk (B, c, F), g_rt, g_at): the packed-splat cotangent, and the paired texel
    cotangents ``g_rt``, ``g_at`` (:func:`_scatter`) with this chunk's added.
    """
    def one(sel, ct_vals, g_rt, g_at):
        w, vjp_lk, rows = jax.vjp(lambda p: _lookups(st, ctx, p, gid, x, y, sel), pk, has_aux=True)
        vals = (_gather(ctx.rgb_texels, rows[0]), _gather(ctx.alpha_texels, rows[1]))
        _, vjp_v = jax.vjp(lambda w_, v_: _values(ctx, w_, v_), w, vals)
        g_w, (g_vr, g_va) = vjp_v(ct_vals)
        if rows[0] is not None:
            g_rt = _scatter(g_rt, rows[0], g_vr)
        if rows[1] is not None:
            g_at = _scatter(g_at, rows[1], g_va)
        return vjp_lk(g_w)[0], g_rt, g_at

    if passes is None:
        return one(None, ct, g_rt, g_at)

    def body(state):
        j, g_pk, g_rt, g_at = state
        sel = _pair_rows(ctx, passes, j)
        g, g_rt, g_at = one(sel, _pick(ct, sel[0]), g_rt, g_at)
        return j + 1, g_pk + g, g_rt, g_at

    init = (jnp.int32(0), jnp.zeros_like(pk), g_rt, g_at)
    return lax.while_loop(lambda state: _more_passes(passes, state[0]), body, init)[1:]
