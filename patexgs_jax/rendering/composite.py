"""Compositing: every tile's list front to back, in chunks, with a hand-written backward.

:func:`composite_tiles` walks each tile's list in chunks of ``RenderConfig.chunk`` splats (pixels x
chunk at a time, :mod:`.chunks`) and stops the tile once every pixel saturated or the list ended,
so the work follows the splats that actually contribute. Its backward (``jax.custom_vjp``) re-walks
the chunks and stores nothing per pair: backward memory is the inputs plus a few per-pixel accumulators.
Within a chunk, the compositing's backward (:func:`_chunk_contrib_bwd`) and the kernel's
(:func:`kernel.chunk_geometry_bwd`) are derived by hand: fewer passes over the (c, B, P) block than
autodiff's, and the per-splat sums as matrix products. The texture lookups' backward is autodiff's
(:func:`texture_lookup.texture_bwd`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .chunks import CompositeInputs, Static, batch_state, chunk_slots, cols, per_slot, prefix_sum_slots, tile_batches
from .config import ALPHA_MAX, T_MIN
from .kernel import alpha_min, chunk_geometry, chunk_geometry_bwd, geometry_terms
from .projection import COLS
from .texture_lookup import texture_bwd, texture_fwd, texture_passes, unpair

_DIST_NEAR, _DIST_FAR = 0.2, 1000.0  # the NDC depth mapping of the 2DGS distortion loss
_F_ACC = 9  # per-pixel accumulators: rgb (3), depth (1), normal (3), D1 = sum w m, D2 = sum w m^2
_LOG_T_MIN = math.log(T_MIN)


class _Terms(NamedTuple):
    """Per-pair terms of a batch's chunk, each (c, B, P), shared by :func:`_chunk_contrib` and its
    hand-derived backward :func:`_chunk_contrib_bwd`."""

    a_raw: jax.Array     # opacity * G (* alpha texture) before the cap
    a_tex: jax.Array | None  # the alpha texture factor (1 where a splat has none), None without
    keep: jax.Array      # the pair is composited (alpha >= 1/255, in front of near, a real slot)
    a: jax.Array         # alpha, zero where not kept
    log1m: jax.Array     # log(1 - a)
    cum: jax.Array       # inclusive prefix sum of log1m along the chunk
    include: jax.Array   # compositing has not stopped before the pair
    trans: jax.Array     # transmittance in front of the pair (0 where not included)
    w: jax.Array         # a * trans, the pair's blending weight
    zs: jax.Array        # z where kept, else 1 (the distortion's NDC depth is safe everywhere)
    m: jax.Array         # the NDC depth of the distortion loss


def _contrib_terms(st: Static, ctx: CompositeInputs, pk, G, z, a_tex, gid, valid, log_t_in, done_in) -> _Terms:
    """The :class:`_Terms` of a batch's chunk; arguments as :func:`_chunk_contrib`'s."""
    cfg = st.config
    a_raw = cols(pk)[COLS.opacity] * G
    if st.alpha:
        a_tex = jnp.where(per_slot(ctx.need("alpha_has")[gid]), a_tex, 1.0)
        a_raw = a_raw * a_tex
    a = jnp.clip(a_raw, 0.0, ALPHA_MAX)
    keep = per_slot(valid) & (a >= alpha_min(st, pk)) & (z > cfg.near)
    a = jnp.where(keep, a, 0.0)
    log1m = jnp.log1p(-a)
    cum = prefix_sum_slots(log1m)
    include = ~done_in & (log_t_in + cum >= _LOG_T_MIN)
    trans = jnp.where(include, jnp.exp(log_t_in + cum - log1m), 0.0)
    zs = jnp.where(keep, z, 1.0)
    m = _DIST_FAR / (_DIST_FAR - _DIST_NEAR) * (1.0 - _DIST_NEAR / zs)
    return _Terms(a_raw, a_tex if st.alpha else None, keep, a, log1m, cum, include, trans, a * trans, zs, m)


def _chunk_contrib(st: Static, ctx: CompositeInputs, pk, G, z, offs, a_tex, gid, valid, log_t_in, done_in):
    """A batch's chunk contribution.

    Args:
      pk: (B, c, F) packed splats; G, z (c, B, P); offs: None or the RGB texture offsets, a list
        of 3 (c, B, P); a_tex: None or the alpha texture values (c, B, P); gid, valid (B, c);
        log_t_in (B, P) log transmittance before the chunk; done_in (B, P) compositing already
        stopped.
    Returns:
      ((dacc (B, P, 9), log_t_out (B, P)), (done_out (B, P), w (c, B, P)))
    """
    t = _contrib_terms(st, ctx, pk, G, z, a_tex, gid, valid, log_t_in, done_in)
    w = t.w
    cn = jnp.einsum("cbp,bcf->bpf", w, pk[:, :, COLS.colour_normal],  # colour and normal
                    precision=lax.Precision.HIGHEST)
    rgb = cn[..., :3]
    if st.rgb:
        has = per_slot(ctx.need("rgb_has")[gid])
        rgb = rgb + jnp.stack([jnp.sum(jnp.where(has, w * o, 0.0), axis=0) for o in offs], axis=-1)
    wm = w * t.m
    dacc = jnp.concatenate([rgb, jnp.sum(w * z, axis=0)[..., None], cn[..., 3:],
                            jnp.stack([jnp.sum(wm, axis=0), jnp.sum(wm * t.m, axis=0)], axis=-1)], axis=-1)
    log_t_out, done_out = _contrib_state(t, log_t_in, done_in)
    return (dacc, log_t_out), (done_out, w)


def _contrib_state(t: _Terms, log_t_in, done_in):
    """The pixels' log transmittance and stop flag (B, P) after a chunk of terms ``t``."""
    return (log_t_in + jnp.sum(jnp.where(t.include, t.log1m, 0.0), axis=0),
            done_in | (log_t_in + t.cum[-1] < _LOG_T_MIN))


def _chunk_contrib_bwd(st: Static, ctx: CompositeInputs, pk, G, z, offs, a_tex, gid, valid, log_t_in, done_in,
                       ct_acc, dot_in, base_term):
    """The backward of :func:`_chunk_contrib`, derived by hand (fewer passes over the (c, B, P)
    block than autodiff's, which would also recompute the accumulators to form ``ct_acc . acc``),
    and the pixels' state after the chunk.

    Args: those of :func:`_chunk_contrib`, and ct_acc (B, P, 9) the pixels' accumulator cotangents,
      dot_in (B, P) ``ct_acc . acc`` through the chunks before this one, base_term (B, P)
      ``ct_acc . acc_final + ct_T * T_final`` (see :func:`composite_tiles`).
    Returns:
      (log_t_out, done_out, dot_out) (B, P) the state after the chunk, and the cotangents
      g_pk (B, c, F), g_G, g_z (c, B, P) and (g_offs, g_a_tex): a list of 3 (c, B, P) or None,
      (c, B, P) or None.

    With w_i = a_i T_i, T_i = T_in prod_{j<i} (1 - a_j), f_i the pair's 9 accumulated features and
    L = log T_out: ``d/da_i = T_i (ct . f_i) - (sum_{j>i} w_j (ct . f_j) + dL) / (1 - a_i)`` for
    an included pair, 0 otherwise (a pair after the stop has only stopped pairs after it).
    """
    t = _contrib_terms(st, ctx, pk, G, z, a_tex, gid, valid, log_t_in, done_in)
    w = t.w
    ct_rgb, ct_z, ct_nrm, ct_m, ct_m2 = (ct_acc[..., 0:3], ct_acc[..., 3], ct_acc[..., 4:7],
                                         ct_acc[..., 7], ct_acc[..., 8])
    # ct . f per pair.
    ct_cn = jnp.concatenate([ct_rgb, ct_nrm], axis=-1)         # (B, P, 6) as pk[..., COLS.colour_normal]
    hi = lax.Precision.HIGHEST
    g_w = (jnp.einsum("bpf,bcf->cbp", ct_cn, pk[:, :, COLS.colour_normal], precision=hi) + ct_z * z
           + (ct_m + ct_m2 * t.m) * t.m)
    g_offs = None
    if st.rgb:
        has = per_slot(ctx.need("rgb_has")[gid])
        g_w = g_w + sum(jnp.where(has, ct_rgb[..., i] * o, 0.0) for i, o in enumerate(offs))
        g_offs = [jnp.where(has, w * ct_rgb[..., i], 0.0) for i in range(3)]
    wf = g_w * w                                                                # w_i (ct . f_i)
    dot_out = dot_in + jnp.sum(wf, axis=0)                                      # ct . acc so far
    g_log_t = base_term - dot_out                                               # (B, P)
    log_t_out, done_out = _contrib_state(t, log_t_in, done_in)
    c = w.shape[0]
    later = jnp.triu(jnp.ones((c, c), w.dtype), 1)    # later[i, j] = 1 where j > i
    behind = jnp.matmul(later, wf.reshape(c, -1), precision=hi).reshape(wf.shape)  # sum_{j>i} w_j (ct . f_j)
    g_a = g_w * t.trans - (behind + jnp.where(t.include, g_log_t, 0.0)) / (1.0 - t.a)
    g_a = jnp.where(t.keep & (t.a_raw < ALPHA_MAX), g_a, 0.0)                  # d/d a_raw
    op = cols(pk)[COLS.opacity]
    g_atex = None
    if st.alpha:
        a_tex = t.a_tex
        assert a_tex is not None  # _contrib_terms sets it when st.alpha
        g_G = g_a * op * a_tex
        g_op = jnp.sum(g_a * G * a_tex, axis=-1)
        g_atex = jnp.where(per_slot(ctx.need("alpha_has")[gid]), g_a * op * G, 0.0)
    else:
        g_G = g_a * op
        g_op = jnp.sum(g_a * G, axis=-1)
    dm_dz = _DIST_FAR / (_DIST_FAR - _DIST_NEAR) * _DIST_NEAR / (t.zs * t.zs)
    g_z = w * (ct_z + (ct_m + 2.0 * ct_m2 * t.m) * dm_dz)
    g_pk = jnp.zeros_like(pk)
    g_pk = g_pk.at[:, :, COLS.opacity].set(g_op.T)
    g_pk = g_pk.at[:, :, COLS.colour_normal].set(jnp.einsum("cbp,bpf->bcf", w, ct_cn, precision=hi))
    return (log_t_out, done_out, dot_out), (g_pk, g_G, g_z, (g_offs, g_atex))


def _chunk_fwd(st: Static, ctx: CompositeInputs, packed, tb, k, x, y, log_t, done):
    """Chunk k of a batch of tiles ``tb`` (B,), forward: x, y (B, P) pixel centres, log_t, done
    (B, P) the state before it. Returns ((dacc (B, P, 9), log_t (B, P)), (done (B, P), w (c, B, P)),
    gid (B, c)). The chunk's per-pair blocks are (c, B, P) (see :mod:`.chunks`)."""
    gid, valid = jax.vmap(lambda t: chunk_slots(st, ctx, t, k))(tb)
    pk = packed[gid]
    G, z = chunk_geometry(pk, x, y, st.prefilter, st.billboard, st.object_space)
    offs, a_tex = None, None
    if st.rgb or st.alpha:
        passes = texture_passes(st, ctx, pk, gid, valid, G, done)
        offs, a_tex = texture_fwd(st, ctx, pk, gid, x, y, passes, G.shape)
    out = _chunk_contrib(st, ctx, pk, G, z, offs, a_tex, gid, valid, log_t, done)
    return out, gid


def _composite_fwd_impl(st: Static, packed, rgb_texels, alpha_texels, ctx: CompositeInputs):
    npx = st.config.tile_size ** 2
    dt = packed.dtype
    B = st.batch

    def batch(tb):
        (x, y), nch = batch_state(st, ctx, tb, dt)

        def cond(state):
            return jnp.any((state[0] < nch) & ~jnp.all(state[2], axis=1))

        def body(state):
            k, log_t, done, acc, best_w, best_id = state
            ((dacc, log_t2), (done2, w)), gid = _chunk_fwd(st, ctx, packed, tb, k, x, y, log_t, done)
            wmax = jnp.max(w, axis=0)
            arg = jnp.take_along_axis(gid, jnp.argmax(w, axis=0), axis=1)
            better = wmax > best_w
            return (k + 1, log_t2, done2, acc + dacc, jnp.maximum(best_w, wmax),
                    jnp.where(better, arg, best_id))

        init = (jnp.int32(0), jnp.zeros((B, npx), dt), jnp.zeros((B, npx), bool),
                jnp.zeros((B, npx, _F_ACC), dt), jnp.zeros((B, npx), dt), jnp.full((B, npx), -1, jnp.int32))
        _, log_t, _, acc, _, best = lax.while_loop(cond, body, init)
        return acc, jnp.exp(log_t), best

    batches = tile_batches(st, ctx)
    acc, t_final, best = lax.map(batch, batches)
    flat = batches.reshape(-1)
    T = st.num_tiles

    def unsort(v):  # duplicated padding tiles write identical values
        return jnp.zeros((T,) + v.shape[2:], v.dtype).at[flat].set(v.reshape((-1,) + v.shape[2:]))

    return unsort(acc), unsort(t_final), unsort(best)


def composite_tiles(st: Static, packed, rgb_texels, alpha_texels, ctx: CompositeInputs):
    """All tiles, front to back in chunks of ``config.chunk`` splats, stopping each tile once every
    pixel's transmittance fell below 1e-4 or its list is exhausted; ``config.tile_batch`` tiles
    (of similar list lengths) advance together.

    Args:
      st: static settings.
      packed: (C, F) per-splat quantities (differentiable).
      rgb_texels, alpha_texels: (M, 3) / (M, 1) flat atlases (:class:`textures.Atlas`) or None
        (differentiable).
      ctx: the tile lists and texture addressing, without gradient (:class:`.chunks.CompositeInputs`,
        every field's shape and dtype there).
    Returns:
      acc (T, P, 9) accumulators, t_final (T, P), best (T, P) int32 id of the largest-weight splat.

    The backward pass walks each tile's chunks front to back again; a chunk's influence on everything
    behind it is through its output transmittance, whose cotangent is
    ``ct_acc . (acc_final - acc_through_chunk) + ct_T * T_final`` (later contributions are linear in
    it), so nothing per pair is stored: the residuals are the inputs and the per-pixel outputs.

    The forward is computed on the inputs without their gradients, and :func:`_with_backward`
    attaches the backward to its outputs: inside a traced program (a jitted renderer called by a
    training step, a loop's body) a ``jax.custom_vjp`` function is traced twice under
    differentiation, once as itself and once as its forward rule; this way the compositor's forward
    is traced once, and the custom rule's primal and forward only pass their outputs through.
    """
    sg = lax.stop_gradient
    acc, t_final, best = _composite_fwd_impl(st, sg(packed), sg(rgb_texels), sg(alpha_texels), ctx)
    # (jax.custom_vjp's type hides _with_backward's return type, a pair of arrays)
    acc, t_final = _with_backward(  # pyright: ignore[reportGeneralTypeIssues]
        st, packed, rgb_texels, alpha_texels, ctx, acc, t_final)
    return acc, t_final, best


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _with_backward(st: Static, packed, rgb_texels, alpha_texels, ctx: CompositeInputs, acc, t_final):
    """``(acc, t_final)`` unchanged (the forward's outputs for these inputs), with the compositor's
    backward as their derivative in packed, rgb_texels and alpha_texels."""
    return acc, t_final


def _with_backward_fwd(st, packed, rgb_texels, alpha_texels, ctx: CompositeInputs, acc, t_final):
    return (acc, t_final), (packed, rgb_texels, alpha_texels, ctx, acc, t_final)


def _with_backward_bwd(st, res, cts):
    # acc and t_final come from inputs without gradients: their cotangents are zero (None).
    return _composite_bwd(st, res, cts) + (None, None)


def _chunk_bwd(st: Static, ctx: CompositeInputs, packed, tb, k, x, y, log_t, done, dot_through, ct_acc, base_term,
               g_rt, g_at):
    """Chunk k of a batch of tiles, backward: its cotangents for the packed splats (returned per
    chunk slot, (B, c, F), with the slots' ids gid (B, c)) and for the texels it read (added to the
    paired accumulators g_rt, g_at), and the state after it (log_t, done, dot_through, (B, P))."""
    gid, valid = jax.vmap(lambda t: chunk_slots(st, ctx, t, k))(tb)
    pk = packed[gid]
    geo = geometry_terms(pk, x, y, st.prefilter, st.billboard, st.object_space)
    G, z = geo.G, geo.z
    textured = st.rgb or st.alpha
    passes, offs, a_tex = None, None, None
    if textured:
        passes = texture_passes(st, ctx, pk, gid, valid, G, done)
        offs, a_tex = texture_fwd(st, ctx, pk, gid, x, y, passes, G.shape)
    (log_t2, done2, dot_through), (g_pk, g_G, g_z, g_tv) = _chunk_contrib_bwd(
        st, ctx, pk, G, z, offs, a_tex, gid, valid, log_t, done, ct_acc, dot_through, base_term)
    g_pk = g_pk + chunk_geometry_bwd(pk, x, y, geo, g_G, g_z, st.prefilter, st.billboard)
    if textured:
        g_tex, g_rt, g_at = texture_bwd(st, ctx, pk, gid, x, y, passes, G.shape, g_tv, g_rt, g_at)
        g_pk = g_pk + g_tex
    return log_t2, done2, dot_through, gid, jnp.where(valid[..., None], g_pk, 0.0), g_rt, g_at


def _composite_bwd(st, res, cts):
    packed, rgb_texels, alpha_texels, ctx, acc_all, tfin_all = res
    ct_acc_all, ct_t_all = cts
    npx = st.config.tile_size ** 2
    dt = packed.dtype
    B = st.batch

    def batch(carry, inp):
        tb, pad = inp
        # Padding entries repeat a tile: zero cotangents so its gradient is not added twice.
        ct_acc = jnp.where(pad[:, None, None], 0.0, ct_acc_all[tb])      # (B, P, 9)
        ct_t = jnp.where(pad[:, None], 0.0, ct_t_all[tb])                # (B, P)
        base_term = ct_t * tfin_all[tb] + jnp.sum(ct_acc * acc_all[tb], axis=-1)
        (x, y), nch = batch_state(st, ctx, tb, dt)

        def cond(state):
            return jnp.any((state[0] < nch) & ~jnp.all(state[2], axis=1))

        def body(state):
            k, log_t, done, dot_through, (g_pk, g_rt, g_at) = state
            log_t, done, dot_through, gid, g_pkc, g_rt, g_at = _chunk_bwd(
                st, ctx, packed, tb, k, x, y, log_t, done, dot_through, ct_acc, base_term, g_rt, g_at)
            g_pk = g_pk.at[gid.reshape(-1)].add(g_pkc.reshape(-1, g_pkc.shape[-1]))
            return k + 1, log_t, done, dot_through, (g_pk, g_rt, g_at)

        init = (jnp.int32(0), jnp.zeros((B, npx), dt), jnp.zeros((B, npx), bool), jnp.zeros((B, npx), dt),
                carry)
        return lax.while_loop(cond, body, init)[4], None

    batches = tile_batches(st, ctx)
    pad = (jnp.arange(batches.size) >= st.num_tiles).reshape(batches.shape)

    def pairs(texels):  # the paired texel cotangents (see texture_lookup._scatter)
        return None if texels is None else jnp.zeros(texels.shape[:-1] + (2 * texels.shape[-1],), texels.dtype)

    def unpaired(g):
        return None if g is None else unpair(g)

    zeros = (jnp.zeros_like(packed), pairs(rgb_texels), pairs(alpha_texels))
    (g_pk, g_rt, g_at), _ = lax.scan(batch, zeros, (batches, pad))
    return g_pk, unpaired(g_rt), unpaired(g_at), jax.tree_util.tree_map(lambda _: None, ctx)


_with_backward.defvjp(_with_backward_fwd, _with_backward_bwd)
