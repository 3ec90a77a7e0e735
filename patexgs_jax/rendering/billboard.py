"""Billboard coverage (``RenderConfig(coverage="billboard")``): the BBSplat primitive (Svitov et al.
2024, "BillBoard Splatting") in this renderer's conventions.

A billboard is a splat whose kernel is the indicator of the square ``|u| <= HALF, |v| <= HALF`` of
its plane (u, v in units of the scales, as the textures), ``HALF = 3``: the square is the span of
the splat's textures (:mod:`patexgs_jax.textures`), so the alpha texture alone shapes it and nothing
falls off inside it: ``alpha = min(0.99, opacity * A_tex(u, v))`` inside, 0 outside. BBSplat's own
rasterizer (``diff-bbsplat-rasterization``) samples its textures over ``[-1, 1]^2`` in units of its
scales (align-corners), bilinearly with zero padding, and has no opacity (alpha is the sampled,
sigmoid-activated alpha texture); here the texture spans ``[-3, 3]^2`` (a BBSplat scale is three of
ours), lookups clamp at the edges and the support stops at the square's edge, and the opacity is a
per-splat factor of the alpha texture (the products span the same alphas). Colour is
``max(SH + 0.5, 0) + RGB_tex``, as BBSplat's.

Gradients: G is piecewise constant, so the square's edge passes no gradient; the geometry learns
through the textures' (u, v) and the depth inside it. (BBSplat's zero padding makes its alpha fall
linearly to 0 over one texel past the edge texels, a ramp that passes a gradient to the geometry;
here an edge texel's value reaches the edge and stops there.)

Screen bounds are exact: the square's part in front of the near plane is a convex polygon (the
square clipped at camera z = near), whose projection's box is the box of its at most 8 vertices
(:func:`square_bounds`). The tile cull (:func:`square_touches`) tests a tile against the four
half-planes of the square's edges on screen; with the box it is the separating-axis test of the
tile and the projected square (conservative only where the near plane clips the square).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

#: Half the side of a billboard's square, in units of the scales: the span of its textures.
HALF = 3.0

HIGHEST = lax.Precision.HIGHEST


def kernel(u, v, ok):
    """G and the in-square mask of rays meeting the plane at (u, v) (``ok``: they meet it): 1 on
    the closed square ``|u|, |v| <= HALF``, else 0 (dtype of u)."""
    inside = ok & (jnp.abs(u) <= HALF) & (jnp.abs(v) <= HALF)
    return inside.astype(u.dtype), inside


def square_bounds(M, near: float):
    """The screen box of each billboard's square where it lies beyond the near plane.

    Args:
      M: (C, 3, 3) the image maps (splat plane (u, v, 1) -> image (x w, y w, w), w the camera z;
        :func:`projection.image_map`), no gradient.
      near: the near plane's depth.
    Returns:
      (xmin, xmax, ymin, ymax), each (C,) in pixels, grown by a float32 rounding margin, and (C,)
      bool, whether some of the square lies beyond ``near`` (the box is empty where not).
    """
    h = HALF
    corners = jnp.asarray([[-h, -h, 1.0], [h, -h, 1.0], [h, h, 1.0], [-h, h, 1.0]], M.dtype)  # around the square
    q = jnp.einsum("cij,kj->cki", M, corners, precision=HIGHEST)        # (C, 4, 3) image homogeneous
    qn = jnp.roll(q, -1, axis=1)                                        # each edge's other end
    w, wn = q[..., 2], qn[..., 2]
    keep = w >= near
    cross = (w - near) * (wn - near) < 0                                # the edge crosses w = near
    t = (near - w) / jnp.where(cross, wn - w, 1.0)
    e = q + t[..., None] * (qn - q)                                     # the crossing, w = near
    pts = jnp.concatenate([q[..., :2] / jnp.where(keep, w, 1.0)[..., None], e[..., :2] / near], axis=1)  # (C, 8, 2)
    ok = jnp.concatenate([keep, cross], axis=1)                         # (C, 8)
    big = 1e9
    lo = jnp.min(jnp.where(ok[..., None], pts, big), axis=1)
    hi = jnp.max(jnp.where(ok[..., None], pts, -big), axis=1)
    any_ = jnp.any(ok, axis=1)
    pad = 1e-3 + 1e-5 * jnp.maximum(jnp.abs(lo), jnp.abs(hi))          # float32 rounding of the edges
    lo = jnp.clip(lo - pad, -big, big)
    hi = jnp.clip(hi + pad, -big, big)
    empty = ~any_[:, None]
    lo = jnp.where(empty, big, lo)
    hi = jnp.where(empty, -big, hi)
    return (lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]), any_


#: square_touches accepts half-plane values down to -SQUARE_EPS times their terms' size (float32
#: rounding), on tiles grown by binning.TOUCH_GROW pixels.
SQUARE_EPS = 1e-4


def square_touches(A, B, C, side, tx, ty, tile_size: int, grow: float):
    """Whether billboards may cover a pixel centre of tile (tx, ty) (each (N,) int32), the tile
    grown by ``grow`` pixels a side: False only where none can. A, B, C (each a list of 3 (N,)) and
    side (N,) are the billboards' footprint columns (:data:`projection.FOOTPRINT`).

    The ray of pixel (x, y) meets the plane at the homogeneous s = x A + y B + C, in front of the
    camera where ``side * s2 > 0``, inside the square where ``side (HALF s2 -+ s0) >= 0`` and
    ``side (HALF s2 -+ s1) >= 0`` (their sums give ``side s2 >= 0``): four half-planes of the
    screen, whose intersection is the square's projection. A tile misses it iff its four corners
    are outside one of them or it is outside the box (which :func:`binning.tile_ranges` has
    already tested): the separating-axis test of two convex polygons. ``side`` 0 (unsure): kept.
    """
    dt = side.dtype
    x0 = (tx * tile_size).astype(dt) + (0.5 - grow)
    y0 = (ty * tile_size).astype(dt) + (0.5 - grow)
    x1 = x0 + (tile_size - 1 + 2 * grow)
    y1 = y0 + (tile_size - 1 + 2 * grow)
    hit = side == 0
    inside = [jnp.zeros(side.shape, bool) for _ in range(4)]
    for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1)):
        s0, s1, s2 = (x * A[i] + y * B[i] + C[i] for i in range(3))
        a2, a0, a1 = HALF * side * s2, side * s0, side * s1
        tol0 = -SQUARE_EPS * (jnp.abs(a2) + jnp.abs(a0))
        tol1 = -SQUARE_EPS * (jnp.abs(a2) + jnp.abs(a1))
        for k, val in enumerate((a2 - a0 - tol0, a2 + a0 - tol0, a2 - a1 - tol1, a2 + a1 - tol1)):
            inside[k] = inside[k] | (val >= 0)
    return hit | (inside[0] & inside[1] & inside[2] & inside[3])
