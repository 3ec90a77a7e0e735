"""The compositor as one Pallas GPU kernel (Triton lowering): one program per tile, one lane per pixel.

``RenderConfig(compositor="pallas")`` composites with :func:`composite_tiles` here instead of
:func:`.composite.composite_tiles`; both take and return the same arrays, so the rest of the
renderer is shared. The kernel is written for the GPU backend; on a CPU it runs in Pallas's
interpret mode (a test path).

Forward (:func:`_forward_kernel`): the grid is the image's tiles. A tile's program holds its P
pixels as (P,) vectors and walks its own depth-ordered list one splat at a time, a loop whose trip
count is the tile's list length, ended early once every pixel stopped (transmittance would fall
below 1e-4; checked every 16 splats, a block-wide reduction, as gsplat checks once per batch).
Each step reads the splat's packed row (:data:`projection.COLS`), evaluates the kernel, alpha,
depth and the distortion terms for the tile's pixels in registers, and blends them: nothing per
(splat, pixel) pair goes to memory. It writes the 9 accumulators, the final transmittance and the
dominant splat of every pixel, as the XLA compositor does, and how far into the tile's list each
pixel's last included pair is.

Backward (:func:`_backward_kernel`): the tile's list replayed back to front from the furthest of
its pixels' last pairs, each pixel from its own; the transmittance in front of a pair recovered by
division, ``T_i = T_{i+1} / (1 - a_i)`` (a_i <= 0.99), and with ``S_i = sum_{j>i} w_j (ct . f_j) +
ct_T T_final`` summed as the walk goes, ``d/da_i = T_i (ct . f_i) - S_i / (1 - a_i)`` (the XLA
compositor's formula, :func:`.composite._chunk_contrib_bwd`; summed from the back, S_i has no
cancellation where the XLA compositor forms it as a total minus the pairs in front). The
per-pair cotangents of the packed columns are summed over the tile's pixels and added to the
splat's gradient row with one atomic add per (splat, tile). The projection's VJP carries that row
on to the scene and to ``screen_offset``.

Textures (:mod:`.pallas_texture`): the RGB and alpha lookups of a pair, with the per-pixel mip
level (nearest or trilinear) and either coverage, are done in the same step, the splat's texture
addressing read as scalars and each pixel's 2 x 2 texels gathered from the flat atlas; the backward
adds each pixel's texel cotangents to the atlas's with atomic adds and carries the lookups' (u, v)
and footprint cotangents into the splat's row. As in the XLA compositor, only the pairs that can
reach alpha 1/255 (``opacity * G * max(alpha texels)``, with its 1e-3 margin) at pixels still
compositing read texels: the gathers of the others are masked off.

Triton's rules: every array value is a power-of-two vector (a tile's pixels, so ``tile_size`` is
a power of two); ``any`` is ``max`` of an int (no boolean reductions in the lowering); the
gradient buffers are zeros aliased to the outputs (atomic adds accumulate into them).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from . import pallas_texture as ptex
from .chunks import CompositeInputs, Static
from .config import ALPHA_MAX, ALPHA_MIN, T_MIN
from .kernel import UV_LIMIT
from .projection import COLS

_DIST_NEAR, _DIST_FAR = 0.2, 1000.0  # the 2DGS distortion's NDC depth mapping, as .composite
_M_SCALE = _DIST_FAR / (_DIST_FAR - _DIST_NEAR)
_F_ACC = 9  # rgb (3), depth, normal (3), D1, D2: the rows of the accumulator output
_STOP_EVERY = 16  # splats between the forward's checks whether every pixel of a tile has stopped
_ROW = 32  # the gradient row: the packed columns (at most COLS.width_prefilter = 29), padded


def _interpret() -> bool:
    """Run the kernel in Pallas's interpreter: on any backend but a GPU."""
    return jax.default_backend() != "gpu"


class _Pixels:
    """A tile's pixel centres (P,) and their offsets from the tile's centre (for the per-splat sums
    of the backward: smaller terms than the absolute coordinates, less cancellation)."""

    def __init__(self, st: Static, t, dtype):
        ts = st.config.tile_size
        p = lax.iota(jnp.int32, ts * ts)
        ix, iy = p % ts, p // ts
        half = 0.5 * ts
        self.cx = ((t % st.tiles_x) * ts).astype(dtype) + half   # the tile's centre
        self.cy = ((t // st.tiles_x) * ts).astype(dtype) + half
        self.xo = ix.astype(dtype) + (0.5 - half)                 # offsets from it
        self.yo = iy.astype(dtype) + (0.5 - half)
        self.x = self.cx + self.xo
        self.y = self.cy + self.yo


class _Refs(NamedTuple):
    """The kernels' inputs: tile lists, packed splats and, per bank present, which splats have a
    texture to look up (int32 (C,)) and the flat atlas (M, ch); the texture addressing."""

    start: Any
    count: Any
    ids: Any
    pk: Any
    meta: Any = None
    peak: Any = None
    rgb_has: Any = None
    rgb: Any = None
    alpha_has: Any = None
    alpha: Any = None


def _split_refs(st: Static, refs) -> tuple[_Refs, list]:
    """The kernel's arguments as :class:`_Refs` (inputs, in :func:`_inputs`' order) and the rest."""
    n = 4 + (2 if st.rgb or st.alpha else 0) + 2 * st.rgb + 2 * st.alpha
    ins = list(refs[:n])
    r = dict(start=ins[0], count=ins[1], ids=ins[2], pk=ins[3])
    rest = ins[4:]
    if st.rgb or st.alpha:
        r["meta"], r["peak"] = rest.pop(0), rest.pop(0)
    if st.rgb:
        r["rgb_has"], r["rgb"] = rest.pop(0), rest.pop(0)
    if st.alpha:
        r["alpha_has"], r["alpha"] = rest.pop(0), rest.pop(0)
    return _Refs(**r), list(refs[n:])


def _inputs(st: Static, packed, rgb_texels, alpha_texels, lists):
    """The kernels' inputs in :class:`_Refs` order; ``lists`` (tile_start, binned, ids_sorted,
    tex_meta, peak, rgb_has, alpha_has)."""
    start, binned, ids, meta, peak, rgb_has, alpha_has = lists
    ins = [start, binned, ids, packed]
    if st.rgb or st.alpha:
        ins += [meta, peak]
    if st.rgb:
        ins += [rgb_has, rgb_texels]
    if st.alpha:
        ins += [alpha_has, alpha_texels]
    return ins


def _row(st: Static, refs: _Refs, g):
    """The packed columns of splat g, as scalars (a dict of name -> scalar or tuple), and its
    texture addressing per bank present ("rgb_tex", "alpha_tex": :func:`.pallas_texture.bank_row`)."""
    pk_ref, prefilter = refs.pk, st.prefilter

    def col(i):
        return pk_ref[g, i]

    def cs(sl):
        return tuple(col(i) for i in range(sl.start, sl.stop))

    r: dict[str, Any] = dict(a=cs(COLS.a), b=cs(COLS.b), c=cs(COLS.c), m2=cs(COLS.m2), mu=cs(COLS.mu),
             opacity=col(COLS.opacity), colour=cs(COLS.colour), normal=cs(COLS.normal), depth=col(COLS.depth))
    if prefilter:
        r.update(conic=cs(COLS.conic), coverage=col(COLS.coverage), support=cs(COLS.support))
    if st.rgb or st.alpha:
        r["peak"] = refs.peak[g]
    if st.rgb:
        r["rgb_tex"] = ptex.bank_row(refs.meta, refs.rgb_has, g, 0)
    if st.alpha:
        r["alpha_tex"] = ptex.bank_row(refs.meta, refs.alpha_has, g, 1 if st.rgb else 0)
    return r


def _geometry(r, px: _Pixels, prefilter: bool):
    """The pair terms of one splat (row r) at the tile's pixels, each (P,): as
    :func:`.kernel.geometry_terms` (G, z, u, v, ok, inv, use3) for one splat, and the ray-plane
    products s (3 (P,))."""
    s0, s1, s2 = (px.x * r["a"][i] + px.y * r["b"][i] + r["c"][i] for i in range(3))
    ok = jnp.abs(s2) * UV_LIMIT > jnp.maximum(jnp.abs(s0), jnp.abs(s1))
    inv = 1.0 / jnp.where(ok, s2, 1.0)
    u = jnp.where(ok, s0 * inv, 0.0)
    v = jnp.where(ok, s1 * inv, 0.0)
    dx, dy = px.x - r["mu"][0], px.y - r["mu"][1]
    if prefilter:
        p, q, t = r["conic"]
        sa, sb, sc = r["support"]
        use3 = ok & ((sa * dx + 2.0 * sb * dy) * dx + sc * dy * dy <= 1.0)
        G = jnp.exp(-0.5 * jnp.where(use3, (p * u + 2.0 * q * v) * u + t * v * v, 1e8))
    else:
        rho3d = jnp.where(ok, u * u + v * v, 1e8)
        rho2d = 2.0 * (dx * dx + dy * dy)
        use3 = rho3d <= rho2d
        G = jnp.exp(-0.5 * jnp.minimum(rho3d, rho2d))
    m = r["m2"]
    z = jnp.where(use3, m[0] * u + m[1] * v + m[2], r["depth"])
    return (G, z, u, v, ok, inv, use3), (s0, s1, s2)


class _Tex(NamedTuple):
    """One splat's texture lookups at the tile's pixels (see :mod:`.pallas_texture`): the footprint
    (or None), per bank its lookups and gathered texels (or None), the RGB offsets (3 (P,), zero
    where the splat has none) and the alpha factor (1 where it has none), or None."""

    fp: Any
    rgb: Any
    alpha: Any
    offs: Any
    a_tex: Any


def _textures(st: Static, refs: _Refs, r, geo, s, active, amin) -> _Tex | None:
    """The texture lookups of splat r (:func:`_row`) at the tile's pixels: those of the pixels
    ``active`` (P,) where the pair can reach alpha ``amin`` (as :func:`.texture_lookup.texture_passes`);
    the others read no texels (their values are then 0, and the pair is not composited)."""
    if not (st.rgb or st.alpha):
        return None
    G, _, u, v, ok, _, _ = geo
    need = active & (r["opacity"] * r["peak"] * G >= amin * (1.0 - 1e-3))
    fp = ptex.footprint(s, r, u, v, ok) if st.need_footprint else None
    lfp = None if fp is None else fp.log2_fp
    cfg = st.config
    rgb = alpha = offs = a_tex = None

    def looked_up(bank, texels_ref, channels, mip):  # (lookup, texels, has) of the pairs that need one
        has = need & bank["has"]
        lk = ptex.lookup(bank, u, v, lfp, cfg, mip)
        return lk, ptex.gather(texels_ref, lk, channels, has), has

    if st.rgb:
        rgb = lk, texels, has = looked_up(r["rgb_tex"], refs.rgb, 3, st.rgb_mip)
        offs = [jnp.where(has, o, 0.0) for o in ptex.value(texels, lk, 3)]
    if st.alpha:
        alpha = lk, texels, _ = looked_up(r["alpha_tex"], refs.alpha, 1, st.alpha_mip)
        a_tex = jnp.where(r["alpha_tex"]["has"], ptex.value(texels, lk, 1)[0], 1.0)  # 0 where not needed
    return _Tex(fp, rgb, alpha, offs, a_tex)


def _alpha(st: Static, refs: _Refs, r, px: _Pixels, active):
    """One splat's alpha at the tile's pixels: the geometry (:func:`_geometry`) and ray-plane
    products, the texture lookups (:func:`_textures`), alpha before the cap, alpha (0 where not
    kept), whether kept, and the distortion's safe depth and NDC depth (all (P,)); as
    :func:`.composite._contrib_terms`."""
    geo, s = _geometry(r, px, st.prefilter)
    G, z = geo[0], geo[1]
    amin = ALPHA_MIN * r["coverage"] if st.prefilter else ALPHA_MIN
    tx = _textures(st, refs, r, geo, s, active, amin)
    a_raw = r["opacity"] * G
    if st.alpha:
        assert tx is not None
        a_raw = a_raw * tx.a_tex
    a = jnp.minimum(a_raw, ALPHA_MAX)
    keep = (a >= amin) & (z > st.config.near)
    a = jnp.where(keep, a, 0.0)
    zs = jnp.where(keep, z, 1.0)
    m = _M_SCALE * (1.0 - _DIST_NEAR / zs)
    return geo, s, tx, a_raw, a, keep, zs, m


def _colour(st: Static, r, tx: _Tex | None):
    """The splat's colour at the tile's pixels: its SH colour plus its RGB texture's offsets."""
    if not st.rgb:
        return r["colour"]
    assert tx is not None
    return tuple(c + o for c, o in zip(r["colour"], tx.offs, strict=True))


def _any(mask):
    """Whether any lane of a boolean (P,) vector is set (Triton lowers no boolean reductions)."""
    return jnp.max(mask.astype(jnp.int32)) > 0


def _forward_kernel(st: Static, *all_refs):
    refs, (out_ref, idx_ref) = _split_refs(st, all_refs)
    t = pl.program_id(0)
    dt = out_ref.dtype
    P = st.config.tile_size ** 2
    px = _Pixels(st, t, dt)
    start, count = refs.start[t], refs.count[t]

    def cond(state):
        return (state[0] < count) & _any(~state[2])

    def step(_, state):  # one splat of the list (none past its end)
        i, T, done, last, acc, best_w, best_id = state
        valid = i < count
        g = refs.ids[start + jnp.minimum(i, count - 1)]
        r = _row(st, refs, g)
        geo, _, tx, _, a, _, _, m = _alpha(st, refs, r, px, ~done & valid)
        a = jnp.where(valid, a, 0.0)
        t_next = T * (1.0 - a)
        stop = t_next < T_MIN
        include = ~done & ~stop & valid
        w = jnp.where(include, a * T, 0.0)
        feats = (*_colour(st, r, tx), geo[1], *r["normal"], m, m * m)
        acc = tuple(s + w * f for s, f in zip(acc, feats, strict=True))
        better = w > best_w
        return (i + 1, jnp.where(include, t_next, T), done | stop, jnp.where(include, i + 1, last), acc,
                jnp.maximum(best_w, w), jnp.where(better, g, best_id))

    def body(state):  # the tile's pixels synchronise (a block-wide reduction) once per this many
        return lax.fori_loop(0, _STOP_EVERY, step, state)

    zeros = jnp.zeros((P,), dt)
    init = (jnp.int32(0), jnp.ones((P,), dt), jnp.zeros((P,), jnp.bool_), jnp.zeros((P,), jnp.int32),
            (zeros,) * _F_ACC, zeros, jnp.full((P,), -1, jnp.int32))
    _, T, _, last, acc, _, best = lax.while_loop(cond, body, init)
    for k in range(_F_ACC):
        out_ref[t, k, :] = acc[k]
    out_ref[t, _F_ACC, :] = T
    idx_ref[t, 0, :] = best
    idx_ref[t, 1, :] = last


def _pallas_call(st: Static, interpret: bool, kernel, out_shape, aliases=None):
    """``kernel`` (partial of ``st``) over the image's tiles, one program each."""
    warps = max(1, min(8, st.config.tile_size ** 2 // 32))  # one lane per pixel, at most 8 warps
    return pl.pallas_call(functools.partial(kernel, st), out_shape=out_shape, grid=(st.num_tiles,),
                          input_output_aliases=aliases or {}, interpret=interpret,
                          compiler_params=plgpu.CompilerParams(num_warps=warps, num_stages=1))


def _forward(st: Static, interpret: bool, packed, rgb_texels, alpha_texels, lists):
    """(out (T, 10, P): the 9 accumulators and the final transmittance; idx (T, 2, P) int32: the
    dominant splat and how far into the tile's list the pixel's last included pair is)."""
    P = st.config.tile_size ** 2
    out_shape = (jax.ShapeDtypeStruct((st.num_tiles, _F_ACC + 1, P), packed.dtype),
                 jax.ShapeDtypeStruct((st.num_tiles, 2, P), jnp.int32))
    return _pallas_call(st, interpret, _forward_kernel, out_shape)(
        *_inputs(st, packed, rgb_texels, alpha_texels, lists))


def _backward_kernel(st: Static, *all_refs, interpret: bool):
    refs, rest = _split_refs(st, all_refs)
    ct_ref, fin_ref, last_ref = rest[:3]
    n_out = 1 + st.rgb + st.alpha
    g_ref, *g_tex = rest[3 + n_out:]  # the outputs (the zeros they alias come first)
    g_rgb_ref = g_tex.pop(0) if st.rgb else None
    g_alpha_ref = g_tex.pop(0) if st.alpha else None
    t = pl.program_id(0)
    dt = ct_ref.dtype
    px = _Pixels(st, t, dt)
    start = refs.start[t]
    ct = [ct_ref[t, k, :] for k in range(_F_ACC)]
    ct_rgb, ct_z, ct_nrm, ct_m, ct_m2 = ct[0:3], ct[3], ct[4:7], ct[7], ct[8]
    t_final, ct_t = fin_ref[t, 0, :], fin_ref[t, 1, :]
    last = last_ref[t, 1, :]
    end = jnp.max(last)
    lane = lax.iota(jnp.int32, _ROW)

    def body(j, state):
        T, behind = state
        i = end - 1 - j
        g = refs.ids[start + i]
        r = _row(st, refs, g)
        live = i < last                             # the pixel's pairs up to its last included one
        geo, s, tx, a_raw, a, keep, zs, m = _alpha(st, refs, r, px, live)
        G, z, u, v, ok, inv, use3 = geo
        a = jnp.where(live, a, 0.0)
        T = T / (1.0 - a)                           # the transmittance in front of the pair
        w = a * T
        # The pair's features against the cotangents, and the compositing's backward.
        colour = _colour(st, r, tx)
        g_w = (sum(c * f for c, f in zip(ct_rgb, colour, strict=True)) + ct_z * z
               + sum(c * f for c, f in zip(ct_nrm, r["normal"], strict=True)) + (ct_m + ct_m2 * m) * m)
        g_a = g_w * T - behind / (1.0 - a)
        g_a = jnp.where(live & keep & (a_raw < ALPHA_MAX), g_a, 0.0)
        behind = behind + w * g_w
        a_tex = 1.0
        if st.alpha:
            assert tx is not None
            a_tex = tx.a_tex
        g_G = g_a * r["opacity"] * a_tex
        dm_dz = _M_SCALE * _DIST_NEAR / (zs * zs)
        g_z = w * (ct_z + (ct_m + 2.0 * ct_m2 * m) * dm_dz)
        # The textures' backward: the cotangents of (u, v), of the footprint's rays, of the texels.
        g_u_tex = g_v_tex = 0.0
        g_s_fp, g_nb = [0.0, 0.0, 0.0], None
        if tx is not None:
            g_lf = 0.0
            for bank, g_val, ch, g_tex_ref in ((tx.rgb, [w * c for c in ct_rgb], 3, g_rgb_ref),
                                               (tx.alpha, [g_a * r["opacity"] * G], 1, g_alpha_ref)):
                if bank is None:
                    continue
                lk, texels, has = bank
                g_val = [jnp.where(has, gv, 0.0) for gv in g_val]
                gu, gv_, glf, tcots = ptex.value_bwd(g_val, texels, lk, ch)
                g_u_tex, g_v_tex = g_u_tex + gu, g_v_tex + gv_
                if glf is not None:
                    g_lf = g_lf + glf
                ptex.scatter_add(g_tex_ref, lk, tcots, ch, has & live, interpret)
            if tx.fp is not None and st.config.mip == "trilinear":
                gu, gv_, g_s_fp, g_nb = ptex.footprint_bwd(g_lf, tx.fp, u, v)
                g_u_tex, g_v_tex = g_u_tex + gu, g_v_tex + gv_
        # The kernel's backward (as .kernel.chunk_geometry_bwd, for one splat).
        g_rho = -0.5 * g_G * G
        g_rho3 = jnp.where(use3 & ok, g_rho, 0.0)
        g_z3 = jnp.where(use3, g_z, 0.0)
        m2 = r["m2"]
        if st.prefilter:
            p, q, tt = r["conic"]
            qu, qv = p * u + q * v, q * u + tt * v
        else:
            qu, qv = u, v
        g_u = jnp.where(ok, 2.0 * qu * g_rho3 + m2[0] * g_z3 + g_u_tex, 0.0)
        g_v = jnp.where(ok, 2.0 * qv * g_rho3 + m2[1] * g_z3 + g_v_tex, 0.0)
        g_s = [a_ + b_ for a_, b_ in zip((g_u * inv, g_v * inv, -(g_u * u + g_v * v) * inv), g_s_fp, strict=True)]
        cols = {}
        for k in range(3):  # s_k = x a_k + y b_k + c_k: the sums of g_s[k] weighted by x, y and 1
            s1 = jnp.sum(g_s[k])
            cols[COLS.a.start + k] = jnp.sum(g_s[k] * px.xo) + px.cx * s1
            cols[COLS.b.start + k] = jnp.sum(g_s[k] * px.yo) + px.cy * s1
            cols[COLS.c.start + k] = s1
        if g_nb is not None:  # the footprint's neighbour rays: s + a (one pixel over) and s + b (one down)
            for k in range(3):
                cols[COLS.a.start + k] = cols[COLS.a.start + k] + jnp.sum(g_nb[0][k])
                cols[COLS.b.start + k] = cols[COLS.b.start + k] + jnp.sum(g_nb[1][k])
        cols[COLS.m2.start] = jnp.sum(g_z3 * u)
        cols[COLS.m2.start + 1] = jnp.sum(g_z3 * v)
        cols[COLS.m2.start + 2] = jnp.sum(g_z3)
        if not st.prefilter:  # d rho2d / d mu = -4 (x - mu)
            h = jnp.where(use3, 0.0, g_rho)
            s1 = jnp.sum(h)
            cols[COLS.mu.start] = -4.0 * (jnp.sum(h * px.xo) + (px.cx - r["mu"][0]) * s1)
            cols[COLS.mu.start + 1] = -4.0 * (jnp.sum(h * px.yo) + (px.cy - r["mu"][1]) * s1)
        cols[COLS.opacity] = jnp.sum(g_a * G * a_tex)
        for k in range(3):
            cols[COLS.colour.start + k] = jnp.sum(w * ct_rgb[k])
            cols[COLS.normal.start + k] = jnp.sum(w * ct_nrm[k])
        cols[COLS.depth] = jnp.sum(g_z - g_z3)
        if st.prefilter:
            cols[COLS.conic.start] = jnp.sum(g_rho3 * u * u)
            cols[COLS.conic.start + 1] = jnp.sum(2.0 * g_rho3 * u * v)
            cols[COLS.conic.start + 2] = jnp.sum(g_rho3 * v * v)
        row = jnp.zeros((_ROW,), dt)
        for k, val in cols.items():
            row = row + jnp.where(lane == k, val, 0.0)
        plgpu.atomic_add(g_ref, (g, pl.ds(jnp.int32(0), _ROW)), row)
        return T, behind

    lax.fori_loop(0, end, body, (t_final, ct_t * t_final))


def _backward(st: Static, interpret: bool, packed, rgb_texels, alpha_texels, lists, ct, fin, idx):
    """The cotangents of the packed splats (C, F) and of the atlases' texels (None for a bank not
    present) for accumulator cotangents ct (T, 9, P), fin (T, 2, P) the final transmittance and its
    cotangent, idx (T, 2, P) the forward's (:func:`_forward`)."""
    C, F = packed.shape
    ins = _inputs(st, packed, rgb_texels, alpha_texels, lists) + [ct, fin, idx]
    outs = [jnp.zeros((C, _ROW), packed.dtype)]
    if st.rgb:
        outs.append(jnp.zeros_like(rgb_texels))
    if st.alpha:
        outs.append(jnp.zeros_like(alpha_texels))
    call = _pallas_call(st, interpret, functools.partial(_backward_kernel, interpret=interpret),
                        [jax.ShapeDtypeStruct(o.shape, o.dtype) for o in outs],
                        aliases={len(ins) + k: k for k in range(len(outs))})
    g = list(call(*ins, *outs))
    g_pk = g.pop(0)[:, :F]
    return g_pk, g.pop(0) if st.rgb else None, g.pop(0) if st.alpha else None


def _outputs(out, idx):
    """The kernel's (T, 10, P) rows as composite_tiles' (acc (T, P, 9), t_final (T, P), best)."""
    return jnp.swapaxes(out[:, :_F_ACC], 1, 2), out[:, _F_ACC], idx[:, 0]


def _composite(st: Static, interpret: bool, packed, rgb_texels, alpha_texels, lists):
    """The kernel's forward on the inputs without their gradients, its outputs given the backward
    kernel as derivative by :func:`_with_backward` (a ``jax.custom_vjp`` function inside a traced
    program is traced twice under differentiation, as itself and as its forward rule; this way the
    forward kernel is traced once: see :func:`.composite.composite_tiles`)."""
    sg = lax.stop_gradient
    out, idx = _forward(st, interpret, sg(packed), sg(rgb_texels), sg(alpha_texels), lists)
    acc, t_final, best = _outputs(out, idx)
    # (jax.custom_vjp's type hides _with_backward's return type, a pair of arrays)
    acc, t_final = _with_backward(  # pyright: ignore[reportGeneralTypeIssues]
        st, interpret, packed, rgb_texels, alpha_texels, lists, acc, t_final, idx)
    return acc, t_final, best


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _with_backward(st: Static, interpret: bool, packed, rgb_texels, alpha_texels, lists, acc, t_final, idx):
    """``(acc, t_final)`` unchanged (the forward kernel's outputs for these inputs, ``idx`` its
    largest-weight rows), with the backward kernel as their derivative."""
    return acc, t_final


def _with_backward_fwd(st, interpret, packed, rgb_texels, alpha_texels, lists, acc, t_final, idx):
    return (acc, t_final), (packed, rgb_texels, alpha_texels, lists, t_final, idx)


def _with_backward_bwd(st, interpret, res, cts):
    packed, rgb_texels, alpha_texels, lists, t_final, idx = res
    ct_acc, ct_t = cts
    fin = jnp.stack([t_final, ct_t], axis=1)
    g_pk, g_rgb, g_alpha = _backward(st, interpret, packed, rgb_texels, alpha_texels, lists,
                                     jnp.swapaxes(ct_acc, 1, 2), fin, idx)
    # acc, t_final and idx come from inputs without gradients: zero cotangents (None).
    return g_pk, g_rgb, g_alpha, jax.tree_util.tree_map(lambda _: None, lists), None, None, None


_with_backward.defvjp(_with_backward_fwd, _with_backward_bwd)


def composite_tiles(st: Static, packed, rgb_texels, alpha_texels, ctx: CompositeInputs, interpret: bool | None = None):
    """:func:`.composite.composite_tiles` as one Pallas kernel: the same arguments and outputs
    (acc (T, P, 9), t_final (T, P), best (T, P) int32), differentiable in ``packed`` and the
    atlases' texels.

    Args:
      interpret: run in Pallas's interpreter; None: on any backend but a GPU.
    """
    if interpret is None:
        interpret = _interpret()

    def as_int(has):
        return None if has is None else has.astype(jnp.int32)

    textured = st.rgb or st.alpha
    lists = (ctx.tile_start, ctx.binned, ctx.ids_sorted, ctx.tex_meta,
             ctx.peak.astype(packed.dtype) if textured else None, as_int(ctx.rgb_has), as_int(ctx.alpha_has))
    return _composite(st, interpret, packed, rgb_texels if st.rgb else None, alpha_texels if st.alpha else None,
                      lists)
