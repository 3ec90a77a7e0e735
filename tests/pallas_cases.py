"""The Pallas compositor (``RenderConfig(compositor="pallas")``, interpreted on the CPU) against the
XLA compositor: every output and the gradients of a loss of every output, with respect to the
scene and to ``screen_offset`` (tests/unit/test_pallas_composite.py, tests/integration/...).

The two compositors do the same maths in a different order (the kernel multiplies transmittances
where the XLA path sums their logarithms), so they agree to float32 rounding except where a
threshold (a pair's alpha at 1/255, the 1e-4 transmittance stop) flips on that rounding.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from patexgs_jax import render_jit
from patexgs_jax.rendering import binning, composite, pallas_composite, projection
from patexgs_jax.rendering.chunks import CompositeInputs, Static

FIELDS = ("rgb", "alpha", "depth", "normal", "distortion")
#: Per-output tolerance, times the output's largest magnitude where above 1 (depth: camera z;
#: distortion: up to (1/near)^2 for splats at the near plane).
ATOL = dict(rgb=2e-5, alpha=2e-5, depth=2e-5, normal=2e-5, distortion=2e-5)
#: Gradients: each leaf within GRAD_RTOL of its largest entry (float32 sums in another order).
GRAD_RTOL = 2e-4
#: The compositor's gradient (packed columns): within this of each column's largest entry. The
#: hard scenes' float32 compositor gradients (either compositor's) are within 3e-4 of float64's;
#: the kernel's within 1e-4 where the XLA compositor's are within 2e-4 (it sums each pixel's
#: terms behind a pair back to front, without the cancellation of ``total - front``).
PACKED_RTOL = 1e-3


@functools.partial(jax.jit, static_argnames=("config", "capacity"))
def render_and_grad(scene, cam, config, capacity):
    """A loss of every output, its gradient (scene, screen_offset) and the outputs."""
    rng = np.random.default_rng(0)
    wts = jnp.asarray(rng.uniform(0.5, 1.5, (cam.height, cam.width, 3)), jnp.float32)

    def loss(s, off):
        out = render_jit(s, cam, config=config, capacity=capacity, screen_offset=off)
        val = (jnp.sum(out.rgb * wts) + 0.7 * jnp.sum(out.alpha) + 0.1 * jnp.sum(out.depth)
               + jnp.sum(out.normal * wts) + 10.0 * jnp.sum(out.distortion))
        return val, out

    off = jnp.zeros((scene.capacity, 2), scene.means.dtype)
    (_, out), grads = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(scene, off)
    return out, grads


@functools.partial(jax.jit, static_argnames=("config", "capacity"))
def render_only(scene, cam, config, capacity):
    """The outputs alone (:func:`compare` at the packed level: its gradients are the compositor's)."""
    return render_jit(scene, cam, config=config, capacity=capacity)


@functools.partial(jax.jit, static_argnames=("config", "capacity", "compositor"))
def composite_grad(scene, cam, config, capacity, compositor):
    """The compositor's own gradient: of a loss of its accumulators and transmittances, with
    respect to the packed splat columns (C, F), for the view's projection and tile lists."""
    ts = config.tile_size
    tiles_x, tiles_y = -(-cam.width // ts), -(-cam.height // ts)
    proj = projection.project(scene, cam, config, None, None, projection.alpha_peak(scene))
    ranges = binning.tile_ranges(proj.bounds, proj.visible, ts, tiles_x, tiles_y)
    ids, start, binned = binning.bin_projection(proj, ranges, tiles_x, tiles_x * tiles_y, capacity.pairs, config)
    st = Static(config=config, tiles_x=tiles_x, num_tiles=tiles_x * tiles_y, rgb=False, alpha=False)
    ctx = CompositeInputs(ids_sorted=ids, tile_start=start, binned=binned, peak=projection.alpha_peak(scene),
                          flag=binned[0] >= 0)
    fn = pallas_composite.composite_tiles if compositor == "pallas" else composite.composite_tiles

    def loss(packed):
        acc, t_final, _ = fn(st, packed, None, None, ctx)
        wts = jnp.linspace(0.5, 1.5, acc.size, dtype=acc.dtype).reshape(acc.shape)
        return jnp.sum(acc * wts) + 0.7 * jnp.sum(t_final)

    return jax.grad(loss)(proj.packed)


def render_float64(scene, cam, config, capacity):
    """The XLA compositor's outputs in float64 (the arbiter of :func:`_as_accurate`)."""
    with jax.enable_x64(True):
        out = render_only(scene.astype(jnp.float64), cam, dataclasses.replace(config, compositor="xla"), capacity)
        return jax.tree_util.tree_map(np.asarray, out)


def _composited(out, field):
    """An output as compared: depth weighted by alpha (depth alone divides by tiny alphas)."""
    x = getattr(out, field)
    return x * out.alpha if field == "depth" else x


def _per_pixel(err):
    return err.max(axis=-1) if err.ndim == 3 else err


def _as_accurate(kernel_error, xla_error, tol):
    """Where the kernel's error against float64 is at most twice the XLA compositor's float32 error,
    plus ``tol``."""
    return kernel_error <= 2.0 * xla_error + tol


def compare(scene, cam, config, capacity, flips=0.0, grads=True, level="scene", packed_rtol=None, leaves=None):
    """The Pallas compositor's outputs (and gradients) against the XLA compositor's for ``config``;
    ``flips``: the share of pixels where a threshold may flip on rounding (outputs beyond the
    tolerance there; gradients are then not compared). ``level``: "scene", the gradients of the
    scene and ``screen_offset``; "packed", the compositor's own (:func:`composite_grad`), for
    ill-conditioned scenes whose projection's backward turns float32 rounding anywhere into
    errors of 1e-3 of the scene gradients (the XLA compositor's against its float64 self too),
    within ``packed_rtol`` (default :data:`PACKED_RTOL`) of each column's largest entry; "texels", the
    scene's texture gradients alone (linear in the texels: no projection between them and the
    compositor).

    At the "packed" level (the hard scenes), where the two float32 compositors disagree beyond the
    tolerance, float64 decides: the kernel passes where it is within twice the XLA compositor's own
    float32 error of the XLA compositor in float64, plus the tolerance (outputs pixel by pixel,
    :func:`_as_accurate`; gradients against the XLA compositor's largest error in the column). An
    ill-conditioned pixel or column (a huge splat seen nearly edge-on, a whole scene inside one
    pixel) is off float64 by more than the tolerance in either compositor, by how much and where
    depending on the order of float32 sums and products, which XLA's code generation sets (the
    focal case's whole scene in one pixel: 17% of a column's largest entry in both)."""
    xla = dataclasses.replace(config, compositor="xla")
    pal = dataclasses.replace(config, compositor="pallas")
    if level == "packed":
        out_x, out_p = (jax.tree_util.tree_map(np.asarray, render_only(scene, cam, c, capacity)) for c in (xla, pal))
        g_x = g_p = None
    else:
        out_x, g_x = jax.tree_util.tree_map(np.asarray, render_and_grad(scene, cam, xla, capacity))
        out_p, g_p = jax.tree_util.tree_map(np.asarray, render_and_grad(scene, cam, pal, capacity))
    assert not out_x.overflow
    out_64 = None
    bad = np.zeros(out_x.alpha.shape, bool)
    for f in FIELDS:
        x, p = _composited(out_x, f), _composited(out_p, f)
        tol = ATOL[f] * max(1.0, float(np.abs(x).max()))  # relative to the output's range
        bad_f = _per_pixel(np.abs(p - x)) > tol
        if level == "packed" and bad_f.any():
            if out_64 is None:
                out_64 = render_float64(scene, cam, xla, capacity)
            r = _composited(out_64, f)
            bad_f &= ~_as_accurate(_per_pixel(np.abs(p - r)), _per_pixel(np.abs(x - r)), tol)
        bad |= bad_f
    assert np.mean(bad) <= flips, (np.mean(bad), {f: np.abs(getattr(out_p, f) - getattr(out_x, f)).max()
                                                  for f in FIELDS})
    same = out_p.dominant == out_x.dominant
    assert np.mean(~same & ~bad) <= 0.002, np.mean(~same)  # ties of equal weights may pick either
    np.testing.assert_array_equal(out_p.visible, out_x.visible)
    if not grads or bad.any():
        return out_x, out_p
    if level == "packed":
        g_x = np.asarray(composite_grad(scene, cam, xla, capacity, "xla"))
        g_p = np.asarray(composite_grad(scene, cam, pal, capacity, "pallas"))
        scale = np.abs(g_x).max(axis=0)  # per packed column
        err = np.abs(g_p - g_x)
        rtol = PACKED_RTOL if packed_rtol is None else packed_rtol
        off = err > rtol * scale + 1e-7
        if off.any():
            with jax.enable_x64(True):
                g_64 = np.asarray(composite_grad(scene.astype(jnp.float64), cam, xla, capacity, "xla"))
            # (column-wise: which entries of an ill-conditioned column are off depends on the rounding)
            off &= ~_as_accurate(np.abs(g_p - g_64), np.abs(g_x - g_64).max(axis=0),
                                 rtol * np.abs(g_64).max(axis=0) + 1e-7)
        ratio = np.where(off, err / (scale + 1e-30), 0.0)
        i = np.unravel_index(np.argmax(ratio), ratio.shape)
        assert not off.any(), (i, ratio[i], g_x[i], g_p[i], scale[i[1]])
        return out_x, out_p
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g_x), jax.tree_util.tree_leaves(g_p), strict=True):
        if not np.issubdtype(a.dtype, np.floating) or not a.size:
            continue
        if level == "texels" and ".buckets" not in jax.tree_util.keystr(path):
            continue
        scale = float(np.abs(a).max())
        # texels: the one-texel textures' gradients come through the projection (they are folded
        # into the colour and opacity), as ill-conditioned there as the scene's (see PACKED_RTOL).
        rtol = PACKED_RTOL if level == "texels" else GRAD_RTOL
        np.testing.assert_allclose(b, a, rtol=0, atol=rtol * scale + 1e-7, err_msg=jax.tree_util.keystr(path))
    return out_x, out_p
