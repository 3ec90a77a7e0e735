"""Compiling ahead: a texture stage's first programs compiled in a background thread before the run
needs them (:mod:`patexgs_jax.ahead` runs the jobs), so the stage's first steps do not wait.

What is compiled ahead, from the end of the 2DGS stage (this run's own texture stage, or that of a
run that starts from this run's stage-1 checkpoint in this process, ``train(..., prepare=)``):

  * the textured step for the warm-up's layout at the padded size of the stage's first view, with
    the tile capacity the first step will fit;
  * for Eq. 7 methods, the allocation's pair counter and renderer, and the textured step for the
    layout a speculative Eq. 7 allocation gives on the warm-up's first state (the real allocation,
    40 steps later, usually falls in the same power-of-two texture buckets).

A prediction that does not match what the run then needs is never used (the run compiles as it
would have), so results never depend on it. The trainer sees a small interface
(:class:`CompileAhead`): ``after_step`` and ``prepare_others`` start jobs, ``predict_own_allocation``
at the texture stage's start, ``claim_step`` / ``claim_eq7`` / ``take`` when a program is needed,
``cancel_unclaimed`` at the end. ``PATEXGS_COMPILE_AHEAD=0`` turns it off.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import ahead, interrupt, padding
from ..adaptive import ContributionCounts
from ..optim import RATE_NAMES, step_rates
from ..render import Capacity, RenderConfig, count_pairs
from ..scene import Scene
from ..schedule import TEXTURE_HEADROOM, TEXTURE_MIN_SPARE, TextureSchedule
from ..textures.rebucket import resize_textures
from .config import TrainConfig
from .step import single_view_step
from .step_cache import shared_step

if TYPE_CHECKING:
    from .trainer import Trainer

__all__ = ["MAX_PREPARED", "PREPARED", "CompileAhead", "Prepared", "discard_prepared", "layout_of", "single_step_jit",
           "step_args", "step_identity"]


def layout_of(scene: Scene) -> tuple:
    """The shapes of a scene's arrays: what, with the static arguments, selects a compiled step."""
    return tuple(np.shape(x) for x in jax.tree_util.tree_leaves(scene))


def single_step_jit(optimizer, render_cfg: RenderConfig, capacity: Capacity | None, distortion: bool):
    """The jitted single-view training step (see ``Trainer.step_fn``) as ``fn(scene, opt_state,
    stats, camera, image, valid_hw, active_sh, w_normal, hp)``, ``hp`` the run's :func:`step_args`.
    It closes over nothing of a Trainer (``optimizer`` only for its structure: the learning rates
    are in ``hp``), so that a step compiled by one run serves another of the same
    :func:`step_identity`; ``distortion``: the distortion loss is on (its weight in ``hp``)."""
    return jax.jit(lambda sc, st, stats, cam, img, hw, sh, wn, hp: single_view_step(
        sc, st, stats, cam, img, hw, sh, wn, optimizer=optimizer, render_config=render_cfg, capacity=capacity,
        lambda_dssim=hp["lambda_dssim"], lambda_dist=hp["lambda_dist"] if distortion else 0.0,
        rates=hp["rates"]), donate_argnums=(0, 1, 2))


def step_identity(config: TrainConfig) -> tuple:
    """What defines a run's training step program besides its render config, tile capacity and
    layout (the key a step compiled ahead, or shared between runs, is matched by): whether the
    distortion loss is on. The scene radius, learning rates and loss weights are the step's
    arguments (:func:`step_args`), so runs on other scenes or of other lengths share programs."""
    return ("distortion" if config.lambda_dist > 0 else "no distortion",)


def step_args(radius: float, config: TrainConfig) -> dict:
    """The traced settings of a run's step, its ``hp``: the learning rates
    (:func:`patexgs_jax.optim.step_rates`; the means' decay over the 2DGS stage, for every method)
    and the loss weights, () float32 each."""
    return dict(rates=step_rates(dataclasses.replace(config.lr, means_steps=config.iters_2dgs), radius),
                lambda_dssim=np.float32(config.lambda_dssim), lambda_dist=np.float32(config.lambda_dist))


def step_image_args(cam) -> tuple:
    """Abstract image, image size, SH degree, normal weight and ``hp`` (:func:`step_args`) of a
    single-view step at ``cam``'s (padded) size, for ``lower``."""
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    hp = dict(rates={k: scalar for k in RATE_NAMES}, lambda_dssim=scalar, lambda_dist=scalar)
    return (jax.ShapeDtypeStruct((cam.height, cam.width, 3), np.float32), jax.ShapeDtypeStruct((2,), np.int32),
            jax.ShapeDtypeStruct((), jnp.int32), scalar, hp)


def owned_copy(tree):
    """A copy of ``tree``'s device arrays that a background job owns (the next step donates the
    originals)."""
    return jax.tree_util.tree_map(lambda x: jnp.copy(x) if isinstance(x, jax.Array) else x, tree)


@dataclasses.dataclass(eq=False)
class Prepared:
    """A texture stage's first programs, being compiled ahead (:mod:`patexgs_jax.ahead`) for a layout
    not reached yet: the textured step for the warm-up's layout at the first view's padded size and,
    for Eq. 7 methods, the allocation's pair counter and renderer (:meth:`CompileAhead.prepare`).

    ``identity``: what defines the step besides its render config and tile capacity
    (:func:`step_identity`); ``capacity``, ``fn`` (the jitted step) and ``eq7`` (programs for
    :class:`patexgs_jax.padding.ViewRenderer`) are set by the background job. ``layout`` is None
    while a predicted allocation's sides are being counted (``counted`` is set once it is known);
    ``then``: the entry of the allocation predicted from this warm-up state."""

    identity: tuple
    render_cfg: RenderConfig
    layout: tuple | None
    padded: tuple[int, int]  # (height, width) of the padded size it is compiled for
    owner: int  # id() of the Trainer whose own stage 2 it is (0: made for another run)
    step_job: ahead.Job | None = None
    eq7_job: ahead.Job | None = None
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
            with contextlib.suppress(ValueError):
                PREPARED.remove(self.then)


#: Stage-2 programs compiled ahead and not yet claimed by the run that needs them (process-wide: a
#: run may prepare the runs that start from its stage-1 checkpoint, see ``train(..., prepare=)``).
PREPARED: list[Prepared] = []

#: Prepared entries kept at most (the oldest are dropped first).
MAX_PREPARED = 4


def discard_prepared() -> None:
    """Cancels every entry of :data:`PREPARED` and empties it: no run of this process will claim
    them (e.g. those a study made for runs it did not reach, before an unrelated run)."""
    for p in list(PREPARED):
        p.cancel()
    PREPARED.clear()


class CompileAhead:
    """The compile-ahead work of one run (:class:`~patexgs_jax.training.trainer.Trainer`).

    ``prepare_for``: configs of runs that start from this run's stage-1 checkpoint in this process
    (``train(..., prepare=)``); ``took``: whether the last step waited for (or took) a program
    compiled ahead (its time is then not a step's); ``outcomes``: each program this run needed
    and found compiled ahead (``hit``) or prepared for something else (the step's ``why``), in
    order (:meth:`record`, summary.json's ``compile_ahead``).
    """

    def __init__(self, run: Trainer):
        self.run = run
        self.prepare_for: tuple[TrainConfig, ...] = ()
        self.took = False
        self.outcomes: list[dict] = []
        self._prepared_own: Capacity | None = None  # the capacity this run's own step was prepared for
        dc = run.densification.config
        self._last_densify = max((t for t in range(1, run.cfg.iters_2dgs) if dc.densify_at(t)), default=0)

    def after_step(self, step: int) -> None:
        """Once densification has stopped, the texture stage's first layout is known: its step is
        compiled ahead (again after a tile-capacity refit that changed the capacity: the step's
        program depends on the shapes and the capacity only, so a refit that keeps the capacity
        would compile the same programs again, every 100 steps, beside the run's own steps)."""
        run = self.run
        if (self._last_densify <= step < run.cfg.iters_2dgs and run.scene.rgb is None
                and run.capacity is not None
                and (self._prepared_own is None or (run.refits_at(step) and run.capacity != self._prepared_own))):
            self._prepared_own = run.capacity
            # (its allocation is predicted at the stage's start, from the warm-up's actual state)
            self.prepare(run.cfg, predict_allocation=False)

    def cancel_unclaimed(self) -> None:
        """At the run's end: the entries made for it and never claimed are not needed."""
        for p in [p for p in PREPARED if p.owner == id(self)]:
            p.cancel()
            with contextlib.suppress(ValueError):  # (cancelling an entry removes its ``then``)
                PREPARED.remove(p)

    def prepare(self, config: TrainConfig, predict_allocation: bool = True) -> None:
        """Starts compiling ahead, in the background (:mod:`patexgs_jax.ahead`), the first programs of
        ``config``'s texture stage (this run's own, or one that will start from this run's stage-1
        checkpoint in this process) from this run's current state: the textured step for the
        warm-up's layout at the padded size of the stage's first view, with the tile capacity the
        first step will fit, and for Eq. 7 methods the allocation's pair counter and renderer and,
        with ``predict_allocation``, the textured step for the layout Eq. 7 gives on the warm-up's
        first state (a speculative allocation: counted and sized in the background; the real one,
        40 steps of training later, usually falls in the same power-of-two buckets). The warm-up's
        layout is known exactly once the Gaussian count is fixed (densification has stopped); the
        capacities are predicted from the current scene. A prediction that does not match what the
        run then needs is not used (the run compiles as it would have), so results never depend on
        it. Does nothing when compiling ahead is off, for 2DGS, batches, or several processes."""
        if (not ahead.enabled() or config.spec.textures is None or config.batch_size != 1
                or config.iters_2dgs != self.run.cfg.iters_2dgs or config.total_steps <= config.iters_2dgs
                or jax.process_count() > 1):
            return
        from ..render import render_jit

        own = config is self.run.cfg
        identity = step_identity(config)
        optimizer = self.run.optimizer  # (its structure only: another run's learning rates are its step's arguments)
        render_cfg = config.render_config(stage=2)
        stage = TextureSchedule(config, optimizer, self.run.train_views, render_cfg)
        state = stage.start(self.run.state)
        scene, opt_state, stats = owned_copy(tuple(state))
        view = self.run.view(config.iters_2dgs, config.seed)
        pad = self._pad(config)
        cam = pad.camera(view.camera, render_cfg.tile_size)
        hw = np.array([view.camera.height, view.camera.width], np.int32)
        layout = layout_of(scene)
        same = [p for p in PREPARED if (p.identity, p.render_cfg, p.layout) == (identity, render_cfg, layout)]
        if same and not own:
            return  # (another run the study trains next has the same first programs: prepared once)
        for old in same:
            old.cancel()  # superseded (a capacity refit since)
            with contextlib.suppress(ValueError):
                PREPARED.remove(old)
        prep = Prepared(identity, render_cfg, layout, (cam.height, cam.width), 0 if not own else id(self))
        # The stage's first step fits the capacity (pad.headroom x its view's pairs) from none (a run started
        # from a stage-1 checkpoint), or this run keeps its own (refitted up at the stage's start
        # when a refit falls there).
        minimum = self.run.capacity if own else None
        keep = own and not self.run.refits_at(config.iters_2dgs)
        args = step_image_args(cam)

        def compile_step():
            done = None
            try:
                if keep:
                    prep.capacity = minimum
                else:  # (its own program: the main thread releases the shared jitted ones at will)
                    counter = count_pairs.lower(scene, cam, config=render_cfg, valid_hw=hw).compile()
                    needed, _ = counter(scene, cam, valid_hw=hw)
                    prep.capacity = pad.capacity(needed, current=minimum)  # (as the run's refit)
                done = shared_step(identity, (render_cfg, prep.capacity), layout, prep.padded)
                prep.fn = done or single_step_jit(optimizer, render_cfg, prep.capacity, config.lambda_dist > 0)
            finally:
                prep.counted.set()
            if done is None:  # (else an earlier run of this process compiled it: the run takes it from there)
                prep.fn.lower(scene, opt_state, stats, cam, *args).compile()

        def compile_eq7():
            programs, caps, cams = {}, {}, {}
            for v in self.run.train_views:  # as TextureSchedule.allocate's ViewRenderer pads and counts them
                c = padding.padded_camera(v.camera, render_cfg.tile_size, padding.EVAL_STEPS_PER_OCTAVE)
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

        say = self.run.say
        whose = "" if own else f" of {config.method}"
        prep.step_job = ahead.submit(f"the textured step{whose} for {cam.width}x{cam.height} px", compile_step, say)
        if config.spec.textures == "adaptive" and config.warmup_tex < config.iters_tex:
            prep.eq7_job = ahead.submit(f"Eq. 7's pair counter and renderer{whose}", compile_eq7, say)
        if prep.step_job is None:
            return
        PREPARED.append(prep)
        if predict_allocation and prep.eq7_job is not None:
            def capacity():
                prep.counted.wait()
                return prep.capacity

            prep.then = self._predict_allocation(config, stage, optimizer, identity, (scene, opt_state, stats),
                                                 prep.eq7_job, capacity, prep.owner, whose)
        while len(PREPARED) > MAX_PREPARED:
            PREPARED.pop(0).cancel()

    def _predict_allocation(self, config: TrainConfig, stage: TextureSchedule, optimizer, identity: tuple,
                            state: tuple, eq7_job: ahead.Job, capacity: Callable[[], Capacity | None], owner: int,
                            whose: str = "") -> Prepared | None:
        """Queues a speculative Eq. 7 allocation of ``config`` on ``state`` (scene, opt_state, stats:
        arrays the background thread owns, at the warm-up's layout) and the compile of the textured
        step for the layout it gives, at the padded size of the allocation step's view and the tile
        capacity ``capacity()`` (called in the background); counted with Eq. 7's programs of
        ``eq7_job``. Returns its entry (in ``PREPARED``; its layout is None until counted), or None
        when compiling ahead is off."""
        render_cfg = config.render_config(stage=2)
        scene, opt_state, stats = state
        view = self.run.view(config.iters_2dgs + config.warmup_tex, config.seed)
        cam = self._pad(config).camera(view.camera, render_cfg.tile_size)
        alloc = Prepared(identity, render_cfg, None, (cam.height, cam.width), owner)
        args = step_image_args(cam)

        def compile_allocation():
            done = None
            try:
                cap = capacity()
                if not eq7_job.ok or cap is None:
                    return
                # As TextureSchedule.allocate counts, with the programs compiled for this layout; not
                # released after (the main thread's Eq. 7 shares them).
                renderer = padding.ViewRenderer(scene, render_cfg, programs=eq7_job.value)
                renderer.prepare([v.camera for v in self.run.train_views])
                counts = ContributionCounts.from_views(
                    (np.asarray(renderer(v.camera).max_contrib_count) for v in self.run.train_views), scene.capacity)
                sides, _, _ = stage.allocation_sides(counts, np.asarray(scene.active) > 0)
                new_scene, new_opt, _ = resize_textures(scene, opt_state, sides, sides, headroom=TEXTURE_HEADROOM,
                                                        min_spare=TEXTURE_MIN_SPARE)
                alloc.capacity, alloc.layout = cap, layout_of(new_scene)
                done = shared_step(identity, (render_cfg, cap), alloc.layout, alloc.padded)
                alloc.fn = done or single_step_jit(optimizer, render_cfg, cap, config.lambda_dist > 0)
            finally:
                alloc.counted.set()
            if done is None:
                alloc.fn.lower(new_scene, new_opt, stats, cam, *args).compile()

        alloc.step_job = ahead.submit(f"the textured step{whose} for Eq. 7's predicted layout", compile_allocation,
                                      self.run.say)
        if alloc.step_job is None:
            return None
        PREPARED.append(alloc)
        return alloc

    def predict_own_allocation(self) -> None:
        """At the texture stage's start of a run through both stages: the speculative allocation (see
        :meth:`_predict_allocation`) from the warm-up's actual first state, with Eq. 7's programs
        compiled ahead for this layout (:meth:`prepare`)."""
        cfg = self.run.cfg
        if (not ahead.enabled() or cfg.spec.textures != "adaptive" or cfg.batch_size != 1
                or cfg.warmup_tex >= cfg.iters_tex or jax.process_count() > 1 or self.run.capacity is None):
            return
        prep = self._find(self.run.render_cfgs[1], layout_of(self.run.scene))
        if prep is None or prep.eq7_job is None or prep.then is not None or prep.eq7_job.cancelled:
            return
        cap = self.run.capacity
        run = self.run
        prep.then = self._predict_allocation(cfg, run.textures, run.optimizer, step_identity(cfg),
                                             owned_copy(tuple(run.state)), prep.eq7_job, lambda: cap, id(self))

    def prepare_others(self) -> None:
        """At the end of the 2DGS stage: the first programs of the runs that start from this state
        (``train(..., prepare=)``), once."""
        for i, other in enumerate(self.prepare_for):
            if len(PREPARED) >= MAX_PREPARED:
                break  # (entries for runs further on would push out those of the runs trained first)
            # The allocation's step too, where its entry leaves room (a run's warm-up step and its
            # allocation are two entries): the next run's always, later runs' while there is room.
            self.prepare(other, predict_allocation=i == 0 or len(PREPARED) + 2 <= MAX_PREPARED)
        self.prepare_for = ()

    def _pad(self, config: TrainConfig) -> padding.TrainPadding:
        """The training padding of ``config`` (this run's, or another run's on the same views)."""
        if config.padding == self.run.cfg.padding:
            return self.run.pad
        return padding.TrainPadding(config.padding, [v.camera for v in self.run.train_views])

    def _find(self, render_cfg: RenderConfig, layout: tuple) -> Prepared | None:
        identity = step_identity(self.run.cfg)
        return next((p for p in PREPARED if p.identity == identity and p.render_cfg == render_cfg
                     and p.layout == layout), None)

    def record(self, program: str, hit: bool, why: str = "") -> None:
        """Notes whether ``program``, needed at the current step, had been compiled ahead; for a
        miss, ``why`` not."""
        entry: dict[str, Any] = dict(step=self.run.step, program=program, hit=hit)
        if not hit:
            entry["why"] = why
        self.outcomes.append(entry)

    def summary(self) -> dict:
        """summary.json's ``compile_ahead``: hits, misses and each outcome (:meth:`record`)."""
        hits = sum(o["hit"] for o in self.outcomes)
        return dict(hits=hits, misses=len(self.outcomes) - hits, outcomes=list(self.outcomes))

    def _predicted(self, render_cfg: RenderConfig) -> bool:
        """Whether a step of this run's settings and ``render_cfg`` was compiled ahead for any layout."""
        identity = step_identity(self.run.cfg)
        return any(p.identity == identity and p.render_cfg == render_cfg for p in PREPARED)

    def claim_step(self, render_cfg: RenderConfig, capacity, layout: tuple) -> Prepared | None:
        """The step prepared ahead for this render config, capacity and layout, if any (see
        :meth:`prepare`); a job not started yet is cancelled (compiling here is sooner). Where a
        step was prepared for this run's settings, a miss is recorded here (:meth:`record`), a hit
        when the step first runs (:meth:`take`)."""
        if self.run.cfg.batch_size != 1:
            return None
        predicted = self._predicted(render_cfg)
        prep = self._find(render_cfg, layout)
        if prep is None:
            self._settle_predictions(render_cfg)
            prep = self._find(render_cfg, layout)
        what = "the textured step"
        if prep is None or prep.step_job is None:
            if predicted:
                self.record(what, False, "compiled ahead for another texture layout")
            return None
        job = prep.step_job
        if job.cancel() or job.cancelled:
            PREPARED.remove(prep)
            prep.cancel()
            self.record(what, False, "its background compile had not started")
            return None
        prep.counted.wait()  # (the capacity is counted first, in seconds)
        if prep.capacity != capacity or prep.fn is None:
            self.record(what, False, f"compiled ahead for tile capacity {prep.capacity}, the run uses {capacity}"
                        if prep.fn is not None else "its background compile failed")
            return None  # (a capacity the run does not use; Eq. 7's programs may still serve)
        prep.owner = id(self)
        if prep.then is not None:
            prep.then.owner = id(self)
        if prep.eq7_job is None:
            PREPARED.remove(prep)
        return prep

    def _settle_predictions(self, render_cfg: RenderConfig) -> None:
        """Waits for the predicted allocations being counted in the background for this run's settings
        (their layout is known within seconds); drops those not started or failed."""
        identity = step_identity(self.run.cfg)
        for p in [p for p in PREPARED if p.layout is None and p.identity == identity and p.render_cfg == render_cfg]:
            job = p.step_job
            if job is not None and not job.cancel() and not job.cancelled and not p.counted.is_set():
                interrupt.set_phase("waiting for the background count of Eq. 7's predicted layout")
                interrupt.set_step(self.run.step, self.run.cfg.total_steps)
                while not p.counted.wait(0.2):
                    interrupt.check()
            if p.layout is None:
                with contextlib.suppress(ValueError):
                    PREPARED.remove(p)

    def claim_eq7(self) -> dict | None:
        """Eq. 7's programs prepared ahead for the current layout (see :meth:`prepare`), waiting
        for them if they are being compiled; None if there are none."""
        render_cfg = self.run.render_cfgs[1]
        predicted = self._predicted(render_cfg)
        prep = self._find(render_cfg, layout_of(self.run.scene))
        what = "Eq. 7's pair counter and renderer"
        if prep is None or prep.eq7_job is None:
            if predicted:
                self.record(what, False, "compiled ahead for another texture layout")
            return None
        PREPARED.remove(prep)
        job = prep.eq7_job
        if job.cancel():
            self.record(what, False, "its background compile had not started")
            return None
        self.wait(job)
        self.record(what, job.ok, "" if job.ok else "its background compile failed")
        return job.value if job.ok else None

    def wait(self, job: ahead.Job) -> None:
        """Waits for a background compile the next step needs (a stop signal still stops the run)."""
        if job.done:
            return
        interrupt.set_phase(f"waiting for the background compile of {job.what}")
        interrupt.set_step(self.run.step, self.run.cfg.total_steps)
        self.run.say(f"[compile ahead] waiting for {job.what} ({time.monotonic() - (job.started or 0):.0f} s "
                 "into its compile)")
        job.wait(poll=interrupt.check)

    def take(self, job: ahead.Job | None, what: str) -> bool:
        """Whether the step's program for a new padded size was compiled ahead by ``job`` (waited for
        if still compiling); False (the step compiles it) if the job failed or had not started."""
        if job is None:
            return False
        if job.cancel():
            self.record(what, False, "its background compile had not started")
            return False
        self.wait(job)
        self.took = True
        self.record(what, job.ok, "" if job.ok else "its background compile failed")
        return job.ok
