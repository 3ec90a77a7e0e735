"""The splat kernel of a chunk's (splat, pixel) pairs, with its hand-derived backward.

Each pixel's ray meets a splat's plane at (u, v) (the homogeneous ray-plane map of
:func:`projection.ray_planes`). The kernel G and the pair's depth z follow the coverage mode
(conventions in :mod:`patexgs_jax.render`): the 2DGS ``exp(-0.5 min(rho3d, rho2d))``, or Eq. 2's
``exp(-0.5 rho3d)`` alone (coverage "object"), or the prefiltered ``exp(-0.5 (p u^2 + 2 r u v + t
v^2))`` cut outside its screen support, or the billboard's square (:mod:`.billboard`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from . import billboard as bb
from .chunks import Static, cols
from .config import ALPHA_MIN
from .projection import COLS

UV_LIMIT = 1e4  # |u|, |v| beyond this count as "no intersection" (G3d underflows long before)


def uv(s0, s1, s2):
    """(u, v) = (s0, s1) / s2 with "no intersection" (ok False) when the ray is (nearly) parallel;
    also returns 1 / s2 (1 where ok is False)."""
    ok = jnp.abs(s2) * UV_LIMIT > jnp.maximum(jnp.abs(s0), jnp.abs(s1))
    inv = 1.0 / jnp.where(ok, s2, 1.0)
    u = jnp.where(ok, s0 * inv, 0.0)
    v = jnp.where(ok, s1 * inv, 0.0)
    return u, v, ok, inv


class Geometry(NamedTuple):
    """The kernel's per-pair terms of a batch's chunk, each (c, B, P) (:func:`geometry_terms`)."""

    G: jax.Array       # the kernel
    z: jax.Array       # the pair's depth
    u: jax.Array       # ray-plane intersection (0 where the ray misses the plane)
    v: jax.Array
    ok: jax.Array      # the ray meets the plane
    inv: jax.Array     # 1 / s2 (see uv)
    use3: jax.Array    # the 3D term wins (rho3d <= rho2d); prefilter: a hit in the support; billboard: in the square


def geometry_terms(pk, x, y, prefilter: bool, billboard: bool = False, object_space: bool = False) -> Geometry:
    """The :class:`Geometry` of pk (B, c, F) packed splats at pixel centres x, y (B, P); with
    ``prefilter`` the kernel is the prefiltered one (coverage "prefilter", columns ``COLS.conic``),
    with ``billboard`` the square's indicator (coverage "billboard"), with ``object_space`` Eq. 2's
    ``exp(-0.5 rho3d)`` without the low-pass (coverage "object")."""
    col = cols(pk)
    ia, ib, ic = COLS.a.start, COLS.b.start, COLS.c.start
    u, v, ok, inv = uv(*[x * col[ia + i] + y * col[ib + i] + col[ic + i] for i in range(3)])
    if billboard:
        G, use3 = bb.kernel(u, v, ok)
    elif prefilter:
        p, r, t = (col[i] for i in range(COLS.conic.start, COLS.conic.stop))
        a, b, c = (col[i] for i in range(COLS.support.start, COLS.support.stop))
        dx, dy = x - col[COLS.mu.start], y - col[COLS.mu.start + 1]
        use3 = ok & ((a * dx + 2.0 * b * dy) * dx + c * dy * dy <= 1.0)
        G = jnp.exp(-0.5 * jnp.where(use3, (p * u + 2.0 * r * v) * u + t * v * v, 1e8))
    else:
        rho3d = jnp.where(ok, u * u + v * v, 1e8)
        dx, dy = x - col[COLS.mu.start], y - col[COLS.mu.start + 1]
        # (object space: the low-pass never wins; a ray that misses the plane has G = 0 either way)
        rho2d = jnp.full_like(rho3d, 1e8) if object_space else 2.0 * (dx * dx + dy * dy)
        use3 = rho3d <= rho2d
        G = jnp.exp(-0.5 * jnp.minimum(rho3d, rho2d))
    m = COLS.m2.start
    z = jnp.where(use3, col[m] * u + col[m + 1] * v + col[m + 2], col[COLS.depth])
    return Geometry(G, z, u, v, ok, inv, use3)


def chunk_geometry(pk, x, y, prefilter: bool = False, billboard: bool = False, object_space: bool = False):
    """G, z (c, B, P) of a batch's chunk: pk (B, c, F) packed splats, x, y (B, P) pixel centres.
    G is the 2DGS kernel exp(-0.5 min(rho3d, rho2d)) and z the depth: at the ray-plane intersection
    where the 3D term wins, else the centre's. With ``prefilter``, G is the prefiltered kernel
    exp(-0.5 (p u^2 + 2 r u v + t v^2)) (0 where the ray misses the plane) and z the intersection's;
    with ``billboard``, G is 1 in the square |u|, |v| <= 3 and 0 outside, z the intersection's in it."""
    t = geometry_terms(pk, x, y, prefilter, billboard, object_space)
    return t.G, t.z


def chunk_geometry_bwd(pk, x, y, geo: Geometry, g_G, g_z, prefilter: bool = False, billboard: bool = False):
    """The cotangent (B, c, F) of pk for cotangents g_G, g_z (c, B, P) of :func:`chunk_geometry`,
    given the forward's terms ``geo`` (:func:`geometry_terms` of the same pk, x, y), derived by
    hand: the per-splat sums over a tile's pixels are products of a few per-pair columns with the
    pixels' (x, y, 1), not a reduction per packed column as autodiff's backward has. The centre's
    cotangent comes from the sums of one column (``-4 (sum g x - mu sum g)``, not a column each for
    x and y), and each column is multiplied on its own: stacking them first adds a copy of the
    (9, c, B, P) block that costs more than the products (docs/benchmarks.md). The pixels of every
    tile must share their offsets from the tile's first pixel (x[b] - x[b, 0] the same for every b,
    and y alike), as the tiles of :func:`chunks.pixel_coords` do. A billboard's G is piecewise
    constant: only the depth passes a gradient to the plane (the square's edge passes none)."""
    G, _, u, v, ok, inv, use3 = geo
    col = cols(pk)
    M2 = col[COLS.m2]
    g_rho = jnp.zeros_like(G) if billboard else -0.5 * g_G * G  # d/d min(rho3d, rho2d), or d/d q
    g_rho3 = jnp.where(use3 & ok, g_rho, 0.0)
    g_z3 = jnp.where(use3, g_z, 0.0)
    if prefilter:  # d q / d(u, v) = 2 P (u, v)
        qu = col[COLS.conic.start] * u + col[COLS.conic.start + 1] * v
        qv = col[COLS.conic.start + 1] * u + col[COLS.conic.start + 2] * v
    else:
        qu, qv = u, v
    g_u = jnp.where(ok, 2.0 * qu * g_rho3 + M2[0] * g_z3, 0.0)
    g_v = jnp.where(ok, 2.0 * qv * g_rho3 + M2[1] * g_z3, 0.0)
    # u = s0 / s2, v = s1 / s2.
    g_s2 = -(g_u * u + g_v * v) * inv
    B, c = pk.shape[:2]
    P = x.shape[-1]
    # (x, y) = centre + (xi, yi): the tile's centre plus the pixel's offset from it, the same in
    # every tile, so the sums over the pixels are plain products with the (P, 3) offsets. (From
    # the centre, not a corner: smaller offsets, less cancellation where the sums are corrected.)
    xi, yi = x[0] - x[0, 0], y[0] - y[0, 0]
    xi, yi = xi - jnp.mean(xi), yi - jnp.mean(yi)
    centre = jnp.stack([x[:, 0] - xi[0], y[:, 0] - yi[0]], axis=-1)[:, None]               # (B, 1, 2)
    Xi = jnp.stack([xi, yi, jnp.ones((P,), x.dtype)], axis=-1)                           # (P, 3)

    def sums(col):  # (c, B, P) -> (B, c, 3): sums over the pixels weighted by xi, yi and 1
        r = jnp.matmul(col.reshape(-1, P), Xi, precision=lax.Precision.HIGHEST)
        return jnp.swapaxes(r.reshape(c, B, 3), 0, 1)

    def xy1(col):  # (B, c, 3): the sums weighted by x, y and 1
        r = sums(col)
        return r.at[..., :2].add(centre * r[..., 2:])

    abc = jnp.stack([xy1(g_u * inv), xy1(g_v * inv), xy1(g_s2)], axis=-1).reshape(B, c, 9)
    if prefilter or billboard:  # the centre is not read
        g_mu = jnp.zeros((B, c, 2), pk.dtype)
    else:  # d rho2d / d mu = -4 (x - mu): from the x-, y- and 1-weighted sums of one column.
        r2 = sums(jnp.where(use3, 0.0, g_rho))
        g_mu = -4.0 * (r2[..., :2] + (centre - pk[..., COLS.mu]) * r2[..., 2:])
    one = [sums(q)[..., 2] for q in (g_z3 * u, g_z3 * v, g_z3, g_z - g_z3)]
    rest = jnp.zeros((B, c, COLS.depth - COLS.opacity), pk.dtype)                      # opacity to normal
    out = [abc, jnp.stack(one[:3], -1), g_mu, rest, one[3][..., None]]
    if prefilter:  # d q / d(p, r, t) = (u^2, 2 u v, v^2); the coverage column is a threshold only
        out += [jnp.stack([sums(q)[..., 2] for q in (g_rho3 * u * u, 2.0 * g_rho3 * u * v, g_rho3 * v * v)], -1),
                jnp.zeros((B, c, 1 + COLS.support.stop - COLS.support.start), pk.dtype)]
    return jnp.concatenate(out, axis=-1)


def alpha_min(st: Static, pk):
    """The alpha below which a pair is skipped: ALPHA_MIN; with the prefilter, ALPHA_MIN times the
    splat's coverage factor (a (c, B, 1) column), so that a sub-pixel splat whose whole footprint is
    fainter than 1/255 is still composited and keeps its integrated coverage, while its fringe is
    cut where the unscaled kernel falls below 1/255, as a resolved splat's is."""
    return ALPHA_MIN * cols(pk)[COLS.coverage] if st.prefilter else ALPHA_MIN
