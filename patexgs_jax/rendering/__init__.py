"""Differentiable tile renderer for textured 2D Gaussian splats with per-pixel mipmaps.

Conventions (fixed for the package)
  * Cameras: OpenCV (x right, y down, z forward), world-to-camera 4x4; pixel (i, j) has its centre
    at continuous coordinates (j + 0.5, i + 0.5).
  * Kernel (2DGS): the ray of a pixel meets the splat plane at (u, v), in units of the scales
    (homogeneous ray-splat intersection); ``rho3d = u^2 + v^2``; the screen-space low-pass is
    ``rho2d = 2 |x - mu2d|^2`` in pixels; ``G = exp(-0.5 min(rho3d, rho2d))``. The depth of a
    pair is the intersection's camera z where rho3d <= rho2d, else the splat centre's. A ray so
    nearly parallel to the splat plane that |u| or |v| would exceed 1e4 has no 3D intersection: rho3d is taken as 1e8 (G from the low-pass only) and its texture lookups use the
    splat centre (u, v) = (0, 0) (whose mip footprint is the coarsest level).
  * ``RenderConfig(coverage="prefilter")`` (the ``patexgs`` methods) replaces ``G`` and the
    low-pass by the EWA resampling filter: with K the 2x2 Jacobian d(pixel)/d(u, v) at the splat's
    centre, the splat-plane Gaussian convolved with a screen Gaussian of variance ``v``
    (``pixel_var``, widened per axis so the filtered screen variance is at least ``min_var``) is
    ``G = exp(-0.5 h^T P h)``, h the pixel's (u, v) offset from the centre mapped through K, P =
    K^T (K K^T + V)^-1 K, and the opacity is multiplied by the coverage factor
    ``|det K| / sqrt(det(K K^T + V))`` (<= 1), which keeps the splat's integrated coverage. Pairs
    are skipped below 1/255 times that factor, so a faint sub-pixel splat still composites. G is
    zero outside the screen ellipse ``d^T S^-1 d <= SUPPORT_Q`` (S = K K^T + V, d the pixel's
    offset from the centre): the filter is affine about the centre, and where P maps a near
    edge-on splat's pixel to far along its plane, the kernel stops at twice the affine footprint.
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
  depth-ordered per-tile lists with one stable sort of (tile) keys over pairs generated in depth
  order; ``composite`` walks each tile's list front to back in chunks of ``RenderConfig.chunk``
  splats (pixels x chunk at a time) and stops the tile once every pixel saturated or the list ended,
  so the work follows the splats that actually contribute. It has a hand-written backward pass
  (``jax.custom_vjp``) that re-walks the chunks and stores nothing per pair: backward memory is
  the inputs plus a few per-pixel accumulators. Within a chunk, the compositing's and the kernel's
  backward are derived by hand (:func:`_chunk_contrib_bwd`, :func:`_chunk_geometry_bwd`: fewer
  passes over the (pixels x splats) block than autodiff's, and the per-splat sums as matrix
  products); the texture lookups' backward is autodiff's.

  Textures: only the (pixel, splat) pairs of a chunk step that can reach alpha 1/255 (bounded by
  ``opacity * G * max(alpha texels)``) at pixels still compositing are looked up, gathered into
  passes of ``RenderConfig.texture_pairs`` of the step's pairs; their texture
  values are spread back into the dense (pixels x splats) block, zero for the pairs skipped, which
  are not composited anyway. A bilinear lookup is one gather of the four texels of a 2 x 2 block
  (see :mod:`patexgs_jax.textures`) per bank and mip level read; the backward adds each lookup's
  texel cotangents to two rows of a paired (texel r, texel r + 1) accumulator. The per-lookup
  address and weight arithmetic is computed once (:func:`_barrier`), not re-derived inside every
  per-texel and per-channel consumer.

  The one static capacity (``Capacity.pairs``, the length of the sorted pair list) is checked
  against the exact need (counted before binning) and the need is returned, so callers grow the
  capacity and render again; :func:`render` does this itself and never returns a truncated image.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import warnings
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
from jax import lax

from .. import textures as tex
from ..camera import Camera
from ..math import quat_to_rotmat, safe_div, safe_log2, safe_normalize, safe_sqrt, sh_basis
from ..scene import Scene

MIP_MODES = ("none", "nearest", "trilinear")
COVERAGE_MODES = ("lowpass", "prefilter")
#: Eq. 11's lambda_mip per coverage mode when RenderConfig.lambda_mip is None (see RenderConfig).
LAMBDA_MIP_DEFAULT = {"lowpass": 0.4, "prefilter": 1.0 / 6.0}
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
#: With the prefilter, a splat's kernel is cut outside d^T S^-1 d <= SUPPORT_Q on screen (S its
#: filtered screen covariance, d the offset from its centre): twice the radius where a fully opaque
#: splat's kernel falls to 1/255 (see _project).
SUPPORT_Q = 4.0 * 2.0 * math.log(255.0)
_UV_LIMIT = 1e4  # |u|, |v| beyond this count as "no intersection" (G3d underflows long before)
_DIST_NEAR, _DIST_FAR = 0.2, 1000.0  # the NDC depth mapping of the 2DGS distortion loss

#: How many times the jitted renderer has been traced, per configuration (tests assert on it).
TRACE_COUNTS: collections.Counter = collections.Counter()


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Static rendering options (hashable; a new value compiles a new renderer).

    Attributes:
      coverage: how a splat covers a pixel. "lowpass" (default): the 2DGS kernel
        ``exp(-0.5 min(rho3d, 2 |x - mu2d|^2))``, which keeps a sub-pixel splat about a pixel wide
        at its full opacity (the paper's literal Eqs. 11-13 and the 2DGS baselines). "prefilter":
        the splat-plane Gaussian convolved with a Gaussian pixel filter of variance
        ``pixel_var`` (px^2), mapped onto the plane at the splat's centre (EWA resampling), with
        the opacity scaled so that the splat's integrated coverage is kept: a splat smaller than a
        pixel fades instead of growing (the PATexGS methods' mode).
      pixel_var: the prefilter's pixel filter variance in px^2 (a box pixel has 1/12).
      min_var: with the prefilter, the smallest screen variance (px^2) of a filtered splat along
        any axis: where a splat is narrower, its filter is widened to reach it (its coverage still
        kept), so that a sub-pixel splat's summed alpha does not depend on where it falls between
        pixel centres (within 3%; with 0, the filter is ``pixel_var`` everywhere and a 0.1-pixel
        splat's summed alpha varies from 0.6 to 1.1 times its coverage as it moves).
      mip: "none" (level 0 only), "nearest" (paper Eq. 11, default) or "trilinear".
      lambda_mip: the paper's lambda_mip in Eq. 11; None takes the coverage mode's value
        (:data:`LAMBDA_MIP_DEFAULT`: 0.4 as the paper for "lowpass"; 1/6 for "prefilter", where
        ``lambda n D`` is then the texels per pixel of a texture spanning 6 scale units).
      rgb_mip: use mipmaps for the RGB textures (False: level 0 always; paper Table 3 ablation).
      alpha_mip: use mipmaps for the alpha textures (paper Eq. 13).
      background: RGB colour behind everything.
      near: near-plane depth; splats whose centre, or pairs whose intersection, is not beyond it are
        skipped.
      tile_size: tile side in pixels.
      chunk: splats evaluated together per tile step; a tile stops after the chunk in which all its
        pixels saturated (transmittance < 1e-4) or its list ended.
      tile_batch: at most this many tiles advanced together (sorted by list length, so they finish
        at similar steps; fewer when that spreads the tiles more evenly over the batches).
      texture_pairs: texture lookups per pass, as a share of a chunk step's (tile, pixel, splat)
        pairs. Only the pairs that can reach alpha 1/255 are looked up, gathered into as many
        passes of this size as they need (a few percent to a few tens of percent of the pairs
        contribute). Any value gives the same image; 1.0 looks up every pair without gathering
        them (the dense path, faster only for the forward of cheap lookups: one alpha bank
        without mipmaps).
    """

    mip: str = "nearest"
    lambda_mip: float | None = None
    coverage: str = "lowpass"
    pixel_var: float = 0.1
    min_var: float = 0.3
    rgb_mip: bool = True
    alpha_mip: bool = True
    background: tuple = (0.0, 0.0, 0.0)
    near: float = 0.01
    tile_size: int = 16
    chunk: int = 32
    tile_batch: int = 8
    texture_pairs: float = 1 / 32

    def __post_init__(self):
        if self.mip not in MIP_MODES:
            raise ValueError(f"RenderConfig.mip must be one of {MIP_MODES}, got {self.mip!r}.")
        if self.coverage not in COVERAGE_MODES:
            raise ValueError(f"RenderConfig.coverage must be one of {COVERAGE_MODES}, got {self.coverage!r}.")
        if self.lambda_mip is None:
            object.__setattr__(self, "lambda_mip", LAMBDA_MIP_DEFAULT[self.coverage])
        if not self.pixel_var > 0:
            raise ValueError(f"pixel_var must be positive, got {self.pixel_var}.")
        if not self.min_var >= 0:
            raise ValueError(f"min_var must be >= 0, got {self.min_var}.")
        if not self.lambda_mip > 0:
            raise ValueError(f"lambda_mip must be positive, got {self.lambda_mip}.")
        if len(tuple(self.background)) != 3:
            raise ValueError("background must be an RGB triple.")
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))
        if self.tile_size < 1 or self.chunk < 1 or self.tile_batch < 1:
            raise ValueError("tile_size, chunk and tile_batch must be positive.")
        if not self.near > 0:
            raise ValueError(f"near must be positive, got {self.near}.")
        if not 0 < self.texture_pairs <= 1:
            raise ValueError(f"texture_pairs must be in (0, 1], got {self.texture_pairs}.")


@dataclasses.dataclass(frozen=True)
class Capacity:
    """Static buffer size of the tile lists.

    Attributes:
      pairs: total (splat, tile) pairs that can be binned (the length of the sorted pair list).
    """

    pairs: int = 1 << 14

    @staticmethod
    def fit(pairs_needed, minimum: "Capacity | None" = None) -> "Capacity":
        """The smallest power-of-two capacity (at least 1024, never below ``minimum``) that holds
        ``pairs_needed`` pairs."""
        v = max(int(math.ceil(float(pairs_needed))), minimum.pairs if minimum is not None else 1024, 1)
        return Capacity(pairs=1 << (v - 1).bit_length())


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
      dominant: (H, W) int32, the splat with the largest weight at each pixel (-1: none); no
        gradient (e.g. to look up per-pixel texture sizes or mip levels).
      radius_px: (C,) float, screen-space half-extent of each splat's footprint (0: not visible).
      visible: (C,) bool, binned into at least one tile.
      pairs_needed: () float32, (splat, tile) pairs the view needs.
      max_tile_count: () int32, the most splats any tile lists (a statistic).
      overflow: () bool, some pair did not fit the capacity (the image is then truncated).
    """

    rgb: jax.Array
    alpha: jax.Array
    depth: jax.Array
    normal: jax.Array
    distortion: jax.Array
    max_contrib_count: jax.Array
    dominant: jax.Array
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


def _prefilter(M, mu, depth, pixel_var, min_var):
    """The prefiltered kernel of each splat (coverage "prefilter").

    With K = d(x, y)/d(u, v) the splat's screen Jacobian at its centre (pixels per scale unit), the
    splat's Gaussian exp(-0.5 |h|^2) convolved with the pixel filter N(0, pixel_var I) (on screen,
    mapped onto the plane by K^-1) is ``coverage * exp(-0.5 h^T P h)`` with
    ``P = K^T (K K^T + pixel_var I)^-1 K`` and ``coverage = |det K| / sqrt(det(K K^T + pixel_var I))``
    (EWA; Mip-Splatting's 2D filter in the splat plane): the integral over the screen is kept.
    The filter's variance is raised above ``pixel_var`` where the splat is narrower than
    ``min_var`` (px^2) along its narrowest screen axis, to ``min_var`` minus the splat's variance
    there: a sampled Gaussian narrower than about half a pixel sums to its integral only up to
    +-50% (depending on where its centre falls between pixel centres), so sub-pixel splats would
    flicker as they move.
    Both forms stay finite for an edge-on splat (K singular: coverage 0). K is normalised by its
    largest entry first, so that neither tiny nor huge splats overflow float32.

    Args:
      M: (C, 3, 3) splat plane (u, v, 1) to image homogeneous coordinates; mu: (C, 2) the centres
        on screen; depth: (C,) the centres' depth (positive).
    Returns:
      (C, 3) (p, r, t) of P, (C,) the coverage factor in [0, 1], (C, 2) the diagonal (xx, yy) of
      the filtered splat's screen covariance S = K K^T + e I (px^2), e the filter's variance, and
      (C, 3) S^-1 (xx, xy, yy).
    """
    K = (M[:, :2, :2] - mu[:, :, None] * M[:, 2, None, :2]) / depth[:, None, None]
    k = jnp.maximum(jnp.max(jnp.abs(K), axis=(1, 2)), 1e-6 * math.sqrt(pixel_var))
    K = K / k[:, None, None]
    k00, k01, k10, k11 = K[:, 0, 0], K[:, 0, 1], K[:, 1, 0], K[:, 1, 1]
    # With f = |K|_F^2 = tr(K K^T) and det = det K: det(K K^T + e I) = det^2 + e f + e^2 and
    # P = (det^2 I + e adj(K)^T adj(K)) / (det^2 + e f + e^2), whose denominators are sums of
    # non-negative terms. The textbook K^T (K K^T + e I)^-1 K cancels catastrophically in float32
    # for a needle: its narrow axis is lost.
    f = k00 * k00 + k01 * k01 + k10 * k10 + k11 * k11
    det = k00 * k11 - k01 * k10
    det2 = det * det
    if min_var > 0:  # the splat's smallest screen variance (over k^2): det^2 / the largest
        lmax = 0.5 * f + safe_sqrt(0.25 * (k00 * k00 + k01 * k01 - k10 * k10 - k11 * k11) ** 2
                                   + (k00 * k10 + k01 * k11) ** 2)
        e = jnp.maximum(pixel_var, min_var - k * k * det2 / lmax) / (k * k)
    else:
        e = pixel_var / (k * k)
    den = det2 + e * f + e * e
    p = (det2 + e * (k00 * k00 + k10 * k10)) / den
    r = e * (k00 * k01 + k10 * k11) / den
    t = (det2 + e * (k01 * k01 + k11 * k11)) / den
    coverage = jnp.abs(det) / jnp.sqrt(den)
    k2 = k * k
    # S^-1 = adj(S) / det S, det S = k^4 den: from den, which does not cancel for a needle.
    inv_screen = jnp.stack([k10 * k10 + k11 * k11 + e, -(k00 * k10 + k01 * k11), k00 * k00 + k01 * k01 + e],
                           axis=-1) / (k2 * den)[:, None]
    screen = jnp.stack([k2 * (k00 * k00 + k01 * k01 + e), k2 * (k10 * k10 + k11 * k11 + e)], axis=-1)
    return jnp.stack([p, r, t], axis=-1), coverage, screen, inv_screen


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
    prefilter = config.coverage == "prefilter"
    if prefilter:
        conic, coverage, screen, inv_screen = _prefilter(M, mu, jnp.where(in_front, depth, 1.0),
                                                         config.pixel_var, config.min_var)
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
    # rho <= 2 log(255 * opacity * max A) =: r2 (with the prefilter, alpha / coverage >= 1/255 and
    # q <= r2: see _alpha_min).
    peak = lax.stop_gradient(opacity * alpha_peak)
    if prefilter:
        opacity = opacity * coverage

    visible = in_front & (peak >= ALPHA_MIN)
    r2 = jnp.where(visible, 2.0 * jnp.log(jnp.maximum(peak, ALPHA_MIN) * 255.0), 0.0)
    Ms = lax.stop_gradient(M)
    if prefilter:
        # Dual conic of the projected ellipse h^T P h = r2: M blockdiag(r2 P^-1, -1) M^T, times
        # det P (> 0), so that an edge-on splat (det P = 0) gives no division: q22 >= 0, unbounded.
        pf = lax.stop_gradient(conic)
        adj = jnp.stack([pf[:, 2], -pf[:, 1], -pf[:, 1], pf[:, 0]], axis=-1).reshape(-1, 2, 2)
        det_p = pf[:, 0] * pf[:, 2] - pf[:, 1] ** 2
        Q = (r2[:, None, None] * jnp.einsum("cia,cab,cjb->cij", Ms[:, :, :2], adj, Ms[:, :, :2])
             - det_p[:, None, None] * Ms[:, :, None, 2] * Ms[:, None, :, 2])
    else:
        # Dual conic of the projected circle u^2 + v^2 = r2: M diag(r2, r2, -1) M^T.
        Q = (r2[:, None, None] * jnp.einsum("cia,cja->cij", Ms[:, :, :2], Ms[:, :, :2])
             - Ms[:, :, None, 2] * Ms[:, None, :, 2])
    q22 = Q[:, 2, 2]
    bounded = q22 < 0
    q22s = jnp.where(bounded, q22, -1.0)
    cx, cy = Q[:, 0, 2] / q22s, Q[:, 1, 2] / q22s
    hx = jnp.sqrt(jnp.maximum(cx * cx - Q[:, 0, 0] / q22s, 0.0))
    hy = jnp.sqrt(jnp.maximum(cy * cy - Q[:, 1, 1] / q22s, 0.0))
    big = 1e9
    if prefilter:
        # The kernel's support is also cut to the screen ellipse d^T S^-1 d <= SUPPORT_Q around the
        # centre, S the filtered splat's screen covariance (the affine EWA footprint), d the pixel's
        # offset. Where the splat is resolved, the plane ellipse lies well inside it and this
        # changes nothing; near edge-on, P's narrow axis maps a pixel to a long stretch of the plane
        # and, under perspective, the plane ellipse can reach the horizon (unbounded on screen): a
        # faint kernel over the whole image, which costs a pair per tile and keeps no coverage the
        # EWA factor accounts for.
        sc = lax.stop_gradient(screen)
        mus = lax.stop_gradient(mu)
        sx, sy = jnp.sqrt(SUPPORT_Q * sc[:, 0]), jnp.sqrt(SUPPORT_Q * sc[:, 1])
        xmin = jnp.maximum(jnp.where(bounded, cx - hx, -big), mus[:, 0] - sx)
        xmax = jnp.minimum(jnp.where(bounded, cx + hx, big), mus[:, 0] + sx)
        ymin = jnp.maximum(jnp.where(bounded, cy - hy, -big), mus[:, 1] - sy)
        ymax = jnp.minimum(jnp.where(bounded, cy + hy, big), mus[:, 1] + sy)
        radius = jnp.where(visible, jnp.maximum(xmax - xmin, ymax - ymin) * 0.5, 0.0)
        support = lax.stop_gradient(inv_screen) / SUPPORT_Q
    else:
        r_lp = jnp.sqrt(0.5 * r2)  # the low-pass disc: 2 |d|^2 <= r2
        mus = lax.stop_gradient(mu)
        xmin = jnp.where(bounded, jnp.minimum(cx - hx, mus[:, 0] - r_lp), -big)
        xmax = jnp.where(bounded, jnp.maximum(cx + hx, mus[:, 0] + r_lp), big)
        ymin = jnp.where(bounded, jnp.minimum(cy - hy, mus[:, 1] - r_lp), -big)
        ymax = jnp.where(bounded, jnp.maximum(cy + hy, mus[:, 1] + r_lp), big)
        radius = jnp.where(visible, jnp.maximum(jnp.maximum(xmax - xmin, ymax - ymin) * 0.5, r_lp), 0.0)

    cols = [A, B, Cc, M2, mu, opacity[:, None], color, normal, depth[:, None]]
    if prefilter:
        cols += [conic, lax.stop_gradient(coverage)[:, None], support]
    packed = jnp.concatenate(cols, axis=-1)
    return dict(packed=packed, depth=depth, visible=visible, bounds=(xmin, xmax, ymin, ymax),
                radius=jnp.where(jnp.isfinite(radius), radius, big))


# Column layout of the packed per-splat array (``_PF`` only with coverage "prefilter").
_A, _B, _C, _M2, _MU, _OP, _COL, _NRM, _DEP = (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12),
                                               slice(12, 14), 14, slice(15, 18), slice(18, 21), 21)
_PF = slice(22, 25)  # the prefiltered kernel's quadratic form (p, r, t): q = p u^2 + 2 r u v + t v^2
_COV = 25  # the prefilter's coverage factor (no gradient): pairs are skipped below ALPHA_MIN times it
_SUP = slice(26, 29)  # the prefilter's support: S^-1 / SUPPORT_Q (xx, xy, yy; no gradient), see _project
_PLANE = 9  # the first columns, A, B and C: all a texture lookup reads (see _plane)
_CN = slice(_COL.start, _NRM.stop)  # colour and normal, adjacent: one product with the weights


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
    """(u, v) = (s0, s1) / s2 with "no intersection" (ok False) when the ray is (nearly) parallel;
    also returns 1 / s2 (1 where ok is False)."""
    ok = jnp.abs(s2) * _UV_LIMIT > jnp.maximum(jnp.abs(s0), jnp.abs(s1))
    inv = 1.0 / jnp.where(ok, s2, 1.0)
    u = jnp.where(ok, s0 * inv, 0.0)
    v = jnp.where(ok, s1 * inv, 0.0)
    return u, v, ok, inv


_F_ACC = 9  # per-pixel accumulators: rgb (3), depth (1), normal (3), D1 = sum w m, D2 = sum w m^2
_LOG_T_MIN = math.log(T_MIN)


_META = 4  # columns per bank of _meta_table


def _meta_table(*atlases):
    """(C, 4 x banks) int32: per splat, for each bank present (RGB first), its block's base row in
    the atlas, bucket side, texture side and top mip level: what a lookup reads per splat, in one
    row, so that a pass gathers it once instead of once per field and bank."""
    cols = [c for a in atlases if a is not None for c in (a.base, a.bucket_side, a.size, a.max_level)]
    return jnp.stack([c.astype(jnp.int32) for c in cols], axis=-1)


class _Lookup(NamedTuple):
    """A chunk's texture lookups in one bank, one entry per mip level read (1, or 2 for trilinear).

    base: (c,) int32 the splats' blocks in the atlas; row: (P, c) float rows within the blocks
    (exact integers, no gradient); stride: (P, c) int32 row strides of the levels read; fa, fb:
    (P, c) bilinear fractions; lw: level blend weights (P, c) for trilinear, else None.
    """

    base: jax.Array
    row: tuple
    stride: tuple
    fa: tuple
    fb: tuple
    lw: tuple | None

    def rows(self):
        """(atlas rows (P, c) int32 of each level read, their strides)."""
        return tuple(self.base + lax.stop_gradient(r).astype(jnp.int32) for r in self.row), self.stride


def _barrier(tree, flag):
    """``tree`` unchanged, computed once: XLA cannot fuse across a conditional, so the arithmetic
    behind ``tree`` is not duplicated into consumers that read its elements many times (per channel
    and texel: the gathers of 4 ch-wide rows and the per-channel products, forward and, through the
    transposed conditional, backward), where XLA's CPU fusion otherwise recomputes all of it.
    ``lax.optimization_barrier`` does not reach XLA's CPU fusion. ``flag`` is a traced True
    (unbatched, so the conditional stays one)."""
    return lax.cond(flag, lambda t: t, lambda t: jax.tree.map(jnp.zeros_like, t), tree)


def _tex_lookups(m, u, v, log2_fp, config: RenderConfig, use_mip: bool) -> _Lookup:
    """Texture lookups of one bank at (u, v): ``m`` (..., 4) int32 the splats' rows of
    :func:`_meta_table` for the bank, broadcasting against u, v; ``log2_fp``, log2 of the mip
    footprint (see :func:`_plane`), for mipmaps."""
    base, side_p, ni, L = m[..., 0], m[..., 1], m[..., 2], m[..., 3]
    n = ni.astype(u.dtype)

    def at_level(lev):
        off, stride, side = tex.level_address(side_p, ni, lev)
        return tex.corners(off, stride, side, u, v), jnp.broadcast_to(stride, u.shape)

    if not use_mip or config.mip == "none":
        (r, fa, fb), stride = at_level(jnp.int32(0))
        return _Lookup(base, (r,), (stride,), (fa,), (fb,), None)
    if config.mip == "nearest":
        lev = tex.mip_level_log2(log2_fp, n, L, config.lambda_mip, trilinear=False)
        (r, fa, fb), stride = at_level(lev)
        return _Lookup(base, (r,), (stride,), (fa,), (fb,), None)
    lev = tex.mip_level_log2(log2_fp, n, L, config.lambda_mip, trilinear=True)
    l0 = jnp.floor(lev)
    frac = lev - l0
    l0i = l0.astype(jnp.int32)
    (r0, fa0, fb0), s0 = at_level(l0i)
    (r1, fa1, fb1), s1 = at_level(jnp.minimum(l0i + 1, L))
    return _Lookup(base, (r0, r1), (s0, s1), (fa0, fa1), (fb0, fb1), (1.0 - frac, frac))


def _tex_value(vals, fa, fb, lw):
    """Texture values, a list of ch arrays (P, c), from the gathered texels ``vals`` (per level read, the
    4 ch arrays of :func:`textures.gather_corners`) and a :class:`_Lookup`'s fractions and level
    weights."""
    out = [tex.bilinear(t, a, b) for t, a, b in zip(vals, fa, fb)]
    if lw is not None:
        out = [[lw[0] * a + lw[1] * b for a, b in zip(*out)]]
    return out[0]


def _gather(texels, rows):
    """Texels of the lookups at ``rows`` (from :meth:`_Lookup.rows`) in the flat atlas ``texels``
    (M, ch): per level read, the 4 ch arrays of :func:`textures.gather_corners`."""
    return None if rows is None else tuple(tex.gather_corners(texels, i, s) for i, s in zip(*rows))


def _scatter(g_pairs, rows, g_vals):
    """Adds the cotangents ``g_vals`` of :func:`_gather` values to ``g_pairs`` (M, 2 ch), the
    cotangent of the flat atlas in pairs: row r holds that of texel r (first ch) and of texel r + 1
    (last ch; see :func:`_unpair`). A lookup adds to two rows, r and r + stride."""
    ch = g_pairs.shape[-1] // 2
    for i, stride, g in zip(*rows, g_vals):
        idx = jnp.concatenate([i.reshape(-1), (i + stride).reshape(-1)])
        upd = jnp.concatenate([jnp.stack(g[2 * j * ch:2 * (j + 1) * ch], axis=-1).reshape(-1, 2 * ch)
                               for j in range(2)])
        g_pairs = g_pairs.at[idx].add(upd, mode="promise_in_bounds")
    return g_pairs


def _unpair(g_pairs):
    """(M, 2 ch) paired cotangents (:func:`_scatter`) -> (M, ch) cotangents of the flat atlas."""
    ch = g_pairs.shape[-1] // 2
    return g_pairs[:, :ch] + jnp.pad(g_pairs[:-1, ch:], ((1, 0), (0, 0)))


def _rays(pk, x, y):
    """The homogeneous ray-plane products s_i = A_i x + B_i y + C_i (i = 0, 1, 2) of pixel centres
    x, y with the splats' planes pk (..., >= 9), broadcast against each other; (u, v) = (s0, s1) / s2
    (:func:`_uv`)."""
    A, B, Cc = pk[..., _A], pk[..., _B], pk[..., _C]
    return [x * A[..., i] + y * B[..., i] + Cc[..., i] for i in range(3)]


def _plane(pk, x, y, need_footprint: bool):
    """Where the rays of pixel centres x, y meet the splats' planes: pk (..., >= 9) packed splats
    (only the plane-equation columns A, B, C are read), x, y broadcast against them.

    Returns u, v, whether the ray meets the plane, and log2 of the mip footprint max(D12, D13)
    (log2 1e4 where a ray misses the plane, the coarsest level) or None, all of the broadcast shape.
    """
    s = _rays(pk, x, y)
    u, v, ok, _ = _uv(*s)
    log2_fp = None
    if need_footprint:
        def neighbour(d):
            """(u, v) of the ray one pixel over ((0, 0) where it misses the plane) and whether it
            meets the plane. The miss is folded into one reciprocal, not a select per coordinate:
            fewer selects let XLA fuse more of this."""
            t = [s[i] + d[..., i] for i in range(3)]
            hit = jnp.abs(t[2]) * _UV_LIMIT > jnp.maximum(jnp.abs(t[0]), jnp.abs(t[1]))
            inv = jnp.where(hit, 1.0 / jnp.where(hit, t[2], 1.0), 0.0)
            return t[0] * inv, t[1] * inv, hit

        ux, vx, okx = neighbour(pk[..., _A])
        uy, vy, oky = neighbour(pk[..., _B])
        # log2 max(D12, D13) = 0.5 log2 max(D12^2, D13^2): no square roots, and the banks share it.
        d2 = jnp.maximum((ux - u) ** 2 + (vx - v) ** 2, (uy - u) ** 2 + (vy - v) ** 2)
        log2_fp = jnp.where(ok & okx & oky, 0.5 * safe_log2(d2), math.log2(_UV_LIMIT))
    return u, v, ok, log2_fp


class _Static(NamedTuple):
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
    def need_footprint(self):
        return self.rgb_mip or self.alpha_mip

    @property
    def batch(self):
        """Tiles advanced together: at most ``config.tile_batch``, spread evenly over the fewest
        batches, so that small images do not repeat a tile to fill a batch (every lane of a batch
        is computed, padding included: a one-tile image with batches of 8 did its work 8 times)."""
        nb = -(-self.num_tiles // self.config.tile_batch)
        return -(-self.num_tiles // nb)


def _pixel_coords(st: _Static, t, dtype):
    ts = st.config.tile_size
    iy, ix = jnp.divmod(jnp.arange(ts * ts, dtype=jnp.int32), ts)
    x = ((t % st.tiles_x) * ts + ix).astype(dtype) + 0.5
    y = ((t // st.tiles_x) * ts + iy).astype(dtype) + 0.5
    return x, y


def _chunk_slots(st: _Static, ctx, t, k):
    """Splat ids (c,) and validity of chunk k of tile t."""
    c = st.config.chunk
    slots = k * c + jnp.arange(c, dtype=jnp.int32)
    valid = slots < ctx["binned"][t]
    ids = ctx["ids_sorted"]
    gid = jnp.where(valid, ids[jnp.clip(ctx["tile_start"][t] + slots, 0, ids.shape[0] - 1)], 0)
    return gid, valid


class _Geometry(NamedTuple):
    """The kernel's per-pair terms of a batch's chunk, each (c, B, P) (:func:`_geometry_terms`)."""

    G: jax.Array       # the 2DGS kernel
    z: jax.Array       # the pair's depth
    u: jax.Array       # ray-plane intersection (0 where the ray misses the plane)
    v: jax.Array
    ok: jax.Array      # the ray meets the plane
    inv: jax.Array     # 1 / s2 (see _uv)
    use3: jax.Array    # the 3D term wins (rho3d <= rho2d); prefilter: a hit within the support


def _cols(pk):
    """(F, c, B, 1): the columns of a batch's chunk of packed splats pk (B, c, F), each to broadcast
    against the chunk's (c, B, P) blocks."""
    return jnp.transpose(pk, (2, 1, 0))[..., None]


def _geometry_terms(pk, x, y, prefilter: bool) -> _Geometry:
    """The :class:`_Geometry` of pk (B, c, F) packed splats at pixel centres x, y (B, P); with
    ``prefilter`` the kernel is the prefiltered one (coverage "prefilter", columns ``_PF``)."""
    col = _cols(pk)
    u, v, ok, inv = _uv(*[x * col[i] + y * col[3 + i] + col[6 + i] for i in range(3)])
    if prefilter:
        p, r, t = (col[i] for i in range(_PF.start, _PF.stop))
        a, b, c = (col[i] for i in range(_SUP.start, _SUP.stop))
        dx, dy = x - col[_MU.start], y - col[_MU.start + 1]
        use3 = ok & ((a * dx + 2.0 * b * dy) * dx + c * dy * dy <= 1.0)
        G = jnp.exp(-0.5 * jnp.where(use3, (p * u + 2.0 * r * v) * u + t * v * v, 1e8))
    else:
        rho3d = jnp.where(ok, u * u + v * v, 1e8)
        dx, dy = x - col[_MU.start], y - col[_MU.start + 1]
        rho2d = 2.0 * (dx * dx + dy * dy)
        use3 = rho3d <= rho2d
        G = jnp.exp(-0.5 * jnp.minimum(rho3d, rho2d))
    z = jnp.where(use3, col[_M2.start] * u + col[_M2.start + 1] * v + col[_M2.start + 2], col[_DEP])
    return _Geometry(G, z, u, v, ok, inv, use3)


def _chunk_geometry(pk, x, y, prefilter: bool = False):
    """G, z (c, B, P) of a batch's chunk: pk (B, c, F) packed splats, x, y (B, P) pixel centres.
    G is the 2DGS kernel exp(-0.5 min(rho3d, rho2d)) and z the depth: at the ray-plane intersection
    where the 3D term wins, else the centre's. With ``prefilter``, G is the prefiltered kernel
    exp(-0.5 (p u^2 + 2 r u v + t v^2)) (0 where the ray misses the plane) and z the intersection's."""
    t = _geometry_terms(pk, x, y, prefilter)
    return t.G, t.z


def _chunk_geometry_bwd(pk, x, y, geo: _Geometry, g_G, g_z, prefilter: bool = False):
    """The cotangent (B, c, F) of pk for cotangents g_G, g_z (c, B, P) of :func:`_chunk_geometry`,
    given the forward's terms ``geo`` (:func:`_geometry_terms` of the same pk, x, y), derived by
    hand: the per-splat sums over a tile's pixels are products of a few per-pair columns with the
    pixels' (x, y, 1), where autodiff's backward made a reduction per packed column. The centre's
    cotangent comes from the sums of one column (``-4 (sum g x - mu sum g)``, not a column each for
    x and y), and each column is multiplied on its own (stacked first, the stack was the costliest op
    of the backward's chunk loop). The pixels of every tile must share their offsets from the
    tile's first pixel (x[b] - x[b, 0] the same for every b, and y alike), as the tiles of
    :func:`_pixel_coords` do."""
    G, _, u, v, ok, inv, use3 = geo
    col = _cols(pk)
    M2 = col[_M2]
    g_rho = -0.5 * g_G * G                                    # d/d min(rho3d, rho2d), or d/d q
    g_rho3 = jnp.where(use3 & ok, g_rho, 0.0)
    g_z3 = jnp.where(use3, g_z, 0.0)
    if prefilter:  # d q / d(u, v) = 2 P (u, v)
        qu = col[_PF.start] * u + col[_PF.start + 1] * v
        qv = col[_PF.start + 1] * u + col[_PF.start + 2] * v
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
    if prefilter:  # the centre is not read
        g_mu = jnp.zeros((B, c, 2), pk.dtype)
    else:  # d rho2d / d mu = -4 (x - mu): from the x-, y- and 1-weighted sums of one column.
        r2 = sums(jnp.where(use3, 0.0, g_rho))
        g_mu = -4.0 * (r2[..., :2] + (centre - pk[..., _MU]) * r2[..., 2:])
    one = [sums(q)[..., 2] for q in (g_z3 * u, g_z3 * v, g_z3, g_z - g_z3)]
    rest = jnp.zeros((B, c, _DEP - _OP), pk.dtype)                                          # opacity to normal
    out = [abc, jnp.stack(one[:3], -1), g_mu, rest, one[3][..., None]]
    if prefilter:  # d q / d(p, r, t) = (u^2, 2 u v, v^2); the coverage column is a threshold only
        out += [jnp.stack([sums(q)[..., 2] for q in (g_rho3 * u * u, 2.0 * g_rho3 * u * v, g_rho3 * v * v)], -1),
                jnp.zeros((B, c, 1 + _SUP.stop - _SUP.start), pk.dtype)]
    return jnp.concatenate(out, axis=-1)


class _Passes(NamedTuple):
    """Which (splat, tile, pixel) pairs of a batch's chunk get texture lookups, and in how many passes.

    The (c, B, P) block is cut into rows of at most 32 slots along its last axis (32 pixels of a
    splat's tile); ``bits`` (R,) uint32 marks the pairs of each row that may reach alpha 1/255
    at a pixel still compositing; ``ends`` (R,) int32 is the inclusive running count of marked pairs
    over the rows; count: () int32 how many in all; K: static pass size; shape: static (c, B, P).
    Pass j looks up the marked pairs of ranks ``j K`` to ``(j + 1) K - 1`` in block order.
    """

    bits: jax.Array
    ends: jax.Array
    count: jax.Array
    K: int
    shape: tuple


_WORD = 32  # slots per row of _Passes: one uint32 bit each


def _row_bits(take):
    """(..., c) bool -> (..., ceil(c / 32)) uint32: the marks of each run of 32 slots as the bits of
    one word (slot w 32 + i of the last axis is bit i of word w)."""
    c = take.shape[-1]
    nw = -(-c // _WORD)
    take = jnp.pad(take, [(0, 0)] * (take.ndim - 1) + [(0, nw * _WORD - c)])
    take = take.reshape(take.shape[:-1] + (nw, _WORD))
    weights = jnp.left_shift(jnp.uint32(1), jnp.arange(_WORD, dtype=jnp.uint32))
    return jnp.sum(jnp.where(take, weights, jnp.uint32(0)), axis=-1, dtype=jnp.uint32)


def _nth_bit(bits, n):
    """Position (int32) of the bit of rank ``n`` (0-based, from the least significant) set in
    ``bits`` (uint32), elementwise; ``n`` must be below the number of set bits. A binary search on
    population counts: 5 halvings of the 32-bit word."""
    pos = jnp.zeros(bits.shape, jnp.uint32)
    n = n.astype(jnp.uint32)
    for width in (16, 8, 4, 2, 1):
        low = lax.population_count(jnp.right_shift(bits, pos) & jnp.uint32((1 << width) - 1))
        up = n >= low
        n = jnp.where(up, n - low, n)
        pos = jnp.where(up, pos + jnp.uint32(width), pos)
    return pos.astype(jnp.int32)


def _texture_passes(st: _Static, ctx, pk, gid, valid, G, done):
    """The :class:`_Passes` of a batch's chunk, or None when every pair is looked up
    (``config.texture_pairs`` 1).

    A pair whose bound ``opacity * G * max(alpha texels)`` is below 1/255 (with a 1e-3 margin for
    rounding) has alpha < 1/255 whatever its texture holds, and a pixel that stopped compositing
    takes nothing more: neither needs a lookup, and their texture values are never read (the pair
    is skipped). Textures then cost in proportion to the pairs that contribute (a few percent to a
    few tens of percent of a chunk's pairs), not to the whole (pixels x splats) block.

    The marks are packed into 32-bit words, one per 32-slot row, and counted with a running sum over
    the rows; each pass finds its pairs from those counts (:func:`_pass_pairs`,
    :func:`_rows_of_ranks`). Nothing block-sized is written, only the words (one per 32 pairs): no
    per-pair index array; the one scatter adds the rows' ends into a pass-sized histogram.
    """
    N = G.size
    K = min(N, max(1, math.ceil(st.config.texture_pairs * N)))
    if K >= N:
        return None
    bound = _cols(pk)[_OP] * _per_slot(ctx["peak"][gid]) * G
    take = _per_slot(valid) & ~done & (bound >= _alpha_min(st, pk) * (1.0 - 1e-3))
    return _mark_passes(take, K)


def _mark_passes(take, K: int) -> _Passes:
    """The :class:`_Passes` of passes of K pairs over the pairs marked in ``take`` (..., n) bool (rows
    of 32 slots along the last axis)."""
    bits = _row_bits(take).reshape(-1)
    counts = lax.population_count(bits).astype(jnp.int32)
    if take.size < 2 ** 24:  # running counts exact in float32: two small matmuls, not reduce-windows
        ends = _running_sum(counts.astype(jnp.float32)).astype(jnp.int32)
    else:
        ends = jnp.cumsum(counts)
    return _Passes(bits, ends, ends[-1], K, take.shape)


def _more_passes(passes: _Passes, j):
    """Whether pass j has pairs (the condition of the pass loops)."""
    return j * passes.K < passes.count


def _rows_of_ranks(ends, start, K: int):
    """(K,) int32: for the ranks ``start`` .. ``start + K - 1``, the row holding each, i.e. how many
    of the inclusive running counts ``ends`` (R,) int32 (nondecreasing) are at most the rank
    (``searchsorted(ends, rank, side="right")``). The ranks are consecutive, so this is the number of
    rows ending before ``start`` plus a running sum of a histogram of where the others end: one
    scatter of R ones and two small matmuls (:func:`_running_sum`), where a binary search would
    gather ``log2 R`` times."""
    before = jnp.sum((ends < start).astype(jnp.int32))
    at = ends - start
    hist = jnp.zeros((K,), jnp.float32).at[jnp.where((at >= 0) & (at < K), at, K)].add(1.0, mode="drop")
    return before + _running_sum(hist).astype(jnp.int32)


def _running_sum(x):
    """Inclusive running sum of a (K,) float32 vector of small integer counts (exact below 2**24), as
    a prefix sum within blocks of w (a power of two, about sqrt K) and one over the blocks' totals:
    two triangular matmuls, where XLA's CPU cumsum is a reduce-window of K^2 adds."""
    K = x.shape[0]
    w = 1 << max(0, math.ceil(math.log2(math.sqrt(K))))
    nb = -(-K // w)
    blocks = _prefix_sum(jnp.pad(x, (0, nb * w - K)).reshape(nb, w))
    offsets = _prefix_sum(blocks[:, -1]) - blocks[:, -1]
    return (blocks + offsets[:, None]).reshape(-1)[:K]


def _pass_pairs(passes: _Passes, j):
    """(K,) int32 flat indices into the block (``passes.shape``) of the pairs of pass j, in block
    order; the block's size for unused slots."""
    n = passes.shape[-1]
    nw = -(-n // _WORD)
    start = j * passes.K
    rank = start + jnp.arange(passes.K, dtype=jnp.int32)
    row = jnp.minimum(_rows_of_ranks(passes.ends, start, passes.K), passes.ends.shape[0] - 1)
    word = passes.bits[row]
    first = passes.ends[row] - lax.population_count(word).astype(jnp.int32)
    bit = _nth_bit(word, rank - first)
    pair = (row // nw) * n + (row % nw) * _WORD + bit
    return jnp.where(rank < passes.count, pair, math.prod(passes.shape))


def _select(pk, gid, x, y, sel):
    """Splats' plane equations (the first ``_PLANE`` columns of pk (B, c, F), all a lookup reads),
    splat ids and pixel centres of the looked-up pairs: with ``sel`` None the whole block,
    broadcasting ((c, B, 1, 9), (c, B, 1), (B, P), (B, P)); else of the pairs of
    :func:`_pair_rows` ``sel``: (K, 9), (K,), (K,), (K,). The columns are cut before the gather,
    so the gather's transpose scatters into (B c, 9); cut from the gathered (K, F) rows, each
    column read became a (K, F) pad in the backward, summed."""
    pk = pk[..., :_PLANE]
    if sel is None:
        return jnp.swapaxes(pk, 0, 1)[:, :, None], _per_slot(gid), x, y
    _, splat, pixel = sel
    B, c, F = pk.shape
    return pk.reshape(B * c, F)[splat], gid.reshape(-1)[splat], x.reshape(-1)[pixel], y.reshape(-1)[pixel]


def _pair_rows(ctx, passes: _Passes, j):
    """(idx, splat, pixel), each (K,) int32: the pairs of pass j (:func:`_pass_pairs`, flat into
    ``passes.shape`` = (c, B, P), N for none), and the rows of their splats in the (B c) chunk slots
    and of their pixels in the (B P) pixels. Through :func:`_barrier`, so that the pass's pair
    search is done once, not again in every gather that reads it (XLA fused it into each, and redid
    it for every gathered element, the columns of a splat row included)."""
    c, B, P = passes.shape
    idx = _pass_pairs(passes, j)
    i = jnp.minimum(idx, c * B * P - 1)
    k, r = i // (B * P), i % (B * P)
    return _barrier((idx, (r // P) * c + k, r), ctx["flag"])


def _lookups(st: _Static, ctx, pk, gid, x, y, sel):
    """Texture lookups of a batch's chunk (all pairs, ``sel`` None) or of the pairs ``sel``
    (:func:`_pair_rows`).

    Args:
      pk: (B, c, F) packed splats; gid (B, c); x, y (B, P) pixel centres; sel: see
        :func:`_select`.
    Returns:
      (rgb weights, alpha weights), differentiable in pk: per bank None or (fa, fb, lw) of its
      :class:`_Lookup`; and (rgb rows, alpha rows), None or :meth:`_Lookup.rows`.
    """
    pk, gid, x, y = _select(pk, gid, x, y, sel)
    u, v, _, fp = _plane(pk, x, y, st.need_footprint)
    # Each per-lookup quantity is computed once (see _barrier): (u, v), the footprint and the splats'
    # texture addressing (one row gathered per lookup), which every lookup reads, then the lookups'
    # rows and weights, which the gathers and products read per texel.
    u, v, fp, m = _barrier((u, v, fp, ctx["tex_meta"][gid]), ctx["flag"])
    cfg = st.config
    lr = _tex_lookups(m[..., :_META], u, v, fp, cfg, st.rgb_mip) if st.rgb else None
    la = _tex_lookups(m[..., -_META:], u, v, fp, cfg, st.alpha_mip) if st.alpha else None
    lr, la = _barrier((lr, la), ctx["flag"])
    weights = lambda lk: None if lk is None else (lk.fa, lk.fb, lk.lw)
    rows = lambda lk: None if lk is None else lk.rows()
    return (weights(lr), weights(la)), (rows(lr), rows(la))


def _values(ctx, weights, vals):
    """Texture values of lookups: (RGB offsets, a list of 3, or None; alpha or None), each of the
    lookups' shape, from their weights (:func:`_lookups`) and gathered texels ``vals`` (per bank None
    or :func:`_gather`'s). Through :func:`_barrier`, so their cotangents are computed once, not
    per texel."""
    (wr, wa), (vr, va) = weights, vals
    return _barrier((None if wr is None else _tex_value(vr, *wr),
                     None if wa is None else _tex_value(va, *wa)[0]), ctx["flag"])


def _pick(dense, idx):
    """(c, B, P) arrays -> their values at the pairs ``idx`` (K,), zero for unused slots."""
    return jax.tree.map(lambda q: q.reshape(-1).at[idx].get(mode="fill", fill_value=0), dense)


def _texture_fwd(st: _Static, ctx, pk, gid, x, y, passes: _Passes | None, shape):
    """Texture values (RGB offsets list of 3 or None, alpha or None), each (c, B, P), of a batch's
    chunk: every pair (``passes`` None) or the pairs of :func:`_texture_passes`, zero elsewhere."""
    def look(sel):
        w, rows = _lookups(st, ctx, pk, gid, x, y, sel)
        return _values(ctx, w, (_gather(ctx["rgb_texels"], rows[0]), _gather(ctx["alpha_texels"], rows[1])))

    if passes is None:
        return look(None)
    N = math.prod(shape)
    dt = pk.dtype
    init = (None if not st.rgb else [jnp.zeros((N,), dt)] * 3, None if not st.alpha else jnp.zeros((N,), dt))

    def body(state):
        j, dense = state
        sel = _pair_rows(ctx, passes, j)
        idx = sel[0]
        vals = look(sel)
        return j + 1, jax.tree.map(lambda d, q: d.at[idx].set(q, mode="drop"), dense, vals)

    _, dense = lax.while_loop(lambda state: _more_passes(passes, state[0]), body, (jnp.int32(0), init))
    return jax.tree.map(lambda d: d.reshape(shape), dense)


def _texture_bwd(st: _Static, ctx, pk, gid, x, y, passes: _Passes | None, shape, ct, g_rt, g_at):
    """The backward of :func:`_texture_fwd` for cotangents ``ct`` of its output. Each pass's lookups
    are computed again here, under ``jax.vjp``, rather than kept from the :func:`_texture_fwd` call
    of :func:`_chunk_bwd` that produced the values: the number of passes is known only at run time,
    so their residuals have no static size. This is work done twice, and not small: in XLA's
    profile the pass loops (the forward's one, the backward's two) take about a quarter of a
    textured forward+backward at 5k.

    Returns (g_pk (B, c, F), g_rt, g_at): the packed-splat cotangent, and the paired texel
    cotangents ``g_rt``, ``g_at`` (:func:`_scatter`) with this chunk's added.
    """
    def one(sel, ct_vals, g_rt, g_at):
        w, vjp_lk, rows = jax.vjp(lambda p: _lookups(st, ctx, p, gid, x, y, sel), pk, has_aux=True)
        vals = (_gather(ctx["rgb_texels"], rows[0]), _gather(ctx["alpha_texels"], rows[1]))
        _, vjp_v = jax.vjp(lambda w_, v_: _values(ctx, w_, v_), w, vals)
        g_w, (g_vr, g_va) = vjp_v(ct_vals)
        if rows[0] is not None:
            g_rt = _scatter(g_rt, rows[0], g_vr)
        if rows[1] is not None:
            g_at = _scatter(g_at, rows[1], g_va)
        return vjp_lk(g_w)[0], g_rt, g_at

    if passes is None:
        return one(None, ct, g_rt, g_at)

    def body(state):
        j, g_pk, g_rt, g_at = state
        sel = _pair_rows(ctx, passes, j)
        g, g_rt, g_at = one(sel, _pick(ct, sel[0]), g_rt, g_at)
        return j + 1, g_pk + g, g_rt, g_at

    init = (jnp.int32(0), jnp.zeros_like(pk), g_rt, g_at)
    return lax.while_loop(lambda state: _more_passes(passes, state[0]), body, init)[1:]


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


def _alpha_min(st: _Static, pk):
    """The alpha below which a pair is skipped: ALPHA_MIN; with the prefilter, ALPHA_MIN times the
    splat's coverage factor (a (c, B, 1) column), so that a sub-pixel splat whose whole footprint is
    fainter than 1/255 is still composited and keeps its integrated coverage, while its fringe is
    cut where the unscaled kernel falls below 1/255, as a resolved splat's is."""
    return ALPHA_MIN * _cols(pk)[_COV] if st.prefilter else ALPHA_MIN


def _per_slot(v):
    """(B, c) per-slot values -> (c, B, 1), to broadcast against a chunk's (c, B, P) blocks."""
    return v.T[..., None]


def _contrib_terms(st: _Static, ctx, pk, G, z, a_tex, gid, valid, log_t_in, done_in) -> _Terms:
    """The :class:`_Terms` of a batch's chunk; arguments as :func:`_chunk_contrib`'s."""
    cfg = st.config
    a_raw = _cols(pk)[_OP] * G
    if st.alpha:
        a_tex = jnp.where(_per_slot(ctx["alpha_has"][gid]), a_tex, 1.0)
        a_raw = a_raw * a_tex
    a = jnp.clip(a_raw, 0.0, ALPHA_MAX)
    keep = _per_slot(valid) & (a >= _alpha_min(st, pk)) & (z > cfg.near)
    a = jnp.where(keep, a, 0.0)
    log1m = jnp.log1p(-a)
    cum = _prefix_sum_slots(log1m)
    include = ~done_in & (log_t_in + cum >= _LOG_T_MIN)
    trans = jnp.where(include, jnp.exp(log_t_in + cum - log1m), 0.0)
    zs = jnp.where(keep, z, 1.0)
    m = _DIST_FAR / (_DIST_FAR - _DIST_NEAR) * (1.0 - _DIST_NEAR / zs)
    return _Terms(a_raw, a_tex if st.alpha else None, keep, a, log1m, cum, include, trans, a * trans, zs, m)


def _chunk_contrib(st: _Static, ctx, pk, G, z, offs, a_tex, gid, valid, log_t_in, done_in):
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
    cn = jnp.einsum("cbp,bcf->bpf", w, pk[:, :, _CN], precision=lax.Precision.HIGHEST)  # colour, normal
    rgb = cn[..., :3]
    if st.rgb:
        has = _per_slot(ctx["rgb_has"][gid])
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


def _chunk_contrib_bwd(st: _Static, ctx, pk, G, z, offs, a_tex, gid, valid, log_t_in, done_in,
                       ct_acc, dot_in, base_term):
    """The backward of :func:`_chunk_contrib`, derived by hand (fewer passes over the (c, B, P)
    block than autodiff's, which also recomputed the accumulators to form ``ct_acc . acc``), and the
    pixels' state after the chunk.

    Args: those of :func:`_chunk_contrib`, and ct_acc (B, P, 9) the pixels' accumulator cotangents,
      dot_in (B, P) ``ct_acc . acc`` through the chunks before this one, base_term (B, P)
      ``ct_acc . acc_final + ct_T * T_final`` (see :func:`_composite`).
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
    ct_cn = jnp.concatenate([ct_rgb, ct_nrm], axis=-1)                  # (B, P, 6) as pk[..., _CN]
    hi = lax.Precision.HIGHEST
    g_w = (jnp.einsum("bpf,bcf->cbp", ct_cn, pk[:, :, _CN], precision=hi) + ct_z * z
           + (ct_m + ct_m2 * t.m) * t.m)
    g_offs = None
    if st.rgb:
        has = _per_slot(ctx["rgb_has"][gid])
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
    op = _cols(pk)[_OP]
    g_atex = None
    if st.alpha:
        g_G = g_a * op * t.a_tex
        g_op = jnp.sum(g_a * G * t.a_tex, axis=-1)
        g_atex = jnp.where(_per_slot(ctx["alpha_has"][gid]), g_a * op * G, 0.0)
    else:
        g_G = g_a * op
        g_op = jnp.sum(g_a * G, axis=-1)
    dm_dz = _DIST_FAR / (_DIST_FAR - _DIST_NEAR) * _DIST_NEAR / (t.zs * t.zs)
    g_z = w * (ct_z + (ct_m + 2.0 * ct_m2 * t.m) * dm_dz)
    g_pk = jnp.zeros_like(pk)
    g_pk = g_pk.at[:, :, _OP].set(g_op.T).at[:, :, _CN].set(jnp.einsum("cbp,bpf->bcf", w, ct_cn, precision=hi))
    return (log_t_out, done_out, dot_out), (g_pk, g_G, g_z, (g_offs, g_atex))


def _prefix_sum(x):
    """Inclusive prefix sum along the last axis (c, small) as a product with the (c, c) upper
    triangle of ones: one small matmul, where XLA's CPU cumsum is a reduce-window of c^2 adds that
    it runs several times slower, forward and backward."""
    c = x.shape[-1]
    upper = jnp.triu(jnp.ones((c, c), x.dtype))
    return jnp.matmul(x, upper, precision=lax.Precision.HIGHEST)


def _prefix_sum_slots(x):
    """Inclusive prefix sum of a chunk's (c, B, P) block along its slots (the first axis): one
    (c, c) x (c, B P) product with the lower triangle of ones (see :func:`_prefix_sum`)."""
    c = x.shape[0]
    lower = jnp.tril(jnp.ones((c, c), x.dtype))
    return jnp.matmul(lower, x.reshape(c, -1), precision=lax.Precision.HIGHEST).reshape(x.shape)


def _num_chunks(st: _Static, ctx, t):
    return (ctx["binned"][t] + st.config.chunk - 1) // st.config.chunk


def _tile_batches(st: _Static, ctx):
    """(num_batches, B) tile ids, longest lists first so a batch's tiles need similar numbers of
    chunks (a batch loops until its slowest tile is done). Padding (fewer than num_batches
    entries, see :attr:`_Static.batch`) repeats the last tile."""
    B = st.batch
    nb = -(-st.num_tiles // B)
    order = jnp.argsort(-ctx["binned"], stable=True).astype(jnp.int32)
    order = jnp.concatenate([order, jnp.full((nb * B - st.num_tiles,), order[-1], jnp.int32)])
    return order.reshape(nb, B)


def _batch_state(st, ctx, tb, dt):
    xy = jax.vmap(lambda t: _pixel_coords(st, t, dt))(tb)
    return xy, jax.vmap(lambda t: _num_chunks(st, ctx, t))(tb)


def _chunk_fwd(st: _Static, ctx, packed, tb, k, x, y, log_t, done):
    """Chunk k of a batch of tiles ``tb`` (B,), forward: x, y (B, P) pixel centres, log_t, done
    (B, P) the state before it. Returns ((dacc (B, P, 9), log_t (B, P)), (done (B, P), w (c, B, P)),
    gid (B, c)).

    A chunk's per-pair blocks are (c, B, P): slots outermost, pixels innermost, so a splat's column
    broadcasts along contiguous pixels and the sums over the chunk's splats add whole rows. (The
    (B, P, c) layout ran the 2DGS chunk step about 2x slower on this CPU: strided column reads and
    reductions along the short inner axis.)"""
    gid, valid = jax.vmap(lambda t: _chunk_slots(st, ctx, t, k))(tb)
    pk = packed[gid]
    G, z = _chunk_geometry(pk, x, y, st.prefilter)
    tvals = (None, None)
    if st.rgb or st.alpha:
        passes = _texture_passes(st, ctx, pk, gid, valid, G, done)
        tvals = _texture_fwd(st, ctx, pk, gid, x, y, passes, G.shape)
    out = _chunk_contrib(st, ctx, pk, G, z, *tvals, gid, valid, log_t, done)
    return out, gid


def _composite_fwd_impl(st: _Static, packed, rgb_texels, alpha_texels, ctx):
    npx = st.config.tile_size ** 2
    dt = packed.dtype
    B = st.batch

    def batch(tb):
        (x, y), nch = _batch_state(st, ctx, tb, dt)

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

    batches = _tile_batches(st, ctx)
    acc, t_final, best = lax.map(batch, batches)
    flat = batches.reshape(-1)
    T = st.num_tiles

    def unsort(v):  # duplicated padding tiles write identical values
        return jnp.zeros((T,) + v.shape[2:], v.dtype).at[flat].set(v.reshape((-1,) + v.shape[2:]))

    return unsort(acc), unsort(t_final), unsort(best)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _composite(st: _Static, packed, rgb_texels, alpha_texels, ctx):
    """All tiles, front to back in chunks of ``config.chunk`` splats, stopping each tile once every
    pixel's transmittance fell below 1e-4 or its list is exhausted; ``config.tile_batch`` tiles
    (of similar list lengths) advance together.

    Args:
      st: static settings.
      packed: (C, F) per-splat quantities (differentiable).
      rgb_texels, alpha_texels: (M, 3) / (M, 1) flat atlases (:class:`textures.Atlas`) or None
        (differentiable).
      ctx: dict of arrays without gradient (tile lists, texture addressing, the atlases' texels
        to read, the splats' alpha bounds).
    Returns:
      acc (T, P, 9) accumulators, t_final (T, P), best (T, P) int32 id of the largest-weight splat.

    The backward pass walks each tile's chunks front to back again; a chunk's influence on everything
    behind it is through its output transmittance, whose cotangent is
    ``ct_acc . (acc_final - acc_through_chunk) + ct_T * T_final`` (later contributions are linear in
    it), so nothing per pair is stored: the residuals are the inputs and the per-pixel outputs.
    """
    return _composite_fwd_impl(st, packed, rgb_texels, alpha_texels, ctx)


def _composite_fwd(st, packed, rgb_texels, alpha_texels, ctx):
    out = _composite_fwd_impl(st, packed, rgb_texels, alpha_texels, ctx)
    return out, (packed, rgb_texels, alpha_texels, ctx, out[0], out[1])


def _chunk_bwd(st: _Static, ctx, packed, tb, k, x, y, log_t, done, dot_through, ct_acc, base_term, g_rt, g_at):
    """Chunk k of a batch of tiles, backward: its cotangents for the packed splats (returned per
    chunk slot, (B, c, F), with the slots' ids gid (B, c)) and for the texels it read (added to the
    paired accumulators g_rt, g_at), and the state after it (log_t, done, dot_through, (B, P))."""
    gid, valid = jax.vmap(lambda t: _chunk_slots(st, ctx, t, k))(tb)
    pk = packed[gid]
    geo = _geometry_terms(pk, x, y, st.prefilter)
    G, z = geo.G, geo.z
    textured = st.rgb or st.alpha
    passes, tvals = None, (None, None)
    if textured:
        passes = _texture_passes(st, ctx, pk, gid, valid, G, done)
        tvals = _texture_fwd(st, ctx, pk, gid, x, y, passes, G.shape)
    (log_t2, done2, dot_through), (g_pk, g_G, g_z, g_tv) = _chunk_contrib_bwd(
        st, ctx, pk, G, z, *tvals, gid, valid, log_t, done, ct_acc, dot_through, base_term)
    g_pk = g_pk + _chunk_geometry_bwd(pk, x, y, geo, g_G, g_z, st.prefilter)
    if textured:
        g_tex, g_rt, g_at = _texture_bwd(st, ctx, pk, gid, x, y, passes, G.shape, g_tv, g_rt, g_at)
        g_pk = g_pk + g_tex
    return log_t2, done2, dot_through, gid, jnp.where(valid[..., None], g_pk, 0.0), g_rt, g_at


def _composite_bwd(st, res, cts):
    packed, rgb_texels, alpha_texels, ctx, acc_all, tfin_all = res
    ct_acc_all, ct_t_all, _ = cts
    npx = st.config.tile_size ** 2
    dt = packed.dtype
    B = st.batch

    def batch(carry, inp):
        tb, pad = inp
        # Padding entries repeat a tile: zero cotangents so its gradient is not added twice.
        ct_acc = jnp.where(pad[:, None, None], 0.0, ct_acc_all[tb])      # (B, P, 9)
        ct_t = jnp.where(pad[:, None], 0.0, ct_t_all[tb])                # (B, P)
        base_term = ct_t * tfin_all[tb] + jnp.sum(ct_acc * acc_all[tb], axis=-1)
        (x, y), nch = _batch_state(st, ctx, tb, dt)

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

    batches = _tile_batches(st, ctx)
    pad = (jnp.arange(batches.size) >= st.num_tiles).reshape(batches.shape)
    pairs = lambda t: None if t is None else jnp.zeros(t.shape[:-1] + (2 * t.shape[-1],), t.dtype)
    zeros = (jnp.zeros_like(packed), pairs(rgb_texels), pairs(alpha_texels))
    (g_pk, g_rt, g_at), _ = lax.scan(batch, zeros, (batches, pad))
    unpair = lambda g: None if g is None else _unpair(g)
    return g_pk, unpair(g_rt), unpair(g_at), jax.tree_util.tree_map(lambda _: None, ctx)


_composite.defvjp(_composite_fwd, _composite_bwd)


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


_LAYOUT_FIX = ("build scenes with Scene.from_arrays or random_scene and cameras with Camera.from_intrinsics "
               "or look_at, which set this layout; see patexgs_jax/scene.py")


def check_inputs(scene: Scene, camera: Camera) -> None:
    """Shapes and dtypes of a scene and camera against the layout the renderer assumes (module
    docstrings of scene.py and camera.py). Static, so it costs nothing under ``jax.jit``: a Scene
    or Camera built or edited by hand fails here, naming the field, not inside the compositor.

    Raises:
      AssertionError (chex's) naming the field, its shape or dtype and the fix.
    """
    c = scene.means.shape[0] if scene.means.ndim else -1
    fields = dict(means=(scene.means, (c, 3)), log_scales=(scene.log_scales, (c, 2)),
                  quats=(scene.quats, (c, 4)), opacity_logits=(scene.opacity_logits, (c,)),
                  sh=(scene.sh, (c, None, 3)), active=(scene.active, (c,)))
    for name, (x, shape) in fields.items():
        msg = f"Scene.{name} must be {shape} floating-point for capacity C={c}; {_LAYOUT_FIX}"
        chex.assert_shape(x, shape, custom_message=msg)
        chex.assert_type(x, float, custom_message=msg)
    if scene.sh.shape[1] not in (1, 4, 9, 16):
        raise AssertionError(f"Scene.sh has {scene.sh.shape[1]} coefficients per channel; SH degrees 0-3 "
                             f"have 1, 4, 9 or 16; {_LAYOUT_FIX}")
    for bank in (scene.rgb, scene.alpha):
        if bank is not None:
            for name in ("bucket", "slot", "size"):
                chex.assert_shape(getattr(bank, name), (c,), custom_message=(
                    f"TextureBank.{name} must be ({c},) for capacity C={c}; {_LAYOUT_FIX}"))
    for name, x, shape in (("K", camera.K, (3, 3)), ("world_to_camera", camera.world_to_camera, (4, 4))):
        msg = f"Camera.{name} must be {shape} floating-point; {_LAYOUT_FIX}"
        chex.assert_shape(x, shape, custom_message=msg)
        chex.assert_type(x, float, custom_message=msg)


def _render(scene: Scene, camera: Camera, config: RenderConfig, capacity: Capacity,
            screen_offset=None, active_sh_degree=None) -> RenderOutput:
    TRACE_COUNTS[(config, capacity)] += 1
    check_inputs(scene, camera)
    H, W, ts = camera.height, camera.width, config.tile_size
    tiles_x, tiles_y = -(-W // ts), -(-H // ts)
    num_tiles = tiles_x * tiles_y
    peak = _alpha_peak(scene)
    proj = _project(scene, camera, config, screen_offset, active_sh_degree, peak)
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
    st = _Static(config=config, tiles_x=tiles_x, num_tiles=num_tiles, rgb=rgb_atlas is not None,
                 alpha=alpha_atlas is not None)
    ctx = dict(ids_sorted=ids_sorted, tile_start=tile_start, binned=binned,
               rgb_has=None if rgb_atlas is None else rgb_atlas.has,
               alpha_has=None if alpha_atlas is None else alpha_atlas.has,
               tex_meta=_meta_table(rgb_atlas, alpha_atlas) if st.rgb or st.alpha else None,
               rgb_texels=None if rgb_atlas is None else lax.stop_gradient(rgb_atlas.texels),
               alpha_texels=None if alpha_atlas is None else lax.stop_gradient(alpha_atlas.texels), peak=peak,
               flag=binned[0] >= 0)  # a True XLA cannot prove (see _barrier)
    acc, t_final, best = _composite(st, proj["packed"], None if rgb_atlas is None else rgb_atlas.texels,
                                    None if alpha_atlas is None else alpha_atlas.texels, ctx)
    bg = jnp.asarray(config.background, acc.dtype)
    rgb = acc[..., 0:3] + t_final[..., None] * bg
    depth, normal = acc[..., 3], acc[..., 4:7]
    distortion = (1.0 - t_final) * acc[..., 8] - acc[..., 7] ** 2
    rgb = _untile(rgb, tiles_x, tiles_y, ts, H, W)
    alpha = 1.0 - _untile(t_final, tiles_x, tiles_y, ts, H, W)
    depth = _untile(depth, tiles_x, tiles_y, ts, H, W)
    depth = jnp.where(alpha > 1e-6, depth / jnp.maximum(alpha, 1e-6), 0.0)
    normal = _untile(normal, tiles_x, tiles_y, ts, H, W)
    distortion = _untile(distortion, tiles_x, tiles_y, ts, H, W)
    dominant = _untile(best, tiles_x, tiles_y, ts, H, W)
    best = dominant.reshape(-1)
    C = scene.capacity
    counts = jnp.zeros((C,), jnp.int32).at[jnp.where(best >= 0, best, C)].add(1, mode="drop")
    overflow = pairs_needed > capacity.pairs
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, distortion=distortion,
                        max_contrib_count=counts, dominant=dominant,
                        radius_px=jnp.where(ok, proj["radius"], 0.0), visible=ok,
                        pairs_needed=pairs_needed, max_tile_count=max_tile, overflow=overflow)


#: The jitted renderer: ``render_jit(scene, camera, config=..., capacity=..., screen_offset=None,
#: active_sh_degree=None)``. It never grows its capacity: check ``output.overflow`` on the host
#: (training does, between steps) and call again with ``Capacity.fit(output.pairs_needed)``. ``screen_offset`` ((C, 2) zeros) is a gradient hook: its gradient is
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
            cap = Capacity.fit(float(needed))
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
        new = Capacity.fit(float(out.pairs_needed), minimum=cap)
        warnings.warn(f"render: capacity {cap} too small for this view (needs {int(out.pairs_needed)} "
                      f"(splat, tile) pairs); growing to {new} and rendering again.", stacklevel=2)
        cap = new
    raise RuntimeError("render: capacity did not converge; this is a bug, please report it.")
