"""Compiling ahead: a texture stage's first programs compiled on the background thread
(:mod:`patexgs_jax.background`) before the run needs them, so the stage's first steps do not wait.

From the end of the 2DGS stage (this run's texture stage, or that of a run that starts from this
run's stage-1 checkpoint in this process, ``train(..., prepare=)``): the textured step for the
warm-up's layout at the padded size of the stage's first view, at the tile capacity the first step
will fit; for Eq. 7 methods, the allocation's pair counter and renderer, and the textured step for
the layout a speculative Eq. 7 allocation gives on the warm-up's first state (the real one, 40 steps
later, usually falls in the same power-of-two buckets). A prediction that does not match what the
run needs is never used, so results never depend on it. :class:`CompileAhead` is the run's last
strategy (:class:`.strategies.Strategy`: it looks at the state the others made, and reads the tile
capacity that the provider and the refit strategy keep), and a listener the step provider asks (``claim_step``,
``take``), as the texture schedule does (``claim_eq7``); the trainer calls ``cancel_unclaimed`` at
the run's end. ``PATEXGS_COMPILE_AHEAD=0`` turns it off.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import background, interrupt, padding
from ..adaptive import ContributionCounts
from ..render import Capacity, RenderConfig, count_pairs
from ..scene import Scene
from ..schedule import TEXTURE_HEADROOM, TEXTURE_MIN_SPARE, TextureSchedule, TrainState
from ..textures.rebucket import resize_textures
from .config import TrainConfig, effective_config
from .steps import (
    PROCESS,
    ProcessPrograms,
    StepEntry,
    TileCapacity,
    layout_of,
    refits_at,
    single_step_jit,
    step_identity,
    step_image_args,
)

__all__ = ["MAX_PREPARED", "CompileAhead", "Prepared"]


def owned_copy(tree):
    """A copy of ``tree``'s device arrays that a background job owns (the next step donates the
    originals)."""
    return jax.tree_util.tree_map(lambda x: jnp.copy(x) if isinstance(x, jax.Array) else x, tree)


@dataclasses.dataclass(eq=False)
class Prepared:
    """Programs being compiled ahead for a layout not reached yet (:meth:`CompileAhead.prepare`).
    ``capacity`` and ``fn`` (the jitted step) are set by the background job; ``layout`` is None while
    a predicted allocation is counted (``counted`` is set once it is known); ``then``: the allocation
    predicted from this warm-up state; ``registry``: the list of prepared entries it is in."""

    identity: tuple
    render_cfg: RenderConfig
    layout: tuple | None
    padded: tuple[int, int]  # (height, width) of the padded size it is compiled for
    owner: int  # id() of the CompileAhead whose own stage 2 it is (0: made for another run)
    registry: list
    step_job: background.Job | None = None
    eq7_job: background.Job | None = None
    capacity: Capacity | None = None
    fn: Any = None
    counted: threading.Event = dataclasses.field(default_factory=threading.Event)
    then: Prepared | None = None

    def cancel(self) -> None:
        for job in (self.step_job, self.eq7_job):
            if job is not None:
                job.cancel()
        if self.then is not None:
            self.then.cancel()
            self.then.drop()

    def drop(self) -> None:
        """Leaves the registry (no run will claim it)."""
        with contextlib.suppress(ValueError):
            self.registry.remove(self)


#: Prepared entries kept at most (the oldest are dropped first).
MAX_PREPARED = 4


class CompileAhead:
    """The compile-ahead work of one run (see the module's docstring). ``shared``: the process's
    programs, whose ``prepared`` list holds the entries no run claimed yet; ``tiles``: the run's tile
    capacity; ``prepare_for``: configs
    of the runs that start from this run's stage-1 checkpoint; ``outcomes``: each program this run
    needed and found compiled ahead (``hit``) or not (``why``), summary.json's ``compile_ahead``."""

    def __init__(self, config: TrainConfig, optimizer, train_views, pad: padding.TrainPadding, tiles: TileCapacity,
                 *, say: Callable[[str], None], shared: ProcessPrograms = PROCESS):
        self.cfg, self.optimizer, self.train_views, self.pad, self.say = config, optimizer, train_views, pad, say
        self.tiles = tiles
        self.prepared = shared.prepared
        self.shared = shared
        self.prepare_for: tuple[TrainConfig, ...] = ()
        self.outcomes: list[dict] = []
        self._prepared_own: Capacity | None = None  # the capacity this run's own step was prepared for
        self._last_densify = max(effective_config(config).densify.densify_steps(config.iters_2dgs), default=0)

    def before_step(self, state: TrainState, step: int) -> TrainState:
        """At the texture stage's start: the speculative allocation from its first state
        (:meth:`predict_own_allocation`); an untextured run resumed there prepares the runs that
        start from its stage-1 checkpoint (:meth:`prepare_others`)."""
        if step == self.cfg.iters_2dgs:
            if state.scene.rgb is None:
                self.prepare_others(state)
            else:
                self.predict_own_allocation(state, self.tiles.current)
        return state

    def after_step(self, state: TrainState, step: int) -> TrainState:
        """At the end of the 2DGS stage, the runs that start from its state are prepared
        (:meth:`prepare_others`). Before it, once densification has stopped, the texture stage's
        first layout is known: its step is compiled ahead, and again when the tile capacity changes
        (the step's program depends on the shapes and the capacity only, so a refit that keeps the
        capacity would compile the same programs again beside the run's own steps)."""
        capacity = self.tiles.current
        if step == self.cfg.iters_2dgs and state.scene.rgb is None:
            self.prepare_others(state)
        elif (self._last_densify < step < self.cfg.iters_2dgs and state.scene.rgb is None
              and capacity is not None and capacity != self._prepared_own):
            self._prepared_own = capacity
            # (its allocation is predicted at the stage's start, from the warm-up's actual state)
            self.prepare(self.cfg, state, capacity, predict_allocation=False)
        return state

    def cancel_unclaimed(self) -> None:
        """At the run's end: the entries made for it and never claimed are not needed."""
        for p in [p for p in self.prepared if p.owner == id(self)]:
            p.cancel()
            p.drop()  # (cancelling an entry drops its ``then``)

    def prepare(self, config: TrainConfig, state: TrainState, capacity: Capacity | None,
                predict_allocation: bool = True) -> None:
        """Starts compiling ahead the first programs of ``config``'s texture stage (this run's, or
        one that starts from this run's stage-1 checkpoint) from this run's ``state`` at tile
        capacity ``capacity`` (see the module's docstring; the allocation's step with
        ``predict_allocation``). The warm-up's layout is exact once densification has stopped; the
        capacities are predicted from the current scene. Nothing for 2DGS, batches or several
        processes, or when compiling ahead is off."""
        if (not background.enabled() or config.spec.textures is None or config.batch_size != 1
                or config.iters_2dgs != self.cfg.iters_2dgs or config.total_steps <= config.iters_2dgs
                or jax.process_count() > 1):
            return
        own = config is self.cfg
        identity = step_identity(config)
        optimizer = self.optimizer  # (its structure only: another run's learning rates are its step's arguments)
        render_cfg = config.render_config(stage=2)
        stage = TextureSchedule(config, optimizer, self.train_views, render_cfg)
        scene, opt_state, stats = owned_copy(tuple(stage.start(state)))
        view = self.train_views[config.view_index(config.iters_2dgs, len(self.train_views))]
        pad = self._pad(config)
        cam = pad.camera(view.camera, render_cfg.tile_size)
        hw = np.array([view.camera.height, view.camera.width], np.int32)
        layout = layout_of(scene)
        same = [p for p in self.prepared if (p.identity, p.render_cfg, p.layout) == (identity, render_cfg, layout)]
        if same and not own:
            return  # (another run the study trains next has the same first programs: prepared once)
        for old in same:
            old.cancel()  # superseded (a capacity refit since)
            old.drop()
        prep = Prepared(identity, render_cfg, layout, (cam.height, cam.width), 0 if not own else id(self),
                        self.prepared)
        # The stage's first step fits the capacity (pad.headroom x its view's pairs) from none (a run started
        # from a stage-1 checkpoint), or this run keeps its own (refitted up at the stage's start
        # when a refit falls there).
        minimum = capacity if own else None
        keep = own and not refits_at(self.cfg, config.iters_2dgs, capacity)
        args = step_image_args(cam)

        def compile_step():
            done = False
            try:
                if keep:
                    capacity = minimum
                else:  # (its own program: the main thread releases the shared jitted ones at will)
                    counter = count_pairs.lower(scene, cam, config=render_cfg, valid_hw=hw).compile()
                    needed, _ = counter(scene, cam, valid_hw=hw)
                    capacity = pad.capacity(needed, current=minimum)  # (as the run's refit)
                done = self._take_step(prep, config, capacity)
            finally:
                prep.counted.set()
            if not done:
                prep.fn.lower(scene, opt_state, stats, cam, *args).compile()

        def compile_eq7():  # (as TextureSchedule.allocate's ViewRenderer pads and counts the views)
            return padding.ViewRenderer(scene, render_cfg).compile([v.camera for v in self.train_views])

        whose = "" if own else f" of {config.method}"
        prep.step_job = background.submit(f"the textured step{whose} for {cam.width}x{cam.height} px", compile_step,
                                     self.say)
        if config.spec.textures == "adaptive" and config.warmup_tex < config.iters_tex:
            prep.eq7_job = background.submit(f"Eq. 7's pair counter and renderer{whose}", compile_eq7, self.say)
        if prep.step_job is None:
            return
        self.prepared.append(prep)
        if predict_allocation and prep.eq7_job is not None:
            def prepared_capacity():
                prep.counted.wait()
                return prep.capacity

            prep.then = self._predict_allocation(config, stage, identity, (scene, opt_state, stats),
                                                 prep.eq7_job, prepared_capacity, prep.owner, whose)
        while len(self.prepared) > MAX_PREPARED:
            self.prepared.pop(0).cancel()

    def _predict_allocation(self, config: TrainConfig, stage: TextureSchedule, identity: tuple, state: tuple,
                            eq7_job: background.Job, capacity: Callable[[], Capacity | None], owner: int,
                            whose: str = "") -> Prepared | None:
        """Queues a speculative Eq. 7 allocation of ``config`` on ``state`` (arrays the background
        owns, at the warm-up's layout), counted with ``eq7_job``'s programs, and the compile of the
        step for the layout it gives at tile capacity ``capacity()``; returns its entry (None when
        compiling ahead is off)."""
        render_cfg = config.render_config(stage=2)
        scene, opt_state, stats = state
        view = self.train_views[config.view_index(config.iters_2dgs + config.warmup_tex, len(self.train_views))]
        cam = self._pad(config).camera(view.camera, render_cfg.tile_size)
        alloc = Prepared(identity, render_cfg, None, (cam.height, cam.width), owner, self.prepared)
        args = step_image_args(cam)
        views = self.train_views

        def compile_allocation():
            done = False
            try:
                cap = capacity()
                if not eq7_job.ok or cap is None:
                    return
                # As TextureSchedule.allocate counts, with the programs compiled for this layout; not
                # released after (the main thread's Eq. 7 shares them).
                renderer = padding.ViewRenderer(scene, render_cfg, programs=eq7_job.value)
                renderer.prepare([v.camera for v in views])
                counts = ContributionCounts.from_views(
                    (np.asarray(renderer(v.camera).max_contrib_count) for v in views), scene.capacity)
                sides, _, _ = stage.allocation_sides(counts, np.asarray(scene.active) > 0)
                new_scene, new_opt, _ = resize_textures(scene, opt_state, sides, sides, headroom=TEXTURE_HEADROOM,
                                                        min_spare=TEXTURE_MIN_SPARE)
                alloc.layout = layout_of(new_scene)
                done = self._take_step(alloc, config, cap)
            finally:
                alloc.counted.set()
            if not done:
                alloc.fn.lower(new_scene, new_opt, stats, cam, *args).compile()

        alloc.step_job = background.submit(f"the textured step{whose} for Eq. 7's predicted layout", compile_allocation,
                                      self.say)
        if alloc.step_job is None:
            return None
        self.prepared.append(alloc)
        return alloc

    def _take_step(self, entry: Prepared, config: TrainConfig, capacity: Capacity | None) -> bool:
        """Sets ``entry``'s capacity and jitted step; True where an earlier run of this process has
        compiled that step for ``entry``'s padded size (the run takes it from there), else the
        caller compiles it."""
        entry.capacity = capacity
        done = self.shared.step(entry.identity, (entry.render_cfg, capacity), entry.layout, entry.padded)
        entry.fn = done or single_step_jit(self.optimizer, entry.render_cfg, capacity, config.lambda_dist > 0)
        return done is not None

    def predict_own_allocation(self, state: TrainState, capacity: Capacity | None) -> None:
        """At the texture stage's start of a run through both stages: the speculative allocation (see
        :meth:`_predict_allocation`) from the warm-up's actual first ``state``, with Eq. 7's
        programs compiled ahead for this layout (:meth:`prepare`)."""
        cfg = self.cfg
        if (not background.enabled() or cfg.spec.textures != "adaptive" or cfg.batch_size != 1
                or cfg.warmup_tex >= cfg.iters_tex or jax.process_count() > 1 or capacity is None):
            return
        render_cfg = cfg.render_config(stage=2)
        prep = self._find(render_cfg, layout_of(state.scene))
        if prep is None or prep.eq7_job is None or prep.then is not None or prep.eq7_job.cancelled:
            return
        stage = TextureSchedule(cfg, self.optimizer, self.train_views, render_cfg)
        prep.then = self._predict_allocation(cfg, stage, step_identity(cfg), owned_copy(tuple(state)),
                                             prep.eq7_job, lambda: capacity, id(self))

    def prepare_others(self, state: TrainState) -> None:
        """At the end of the 2DGS stage: the first programs of the runs that start from ``state``
        (``train(..., prepare=)``), once."""
        for i, other in enumerate(self.prepare_for):
            if len(self.prepared) >= MAX_PREPARED:
                break  # (entries for runs further on would push out those of the runs trained first)
            # The allocation's step too, where its entry leaves room (a run's warm-up step and its
            # allocation are two entries): the next run's always, later runs' while there is room.
            self.prepare(other, state, None, predict_allocation=i == 0 or len(self.prepared) + 2 <= MAX_PREPARED)
        self.prepare_for = ()

    def _pad(self, config: TrainConfig) -> padding.TrainPadding:
        """The training padding of ``config`` (this run's, or another run's on the same views)."""
        if config.padding == self.cfg.padding:
            return self.pad
        return padding.TrainPadding(config.padding, [v.camera for v in self.train_views])

    def _find(self, render_cfg: RenderConfig, layout: tuple) -> Prepared | None:
        identity = step_identity(self.cfg)
        return next((p for p in self.prepared if p.identity == identity and p.render_cfg == render_cfg
                     and p.layout == layout), None)

    def record(self, step: int, program: str, hit: bool, why: str = "") -> None:
        """Notes whether ``program``, needed at ``step``, had been compiled ahead; for a miss,
        ``why`` not."""
        entry: dict[str, Any] = dict(step=step, program=program, hit=hit)
        if not hit:
            entry["why"] = why
        self.outcomes.append(entry)

    def summary(self) -> dict:
        """summary.json's ``compile_ahead``: hits, misses and each outcome (:meth:`record`)."""
        hits = sum(o["hit"] for o in self.outcomes)
        return dict(hits=hits, misses=len(self.outcomes) - hits, outcomes=list(self.outcomes))

    def _predicted(self, render_cfg: RenderConfig) -> bool:
        """Whether a step of this run's settings and ``render_cfg`` was compiled ahead for any layout."""
        identity = step_identity(self.cfg)
        return any(p.identity == identity and p.render_cfg == render_cfg for p in self.prepared)

    def claim_step(self, render_cfg: RenderConfig, capacity, layout: tuple, step: int) -> StepEntry | None:
        """The step prepared ahead for this render config, capacity and layout, if any (see
        :meth:`prepare`), as the provider keeps it; a job not started yet is cancelled (compiling
        here is sooner). Where a step was prepared for this run's settings, a miss is recorded here
        (:meth:`record`), a hit when the step first runs (:meth:`take`)."""
        if self.cfg.batch_size != 1:
            return None
        predicted = self._predicted(render_cfg)
        prep = self._find(render_cfg, layout)
        if prep is None:
            self._settle_predictions(render_cfg, step)
            prep = self._find(render_cfg, layout)
        what = "the textured step"
        if prep is None or prep.step_job is None:
            if predicted:
                self.record(step, what, False, "compiled ahead for another texture layout")
                self._one_compile_at_a_time(step)
            return None
        job = prep.step_job
        if job.cancel() or job.cancelled:
            prep.drop()
            prep.cancel()
            self.record(step, what, False, "its background compile had not started")
            return None
        prep.counted.wait()  # (the capacity is counted first, in seconds)
        if prep.capacity != capacity or prep.fn is None:
            self.record(step, what, False, f"compiled ahead for tile capacity {prep.capacity}, the run uses {capacity}"
                        if prep.fn is not None else "its background compile failed")
            self._one_compile_at_a_time(step)
            return None  # (a capacity the run does not use; Eq. 7's programs may still serve)
        prep.owner = id(self)
        if prep.then is not None:
            prep.then.owner = id(self)
        if prep.eq7_job is None:
            prep.drop()
        return StepEntry(prep.fn, set(), {prep.padded: prep.step_job})

    def _one_compile_at_a_time(self, step: int) -> None:
        """On a CPU, where the main thread is about to compile a textured step this run's compile
        ahead did not predict: waits for that prediction's compile if it is still running, so that
        the process compiles one textured step at a time: the peak the plan and the memory check count
        holds one such compile (two at once, measured in docs/performance.md, hold far more). A GPU
        run does not wait (the compiles' memory is the host's, not the device's)."""
        if jax.default_backend() != "cpu":
            return
        identity = step_identity(self.cfg)
        for p in self.prepared:
            job = p.step_job
            if p.identity == identity and job is not None and job.running:
                interrupt.set_phase(f"waiting for the background compile of {job.what}")
                interrupt.set_step(step, self.cfg.total_steps)
                self.say(f"[compile ahead] waiting for {job.what} ({time.monotonic() - (job.started or 0):.0f} s "
                         "into its compile; not used) before compiling the textured step here: one compile at a "
                         "time")
                job.wait(poll=interrupt.check)

    def _settle_predictions(self, render_cfg: RenderConfig, step: int) -> None:
        """Waits for the predicted allocations being counted in the background for this run's settings
        (their layout is known within seconds); drops those not started or failed."""
        identity = step_identity(self.cfg)
        for p in [p for p in self.prepared
                  if p.layout is None and p.identity == identity and p.render_cfg == render_cfg]:
            job = p.step_job
            if job is not None and not job.cancel() and not job.cancelled and not p.counted.is_set():
                interrupt.set_phase("waiting for the background count of Eq. 7's predicted layout")
                interrupt.set_step(step, self.cfg.total_steps)
                while not p.counted.wait(0.2):
                    interrupt.check()
            if p.layout is None:
                p.drop()

    def claim_eq7(self, scene: Scene, step: int) -> dict | None:
        """Eq. 7's programs prepared ahead for ``scene``'s layout (see :meth:`prepare`), waiting for
        them if they are being compiled; None if there are none. What the texture schedule's
        allocation at ``step`` renders with (:class:`patexgs_jax.padding.ViewRenderer`)."""
        render_cfg = self.cfg.render_config(stage=2)
        predicted = self._predicted(render_cfg)
        prep = self._find(render_cfg, layout_of(scene))
        what = "Eq. 7's pair counter and renderer"
        if prep is None or prep.eq7_job is None:
            if predicted:
                self.record(step, what, False, "compiled ahead for another texture layout")
            return None
        prep.drop()
        return prep.eq7_job.value if self.take(prep.eq7_job, what, step) else None

    def take(self, job: background.Job | None, what: str, step: int) -> bool:
        """Whether ``what``, needed at ``step``, was compiled ahead by ``job`` (waited for if still
        compiling; a stop signal still stops the run); False (the caller compiles it) if the job
        failed or had not started."""
        if job is None:
            return False
        if job.cancel():
            self.record(step, what, False, "its background compile had not started")
            return False
        if not job.done:
            interrupt.set_phase(f"waiting for the background compile of {job.what}")
            interrupt.set_step(step, self.cfg.total_steps)
            self.say(f"[compile ahead] waiting for {job.what} ({time.monotonic() - (job.started or 0):.0f} s "
                     "into its compile)")
            job.wait(poll=interrupt.check)
        self.record(step, what, job.ok, "" if job.ok else "its background compile failed")
        return job.ok
