"""The alpha textures billboards start from (the ``bbsplat`` methods, ``coverage="billboard"``).

A billboard's kernel is 1 on its whole texture square (:mod:`patexgs_jax.rendering.billboard`), so
the stage-2 textures cannot start neutral (alpha 1) as the Gaussian methods' do: every splat would
turn into an opaque square. They start as the 2DGS Gaussian sampled at the texel positions,
``A[a, c] = exp(-0.5 (x_a^2 + x_c^2))`` with x the align-corners positions in [-3, 3], so that the
first render reproduces the stage-1 2DGS render (up to the bilinear interpolation between texels
and the 2DGS low-pass, which billboards do not have). BBSplat initialises its alpha textures with a
Gaussian image too (its ``alpha_init_gaussian`` asset, halved), on points rather than on a trained
2DGS model.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..scene import Scene
from .bank import TextureBank

__all__ = ["gaussian_alpha", "gaussian_weighted", "with_gaussian_alpha"]


def gaussian_alpha(n: int) -> np.ndarray:
    """(n, n) float32: the splat-plane Gaussian ``exp(-0.5 (u^2 + v^2))`` at the texel positions of
    an n x n texture (align-corners over [-3, 3]; a 1 x 1 texture, a constant, is the Gaussian's
    mean over the square, which keeps the splat's integrated alpha)."""
    if n == 1:
        mean = (math.sqrt(2.0 * math.pi) * math.erf(3.0 / math.sqrt(2.0)) / 6.0) ** 2
        return np.full((1, 1), mean, np.float32)
    x = np.linspace(-3.0, 3.0, n)
    return np.exp(-0.5 * (x[:, None] ** 2 + x[None, :] ** 2)).astype(np.float32)


def gaussian_weighted(bank: TextureBank) -> TextureBank:
    """``bank`` with every texture multiplied by :func:`gaussian_alpha` of its side (traceable: inside
    jit, for ``RenderConfig(coverage="texel-grid")``): each slot's side is its Gaussian's, the
    padding beyond it is multiplied by 0."""
    mean = (math.sqrt(2.0 * math.pi) * math.erf(3.0 / math.sqrt(2.0)) / 6.0) ** 2
    size = jnp.asarray(bank.size).astype(jnp.float32)
    out = []
    for b, data in enumerate(bank.buckets):
        count, P = data.shape[0], data.shape[1]
        at = jnp.where((jnp.asarray(bank.bucket) == b) & (size > 0), jnp.asarray(bank.slot).astype(jnp.int32),
                       count)
        n = jnp.zeros((count,), jnp.float32).at[at].set(size, mode="drop")[:, None]  # (count, 1)
        a = jnp.arange(P, dtype=jnp.float32)[None, :]
        x = -3.0 + 6.0 * a / jnp.maximum(n - 1.0, 1.0)
        g = jnp.where(a < n, jnp.exp(-0.5 * x * x), 0.0)  # (count, P): the separable factor
        g = jnp.where(n == 1.0, jnp.where(a < 1, math.sqrt(mean), 0.0), g)
        out.append(data * (g[:, :, None] * g[:, None, :])[..., None])
    return TextureBank(buckets=tuple(out), bucket=bank.bucket, slot=bank.slot, size=bank.size,
                       channels=bank.channels)


def with_gaussian_alpha(scene: Scene, active=None) -> Scene:
    """``scene`` with every alpha texture (of the ``active`` Gaussians, all by default) replaced by
    :func:`gaussian_alpha` of its side; the padding of the bucket slots stays zero. Host-side."""
    bank = scene.alpha
    if bank is None:
        raise ValueError("with_gaussian_alpha: the scene has no alpha textures; add them first "
                         "(rebucket.add_textures).")
    size = np.asarray(bank.size).astype(np.int64)
    bucket = np.asarray(bank.bucket).astype(np.int64)
    slot = np.asarray(bank.slot).astype(np.int64)
    act = np.ones(size.shape, bool) if active is None else np.asarray(active) > 0
    data = [np.array(b) for b in bank.buckets]
    for n in np.unique(size[act & (size > 0)]):
        sel = act & (size == n)
        for b in np.unique(bucket[sel]):
            rows = slot[sel & (bucket == b)]
            data[b][rows, :n, :n, 0] = gaussian_alpha(int(n))
    new = TextureBank(buckets=tuple(jnp.asarray(d) for d in data), bucket=bank.bucket, slot=bank.slot,
                      size=bank.size, channels=bank.channels)
    return scene.replace(alpha=new)
