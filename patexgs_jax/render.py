"""Differentiable tile renderer for textured 2D Gaussian splats with per-pixel mipmaps.

Conventions (fixed for the package)
  * Cameras: OpenCV (x right, y down, z forward), world-to-camera 4x4; pixel (i, j) has its centre
    at continuous coordinates (j + 0.5, i + 0.5).
  * Kernel (2DGS): the ray of a pixel meets the splat plane at (u, v), in units of the scales
    (homogeneous ray-splat intersection); ``rho3d = u^2 + v^2``; the screen-space low-pass is
    ``rho2d = 2 |x - mu2d|^2`` in pixels; ``G = exp(-0.5 min(rho3d, rho2d))``.
  * ``alpha = min(0.99, opacity * G * A_tex(u, v))``; a pair with alpha < 1/255, or whose
    intersection lies at depth <= ``near``, is skipped; front-to-back compositing in order of the
    Gaussians' centre depths stops before the first splat that would bring transmittance below 1e-4.
  * Colour of a splat at a pixel: ``max(SH(d) + 0.5, 0) + RGB_tex(u, v)``, d the unit direction
    from the camera centre to the splat's mean (one direction per splat, as in 3DGS).
  * Textures span ``[-3, 3]^2`` of the splat plane, align-corners bilinear, clamped at the edges
    (see :mod:`patexgs_jax.textures`).
  * Mip level per pixel and splat (paper Eq. 11): with (u1, v1), (u2, v2), (u3, v3) the
    intersections of the rays of pixel (X, Y), (X + 1, Y) and (X, Y + 1) with the splat plane,
    ``D = max(|p2 - p1|, |p3 - p1|)`` in splat-plane units and
    ``l = min(L, max(0, floor(log2(lambda_mip * n * D))))`` with n the texture side and
    L = ceil(log2 n). RGB and alpha textures pick their levels independently (their n may differ).
    ``mip="trilinear"`` blends the two nearest levels by the fractional level instead.
  * Outputs: ``rgb`` composited over ``background``; ``alpha = 1 - T_final``; ``depth`` is the
    alpha-normalised expected ray-splat intersection depth (camera z), 0 where nothing is hit;
    ``normal`` is the alpha-weighted sum of the splats' camera-frame unit normals, each flipped to
    face the camera (divide by alpha for a unit normal).

Structure
  ``project`` computes per-splat quantities (C of them) and screen-space bounds; ``bin`` builds
  depth-ordered fixed-capacity per-tile lists with one stable sort of (tile) keys over pairs
  generated in depth order; ``composite`` evaluates every tile's (pixels x slots) grid, in
  sequential batches of tiles (``lax.map``) whose work is rematerialised in the backward pass
  (``jax.checkpoint``), so backward memory is bounded by one batch.

  Static capacities (``Capacity``): total (splat, tile) pairs and slots per tile. Needs beyond them
  are counted exactly (a 2D difference-array histogram of tile coverage) and returned, so callers
  grow the capacity and render again; :func:`render` does this itself and never returns a truncated
  image.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import textures as tex
from .camera import Camera
from .math import quat_to_rotmat, safe_div, safe_normalize, safe_sqrt, sh_basis
from .scene import Scene

MIP_MODES = ("none", "nearest", "trilinear")
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
_UV_LIMIT = 1e4  # |u|, |v| beyond this count as "no intersection" (G3d underflows long before)
_DIST_NEAR, _DIST_FAR = 0.2, 1000.0  # the NDC depth mapping of the 2DGS distortion loss

#: How many times the jitted renderer has been traced, per configuration (tests assert on it).
TRACE_COUNTS: collections.Counter = collections.Counter()


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Static rendering options (hashable; a new value compiles a new renderer).

    Attributes:
      mip: "none" (level 0 only), "nearest" (paper Eq. 11, default) or "trilinear".
      lambda_mip: the paper's lambda_mip in Eq. 11.
      rgb_mip: use mipmaps for the RGB textures (False: level 0 always; paper Table 3 ablation).
      alpha_mip: use mipmaps for the alpha textures (paper Eq. 13).
      background: RGB colour behind everything.
      near: near-plane depth; splats whose centre, or pairs whose intersection, is not beyond it are
        skipped.
      tile_size: tile side in pixels.
      tiles_per_batch: tiles composited together in one sequential step (bounded by memory: it is
        reduced automatically for large per-tile capacities).
    """

    mip: str = "nearest"
    lambda_mip: float = 0.4
    rgb_mip: bool = True
    alpha_mip: bool = True
    background: tuple = (0.0, 0.0, 0.0)
    near: float = 0.01
    tile_size: int = 16
    tiles_per_batch: int = 16

    def __post_init__(self):
        if self.mip not in MIP_MODES:
            raise ValueError(f"RenderConfig.mip must be one of {MIP_MODES}, got {self.mip!r}.")
        if not self.lambda_mip > 0:
            raise ValueError(f"lambda_mip must be positive, got {self.lambda_mip}.")
        if len(tuple(self.background)) != 3:
            raise ValueError("background must be an RGB triple.")
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))
        if self.tile_size < 1 or self.tiles_per_batch < 1:
            raise ValueError("tile_size and tiles_per_batch must be positive.")
        if not self.near > 0:
            raise ValueError(f"near must be positive, got {self.near}.")


@dataclasses.dataclass(frozen=True)
class Capacity:
    """Static buffer sizes of the tile lists.

    Attributes:
      pairs: total (splat, tile) pairs that can be binned.
      per_tile: splats composited per tile (slots).
    """

    pairs: int = 1 << 14
    per_tile: int = 64

    @staticmethod
    def fit(pairs_needed, max_tile_count, minimum: "Capacity | None" = None) -> "Capacity":
        """The smallest power-of-two capacity holding the given needs (never below ``minimum``)."""
        def pow2(v, lo):
            v = max(int(math.ceil(float(v))), lo, 1)
            return 1 << (v - 1).bit_length()

        lo_p, lo_t = (minimum.pairs, minimum.per_tile) if minimum is not None else (1024, 16)
        return Capacity(pairs=pow2(pairs_needed, lo_p), per_tile=pow2(max_tile_count, lo_t))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderOutput:
    """What the renderer returns.

    Attributes:
      rgb: (H, W, 3) colour.
      alpha: (H, W) accumulated opacity, 1 - final transmittance.
      depth: (H, W) alpha-normalised expected intersection depth (0 where alpha is 0).
      normal: (H, W, 3) alpha-weighted camera-frame normals (facing the camera).
      distortion: (H, W) the 2DGS depth-distortion term sum_{i<j} w_i w_j (m_i - m_j)^2, m the
        depth mapped to [0, 1) by m = f/(f-n) (1 - n/z) with n = 0.2, f = 1000 (as 2DGS).
      max_contrib_count: (C,) int32, pixels at which each splat has the largest weight
        alpha_i T_i (paper Eq. 6); no gradient.
      radius_px: (C,) float, screen-space half-extent of each splat's footprint (0: not visible).
      visible: (C,) bool, binned into at least one tile.
      pairs_needed: () float32, (splat, tile) pairs the view needs.
      max_tile_count: () int32, the most splats any tile needs.
      overflow: () bool, some pair or slot did not fit the capacity (the image is then truncated).
    """

    rgb: jax.Array
    alpha: jax.Array
    depth: jax.Array
    normal: jax.Array
    distortion: jax.Array
    max_contrib_count: jax.Array
    radius_px: jax.Array
    visible: jax.Array
    pairs_needed: jax.Array
    max_tile_count: jax.Array
    overflow: jax.Array


# ------------------------------------------------------------------------------------------------
# Projection
# ------------------------------------------------------------------------------------------------
def _cross(a, b):
    return jnp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                      a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                      a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _project(scene: Scene, camera: Camera, config: RenderConfig, screen_offset, active_sh_degree,
             alpha_peak):
    """Per-splat quantities. Returns a dict of (C, ...) arrays (see the keys below)."""
    dt = scene.means.dtype
    K = camera.K.astype(dt)
    w2c = camera.world_to_camera.astype(dt)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    R = quat_to_rotmat(scene.quats)
    s = jnp.exp(scene.log_scales)
    p = scene.means @ Rc.T + tc                        # (C, 3) camera-frame centre
    tu = (R[:, :, 0] * s[:, :1]) @ Rc.T                # (C, 3) scaled tangent axes, camera frame
    tv = (R[:, :, 1] * s[:, 1:]) @ Rc.T
    nrm = R[:, :, 2] @ Rc.T
    # M maps splat-plane homogeneous (u, v, 1) to image homogeneous (x w, y w, w), w = camera z.
    M = jnp.einsum("ij,cjk->cik", K, jnp.stack([tu, tv, p], axis=-1))
    M0, M1, M2 = M[:, 0], M[:, 1], M[:, 2]
    # (u, v, 1) ~ adj(M) (x, y, 1) = x A + y B + Cc.
    A, B, Cc = _cross(M1, M2), _cross(M2, M0), _cross(M0, M1)
    depth = p[:, 2]
    in_front = depth > config.near
    mu = safe_div(M[:, :2, 2], jnp.where(in_front, depth, 1.0)[:, None])
    if screen_offset is not None:
        off = screen_offset.astype(dt)
        Cc = Cc - off[:, :1] * A - off[:, 1:] * B
        mu = mu + off

    # Colour from SH, one view direction per splat.
    cam_center = -jnp.linalg.solve(Rc, tc)  # exact even if a float32 pose is not quite orthonormal
    dirs = safe_normalize(scene.means - cam_center)
    degree = scene.sh_degree
    basis = sh_basis(dirs, degree, active_sh_degree)
    color = jnp.maximum(jnp.einsum("ck,ckj->cj", basis, scene.sh) + 0.5, 0.0)

    normal = jnp.where((jnp.sum(nrm * p, axis=-1) > 0)[:, None], -nrm, nrm)
    opacity = jax.nn.sigmoid(scene.opacity_logits) * (scene.active > 0)

    # Culling and screen-space bounds (no gradient): alpha >= 1/255 needs
    # rho <= 2 log(255 * opacity * max A) =: r2.
    peak = lax.stop_gradient(opacity * alpha_peak)
    visible = in_front & (peak >= ALPHA_MIN)
    r2 = jnp.where(visible, 2.0 * jnp.log(jnp.maximum(peak, ALPHA_MIN) * 255.0), 0.0)
    Ms = lax.stop_gradient(M)
    # Dual conic of the projected circle u^2 + v^2 = r2: M diag(r2, r2, -1) M^T.
    Q = (r2[:, None, None] * jnp.einsum("cia,cja->cij", Ms[:, :, :2], Ms[:, :, :2])
         - Ms[:, :, None, 2] * Ms[:, None, :, 2])
    q22 = Q[:, 2, 2]
    bounded = q22 < 0
    q22s = jnp.where(bounded, q22, -1.0)
    cx, cy = Q[:, 0, 2] / q22s, Q[:, 1, 2] / q22s
    hx = jnp.sqrt(jnp.maximum(cx * cx - Q[:, 0, 0] / q22s, 0.0))
    hy = jnp.sqrt(jnp.maximum(cy * cy - Q[:, 1, 1] / q22s, 0.0))
    r_lp = jnp.sqrt(0.5 * r2)  # the low-pass disc: 2 |d|^2 <= r2
    mus = lax.stop_gradient(mu)
    big = 1e9
    xmin = jnp.where(bounded, jnp.minimum(cx - hx, mus[:, 0] - r_lp), -big)
    xmax = jnp.where(bounded, jnp.maximum(cx + hx, mus[:, 0] + r_lp), big)
    ymin = jnp.where(bounded, jnp.minimum(cy - hy, mus[:, 1] - r_lp), -big)
    ymax = jnp.where(bounded, jnp.maximum(cy + hy, mus[:, 1] + r_lp), big)
    radius = jnp.where(visible, jnp.maximum(jnp.maximum(xmax - xmin, ymax - ymin) * 0.5, r_lp), 0.0)

    packed = jnp.concatenate([
        A, B, Cc, M2, mu, opacity[:, None], color, normal, depth[:, None]], axis=-1)
    return dict(packed=packed, depth=depth, visible=visible, bounds=(xmin, xmax, ymin, ymax),
                radius=jnp.where(jnp.isfinite(radius), radius, big))


# Column layout of the packed per-splat array.
_A, _B, _C, _M2, _MU, _OP, _COL, _NRM, _DEP = (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12),
                                               slice(12, 14), 14, slice(15, 18), slice(18, 21), 21)


# ------------------------------------------------------------------------------------------------
# Binning
# ------------------------------------------------------------------------------------------------
def _tile_ranges(bounds, visible, tile_size, tiles_x, tiles_y):
    xmin, xmax, ymin, ymax = bounds

    def rng(lo, hi, n):
        lo = jnp.floor(jnp.clip((lo - 0.5) / tile_size, -1.0, n + 1.0))
        hi = jnp.floor(jnp.clip((hi - 0.5) / tile_size, -1.0, n + 1.0)) + 1
        lo = jnp.where(jnp.isnan(lo), 0.0, lo)
        hi = jnp.where(jnp.isnan(hi), float(n), hi)
        return jnp.clip(lo, 0, n).astype(jnp.int32), jnp.clip(hi, 0, n).astype(jnp.int32)

    tx0, tx1 = rng(xmin, xmax, tiles_x)
    ty0, ty1 = rng(ymin, ymax, tiles_y)
    ok = visible & (tx1 > tx0) & (ty1 > ty0)
    return tx0, tx1, ty0, ty1, ok


def _tile_histogram(tx0, tx1, ty0, ty1, ok, tiles_x, tiles_y):
    """Exact number of splats per tile, by a 2D difference array: O(C + tiles)."""
    one = ok.astype(jnp.int32)
    diff = jnp.zeros((tiles_y + 1, tiles_x + 1), jnp.int32)
    diff = diff.at[ty0, tx0].add(one).at[ty0, tx1].add(-one)
    diff = diff.at[ty1, tx0].add(-one).at[ty1, tx1].add(one)
    return jnp.cumsum(jnp.cumsum(diff, axis=0), axis=1)[:tiles_y, :tiles_x].reshape(-1)


def _bin(depth, tx0, tx1, ty0, ty1, ok, tiles_x, num_tiles, pair_capacity):
    """Depth-ordered per-tile lists.

    Returns (sorted_ids (P,), tile_start (T,), tile_count_binned (T,)): the splat ids of pairs
    sorted by tile, each tile's run in front-to-back order.
    """
    C = depth.shape[0]
    counts = jnp.where(ok, (tx1 - tx0) * (ty1 - ty0), 0)
    key = jnp.where(ok, depth, jnp.inf)
    order = jnp.argsort(key, stable=True).astype(jnp.int32)
    counts_s = counts[order]
    ends = jnp.cumsum(counts_s)
    starts = ends - counts_s
    total = ends[-1]
    p = jnp.arange(pair_capacity, dtype=jnp.int32)
    mark = jnp.full((pair_capacity,), -1, jnp.int32)
    mark = mark.at[jnp.where(counts_s > 0, starts, pair_capacity)].max(
        jnp.arange(C, dtype=jnp.int32), mode="drop")
    rank = jnp.maximum(lax.cummax(mark), 0)
    g = order[rank]
    k = p - starts[rank]
    w = jnp.maximum(tx1[g] - tx0[g], 1)
    tile = (ty0[g] + k // w) * tiles_x + tx0[g] + k % w
    valid = (p < total) & (k >= 0)
    tile = jnp.where(valid, tile, num_tiles)
    tile_sorted, ids_sorted = lax.sort((tile, g), num_keys=1, is_stable=True)
    binned = jnp.zeros((num_tiles + 1,), jnp.int32).at[tile].add(1)[:num_tiles]
    tile_start = jnp.cumsum(binned) - binned
    return ids_sorted, tile_start, binned


# ------------------------------------------------------------------------------------------------
# Compositing
# ------------------------------------------------------------------------------------------------
def _uv(s0, s1, s2):
    """(u, v) = (s0, s1) / s2 with "no intersection" (ok False) when the ray is (nearly) parallel."""
    ok = jnp.abs(s2) * _UV_LIMIT > jnp.maximum(jnp.abs(s0), jnp.abs(s1))
    inv = 1.0 / jnp.where(ok, s2, 1.0)
    u = jnp.where(ok, s0 * inv, 0.0)
    v = jnp.where(ok, s1 * inv, 0.0)
    return u, v, ok


def _sample_bank(atlas: tex.Atlas, gid, u, v, footprint, config: RenderConfig, use_mip: bool,
                 default: float):
    """Texture values of the splats ``gid`` (S,) at (u, v) (pixels, S); (pixels, S, ch)."""
    base, side_p, n = atlas.base[gid], atlas.bucket_side[gid], atlas.size[gid]
    has = atlas.has[gid]
    if not use_mip or config.mip == "none":
        val = tex.sample(atlas.texels, base, side_p, n.astype(jnp.int32), u, v)
    else:
        L = atlas.max_level[gid]
        trilinear = config.mip == "trilinear"
        lev = tex.mip_level(footprint, n, L, config.lambda_mip, trilinear)
        ni = n.astype(jnp.int32)

        def at_level(l):
            return tex.sample(atlas.texels, *tex.level_address(base, side_p, ni, l), u, v)

        if trilinear:
            l0 = jnp.floor(lev)
            frac = (lev - l0)[..., None]
            l0i = l0.astype(jnp.int32)
            l1i = jnp.minimum(l0i + 1, L)
            val = (1 - frac) * at_level(l0i) + frac * at_level(l1i)
        else:
            val = at_level(lev)
    return jnp.where(has[:, None], val, default)


def _composite_tiles(packed, rgb_atlas, alpha_atlas, ids_sorted, tile_start, binned, config,
                     capacity: Capacity, tiles_x, num_tiles):
    """Composites all tiles. Returns per-tile (T, ts*ts, ...) rgb, T_final, depth, normal, best id."""
    ts = config.tile_size
    S = capacity.per_tile
    npx = ts * ts
    bg = jnp.asarray(config.background, packed.dtype)
    iy, ix = jnp.divmod(jnp.arange(npx, dtype=jnp.int32), ts)
    need_footprint = config.mip != "none" and (
        (rgb_atlas is not None and config.rgb_mip) or (alpha_atlas is not None and config.alpha_mip))

    def tile_fn(t):
        start, cnt = tile_start[t], binned[t]
        slot = jnp.arange(S, dtype=jnp.int32)
        valid = slot < cnt
        gid = jnp.where(valid, ids_sorted[jnp.clip(start + slot, 0, ids_sorted.shape[0] - 1)], 0)
        pk = packed[gid]                                              # (S, F)
        x = ((t % tiles_x) * ts + ix).astype(packed.dtype)[:, None] + 0.5   # (npx, 1)
        y = ((t // tiles_x) * ts + iy).astype(packed.dtype)[:, None] + 0.5
        A, B, Cc = pk[:, _A], pk[:, _B], pk[:, _C]
        s = [x * A[:, i] + y * B[:, i] + Cc[:, i] for i in range(3)]  # each (npx, S)
        u, v, ok = _uv(*s)
        rho3d = jnp.where(ok, u * u + v * v, 1e8)
        dx, dy = x - pk[:, _MU][:, 0], y - pk[:, _MU][:, 1]
        rho2d = 2.0 * (dx * dx + dy * dy)
        use3d = rho3d <= rho2d
        G = jnp.exp(-0.5 * jnp.minimum(rho3d, rho2d))
        M2 = pk[:, _M2]
        z = jnp.where(use3d, M2[:, 0] * u + M2[:, 1] * v + M2[:, 2], pk[:, _DEP])

        footprint = None
        if need_footprint:
            ux, vx, okx = _uv(*(s[i] + A[:, i] for i in range(3)))
            uy, vy, oky = _uv(*(s[i] + B[:, i] for i in range(3)))
            d12 = safe_sqrt((ux - u) ** 2 + (vx - v) ** 2)
            d13 = safe_sqrt((uy - u) ** 2 + (vy - v) ** 2)
            footprint = jnp.where(ok & okx & oky, jnp.maximum(d12, d13), _UV_LIMIT)

        a = pk[:, _OP] * G
        if alpha_atlas is not None:
            a = a * _sample_bank(alpha_atlas, gid, u, v, footprint, config, config.alpha_mip, 1.0)[..., 0]
        a = jnp.clip(a, 0.0, ALPHA_MAX)
        keep = valid & (a >= ALPHA_MIN) & (z > config.near)
        a = jnp.where(keep, a, 0.0)
        log1m = jnp.log1p(-a)
        cum = jnp.cumsum(log1m, axis=1)
        include = jnp.exp(cum) >= T_MIN
        w = jnp.where(include, a * jnp.exp(cum - log1m), 0.0)            # (npx, S)
        log_t = jnp.sum(jnp.where(include, log1m, 0.0), axis=1)
        t_final = jnp.exp(log_t)
        rgb = w @ pk[:, _COL]
        if rgb_atlas is not None:
            offs = _sample_bank(rgb_atlas, gid, u, v, footprint, config, config.rgb_mip, 0.0)
            rgb = rgb + jnp.einsum("ps,psc->pc", w, offs)
        rgb = rgb + t_final[:, None] * bg
        depth = jnp.sum(w * z, axis=1)
        normal = w @ pk[:, _NRM]
        # 2DGS depth distortion: sum_{i<j} w_i w_j (m_i - m_j)^2 = A D2 - D1^2 with m the
        # NDC-mapped depth, A = sum w, D1 = sum w m, D2 = sum w m^2.
        m = _DIST_FAR / (_DIST_FAR - _DIST_NEAR) * (1.0 - _DIST_NEAR / jnp.where(keep, z, 1.0))
        wm = w * m
        d1 = jnp.sum(wm, axis=1)
        distortion = (1.0 - t_final) * jnp.sum(wm * m, axis=1) - d1 * d1
        best_slot = jnp.argmax(w, axis=1)
        best = jnp.where(jnp.max(w, axis=1) > 0, gid[best_slot], -1)
        return rgb, t_final, depth, normal, distortion, best

    # Per-batch work bounded to about 2^16 (pixel, slot) pairs per tile step times the batch.
    tb = max(1, min(config.tiles_per_batch, (1 << 20) // (npx * S)))
    nb = -(-num_tiles // tb)
    tiles = jnp.arange(nb * tb, dtype=jnp.int32).reshape(nb, tb)
    tiles = jnp.minimum(tiles, num_tiles - 1)
    out = lax.map(jax.checkpoint(jax.vmap(tile_fn)), tiles)
    return jax.tree_util.tree_map(lambda o: o.reshape((nb * tb,) + o.shape[2:])[:num_tiles], out)


def _untile(x, tiles_x, tiles_y, ts, H, W):
    """(T, ts*ts, ...) per-tile values -> (H, W, ...) image."""
    rest = x.shape[2:]
    x = x.reshape((tiles_y, tiles_x, ts, ts) + rest)
    x = jnp.moveaxis(x, 2, 1).reshape((tiles_y * ts, tiles_x * ts) + rest)
    return x[:H, :W]


def _alpha_peak(scene: Scene):
    """(C,) the largest alpha-texture value of each splat (1 without alpha texture); no gradient."""
    if scene.alpha is None:
        return jnp.ones_like(scene.opacity_logits)
    bank = scene.alpha
    bucket = lax.stop_gradient(bank.bucket).astype(jnp.int32)
    slot = lax.stop_gradient(bank.slot).astype(jnp.int32)
    peak = jnp.ones_like(scene.opacity_logits)
    for b, data in enumerate(bank.buckets):
        if data.shape[0] == 0:
            continue
        m = jnp.max(lax.stop_gradient(data), axis=(1, 2, 3))
        peak = jnp.where(bucket == b, m[jnp.clip(slot, 0, data.shape[0] - 1)], peak)
    return peak


def _render(scene: Scene, camera: Camera, config: RenderConfig, capacity: Capacity,
            screen_offset=None, active_sh_degree=None) -> RenderOutput:
    TRACE_COUNTS[(config, capacity)] += 1
    H, W, ts = camera.height, camera.width, config.tile_size
    tiles_x, tiles_y = -(-W // ts), -(-H // ts)
    num_tiles = tiles_x * tiles_y
    proj = _project(scene, camera, config, screen_offset, active_sh_degree, _alpha_peak(scene))
    tx0, tx1, ty0, ty1, ok = _tile_ranges(proj["bounds"], proj["visible"], ts, tiles_x, tiles_y)
    hist = _tile_histogram(tx0, tx1, ty0, ty1, ok, tiles_x, tiles_y)
    pairs_needed = jnp.sum(jnp.where(ok, (tx1 - tx0) * (ty1 - ty0), 0).astype(jnp.float32))
    max_tile = jnp.max(hist)
    ids_sorted, tile_start, binned = _bin(proj["depth"], tx0, tx1, ty0, ty1, ok, tiles_x, num_tiles,
                                          capacity.pairs)

    use_mip = config.mip != "none"
    rgb_atlas = alpha_atlas = None
    if scene.rgb is not None:
        rgb_atlas = tex.build_atlas(scene.rgb, use_mip and config.rgb_mip)
    if scene.alpha is not None:
        alpha_atlas = tex.build_atlas(scene.alpha, use_mip and config.alpha_mip)
    rgb, t_final, depth, normal, distortion, best = _composite_tiles(
        proj["packed"], rgb_atlas, alpha_atlas, ids_sorted, tile_start, binned, config, capacity,
        tiles_x, num_tiles)
    rgb = _untile(rgb, tiles_x, tiles_y, ts, H, W)
    alpha = 1.0 - _untile(t_final, tiles_x, tiles_y, ts, H, W)
    depth = _untile(depth, tiles_x, tiles_y, ts, H, W)
    depth = jnp.where(alpha > 1e-6, depth / jnp.maximum(alpha, 1e-6), 0.0)
    normal = _untile(normal, tiles_x, tiles_y, ts, H, W)
    distortion = _untile(distortion, tiles_x, tiles_y, ts, H, W)
    best = _untile(best, tiles_x, tiles_y, ts, H, W).reshape(-1)
    C = scene.capacity
    counts = jnp.zeros((C,), jnp.int32).at[jnp.where(best >= 0, best, C)].add(1, mode="drop")
    overflow = (pairs_needed > capacity.pairs) | (max_tile > capacity.per_tile)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, distortion=distortion,
                        max_contrib_count=counts,
                        radius_px=jnp.where(ok, proj["radius"], 0.0), visible=ok,
                        pairs_needed=pairs_needed, max_tile_count=max_tile, overflow=overflow)


#: The jitted renderer: ``render_jit(scene, camera, config=..., capacity=..., screen_offset=None,
#: active_sh_degree=None)``. It never grows its capacity: check ``output.overflow`` on the host
#: (training does, between steps) and call again with ``Capacity.fit(output.pairs_needed,
#: output.max_tile_count)``. ``screen_offset`` ((C, 2) zeros) is a gradient hook: its gradient is
#: the loss gradient with respect to a screen-space translation of each splat, in pixels (the
#: densification statistic); ``active_sh_degree`` (traced int) masks SH bands above it.
render_jit = jax.jit(_render, static_argnames=("config", "capacity"))

_capacity_cache: dict = {}


def _count(scene: Scene, camera: Camera, config: RenderConfig):
    ts = config.tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    proj = _project(scene, camera, config, None, None, _alpha_peak(scene))
    tx0, tx1, ty0, ty1, ok = _tile_ranges(proj["bounds"], proj["visible"], ts, tiles_x, tiles_y)
    hist = _tile_histogram(tx0, tx1, ty0, ty1, ok, tiles_x, tiles_y)
    return jnp.sum(jnp.where(ok, (tx1 - tx0) * (ty1 - ty0), 0).astype(jnp.float32)), jnp.max(hist)


#: Exact (pairs_needed, max_tile_count) of a view, without rendering it.
count_pairs = jax.jit(_count, static_argnames=("config",))


def render(scene: Scene, camera: Camera, config: RenderConfig = RenderConfig(), *,
           capacity: Capacity | None = None, active_sh_degree=None) -> RenderOutput:
    """Renders ``scene`` from ``camera``; never returns a truncated image.

    Args:
      scene: the splats (C slots).
      camera: the view (H = camera.height, W = camera.width).
      config: static options (:class:`RenderConfig`).
      capacity: optional starting capacity; by default the last one that fitted this scene capacity
        and image size, or the exact need counted for this view.
      active_sh_degree: optional int, SH bands above it are ignored.
    Returns:
      :class:`RenderOutput` with (H, W) images. If the capacity overflows it is grown to fit and the
      view rendered again (a warning says so, once per growth). Differentiable with ``jax.grad``
      (outside ``jax.jit``; under an outer jit use :data:`render_jit` and check ``overflow``).
    """
    key = (scene.capacity, camera.width, camera.height, config.tile_size)
    cap = capacity or _capacity_cache.get(key)
    if cap is None:
        try:
            needed, max_tile = count_pairs(lax.stop_gradient(scene), camera, config)
            cap = Capacity.fit(float(needed), int(max_tile))
        except jax.errors.ConcretizationTypeError:
            cap = Capacity()
    for _ in range(4):
        out = render_jit(scene, camera, config=config, capacity=cap,
                         active_sh_degree=active_sh_degree)
        try:
            overflowed = bool(out.overflow)
        except jax.errors.ConcretizationTypeError:
            return out  # traced under an outer jit: the caller checks `overflow`
        if not overflowed:
            _capacity_cache[key] = cap
            return out
        new = Capacity.fit(float(out.pairs_needed), int(out.max_tile_count), minimum=cap)
        warnings.warn(f"render: capacity {cap} too small for this view (needs "
                      f"{int(out.pairs_needed)} pairs, {int(out.max_tile_count)} splats in one tile); "
                      f"growing to {new} and rendering again.", stacklevel=2)
        cap = new
    raise RuntimeError("render: capacity did not converge; this is a bug, please report it.")
