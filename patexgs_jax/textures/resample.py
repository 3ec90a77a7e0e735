"""Resampling a texture to another side, as the renderer samples it (the map
:func:`patexgs_jax.textures.rebucket.resize_textures` applies to texels and their Adam moments when a
texture's side changes; its module docstring says how)."""

from __future__ import annotations

import numpy as np

__all__ = ["resample_matrix", "resample_texture"]


def _hat_integral(x: np.ndarray) -> np.ndarray:
    """``F(x) = integral_{-inf}^{x} max(0, 1 - |s|) ds``: the antiderivative of a unit hat."""
    x = np.clip(x, -1.0, 1.0)
    return np.where(x <= 0.0, 0.5 * (x + 1.0) ** 2, 1.0 - 0.5 * (1.0 - x) ** 2)


def resample_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) float64 resampling matrix: non-negative weights, each row summing to one.

    Growing or keeping the side (``n_out >= n_in``): row j holds the bilinear weights of the old
    texels at new texel j's position ``-3 + 6 j / (n_out - 1)``, with the renderer's edge clamp
    (the renderer's own sampling; exact integer arithmetic for the positions).

    Shrinking (``n_out < n_in``): an area filter. New texel j is the mean of the old texture's
    bilinear interpolant over its cell, ``[-3 + 6 (j - 1/2) / (n_out - 1), -3 + 6 (j + 1/2) /
    (n_out - 1)]`` cut to [-3, 3] (the whole square when ``n_out == 1``). The cells tile the square
    with the widths the new interpolant's trapezoid rule gives its texels, so the interpolant's mean
    over the square is kept exactly: a texture that shrinks keeps its mean colour and coverage, and
    every old texel contributes (point-sampling a 5 x 5 texture at side 2 would read only its corners).
    """
    n_in, n_out = int(n_in), int(n_out)
    if n_in < 1 or n_out < 1:
        raise ValueError(f"resample sizes must be >= 1, got {n_in} -> {n_out}.")
    R = np.zeros((n_out, n_in))
    if n_in == 1:
        R[:, 0] = 1.0
        return R
    if n_out < n_in:
        # In old-grid units t in [0, n_in - 1]: old texel a is the hat max(0, 1 - |t - a|).
        last = n_in - 1.0
        if n_out == 1:
            lo, hi = np.array([0.0]), np.array([last])
        else:
            h = last / (n_out - 1)
            c = np.arange(n_out) * h
            lo, hi = np.maximum(c - h / 2, 0.0), np.minimum(c + h / 2, last)
        a = np.arange(n_in)[None, :]
        R = (_hat_integral(hi[:, None] - a) - _hat_integral(lo[:, None] - a)) / (hi - lo)[:, None]
        return R / R.sum(axis=1, keepdims=True)  # (sums are one up to rounding; make them exact-er)
    for j in range(n_out):
        # Old-grid coordinate t = j (n_in - 1) / (n_out - 1) = a0 + f.
        num, den = j * (n_in - 1), n_out - 1
        a0, rem = divmod(num, den)
        f = rem / den
        if a0 >= n_in - 1:  # the last texel: clamp like the renderer (a0 = n - 2, f = 1)
            a0, f = n_in - 2, 1.0
        R[j, a0] += 1.0 - f
        R[j, a0 + 1] += f
    return R


def resample_texture(tex, n_out: int) -> np.ndarray:
    """Resamples textures to side ``n_out`` (float64 math, float32 result).

    Args:
      tex: (..., n, n, ch) textures.
      n_out: new side m >= 1.
    Returns:
      (..., m, m, ch) float32.
    """
    tex = np.asarray(tex, np.float64)
    if tex.ndim < 3 or tex.shape[-3] != tex.shape[-2]:
        raise ValueError(f"textures must have shape (..., n, n, ch), got {tex.shape}.")
    R = resample_matrix(tex.shape[-3], n_out)
    # R X R^T per texture and channel as two batched matmuls with the channel axis moved ahead
    # (np.einsum's contraction path took 1.1-2x as long on a million textures; the same products).
    rows = np.matmul(R, np.moveaxis(tex, -1, -3))  # (..., ch, m, n)
    return np.moveaxis(np.matmul(rows, R.T), -3, -1).astype(np.float32)
