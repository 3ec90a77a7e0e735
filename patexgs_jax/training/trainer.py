"""The host loop of a run (:class:`Trainer`): views, the jitted step, strategies, checkpoints.

Each step: the strategies' ``before_step`` (:mod:`.strategies`: densification, the 3D filter, the
tile capacity's refits; the texture stage, :mod:`patexgs_jax.schedule`; compile-ahead,
:mod:`.compile_ahead`), the step the provider runs and times (:mod:`.steps`: the tile capacity,
which compiled program runs, compile counts, the memory-map guard, the time estimate's clean
steps), a retry at a grown tile capacity on overflow or a skipped update on a non-finite loss or
gradient (never applied; ``max_bad_steps`` in a row stop the run), the strategies' ``after_step``,
the log line and the checkpoint. The data order is a per-epoch permutation
seeded by (seed, epoch) and every random choice is seeded by (seed, step), so ``resume`` reaches the
same result as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .. import checkpoint as ckpt
from .. import densify as dens
from .. import interrupt, memory_maps, padding, parallel, progress
from ..adaptive import TextureScheduleState
from ..checkpoint_writer import CheckpointWriter
from ..evaluation import camera_problem, image_problem
from ..optim import ages_per_slot, make_optimizer, step_rates, upgrade_state
from ..render import Capacity, RenderConfig
from ..schedule import TextureSchedule, TrainState
from .compile_ahead import CompileAhead
from .config import TrainConfig, config_dict
from .estimate import Estimate, StepWindow
from .steps import StepProvider, TileCapacity, layout_of
from .strategies import Densification, SmoothingFilter, Strategy, TileRefit, init_scene

__all__ = ["STAGE1_DIR", "Trainer", "init_scene"]

#: Sub-folder of a run's checkpoints holding its end-of-2DGS-stage checkpoint (see Trainer.save_stage1).
STAGE1_DIR = "stage1"


class Trainer:
    """The mutable host-side state of one run (everything a checkpoint holds) and its loop.

    ``scene``, ``opt_state`` and ``stats`` (together :attr:`state`) are what the jitted step updates;
    :attr:`strategies` (densification, the 3D filter, the texture stage, then :attr:`ahead`, which
    compiles the texture stage's first programs in the background) rewrite them between steps;
    :attr:`steps` (a :class:`~.steps.StepProvider`) runs the step at the tile capacity of
    :attr:`tiles`.
    """

    def __init__(self, dataset, config: TrainConfig, out_dir: Path | None, verbose: bool,
                 map_guard: memory_maps.MapGuard | None = None):
        self.ds, self.cfg, self.out, self.verbose = dataset, config, out_dir, verbose
        # With several processes (jax.distributed) only process 0 writes and prints progress.
        self.main = jax.process_index() == 0
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
        rates = step_rates(self.lr, self.radius)  # (the step's arguments: one program serves every scene)
        # How the views are padded and the tile capacity sized (TrainConfig.padding; batches have one size).
        self.pad = padding.TrainPadding(config.padding if config.batch_size == 1 else "per-size",
                                        [v.camera for v in self.train_views])
        self.tiles = TileCapacity(self.pad)
        self.step = 0
        self.bad_streak = 0
        self.skipped = 0
        self.t_train = 0.0
        self.stage1_saved = False
        self.log_path = None if out_dir is None else out_dir / "log.jsonl"
        self.ahead = CompileAhead(config, self.optimizer, self.train_views, self.pad, self.tiles, say=self.say)
        self.estimate = Estimate(config, self.train_views, float(getattr(dataset, "factor", 1.0) or 1.0), self.say)
        self.steps = StepProvider(config, self.optimizer, rates, self.pad, self.tiles, ahead=self.ahead,
                                  times=self.estimate, say=self.say,
                                  map_guard=map_guard if map_guard is not None else memory_maps.MapGuard(),
                                  on_map_limit=self.stop_at_map_limit)
        # The positions in each batch of the views this process loads (all of them with one process).
        self.share = self.steps.batch_share() if config.batch_size > 1 else range(1)
        self.densification, smoothing = Densification(config, self.radius), SmoothingFilter(config, self.train_views)
        refit = TileRefit(config, self.tiles, self.train_views, self.render_cfgs)
        self.textures = TextureSchedule(config, self.optimizer, self.train_views, self.render_cfgs[1],
                                        log=self.log, say=self.say, programs=self.ahead.claim_eq7)
        # (compiling ahead last: it looks at the state and the tile capacity the others made)
        self.strategies: tuple[Strategy, ...] = (self.densification, smoothing, self.textures, refit, self.ahead)
        self.saved_step = 0  # the newest checkpoint's step (0: the initial state, which is reproducible)
        self.writer = CheckpointWriter()  # checkpoints written off the training thread, one at a time
        self.t_start = time.perf_counter()

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
        self.scene = init_scene(self.ds.points, self.ds.colors, self.cfg)
        self.opt_state = self.optimizer.init(self.scene)  # pyright: ignore[reportArgumentType]  (a Scene is a pytree)
        self.stats = dens.DensifyStats.zeros(self.scene.capacity)

    def state_tree(self):
        tex = self.textures.state
        return dict(scene=self.scene, opt_state=ages_per_slot(self.opt_state), stats=self.stats,
                    tex_sizes=None if tex is None else tex.sizes,
                    tex_counters=None if tex is None else np.array(
                        [tex.last_growth_step, tex.num_growth_events, tex.num_grown]),
                    # None (refit before the next step) after a densification that grew the scene: 0.
                    capacity=np.array([0 if self.tiles.current is None else self.tiles.current.pairs]),
                    capacity_floor=np.array([0 if self.tiles.floor is None else self.tiles.floor.pairs]),
                    counters=np.array([self.step, self.skipped, self.steps.compiles.count]),
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
        self.tiles.current = Capacity(int(tree["capacity"][0])) if int(tree["capacity"][0]) > 0 else None
        floor = int(tree["capacity_floor"][0]) if tree.get("capacity_floor") is not None else 0
        self.tiles.floor = Capacity(floor) if floor > 0 else None
        self.step, self.skipped, self.steps.compiles.count = (int(v) for v in tree["counters"])
        self.t_train = float(tree["t_train"])

    def save(self):
        """Writes a checkpoint (process 0); with several processes, first checks that every process
        holds the same state (the replicated state must never diverge), then waits until it is written."""
        if self.out is None:
            return
        tree = self.state_tree()
        several = jax.process_count() > 1
        if several:
            same = {k: v for k, v in tree.items() if k != "t_train"}  # (wall-clock time differs between processes)
            parallel.check_same(f"the training state at step {self.step} (a checksum of every array; the host-side "
                                "work must give the same result on every process)",
                                [self.step, parallel.tree_checksum(same)])
        step = self.step
        if self.main:  # (the stop message names it once it is on disk)
            self.writer.save(ckpt.checkpoint_path(self.out / "checkpoints", step), tree, dict(
                config=config_dict(self.cfg), step=step), keep=2, on_written=lambda _: self.note_saved(step))
        else:
            self.note_saved(step)
        self.saved_step = step  # (now: save_on_stop's age of the newest checkpoint counts the one being written)
        if several:  # the others wait until it is written (a study reads it next)
            self.writer.wait()
            parallel.check_same(f"the checkpoint of step {self.step} being written", [self.step])

    def note_saved(self, step: int) -> None:
        """Records that the checkpoint of ``step`` (written or loaded) holds the run's work."""
        self.saved_step = step
        if self.out is not None:
            interrupt.set_saved(f"the checkpoint of step {step} in {self.out / 'checkpoints'}")

    def save_on_stop(self) -> None:
        """On a stop signal between steps: a checkpoint, unless the newest is at most
        ``checkpoint_on_stop`` steps old, the run is in a non-finite streak (the last good one stays)
        or it runs in several processes (a save is collective, and the others may stop at another
        step; the periodic checkpoints hold the work)."""
        if self.out is None or self.bad_streak or self.step - self.saved_step <= self.cfg.checkpoint_on_stop:
            return
        if jax.process_count() == 1:
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
            self.writer.save(ckpt.checkpoint_path(self.out / "checkpoints" / STAGE1_DIR, self.step),
                             self.state_tree(), meta, keep=1)
            self.writer.wait()  # (another method of this process may start from it next)

    def stop_at_map_limit(self, maps: tuple[int, int] | None, other: int | None) -> None:
        """Near the memory-map cap even after releasing compiled code (``maps``: this process's
        count and cap; ``other``: the process that hit it): saves a checkpoint and raises
        :class:`memory_maps.MapLimitReached` (a clear stop, not a crash in XLA)."""
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
            raise memory_maps.MapLimitReached(f"process {other} of this run neared its memory-map cap, so every "
                                              f"process stops. {what}")
        raise memory_maps.MapLimitReached(memory_maps.limit_message(maps[0], maps[1], what))

    # -- helpers ---------------------------------------------------------------------------------
    def view(self, step, seed: int | None = None):
        """The training view of ``step`` (:meth:`TrainConfig.view_index`)."""
        return self.train_views[self.cfg.view_index(step, len(self.train_views), seed)]

    def step_fn(self) -> Callable[..., Any]:
        """The training step of the current scene, stage and capacity (:meth:`.steps.StepProvider.get`)."""
        return self.steps.get(layout_of(self.scene), self.render_cfg, self.tiles.current)

    def data_mesh(self):
        """The device mesh of the data-parallel step (``batch_size`` > 1)."""
        return self.steps.data_mesh()

    def say(self, msg):
        if self.verbose and self.main:
            progress.say(msg)

    def log(self, record):
        """Appends ``record`` to ``log.jsonl`` with its wall-clock time (UTC, ISO 8601) and the
        seconds since this process started the run."""
        if self.log_path is not None and self.main:
            now = datetime.datetime.now(datetime.UTC)
            record = dict(record, time=now.isoformat(timespec="milliseconds").replace("+00:00", "Z"),
                          elapsed_s=round(time.perf_counter() - self.t_start, 3))
            with open(self.log_path, "a") as f:
                f.write(json.dumps(record) + "\n")

    # -- main loop -------------------------------------------------------------------------------
    def before_step(self, step):
        """Host-side work before the step that starts at ``step``: the stage-1 checkpoint, then the
        strategies (the texture stage's start and Eq. 7 allocation)."""
        if step == self.cfg.iters_2dgs and self.scene.rgb is None and not self.stage1_saved:
            self.save_stage1()
        for strategy in self.strategies:
            self.state = strategy.before_step(self.state, step)

    def after_step(self, step):
        """Host-side work between steps (``step`` counts completed steps, from 1): the strategies."""
        for strategy in self.strategies:
            self.state = strategy.after_step(self.state, step)

    def _views(self, step):
        """The batch of ``step``: its views, images (None where another process loads them) and each
        view's problem (None for a usable view)."""
        cfg = self.cfg
        # Step s takes views s B .. s B + B - 1 of the stream of per-epoch permutations.
        views = [self.view(step * cfg.batch_size + j) for j in range(cfg.batch_size)]
        # Each process loads only its share of the batch (all of it with one process); the
        # cameras, known to every process, are checked everywhere.
        share = self.share
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

    def skip(self, step: int, view, problem: str) -> None:
        """A step whose update is skipped (never applied); it still counts, and its scheduled host-side
        work, log line and checkpoint happen as usual. Too many in a row stop the run."""
        self.bad_streak += 1
        self.skipped += 1
        self.say(f"[step {step}] view {view.name!r}: {problem}; update skipped")
        if self.bad_streak >= self.cfg.max_bad_steps:
            raise FloatingPointError(f"{self.bad_streak} consecutive non-finite steps up to step {step}; stopping. "
                                     "The last good checkpoint is kept in the output directory.")

    def run(self):
        """Trains to ``cfg.total_steps``. On a stop signal (:mod:`patexgs_jax.interrupt`) it stops
        between two steps, writes a checkpoint if the newest is too old (:meth:`save_on_stop`) and
        raises :class:`~patexgs_jax.interrupt.Interrupted`."""
        cfg, total = self.cfg, self.cfg.total_steps
        window = StepWindow(cfg.log_every)
        with self._session() as bar:
            while self.step < total:
                step = self.step
                self.steps.begin(step)  # (a stop signal, the heartbeat, the memory-map guard)
                self.before_step(step)
                views, images, problems = self._views(step)
                bad = next((i for i, p in enumerate(problems) if p is not None), 0)
                problem, m, seconds = problems[bad], None, 0.0
                if problem is None:
                    self.state, m, seconds = self.steps.run(self.state, step, views, images, self.render_cfg)
                    if m is None:  # the tile capacity overflowed: it has grown, and the step runs again
                        continue
                    if not bool(m["ok"]):
                        bad_groups = [k for k, v in m["finite"].items() if not bool(v)]
                        problem = f"non-finite loss or gradient (groups: {bad_groups or ['loss']})"
                if problem is not None or m is None:
                    self.skip(step, views[bad], str(problem))
                else:
                    self.bad_streak = 0
                    self.t_train += seconds
                    window.add(m)
                self.step += 1
                interrupt.set_step(self.step, total)
                bar.update(1)
                self.after_step(step + 1)
                if self.step % cfg.log_every == 0 or self.step == total:
                    self.log_progress(window, bar)
                if (self.step % cfg.checkpoint_every == 0 or self.step == total) and self.bad_streak == 0:
                    self.save()  # (not during a non-finite streak: the last good checkpoint stays the newest)

    @contextlib.contextmanager
    def _session(self) -> Iterator[Any]:
        """The loop's progress bar; on a stop signal, the checkpoint :meth:`save_on_stop` calls for;
        at the end, the programs compiled ahead for nothing cancelled and every checkpoint on disk
        (before the caller reads one or the process ends)."""
        bar = progress.bar(self.cfg.total_steps, f"train {self.cfg.method}", initial=self.step,
                           show=self.verbose and self.main)
        try:
            yield bar
        except interrupt.Interrupted:
            self.save_on_stop()
            raise
        finally:
            bar.close()
            self.ahead.cancel_unclaimed()
            self.writer.release()

    def log_progress(self, window: StepWindow, bar) -> None:
        """The progress line and ``log.jsonl`` record of the steps since the last one."""
        loss, psnr, ms = window.take()
        rec = dict(step=self.step, loss=loss, psnr=psnr, gaussians=self.scene.num_active(),
                   texels=sum(self.scene.texel_count().values()), ms_per_step=ms,
                   recompiles=self.steps.compiles.count, skipped=self.skipped)
        self.log(rec)
        bar.set_postfix(psnr=f"{psnr:.2f}", gaussians=rec["gaussians"], refresh=False)
        self.say(f"step {self.step:6d}/{self.cfg.total_steps}  loss {loss:.4f}  psnr {psnr:6.2f}  "
                 f"gaussians {rec['gaussians']:7d}  texels {rec['texels']:8d}  {ms:7.1f} ms/step")
