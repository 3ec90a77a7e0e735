"""Projection of 3D Gaussians (3DGS, Mip-Splatting) into the compositor's packed columns.

A 3D Gaussian has a mean m, a rotation R and three scales s (``Scene.log_scales`` (C, 3)), so the
covariance ``Sigma = R diag(s^2) R^T``; where the scene carries Mip-Splatting's 3D filter
(``Scene.filter3d``, a variance f per Gaussian) it is ``Sigma + f I`` and the opacity is scaled by
``sqrt(det Sigma / det(Sigma + f I))`` (:mod:`patexgs_jax.filter3d`). As in 3DGS (EWA splatting,
Zwicker et al. 2001) the screen covariance is ``Sigma' = J W Sigma W^T J^T``: W the camera's
rotation, J = d(pixel)/d(camera point) at the centre; as 3DGS, the centre's x/z and y/z in J are
clamped to 1.3 times the half field of view (pixels cx +- 0.65 W, cy +- 0.65 H), so that Gaussians
far outside the view do not get huge footprints. The kernel at pixel offset d from the projected
centre is ``G = exp(-0.5 d^T (Sigma' + e I)^-1 d)`` with, by ``RenderConfig.coverage``:

* "lowpass": 3DGS's dilation, e = :data:`DILATION` (0.3 px^2), the opacity unchanged (what the 3DGS
  paper calls its screen-space low-pass filter);
* "prefilter": Mip-Splatting's 2D Mip filter, e = ``RenderConfig.pixel_var`` (0.1 px^2 by default,
  the paper's), the opacity times ``sqrt(det Sigma' / det(Sigma' + e I))`` (the splat's integral is
  kept). ``RenderConfig.min_var`` is a 2D-splat setting and does not apply: 3D Gaussians are kept
  from going sub-pixel by the 3D filter instead.

A pair is skipped below alpha 1/255 of the composited alpha, as both reference rasterizers do (the
coverage column is 1). The depth of every pair is the centre's camera z; the normal is the
camera-frame axis of the Gaussian's smallest scale, turned to face the camera (a 3D Gaussian has no surface: it is
the axis a flattened Gaussian's surface would have).

The compositor evaluates G with its prefiltered kernel (:mod:`.kernel`), whose conic, support and
ray-plane columns fit a screen-space quadratic form exactly: the "plane" map sends pixel (x, y) to
(u, v) = d / w (A = (1, 0, 0) / w, B = (0, 1, 0) / w, C = (-mu_x / w, -mu_y / w, 1), w the larger
screen standard deviation) and the conic columns hold ``w^2 (Sigma' + e I)^-1``. Binning, tile
culling, compositing and the hand-written backward are those of 2D splats (:func:`kernel_config`);
gradients reach the mean through C and the covariance through the conic.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import lax

from ..camera import Camera
from ..math import quat_to_rotmat, safe_normalize, safe_sqrt, sh_basis
from ..scene import Scene
from .config import ALPHA_MIN, SUPPORT_Q, RenderConfig
from .projection import COLS, HIGHEST, Projection, _footprint, filtered_log_scales

__all__ = ["DILATION", "FOV_CLAMP", "kernel_config", "project3d", "screen_covariance"]

#: 3DGS's screen-space dilation (px^2), added to every projected covariance under coverage "lowpass".
DILATION = 0.3
#: J's centre is clamped to this many times the half field of view (3DGS's 1.3).
FOV_CLAMP = 1.3


def kernel_config(config: RenderConfig, scene: Scene) -> RenderConfig:
    """The settings binning and the compositor run with: ``config`` for 2D splats; for 3D Gaussians
    coverage "prefilter" whatever their coverage mode (their packed columns are always those of the
    screen-space quadratic form, see the module docstring)."""
    if scene.is_3d and config.coverage in ("object", "texel-grid"):
        raise ValueError(f"coverage {config.coverage!r} is a reading of Eq. 13 for 2D splats; render 3D Gaussians "
                         "with coverage 'lowpass' (3DGS's dilation) or 'prefilter' (Mip-Splatting's 2D filter).")
    if scene.is_3d and config.coverage != "prefilter":
        return dataclasses.replace(config, coverage="prefilter")
    return config


def screen_covariance(scene: Scene, camera: Camera, p, mu):
    """The EWA projection of each Gaussian (3D filter included).

    Args:
      p: (C, 3) the centres in the camera frame; mu: (C, 2) projected (pixels), before any screen
        offset.
    Returns:
      T (C, 2, 3) with ``Sigma' = T T^T`` (px^2), T = J W R diag(s) over k, and k (C,) >= 1 the scale
      taken out of T so that neither huge nor tiny Gaussians overflow float32; the filter's opacity
      factor (C,).
    """
    dt = scene.means.dtype
    K = camera.K.astype(dt)
    Rc = camera.world_to_camera.astype(dt)[:3, :3]
    z = jnp.where(p[:, 2] > 0, p[:, 2], 1.0)
    half = 0.5 * FOV_CLAMP * jnp.asarray([camera.width, camera.height], dt)
    mu_c = jnp.clip(mu, K[:2, 2] - half, K[:2, 2] + half)
    e3 = jnp.asarray([0.0, 0.0, 1.0], dt)
    J = (K[None, :2, :] - mu_c[:, :, None] * e3[None, None, :]) / z[:, None, None]       # (C, 2, 3)
    ls_f, factor = filtered_log_scales(scene)
    L = jnp.einsum("ij,cjk->cik", Rc, quat_to_rotmat(scene.quats), precision=HIGHEST) * jnp.exp(ls_f)[:, None, :]
    T = jnp.einsum("cij,cjk->cik", J, L, precision=HIGHEST)
    k = jnp.maximum(lax.stop_gradient(jnp.max(jnp.abs(T), axis=(1, 2))), 1.0)
    return T / k[:, None, None], k, factor


def project3d(scene: Scene, camera: Camera, config: RenderConfig, screen_offset, active_sh_degree) -> Projection:
    """The per-Gaussian quantities of a view in the :data:`projection.COLS` layout of the prefilter
    (width 29), as :func:`projection.project` returns them for 2D splats.

    Args:
      screen_offset: None or (C, 2), added to the centres on screen (the densification's gradient hook).
      active_sh_degree: None or a traced int: SH bands above it are masked.
    """
    dt = scene.means.dtype
    K = camera.K.astype(dt)
    w2c = camera.world_to_camera.astype(dt)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    p = jnp.matmul(scene.means, Rc.T, precision=HIGHEST) + tc
    depth = p[:, 2]
    in_front = depth > config.near
    zs = jnp.where(in_front, depth, 1.0)
    mu = jnp.matmul(p, K[:2].T, precision=HIGHEST) / zs[:, None]
    T, k, filter_factor = screen_covariance(scene, camera, p, mu)
    t0, t1 = T[:, 0], T[:, 1]
    a, b, c = jnp.sum(t0 * t0, -1), jnp.sum(t0 * t1, -1), jnp.sum(t1 * t1, -1)
    # det(T T^T) = |t0 x t1|^2 (Cauchy-Binet): a sum of squares, no cancellation for a flat Gaussian.
    cr = jnp.stack([t0[:, 1] * t1[:, 2] - t0[:, 2] * t1[:, 1], t0[:, 2] * t1[:, 0] - t0[:, 0] * t1[:, 2],
                    t0[:, 0] * t1[:, 1] - t0[:, 1] * t1[:, 0]], axis=-1)
    det = jnp.sum(cr * cr, -1)
    prefilter = config.coverage == "prefilter"
    k2 = k * k
    e = (config.pixel_var if prefilter else DILATION) / k2
    den = det + e * (a + c) + e * e                         # det(Sigma' + e I) / k^4, > 0
    conic = jnp.stack([c + e, -b, a + e], axis=-1) / (k2 * den)[:, None]
    screen = jnp.stack([k2 * (a + e), k2 * (c + e)], axis=-1)  # the filtered covariance's diagonal
    if screen_offset is not None:
        mu = mu + screen_offset.astype(dt)

    cam_center = -jnp.linalg.solve(Rc, tc)
    dirs = safe_normalize(scene.means - cam_center)
    basis = sh_basis(dirs, scene.sh_degree, active_sh_degree)
    color = jnp.maximum(jnp.einsum("ck,ckj->cj", basis, scene.sh, precision=HIGHEST) + 0.5, 0.0)
    R = quat_to_rotmat(scene.quats)
    short = jax.nn.one_hot(jnp.argmin(lax.stop_gradient(scene.log_scales), axis=-1), 3, dtype=dt)
    nrm = jnp.matmul(jnp.einsum("cjk,ck->cj", R, short, precision=HIGHEST), Rc.T, precision=HIGHEST)
    normal = jnp.where((jnp.sum(nrm * p, axis=-1) > 0)[:, None], -nrm, nrm)

    opacity = jax.nn.sigmoid(scene.opacity_logits) * (scene.active > 0) * filter_factor
    if prefilter:  # Mip-Splatting's 2D filter keeps the integral: sqrt(det Sigma' / det(Sigma' + e I))
        opacity = opacity * safe_sqrt(det / den)
    peak = lax.stop_gradient(opacity)
    visible = in_front & (peak >= ALPHA_MIN)
    r2 = jnp.where(visible, 2.0 * jnp.log(jnp.maximum(peak, ALPHA_MIN) * 255.0), 0.0)
    mus, sc = lax.stop_gradient(mu), lax.stop_gradient(screen)
    hx, hy = jnp.sqrt(r2 * sc[:, 0]), jnp.sqrt(r2 * sc[:, 1])
    bounds = (mus[:, 0] - hx, mus[:, 0] + hx, mus[:, 1] - hy, mus[:, 1] + hy)
    radius = jnp.where(visible, jnp.maximum(hx, hy), 0.0)

    C = depth.shape[0]
    one, zero = jnp.ones((C, 1), dt), jnp.zeros((C, 1), dt)
    # (u, v) = d / w, in units of the larger screen standard deviation w (a constant for the
    # gradient: q = d^T conic d whatever w), so that the compositor's "no intersection" limit
    # (|u|, |v| < kernel.UV_LIMIT) lies 1e4 deviations out, where G has long underflowed, for a
    # Gaussian of any size on screen.
    w = lax.stop_gradient(jnp.sqrt(jnp.maximum(screen[:, 0], screen[:, 1])))[:, None]
    plane = [1.0 / w, zero, zero, zero, 1.0 / w, zero, -mu[:, :1] / w, -mu[:, 1:] / w, one]   # A, B, C
    m2 = [zero, zero, depth[:, None]]                                             # z of every pair: the centre's
    cols = plane + m2 + [mu, opacity[:, None], color, normal, depth[:, None], conic * (w * w), one,
                         lax.stop_gradient(conic) / SUPPORT_Q]
    packed = jnp.concatenate(cols, axis=-1)
    assert packed.shape[-1] == COLS.width_prefilter
    big = 1e9
    return Projection(packed=packed, depth=depth, visible=visible, bounds=bounds,
                      radius=jnp.where(jnp.isfinite(radius), radius, big),
                      footprint=_footprint(lax.stop_gradient(packed), peak, True))
