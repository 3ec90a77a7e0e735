"""The host loop of a run (:class:`Trainer`): views, the jitted step, strategies, checkpoints.

Stages
  1. 2DGS (every method): SfM-point initialisation (:func:`init_scene`), per-group Adam
     (:mod:`patexgs_jax.optim`), the loss of :mod:`patexgs_jax.training.step`, one SH band every
     ``sh_interval`` steps, adaptive density control (:class:`~.strategies.Densification`).
  2. Textures (all methods but ``2dgs``; :class:`patexgs_jax.schedule.TextureSchedule`).

Robustness
  The data order is a per-epoch permutation seeded by (seed, epoch), and every random choice is
  seeded by (seed, step), so ``resume`` from a checkpoint reaches the same result as an
  uninterrupted run. A non-finite loss or gradient, or a render whose tile capacity overflowed,
  skips the update (never applied, never poisoning the state); overflow grows the capacity and the
  step is retried; ``max_bad_steps`` consecutive non-finite steps stop the run, keeping the last
  good checkpoint.

Compiled programs (see :mod:`patexgs_jax.compiled`)
  A training view is padded to its tile grid, or on a GPU to the largest grid of the training
  views (``TrainConfig.padding``, :mod:`patexgs_jax.padding`; the loss is the view's own, the
  per-splat statistics the unpadded render's), so the step compiles once per distinct tile grid
  (or once), not once per image size, and again only when the tile capacity or the scene's
  shapes change (densification; the texture stage's start and Eq. 7
  allocation; a growth event only when it overflows a texture bucket's headroom, see
  :mod:`patexgs_jax.textures.rebucket`). The runs of one process share their steps (a resumed run, a
  study's runs of one configuration, a notebook's second run take the executables an earlier run
  compiled); a run that leaves a layout in a process holding a quarter of its memory-map cap
  releases the programs of the layouts left behind. Near the
  kernel's memory-map cap the run releases all compiled code and, if that is not enough,
  checkpoints and stops with :class:`patexgs_jax.compiled.MapLimitReached` (resume with
  ``resume=True``).
"""

from __future__ import annotations

import collections
import dataclasses
import datetime
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import checkpoint as ckpt
from .. import compiled, interrupt, padding, progress
from .. import densify as dens
from ..adaptive import TextureScheduleState
from ..evaluation import camera_problem, image_problem
from ..optim import ages_per_slot, make_optimizer, upgrade_state
from ..render import Capacity, RenderConfig, count_pairs
from ..scene import Scene
from ..schedule import TextureSchedule, TrainState
from .compile_ahead import CompileAhead, layout_of, single_step_jit, step_args, step_identity
from .config import TrainConfig, config_dict, effective_config
from .progress import Estimate
from .step import STEP_TRACES, batch_step
from .step_cache import StepCache, StepEntry
from .strategies import Densification, SmoothingFilter

__all__ = ["STAGE1_DIR", "Trainer", "init_scene"]

#: Sub-folder of a run's checkpoints holding its end-of-2DGS-stage checkpoint (see Trainer.save_stage1).
STAGE1_DIR = "stage1"

#: Steps between two looks at the memory-map count (it is also read after every compile).
_MAP_CHECK_EVERY = 25


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
        self.lambda_normal = effective_config(config).lambda_normal
        self.render_cfgs = (config.render_config(stage=1), config.render_config(stage=2))
        # The position learning rate decays over the 2DGS stage for every method, so stage 1 is the
        # same run whatever the method (and can be shared: ``train(..., stage1=)``, see .run).
        self.lr = dataclasses.replace(config.lr, means_steps=config.iters_2dgs)
        self.optimizer = make_optimizer(self.radius, self.lr)
        # The step's learning rates and loss weights, passed to it (not compiled into it).
        self.hp = jax.device_put(step_args(self.radius, config))
        # How the views are padded and the tile capacity sized (TrainConfig.padding; batches have one size).
        self.pad = padding.TrainPadding(config.padding if config.batch_size == 1 else "per-size",
                                        [v.camera for v in self.train_views])
        self.capacity = None
        # The tile capacity before the scene last grew: a refit after densification never goes below
        # it (more Gaussians do not need fewer pairs; a smaller capacity would overflow and compile
        # the step again for every padded size).
        self.capacity_floor = None
        self.step = 0
        self.bad_streak = 0
        self.skipped = 0
        self.recompiles = 0
        self.compiled_at: list[int] = []  # steps whose program this process traced in the main thread
        self.compile_s = 0.0  # seconds those steps' calls took (tracing, compiling, dispatch)
        self.t_train = 0.0
        self.stage1_saved = False
        # With several processes (jax.distributed) only process 0 writes and prints progress.
        self.main = jax.process_index() == 0
        self.log_path = None if out_dir is None else out_dir / "log.jsonl"
        self.densification = Densification(config, self.radius)
        self.textures = TextureSchedule(config, self.optimizer, self.train_views, self.render_cfgs[1],
                                     log=self.log, say=self.say)
        self.strategies = (self.densification, SmoothingFilter(config, self.train_views),
                           self.textures)
        # The jitted steps of the current scene layout, per (render config, capacity), each with one
        # program per padded size; the single-view ones shared with the process's other runs.
        self.steps = StepCache(step_identity(config))
        self.saved_step = 0  # the newest checkpoint's step (0: the initial state, which is reproducible)
        self.t_start = time.perf_counter()
        self.estimate = Estimate(self)  # how long the run takes, from the steps that compiled nothing
        self.ahead = CompileAhead(self)  # the texture stage's first programs, compiled in the background

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
        return dict(scene=self.scene, opt_state=ages_per_slot(self.opt_state), stats=self.stats,
                    tex_sizes=None if tex is None else tex.sizes,
                    tex_counters=None if tex is None else np.array(
                        [tex.last_growth_step, tex.num_growth_events, tex.num_grown]),
                    # None (refit before the next step) after a densification that grew the scene: 0.
                    capacity=np.array([0 if self.capacity is None else self.capacity.pairs]),
                    capacity_floor=np.array([0 if self.capacity_floor is None else self.capacity_floor.pairs]),
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
        floor = int(tree["capacity_floor"][0]) if tree.get("capacity_floor") is not None else 0
        self.capacity_floor = Capacity(floor) if floor > 0 else None
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
                       claim: Callable[[tuple], Any] | None = None, shared: bool = False) -> StepEntry:
        """The jitted step for ``key`` at the scene's current layout (see :meth:`StepCache.get`)."""
        return self.steps.get(layout_of(self.scene), key, make, claim, shared)

    def stage_name(self, step: int | None = None) -> str:
        """``"2DGS"`` (``"3DGS"`` for 3D Gaussians) or ``"textured"``: which step ``step`` (default:
        the current one) runs."""
        step = self.step if step is None else step
        return self.spec.stage1_name if self.in_stage1(step) else "textured"

    def in_stage1(self, step: int) -> bool:
        """Whether step ``step`` trains as the first stage (every step of an untextured method)."""
        return step < self.cfg.iters_2dgs or self.spec.textures is None

    def announce_compile(self, what: str) -> None:
        """Marks the phase as a compile (the heartbeat then says how long it has taken)."""
        interrupt.set_phase(f"compiling the {self.stage_name()} step for {what}")
        interrupt.set_step(self.step, self.cfg.total_steps)

    def step_fn(self) -> Callable[..., Any]:
        """The training step as ``fn(scene, opt_state, stats, camera, image, active_sh, w_normal)``
        (``image`` (H, W, 3) of the camera's size). The view is padded on the host to its own tile
        grid or to the run's one size (:attr:`pad`), so the views of one padded size share a program."""
        if self.cfg.batch_size > 1:
            return self._batch_step_fn()
        cfg, render_cfg, capacity = self.cfg, self.render_cfg, self.capacity
        fn, buckets_seen, ahead_jobs = self._compiled_step(
            (render_cfg, capacity),
            lambda: single_step_jit(self.optimizer, render_cfg, capacity, cfg.lambda_dist > 0),
            claim=lambda layout: self.ahead.claim_step(render_cfg, capacity, layout), shared=True)

        def step(scene, opt_state, stats, camera, image, active_sh, w_normal):
            cam = self.pad.camera(camera, render_cfg.tile_size)
            if (cam.height, cam.width) not in buckets_seen:  # this call compiles (see StepCache.get)
                buckets_seen.add((cam.height, cam.width))
                job = ahead_jobs.pop((cam.height, cam.width), None)
                what = f"{cam.width}x{cam.height} px"
                if not self.ahead.take(job, f"the {self.stage_name()} step for {what}"):
                    self.announce_compile(what)
            img = padding.pad_image(image, cam.height, cam.width)
            hw = np.array([camera.height, camera.width], np.int32)
            return fn(scene, opt_state, stats, cam, img, hw, active_sh, w_normal, self.hp)

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
        distortion = cfg.lambda_dist > 0
        jitted, seen, _ = self._compiled_step((render_cfg, capacity, cfg.batch_size), lambda: jax.jit(
            lambda sc, st, stats, cams, imgs, sh, wn, hp: batch_step(
                sc, st, stats, cams, imgs, sh, wn, mesh=mesh, optimizer=self.optimizer,
                render_config=render_cfg, capacity=capacity, lambda_dssim=hp["lambda_dssim"],
                lambda_dist=hp["lambda_dist"] if distortion else 0.0, rates=hp["rates"]),
            out_shardings=parallel.replicated(mesh), donate_argnums=(0, 1, 2)))

        def fn(*args):
            if not seen:  # the first call compiles
                seen.add(())
                self.announce_compile(f"batches of {cfg.batch_size} views")
            return jitted(*args)

        if jax.process_count() == 1:
            return lambda *args: fn(*args, self.hp)

        def step(scene, opt_state, stats, cams, imgs, active_sh, w_normal):
            # Each process passes (and gets back) its own copy of the replicated state: see parallel.to_global.
            sc, st, stats, sh, wn, hp = parallel.to_global((scene, opt_state, stats, active_sh, w_normal, self.hp),
                                                           mesh)
            try:
                out = jax.block_until_ready(fn(sc, st, stats, cams, imgs, sh, wn, hp))
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
        # Counted at the step's padded size, on the view's own tiles (the step's count), one program a size.
        hw = None if self.cfg.batch_size > 1 else np.array([camera.height, camera.width], np.int32)
        camera = camera if self.cfg.batch_size > 1 else self.pad.camera(camera, self.render_cfg.tile_size)
        needed, _ = count_pairs(self.scene, camera, self.render_cfg, hw)
        # (None after the scene grew: the step compiles anyway, so the fit takes the full headroom)
        cap = self.pad.capacity(needed, minimum=self.capacity_floor, current=self.capacity)
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

        maps = self.map_guard.check(on_release=self.steps.clear)
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
                self.ahead.prepare_others()
        except interrupt.Interrupted:
            self.save_on_stop()
            raise
        finally:
            bar.close()
            self.ahead.cancel_unclaimed()

    def before_step(self, step):
        """Host-side work before the step that starts at ``step``: the stage-1 checkpoint, then the
        strategies (the texture stage's start and Eq. 7 allocation)."""
        if step == self.cfg.iters_2dgs and self.scene.rgb is None and not self.stage1_saved:
            self.save_stage1()
            self.ahead.prepare_others()
        if self.textures.allocates_at(self.state, step):
            self.textures.programs = self.ahead.claim_eq7()
        for strategy in self.strategies:
            self.state = strategy.before_step(self.state, step)
        if step == self.cfg.iters_2dgs and self.scene.rgb is not None:
            self.ahead.predict_own_allocation()

    def after_step(self, step):
        """Host-side work between steps (``step`` counts completed steps, from 1): the strategies,
        then (stage 1) a tile-capacity refit every 100 steps."""
        capacity = self.scene.capacity
        for strategy in self.strategies:
            self.state = strategy.after_step(self.state, step)
        if self.scene.capacity != capacity:  # the scene's shapes changed: refit before the next step
            self.capacity_floor, self.capacity = self.capacity or self.capacity_floor, None
        if self.refits_at(step):
            self.fit_capacity(self.view(step).camera)
        self.ahead.after_step(step)

    def refits_at(self, step: int) -> bool:
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
            # Mappings grow only when something compiles (a new padded size, capacity or layout); reading
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
                # (effective_config: no normal loss for 3D Gaussians, which have no surface normal)
                w_normal = jnp.float32(self.lambda_normal if step >= cfg.normal_from else 0.0)
                data = ((view.camera, image) if cfg.batch_size == 1
                        else self.batch_inputs(views, images))
                scene, opt_state, stats, m = fn(self.scene, self.opt_state, self.stats, *data, active_sh, w_normal)
                self.scene, self.opt_state, self.stats = scene, opt_state, stats
                if self.ahead.took:  # (its mappings are new; its time is not a step's)
                    self.ahead.took, compiled_last = False, True
                    interrupt.set_phase(f"training the {self.stage_name(step)} stage")
                if sum(STEP_TRACES.values()) > traces:
                    self.compile_s += time.perf_counter() - t0  # (compiling is synchronous; the step is not)
                    self.recompiles += 1
                    self.compiled_at.append(step)
                    compiled_last = True
                    interrupt.set_phase(f"training the {self.stage_name(step)} stage")
                if bool(m["overflow"]) and np.isfinite(float(m["pairs_needed"])):
                    old = self.capacity
                    self.capacity = self.pad.capacity(m["pairs_needed"], current=old)
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
                    self.estimate.measure(step, seconds)
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
