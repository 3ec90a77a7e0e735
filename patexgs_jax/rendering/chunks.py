"""How the compositor walks the image: its static settings, tile batches, a chunk's slots and pixels,
and helpers for a chunk's per-pair blocks.

Tiles advance in batches of B (:attr:`Static.batch`), each walking its depth-ordered list in chunks
of c = ``RenderConfig.chunk`` splats. A chunk's per-pair values are (c, B, P) blocks, P the pixels
of a tile: slots outermost, pixels innermost, so that a splat's column broadcasts along contiguous
pixels and a sum over the chunk's splats adds whole rows (docs/benchmarks.md has the A/B against
the (B, P, c) layout).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .config import RenderConfig
from .tiling import resolve_tile_batch


class Static(NamedTuple):
    """Hashable static settings of the compositor."""

    config: RenderConfig
    tiles_x: int
    num_tiles: int
    rgb: bool          # RGB textures present
    alpha: bool        # alpha textures present

    @property
    def rgb_mip(self):
        return self.rgb and self.config.mip != "none" and self.config.rgb_mip

    @property
    def alpha_mip(self):
        return self.alpha and self.config.mip != "none" and self.config.alpha_mip

    @property
    def prefilter(self):
        return self.config.coverage == "prefilter"

    @property
    def billboard(self):  # (the texel-grid reading of Eq. 13 renders under the billboard square)
        return self.config.coverage in ("billboard", "texel-grid")

    @property
    def object_space(self):
        return self.config.coverage == "object"

    @property
    def need_footprint(self):
        return self.rgb_mip or self.alpha_mip

    @property
    def batch(self):
        """Tiles advanced together: at most ``config.tile_batch``, spread evenly over the fewest
        batches, so that small images do not repeat a tile to fill a batch (every lane of a batch
        is computed, padding included: a one-tile image in a batch of 8 would do its work 8 times).
        A config that leaves ``tile_batch`` to the device takes :func:`.schedule.resolve_tile_batch`'s."""
        cfg = self.config
        limit = resolve_tile_batch(cfg.tile_batch, self.num_tiles, tile_size=cfg.tile_size, chunk=cfg.chunk)
        nb = -(-self.num_tiles // limit)
        return -(-self.num_tiles // nb)


class CompositeInputs(NamedTuple):
    """What the compositor reads besides the splats' packed columns and the texels it differentiates:
    a view's tile lists and, per splat, its texture addressing; nothing here carries a gradient. C is
    the scene's splat count, T the image's tiles, K the pair capacity (``Capacity.pairs``), M and M'
    the rows of the RGB and alpha atlases (:class:`patexgs_jax.textures.Atlas`). Both compositors (XLA,
    :mod:`.composite`; Pallas, :mod:`.pallas_composite`) take it; as a NamedTuple it is a pytree, so
    it passes through jit, ``custom_vjp`` and ``lax.map`` as its arrays.

    ids_sorted: (K,) int32, the splat ids of the (splat, tile) pairs, tile by tile, front to back
      (:func:`.binning.bin_pairs`).
    tile_start: (T,) int32, each tile's first pair in ``ids_sorted``.
    binned: (T,) int32, each tile's number of pairs.
    peak: (C,) float32, each splat's largest alpha-texture value (1 where its alpha texture is one
      texel, folded into the opacity): the bound a pass compares with the alpha threshold.
    flag: () bool, a traced True that XLA cannot prove (see :func:`barrier`).
    rgb_has, alpha_has: (C,) bool per bank, the splats with a texture to look up (not the one-texel
      ones, folded into ``packed``); None without that bank.
    tex_has: (C,) bool, the splats with either; None without textures.
    tex_meta: (C, 4 x banks) int32, the texture addressing (:func:`.texture_lookup.meta_table`); None
      without textures.
    rgb_texels: (M, 3) float32, alpha_texels: (M', 1) float32, the atlases' texels as the lookups read
      them (gradient stopped: the compositor's backward returns the texels' gradient itself); None
      without that bank.
    """

    ids_sorted: jax.Array
    tile_start: jax.Array
    binned: jax.Array
    peak: jax.Array
    flag: jax.Array
    rgb_has: jax.Array | None = None
    alpha_has: jax.Array | None = None
    tex_has: jax.Array | None = None
    tex_meta: jax.Array | None = None
    rgb_texels: jax.Array | None = None
    alpha_texels: jax.Array | None = None

    def need(self, name: str) -> jax.Array:
        """The field ``name``, which the static settings read (``rgb_has`` under ``Static.rgb``,
        ``tex_meta`` and ``tex_has`` with textures); an error at trace time where it was left None."""
        value = getattr(self, name)
        if value is None:
            raise ValueError(f"CompositeInputs.{name} is None, but the compositor's static settings read it "
                             "(a textured bank): build the inputs with it set, as render does.")
        return value


def pixel_coords(st: Static, t, dtype):
    """x, y (P,): the pixel centres of tile t, row by row."""
    ts = st.config.tile_size
    iy, ix = jnp.divmod(jnp.arange(ts * ts, dtype=jnp.int32), ts)
    x = ((t % st.tiles_x) * ts + ix).astype(dtype) + 0.5
    y = ((t // st.tiles_x) * ts + iy).astype(dtype) + 0.5
    return x, y


def chunk_slots(st: Static, ctx: CompositeInputs, t, k):
    """Splat ids (c,) and validity of chunk k of tile t."""
    c = st.config.chunk
    slots = k * c + jnp.arange(c, dtype=jnp.int32)
    valid = slots < ctx.binned[t]
    ids = ctx.ids_sorted
    gid = jnp.where(valid, ids[jnp.clip(ctx.tile_start[t] + slots, 0, ids.shape[0] - 1)], 0)
    return gid, valid


def _num_chunks(st: Static, ctx: CompositeInputs, t):
    """How many chunks tile t's list fills."""
    return (ctx.binned[t] + st.config.chunk - 1) // st.config.chunk


def tile_batches(st: Static, ctx: CompositeInputs):
    """(num_batches, B) tile ids, longest lists first so a batch's tiles need similar numbers of
    chunks (a batch loops until its slowest tile is done). Padding (fewer than num_batches
    entries, see :attr:`Static.batch`) repeats the last tile."""
    B = st.batch
    nb = -(-st.num_tiles // B)
    order = jnp.argsort(-ctx.binned, stable=True).astype(jnp.int32)
    order = jnp.concatenate([order, jnp.full((nb * B - st.num_tiles,), order[-1], jnp.int32)])
    return order.reshape(nb, B)


def batch_state(st: Static, ctx: CompositeInputs, tb, dt):
    """The pixel centres ((B, P), (B, P)) and the chunk counts (B,) of the batch of tiles tb (B,)."""
    xy = jax.vmap(lambda t: pixel_coords(st, t, dt))(tb)
    return xy, jax.vmap(lambda t: _num_chunks(st, ctx, t))(tb)


def cols(pk):
    """(F, c, B, 1): the columns of a batch's chunk of packed splats pk (B, c, F), each to broadcast
    against the chunk's (c, B, P) blocks."""
    return jnp.transpose(pk, (2, 1, 0))[..., None]


def per_slot(v):
    """(B, c) per-slot values -> (c, B, 1), to broadcast against a chunk's (c, B, P) blocks."""
    return v.T[..., None]


def prefix_sum(x):
    """Inclusive prefix sum along the last axis (c, small) as a product with the (c, c) upper
    triangle of ones: one small matmul, where XLA's CPU cumsum is a reduce-window of c^2 adds that
    it runs several times slower, forward and backward."""
    c = x.shape[-1]
    upper = jnp.triu(jnp.ones((c, c), x.dtype))
    return jnp.matmul(x, upper, precision=lax.Precision.HIGHEST)


def prefix_sum_slots(x):
    """Inclusive prefix sum of a chunk's (c, B, P) block along its slots (the first axis): one
    (c, c) x (c, B P) product with the lower triangle of ones (see :func:`prefix_sum`)."""
    c = x.shape[0]
    lower = jnp.tril(jnp.ones((c, c), x.dtype))
    return jnp.matmul(lower, x.reshape(c, -1), precision=lax.Precision.HIGHEST).reshape(x.shape)


def barrier(tree, flag):
    """``tree`` unchanged, computed once: XLA cannot fuse across a conditional, so the arithmetic
    behind ``tree`` is not duplicated into consumers that read its elements many times (per channel
    and texel: the gathers of 4 ch-wide rows and the per-channel products, forward and, through the
    transposed conditional, backward), where XLA's CPU fusion otherwise recomputes all of it.
    ``lax.optimization_barrier`` does not reach XLA's CPU fusion. ``flag`` is a traced True
    (unbatched, so the conditional stays one)."""
    return lax.cond(flag, lambda t: t, lambda t: jax.tree.map(jnp.zeros_like, t), tree)
