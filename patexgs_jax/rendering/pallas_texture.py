"""Texture lookups inside the Pallas compositor (:mod:`.pallas_composite`): one splat's RGB and alpha
lookups at a tile's pixels, (P,) vectors, with their hand-derived backward.

The same maths as :mod:`.texture_lookup` and :mod:`patexgs_jax.textures` (the atlas layout of
:class:`textures.Atlas`, the mip footprint of paper Eq. 11, align-corners bilinear clamped at the
edges, nearest or trilinear levels), for one splat at a time: the splat's addressing (its row of
:func:`.texture_lookup.meta_table`) is read as scalars and each pixel gathers its 2 x 2 texels from
the flat atlas. The backward returns the cotangents of (u, v) and of the footprint's neighbour
rays, and adds each pixel's texel cotangents to the atlas's with atomic adds.

Interpret mode: Pallas's interpreter writes an atomic add of a vector of indices as one scatter
that keeps one of two lanes adding to the same texel (neighbouring pixels share texels), so there
the texel cotangents are added lane by lane (:func:`scatter_add`); on the GPU it is one atomic add
of the whole vector.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental.pallas import triton as plgpu

from .kernel import UV_LIMIT

_META = 4  # columns per bank of texture_lookup.meta_table: base, bucket side, size, top level
_LN2 = math.log(2.0)  # d log2(x) / dx = 1 / (x ln 2)


def bank_row(meta_ref, has_ref, g, bank: int) -> dict[str, Any]:
    """Splat g's addressing in bank ``bank`` (0: the first bank of the meta table) as scalars."""
    m = [meta_ref[g, bank * _META + i] for i in range(_META)]
    return dict(base=m[0], side=m[1], n=m[2], L=m[3], has=has_ref[g] != 0)


class Footprint(NamedTuple):
    """log2 of the mip footprint max(D12, D13) at the tile's pixels and what its backward reads."""

    log2_fp: jax.Array
    nb: tuple       # per neighbour (+x, +y): (u, v, 1 / t2 (0 where the ray misses), t0, t1)
    d2: jax.Array   # max of the squared distances
    use_x: jax.Array  # the +x neighbour's distance is the larger
    live: jax.Array   # the three rays meet the plane (else the coarsest level: no gradient)


def footprint(s, r, u, v, ok) -> Footprint:
    """As :func:`.texture_lookup._plane`: s the pixels' ray-plane products (3 (P,)), r the splat's
    row (:func:`.pallas_composite._row`), (u, v, ok) the pixels' intersections."""
    nb = []
    hits = []
    for col in (r["a"], r["b"]):
        t = [s[i] + col[i] for i in range(3)]
        hit = jnp.abs(t[2]) * UV_LIMIT > jnp.maximum(jnp.abs(t[0]), jnp.abs(t[1]))
        inv = jnp.where(hit, 1.0 / jnp.where(hit, t[2], 1.0), 0.0)
        nb.append((t[0] * inv, t[1] * inv, inv))
        hits.append(hit)
    dx2 = (nb[0][0] - u) ** 2 + (nb[0][1] - v) ** 2
    dy2 = (nb[1][0] - u) ** 2 + (nb[1][1] - v) ** 2
    d2 = jnp.maximum(dx2, dy2)
    live = ok & hits[0] & hits[1]
    log2_fp = jnp.where(live, 0.5 * jnp.log2(jnp.maximum(d2, 1e-30)), math.log2(UV_LIMIT))
    return Footprint(log2_fp, tuple(nb), d2, dx2 >= dy2, live)


class Lookup(NamedTuple):
    """One bank's bilinear lookups at the tile's pixels, one entry per level read (1, or 2 with
    trilinear): atlas rows (int32), row strides, fractions, and the (u, v) -> fraction slopes (0
    where clamped); level weights and the fractional level's slope for trilinear, else None."""

    rows: tuple
    strides: tuple
    fa: tuple
    fb: tuple
    da: tuple
    db: tuple
    lw: tuple | None
    dlev: Any


def _level_address(side, n, lev):
    """As :func:`textures.level_address`: (offset, stride, side) of level ``lev`` (int32)."""
    s = jnp.right_shift(side, lev)
    zero = lev == 0
    off = ((side * side - s * s) * 4).astype(jnp.float32) / 3.0
    return jnp.where(zero, 0, off.astype(jnp.int32)), jnp.where(zero, side, s), jnp.where(zero, n, s)


def _corners(off, stride, side, u, v, base):
    """As :func:`textures.corners`, with the atlas row (base added) and the fractions' slopes."""
    dt = u.dtype
    last = jnp.maximum(side.astype(dt) - 1.0, 0.0)
    top = jnp.maximum(last - 1.0, 0.0)
    out = []
    for w in (u, v):
        raw = (w + 3.0) * (1.0 / 6.0) * last
        t = jnp.minimum(jnp.maximum(raw, 0.0), last)
        t0 = jnp.minimum(jnp.floor(t), top)
        out.append((t0, t - t0, jnp.where((raw > 0.0) & (raw < last), last * (1.0 / 6.0), 0.0)))
    (a0, fa, da), (b0, fb, db) = out
    row = base + off + a0.astype(jnp.int32) * stride + b0.astype(jnp.int32)
    return row, fa, fb, da, db


def lookup(bank, u, v, log2_fp, config, use_mip: bool) -> Lookup:
    """As :func:`.texture_lookup._tex_lookups`, for one splat's bank (:func:`bank_row`)."""
    base, side, n_i, L = bank["base"], bank["side"], bank["n"], bank["L"]
    n = n_i.astype(u.dtype)

    def at(lev):
        off, stride, sd = _level_address(side, n_i, lev)
        return _corners(off, stride, sd, u, v, base), stride

    zero = jnp.zeros(u.shape, jnp.int32)
    if not use_mip or config.mip == "none":
        levels, lw, dlev = [at(zero)], None, None
    else:
        lf = log2_fp + jnp.log2(jnp.maximum(config.lambda_mip * n, 1e-30))
        Lf = L.astype(u.dtype)
        if config.mip == "nearest":
            lev = jnp.minimum(jnp.maximum(jnp.floor(lf), 0.0), Lf).astype(jnp.int32)
            levels, lw, dlev = [at(lev)], None, None
        else:
            lev = jnp.minimum(jnp.maximum(lf, 0.0), Lf)
            l0 = jnp.floor(lev)
            frac = lev - l0
            l0i = l0.astype(jnp.int32)
            levels = [at(l0i), at(jnp.minimum(l0i + 1, L))]
            lw = (1.0 - frac, frac)
            dlev = jnp.where((lf > 0.0) & (lf < Lf), 1.0, 0.0)
    (c0, s0), *more = levels
    cs = [c0] + [c for c, _ in more]
    strides = (s0,) + tuple(s for _, s in more)
    return Lookup(tuple(c[0] for c in cs), strides, tuple(c[1] for c in cs), tuple(c[2] for c in cs),
                  tuple(c[3] for c in cs), tuple(c[4] for c in cs), lw, dlev)


def _offsets(row, stride):
    return (row, row + 1, row + stride, row + stride + 1)


def gather(tex_ref, lk: Lookup, ch: int, mask):
    """The 2 x 2 texels of each level read: per level, 4 corners of ch (P,) vectors (lanes where
    ``mask`` is False read 0)."""
    out = []
    for row, stride in zip(lk.rows, lk.strides, strict=True):
        out.append([[plgpu.load(tex_ref.at[i, k], mask=mask, other=0.0) for k in range(ch)]
                    for i in _offsets(row, stride)])
    return out


def _bilinear(t, fa, fb, k):
    ga, gb = 1.0 - fa, 1.0 - fb
    return ga * (gb * t[0][k] + fb * t[1][k]) + fa * (gb * t[2][k] + fb * t[3][k])


def value(texels, lk: Lookup, ch: int):
    """The lookups' values, ch (P,) vectors (trilinear: the levels blended)."""
    per = [[_bilinear(t, fa, fb, k) for k in range(ch)] for t, fa, fb in zip(texels, lk.fa, lk.fb, strict=True)]
    if lk.lw is None:
        return per[0]
    return [lk.lw[0] * a + lk.lw[1] * b for a, b in zip(*per, strict=True)]


def value_bwd(g_val, texels, lk: Lookup, ch: int):
    """The backward of :func:`value` for cotangents ``g_val`` (ch (P,)): (g_u, g_v, g_lf) (g_lf the
    fractional level's, None without trilinear) and, per level, the 4 corners' ch texel cotangents."""
    g_u = g_v = 0.0
    tcots = []
    per_level = []
    for li, (t, fa, fb, da, db) in enumerate(zip(texels, lk.fa, lk.fb, lk.da, lk.db, strict=True)):
        wl = 1.0 if lk.lw is None else lk.lw[li]
        ga, gb = 1.0 - fa, 1.0 - fb
        g_fa = g_fb = 0.0
        corner = [[], [], [], []]
        for k in range(ch):
            g = g_val[k] * wl
            g_fa = g_fa + g * (gb * (t[2][k] - t[0][k]) + fb * (t[3][k] - t[1][k]))
            g_fb = g_fb + g * (ga * (t[1][k] - t[0][k]) + fa * (t[3][k] - t[2][k]))
            for q, wq in enumerate((ga * gb, ga * fb, fa * gb, fa * fb)):
                corner[q].append(g * wq)
        g_u = g_u + g_fa * da
        g_v = g_v + g_fb * db
        tcots.append(corner)
        if lk.lw is not None:
            per_level.append([_bilinear(t, fa, fb, k) for k in range(ch)])
    g_lf = None
    if lk.lw is not None:  # value = (1 - frac) v0 + frac v1, frac = lf - floor(lf) where unclamped
        g_lf = sum(g_val[k] * (per_level[1][k] - per_level[0][k]) for k in range(ch)) * lk.dlev
    return g_u, g_v, g_lf, tcots


def scatter_add(g_ref, lk: Lookup, tcots, ch: int, mask, interpret: bool):
    """Adds the texel cotangents ``tcots`` (:func:`value_bwd`) to the atlas's cotangent ``g_ref``."""
    for row, stride, corner in zip(lk.rows, lk.strides, tcots, strict=True):
        for idx, vals in zip(_offsets(row, stride), corner, strict=True):
            for k in range(ch):
                if not interpret:
                    plgpu.atomic_add(g_ref, (idx, jnp.int32(k)), vals[k], mask=mask)
                    continue
                val = jnp.where(mask, vals[k], 0.0)

                def lane(j, carry, idx=idx, val=val, k=k):
                    plgpu.atomic_add(g_ref, (idx[j], jnp.int32(k)), val[j])
                    return carry

                lax.fori_loop(0, idx.shape[0], lane, 0)


def footprint_bwd(g_lf, fp: Footprint, u, v):
    """The backward of :func:`footprint` for the cotangent ``g_lf`` of log2 of the footprint (P,):
    (g_u, g_v, g_s (3 (P,)): of the pixels' ray-plane products, g_nb: per neighbour (+x: the a
    columns, +y: the b columns) 3 (P,) of its offsets)."""
    g_d2 = jnp.where(fp.live & (fp.d2 > 1e-30), g_lf * 0.5 / (_LN2 * jnp.maximum(fp.d2, 1e-30)), 0.0)
    g_u = g_v = 0.0
    g_s = [0.0, 0.0, 0.0]
    g_nb = []
    for (nu, nv, inv), pick in zip(fp.nb, (fp.use_x, ~fp.use_x), strict=True):
        g = jnp.where(pick, g_d2, 0.0)
        g_nu, g_nv = 2.0 * (nu - u) * g, 2.0 * (nv - v) * g
        g_u, g_v = g_u - g_nu, g_v - g_nv
        g_t = (g_nu * inv, g_nv * inv, -(g_nu * nu + g_nv * nv) * inv)
        g_s = [a + b for a, b in zip(g_s, g_t, strict=True)]
        g_nb.append(g_t)
    return g_u, g_v, g_s, g_nb

