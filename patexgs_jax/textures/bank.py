"""Per-Gaussian textures in power-of-two buckets (:class:`TextureBank`); their mip pyramids' sizes and filter.

Storage
  A texture of n x n texels (any n >= 1) lives in bucket ``b = ceil(log2 n)``, whose slots are
  ``P x P`` with ``P = 2**b``; only the top-left ``n x n`` block is used (the rest stays zero and
  receives no gradient). Index ``[a, c]`` of a texture runs along the splat's first tangent axis (u)
  for ``a`` and the second (v) for ``c``. A texture spans the splat-plane square ``[-3, 3]^2`` in
  units of the scales, align-corners: texel 0 sits at -3 and texel n-1 at +3; lookups are bilinear
  and clamp at the edges. A 1 x 1 texture is a constant.

Mip pyramid (paper Eqs. 11-13)
  ``L = ceil(log2 n)`` levels above level 0; level 0 is the texture itself (n x n) and level k >= 1
  has ``2**(L-k)`` texels a side. Level k is computed from level k-1 by an antialiased bilinear
  (tent-filter) downsampling over the align-corners texel positions: output texel j takes the
  weights ``max(0, 1 - |x_i - y_j| / h)`` of the input texels i, normalised to sum to one, where h is
  the output texel spacing (a 1-texel level is the mean of its parent). Constants are preserved
  exactly, and for power-of-two n each level is a low-pass of the previous one.

The flat texel atlas the renderer reads is :mod:`.atlas`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def bucket_of(n: int) -> int:
    """Bucket index ``ceil(log2 n)`` of an n x n texture (n >= 1)."""
    n = int(n)
    if n < 1:
        raise ValueError(f"texture size must be >= 1, got {n}")
    return (n - 1).bit_length()


def mip_level_sizes(n: int) -> list[int]:
    """Side lengths of the pyramid of an n x n texture: ``[n, 2**(L-1), ..., 1]``, L = ceil(log2 n)."""
    L = bucket_of(n)
    return [int(n)] + [2 ** (L - k) for k in range(1, L + 1)]


@functools.cache
def downsample_matrix(size_in: int, size_out: int) -> np.ndarray:
    """(size_out, size_in) float64 tent-filter resampling matrix between align-corners grids.

    Rows sum to one. ``size_out == 1`` gives the mean. Used separably: ``D @ X @ D.T``.
    """
    if size_out == 1:
        return np.full((1, size_in), 1.0 / size_in)
    if size_in == 1:
        return np.ones((size_out, 1))
    x = np.linspace(-3.0, 3.0, size_in)
    y = np.linspace(-3.0, 3.0, size_out)
    h = 6.0 / (size_out - 1)
    w = np.maximum(0.0, 1.0 - np.abs(x[None, :] - y[:, None]) / max(h, 6.0 / (size_in - 1)))
    return w / w.sum(axis=1, keepdims=True)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TextureBank:
    """Textures of one channel group (RGB offsets or alpha) for a scene of capacity C.

    Attributes:
      buckets: tuple of B arrays; ``buckets[b]`` is (capacity_b, 2**b, 2**b, channels) float32.
        Bucket capacities are static (shapes); a zero-capacity bucket costs nothing.
      bucket: (C,) float32 holding exact integers: the Gaussian's bucket, -1 for no texture.
      slot: (C,) float32 holding exact integers: the slot inside that bucket.
      size: (C,) float32 holding exact integers: the true side n (0 for no texture).
      channels: 3 for RGB, 1 for alpha (static).

    Indices are stored as float32 so that ``jax.grad`` over a whole Scene works without
    ``allow_int``; they receive zero gradient and are exact up to 2**24.
    """

    buckets: tuple
    bucket: jax.Array
    slot: jax.Array
    size: jax.Array
    channels: int = dataclasses.field(metadata=dict(static=True))

    @property
    def num_buckets(self) -> int:
        return len(self.buckets)

    @property
    def capacities(self) -> tuple[int, ...]:
        return tuple(int(b.shape[0]) for b in self.buckets)

    @classmethod
    def from_list(cls, textures: Sequence, capacity: int, channels: int, default: float,
                  min_buckets: int = 0) -> TextureBank:
        """Packs per-Gaussian textures into buckets.

        Args:
          textures: length-N sequence (N <= capacity); entry i is None (no texture) or an array of
            shape (n, n, channels) (or (n, n) when channels == 1).
          capacity: the scene's Gaussian capacity C.
          channels: 3 or 1.
          default: the value a texture-less Gaussian samples (0 for RGB offsets, 1 for alpha); only
            used for validation messages.
          min_buckets: build at least this many buckets (zero-capacity ones included).
        """
        del default
        sizes = np.zeros(len(textures), np.int64)
        arrays = []
        for i, t in enumerate(textures):
            if t is None:
                continue
            t = np.asarray(t, np.float32)
            if channels == 1 and t.ndim == 2:
                t = t[..., None]
            if t.ndim != 3 or t.shape[0] != t.shape[1] or t.shape[2] != channels or t.shape[0] < 1:
                want = "(n, n)" if channels == 1 else f"(n, n, {channels})"
                raise ValueError(f"texture of Gaussian {i} has shape {t.shape}; expected {want} with n >= 1.")
            if not np.all(np.isfinite(t)):
                raise ValueError(f"texture of Gaussian {i} has non-finite texels.")
            sizes[i] = t.shape[0]
            arrays.append(t.reshape(-1, channels))
        texels = np.concatenate(arrays) if arrays else np.zeros((0, channels), np.float32)
        return cls.from_packed(sizes, texels, capacity, channels, min_buckets)

    @classmethod
    def from_packed(cls, sizes, texels, capacity: int, channels: int, min_buckets: int = 0) -> TextureBank:
        """Packs textures given back to back into buckets, without a loop over Gaussians.

        The layout is :meth:`from_list`'s: Gaussian i (in order) takes the next slot of its bucket,
        and a bucket's capacity is the power of two at or above its count.

        Args:
          sizes: (N,) int sides, N <= capacity (0: no texture).
          texels: (sum sizes**2, channels) float32: the textures in Gaussian order, each row-major
            (texel [a, c] of Gaussian i at row ``offset_i + a * n_i + c``), as the PLY sidecar stores them.
          capacity: the scene's Gaussian capacity C.
          channels: 3 or 1.
          min_buckets: build at least this many buckets (zero-capacity ones included).
        """
        n_in = np.asarray(sizes).astype(np.int64)
        if n_in.ndim != 1 or n_in.shape[0] > capacity or np.any(n_in < 0):
            raise ValueError(f"sizes must be (N,) non-negative with N <= capacity {capacity}, got shape "
                             f"{n_in.shape}.")
        texels = np.asarray(texels, np.float32).reshape(-1, channels)
        total = int(np.sum(n_in * n_in))
        if texels.shape[0] != total:
            raise ValueError(f"texels has {texels.shape[0]} rows; the sizes need {total}.")
        sizes = np.zeros(capacity, np.int64)
        sizes[: n_in.shape[0]] = n_in
        has = sizes > 0
        # bucket ceil(log2 n) = bit_length(n - 1): frexp's exponent of n - 1 (exact for n < 2**53).
        bucket = np.where(has, np.frexp(np.maximum(sizes - 1, 0).astype(np.float64))[1], -1).astype(np.int64)
        nb = max(int(bucket.max(initial=-1)) + 1, int(min_buckets))
        counts = np.bincount(bucket[has], minlength=nb)
        # slot: the Gaussian's rank among those of its bucket, in index order (a stable sort).
        idx = np.flatnonzero(has)
        order = idx[np.argsort(bucket[idx], kind="stable")]
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.zeros(capacity, np.int64)
        slot[order] = np.arange(order.size) - starts[bucket[order]]
        caps = [0 if c == 0 else 1 << (int(c) - 1).bit_length() for c in counts]
        data = [np.zeros((caps[b], 1 << b, 1 << b, channels), np.float32) for b in range(nb)]
        offsets = np.concatenate([[0], np.cumsum(sizes * sizes)])
        for n in np.unique(sizes[has]):
            sel = np.flatnonzero(sizes == n)
            rows = offsets[sel][:, None] + np.arange(n * n)[None, :]
            data[bucket_of(int(n))][slot[sel], :n, :n] = texels[rows].reshape(sel.size, n, n, channels)
        return cls(buckets=tuple(jnp.asarray(d) for d in data),
                   bucket=jnp.asarray(bucket, jnp.float32), slot=jnp.asarray(slot, jnp.float32),
                   size=jnp.asarray(sizes, jnp.float32), channels=channels)

    def texture(self, i: int) -> np.ndarray | None:
        """Host-side copy of Gaussian i's level-0 texture, (n, n, channels), or None."""
        b = int(self.bucket[i])
        if b < 0:
            return None
        n = int(self.size[i])
        return np.asarray(self.buckets[b][int(self.slot[i]), :n, :n])

    def texel_count(self, active=None) -> int:
        """Number of stored texels (sum of n*n over textured, optionally active, Gaussians)."""
        n = np.asarray(self.size, np.int64)
        if active is not None:
            n = n * (np.asarray(active) > 0)
        return int(np.sum(n * n))
