"""Projection: per-splat quantities of a view, packed into one (C, F) array for the compositor.

Each splat's plane is mapped to the image (:func:`image_map`); its inverse, the homogeneous
ray-plane map (:func:`ray_planes`), gives every pixel's (u, v) on the splat with a few products.
:func:`project` adds the colour from SH, the camera-facing normal, the opacity (times the coverage
factor with the prefilter, :func:`_prefilter`), the culling and the footprint's screen bounds, and
lays the per-splat columns out as :data:`COLS` says.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from ..camera import Camera
from ..math import quat_to_rotmat, safe_div, safe_normalize, safe_sqrt, sh_basis
from ..scene import Scene
from .billboard import square_bounds
from .config import ALPHA_MIN, SUPPORT_Q, RenderConfig


class Columns(NamedTuple):
    """The column layout of the packed per-splat array :attr:`Projection.packed` (C, F): one row per
    splat, so that a chunk of the compositor gathers its splats in one gather. F is ``width`` (22),
    or ``width_prefilter`` (29) with coverage "prefilter", whose columns come last. Each field is
    the slice (or index) of its columns; use the instance :data:`COLS`."""

    a: slice = slice(0, 3)  # the ray-plane map (u, v, 1) ~ x a + y b + c at pixel (x, y), see ray_planes
    b: slice = slice(3, 6)
    c: slice = slice(6, 9)
    m2: slice = slice(9, 12)  # the image map's last row: the camera z of plane point (u, v) is m2 . (u, v, 1)
    mu: slice = slice(12, 14)  # the centre on screen (px)
    opacity: int = 14  # sigmoid of the logit; with the prefilter, times the coverage factor
    colour: slice = slice(15, 18)  # max(SH(d) + 0.5, 0)
    normal: slice = slice(18, 21)  # the camera-frame unit normal, facing the camera
    depth: int = 21  # the centre's camera z
    conic: slice = slice(22, 25)  # prefilter: the kernel's quadratic form (p, r, t), q = p u^2 + 2 r u v + t v^2
    coverage: int = 25  # prefilter: the coverage factor (no gradient); pairs are skipped below ALPHA_MIN times it
    support: slice = slice(26, 29)  # prefilter: S^-1 / SUPPORT_Q (xx, xy, yy; no gradient), see project
    plane: int = 9  # the first columns, a, b and c: all a texture lookup reads
    colour_normal: slice = slice(15, 21)  # colour and normal, adjacent: one product with the weights
    width: int = 22
    width_prefilter: int = 29


#: The packed columns' layout (:class:`Columns`).
COLS = Columns()


class Projection(NamedTuple):
    """What :func:`project` returns for C splats.

    packed: (C, F) the per-splat columns the compositor reads (layout :data:`COLS`).
    depth: (C,) the centres' camera z: the binning's sort key.
    visible: (C,) bool, in front of the near plane and bright enough to reach alpha 1/255.
    bounds: (xmin, xmax, ymin, ymax), each (C,): the footprint's screen-space box in pixels (no
      gradient; +-1e9 where unbounded).
    radius: (C,) half the box's larger side in pixels (0 where not visible, 1e9 where unbounded).
    footprint: (C, 16) what the binning's per-tile test reads (no gradient; layout
      :data:`FOOTPRINT`).
    """

    packed: jax.Array
    depth: jax.Array
    visible: jax.Array
    bounds: tuple[jax.Array, jax.Array, jax.Array, jax.Array]
    radius: jax.Array
    footprint: jax.Array


class Footprint(NamedTuple):
    """The column layout of :attr:`Projection.footprint` (C, 16), the alpha-1/255 region of each splat
    as :func:`binning.tile_touches` tests it against a tile. The region is where the pixel's ray meets
    the splat's plane in front of the camera at (u, v) with ``h^T P h <= r2`` (``P`` the kernel's
    quadratic form: the identity without the prefilter; ``r2`` as in :func:`project`, with the
    margin of ``texture_lookup.texture_passes``), plus, without the prefilter, the low-pass disc
    ``2 |d|^2 <= r2`` around the centre."""

    a: slice = slice(0, 3)  # the ray-plane map, as COLS.a, b, c
    b: slice = slice(3, 6)
    c: slice = slice(6, 9)
    conic: slice = slice(9, 12)  # P as (p, r, t)
    r2: int = 12
    side: int = 13  # sign(det M): the homogeneous (u, v, 1) of a ray in front of the camera has this sign; 0: unsure
    mu: slice = slice(14, 16)  # the centre on screen (px)
    width: int = 16


#: The footprint columns' layout (:class:`Footprint`).
FOOTPRINT = Footprint()


# Every product here states its precision: without it a GPU computes float32 matmuls in TF32
# (about 10 mantissa bits), which moves splat centres and footprints by up to 1e-3 of a pixel.
HIGHEST = lax.Precision.HIGHEST


def _mm(a, b):
    """(N, K) @ (K, M) in full float32 (or float64) precision."""
    return jnp.matmul(a, b, precision=HIGHEST)


def _cross(a, b):
    return jnp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                      a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                      a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _prefilter(M, mu, depth, pixel_var, min_var, plane=None):
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

    With ``plane`` (the 3D smoothing filter in the splat's plane, :func:`plane_filter`), the splat is
    first convolved in its plane with a Gaussian of variance D - I (D = diag(d_u, d_v), in units of
    the scales): the plane covariance is D + e (K^T K)^-1. With h = D^1/2 h' that is the form above
    of K' = K D^1/2, so P = D^-1/2 P' D^-1/2 and the coverage is coverage' / sqrt(det D): the
    integral is kept again, and the screen covariance S is the filtered splat's (K' K'^T + e I).

    Args:
      M: (C, 3, 3) splat plane (u, v, 1) to image homogeneous coordinates; mu: (C, 2) the centres
        on screen; depth: (C,) the centres' depth (positive); plane: None or (C, 2) d_u, d_v >= 1.
    Returns:
      (C, 3) (p, r, t) of P, (C,) the coverage factor in [0, 1], (C, 2) the diagonal (xx, yy) of
      the filtered splat's screen covariance S = K K^T + e I (px^2), e the filter's variance, and
      (C, 3) S^-1 (xx, xy, yy).
    """
    K = (M[:, :2, :2] - mu[:, :, None] * M[:, 2, None, :2]) / depth[:, None, None]
    if plane is not None:
        K = K * jnp.sqrt(plane)[:, None, :]
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
    if plane is not None:
        du, dv = plane[:, 0], plane[:, 1]
        duv = jnp.sqrt(du) * jnp.sqrt(dv)  # (du * dv can overflow float32 for a degenerate splat)
        p, r, t, coverage = p / du, r / duv, t / dv, coverage / duv
    return jnp.stack([p, r, t], axis=-1), coverage, screen, inv_screen


def filtered_log_scales(scene: Scene):
    """(C, D) log scales with the 3D filter's variance added (``Scene.filter3d``; the scales
    themselves without one) and (C,) the filter's opacity factor prod_i s_i / sqrt(s_i^2 + f), i.e.
    sqrt(det Sigma / det(Sigma + f I)) (ones without one): a 3D Gaussian's (D = 3), or an untextured
    splat's in its plane (D = 2). In log space, so degenerate scales (exp(2 log s) underflowing) stay
    finite; no gradient through f (it is not trained)."""
    ls = scene.log_scales
    if scene.filter3d is None:
        return ls, jnp.ones(ls.shape[:1], ls.dtype)
    f = lax.stop_gradient(scene.filter3d)[:, None]
    pos = f > 0  # (a zero filter leaves the Gaussian as it is, however small)
    ls_f = jnp.where(pos, 0.5 * jnp.logaddexp(2.0 * ls, jnp.log(jnp.where(pos, f, 1.0))), ls)
    return ls_f, jnp.exp(jnp.sum(ls - ls_f, axis=-1))


def plane_filter(scene: Scene):
    """(C, 2) d = 1 + f / s^2 per tangent axis of a 2D scene's 3D smoothing filter (``Scene.filter3d``,
    variance f in world units^2; :mod:`patexgs_jax.filter3d`): the filter restricted to the splat's
    plane, in units of its scales, for :func:`_prefilter` (a surfel has no extent along its normal,
    so the filter widens it in its plane only), from :func:`filtered_log_scales` (d = (s_f / s)^2,
    capped at e^80 so a degenerate splat stays finite). None without a filter."""
    if scene.filter3d is None:
        return None
    ls_f, _ = filtered_log_scales(scene)
    return jnp.exp(jnp.minimum(2.0 * (ls_f - scene.log_scales), 80.0))


def image_map(scene: Scene, camera: Camera):
    """Each splat's plane seen from ``camera``.

    Returns:
      M (C, 3, 3), mapping splat-plane homogeneous (u, v, 1) (in units of the scales) to image
      homogeneous (x w, y w, w), w the camera z; p (C, 3) the centres and nrm (C, 3) the planes'
      unit normals in the camera frame (the normals not yet turned to face the camera).
    """
    dt = scene.means.dtype
    K = camera.K.astype(dt)
    w2c = camera.world_to_camera.astype(dt)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    R = quat_to_rotmat(scene.quats)
    s = jnp.exp(scene.log_scales)
    p = _mm(scene.means, Rc.T) + tc                    # (C, 3) camera-frame centre
    tu = _mm(R[:, :, 0] * s[:, :1], Rc.T)              # (C, 3) scaled tangent axes, camera frame
    tv = _mm(R[:, :, 1] * s[:, 1:], Rc.T)
    nrm = _mm(R[:, :, 2], Rc.T)
    M = jnp.einsum("ij,cjk->cik", K, jnp.stack([tu, tv, p], axis=-1), precision=HIGHEST)
    return M, p, nrm


def ray_planes(M0, M1, M2):
    """(A, B, C), each (C, 3): the ray-plane map of the image maps whose rows are M0, M1, M2 (each
    (C, 3), :func:`image_map`), (u, v, 1) ~ adj(M) (x, y, 1) = x A + y B + C at pixel coordinates
    (x, y)."""
    return _cross(M1, M2), _cross(M2, M0), _cross(M0, M1)


def project(scene: Scene, camera: Camera, config: RenderConfig, screen_offset, active_sh_degree,
            tex_peak, constant=None) -> Projection:
    """The per-splat quantities of a view (see :class:`Projection` and :class:`Columns`).

    Args:
      screen_offset: None or (C, 2), added to the centres on screen (a gradient hook, see
        :data:`patexgs_jax.render.render_jit`).
      active_sh_degree: None or a traced int: SH bands above it are masked.
      tex_peak: (C,) the largest alpha-texture value of each splat (:func:`alpha_peak`), for the
        culling.
      constant: None, or the :func:`constant_textures` of the scene, folded into the colour and
        the opacity (the compositor then does not look those textures up).
    """
    dt = scene.means.dtype
    w2c = camera.world_to_camera.astype(dt)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    prefilter = config.coverage == "prefilter"
    filter_factor = None
    if scene.filter3d is not None and not prefilter:
        # The 3D filter in the plane of an untextured splat under the 2DGS low-pass: the filtered
        # Gaussian is the splat with scales sqrt(s^2 + f) (the prefilter folds it into its kernel).
        if config.coverage != "lowpass" or scene.rgb is not None or scene.alpha is not None:
            raise ValueError("render: the 3D smoothing filter (Scene.filter3d) of textured 2D splats or "
                             f"billboards needs coverage 'prefilter', got {config.coverage!r}; render with "
                             "RenderConfig(coverage='prefilter') or drop the filter (scene.replace(filter3d=None)).")
        ls_f, filter_factor = filtered_log_scales(scene)
        M, p, nrm = image_map(scene.replace(log_scales=ls_f), camera)
    else:
        M, p, nrm = image_map(scene, camera)
    M0, M1, M2 = M[:, 0], M[:, 1], M[:, 2]
    A, B, Cc = ray_planes(M0, M1, M2)
    depth = p[:, 2]
    in_front = depth > config.near
    mu = safe_div(M[:, :2, 2], jnp.where(in_front, depth, 1.0)[:, None])
    if prefilter:
        conic, coverage, screen, inv_screen = _prefilter(M, mu, jnp.where(in_front, depth, 1.0),
                                                         config.pixel_var, config.min_var, plane_filter(scene))
    if screen_offset is not None:
        off = screen_offset.astype(dt)
        Cc = Cc - off[:, :1] * A - off[:, 1:] * B
        mu = mu + off

    # Colour from SH, one view direction per splat.
    cam_center = -jnp.linalg.solve(Rc, tc)  # exact even if a float32 pose is not quite orthonormal
    dirs = safe_normalize(scene.means - cam_center)
    degree = scene.sh_degree
    basis = sh_basis(dirs, degree, active_sh_degree)
    color = jnp.maximum(jnp.einsum("ck,ckj->cj", basis, scene.sh, precision=HIGHEST) + 0.5, 0.0)

    normal = jnp.where((jnp.sum(nrm * p, axis=-1) > 0)[:, None], -nrm, nrm)
    opacity = jax.nn.sigmoid(scene.opacity_logits) * (scene.active > 0)
    if filter_factor is not None:
        opacity = opacity * filter_factor
    # Culling and screen-space bounds (no gradient): alpha >= 1/255 needs
    # rho <= 2 log(255 * opacity * max A) =: r2 (with the prefilter, alpha / coverage >= 1/255 and
    # q <= r2: see kernel.alpha_min).
    peak = lax.stop_gradient(opacity * tex_peak)
    if constant is not None:
        rgb_add, alpha_mul = constant
        if rgb_add is not None:
            color = color + rgb_add
        if alpha_mul is not None:
            opacity = opacity * alpha_mul
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
        Q = (r2[:, None, None] * jnp.einsum("cia,cab,cjb->cij", Ms[:, :, :2], adj, Ms[:, :, :2],
                                            precision=HIGHEST)
             - det_p[:, None, None] * Ms[:, :, None, 2] * Ms[:, None, :, 2])
    else:
        # Dual conic of the projected circle u^2 + v^2 = r2: M diag(r2, r2, -1) M^T.
        Q = (r2[:, None, None] * jnp.einsum("cia,cja->cij", Ms[:, :, :2], Ms[:, :, :2], precision=HIGHEST)
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
    elif config.coverage in ("billboard", "texel-grid"):  # the square's part beyond the near plane
        (xmin, xmax, ymin, ymax), hit = square_bounds(Ms, config.near)
        visible = visible & hit
        radius = jnp.where(visible, jnp.maximum(xmax - xmin, ymax - ymin) * 0.5, 0.0)
    else:
        r_lp = jnp.sqrt(0.5 * r2)  # the low-pass disc: 2 |d|^2 <= r2
        mus = lax.stop_gradient(mu)
        xmin = jnp.where(bounded, jnp.minimum(cx - hx, mus[:, 0] - r_lp), -big)
        xmax = jnp.where(bounded, jnp.maximum(cx + hx, mus[:, 0] + r_lp), big)
        ymin = jnp.where(bounded, jnp.minimum(cy - hy, mus[:, 1] - r_lp), -big)
        ymax = jnp.where(bounded, jnp.maximum(cy + hy, mus[:, 1] + r_lp), big)
        radius = jnp.where(visible, jnp.maximum(jnp.maximum(xmax - xmin, ymax - ymin) * 0.5, r_lp), 0.0)

    cols = [A, B, Cc, M2, mu, opacity[:, None], color, normal, depth[:, None]]  # in the order of Columns
    if prefilter:
        cols += [conic, lax.stop_gradient(coverage)[:, None], support]
    packed = jnp.concatenate(cols, axis=-1)
    assert packed.shape[-1] == (COLS.width_prefilter if prefilter else COLS.width)
    return Projection(packed=packed, depth=depth, visible=visible, bounds=(xmin, xmax, ymin, ymax),
                      radius=jnp.where(jnp.isfinite(radius), radius, big),
                      footprint=_footprint(lax.stop_gradient(packed), peak, prefilter))


def _footprint(packed, peak, prefilter: bool):
    """The (C, 16) :data:`FOOTPRINT` columns of packed splats (see :class:`Footprint`)."""
    A, B, Cc, M2 = packed[:, COLS.a], packed[:, COLS.b], packed[:, COLS.c], packed[:, COLS.m2]
    # A ray (x, y) meets the plane at camera z = det M / s2, s2 = x A2 + y B2 + C2, det M = M2 . C.
    # Where the plane (nearly) contains the camera centre, the sign is not to be trusted in float32:
    # side 0, every tile of the box is kept.
    det = jnp.sum(M2 * Cc, axis=-1)
    sure = jnp.abs(det) > 1e-4 * jnp.linalg.norm(M2, axis=-1) * jnp.linalg.norm(Cc, axis=-1)
    side = jnp.where(sure, jnp.sign(det), 0.0)
    if prefilter:
        conic = packed[:, COLS.conic]
    else:
        conic = jnp.broadcast_to(jnp.asarray([1.0, 0.0, 1.0], packed.dtype), A.shape)
    r2 = 2.0 * jnp.log(jnp.maximum(peak, ALPHA_MIN) * (255.0 / (1.0 - 1e-3)))
    # The test is homogeneous in (A, B, C): scaled so that s = x A + y B + C stays far from float32's
    # range at any pixel (x, y up to about 1e4).
    m = jnp.maximum(jnp.max(jnp.abs(jnp.concatenate([A, B], axis=-1)), axis=-1) * 1e4,
                    jnp.max(jnp.abs(Cc), axis=-1))
    k = 1.0 / jnp.maximum(m, 1e-30)[:, None]
    A, B, Cc = A * k, B * k, Cc * k
    return jnp.concatenate([A, B, Cc, conic, r2[:, None], side[:, None], packed[:, COLS.mu]], axis=-1)


def alpha_peak(scene: Scene):
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


def constant_textures(scene: Scene):
    """The textures of one texel (side 1, bucket 0: a constant, which a lookup returns exactly) as
    per-splat terms: (rgb_add (C, 3) or None, alpha_mul (C,) or None, rgb_const (C,) bool or None,
    alpha_const (C,) bool or None): the RGB offset to add to the colour (0 elsewhere), the factor of
    the opacity (1 elsewhere), and which splats' textures they are. Differentiable in the texels."""
    out = []
    for bank, neutral in ((scene.rgb, 0.0), (scene.alpha, 1.0)):
        if bank is None or not bank.buckets or bank.buckets[0].shape[0] == 0:
            out.append((None, None))
            continue
        data = bank.buckets[0]
        const = lax.stop_gradient(bank.bucket) == 0
        slot = jnp.clip(lax.stop_gradient(bank.slot).astype(jnp.int32), 0, data.shape[0] - 1)
        value = data[slot, 0, 0]  # (C, ch)
        value = jnp.where(const[:, None], value, neutral)
        out.append((value if bank.channels > 1 else value[:, 0], const))
    (rgb_add, rgb_const), (alpha_mul, alpha_const) = out
    return rgb_add, alpha_mul, rgb_const, alpha_const
