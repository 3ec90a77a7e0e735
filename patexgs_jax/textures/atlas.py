"""The flat texel atlas of a texture bank, with its mip pyramids (built inside jit), and its lookups.

Atlas
  Every texel, of every bucket and level, sits in one flat ``(M, channels)`` array (the
  differentiable one) in which each Gaussian's pyramid is one contiguous block; a level's offset in
  the block, row stride and side are computed from the bucket side and the level
  (:func:`level_address`), so a lookup needs no per-level tables. A bilinear lookup reads the four
  texels r, r + 1, r + stride, r + stride + 1 of the atlas in one gather (:func:`gather_corners`);
  past a level's edge (1 x 1 levels) it reads a neighbour's texel with weight exactly 0, and zero rows
  at the end of the atlas keep every read in bounds. Pyramids are built only when a configuration
  uses them.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .bank import TextureBank, downsample_matrix


@functools.cache
def _first_level_table(P: int) -> np.ndarray:
    """(P//2, P//2, P) float32: for n = P//2 + 1 + i, the level-0 (n) to level-1 (P//2) matrix.

    Columns beyond n are zero, so the padding of a bucket slot never leaks into the pyramid.
    """
    half = P // 2
    table = np.zeros((half, half, P), np.float32)
    for i in range(half):
        n = half + 1 + i
        table[i, :, :n] = downsample_matrix(n, half)
    return table

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Atlas:
    """The texels of one bank, all buckets and used levels flattened (built inside jit).

    Each Gaussian's pyramid is one contiguous block starting at ``base``: level 0 stored P x P
    (row stride P, true side n), then level 1 ((P/2)^2 texels), level 2, ... down to 1 x 1.
    Level l >= 1 starts at ``(4/3) (P^2 - (P >> l)^2)`` within the block (see :func:`level_address`).

    Attributes:
      texels: (M + pad, channels) float, the flat pyramids (differentiable); row 0 is a dummy (zeros)
        for texture-less Gaussians, and ``pad`` zero rows at the end keep every neighbour row of a
        lookup (r + 1, r + stride, r + stride + 1, weight 0 past a level's edge) in bounds.
      base: (C,) int32 flat offset of each Gaussian's block.
      bucket_side: (C,) int32 P, the bucket's slot side.
      size: (C,) float32 true n (0: no texture).
      max_level: (C,) int32 coarsest level L = ceil(log2 n) (0 when only level 0 is built).
      has: (C,) bool, textured.
    """

    texels: jax.Array
    base: jax.Array
    bucket_side: jax.Array
    size: jax.Array
    max_level: jax.Array
    has: jax.Array


_UNROLL_MAX = 16  # largest slot side filtered with unrolled sums (see _sandwich); einsums above


def _rows_filter(D, Xf):
    """``Y[k, i, x] = sum_p D[k, i, p] Xf[k, p, x]``: D (K | 1, I, P), Xf (K, P, X) -> (K, I, X), as a
    sum of P broadcast products, which XLA fuses into one loop."""
    K, P, X = Xf.shape
    return _sum_of_products(lax.split(D, (1,) * P, axis=2), (0, 1, 2),
                            lax.split(Xf, (1,) * P, axis=1), (0, 1, 2), (K, D.shape[1], X))


def _cols_filter(D, Y):
    """``Z[k, i, j, c] = sum_q Y[k, i, q, c] D[k, j, q]``: Y (K, I, P, C) -> (K, I, J, C)."""
    K, I, P, C = Y.shape
    return _sum_of_products(lax.split(Y, (1,) * P, axis=2), (0, 1, 2, 3),
                            lax.split(D, (1,) * P, axis=2), (0, 2, 3), (K, I, D.shape[1], C))


def _sum_of_products(a, a_dims, b, b_dims, shape):
    """``sum_p a[p] * b[p]``, each pair broadcast to ``shape`` (``lax.broadcast_in_dim`` with the
    given dimensions), added in order of p. The slices come from one ``lax.split`` per operand and
    the products are written with lax directly: the same fused loop as indexing and broadcasting with
    jax.numpy, in half the traced operations (the pyramids are a large share of a textured program's
    tracing and lowering)."""
    acc = None
    for x, y in zip(a, b):
        t = lax.mul(lax.broadcast_in_dim(x, shape, a_dims), lax.broadcast_in_dim(y, shape, b_dims))
        acc = t if acc is None else lax.add(acc, t)
    return acc


def _filter_shape(fn, D, X):
    """The shape of ``fn(D, X)`` for fn :func:`_rows_filter` or :func:`_cols_filter`, without
    tracing it."""
    if fn is _rows_filter:
        return (X.shape[0], D.shape[1], X.shape[2])
    return (X.shape[0], X.shape[1], D.shape[1], X.shape[3])


def _once(fn, D, X):
    """``fn(D, X)`` in a conditional's branch (its predicate, D's first entry being finite, is always
    true but XLA cannot prove it). XLA cannot fuse across a conditional: fused into their consumers,
    a level was computed again in each (the next level's filter and the atlas concatenation), and a
    filter's first stage again for every element of its second."""
    def zeros(D, X):
        return jnp.zeros(_filter_shape(fn, D, X), X.dtype)

    return lax.cond(jnp.isfinite(D[0, 0, 0]), fn, zeros, D, X)


def _sandwich(D, X, once: bool = False):
    """``D X D^T`` per slot and channel: D (K | 1, I, P) filters, X (K, P, P, C) -> (K, I, I, C).

    Written as sums over the P contracted rows, then columns, of broadcast products, which XLA fuses
    into one loop each; an einsum would make XLA's CPU backend first transpose X (and, in the
    backward, the cotangent) into a batched matmul's layout, which is slower for these tiny
    matrices (docs/benchmarks.md). With ``once``, each stage is computed once (:func:`_once`).
    """
    K, P, _, C = X.shape
    I = D.shape[1]
    stage = _once if once else (lambda fn, D, X: fn(D, X))
    Y = stage(_rows_filter, D, X.reshape(K, P, P * C)).reshape(K, I, P, C)
    return stage(_cols_filter, D, Y)


def _filter(D, X):
    """:func:`_sandwich`, linear in X, whose transpose is the same sums with D^T (no gradient for D:
    the filters depend on texture sizes only). The forward's stages are computed once; the transpose
    has no conditionals, which would slow it (the cotangents' sums fuse well as they are;
    docs/benchmarks.md). The forward is computed without gradients and :func:`_with_transpose`
    gives its output the transpose as derivative: a ``jax.custom_vjp`` function inside a traced
    program is traced twice under differentiation (as itself and as its forward rule); this way the
    filter is traced once."""
    sg = lax.stop_gradient
    return _with_transpose(D, X, _sandwich(sg(D), sg(X), once=True))


@jax.custom_vjp
def _with_transpose(D, X, Y):
    """Y (= ``D X D^T``) unchanged, with the derivative of ``D X D^T`` in X."""
    return Y


_with_transpose.defvjp(lambda D, X, Y: (Y, D),
                       lambda D, g: (jnp.zeros_like(D), _sandwich(jnp.swapaxes(D, 1, 2), g), None))


def _downsample(D, X):
    """``D X D^T``: D (K | 1, I, P), X (K, P, P, C) -> (K, I, I, C); :func:`_filter` for slots up to
    ``_UNROLL_MAX`` a side, an einsum above (few slots, and P^3 products each)."""
    if X.shape[1] <= _UNROLL_MAX:
        return _filter(D, X)
    if D.shape[0] == 1:
        return jnp.einsum("ip,kpqc,jq->kijc", D[0], X, D[0], precision=lax.Precision.HIGHEST)
    return jnp.einsum("kip,kpqc,kjq->kijc", D, X, D, precision=lax.Precision.HIGHEST)


def _pyramid(level0: jax.Array, n: jax.Array, b: int) -> list[jax.Array]:
    """Levels 0..b of a bucket's textures: (cap, P, P, ch) -> list of (cap, s_k, s_k, ch)."""
    levels = [level0]
    if b == 0:
        return levels
    P = 1 << b
    table = jnp.asarray(_first_level_table(P), level0.dtype)
    idx = jnp.clip(n - (P // 2 + 1), 0, P // 2 - 1)
    levels.append(_downsample(table[idx], level0))  # each slot's filter (cap, P/2, P) for its size
    for k in range(2, b + 1):
        Dk = jnp.asarray(downsample_matrix(P >> (k - 1), P >> k), level0.dtype)
        levels.append(_downsample(Dk[None], levels[-1]))
    return levels


def build_atlas(bank: TextureBank, use_mip: bool) -> Atlas:
    """Flattens a bank (with its mip pyramids when ``use_mip``) into one texel array."""
    ch = bank.channels
    bucket = jax.lax.stop_gradient(bank.bucket).astype(jnp.int32)
    slot = jax.lax.stop_gradient(bank.slot).astype(jnp.int32)
    size_f = jax.lax.stop_gradient(bank.size)
    size = size_f.astype(jnp.int32)
    has = bucket >= 0
    dtype = bank.buckets[0].dtype if bank.buckets else jnp.float32
    chunks = [jnp.zeros((1, ch), dtype)]
    offset = 1
    base = jnp.zeros(bucket.shape, jnp.int32)
    for b, data in enumerate(bank.buckets):
        cap = data.shape[0]
        if cap == 0:
            continue
        mine = bucket == b
        if use_mip:
            # n of each slot, for the level-0 -> level-1 filter: scatter sizes into slots.
            n_slot = jnp.zeros((cap,), jnp.int32).at[jnp.where(mine, slot, cap)].set(size, mode="drop")
            levels = _pyramid(data, n_slot, b)
        else:
            levels = [data]
        block = jnp.concatenate([lev.reshape(cap, -1, ch) for lev in levels], axis=1)
        chunks.append(block.reshape(-1, ch))
        base = jnp.where(mine, offset + jnp.clip(slot, 0, cap - 1) * block.shape[1], base)
        offset += block.shape[0] * block.shape[1]
    bucket_side = jnp.where(has, jnp.left_shift(1, jnp.maximum(bucket, 0)), 1)
    max_level = jnp.where(has, bucket, 0) if use_mip else jnp.zeros_like(bucket)
    chunks.append(jnp.zeros(((1 << max(len(bank.buckets) - 1, 0)) + 2, ch), dtype))
    return Atlas(texels=jnp.concatenate(chunks, axis=0), base=base,
                 bucket_side=bucket_side, size=size_f, max_level=max_level, has=has)


def level_address(bucket_side, size, level):
    """(offset within the block, row stride, side) of pyramid ``level``; int32, broadcasting.

    Level 0: (0, P, n); level l >= 1: ((4/3)(P^2 - s^2), s, s) with s = P >> l.
    """
    s = jnp.right_shift(bucket_side, level)
    zero = level == 0
    # 4 (P^2 - s^2) = 4 s^2 (4^l - 1) and its third are exact in float32 for l <= 12 (bucket sides up
    # to 4096), so the division is exact; XLA's CPU emulates an integer floor division per element
    # (a sign, a remainder and selects) in every texture lookup.
    off = ((bucket_side * bucket_side - s * s) * 4).astype(jnp.float32) / 3.0
    return jnp.where(zero, 0, off.astype(jnp.int32)), jnp.where(zero, bucket_side, s), jnp.where(zero, size, s)


def corners(offset, stride, side, u, v):
    """Row and fractions of the bilinear, edge-clamped lookup of one level (align-corners).

    The row ``offset + a0 * stride + b0`` of a Gaussian's block holds texel (a0, b0); the lookup
    reads it with (a0, b0 + 1), (a0 + 1, b0), (a0 + 1, b0 + 1) (:func:`gather_corners`). a0 and b0
    are at most side - 2 (for side >= 2); for side 1 the neighbours (past the edge) get weight
    exactly 0.

    Args:
      offset, stride, side: int32 arrays broadcastable with u (per lookup): the level's offset in the
        block, row stride and side (:func:`level_address`).
      u, v: float splat-plane coordinates in units of the scales (texture spans [-3, 3]^2).
    Returns:
      (row (...) the row within the block, as a float holding an exact integer (blocks have fewer
      than 2**24 rows), fa (...), fb (...) the fractional positions along a and b); the fractions
      are differentiable in (u, v), the row piecewise constant.
    """
    dt = u.dtype
    last = jnp.maximum(side.astype(dt) - 1.0, 0.0)
    top = jnp.maximum(last - 1.0, 0.0)
    ta = jnp.clip((u + 3.0) * (1.0 / 6.0) * last, 0.0, last)
    tb = jnp.clip((v + 3.0) * (1.0 / 6.0) * last, 0.0, last)
    a0 = jnp.minimum(jnp.floor(ta), top)
    b0 = jnp.minimum(jnp.floor(tb), top)
    row = offset.astype(dt) + a0 * stride.astype(dt) + b0
    return row, ta - a0, tb - b0


def gather_corners(texels, row, stride):
    """The 2 x 2 texels of bilinear lookups: ``texels`` (M, ch) the atlas, ``row`` (...) int32 atlas
    rows (block base plus :func:`corners` row), ``stride`` (...) int32 their levels' row strides ->
    list of 4 ch arrays (...): texel (a0, b0) channels, then (a0, b0 + 1), (a0 + 1, b0),
    (a0 + 1, b0 + 1). One gather of four rows per lookup (XLA's CPU gathers cost per index)."""
    idx = jnp.stack([row, row + 1, row + stride, row + stride + 1], axis=-1)
    t = texels.at[idx].get(mode="promise_in_bounds")  # (..., 4, ch)
    return [t[..., q, k] for q in range(4) for k in range(texels.shape[-1])]


def bilinear(t, fa, fb):
    """Bilinear values from :func:`gather_corners` texels ``t`` (4 ch arrays) and fractions fa, fb ->
    list of ch arrays.

    Per-channel arrays (not an (..., ch) array): the callers combine channels with per-lookup
    scalars, and per-channel arrays keep those products elementwise, forward and backward.
    """
    ch = len(t) // 4
    ga, gb = 1.0 - fa, 1.0 - fb
    return [ga * (gb * t[k] + fb * t[ch + k]) + fa * (gb * t[2 * ch + k] + fb * t[3 * ch + k])
            for k in range(ch)]


def mip_level(footprint, n, max_level, lambda_mip: float, trilinear: bool):
    """Per-lookup mip level from the splat-plane footprint (paper Eq. 11).

    Args:
      footprint: max(D12, D13), the distance in splat-plane units (units of the scales) between the
        pixel's ray-splat intersection and those of its +x and +y neighbours.
      n: true texture side (float), broadcastable.
      max_level: int L = ceil(log2 n), broadcastable.
      lambda_mip: the paper's lambda (0.4 by default).
      trilinear: if False, ``l = clip(floor(log2(lambda * n * D)), 0, L)`` (int32); if True the
        fractional level ``clip(log2(lambda * n * D), 0, L)`` (float).
    """
    from ..math import safe_log2

    return mip_level_log2(safe_log2(footprint), n, max_level, lambda_mip, trilinear)


def mip_level_log2(log2_footprint, n, max_level, lambda_mip: float, trilinear: bool):
    """:func:`mip_level` from ``log2(footprint)``: ``log2(lambda n D) = log2(D) + log2(lambda n)``,
    so the renderer takes one logarithm per pixel and splat, shared by every bank and level it reads,
    and one per splat for the texture side."""
    from ..math import safe_log2

    lf = log2_footprint + safe_log2(lambda_mip * n)
    Lf = max_level.astype(lf.dtype)
    if trilinear:
        return jnp.clip(lf, 0.0, Lf)
    return jnp.clip(jnp.floor(lf), 0.0, Lf).astype(jnp.int32)
