"""The host loop of a run (:class:`Trainer`): views, the jitted step, strategies, checkpoints.

Stages
  1. 2DGS (every method): SfM-point initialisation (:func:`init_scene`), per-group Adam
     (:mod:`patexgs_jax.optim`), the loss of :mod:`patexgs_jax.training.step`, one SH band every
     ``sh_interval`` steps, adaptive density control (:class:`~.strategies.Densification`).
  2. Textures (all methods but ``2dgs``; :class:`~.strategies.TextureStage`).

Robustness
  The data order is a per-epoch permutation seeded by (seed, epoch), and every random choice is
  seeded by (seed, step), so ``resume`` from a checkpoint reaches the same result as an
  uninterrupted run. A non-finite loss or gradient, or a render whose tile capacity overflowed,
  skips the update (never applied, never poisoning the state); overflow grows the capacity and the
  step is retried; ``max_bad_steps`` consecutive non-finite steps stop the run, keeping the last
  good checkpoint.

Compiled programs (see :mod:`patexgs_jax.compiled`)
  A training view is padded to the renderer's tile grid (:mod:`patexgs_jax.buckets`; the loss is
  the view's own, the per-splat statistics the unpadded render's), so the step compiles once per
  distinct tile grid of the training images, not once per image size, and again only when the
  tile capacity or the scene's shapes change (densification; the texture stage's start and Eq. 7
  allocation; a growth event only when it overflows a texture bucket's headroom, see
  :mod:`patexgs_jax.rebucket`); the programs of earlier shapes are then released (and at most a
  few capacities kept per shapes). Near the
  kernel's memory-map cap the run releases all compiled code and, if that is not enough,
  checkpoints and stops with :class:`patexgs_jax.compiled.MapLimitReached` (resume with
  ``resume=True``).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import datetime
import json
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import ahead, buckets, compiled, interrupt, progress
from .. import checkpoint as ckpt
from .. import densify as dens
from ..adaptive import TextureScheduleState
from ..evaluation import camera_problem, image_problem
from ..optim import make_optimizer, upgrade_state
from ..rebucket import resize_textures
from ..rendering import Capacity, RenderConfig, count_pairs
from ..scene import Scene
from .config import TrainConfig, config_dict
from .step import STEP_TRACES, batch_step, single_view_step
from .strategies import TEXTURE_HEADROOM, TEXTURE_MIN_SPARE, Densification, SmoothingFilter, TextureStage, TrainState

__all__ = ["STAGE1_DIR", "Trainer", "device_description", "format_seconds", "init_scene", "long_run_note",
           "rgba_texels", "run_estimate", "step_seconds", "typical_size"]

#: Sub-folder of a run's checkpoints holding its end-of-2DGS-stage checkpoint (see Trainer.save_stage1).
STAGE1_DIR = "stage1"

#: Steps between two looks at the memory-map count (it is also read after every compile).
_MAP_CHECK_EVERY = 25

#: Jitted steps (capacities) kept for one scene layout.
_MAX_STEP_FNS = 4

#: A jitted step as Trainer._compiled_step keeps it: the function, the size buckets it has been
#: called with (a new one compiles), and the background jobs compiling it ahead, per bucket.
StepEntry = tuple[Callable, set, dict[tuple[int, int], "ahead.Job | None"]]

#: A textured step's cost in 2DGS steps, for the time estimate made before the texture stage is
#: measured (2.5-4x on a 2-core CPU, docs/performance.md).
TEXTURED_STEP_COST = 3.0

#: Runs estimated to take longer than this many seconds say so at the start, with the flags that
#: shorten them.
LONG_RUN_SECONDS = 3600.0

#: The shortest image side (px) a ``--factor`` suggestion may leave.
MIN_SUGGESTED_SIDE = 128


def format_seconds(seconds: float) -> str:
    """``"2 h 05 min"``, ``"14 min"``, ``"40 s"``."""
    seconds = max(0.0, float(seconds))
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = int(round(seconds / 60))
    if minutes < 60:
        return f"{minutes} min"
    return f"{minutes // 60} h {minutes % 60:02d} min"


def rgba_texels(scene: Scene) -> int:
    """RGBA texels of a scene's active Gaussians: ``sum_i max(rgb side_i, alpha side_i)^2``, the
    count the texture-stage lines give (the RGB and alpha textures share their sides once Eq. 7 has
    allocated them; during the warm-up the 5x5 alpha textures set it). 0 without textures."""
    sides = [np.asarray(bank.size, np.int64) for bank in (scene.rgb, scene.alpha) if bank is not None]
    if not sides:
        return 0
    side = np.maximum.reduce(sides) * (np.asarray(scene.active) > 0)
    return int(np.sum(side * side))


def step_seconds(textured: bool, stage: int, per_step: float) -> tuple[float, float]:
    """Seconds of a 2DGS step and of a stage-2 step from ``per_step``, the measured seconds of a step
    of ``stage`` (1: 2DGS, 2: the second stage); a textured step not yet measured counts as
    :data:`TEXTURED_STEP_COST` 2DGS steps (and a measured one as a 2DGS step, where it is the only
    measure)."""
    return per_step, (per_step * TEXTURED_STEP_COST if (stage == 1 and textured) else per_step)


def run_estimate(cfg: TrainConfig, textured: bool, step: int, stage: int, per_step: float) -> tuple[float, float]:
    """Seconds (left from ``step``, whole run) from ``per_step`` (see :func:`step_seconds`).
    Compiles and the evaluation are not included."""
    per1, per2 = step_seconds(textured, stage, per_step)
    n1, n2 = cfg.iters_2dgs, cfg.total_steps - cfg.iters_2dgs
    left = max(0, n1 - step) * per1 + min(n2, cfg.total_steps - max(step, n1)) * per2
    return left, n1 * per1 + n2 * per2


def long_run_note(cfg: TrainConfig, per_steps: tuple[float, float], width: int, height: int,
                  factor: float) -> str:
    """The line that says a run is long, and what ``--preset cpu`` and a ``--factor`` (the smallest
    that brings the run under :data:`LONG_RUN_SECONDS`, a step's time taken to go with its pixels)
    would take instead. ``per_steps``: :func:`step_seconds`; ``factor``: the images' downsampling."""
    import math

    from .config import preset_config

    per1, per2 = per_steps
    n2 = cfg.total_steps - cfg.iters_2dgs
    whole = cfg.iters_2dgs * per1 + n2 * per2
    cpu_preset = preset_config("cpu")
    cpu1, cpu2 = cpu_preset.iters_2dgs, cpu_preset.iters_tex
    cpu = cpu1 * per1 + (cpu2 * per2 if n2 else 0.0)
    new_factor = max(int(math.ceil(factor * math.sqrt(whole / LONG_RUN_SECONDS))), int(math.floor(factor)) + 1)
    smaller = whole * (factor / new_factor) ** 2
    # Below about MIN_SUGGESTED_SIDE px a step's fixed costs dominate (and little of the scene is left).
    short_side = min(width, height) * factor / new_factor
    shrink = "" if short_side < MIN_SUGGESTED_SIDE else (
        f" or --factor {new_factor} (images {new_factor}x smaller a side than full size, about "
        f"{format_seconds(smaller)})")
    return (f"note: this run takes about {format_seconds(whole)} on {device_description()} "
            f"({cfg.iters_2dgs:,} + {n2:,} steps on {width}x{height} px images); --preset cpu "
            f"({cpu1:,} + {cpu2:,} steps, about {format_seconds(cpu)}){shrink} brings it down. Going on.")


def typical_size(views) -> tuple[int, int]:
    """The most common (width, height) of ``views``' cameras."""
    sizes = collections.Counter((v.camera.width, v.camera.height) for v in views)
    return sizes.most_common(1)[0][0]


def device_description() -> str:
    """The devices a run uses, e.g. ``"cpu (2 cores)"`` or ``"1 x NVIDIA H100 80GB HBM3"``."""
    devices = jax.devices()
    if devices[0].platform == "cpu":
        return f"cpu ({os.cpu_count()} cores)"
    return f"{len(devices)} x {devices[0].device_kind}"


def _layout(scene: Scene) -> tuple:
    """The shapes of a scene's arrays: what, with the static arguments, selects a compiled step."""
    return tuple(np.shape(x) for x in jax.tree_util.tree_leaves(scene))


def _single_step_jit(optimizer, render_cfg: RenderConfig, capacity: Capacity | None, lambda_dssim: float,
                     lambda_dist: float):
    """The jitted single-view training step (see :meth:`Trainer.step_fn`); it closes over nothing of
    a Trainer, so that a step compiled ahead by one run serves another."""
    return jax.jit(lambda sc, st, stats, cam, img, hw, sh, wn: single_view_step(
        sc, st, stats, cam, img, hw, sh, wn, optimizer=optimizer, render_config=render_cfg, capacity=capacity,
        lambda_dssim=lambda_dssim, lambda_dist=lambda_dist), donate_argnums=(0, 1, 2))


def _step_identity(radius: float, config: TrainConfig) -> tuple:
    """What defines a run's training step besides its render config, tile capacity and layout (the
    key a step compiled ahead is matched by): scene radius, learning rates, loss weights."""
    return (radius, dataclasses.replace(config.lr, means_steps=config.iters_2dgs), config.lambda_dssim,
            config.lambda_dist)


def _step_image_args(cam) -> tuple:
    """Abstract image, image size, SH degree and normal weight of a single-view step at ``cam``'s
    (padded) size, for ``lower``."""
    return (jax.ShapeDtypeStruct((cam.height, cam.width, 3), np.float32), jax.ShapeDtypeStruct((2,), np.int32),
            jax.ShapeDtypeStruct((), jnp.int32), jax.ShapeDtypeStruct((), jnp.float32))


def _owned_copy(tree):
    """A copy of ``tree``'s device arrays that a background job owns (the next step donates the
    originals)."""
    return jax.tree_util.tree_map(lambda x: jnp.copy(x) if isinstance(x, jax.Array) else x, tree)


@dataclasses.dataclass(eq=False)
class _Prepared:
    """A texture stage's first programs, being compiled ahead (:mod:`patexgs_jax.ahead`) for a layout
    not reached yet: the textured step for the warm-up's layout at the first view's size bucket and,
    for Eq. 7 methods, the allocation's pair counter and renderer (:meth:`Trainer.prepare_stage2`).

    ``identity``: what defines the step besides its render config and tile capacity (scene radius,
    learning rates, loss weights); ``capacity``, ``fn`` (the jitted step) and ``eq7`` (programs for
    :class:`patexgs_jax.buckets.ViewRenderer`) are set by the background job. ``layout`` is None
    while a predicted allocation's sides are being counted (``counted`` is set once it is known);
    ``then``: the entry of the allocation predicted from this warm-up state."""

    identity: tuple
    render_cfg: RenderConfig
    layout: tuple | None
    bucket: tuple[int, int]
    owner: int  # id() of the Trainer whose own stage 2 it is (0: made for another run)
    step_job: ahead.Job | None = None
    eq7_job: ahead.Job | None = None
    capacity: Capacity | None = None
    fn: Any = None
    counted: threading.Event = dataclasses.field(default_factory=threading.Event)
    then: _Prepared | None = None

    def cancel(self) -> None:
        for job in (self.step_job, self.eq7_job):
            if job is not None:
                job.cancel()
        if self.then is not None:
            self.then.cancel()
            with contextlib.suppress(ValueError):
                _PREPARED.remove(self.then)


#: Stage-2 programs compiled ahead and not yet claimed by the run that needs them (process-wide: a
#: run may prepare the runs that start from its stage-1 checkpoint, see ``train(..., prepare=)``).
_PREPARED: list[_Prepared] = []

#: Prepared entries kept at most (the oldest are dropped first).
_MAX_PREPARED = 4


def init_scene(points, colors, config: TrainConfig, capacity: int | None = None) -> Scene:
    """2DGS initialisation from points (M, 3) and colours (M, 3) in [0, 1] (or None: grey).

    Scales: the mean distance to the 3 nearest neighbours (both axes; all three for the 3D methods,
    whose Mip-Splatting filter starts at zero); random rotations; opacity ``config.init_opacity``;
    SH DC from the colours, higher bands zero.
    """
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (missing from scipy's stubs)

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
    spec = config.spec
    return Scene.from_arrays(points, np.repeat(dist[:, None], 3 if spec.primitive == "3d" else 2, axis=1), quats,
                             np.full(n, config.init_opacity), sh, capacity=cap,
                             filter3d=np.zeros(n) if spec.filter3d else None)


class Trainer:
    """The mutable host-side state of one run (everything a checkpoint holds) and its loop.

    ``scene``, ``opt_state`` and ``stats`` (together :attr:`state`) are what the jitted step updates;
    :attr:`strategies` (densification, then the texture stage) rewrite them between steps.
    """

    def __init__(self, dataset, config: TrainConfig, out_dir: Path | None, verbose: bool,
                 map_guard: compiled.MapGuard | None = None):
        self.ds, self.cfg, self.out, self.verbose = dataset, config, out_dir, verbose
        self.map_guard = map_guard if map_guard is not None else compiled.MapGuard()
        self.train_views = list(dataset.train_views)
        if not self.train_views:
            raise ValueError("the dataset has no training views.")
        self.radius = float(dataset.normalization.radius)
        self.spec = config.spec
        self.render_cfgs = (config.render_config(stage=1), config.render_config(stage=2))
        # The position learning rate decays over the 2DGS stage for every method, so stage 1 is the
        # same run whatever the method (and can be shared: ``train(..., stage1=)``, see .run).
        self.lr = dataclasses.replace(config.lr, means_steps=config.iters_2dgs)
        self.optimizer = make_optimizer(self.radius, self.lr)
        self.capacity = None
        self.step = 0
        self.bad_streak = 0
        self.skipped = 0
        self.recompiles = 0
        self.t_train = 0.0
        self.stage1_saved = False
        # With several processes (jax.distributed) only process 0 writes and prints progress.
        self.main = jax.process_index() == 0
        self.log_path = None if out_dir is None else out_dir / "log.jsonl"
        self.densification = Densification(config, self.radius)
        self.textures = TextureStage(config, self.optimizer, self.train_views, self.render_cfgs[1],
                                     log=self.log, say=self.say)
        self.strategies = (self.densification, SmoothingFilter(config, [v.camera for v in self.train_views]),
                           self.textures)
        # The jitted steps of the current scene layout, per (render config, capacity), each with one
        # program per size bucket; released when the layout changes (see _compiled_step).
        self._jit_cache: dict[Any, StepEntry] = {}
        self._jit_layout = None
        self.saved_step = 0  # the newest checkpoint's step (0: the initial state, which is reproducible)
        self.t_start = time.perf_counter()
        # Durations of steps that compiled nothing, per stage, for the time estimate (see _measure).
        self._clean_steps: dict[int, list[float]] = {1: [], 2: []}
        self.estimated: set[int] = set()  # the stages whose steps gave an estimate
        # Compiling ahead (see prepare_stage2): the configs of runs that start from this run's stage-1
        # checkpoint in this process (train(..., prepare=)), whether this run has prepared its own
        # texture stage, and whether the last step waited for (or took) a program compiled ahead.
        self.prepare_for: tuple[TrainConfig, ...] = ()
        self._prepared_own = False
        self._took_ahead = False
        dc = self.densification.config
        self._last_densify = max((t for t in range(1, config.iters_2dgs) if dc.densify_at(t)), default=0)

    @property
    def render_cfg(self) -> RenderConfig:
        """The renderer's settings of the current stage (see :meth:`TrainConfig.render_config`)."""
        return self.render_cfgs[0 if self.step < self.cfg.iters_2dgs else 1]

    @property
    def state(self) -> TrainState:
        return TrainState(self.scene, self.opt_state, self.stats)

    @state.setter
    def state(self, state: TrainState):
        self.scene, self.opt_state, self.stats = state

    # -- state -----------------------------------------------------------------------------------
    def fresh(self):
        pts, cols = self.ds.points, self.ds.colors
        self.scene = init_scene(pts, cols, self.cfg)
        self.opt_state = self.optimizer.init(self.scene)
        self.stats = dens.DensifyStats.zeros(self.scene.capacity)

    def state_tree(self):
        tex = self.textures.state
        return dict(scene=self.scene, opt_state=self.opt_state, stats=self.stats,
                    tex_sizes=None if tex is None else tex.sizes,
                    tex_counters=None if tex is None else np.array(
                        [tex.last_growth_step, tex.num_growth_events, tex.num_grown]),
                    # None (refit before the next step) after a densification that grew the scene: 0.
                    capacity=np.array([0 if self.capacity is None else self.capacity.pairs]),
                    counters=np.array([self.step, self.skipped, self.recompiles]),
                    t_train=np.array(self.t_train), allocation=self.textures.allocation,
                    growth_events=list(self.textures.growth_events))

    def load_state(self, tree):
        self.scene, self.stats = tree["scene"], tree["stats"]
        self.opt_state = upgrade_state(tree["opt_state"])
        tex = None
        if tree["tex_sizes"] is not None:
            c = tree["tex_counters"]
            tex = TextureScheduleState(np.asarray(tree["tex_sizes"]), int(c[0]), int(c[1]), int(c[2]))
        self.textures.load(tex, tree.get("allocation"), tree.get("growth_events"))
        self.capacity = Capacity(int(tree["capacity"][0])) if int(tree["capacity"][0]) > 0 else None
        self.step, self.skipped, self.recompiles = (int(v) for v in tree["counters"])
        self.t_train = float(tree["t_train"])

    def save(self):
        """Writes a checkpoint (process 0); with several processes, first checks that every process
        holds the same state (the replicated state must never diverge), then waits until it is written."""
        from .. import parallel

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
            ckpt.save_checkpoint(path, tree, dict(config=config_dict(self.cfg), step=self.step), keep=2)
        self.note_saved(self.step)
        if several:  # the others wait until it is written (a study reads it next)
            parallel.check_same(f"the checkpoint of step {self.step} being written", [self.step])

    def note_saved(self, step: int) -> None:
        """Records that the checkpoint of ``step`` (written or loaded) holds the run's work."""
        self.saved_step = step
        if self.out is not None:
            interrupt.set_saved(f"the checkpoint of step {step} in {self.out / 'checkpoints'}")

    def save_on_stop(self) -> None:
        """On a stop signal between steps: a checkpoint, unless the newest is at most
        ``checkpoint_on_stop`` steps old, the run is in a non-finite streak (the last good one stays)
        or it runs in several processes (the periodic checkpoints hold the work)."""
        if self.out is None or self.bad_streak or self.step - self.saved_step <= self.cfg.checkpoint_on_stop:
            return
        if jax.process_count() > 1:  # a save is collective, and the others may stop at another step
            return
        self.save()

    def save_stage1(self):
        """At the end of the 2DGS stage of a run that goes on: a checkpoint (a restart point) and a
        copy kept in ``checkpoints/stage1/`` (out of the rotation), from which other methods can
        start (:func:`patexgs_jax.training.run.stage1_checkpoint`)."""
        self.stage1_saved = True
        if self.out is None or self.step >= self.cfg.total_steps:
            return
        self.save()
        if self.main:
            meta = dict(config=config_dict(self.cfg), step=self.step)
            ckpt.save_checkpoint(ckpt.checkpoint_path(self.out / "checkpoints" / STAGE1_DIR, self.step),
                                 self.state_tree(), meta, keep=1)

    # -- helpers ---------------------------------------------------------------------------------
    def view(self, step, seed: int | None = None):
        """The training view of ``step`` (a per-epoch permutation seeded by (seed, epoch); ``seed``
        defaults to the run's)."""
        n = len(self.train_views)
        epoch, i = divmod(step, n)
        perm = np.random.default_rng([self.cfg.seed if seed is None else seed, epoch]).permutation(n)
        return self.train_views[perm[i]]

    def _compiled_step(self, key, make: Callable[[], Callable],
                       claim: Callable[[tuple], Any] | None = None) -> StepEntry:
        """The jitted step for ``key`` (render config, capacity, ...) and the scene's current layout,
        made by ``make()`` when new (or taken from a step compiled ahead, ``claim(layout)``); returns
        (the jitted step, the size buckets it has been called with, the background jobs compiling it
        ahead per bucket). A layout, once left, is rarely met again within a run (the
        Gaussian capacity only grows; texture buckets are sized afresh when one overflows), so when
        the layout changes the steps of the old one are dropped, with the renderer's and pair
        counter's programs of the old layout, and their memory mappings returned (see
        :mod:`patexgs_jax.compiled`). Within a layout at most :data:`_MAX_STEP_FNS` steps
        (capacities) are kept, the oldest dropped first."""
        layout = _layout(self.scene)
        if self._jit_layout != layout:
            if self._jit_cache:
                self._jit_cache.clear()
                buckets.release_scene_programs()
            self._jit_layout = layout
        if key not in self._jit_cache:
            while len(self._jit_cache) >= _MAX_STEP_FNS:
                self._jit_cache.pop(next(iter(self._jit_cache)))
            prepared = None if claim is None else claim(layout)
            if prepared is not None:
                self._jit_cache[key] = (prepared.fn, set(), {prepared.bucket: prepared.step_job})
            else:
                self._jit_cache[key] = (make(), set(), {})
        return self._jit_cache[key]

    def prepare_stage2(self, config: TrainConfig, predict_allocation: bool = True) -> None:
        """Starts compiling ahead, in the background (:mod:`patexgs_jax.ahead`), the first programs of
        ``config``'s texture stage (this run's own, or one that will start from this run's stage-1
        checkpoint in this process) from this run's current state: the textured step for the
        warm-up's layout at the size bucket of the stage's first view, with the tile capacity the
        first step will fit, and for Eq. 7 methods the allocation's pair counter and renderer and,
        with ``predict_allocation``, the textured step for the layout Eq. 7 gives on the warm-up's
        first state (a speculative allocation: counted and sized in the background; the real one,
        40 steps of training later, usually falls in the same power-of-two buckets). The warm-up's
        layout is known exactly once the Gaussian count is fixed (densification has stopped); the
        capacities are predicted from the current scene. A prediction that does not match what the
        run then needs is not used (the run compiles as it would have), so results never depend on
        it. Does nothing when compiling ahead is off, for 2DGS, batches, or several processes."""
        if (not ahead.enabled() or config.spec.textures is None or config.batch_size != 1
                or config.iters_2dgs != self.cfg.iters_2dgs or config.total_steps <= config.iters_2dgs
                or jax.process_count() > 1):
            return
        from ..rendering import render_jit

        own = config is self.cfg
        identity = _step_identity(self.radius, config)
        optimizer = self.optimizer if own else make_optimizer(self.radius, identity[1])  # (its learning rates)
        render_cfg = config.render_config(stage=2)
        stage = TextureStage(config, optimizer, self.train_views, render_cfg)
        state = stage.start(self.state)
        scene, opt_state, stats = _owned_copy(tuple(state))
        view = self.view(config.iters_2dgs, config.seed)
        cam = buckets.padded_camera(view.camera, render_cfg.tile_size)
        layout = _layout(scene)
        same = [p for p in _PREPARED if (p.identity, p.render_cfg, p.layout) == (identity, render_cfg, layout)]
        if same and not own:
            return  # (another run the study trains next has the same first programs: prepared once)
        for old in same:
            old.cancel()  # superseded (a capacity refit since)
            with contextlib.suppress(ValueError):
                _PREPARED.remove(old)
        prep = _Prepared(identity, render_cfg, layout, (cam.height, cam.width), 0 if not own else id(self))
        # The stage's first step fits the capacity (1.25 x its view's pairs) from none (a run started
        # from a stage-1 checkpoint), or this run keeps its own (refitted up at the stage's start
        # when a refit falls there).
        minimum = self.capacity if own else None
        keep = own and not self._refits_at(config.iters_2dgs)
        args = _step_image_args(cam)

        def compile_step():
            try:
                if keep:
                    prep.capacity = minimum
                else:  # (its own program: the main thread releases the shared jitted ones at will)
                    needed, _ = count_pairs.lower(scene, cam, config=render_cfg).compile()(scene, cam)
                    prep.capacity = Capacity.fit(float(needed) * 1.25, minimum=minimum)
                prep.fn = _single_step_jit(optimizer, render_cfg, prep.capacity, config.lambda_dssim,
                                           config.lambda_dist)
            finally:
                prep.counted.set()
            prep.fn.lower(scene, opt_state, stats, cam, *args).compile()

        def compile_eq7():
            programs, caps, cams = {}, {}, {}
            for v in self.train_views:  # as TextureStage.allocate's ViewRenderer buckets and counts them
                c = buckets.padded_camera(v.camera, render_cfg.tile_size, buckets.EVAL_STEPS_PER_OCTAVE)
                key = (c.height, c.width)
                if ("count", *key) not in programs:
                    programs[("count", *key)] = count_pairs.lower(scene, c, config=render_cfg).compile()
                    cams[key] = c
                needed, _ = programs[("count", *key)](scene, c)
                caps[key] = Capacity.fit(float(needed), minimum=caps.get(key))
            for key, cap in caps.items():
                programs[("render", *key, cap)] = render_jit.lower(
                    scene, cams[key], config=render_cfg, capacity=cap, active_sh_degree=None,
                    textures=None).compile()
            return programs

        say = self.say
        whose = "" if own else f" of {config.method}"
        prep.step_job = ahead.submit(f"the textured step{whose} for {cam.width}x{cam.height} px", compile_step, say)
        if config.spec.textures == "adaptive" and config.warmup_tex < config.iters_tex:
            prep.eq7_job = ahead.submit(f"Eq. 7's pair counter and renderer{whose}", compile_eq7, say)
        if prep.step_job is None:
            return
        _PREPARED.append(prep)
        if predict_allocation and prep.eq7_job is not None:
            def capacity():
                prep.counted.wait()
                return prep.capacity

            prep.then = self._predict_allocation(config, stage, optimizer, identity, (scene, opt_state, stats),
                                                 prep.eq7_job, capacity, prep.owner, whose)
        while len(_PREPARED) > _MAX_PREPARED:
            _PREPARED.pop(0).cancel()

    def _predict_allocation(self, config: TrainConfig, stage: TextureStage, optimizer, identity: tuple,
                            state: tuple, eq7_job: ahead.Job, capacity: Callable[[], Capacity | None], owner: int,
                            whose: str = "") -> _Prepared | None:
        """Queues a speculative Eq. 7 allocation of ``config`` on ``state`` (scene, opt_state, stats:
        arrays the background thread owns, at the warm-up's layout) and the compile of the textured
        step for the layout it gives, at the size bucket of the allocation step's view and the tile
        capacity ``capacity()`` (called in the background); counted with Eq. 7's programs of
        ``eq7_job``. Returns its entry (in ``_PREPARED``; its layout is None until counted), or None
        when compiling ahead is off."""
        render_cfg = config.render_config(stage=2)
        scene, opt_state, stats = state
        view = self.view(config.iters_2dgs + config.warmup_tex, config.seed)
        cam = buckets.padded_camera(view.camera, render_cfg.tile_size)
        alloc = _Prepared(identity, render_cfg, None, (cam.height, cam.width), owner)
        args = _step_image_args(cam)

        def compile_allocation():
            try:
                cap = capacity()
                if not eq7_job.ok or cap is None:
                    return
                # As TextureStage.allocate counts, with the programs compiled for this layout; not
                # released after (the main thread's Eq. 7 shares them).
                renderer = buckets.ViewRenderer(scene, render_cfg, programs=eq7_job.value)
                renderer.prepare([v.camera for v in self.train_views])
                counts = np.stack([np.asarray(renderer(v.camera).max_contrib_count) for v in self.train_views])
                sides, _, _ = stage.allocation_sides(counts, np.asarray(scene.active) > 0)
                new_scene, new_opt, _ = resize_textures(scene, opt_state, sides, sides, headroom=TEXTURE_HEADROOM,
                                                        min_spare=TEXTURE_MIN_SPARE)
                alloc.capacity, alloc.layout = cap, _layout(new_scene)
                alloc.fn = _single_step_jit(optimizer, render_cfg, cap, config.lambda_dssim, config.lambda_dist)
            finally:
                alloc.counted.set()
            alloc.fn.lower(new_scene, new_opt, stats, cam, *args).compile()

        alloc.step_job = ahead.submit(f"the textured step{whose} for Eq. 7's predicted layout", compile_allocation,
                                      self.say)
        if alloc.step_job is None:
            return None
        _PREPARED.append(alloc)
        return alloc

    def _predict_own_allocation(self) -> None:
        """At the texture stage's start of a run through both stages: the speculative allocation (see
        :meth:`_predict_allocation`) from the warm-up's actual first state, with Eq. 7's programs
        compiled ahead for this layout (:meth:`prepare_stage2`)."""
        cfg = self.cfg
        if (not ahead.enabled() or cfg.spec.textures != "adaptive" or cfg.batch_size != 1
                or cfg.warmup_tex >= cfg.iters_tex or jax.process_count() > 1 or self.capacity is None):
            return
        prep = self._find_prepared(self.render_cfgs[1], _layout(self.scene))
        if prep is None or prep.eq7_job is None or prep.then is not None or prep.eq7_job.cancelled:
            return
        cap = self.capacity
        prep.then = self._predict_allocation(cfg, self.textures, self.optimizer, _step_identity(self.radius, cfg),
                                             _owned_copy(tuple(self.state)), prep.eq7_job, lambda: cap, id(self))

    def _prepare_others(self) -> None:
        """At the end of the 2DGS stage: the first programs of the runs that start from this state
        (``train(..., prepare=)``), once."""
        for i, other in enumerate(self.prepare_for):
            if len(_PREPARED) >= _MAX_PREPARED:
                break  # (entries for runs further on would push out those of the runs trained first)
            self.prepare_stage2(other, predict_allocation=i == 0)  # (the allocation: the next run's only)
        self.prepare_for = ()

    def _find_prepared(self, render_cfg: RenderConfig, layout: tuple) -> _Prepared | None:
        identity = _step_identity(self.radius, self.cfg)
        return next((p for p in _PREPARED if p.identity == identity and p.render_cfg == render_cfg
                     and p.layout == layout), None)

    def _claim_step(self, render_cfg: RenderConfig, capacity, layout: tuple) -> _Prepared | None:
        """The step prepared ahead for this render config, capacity and layout, if any (see
        :meth:`prepare_stage2`); a job not started yet is cancelled (compiling here is sooner)."""
        if self.cfg.batch_size != 1:
            return None
        prep = self._find_prepared(render_cfg, layout)
        if prep is None:
            self._settle_predictions(render_cfg)
            prep = self._find_prepared(render_cfg, layout)
        if prep is None or prep.step_job is None:
            return None
        job = prep.step_job
        if job.cancel() or job.cancelled:
            _PREPARED.remove(prep)
            prep.cancel()
            return None
        prep.counted.wait()  # (the capacity is counted first, in seconds)
        if prep.capacity != capacity or prep.fn is None:
            return None  # (a capacity the run does not use; Eq. 7's programs may still serve)
        prep.owner = id(self)
        if prep.then is not None:
            prep.then.owner = id(self)
        if prep.eq7_job is None:
            _PREPARED.remove(prep)
        return prep

    def _settle_predictions(self, render_cfg: RenderConfig) -> None:
        """Waits for the predicted allocations being counted in the background for this run's settings
        (their layout is known within seconds); drops those not started or failed."""
        identity = _step_identity(self.radius, self.cfg)
        for p in [p for p in _PREPARED if p.layout is None and p.identity == identity and p.render_cfg == render_cfg]:
            job = p.step_job
            if job is not None and not job.cancel() and not job.cancelled and not p.counted.is_set():
                interrupt.set_phase("waiting for the background count of Eq. 7's predicted layout")
                interrupt.set_step(self.step, self.cfg.total_steps)
                while not p.counted.wait(0.2):
                    interrupt.check()
            if p.layout is None:
                with contextlib.suppress(ValueError):
                    _PREPARED.remove(p)

    def _claim_eq7(self) -> dict | None:
        """Eq. 7's programs prepared ahead for the current layout (see :meth:`prepare_stage2`), waiting
        for them if they are being compiled; None if there are none."""
        prep = self._find_prepared(self.render_cfgs[1], _layout(self.scene))
        if prep is None or prep.eq7_job is None:
            return None
        _PREPARED.remove(prep)
        job = prep.eq7_job
        if job.cancel():
            return None
        self._wait_ahead(job)
        return job.value if job.ok else None

    def _wait_ahead(self, job: ahead.Job) -> None:
        """Waits for a background compile the next step needs (a stop signal still stops the run)."""
        if job.done:
            return
        interrupt.set_phase(f"waiting for the background compile of {job.what}")
        interrupt.set_step(self.step, self.cfg.total_steps)
        self.say(f"[compile ahead] waiting for {job.what} ({time.monotonic() - (job.started or 0):.0f} s "
                 "into its compile)")
        job.wait(poll=interrupt.check)

    def _take_ahead(self, job: ahead.Job | None, what: str) -> bool:
        """Whether the step's program for a new size bucket was compiled ahead by ``job`` (waited for
        if still compiling); False (the step compiles it) if the job failed or had not started."""
        if job is None or job.cancel():
            return False
        self._wait_ahead(job)
        self._took_ahead = True
        return job.ok

    def stage_name(self, step: int | None = None) -> str:
        """``"2DGS"`` or ``"textured"``: which step ``step`` (default: the current one) runs."""
        step = self.step if step is None else step
        return "2DGS" if step < self.cfg.iters_2dgs or self.spec.textures is None else "textured"

    def announce_compile(self, what: str) -> None:
        """Marks the phase as a compile (the heartbeat then says how long it has taken)."""
        interrupt.set_phase(f"compiling the {self.stage_name()} step for {what}")
        interrupt.set_step(self.step, self.cfg.total_steps)

    def step_fn(self) -> Callable[..., Any]:
        """The training step as ``fn(scene, opt_state, stats, camera, image, active_sh, w_normal)``
        (``image`` (H, W, 3) of the camera's size). The view is padded to its size bucket (the
        renderer's exact tile grid) on the host, so the views of one bucket share a program."""
        if self.cfg.batch_size > 1:
            return self._batch_step_fn()
        cfg, render_cfg, capacity = self.cfg, self.render_cfg, self.capacity
        fn, buckets_seen, ahead_jobs = self._compiled_step(
            (render_cfg, capacity),
            lambda: _single_step_jit(self.optimizer, render_cfg, capacity, cfg.lambda_dssim, cfg.lambda_dist),
            claim=lambda layout: self._claim_step(render_cfg, capacity, layout))

        def step(scene, opt_state, stats, camera, image, active_sh, w_normal):
            cam = buckets.padded_camera(camera, render_cfg.tile_size)
            if (cam.height, cam.width) not in buckets_seen:  # this call compiles (see _compiled_step)
                buckets_seen.add((cam.height, cam.width))
                job = ahead_jobs.pop((cam.height, cam.width), None)
                what = f"{cam.width}x{cam.height} px"
                if not self._take_ahead(job, f"the {self.stage_name()} step for {what}"):
                    self.announce_compile(what)
            img = buckets.pad_image(image, cam.height, cam.width)
            hw = np.array([camera.height, camera.width], np.int32)
            return fn(scene, opt_state, stats, cam, img, hw, active_sh, w_normal)

        return step

    def data_mesh(self):
        """The device mesh of the data-parallel step (``batch_size`` > 1), built once per run."""
        from .. import parallel

        if getattr(self, "_mesh", None) is None:
            self._mesh = parallel.data_mesh(parallel.num_batch_devices(self.cfg.batch_size, self.cfg.devices))
        return self._mesh

    def _batch_step_fn(self):
        from .. import parallel

        mesh, render_cfg, capacity, cfg = self.data_mesh(), self.render_cfg, self.capacity, self.cfg
        jitted, seen, _ = self._compiled_step((render_cfg, capacity, cfg.batch_size), lambda: jax.jit(
            lambda sc, st, stats, cams, imgs, sh, wn: batch_step(
                sc, st, stats, cams, imgs, sh, wn, mesh=mesh, optimizer=self.optimizer,
                render_config=render_cfg, capacity=capacity, lambda_dssim=cfg.lambda_dssim,
                lambda_dist=cfg.lambda_dist),
            out_shardings=parallel.replicated(mesh), donate_argnums=(0, 1, 2)))

        def fn(*args):
            if not seen:  # the first call compiles
                seen.add(())
                self.announce_compile(f"batches of {cfg.batch_size} views")
            return jitted(*args)

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
        from .. import parallel

        return range(self.cfg.batch_size)[parallel.process_slice(self.cfg.batch_size, self.data_mesh())]

    def batch_inputs(self, views, images):
        """Stacked cameras and (B, H, W, 3) images placed over the mesh, the state replicated on it.
        ``images``: the batch's images; only those at :meth:`batch_share` are read (with several
        processes the others are not loaded and may be None)."""
        from .. import parallel

        mesh = self.data_mesh()
        self.scene, self.opt_state, self.stats = parallel.replicate((self.scene, self.opt_state, self.stats),
                                                                    parallel.local_mesh(mesh))
        share = self.batch_share()
        cams = parallel.stack_cameras([views[j].camera for j in share])
        return parallel.shard_batch((cams, np.stack([np.asarray(images[j], np.float32) for j in share])), mesh)

    def fit_capacity(self, camera):
        interrupt.set_phase("counting the tile pairs of a view (the counter compiles once per size)")
        # Counted at the step's size bucket (the same tile grid: the same count), one program a bucket.
        camera = camera if self.cfg.batch_size > 1 else buckets.padded_camera(camera, self.render_cfg.tile_size)
        needed, _ = count_pairs(self.scene, camera, self.render_cfg)
        cap = Capacity.fit(float(needed) * 1.25, minimum=self.capacity)
        if cap != self.capacity:
            self.capacity = cap

    def log(self, record):
        """Appends ``record`` to ``log.jsonl`` with its wall-clock time (UTC, ISO 8601) and the
        seconds since this process started the run."""
        if self.log_path is not None and self.main:
            now = datetime.datetime.now(datetime.UTC)
            record = dict(record, time=now.isoformat(timespec="milliseconds").replace("+00:00", "Z"),
                          elapsed_s=round(time.perf_counter() - self.t_start, 3))
            with open(self.log_path, "a") as f:
                f.write(json.dumps(record) + "\n")

    def say(self, msg):
        if self.verbose and self.main:
            progress.say(msg)

    def check_memory_maps(self):
        """Releases compiled code near the memory-map cap; at the guard's stop share even so, saves a
        checkpoint and raises :class:`compiled.MapLimitReached` (a clear stop, not a crash in XLA)."""
        from .. import parallel

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
        """Trains to ``cfg.total_steps``. On a stop signal (:mod:`patexgs_jax.interrupt`) it stops
        between two steps, writes a checkpoint if the newest is too old (:meth:`save_on_stop`) and
        raises :class:`~patexgs_jax.interrupt.Interrupted`."""
        bar = progress.bar(self.cfg.total_steps, f"train {self.cfg.method}", initial=self.step,
                           show=self.verbose and self.main)
        try:
            self._run(bar)
            if self.step == self.cfg.iters_2dgs and self.scene.rgb is None:  # (a run of stage 1 alone)
                self._prepare_others()
        except interrupt.Interrupted:
            self.save_on_stop()
            raise
        finally:
            bar.close()
            for p in [p for p in _PREPARED if p.owner == id(self)]:  # (never claimed: not needed)
                p.cancel()
                with contextlib.suppress(ValueError):  # (cancelling an entry removes its ``then``)
                    _PREPARED.remove(p)

    def _measure(self, step: int, seconds: float) -> None:
        """Records the duration of a step that compiled nothing; after the first few steps of each
        stage, says how long the rest of the run will take, and the first time, when the whole run
        takes over :data:`LONG_RUN_SECONDS`, how to shorten it."""
        stage = 1 if self.stage_name(step) == "2DGS" else 2
        times = self._clean_steps[stage]
        times.append(seconds)
        if stage in self.estimated or not (len(times) >= 10 or (len(times) >= 2 and sum(times) >= 20.0)):
            return
        first = not self.estimated
        self.estimated.add(stage)
        per = float(np.median(times))
        textured = self.spec.textures is not None
        left, whole = run_estimate(self.cfg, textured, self.step, stage, per)
        guess = (f", a textured step taken as {TEXTURED_STEP_COST:g}x that"
                 if stage == 1 and textured and self.cfg.iters_tex else "")
        self.say(f"estimated time: {format_seconds(left)} for the {self.cfg.total_steps - self.step} steps left "
                 f"({1e3 * per:.0f} ms a {self.stage_name(step)} step{guess}), plus compiles and the evaluation")
        if first and whole > LONG_RUN_SECONDS:
            width, height = typical_size(self.train_views)
            self.say(long_run_note(self.cfg, step_seconds(textured, stage, per), width, height,
                                   float(getattr(self.ds, "factor", 1.0) or 1.0)))

    def before_step(self, step):
        """Host-side work before the step that starts at ``step``: the stage-1 checkpoint, then the
        strategies (the texture stage's start and Eq. 7 allocation)."""
        if step == self.cfg.iters_2dgs and self.scene.rgb is None and not self.stage1_saved:
            self.save_stage1()
            self._prepare_others()
        if self.textures.allocates_at(self.state, step):
            self.textures.programs = self._claim_eq7()
        for strategy in self.strategies:
            self.state = strategy.before_step(self.state, step)
        if step == self.cfg.iters_2dgs and self.scene.rgb is not None:
            self._predict_own_allocation()

    def after_step(self, step):
        """Host-side work between steps (``step`` counts completed steps, from 1): the strategies,
        then (stage 1) a tile-capacity refit every 100 steps."""
        capacity = self.scene.capacity
        for strategy in self.strategies:
            self.state = strategy.after_step(self.state, step)
        if self.scene.capacity != capacity:  # the scene's shapes changed: refit before the next step
            self.capacity = None
        if self._refits_at(step):
            self.fit_capacity(self.view(step).camera)
        # Once densification has stopped, the texture stage's first layout is known: compile its step
        # ahead (again after a capacity refit, which may change the prediction).
        if (self._last_densify <= step < self.cfg.iters_2dgs and self.scene.rgb is None
                and self.capacity is not None and (not self._prepared_own or self._refits_at(step))):
            self._prepared_own = True
            # (its allocation is predicted at the stage's start, from the warm-up's actual state)
            self.prepare_stage2(self.cfg, predict_allocation=False)

    def _refits_at(self, step: int) -> bool:
        """Whether :meth:`after_step` refits the tile capacity after ``step`` steps (every 100 steps of
        the 2DGS stage, up to and including its end)."""
        return step <= self.cfg.iters_2dgs and self.capacity is not None and step % 100 == 0

    def _views(self, step):
        """The batch of ``step``: its views, images (None where another process loads them) and each
        view's problem (None for a usable view)."""
        cfg = self.cfg
        # Step s takes views s B .. s B + B - 1 of the stream of per-epoch permutations.
        views = [self.view(step * cfg.batch_size + j) for j in range(cfg.batch_size)]
        # Each process loads only its share of the batch (all of it with one process); the
        # cameras, known to every process, are checked everywhere.
        share = self.batch_share() if cfg.batch_size > 1 else range(1)
        images = [views[j].image if j in share else None for j in range(len(views))]
        problems = [camera_problem(v.camera) for v in views]
        for j in share:
            problems[j] = problems[j] or image_problem(images[j])
            if problems[j] is not None and jax.process_count() > 1:
                # The other processes cannot see this image: it goes into the step as NaNs, which
                # makes the step skip its update on every process.
                print(f"[step {step}, process {jax.process_index()}] view {views[j].name!r}: {problems[j]}; "
                      "the update is skipped", flush=True)
                images[j], problems[j] = np.full((views[j].camera.height, views[j].camera.width, 3), np.nan,
                                                 np.float32), None
        return views, images, problems

    def _run(self, bar):
        cfg = self.cfg
        total = cfg.total_steps
        t_last = time.perf_counter()
        window = collections.deque(maxlen=max(1, cfg.log_every))
        compiled_last = True
        while self.step < total:
            step = self.step
            interrupt.check()  # between steps: the state is whole (a stop writes it, see run())
            if interrupt.set_phase(f"training the {self.stage_name(step)} stage"):
                interrupt.set_step(step, total)
            # Mappings grow only when something compiles (a new bucket, capacity or layout); reading
            # /proc/self/maps costs milliseconds, so look after compiles and every few steps.
            if compiled_last or step % _MAP_CHECK_EVERY == 0:
                self.check_memory_maps()
            compiled_last = False
            self.before_step(step)
            views, images, problems = self._views(step)
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
                w_normal = jnp.float32(cfg.lambda_normal if step >= cfg.normal_from and self.spec.primitive == "2d"
                                       else 0.0)  # (3D Gaussians have no surface normal)
                data = ((view.camera, image) if cfg.batch_size == 1
                        else self.batch_inputs(views, images))
                scene, opt_state, stats, m = fn(self.scene, self.opt_state, self.stats, *data, active_sh, w_normal)
                self.scene, self.opt_state, self.stats = scene, opt_state, stats
                if self._took_ahead:  # (its mappings are new; its time is not a step's)
                    self._took_ahead, compiled_last = False, True
                    interrupt.set_phase(f"training the {self.stage_name(step)} stage")
                if sum(STEP_TRACES.values()) > traces:
                    self.recompiles += 1
                    compiled_last = True
                    interrupt.set_phase(f"training the {self.stage_name(step)} stage")
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
                seconds = time.perf_counter() - t0
                self.t_train += seconds
                if not compiled_last:
                    self._measure(step, seconds)
                window.append((float(m["loss"]), float(m["psnr"])))
            self.step += 1
            interrupt.set_step(self.step, total)
            bar.update(1)
            self.after_step(step + 1)
            if self.step % cfg.log_every == 0 or self.step == total:
                now = time.perf_counter()

                def mean(k):
                    return float(np.mean([w[k] for w in window])) if window else float("nan")

                rec = dict(step=self.step, loss=mean(0), psnr=mean(1), gaussians=self.scene.num_active(),
                           rgba_texels=rgba_texels(self.scene), texels=sum(self.scene.texel_count().values()),
                           ms_per_step=1e3 * (now - t_last) / cfg.log_every, recompiles=self.recompiles,
                           skipped=self.skipped)
                t_last = now
                window.clear()
                self.log(rec)
                bar.set_postfix(psnr=f"{rec['psnr']:.2f}", gaussians=rec["gaussians"], refresh=False)
                self.say(f"step {rec['step']:6d}/{total}  loss {rec['loss']:.4f}  psnr {rec['psnr']:6.2f}  "
                         f"gaussians {rec['gaussians']:7d}  RGBA texels {rec['rgba_texels']:8d}  "
                         f"{rec['ms_per_step']:7.1f} ms/step")
            if (self.step % cfg.checkpoint_every == 0 or self.step == total) and self.bad_streak == 0:
                self.save()  # (not during a non-finite streak: the last good checkpoint stays the newest)
