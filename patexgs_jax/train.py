"""Training: the 2DGS stage, then the PATexGS texture stage (or a baseline), with checkpoints.

    python -m patexgs_jax.train --data PATH --method patexgs --out DIR [--factor F]
        [--iters-2dgs N] [--iters-tex N] [--max-gaussians N] [--resume]
        [--batch-size B [--devices D]] [--coordinator HOST:PORT --num-processes N --process-id I]

``--batch-size`` trains data-parallel over devices and, with the last three flags (or under SLURM
``srun`` / Open MPI ``mpirun``), over several processes: see :mod:`patexgs_jax.parallel` and
docs/parallel.md.

Without ``--data`` it trains on the embedded synthetic scene (generated once into the cache).

Stages
  1. 2DGS (every method): SfM-point initialisation, per-group Adam (:mod:`patexgs_jax.optim`),
     loss ``0.8 L1 + 0.2 (1 - SSIM)`` plus the normal-consistency (from ``normal_from``) and
     depth-distortion regularisers, one SH band every ``sh_interval`` steps, adaptive density
     control (:mod:`patexgs_jax.densify`).
  2. Textures (all methods but ``2dgs``): ``patexgs*`` start every Gaussian with a 5x5 alpha
     texture (ones) and a 1x1 RGB offset (zeros) - the first render equals the 2DGS one - warm up
     ``warmup_tex`` steps, then allocate Eq. 7 sizes from the max-contribution counts over all
     training views and grow them by Eqs. 8-10 every ``growth_interval`` steps
     (:mod:`patexgs_jax.schedule`); ``textured-fixed-N`` gives every Gaussian an N x N RGBA texture.

Methods: ``2dgs``, ``textured-fixed-N`` (N in 1, 2, 4, 8, 16, 32; no mipmaps, as Textured Gaussians),
``patexgs`` (adaptive + RGBA mipmaps), ``patexgs-no-mip``, ``patexgs-no-alpha-mip``,
``patexgs-no-rgb-mip``, ``patexgs-no-adaptive`` (RGBA mipmaps with a fixed 8x8 texture per Gaussian:
the mipmaps without the adaptive allocation), ``patexgs-fixed-N`` (N in 1..32: ``patexgs`` with N x N
textures for every Gaussian at the allocation step and no growth, the fixed rows of the paper's
Table 4), ``patexgs-trilinear`` (mip levels blended trilinearly),
``patexgs-literal`` (the paper's Eqs. 11-13 read literally: the 2DGS screen-space low-pass and
lambda_mip 0.4). The ``patexgs`` family, but ``patexgs-literal``, renders its texture stage, and
is evaluated, with the prefiltered coverage (``RenderConfig(coverage="prefilter")``); stage 1 is
2DGS for every method.

Robustness
  The data order is a per-epoch permutation seeded by (seed, epoch), and every random choice is
  seeded by (seed, step), so ``--resume`` from a checkpoint reaches the same result as an
  uninterrupted run. A non-finite loss or gradient, or a render whose tile capacity overflowed,
  skips the update (never applied, never poisoning the state); overflow grows the capacity and the
  step is retried; ``max_bad_steps`` consecutive non-finite steps stop the run, keeping the last
  good checkpoint.

Compiled programs (see :mod:`patexgs_jax.compiled`)
  A training view is padded to the renderer's tile grid (:mod:`patexgs_jax.buckets`; the loss is
  the view's own, the per-splat statistics the unpadded render's), so the step compiles once per
  distinct tile grid of the training images, not once per image size, and again only when the
  tile capacity or the scene's shapes change (densification, texture growth); the programs of
  earlier shapes are then released (and at most a few capacities kept per shapes). Near the kernel's memory-map cap the run releases
  all compiled code and, if that is not enough, checkpoints and stops with
  :class:`patexgs_jax.compiled.MapLimitReached` (resume with ``--resume``).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import sys
import time
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import buckets
from . import checkpoint as ckpt
from . import compiled
from . import densify as dens
from . import losses, progress
from . import schedule as sched
from .metrics import storage_mb
from .optim import LearningRates, make_optimizer, upgrade_state
from .rendering import Capacity, RenderConfig, count_pairs, render_jit
from .scene import Scene

#: Traces of the jitted training step, per (render config, capacity): tests assert on it.
STEP_TRACES: collections.Counter = collections.Counter()

#: Sub-folder of a run's checkpoints holding its end-of-2DGS-stage checkpoint (see _Run.save_stage1).
STAGE1_DIR = "stage1"

#: Steps between two looks at the memory-map count (it is also read after every compile).
_MAP_CHECK_EVERY = 25

#: Jitted steps (capacities) kept for one scene layout.
_MAX_STEP_FNS = 4


def _layout(scene: Scene) -> tuple:
    """The shapes of a scene's arrays: what, with the static arguments, selects a compiled step."""
    return tuple(np.shape(x) for x in jax.tree_util.tree_leaves(scene))


FIXED_SIZES = (1, 2, 4, 8, 16, 32)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a run depends on (saved in checkpoints and the summary).

    Attributes:
      method: see the module docstring.
      iters_2dgs, iters_tex: steps of the two stages (``iters_tex`` unused by ``2dgs``).
      continue_2dgs: ``2dgs`` only: steps that continue the 2DGS stage after ``iters_2dgs`` (its
        schedules as at the end of the stage: no densification, the final position learning rate).
        Set to ``iters_tex`` for a 2DGS baseline that trains as many steps as the textured methods
        (the studies do).
      warmup_tex: stage-2 warm-up steps before the Eq. 7 allocation (patexgs methods).
      growth_interval: steps between Eq. 8-10 growth events.
      growth_stop: fraction of stage 2 after which textures stop growing (t_final).
      tau_preset: Eq. 9's initial threshold (NDC gradient units, as densification).
      sigma: Eq. 7's sigma; None: :func:`patexgs_jax.schedule.pixel_share_sigma` of the training views
        and the Gaussians at the allocation (the paper's H * W / 1e4 at the paper's scale, the same
        meaning at other scales).
      texture_budget_mb: optional texel budget (MiB of RGBA texels): sigma is solved so that the Eq. 7
        allocation spends ``budget_eq7_share`` of it, and growth (Eqs. 8-10) may spend the rest; the
        total never exceeds it.
      budget_eq7_share: the share of ``texture_budget_mb`` the Eq. 7 allocation spends (at least one
        texel per Gaussian); growth is left the rest.
      max_texture_size: largest texture side.
      lambda_dssim, lambda_normal, lambda_dist: loss weights; ``normal_from`` the first step of
        the normal-consistency term.
      sh_degree, sh_interval: final SH degree and steps per added band.
      densify: adaptive density control (stage 1).
      max_gaussians: cap on the number of Gaussians (budget runs); None for no cap.
      lr: learning rates.
      background: RGB behind the scene.
      lambda_mip: the paper's lambda_mip (Eq. 11); None: the coverage mode's calibrated value
        (:data:`patexgs_jax.rendering.LAMBDA_MIP_DEFAULT`).
      seed: seeds data order, initialisation and every random choice.
      checkpoint_every: steps between checkpoints (and one at the end of each stage and the run).
      log_every: steps between progress lines.
      max_bad_steps: consecutive non-finite steps that stop the run.
      init_opacity: opacity of initial Gaussians.
      batch_size: views per step (one Adam update from the mean of their gradients); 1 is the
        single-view step. B > 1 takes B consecutive views of the per-epoch permutations and splits
        them over ``devices`` (:mod:`patexgs_jax.parallel`); every training view must have the
        same image size.
      devices: devices the batch is split over (must divide ``batch_size``); None: as many as
        JAX sees that divide it. Unused when ``batch_size`` is 1.
    """

    method: str = "patexgs"
    iters_2dgs: int = 30_000
    iters_tex: int = 30_000
    continue_2dgs: int = 0
    warmup_tex: int = 1_000
    growth_interval: int = 100
    growth_stop: float = 0.5
    tau_preset: float = 1e-5
    sigma: float | None = None
    texture_budget_mb: float | None = None
    budget_eq7_share: float = 0.8
    max_texture_size: int = 32
    lambda_dssim: float = 0.2
    lambda_normal: float = 0.05
    normal_from: int = 7_000
    lambda_dist: float = 0.0
    sh_degree: int = 3
    sh_interval: int = 1_000
    densify: dens.DensifyConfig = dens.DensifyConfig()
    max_gaussians: int | None = None
    lr: LearningRates = LearningRates()
    background: tuple = (0.0, 0.0, 0.0)
    lambda_mip: float | None = None
    seed: int = 0
    checkpoint_every: int = 2_000
    log_every: int = 100
    max_bad_steps: int = 20
    init_opacity: float = 0.1
    batch_size: int = 1
    devices: int | None = None

    def __post_init__(self):
        method_spec(self.method)
        if self.batch_size < 1 or (self.devices is not None and self.devices < 1):
            raise ValueError(f"batch_size and devices must be >= 1, got {self.batch_size} and {self.devices}.")
        if self.checkpoint_every < 1 or self.log_every < 1:
            raise ValueError(f"checkpoint_every and log_every must be >= 1, got {self.checkpoint_every} and "
                             f"{self.log_every}.")
        if self.iters_2dgs < 1 or self.iters_tex < 0:
            raise ValueError("iters_2dgs must be >= 1 and iters_tex >= 0.")
        if self.continue_2dgs < 0 or (self.continue_2dgs and self.method != "2dgs"):
            raise ValueError(f"continue_2dgs (steps that continue the 2DGS stage) must be >= 0 and is for method "
                             f"'2dgs' only, got {self.continue_2dgs} with method {self.method!r}.")
        if not 0 < self.budget_eq7_share <= 1:
            raise ValueError(f"budget_eq7_share (the share of the texture budget Eq. 7 spends) must be in (0, 1], got "
                             f"{self.budget_eq7_share}.")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}.")
        if self.growth_interval < 1 or self.warmup_tex < 0:
            raise ValueError(f"growth_interval must be >= 1 and warmup_tex >= 0, got {self.growth_interval} and "
                             f"{self.warmup_tex}.")
        if method_spec(self.method)["textures"] == "adaptive" and self.warmup_tex >= self.iters_tex:
            raise ValueError(
                f"method {self.method!r} allocates its texture sizes (Eq. 7) after the {self.warmup_tex}-step "
                f"texture warm-up, but the texture stage has only {self.iters_tex} steps: the allocation would never "
                "happen. Give more texture steps (iters_tex, --iters-tex) or a shorter warm-up (warmup_tex); "
                "preset_config scales the warm-up with an iters_tex override.")

    @property
    def total_steps(self) -> int:
        return self.iters_2dgs + (self.continue_2dgs if self.method == "2dgs" else self.iters_tex)

    def render_config(self, stage: int = 2) -> RenderConfig:
        """The renderer's settings in ``stage`` (1: the 2DGS stage, the same for every method so that
        it can be shared; 2: the method's own, also used to evaluate the trained scene)."""
        spec = method_spec(self.method)
        if stage == 1:
            return RenderConfig(mip="none", background=tuple(self.background))
        return RenderConfig(mip=spec["mip"], rgb_mip=spec["rgb_mip"], alpha_mip=spec["alpha_mip"],
                            coverage=spec["coverage"], lambda_mip=self.lambda_mip,
                            background=tuple(self.background))


#: The ``cpu`` preset (see :data:`PRESETS`).
CPU_PRESET = dict(iters_2dgs=1_000, iters_tex=400, warmup_tex=40, growth_interval=25, growth_stop=0.8,
                  normal_from=500, sh_interval=250, log_every=50, checkpoint_every=250, max_gaussians=6_000,
                  densify=dens.DensifyConfig(start=100, stop=700, interval=50, opacity_reset_interval=10_000))

#: Named schedules. ``tiny``: minutes on a 2-core CPU (the embedded-scene default); ``small``: a
#: quick real-scene run; ``paper``: the 2DGS/PATexGS iteration counts (the TrainConfig defaults).
PRESETS = {
    # tiny: no opacity reset (it costs more steps to recover than the run has). Its texture stage is
    # long enough for every stage to act: warm-up, Eq. 7, then growth every 15 steps up to 80% of the
    # stage (8 events, each followed by training) and 40 steps after the last.
    "tiny": dict(iters_2dgs=600, iters_tex=200, warmup_tex=40, growth_interval=15, growth_stop=0.8,
                 normal_from=300, sh_interval=150, log_every=50, checkpoint_every=200, max_gaussians=4_000,
                 densify=dens.DensifyConfig(start=100, stop=450, interval=50, opacity_reset_interval=10_000)),
    # cpu: real captures downsampled to about 200-400 px (beer at --factor 4: 175 x 312) on a 2-core
    # CPU in at most about 30 minutes a method, sized from measured step times (docs/tradeoffs.md):
    # 6,000 Gaussians, 1,000 + 400 steps, 11 growth events.
    "cpu": CPU_PRESET,
    "small": dict(iters_2dgs=7_000, iters_tex=5_000, warmup_tex=500, growth_interval=100, normal_from=3_500,
                  sh_interval=1_000, densify=dens.DensifyConfig(start=500, stop=3_500, interval=100,
                                                                opacity_reset_interval=3_000)),
    "paper": {},
}


#: Texture-stage fields that :func:`preset_config` scales with an ``iters_tex`` override.
TEXTURE_SCHEDULE_FIELDS = ("warmup_tex", "growth_interval")


def preset_config(preset: str = "paper", **overrides) -> TrainConfig:
    """A :class:`TrainConfig` from a named preset, with keyword overrides (None values ignored).

    An ``iters_tex`` override scales the preset's texture schedule with it: ``warmup_tex`` and
    ``growth_interval`` (unless given too) keep their share of the stage, so that the warm-up,
    the Eq. 7 allocation and the growth events all still happen (the paper preset's 1,000-step
    warm-up would otherwise outlast a 600-step texture stage). :class:`TrainConfig` refuses a
    schedule whose warm-up leaves no room for Eq. 7.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}.")
    kw = dict(PRESETS[preset])
    given = {k: v for k, v in overrides.items() if v is not None}
    if "iters_tex" in given:
        base = kw.get("iters_tex", TrainConfig.iters_tex)
        f = given["iters_tex"] / base
        for name in TEXTURE_SCHEDULE_FIELDS:
            if name not in given:
                given[name] = max(1, round(f * kw.get(name, getattr(TrainConfig, name))))
    kw.update(given)
    return TrainConfig(**kw)


def method_spec(method: str) -> dict:
    """What a ``--method`` name means: textures, size, mip flags and coverage mode
    (:class:`RenderConfig`: the ``patexgs`` family prefilters, the baselines and ``patexgs-literal``
    keep the 2DGS low-pass).

    ``textures``: None (2DGS); "fixed" (every Gaussian gets ``size`` x ``size`` textures when stage 2
    starts); "adaptive" (the warm-up textures, then at the allocation step the Eq. 7 sizes and
    Eqs. 8-10 growth, or, when ``size`` is set, ``size`` x ``size`` for every Gaussian and no growth:
    ``patexgs-fixed-N``, which differs from ``patexgs`` in the sizes only).
    """
    base = dict(textures="adaptive", size=None, mip="nearest", rgb_mip=True, alpha_mip=True, coverage="prefilter")
    if method == "2dgs":
        return dict(base, textures=None, mip="none", coverage="lowpass")
    if method.startswith("patexgs-fixed-"):
        n = method.rsplit("-", 1)[1]
        if not n.isdigit() or not 1 <= int(n) <= sched.DEFAULT_MAX_SIZE:
            raise ValueError(f"patexgs-fixed-N takes N in 1..{sched.DEFAULT_MAX_SIZE}, got {method!r}.")
        return dict(base, size=int(n))
    if method.startswith("textured-fixed-"):
        n = method.rsplit("-", 1)[1]
        if not n.isdigit() or int(n) not in FIXED_SIZES:
            raise ValueError(f"textured-fixed-N takes N in {FIXED_SIZES}, got {method!r}.")
        return dict(base, textures="fixed", size=int(n), mip="none", coverage="lowpass")
    variants = {"patexgs": {}, "patexgs-no-mip": dict(mip="none"),
                "patexgs-no-alpha-mip": dict(alpha_mip=False), "patexgs-no-rgb-mip": dict(rgb_mip=False),
                "patexgs-no-adaptive": dict(textures="fixed", size=8),
                "patexgs-trilinear": dict(mip="trilinear"),
                "patexgs-literal": dict(coverage="lowpass")}
    if method not in variants:
        raise ValueError(f"unknown method {method!r}; choose one of 2dgs, textured-fixed-N (N in "
                         f"{FIXED_SIZES}), patexgs-fixed-N (N in 1..{sched.DEFAULT_MAX_SIZE}), "
                         f"{', '.join(variants)}.")
    return dict(base, **variants[method])


# ------------------------------------------------------------------------------------------------
# Initialisation
# ------------------------------------------------------------------------------------------------
def init_scene(points, colors, config: TrainConfig, capacity: int | None = None) -> Scene:
    """2DGS initialisation from points (M, 3) and colours (M, 3) in [0, 1] (or None: grey).

    Scales: the mean distance to the 3 nearest neighbours (both axes); random rotations; opacity
    ``config.init_opacity``; SH DC from the colours, higher bands zero.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"need a non-empty (M, 3) point cloud to initialise from, got {points.shape}.")
    if config.max_gaussians is not None and len(points) > config.max_gaussians:
        keep = np.random.default_rng(config.seed).choice(len(points), config.max_gaussians, replace=False)
        points = points[np.sort(keep)]
        colors = None if colors is None else np.asarray(colors)[np.sort(keep)]
    n = len(points)
    k = min(4, n)
    d, _ = cKDTree(points).query(points, k=k)
    dist = np.sqrt(np.mean(np.square(d[:, 1:]), axis=1)) if k > 1 else np.ones(n)
    dist = np.maximum(dist, 1e-7)
    rng = np.random.default_rng(config.seed)
    quats = rng.normal(size=(n, 4))
    K = (config.sh_degree + 1) ** 2
    sh = np.zeros((n, K, 3))
    col = np.full((n, 3), 0.5) if colors is None else np.clip(np.asarray(colors, np.float64), 0, 1)
    sh[:, 0] = (col - 0.5) / 0.28209479177387814
    cap = capacity or 1 << max(n - 1, 1).bit_length()
    return Scene.from_arrays(points, np.repeat(dist[:, None], 2, axis=1), quats,
                             np.full(n, config.init_opacity), sh, capacity=cap)


# ------------------------------------------------------------------------------------------------
# The jitted step
# ------------------------------------------------------------------------------------------------
_GROUPS = ("means", "log_scales", "quats", "opacity_logits", "sh", "rgb", "alpha")


def _view_loss_and_grads(scene, camera, image, active_sh, w_normal, *, render_config, capacity, lambda_dssim,
                         lambda_dist, valid_hw=None):
    """One view's loss and gradients: ``((loss, (out, l1, mse)), (g_scene, g_offset))``, g_offset
    (C, 2) the gradient w.r.t. the renderer's ``screen_offset`` (densification statistics).

    ``camera`` and ``image`` (Hb, Wb, 3) may be padded to a size bucket (:mod:`patexgs_jax.buckets`);
    ``valid_hw`` ((2,) int, traced) is then the view's own (H, W): the loss is that of the top-left
    H x W block, so views of every size in one bucket share one compiled step."""
    chex.assert_shape(image, (camera.height, camera.width, 3), custom_message=(
        "the training image and its camera disagree; each view's image must be (H, W, 3) at its "
        "camera's size (a loader or a hand-made view gave another size)"))
    chex.assert_type(image, float, custom_message="training images are floating-point RGB in [0, 1]")
    offset = jnp.zeros((scene.capacity, 2), scene.means.dtype)
    valid = None if valid_hw is None else buckets.valid_mask(image.shape[:2], valid_hw)

    def loss_fn(sc, off):
        out = render_jit(sc, camera, config=render_config, capacity=capacity, screen_offset=off,
                         active_sh_degree=active_sh)
        photo, l1 = losses.photometric(out.rgb, image, lambda_dssim, valid=valid)
        loss = photo
        loss = loss + w_normal * losses.normal_consistency(out.normal, out.depth, out.alpha, camera.K, valid=valid)
        if lambda_dist > 0:
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


def _step(scene, opt_state, stats, camera, image, valid_hw, active_sh, w_normal, *, optimizer, render_config,
          capacity, lambda_dssim, lambda_dist):
    """One single-view update.

    Args:
      camera: the view's camera at its size bucket (``buckets.padded_camera`` with the exact tile
        grid: every per-splat output equals the unpadded render's).
      image: (Hb, Wb, 3) float32, the view's image zero-padded to the bucket.
      valid_hw: (2,) int32, the view's own (H, W).
      active_sh, w_normal: traced SH degree and normal-consistency weight.
    Returns:
      (scene, opt_state, stats, metrics); the update is skipped (state unchanged) on overflow or a
      non-finite loss or gradient.
    """
    STEP_TRACES[(render_config, capacity)] += 1
    (loss, (out, l1, mse)), (g_scene, g_off) = _view_loss_and_grads(
        scene, camera, image, active_sh, w_normal, render_config=render_config, capacity=capacity,
        lambda_dssim=lambda_dssim, lambda_dist=lambda_dist, valid_hw=valid_hw)
    finite = _finite_groups(g_scene)
    all_finite = jnp.isfinite(loss) & jnp.all(jnp.stack(list(finite.values())))
    ok = all_finite & ~out.overflow
    updates, new_opt = optimizer.update(g_scene, opt_state, scene)
    new_scene = optax.apply_updates(scene, updates)
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)  # noqa: E731
    new_stats = dens.accumulate(stats, jnp.where(ok, g_off, 0.0), out.visible & ok, out.radius_px,
                                valid_hw[1], valid_hw[0])
    metrics = dict(loss=loss, l1=l1, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-10)), ok=ok,
                   finite=finite, overflow=out.overflow, pairs_needed=out.pairs_needed,
                   max_tile_count=out.max_tile_count)
    return keep(new_scene, scene), keep(new_opt, opt_state), new_stats, metrics


def _batch_step(scene, opt_state, stats, cameras, images, active_sh, w_normal, *, mesh, optimizer,
                render_config, capacity, lambda_dssim, lambda_dist):
    """One update from a batch of B views (data-parallel over ``mesh``, see :mod:`.parallel`).

    Args:
      cameras: a Camera with K (B, 3, 3) and world_to_camera (B, 4, 4), one image size.
      images: (B, H, W, 3) float32.
      Everything else as :func:`_step`.
    Returns:
      As :func:`_step`. The loss is the mean of the B views' losses (so the gradient is the mean of
      their gradients: one Adam update), the densification statistics gain the B views one after
      another (each with its own screen-offset gradient, as B single-view steps would add them), and
      the update is skipped if any view overflowed or any gradient is non-finite; ``pairs_needed``
      and ``max_tile_count`` are the maxima over the batch, ``l1`` and ``psnr`` the means.
    """
    from . import parallel

    B = images.shape[0]
    STEP_TRACES[(render_config, capacity, B)] += 1

    def one_view(shared, view):
        sc, sh, wn = shared
        cam, img = view
        (loss, (out, l1, mse)), (g_scene, g_off) = _view_loss_and_grads(
            sc, cam, img, sh, wn, render_config=render_config, capacity=capacity, lambda_dssim=lambda_dssim,
            lambda_dist=lambda_dist)
        per = dict(loss=loss, l1=l1, mse=mse, g_off=g_off, visible=out.visible, radius_px=out.radius_px,
                   overflow=out.overflow, pairs_needed=out.pairs_needed, max_tile_count=out.max_tile_count)
        return g_scene, per

    g_sum, per = parallel.sum_over_views(one_view, mesh)((scene, active_sh, w_normal), (cameras, images))
    g_scene = jax.tree_util.tree_map(lambda g: g / B, g_sum)
    loss = jnp.mean(per["loss"])
    finite = _finite_groups(g_scene)
    all_finite = jnp.isfinite(loss) & jnp.all(jnp.stack(list(finite.values())))
    overflow = jnp.any(per["overflow"])
    ok = all_finite & ~overflow
    updates, new_opt = optimizer.update(g_scene, opt_state, scene)
    new_scene = optax.apply_updates(scene, updates)
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)  # noqa: E731
    new_stats = stats
    for b in range(B):
        new_stats = dens.accumulate(new_stats, jnp.where(ok, per["g_off"][b], 0.0), per["visible"][b] & ok,
                                    per["radius_px"][b], cameras.width, cameras.height)
    psnr = -10.0 * jnp.log10(jnp.maximum(per["mse"], 1e-10))
    metrics = dict(loss=loss, l1=jnp.mean(per["l1"]), psnr=jnp.mean(psnr), ok=ok, finite=finite,
                   overflow=overflow, pairs_needed=jnp.max(per["pairs_needed"]),
                   max_tile_count=jnp.max(per["max_tile_count"]))
    return keep(new_scene, scene), keep(new_opt, opt_state), new_stats, metrics


# ------------------------------------------------------------------------------------------------
# The run
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns: the trained scene and the summary written to ``summary.json``."""

    scene: Scene
    summary: dict
    out_dir: Path | None


class _Run:
    """The mutable host-side state of one run (everything a checkpoint holds)."""

    def __init__(self, dataset, config: TrainConfig, out_dir: Path | None, verbose: bool,
                 map_guard: compiled.MapGuard | None = None):
        self.ds, self.cfg, self.out, self.verbose = dataset, config, out_dir, verbose
        self.map_guard = map_guard if map_guard is not None else compiled.MapGuard()
        self.train_views = list(dataset.train_views)
        if not self.train_views:
            raise ValueError("the dataset has no training views.")
        self.radius = float(dataset.normalization.radius)
        self.spec = method_spec(config.method)
        self.render_cfgs = (config.render_config(stage=1), config.render_config(stage=2))
        # The position learning rate decays over the 2DGS stage for every method, so stage 1 is the
        # same run whatever the method (and can be shared: ``train(..., stage1=)``).
        self.lr = dataclasses.replace(config.lr, means_steps=config.iters_2dgs)
        self.optimizer = make_optimizer(self.radius, self.lr)
        self.capacity = None
        self.step = 0
        self.tex_state = None
        self.bad_streak = 0
        self.skipped = 0
        self.recompiles = 0
        self.t_train = 0.0
        self.texel_budget = None
        self.allocation = None
        self.growth_events = []  # one dict per Eq. 8-10 event that grew textures (summary.json)
        self.stage1_saved = False
        # With several processes (jax.distributed) only process 0 writes and prints progress.
        self.main = jax.process_index() == 0
        self.log_path = None if out_dir is None else out_dir / "log.jsonl"
        # The jitted steps of the current scene layout, per (render config, capacity), each with one
        # program per size bucket; released when the layout changes (see _compiled_step).
        self._jit_cache = {}
        self._jit_layout = None

    @property
    def render_cfg(self) -> RenderConfig:
        """The renderer's settings of the current stage (see :meth:`TrainConfig.render_config`)."""
        return self.render_cfgs[0 if self.step < self.cfg.iters_2dgs else 1]

    # -- state -----------------------------------------------------------------------------------
    def fresh(self):
        pts, cols = self.ds.points, self.ds.colors
        self.scene = init_scene(pts, cols, self.cfg)
        self.opt_state = self.optimizer.init(self.scene)
        self.stats = dens.DensifyStats.zeros(self.scene.capacity)

    def state_tree(self):
        return dict(scene=self.scene, opt_state=self.opt_state, stats=self.stats,
                    tex_sizes=None if self.tex_state is None else self.tex_state.sizes,
                    tex_counters=None if self.tex_state is None else np.array(
                        [self.tex_state.last_growth_step, self.tex_state.num_growth_events,
                         self.tex_state.num_grown]),
                    # None (refit before the next step) after a densification that grew the scene: 0.
                    capacity=np.array([0 if self.capacity is None else self.capacity.pairs]),
                    counters=np.array([self.step, self.skipped, self.recompiles]),
                    t_train=np.array(self.t_train), allocation=self.allocation,
                    growth_events=list(self.growth_events))

    def load_state(self, tree):
        self.scene, self.stats = tree["scene"], tree["stats"]
        self.opt_state = upgrade_state(tree["opt_state"])
        if tree["tex_sizes"] is not None:
            c = tree["tex_counters"]
            self.tex_state = sched.TextureScheduleState(np.asarray(tree["tex_sizes"]), int(c[0]), int(c[1]), int(c[2]))
        self.capacity = Capacity(int(tree["capacity"][0])) if int(tree["capacity"][0]) > 0 else None
        self.step, self.skipped, self.recompiles = (int(v) for v in tree["counters"])
        self.t_train = float(tree["t_train"])
        self.allocation = tree.get("allocation")
        self.growth_events = list(tree.get("growth_events") or [])

    def save(self):
        """Writes a checkpoint (process 0); with several processes, first checks that every process
        holds the same state (the replicated state must never diverge), then waits until it is written."""
        from . import parallel

        if self.out is None:
            return
        tree = self.state_tree()
        several = jax.process_count() > 1
        if several:
            same = {k: v for k, v in tree.items() if k != "t_train"}  # (wall-clock time differs between processes)
            parallel.check_same(f"the training state at step {self.step} (a checksum of every array; the host-side "
                                "work must give the same result on every process)",
                                [self.step, parallel.tree_checksum(same)])
        if self.main:
            path = ckpt.checkpoint_path(self.out / "checkpoints", self.step)
            ckpt.save_checkpoint(path, tree, dict(config=_config_dict(self.cfg), step=self.step), keep=2)
        if several:  # the others wait until it is written (a study reads it next)
            parallel.check_same(f"the checkpoint of step {self.step} being written", [self.step])

    def save_stage1(self):
        """At the end of the 2DGS stage of a run that goes on: a checkpoint (a restart point) and a
        copy kept in ``checkpoints/stage1/`` (out of the rotation), from which other methods can
        start (:func:`stage1_checkpoint`)."""
        self.stage1_saved = True
        if self.out is None or self.step >= self.cfg.total_steps:
            return
        self.save()
        if self.main:
            meta = dict(config=_config_dict(self.cfg), step=self.step)
            ckpt.save_checkpoint(ckpt.checkpoint_path(self.out / "checkpoints" / STAGE1_DIR, self.step),
                                 self.state_tree(), meta, keep=1)

    # -- helpers ---------------------------------------------------------------------------------
    def view(self, step):
        n = len(self.train_views)
        epoch, i = divmod(step, n)
        perm = np.random.default_rng([self.cfg.seed, epoch]).permutation(n)
        return self.train_views[perm[i]]

    def _compiled_step(self, key, make):
        """The jitted step for ``key`` (render config, capacity, ...) and the scene's current layout,
        made by ``make()`` when new. Scene layouts only grow within a run (more Gaussians, larger
        texture buckets), so when the layout changes the steps of the old one are never called
        again: they are dropped, with the renderer's and pair counter's programs of the old layout,
        and their memory mappings returned (see :mod:`patexgs_jax.compiled`). Within a layout at most
        :data:`_MAX_STEP_FNS` steps (capacities) are kept, the oldest dropped first."""
        layout = _layout(self.scene)
        if self._jit_layout != layout:
            if self._jit_cache:
                self._jit_cache.clear()
                buckets.release_scene_programs()
            self._jit_layout = layout
        if key not in self._jit_cache:
            while len(self._jit_cache) >= _MAX_STEP_FNS:
                self._jit_cache.pop(next(iter(self._jit_cache)))
            self._jit_cache[key] = make()
        return self._jit_cache[key]

    def step_fn(self):
        """The training step as ``fn(scene, opt_state, stats, camera, image, active_sh, w_normal)``
        (``image`` (H, W, 3) of the camera's size). The view is padded to its size bucket (the
        renderer's exact tile grid) on the host, so the views of one bucket share a program."""
        if self.cfg.batch_size > 1:
            return self._batch_step_fn()
        cfg, render_cfg, capacity = self.cfg, self.render_cfg, self.capacity
        fn = self._compiled_step((render_cfg, capacity), lambda: jax.jit(
            lambda sc, st, stats, cam, img, hw, sh, wn: _step(
                sc, st, stats, cam, img, hw, sh, wn, optimizer=self.optimizer, render_config=render_cfg,
                capacity=capacity, lambda_dssim=cfg.lambda_dssim, lambda_dist=cfg.lambda_dist),
            donate_argnums=(0, 1, 2)))

        def step(scene, opt_state, stats, camera, image, active_sh, w_normal):
            cam = buckets.padded_camera(camera, render_cfg.tile_size)
            img = buckets.pad_image(image, cam.height, cam.width)
            hw = np.array([camera.height, camera.width], np.int32)
            return fn(scene, opt_state, stats, cam, img, hw, active_sh, w_normal)

        return step

    def data_mesh(self):
        """The device mesh of the data-parallel step (``batch_size`` > 1), built once per run."""
        from . import parallel

        if getattr(self, "_mesh", None) is None:
            self._mesh = parallel.data_mesh(parallel.num_batch_devices(self.cfg.batch_size, self.cfg.devices))
        return self._mesh

    def _batch_step_fn(self):
        from . import parallel

        mesh, render_cfg, capacity, cfg = self.data_mesh(), self.render_cfg, self.capacity, self.cfg
        fn = self._compiled_step((render_cfg, capacity, cfg.batch_size), lambda: jax.jit(
            lambda sc, st, stats, cams, imgs, sh, wn: _batch_step(
                sc, st, stats, cams, imgs, sh, wn, mesh=mesh, optimizer=self.optimizer,
                render_config=render_cfg, capacity=capacity, lambda_dssim=cfg.lambda_dssim,
                lambda_dist=cfg.lambda_dist),
            out_shardings=parallel.replicated(mesh), donate_argnums=(0, 1, 2)))
        if jax.process_count() == 1:
            return fn

        def step(scene, opt_state, stats, cams, imgs, active_sh, w_normal):
            # Each process passes (and gets back) its own copy of the replicated state: see parallel.to_global.
            sc, st, stats, sh, wn = parallel.to_global((scene, opt_state, stats, active_sh, w_normal), mesh)
            try:
                out = jax.block_until_ready(fn(sc, st, stats, cams, imgs, sh, wn))
            except Exception as e:  # a failed all-reduce surfaces here as XLA's runtime error
                raise parallel.lost_process(f"the training step {self.step}", e) from e
            return parallel.to_local(out, mesh)

        return step

    def batch_share(self) -> range:
        """Positions in each batch of the views this process loads (all of them with one process)."""
        from . import parallel

        return range(self.cfg.batch_size)[parallel.process_slice(self.cfg.batch_size, self.data_mesh())]

    def batch_inputs(self, views, images):
        """Stacked cameras and (B, H, W, 3) images placed over the mesh, the state replicated on it.
        ``images``: the batch's images; only those at :meth:`batch_share` are read (with several
        processes the others are not loaded and may be None)."""
        from . import parallel

        mesh = self.data_mesh()
        self.scene, self.opt_state, self.stats = parallel.replicate((self.scene, self.opt_state, self.stats),
                                                                    parallel.local_mesh(mesh))
        share = self.batch_share()
        cams = parallel.stack_cameras([views[j].camera for j in share])
        return parallel.shard_batch((cams, np.stack([np.asarray(images[j], np.float32) for j in share])), mesh)

    def fit_capacity(self, camera):
        # Counted at the step's size bucket (the same tile grid: the same count), one program a bucket.
        camera = camera if self.cfg.batch_size > 1 else buckets.padded_camera(camera, self.render_cfg.tile_size)
        needed, _ = count_pairs(self.scene, camera, self.render_cfg)
        cap = Capacity.fit(float(needed) * 1.25, minimum=self.capacity)
        if cap != self.capacity:
            self.capacity = cap

    def log(self, record):
        if self.log_path is not None and self.main:
            with open(self.log_path, "a") as f:
                f.write(json.dumps(record) + "\n")

    def say(self, msg):
        if self.verbose and self.main:
            progress.say(msg)

    # -- stage transitions -----------------------------------------------------------------------
    def start_textures(self):
        spec = self.spec
        C = self.scene.capacity
        act = np.asarray(self.scene.active) > 0
        if spec["textures"] == "fixed":
            n = spec["size"]
            sizes = np.where(act, n, 0)
            self.scene, self.opt_state, _ = sched.add_textures(self.scene, self.opt_state, self.optimizer,
                                                               sizes, sizes)
            self.say(f"[stage 2] every Gaussian gets a {n}x{n} RGBA texture")
        else:
            self.scene, self.opt_state, _ = sched.add_textures(
                self.scene, self.opt_state, self.optimizer, np.where(act, 1, 0), np.where(act, 5, 0))
            self.say("[stage 2] 5x5 alpha + 1x1 RGB textures; warm-up "
                     f"{self.cfg.warmup_tex} steps")
        self.stats = dens.DensifyStats.zeros(C)

    def allocate_textures(self):
        """Eq. 6-7: contribution counts over all training views -> initial sizes."""
        counts = []
        with buckets.ViewRenderer(self.scene, self.render_cfg) as renderer:
            renderer.prepare([v.camera for v in self.train_views])
            for v in self.train_views:
                counts.append(np.asarray(renderer(v.camera).max_contrib_count))
        S = np.stack(counts)
        act = np.asarray(self.scene.active) > 0
        budget = None
        if self.spec["size"] is not None:  # patexgs-fixed-N: the same schedule with one size for all
            sigma = None
            sides = np.where(act, self.spec["size"], 0).astype(np.int64)
        else:
            if self.cfg.texture_budget_mb is not None:
                budget = sched.mb_to_texels(self.cfg.texture_budget_mb)
                # Eq. 7 spends its share (at least one texel a Gaussian), growth the rest.
                target = max(int(round(self.cfg.budget_eq7_share * budget)), int(act.sum()))
                sigma = sched.solve_sigma_for_budget(S, target, max_size=self.cfg.max_texture_size, active=act)
            else:
                pixels = sum(v.camera.height * v.camera.width for v in self.train_views)
                sigma = self.cfg.sigma or sched.pixel_share_sigma(pixels, int(act.sum()))
            sides = sched.initial_texture_sizes(S, sigma, max_size=self.cfg.max_texture_size, active=act)
        self.tex_state = sched.TextureScheduleState.create(sides)
        self.scene, self.opt_state, info = sched.resize_textures(self.scene, self.opt_state, sides, sides)
        self.texel_budget = budget
        self.allocation = dict(step=self.step, sigma=None if sigma is None else float(sigma),
                               texels=int(np.sum(sides[act] ** 2)), budget_texels=budget,
                               sides=_side_histogram(sides, act))
        self.log(dict(event="allocation", **self.allocation))
        n = self.spec["size"]
        how = f"{n}x{n} for every Gaussian" if sigma is None else f"Eq. 7, sigma {sigma:.4g}"
        self.say(f"[stage 2] allocation ({how}): sides {np.bincount(sides[act]).nonzero()[0].tolist()}, "
                 f"{int(np.sum(sides[act] ** 2))} RGBA texels")
        self.stats = dens.DensifyStats.zeros(self.scene.capacity)

    def growth_schedule(self):
        return growth_schedule(self.cfg)

    def check_memory_maps(self):
        """Releases compiled code near the memory-map cap; at the guard's stop share even so, saves a
        checkpoint and raises :class:`compiled.MapLimitReached` (a clear stop, not a crash in XLA)."""
        from . import parallel

        maps = self.map_guard.check(on_release=self._jit_cache.clear)
        other = None
        if jax.process_count() > 1:  # the processes stop together: the checkpoint below is collective
            hit = parallel.process_allgather_ints([maps is not None])[:, 0]
            other = None if not hit.any() else int(np.argmax(hit))
        if maps is None and other is None:
            return
        if self.out is None:
            what = f"Training stopped at step {self.step}; no output directory was given, so nothing was saved."
        elif self.bad_streak == 0:
            self.save()
            what = (f"Training stopped at step {self.step} and saved a checkpoint in {self.out / 'checkpoints'}; "
                    "continue in a new process with `python -m patexgs_jax.train ... --resume` "
                    "(train(..., resume=True); a study continues where it stopped when run again).")
        else:
            what = (f"Training stopped at step {self.step}, during non-finite steps: the last good checkpoint in "
                    f"{self.out / 'checkpoints'} is kept; continue from it with --resume (train(..., resume=True)).")
        if maps is None:
            raise compiled.MapLimitReached(f"process {other} of this run neared its memory-map cap, so every process "
                                           f"stops. {what}")
        raise compiled.MapLimitReached(compiled.limit_message(maps[0], maps[1], what))

    # -- main loop -------------------------------------------------------------------------------
    def run(self):
        bar = progress.bar(self.cfg.total_steps, f"train {self.cfg.method}", initial=self.step,
                           show=self.verbose and self.main)
        try:
            self._run(bar)
        finally:
            bar.close()

    def _run(self, bar):
        cfg = self.cfg
        total = cfg.total_steps
        t_last = time.perf_counter()
        window = collections.deque(maxlen=max(1, cfg.log_every))
        compiled_last = True
        while self.step < total:
            step = self.step
            # Mappings grow only when something compiles (a new bucket, capacity or layout); reading
            # /proc/self/maps costs milliseconds, so look after compiles and every few steps.
            if compiled_last or step % _MAP_CHECK_EVERY == 0:
                self.check_memory_maps()
            compiled_last = False
            if step == cfg.iters_2dgs and self.scene.rgb is None and not self.stage1_saved:
                self.save_stage1()
            if self.spec["textures"] is not None and step == cfg.iters_2dgs and self.scene.rgb is None:
                self.start_textures()
            if (self.spec["textures"] == "adaptive" and self.tex_state is None
                    and step == cfg.iters_2dgs + cfg.warmup_tex):
                self.allocate_textures()
            # Step s takes views s B .. s B + B - 1 of the stream of per-epoch permutations.
            views = [self.view(step * cfg.batch_size + j) for j in range(cfg.batch_size)]
            # Each process loads only its share of the batch (all of it with one process); the
            # cameras, known to every process, are checked everywhere.
            share = self.batch_share() if cfg.batch_size > 1 else range(1)
            images = [views[j].image if j in share else None for j in range(len(views))]
            problems = [_camera_problem(v.camera) for v in views]
            for j in share:
                problems[j] = problems[j] or _image_problem(images[j])
                if problems[j] is not None and jax.process_count() > 1:
                    # The other processes cannot see this image: it goes into the step as NaNs, which
                    # makes the step skip its update on every process.
                    print(f"[step {step}, process {jax.process_index()}] view {views[j].name!r}: {problems[j]}; "
                          "the update is skipped", flush=True)
                    images[j], problems[j] = np.full((views[j].camera.height, views[j].camera.width, 3), np.nan,
                                                     np.float32), None
            bad_view = next((i for i, p in enumerate(problems) if p is not None), 0)
            view, image, problem = views[bad_view], images[bad_view], problems[bad_view]
            if problem is None:
                if self.capacity is None:
                    for v in views:
                        self.fit_capacity(v.camera)
                fn = self.step_fn()
                t0 = time.perf_counter()
                traces = sum(STEP_TRACES.values())
                active_sh = jnp.int32(min(step // cfg.sh_interval, cfg.sh_degree))
                w_normal = jnp.float32(cfg.lambda_normal if step >= cfg.normal_from else 0.0)
                data = ((view.camera, image) if cfg.batch_size == 1
                        else self.batch_inputs(views, images))
                scene, opt_state, stats, m = fn(self.scene, self.opt_state, self.stats, *data, active_sh, w_normal)
                self.scene, self.opt_state, self.stats = scene, opt_state, stats
                if sum(STEP_TRACES.values()) > traces:
                    self.recompiles += 1
                    compiled_last = True
                if bool(m["overflow"]) and np.isfinite(float(m["pairs_needed"])):
                    old = self.capacity
                    self.capacity = Capacity.fit(float(m["pairs_needed"]) * 1.25,
                                                 minimum=old)
                    self.say(f"[step {step}] tile capacity {old} overflowed; growing to {self.capacity} and retrying")
                    continue
                if not bool(m["ok"]):
                    bad = [k for k, v in m["finite"].items() if not bool(v)]
                    problem = f"non-finite loss or gradient (groups: {bad or ['loss']})"
            if problem is not None:
                # Skipped (never applied); the step still counts, and its scheduled host-side work,
                # log line and checkpoint happen as usual.
                self.bad_streak += 1
                self.skipped += 1
                self.say(f"[step {step}] view {view.name!r}: {problem}; update skipped")
                if self.bad_streak >= cfg.max_bad_steps:
                    raise FloatingPointError(
                        f"{self.bad_streak} consecutive non-finite steps up to step {step}; stopping. "
                        "The last good checkpoint is kept in the output directory.")
            else:
                self.bad_streak = 0
                self.t_train += time.perf_counter() - t0
                window.append((float(m["loss"]), float(m["psnr"])))
            self.step += 1
            bar.update(1)
            self.after_step(step + 1)
            if self.step % cfg.log_every == 0 or self.step == total:
                now = time.perf_counter()
                mean = lambda k: float(np.mean([w[k] for w in window])) if window else float("nan")  # noqa: E731
                rec = dict(step=self.step, loss=mean(0), psnr=mean(1), gaussians=self.scene.num_active(),
                           texels=sum(self.scene.texel_count().values()),
                           ms_per_step=1e3 * (now - t_last) / cfg.log_every, recompiles=self.recompiles,
                           skipped=self.skipped)
                t_last = now
                window.clear()
                self.log(rec)
                bar.set_postfix(psnr=f"{rec['psnr']:.2f}", gaussians=rec["gaussians"], refresh=False)
                self.say(f"step {rec['step']:6d}/{total}  loss {rec['loss']:.4f}  psnr {rec['psnr']:6.2f}  "
                         f"gaussians {rec['gaussians']:7d}  texels {rec['texels']:8d}  "
                         f"{rec['ms_per_step']:7.1f} ms/step")
            if (self.step % cfg.checkpoint_every == 0 or self.step == total) and self.bad_streak == 0:
                self.save()  # (not during a non-finite streak: the last good checkpoint stays the newest)

    def after_step(self, step):
        """Host-side work between steps (``step`` counts completed steps, from 1)."""
        cfg, dc = self.cfg, self.cfg.densify
        if step <= cfg.iters_2dgs:
            dcfg = dataclasses.replace(dc, max_gaussians=cfg.max_gaussians)
            if dcfg.densify_at(step) and step < cfg.iters_2dgs:
                self.scene, self.opt_state, self.stats, info = dens.densify_and_prune(
                    self.scene, self.opt_state, self.stats, dcfg, self.radius,
                    np.random.default_rng([cfg.seed, step]), prune_large=dcfg.prune_large(step))
                if info.shapes_changed:
                    self.capacity = None
            if dcfg.reset_opacity_at(step) and step < cfg.iters_2dgs:
                self.scene, self.opt_state = dens.reset_opacity(self.scene, self.opt_state,
                                                                dcfg.opacity_reset_value)
            if self.capacity is not None and step % 100 == 0:
                self.fit_capacity(self.view(step).camera)
            return
        if self.tex_state is not None and self.spec["size"] is None:
            schedule = self.growth_schedule()
            if schedule.is_growth_step(step):
                grad = self.stats.mean_grad()
                act = np.asarray(self.scene.active) > 0
                before = self.tex_state.sides(self.cfg.max_texture_size)
                new_state, sides, sel = self.tex_state.step(grad, step, schedule, active=act,
                                                            texel_budget=self.texel_budget)
                self.tex_state = new_state
                if sel.any():
                    self.scene, self.opt_state, info = sched.resize_textures(self.scene, self.opt_state, sides, sides)
                    event = dict(step=step, grown=int(np.sum(sides[act] > before[act])),
                                 texels_added=int(np.sum(sides[act] ** 2) - np.sum(before[act] ** 2)),
                                 texels=int(np.sum(sides[act] ** 2)))
                    self.growth_events.append(event)
                    self.log(dict(event="growth", **event))
                    self.say(f"[stage 2] Eq. 8-10 growth at step {step}: {event['grown']} Gaussians grew, "
                             f"+{event['texels_added']} RGBA texels ({event['texels']} in all)")
                self.stats = dens.DensifyStats.zeros(self.scene.capacity)


def growth_schedule(cfg: TrainConfig) -> sched.GrowthSchedule:
    """The Eqs. 8-10 schedule of a run: growth every ``growth_interval`` steps from one interval after
    the Eq. 7 allocation (step ``iters_2dgs + warmup_tex``) up to ``growth_stop`` of the texture stage."""
    t0 = cfg.iters_2dgs + cfg.warmup_tex + cfg.growth_interval
    t_final = max(t0 + 1, cfg.iters_2dgs + int(cfg.growth_stop * cfg.iters_tex))
    return sched.GrowthSchedule(t0=t0, t_final=t_final, interval=cfg.growth_interval, tau_preset=cfg.tau_preset,
                                max_size=cfg.max_texture_size)


def growth_steps(cfg: TrainConfig) -> list[int]:
    """The steps (completed steps, as :meth:`_Run.after_step` counts them) at which growth events run."""
    if method_spec(cfg.method)["textures"] != "adaptive" or method_spec(cfg.method)["size"] is not None:
        return []
    g = growth_schedule(cfg)
    return [t for t in range(g.t0, min(g.t_final, cfg.total_steps) + 1) if g.is_growth_step(t)]


#: Fields that only matter after the 2DGS stage: runs that agree on every other field have the same
#: stage 1, which :func:`train` can take from another run's end-of-stage-1 checkpoint.
STAGE2_FIELDS = frozenset({"method", "iters_tex", "continue_2dgs", "warmup_tex", "growth_interval", "growth_stop", "tau_preset",
                           "sigma", "texture_budget_mb", "budget_eq7_share", "max_texture_size", "lambda_mip",
                           "checkpoint_every", "log_every", "max_bad_steps"})


#: Fields that change how a run executes, not what it computes: a run may resume (or take its stage 1
#: from a run) with other values of these.
RUNTIME_FIELDS = frozenset({"devices", "checkpoint_every", "log_every"})


def _side_histogram(sides, active) -> dict:
    """``{side: number of active Gaussians with that texture side}`` (str keys, as JSON writes them)."""
    values, counts = np.unique(np.asarray(sides)[np.asarray(active)].astype(int), return_counts=True)
    return {str(int(v)): int(c) for v, c in zip(values, counts)}


def _comparable(saved: dict) -> dict:
    """A saved config as compared on resume: fields added since it was written take their defaults
    (which reproduce the older behaviour), and :data:`RUNTIME_FIELDS` are left out."""
    full = {**_config_dict(TrainConfig()), **saved}
    return {k: v for k, v in full.items() if k not in RUNTIME_FIELDS}


def _stage1_part(saved: dict) -> dict:
    """The part of a saved config that determines stage 1."""
    return {k: v for k, v in _comparable(saved).items() if k not in STAGE2_FIELDS}


def stage1_key(cfg: TrainConfig) -> dict:
    """The part of a config that determines stage 1 (JSON-able; equal keys, equal 2DGS stages)."""
    return _stage1_part(_config_dict(cfg))


def stage1_checkpoint(run_dir, config: TrainConfig) -> Path | None:
    """The end-of-2DGS-stage checkpoint of the run in ``run_dir`` usable by ``config``, or None: the
    run's final checkpoint if it ended there, else the copy kept in ``checkpoints/stage1/``."""
    directory = Path(run_dir) / "checkpoints"
    paths = list(reversed(ckpt.list_checkpoints(directory))) + list(reversed(ckpt.list_checkpoints(
        directory / STAGE1_DIR)))
    for path in paths:
        try:
            meta = ckpt.read_metadata(path)
        except ckpt.CheckpointError:
            continue
        cfg = meta.get("config") or {}
        if meta.get("step") == config.iters_2dgs and _stage1_part(cfg) == stage1_key(config):
            return path
    return None


def _config_dict(cfg: TrainConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))


def _image_problem(image) -> str | None:
    """Why an image cannot be trained on (empty or non-finite), or None."""
    if image is None or np.size(image) == 0 or not np.all(np.isfinite(image)):
        return "image is empty or not finite"
    return None


def _camera_problem(camera) -> str | None:
    """Why a camera cannot be trained on (non-finite), or None."""
    if not (np.all(np.isfinite(np.asarray(camera.K))) and np.all(np.isfinite(np.asarray(camera.world_to_camera)))):
        return "camera is not finite"
    return None


def _view_problem(camera, image) -> str | None:
    """Why a view cannot be used (empty or non-finite image, non-finite camera), or None."""
    return _image_problem(image) or _camera_problem(camera)


def evaluate(scene: Scene, views, render_config: RenderConfig) -> dict:
    """Mean PSNR and SSIM over views, renders clipped to [0, 1]. Views are rendered at their size
    buckets (:class:`patexgs_jax.buckets.ViewRenderer`: a few programs, released at the end)."""
    from .metrics import psnr, ssim

    ps, ss = [], []
    # as in training: empty or non-finite images and cameras are left out
    views = [v for v in views if _view_problem(v.camera, v.image) is None]
    with buckets.ViewRenderer(scene, render_config) as renderer:
        renderer.prepare([v.camera for v in views])
        for v in views:
            img = renderer.image(v.camera)
            ps.append(float(psnr(img, v.image)))
            ss.append(float(ssim(jnp.asarray(img), jnp.asarray(v.image))))
            # SSIM compiles per image size and cannot be padded: bound what it keeps
            compiled.trim_programs(ssim)
    return dict(psnr=float(np.mean(ps)) if ps else None, ssim=float(np.mean(ss)) if ss else None)


def train(dataset, config: TrainConfig = TrainConfig(), out_dir=None, *, resume: bool = False,
          verbose: bool = True, stage1=None, map_guard: compiled.MapGuard | None = None,
          evaluate_everywhere: bool = False, end_distributed: bool = False,
          check_memory: bool = True) -> TrainResult:
    """Trains ``config.method`` on ``dataset`` (see :func:`patexgs_jax.data.load`).

    Args:
      dataset: a loaded dataset (train/test views, points).
      config: :class:`TrainConfig`.
      out_dir: where checkpoints, ``log.jsonl``, ``scene.ply`` (+ texture sidecar) and
        ``summary.json`` go; None keeps everything in memory.
      resume: continue from the newest complete checkpoint in ``out_dir`` if there is one.
      verbose: print progress.
      stage1: start from the end of another run's 2DGS stage instead of training it again: a
        checkpoint file written at step ``config.iters_2dgs`` by a run whose config agrees with
        ``config`` outside :data:`STAGE2_FIELDS` (see :func:`stage1_checkpoint`). The stage-1
        training time is carried over into ``train_seconds``. Ignored when resuming.
      map_guard: when the process nears the kernel's memory-map cap, compiled code is released and,
        if that is not enough, the run checkpoints and raises :class:`compiled.MapLimitReached`
        (default ``compiled.MapGuard()``: release at half the cap, stop at 90%).
      evaluate_everywhere, end_distributed: with several processes (``jax.distributed``, see
        :mod:`patexgs_jax.parallel`) every process trains and process 0 alone writes the outputs
        and, by default, evaluates (the others' summaries have None metrics). With
        ``evaluate_everywhere`` every process evaluates (the processes stay in step for what
        follows); with ``end_distributed`` ``jax.distributed`` is shut down once training is done,
        so the other processes can exit while process 0 evaluates and writes (the command line's
        choice; nothing cross-process can follow).
      check_memory: before the first step, compare the step's estimated memory with the memory
        available (:func:`patexgs_jax.memory.check_training_memory`; CPU backend only).
    Returns:
      :class:`TrainResult`.
    Raises:
      compiled.MapLimitReached: near the memory-map cap (the message says how to resume).
      parallel.DistributedError: with several processes, they do not start from the same state, or
        one of them stopped (the message says what to do).
      memory.NotEnoughMemory: the step would not fit in memory (the message names a factor that fits).
    """
    # Runs build their own jitted steps: in a process that trains many runs, free the compiled code of
    # earlier ones before the kernel's memory-map cap is near (see patexgs_jax.compiled).
    from . import parallel

    compiled.release_compiled_code()
    if jax.process_count() > 1:  # the batch must split evenly over every process's devices
        parallel.num_batch_devices(config.batch_size, config.devices)
    out = None if out_dir is None else Path(out_dir)
    main = parallel.is_main_process()
    if out is not None and main:
        ckpt.check_writable(out)
        ckpt.check_writable(out / "checkpoints")
    run = _Run(dataset, config, out, verbose, map_guard)
    latest = ckpt.latest_checkpoint(out / "checkpoints") if (out is not None and resume) else None
    if latest is not None:
        tree, meta = ckpt.load_checkpoint(latest)
        saved, wanted = _comparable(meta.get("config") or {}), _comparable(_config_dict(config))
        if saved != wanted:
            differ = sorted(k for k in wanted if saved.get(k) != wanted[k])
            raise ValueError(f"checkpoint {latest} was written with a different configuration ({', '.join(differ)} "
                             "differ); resume with the same settings or choose a new output directory.")
        run.load_state(tree)
        if run.tex_state is not None:
            run.texel_budget = (sched.mb_to_texels(config.texture_budget_mb)
                                if config.texture_budget_mb is not None else None)
        run.say(f"resuming from {latest} at step {run.step}")
    else:
        if out is not None and not resume and ckpt.latest_checkpoint(out / "checkpoints") is not None:
            raise FileExistsError(f"{out} already holds checkpoints; pass resume=True (--resume) to continue "
                                  "that run, or choose another output directory.")
        if stage1 is not None:
            _load_stage1(run, Path(stage1), config)
        else:
            run.fresh()
    if out is not None and main:  # fail now if checkpoints cannot fit (two kept + one being written), not hours later
        ckpt.check_writable(out / "checkpoints", required_bytes=3 * sum(
            np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(run.state_tree())))
    if jax.process_count() > 1:  # every process starts from the same state (data; checkpoint when resuming)
        parallel.check_same("the starting state (step and a checksum of the scene); every process needs the same "
                            "--data and, to resume, must see process 0's --out folder (a shared filesystem)",
                            [run.step, parallel.tree_checksum(run.scene)])
    if check_memory:  # a clear stop now rather than the kernel's OOM kill mid-step
        from . import memory

        memory.check_training_memory(dataset, gaussians=max(run.scene.capacity, config.max_gaussians or 0),
                                     textured=run.spec["textures"] is not None)
    run.run()
    scene = run.scene
    texels = scene.texel_count()
    summary = dict(method=config.method, steps=run.step, train_seconds=run.t_train,
                   num_gaussians=scene.num_active(), texels=texels["rgb"] + texels["alpha"],
                   texels_rgb=texels["rgb"], texels_alpha=texels["alpha"],
                   storage_mb=storage_mb(scene.num_active(), int(scene.sh.shape[1]), texels["rgb"], texels["alpha"]),
                   recompiles=run.recompiles, skipped_steps=run.skipped, allocation=run.allocation,
                   growth_events=run.growth_events,
                   sides_final=None if scene.rgb is None else _side_histogram(
                       np.asarray(scene.rgb.size), np.asarray(scene.active) > 0),
                   stage1_from=None if stage1 is None else str(stage1))
    if end_distributed and jax.process_count() > 1:
        jax.distributed.shutdown()  # the processes are done with each other (every one calls this)
    if main or evaluate_everywhere:
        train_eval = evaluate(scene, run.train_views[:32], run.render_cfg)
        test_eval = evaluate(scene, list(dataset.test_views), run.render_cfg)
    else:  # evaluation and outputs are process 0's
        train_eval = test_eval = dict(psnr=None, ssim=None)
    summary.update(train_psnr=train_eval["psnr"], test_psnr=test_eval["psnr"], test_ssim=test_eval["ssim"],
                   config=_config_dict(config))
    if out is not None and main:
        from .export import export_ply

        export_ply(scene, out / "scene.ply")
        tmp = out / "summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=1))
        tmp.replace(out / "summary.json")
    if verbose and main:
        print(f"done: train PSNR {summary['train_psnr']:.2f}, test PSNR "
              f"{summary['test_psnr'] if summary['test_psnr'] is None else round(summary['test_psnr'], 2)}, "
              f"{summary['num_gaussians']} Gaussians, {summary['texels']} texels, "
              f"{summary['storage_mb']:.2f} MB, {summary['train_seconds']:.0f} s", flush=True)
    return TrainResult(scene=scene, summary=summary, out_dir=out)


def _load_stage1(run: _Run, path: Path, config: TrainConfig) -> None:
    meta = ckpt.read_metadata(path)
    cfg = _stage1_part(meta.get("config") or {})
    want = stage1_key(config)
    if cfg != want:
        diff = sorted(k for k in set(cfg) | set(want) if cfg.get(k) != want.get(k))
        raise ValueError(f"stage-1 checkpoint {path} was trained with different 2DGS-stage settings "
                         f"({', '.join(diff)}); train stage 1 again or pass a matching checkpoint.")
    if meta.get("step") != config.iters_2dgs:
        raise ValueError(f"stage-1 checkpoint {path} is at step {meta.get('step')}, not at the end of the "
                         f"2DGS stage (step {config.iters_2dgs}).")
    tree, _ = ckpt.load_checkpoint(path)
    run.load_state(tree)
    run.capacity = None  # refit for this method's render configuration
    run.say(f"stage 1 from {path} ({run.t_train:.0f} s of 2DGS training)")


def main(argv=None) -> int:
    from . import parallel

    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="scene folder (COLMAP, LLFF or transforms.json); "
                    "default: the embedded synthetic scene")
    ap.add_argument("--method", default="patexgs")
    ap.add_argument("--out", required=True)
    ap.add_argument("--factor", type=int, default=None, help="image downsampling (default: the Mip-NeRF 360 "
                    "factors for those scenes, else images wider than 1600 px resized to 1600 wide; 1: full size)")
    ap.add_argument("--preset", default="paper", choices=sorted(PRESETS),
                    help="iteration schedule (default: paper); --iters-* override it")
    ap.add_argument("--iters-2dgs", type=int, default=None)
    ap.add_argument("--iters-tex", type=int, default=None,
                    help="texture-stage steps; the preset's warm-up and growth interval scale with it")
    ap.add_argument("--max-gaussians", type=int, default=None)
    ap.add_argument("--texture-budget-mb", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint-every", type=int, default=None, help="steps between checkpoints (default: the "
                    "preset's; one is always written at the end)")
    ap.add_argument("--log-every", type=int, default=None, help="steps between progress lines and log.jsonl "
                    "records (default: the preset's)")
    ap.add_argument("--batch-size", type=int, default=None,
                    help="views per step (default 1); > 1 trains data-parallel (see patexgs_jax.parallel)")
    ap.add_argument("--devices", type=int, default=None,
                    help="devices the batch is split over (must divide --batch-size; default: as many as "
                         "divide it); on CPU this many CPU devices are created")
    ap.add_argument("--resume", action="store_true")
    parallel.add_cli_arguments(ap)
    return parallel.run_cli(ap.parse_args(argv), _train_cli)


def _train_cli(args) -> int:
    from . import parallel
    from .data import load

    try:
        if args.data is None:
            from .data.synthetic import ensure_default_scene

            args.data = str(ensure_default_scene())
        if jax.process_index() == 0:  # the process that writes; before the data is loaded
            ckpt.check_output_dir(args.out)
        cfg = preset_config(args.preset, method=args.method, iters_2dgs=args.iters_2dgs,
                            iters_tex=args.iters_tex, max_gaussians=args.max_gaussians,
                            texture_budget_mb=args.texture_budget_mb, seed=args.seed,
                            checkpoint_every=args.checkpoint_every, log_every=args.log_every,
                            batch_size=args.batch_size, devices=args.devices)
        ds = load(args.data, factor=args.factor)
        train(ds, cfg, args.out, resume=args.resume, end_distributed=True)
    except parallel.DistributedError as e:
        print(f"error: {e}", file=sys.stderr)
        return parallel.EXIT_DISTRIBUTED
    except (ValueError, FileExistsError, OSError, MemoryError, ckpt.CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except BaseException:
        if jax.process_count() == 1:
            raise
        import traceback

        traceback.print_exc()  # an unexpected error: its traceback, then this process ends (no hang)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
