"""The jitted training steps: one view's loss and gradients, and the guarded Adam update.

:func:`single_view_step` and :func:`batch_step` share :func:`_view_loss_and_grads` (the loss) and
:func:`_guarded_update` (the update, skipped on a non-finite loss or gradient or a tile-capacity
overflow). They are jitted by :class:`patexgs_jax.training.trainer.Trainer`, once per render
configuration, tile capacity and scene layout, with the state donated.
"""

from __future__ import annotations

import collections

import chex
import jax
import jax.numpy as jnp
import optax

from .. import background, losses, padding, parallel
from .. import densify as dens
from ..render import render_jit

__all__ = ["AHEAD_STEP_TRACES", "STEP_TRACES", "batch_step", "single_view_step", "view_loss_and_grads"]

#: Traces of the jitted training step, per (render config, capacity[, batch size]): tests assert on it.
#: Traces made by a background compile (:mod:`patexgs_jax.background`) count in AHEAD_STEP_TRACES instead,
#: so that STEP_TRACES counts what the steps themselves trace (and a step can tell that it traced).
STEP_TRACES: collections.Counter = collections.Counter()
AHEAD_STEP_TRACES: collections.Counter = collections.Counter()


def _count_trace(key) -> None:
    (AHEAD_STEP_TRACES if background.in_background() else STEP_TRACES)[key] += 1

_GROUPS = ("means", "log_scales", "quats", "opacity_logits", "sh", "rgb", "alpha")


def _term_on(weight) -> bool:
    """Whether a loss term is computed: a weight given as a Python number switches it off at 0 (the
    term is compiled out); a traced weight (an argument of the step) keeps it."""
    return not isinstance(weight, (int, float)) or weight > 0


def view_loss_and_grads(scene, camera, image, active_sh, w_normal, *, render_config, capacity, lambda_dssim,
                        lambda_dist, valid_hw=None):
    """One view's loss and gradients: ``((loss, (out, l1, mse)), (g_scene, g_offset))``, g_offset
    (C, 2) the gradient w.r.t. the renderer's ``screen_offset`` (densification statistics).
    ``lambda_dssim`` and ``lambda_dist`` are numbers or traced () floats (see :func:`_term_on`).

    ``camera`` and ``image`` (Hb, Wb, 3) may be padded to a padded size (:mod:`patexgs_jax.padding`);
    ``valid_hw`` ((2,) int, traced) is then the view's own (H, W): the loss is that of the top-left
    H x W block and the renderer bins the tiles covering that block only, so views of every size
    of one padded size share one compiled step, whatever the padded size (one per view's tile grid,
    or one for every view: :func:`patexgs_jax.padding.train_camera`)."""
    chex.assert_shape(image, (camera.height, camera.width, 3), custom_message=(
        "the training image and its camera disagree; each view's image must be (H, W, 3) at its "
        "camera's size (a loader or a hand-made view gave another size)"))
    chex.assert_type(image, float, custom_message="training images are floating-point RGB in [0, 1]")
    offset = jnp.zeros((scene.capacity, 2), scene.means.dtype)
    valid = None if valid_hw is None else padding.valid_mask(image.shape[:2], valid_hw)

    def loss_fn(sc, off):
        out = render_jit(sc, camera, config=render_config, capacity=capacity, screen_offset=off,
                         active_sh_degree=active_sh, valid_hw=valid_hw)
        photo, l1 = losses.photometric(out.rgb, image, lambda_dssim, valid=valid)
        loss = photo
        loss = loss + w_normal * losses.normal_consistency(out.normal, out.depth, out.alpha, camera.K, valid=valid)
        if _term_on(lambda_dist):
            loss = loss + lambda_dist * losses.distortion(out.distortion, valid=valid)
        mse = losses.masked_mean(jnp.square(jnp.clip(out.rgb, 0, 1) - image), valid)
        return loss, (out, l1, mse)

    return jax.value_and_grad(loss_fn, argnums=(0, 1), has_aux=True)(scene, offset)


def _finite_groups(g_scene) -> dict:
    """Per parameter group, whether every gradient entry is finite (() bool each)."""
    finite = {}
    for name in _GROUPS:
        leaves = jax.tree_util.tree_leaves(getattr(g_scene, name))
        finite[name] = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.array(True)
    return finite


def _guarded_update(scene, opt_state, g_scene, loss, overflow, optimizer, rates=None):
    """The optimiser's update from ``g_scene`` (with the traced learning rates ``rates`` where given,
    :func:`patexgs_jax.optim.step_rates`), applied only if the loss and every gradient are finite
    and the render did not overflow: ``(scene, opt_state, ok, finite)``, the inputs unchanged when
    ``ok`` is False (so a bad step never poisons the state)."""
    finite = _finite_groups(g_scene)
    all_finite = jnp.isfinite(loss) & jnp.all(jnp.stack(list(finite.values())))
    ok = all_finite & ~overflow
    extra = {} if rates is None else dict(rates=rates)
    updates, new_opt = optimizer.update(g_scene, opt_state, scene, **extra)
    new_scene = optax.apply_updates(scene, updates)

    def keep(new, old):  # the update where every gradient is finite and nothing overflowed, else the old state
        return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)

    return keep(new_scene, scene), keep(new_opt, opt_state), ok, finite


def single_view_step(scene, opt_state, stats, camera, image, valid_hw, active_sh, w_normal, *, optimizer,
                     render_config, capacity, lambda_dssim, lambda_dist, rates=None):
    """One single-view update.

    Args:
      camera: the view's camera at its padded size (:func:`patexgs_jax.padding.train_camera`: its
        own tile grid or a larger one; either way every per-splat output equals the unpadded
        render's, the renderer binning the tiles of the view's own grid only).
      image: (Hb, Wb, 3) float32, the view's image zero-padded to its padded size.
      valid_hw: (2,) int32, the view's own (H, W).
      active_sh, w_normal: traced SH degree and normal-consistency weight.
      lambda_dssim, lambda_dist: loss weights, numbers or traced (see :func:`view_loss_and_grads`).
      rates: None (the optimiser's own learning rates) or the traced ones it takes as ``rates=``
        (:func:`patexgs_jax.optim.step_rates`).
    Returns:
      (scene, opt_state, stats, metrics); the update is skipped (state unchanged) on overflow or a
      non-finite loss or gradient.
    """
    _count_trace((render_config, capacity))
    (loss, (out, l1, mse)), (g_scene, g_off) = view_loss_and_grads(
        scene, camera, image, active_sh, w_normal, render_config=render_config, capacity=capacity,
        lambda_dssim=lambda_dssim, lambda_dist=lambda_dist, valid_hw=valid_hw)
    new_scene, new_opt, ok, finite = _guarded_update(scene, opt_state, g_scene, loss, out.overflow, optimizer, rates)
    new_stats = dens.accumulate(stats, jnp.where(ok, g_off, 0.0), out.visible & ok, out.radius_px,
                                valid_hw[1], valid_hw[0])
    metrics = dict(loss=loss, l1=l1, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-10)), ok=ok,
                   finite=finite, overflow=out.overflow, pairs_needed=out.pairs_needed,
                   max_tile_count=out.max_tile_count)
    return new_scene, new_opt, new_stats, metrics


def batch_step(scene, opt_state, stats, cameras, images, active_sh, w_normal, *, mesh, optimizer,
               render_config, capacity, lambda_dssim, lambda_dist, rates=None):
    """One update from a batch of B views (data-parallel over ``mesh``, see :mod:`patexgs_jax.parallel`).

    Args:
      cameras: a Camera with K (B, 3, 3) and world_to_camera (B, 4, 4), one image size.
      images: (B, H, W, 3) float32.
      Everything else as :func:`single_view_step`.
    Returns:
      As :func:`single_view_step`. The loss is the mean of the B views' losses (so the gradient is
      the mean of their gradients: one Adam update), the densification statistics gain the B views
      one after another (each with its own screen-offset gradient, as B single-view steps would add
      them), and the update is skipped if any view overflowed or any gradient is non-finite;
      ``pairs_needed`` and ``max_tile_count`` are the maxima over the batch, ``l1`` and ``psnr``
      the means.
    """
    B = images.shape[0]
    _count_trace((render_config, capacity, B))

    dist_on = _term_on(lambda_dist)

    def one_view(shared, view):
        sc, sh, wn, (w_dssim, w_dist) = shared  # (the weights as inputs: they may be traced)
        cam, img = view
        (loss, (out, l1, mse)), (g_scene, g_off) = view_loss_and_grads(
            sc, cam, img, sh, wn, render_config=render_config, capacity=capacity, lambda_dssim=w_dssim,
            lambda_dist=w_dist if dist_on else 0.0)
        per = dict(loss=loss, l1=l1, mse=mse, g_off=g_off, visible=out.visible, radius_px=out.radius_px,
                   overflow=out.overflow, pairs_needed=out.pairs_needed, max_tile_count=out.max_tile_count)
        return g_scene, per

    g_sum, per = parallel.sum_over_views(one_view, mesh)(
        (scene, active_sh, w_normal, (jnp.float32(lambda_dssim), jnp.float32(lambda_dist))), (cameras, images))
    g_scene = jax.tree_util.tree_map(lambda g: g / B, g_sum)
    loss = jnp.mean(per["loss"])
    overflow = jnp.any(per["overflow"])
    new_scene, new_opt, ok, finite = _guarded_update(scene, opt_state, g_scene, loss, overflow, optimizer, rates)
    new_stats = stats
    for b in range(B):
        new_stats = dens.accumulate(new_stats, jnp.where(ok, per["g_off"][b], 0.0), per["visible"][b] & ok,
                                    per["radius_px"][b], cameras.width, cameras.height)
    psnr = -10.0 * jnp.log10(jnp.maximum(per["mse"], 1e-10))
    metrics = dict(loss=loss, l1=jnp.mean(per["l1"]), psnr=jnp.mean(psnr), ok=ok, finite=finite,
                   overflow=overflow, pairs_needed=jnp.max(per["pairs_needed"]),
                   max_tile_count=jnp.max(per["max_tile_count"]))
    return new_scene, new_opt, new_stats, metrics
