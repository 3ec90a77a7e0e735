"""Which compiled training step runs, and running it: the :class:`StepProvider` of a run.

The provider runs each step (:meth:`StepProvider.run`) at the run's tile capacity
(:class:`TileCapacity`: fitted where unset, grown on overflow). A run's step is one jitted function
per (render config, tile capacity[, batch size]) and scene layout, with one program per padded view
size (:mod:`patexgs_jax.padding`). The provider gives the step (:meth:`StepProvider.get`) from the
run's cache, the process's (:class:`ProcessPrograms`: a resumed run or a study's next run call what
an earlier run compiled), a compile-ahead listener (:mod:`.compile_ahead`) or a fresh jit; it
announces and counts compiles (:class:`Compiles`: a call compiles when its padded size is new to its
step and no background compile made it) and guards the memory-map cap
(:mod:`patexgs_jax.memory_maps`). A layout once left is rarely met again (the Gaussian capacity only
grows; texture buckets are sized afresh when one overflows), so leaving one in a process past
:data:`~patexgs_jax.memory_maps.KEEP_SHARE` of its cap releases its programs.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from collections.abc import Callable
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from .. import interrupt, memory_maps, padding, parallel
from ..optim import RATE_NAMES
from ..render import Capacity, RenderConfig, count_pairs
from ..scene import Scene
from .config import TrainConfig, effective_config
from .step import batch_step, single_view_step

__all__ = ["PROCESS", "Compiles", "ProcessPrograms", "StepEntry", "StepProvider", "TileCapacity", "layout_of",
           "refits_at", "single_step_jit", "step_args", "step_identity", "step_image_args"]

#: Jitted steps (capacities) a run keeps for one scene layout.
_MAX_STEP_FNS = 4

#: Steps the process keeps for its runs at most (the least recently used released first).
_MAX_SHARED_STEPS = 16

#: Steps between two looks at the memory-map count (it is also read after every compile).
MAP_CHECK_EVERY = 25


def layout_of(scene: Scene) -> tuple:
    """The shapes of a scene's arrays: what, with the static arguments, selects a compiled step."""
    return tuple(np.shape(x) for x in jax.tree_util.tree_leaves(scene))


def refits_at(config: TrainConfig, step: int, capacity: Capacity | None) -> bool:
    """Whether the tile capacity is refitted after ``step`` steps (:class:`.strategies.TileRefit`):
    every 100 steps of the 2DGS stage, up to and including its end, once a capacity was fitted."""
    return step <= config.iters_2dgs and capacity is not None and step % 100 == 0


@dataclasses.dataclass
class TileCapacity:
    """A run's tile capacity: ``current``, the tile-Gaussian pairs its step is compiled for (None:
    fitted before the next step), and ``floor``, the capacity before the scene last grew, under
    which a refit never goes (more Gaussians do not need fewer pairs; a smaller capacity would
    overflow and compile the step again for every padded size). ``pad`` sizes both."""

    pad: padding.TrainPadding
    current: Capacity | None = None
    floor: Capacity | None = None

    def fit(self, scene: Scene, camera, render_cfg: RenderConfig, batch: bool) -> None:
        """Fits ``current`` to ``camera``'s pairs (at the step's padded size, on the view's own tiles:
        the step's count, one program a size; ``batch``: the batch step's unpadded size)."""
        interrupt.set_phase("counting the tile pairs of a view (the counter compiles once per size)")
        hw = None if batch else np.array([camera.height, camera.width], np.int32)
        camera = camera if batch else self.pad.camera(camera, render_cfg.tile_size)
        needed, _ = count_pairs(scene, camera, render_cfg, hw)
        # (None after the scene grew: the step compiles anyway, so the fit takes the full headroom)
        self.current = self.pad.capacity(needed, minimum=self.floor, current=self.current)

    def overflowed(self, metrics: dict) -> Capacity | None:
        """After a step: the capacity it overflowed, now grown to fit (the step is retried), or None."""
        if not (bool(metrics["overflow"]) and np.isfinite(float(metrics["pairs_needed"]))):
            return None
        old, self.current = self.current, self.pad.capacity(metrics["pairs_needed"], current=self.current)
        return old

    def scene_grew(self) -> None:
        """The scene's shapes changed (densification): refit before the next step, from this floor."""
        self.floor, self.current = self.current or self.floor, None


def step_identity(config: TrainConfig) -> tuple:
    """What defines a run's step program besides its render config, tile capacity and layout (the
    key a step compiled ahead, or shared between runs, is matched by): whether the distortion loss
    is on. The scene radius, learning rates and loss weights are the step's arguments
    (:func:`step_args`), so runs on other scenes or of other lengths share programs."""
    return ("distortion" if config.lambda_dist > 0 else "no distortion",)


def step_args(rates: dict, config: TrainConfig) -> dict:
    """The traced settings of a run's step, its ``hp``: the learning ``rates``
    (:func:`patexgs_jax.optim.step_rates`; the means' decay over the 2DGS stage, for every method)
    and the loss weights, () float32 each."""
    return dict(rates=rates, lambda_dssim=np.float32(config.lambda_dssim), lambda_dist=np.float32(config.lambda_dist))


def step_image_args(cam) -> tuple:
    """Abstract image, image size, SH degree, normal weight and ``hp`` (:func:`step_args`) of a
    single-view step at ``cam``'s (padded) size, for ``lower``."""
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    hp = dict(rates={k: scalar for k in RATE_NAMES}, lambda_dssim=scalar, lambda_dist=scalar)
    return (jax.ShapeDtypeStruct((cam.height, cam.width, 3), np.float32), jax.ShapeDtypeStruct((2,), np.int32),
            jax.ShapeDtypeStruct((), jnp.int32), scalar, hp)


def single_step_jit(optimizer, render_cfg: RenderConfig, capacity: Capacity | None, distortion: bool):
    """The jitted single-view step as ``fn(scene, opt_state, stats, camera, image, valid_hw,
    active_sh, w_normal, hp)``, ``hp`` the run's :func:`step_args`. It closes over no run (``optimizer``
    only for its structure: the learning rates are in ``hp``), so a step compiled by one run serves
    another of the same :func:`step_identity`; ``distortion``: the distortion loss is on."""
    return jax.jit(lambda sc, st, stats, cam, img, hw, sh, wn, hp: single_view_step(
        sc, st, stats, cam, img, hw, sh, wn, optimizer=optimizer, render_config=render_cfg, capacity=capacity,
        lambda_dssim=hp["lambda_dssim"], lambda_dist=hp["lambda_dist"] if distortion else 0.0,
        rates=hp["rates"]), donate_argnums=(0, 1, 2))


@dataclasses.dataclass(eq=False)
class StepEntry:
    """A jitted step as a run keeps it: ``fn``, the padded sizes it has been called with
    (``compiled``: a new one compiles; shared with the process's entry for the same step) and the
    background jobs compiling it ahead, per padded size (``ahead``)."""

    fn: Callable
    compiled: set = dataclasses.field(default_factory=set)
    ahead: dict = dataclasses.field(default_factory=dict)


class ProcessPrograms:
    """What the runs of one process share: their single-view steps (keyed by step identity, key and
    layout) and the stage-2 programs compiled ahead and not yet claimed (``prepared``, managed by
    :mod:`.compile_ahead`: a run may prepare the runs that start from its stage-1 checkpoint)."""

    def __init__(self):
        self.steps: collections.OrderedDict[tuple, StepEntry] = collections.OrderedDict()
        self.prepared: list[Any] = []

    def step(self, identity: tuple, key, layout: tuple | None, padded: tuple[int, int]) -> Callable | None:
        """The jitted step an earlier run shared for this identity, key and layout, if it has compiled
        the padded size ``padded`` (else None); safe from compile-ahead's thread (a lookup)."""
        entry = self.steps.get((identity, key, layout))
        return entry.fn if entry is not None and padded in entry.compiled else None

    def release_steps(self) -> None:
        """Releases the shared steps and their programs: the next run traces and compiles its own."""
        for entry in self.steps.values():
            _release(entry)
        self.steps.clear()

    def discard_prepared(self) -> None:
        """Cancels every program being compiled ahead: no run of this process will claim them."""
        for p in list(self.prepared):
            p.cancel()
        self.prepared.clear()


def _release(entry: StepEntry) -> None:
    memory_maps.release_programs(entry.fn)
    entry.compiled.clear()  # (its programs are gone: every size compiles again)


#: The programs of this process's runs (see :class:`ProcessPrograms`).
PROCESS = ProcessPrograms()
memory_maps.on_clear(PROCESS.steps.clear)  # (JAX's caches cleared: the steps hold no programs any more)


@dataclasses.dataclass
class Compiles:
    """The step programs of a run: ``count`` (checkpointed: a resumed run's include those before),
    and those this process compiled in the main thread: at which steps (``at``) and the seconds
    those steps' calls took (``seconds``: tracing, compiling, dispatch)."""

    count: int = 0
    at: list[int] = dataclasses.field(default_factory=list)
    seconds: float = 0.0


class AheadListener(Protocol):
    """What the provider asks of compiling ahead (:class:`.compile_ahead.CompileAhead`)."""

    def claim_step(self, render_cfg: RenderConfig, capacity, layout: tuple, step: int) -> StepEntry | None: ...

    def take(self, job, what: str, step: int) -> bool: ...


class StepTimes(Protocol):
    """Where the provider reports the duration of a step that compiled nothing and whose update
    was applied (:class:`.estimate.Estimate`)."""

    def measure(self, step: int, seconds: float) -> None: ...


class StepProvider:
    """The compiled steps of one run (see the module's docstring). ``pad``: the run's padding;
    ``tiles``: the run's tile capacity; ``ahead``: the compile-ahead listener, or None; ``times``:
    told each clean step's duration, or None; ``say``: where a capacity overflow is told;
    ``on_map_limit(maps, process)``, called past the ``map_guard``'s stop share (``maps`` this
    process's (count, cap), or None when another ``process`` hit it), saves and raises; ``shared``:
    the process's programs."""

    def __init__(self, config: TrainConfig, optimizer, rates: dict, pad: padding.TrainPadding, tiles: TileCapacity, *,
                 ahead: AheadListener | None, times: StepTimes | None, say: Callable[[str], None],
                 map_guard: memory_maps.MapGuard, on_map_limit: Callable[[tuple[int, int] | None, int | None], None],
                 shared: ProcessPrograms = PROCESS):
        self.cfg, self.optimizer, self.pad, self.tiles, self.ahead, self.say = config, optimizer, pad, tiles, ahead, say
        self.times = times
        # (effective_config: no normal loss for 3D Gaussians, which have no surface normal)
        self.lambda_normal = effective_config(config).lambda_normal
        self.map_guard, self.on_map_limit, self.shared = map_guard, on_map_limit, shared
        self.identity = step_identity(config)
        self.hp = jax.device_put(step_args(rates, config))
        self.entries: dict[Any, StepEntry] = {}
        self.layout: tuple | None = None
        self.compiles = Compiles()
        self.step = 0
        self.compiled_now = True  # (the first step looks at the memory maps)
        self._mesh = None

    # -- the step loop's calls --------------------------------------------------------------------
    def begin(self, step: int) -> None:
        """Before the step that starts at ``step``: a stop signal stops here (the state is whole),
        the heartbeat names the stage, and the memory maps are looked at after a compile (they grow
        only then; reading /proc/self/maps costs milliseconds) and every few steps."""
        interrupt.check()
        if interrupt.set_phase(self.phase(step)):
            interrupt.set_step(step, self.cfg.total_steps)
        if self.compiled_now or step % MAP_CHECK_EVERY == 0:
            self.check_memory_maps()
        self.step, self.compiled_now = step, False

    def phase(self, step: int) -> str:  # (the heartbeat's)
        return f"training the {self.cfg.stage_name(step)} stage"

    def check_memory_maps(self) -> None:
        """Releases compiled code near the memory-map cap; past the guard's stop share (on any
        process: they stop together) calls ``on_map_limit``."""
        maps = self.map_guard.check(on_release=self.clear)
        other = None
        if jax.process_count() > 1:
            hit = parallel.process_allgather_ints([maps is not None])[:, 0]
            other = None if not hit.any() else int(np.argmax(hit))
        if maps is not None or other is not None:
            self.on_map_limit(maps, other)

    def clear(self) -> None:
        """Forgets this run's steps (near the memory-map cap, with JAX's caches)."""
        self.entries.clear()

    def run(self, state, step: int, views, images, render_cfg: RenderConfig) -> tuple[Any, dict | None, float]:
        """Runs the step that starts at ``step`` on its ``views`` (``images``: theirs, None where
        another process loads them) from ``state`` (a :class:`~patexgs_jax.schedule.TrainState`,
        donated), fitting the tile capacity first where it is unset. Returns the new state, the
        step's metrics and its seconds (a step that compiled nothing and whose update is applied
        is told to ``times``); or None for the metrics when the capacity overflowed: it has grown,
        and the step is to run again (on the returned state, which the step left unchanged)."""
        cfg = self.cfg
        t0 = time.perf_counter()
        if self.tiles.current is None:
            for v in views:
                self.tiles.fit(state.scene, v.camera, render_cfg, batch=cfg.batch_size > 1)
        fn = self.get(layout_of(state.scene), render_cfg, self.tiles.current)
        active_sh = jnp.int32(min(step // cfg.sh_interval, cfg.sh_degree))
        w_normal = jnp.float32(self.lambda_normal if step >= cfg.normal_from else 0.0)
        if cfg.batch_size == 1:
            data = (views[0].camera, images[0])
        else:
            state, data = self.batch_inputs(state, views, images)
        scene, opt_state, stats, m = fn(*state, *data, active_sh, w_normal)
        state = type(state)(scene, opt_state, stats)
        old = self.tiles.overflowed(m)  # (reads the metrics: the step is done)
        seconds = time.perf_counter() - t0
        if old is None:
            if self.times is not None and not self.compiled_now and bool(m["ok"]):
                self.times.measure(step, seconds)
            return state, m, seconds
        self.say(f"[step {step}] tile capacity {old} overflowed; growing to {self.tiles.current} and retrying")
        return state, None, seconds

    def get(self, layout: tuple, render_cfg: RenderConfig, capacity: Capacity | None) -> Callable[..., Any]:
        """The training step for the scene layout ``layout`` as ``fn(scene, opt_state, stats,
        camera, image, active_sh, w_normal)`` (``image`` (H, W, 3) at the camera's size; batches:
        stacked cameras and images, :meth:`~.trainer.Trainer.batch_inputs`)."""
        if self.cfg.batch_size > 1:
            key = (render_cfg, capacity, self.cfg.batch_size)
            return self._batch_call(self._entry(layout, key, lambda: self._batch_jit(render_cfg, capacity)))
        key = (render_cfg, capacity)
        entry = self._entry(layout, key, lambda: single_step_jit(self.optimizer, render_cfg, capacity,
                                                                 self.cfg.lambda_dist > 0), shared=True)
        tile = render_cfg.tile_size

        def step(scene, opt_state, stats, camera, image, active_sh, w_normal):
            cam = self.pad.camera(camera, tile)
            return self._call(entry, (cam.height, cam.width), f"{cam.width}x{cam.height} px", scene, opt_state,
                              stats, cam, padding.pad_image(image, cam.height, cam.width),
                              np.array([camera.height, camera.width], np.int32), active_sh, w_normal, self.hp)

        return step

    # -- the caches -------------------------------------------------------------------------------
    def _entry(self, layout: tuple, key, make: Callable[[], Callable], shared: bool = False) -> StepEntry:
        """The step for ``key`` at ``layout``: this run's, the process's (``shared``), one compiled
        ahead, or ``make()``; at most :data:`_MAX_STEP_FNS` kept within a layout."""
        if self.layout != layout:
            if self.entries:
                self.entries.clear()
                if padding.release_scene_programs(retire=True):
                    self.shared.release_steps()
            self.layout = layout
        if key in self.entries:
            return self.entries[key]
        while len(self.entries) >= _MAX_STEP_FNS:
            self.entries.pop(next(iter(self.entries)))
        process_key = (self.identity, key, layout)
        if shared and process_key in self.shared.steps:
            self.shared.steps.move_to_end(process_key)
            theirs = self.shared.steps[process_key]
            self.entries[key] = StepEntry(theirs.fn, theirs.compiled)
            return self.entries[key]
        claimed = None
        if shared and self.ahead is not None:
            claimed = self.ahead.claim_step(key[0], key[1], layout, self.step)
        entry = self.entries[key] = claimed or StepEntry(make())
        if shared:  # (its padded sizes are shared; the jobs compiling it ahead are this run's)
            self.shared.steps[process_key] = StepEntry(entry.fn, entry.compiled)
            while len(self.shared.steps) > _MAX_SHARED_STEPS:
                _release(self.shared.steps.popitem(last=False)[1])
        return entry

    def _call(self, entry: StepEntry, size: tuple, what: str, *args):
        """``entry.fn(*args)`` at padded size ``size``, counted as a compile where it compiles
        (compiling is synchronous; the step is not)."""
        compiles = self._compiles(entry, size, what)
        t0 = time.perf_counter()
        out = entry.fn(*args)
        if compiles:
            self.compiles.count += 1
            self.compiles.at.append(self.step)
            self.compiles.seconds += time.perf_counter() - t0
            self.compiled_now = True
            interrupt.set_phase(self.phase(self.step))
        return out

    def _compiles(self, entry: StepEntry, size: tuple, what: str) -> bool:
        """Whether the call of ``entry`` at ``size`` compiles: not when the size was called before or
        a background compile made its program (waited for here)."""
        if size in entry.compiled:
            return False
        entry.compiled.add(size)
        job = entry.ahead.pop(size, None)
        if job is not None:
            self.compiled_now = True  # (its mappings are new, and its time is not a step's)
            took = self.ahead is not None and self.ahead.take(job, f"the {self.cfg.stage_name(self.step)} step for "
                                                                   f"{what}", self.step)
            interrupt.set_phase(self.phase(self.step))
            if took:
                return False
        interrupt.set_phase(f"compiling the {self.cfg.stage_name(self.step)} step for {what}")
        interrupt.set_step(self.step, self.cfg.total_steps)
        return True

    # -- batches over devices ---------------------------------------------------------------------
    def data_mesh(self):
        """The device mesh of the data-parallel step (``batch_size`` > 1), built once per run."""
        if self._mesh is None:
            self._mesh = parallel.data_mesh(parallel.num_batch_devices(self.cfg.batch_size, self.cfg.devices))
        return self._mesh

    def batch_share(self) -> range:
        """Positions in each batch of the views this process loads (all of them with one process)."""
        return range(self.cfg.batch_size)[parallel.process_slice(self.cfg.batch_size, self.data_mesh())]

    def batch_inputs(self, state, views, images) -> tuple[Any, tuple]:
        """``state`` replicated on the mesh, and the stacked cameras and (B, H, W, 3) images placed
        over it. ``images``: the batch's; only those at :meth:`batch_share` are read (with several
        processes the others are not loaded and may be None)."""
        mesh = self.data_mesh()
        state = type(state)(*parallel.replicate(tuple(state), parallel.local_mesh(mesh)))
        share = self.batch_share()
        cams = parallel.stack_cameras([views[j].camera for j in share])
        return state, parallel.shard_batch((cams, np.stack([np.asarray(images[j], np.float32) for j in share])), mesh)

    def _batch_jit(self, render_cfg: RenderConfig, capacity: Capacity | None):
        mesh, distortion = self.data_mesh(), self.cfg.lambda_dist > 0
        return jax.jit(lambda sc, st, stats, cams, imgs, sh, wn, hp: batch_step(
            sc, st, stats, cams, imgs, sh, wn, mesh=mesh, optimizer=self.optimizer, render_config=render_cfg,
            capacity=capacity, lambda_dssim=hp["lambda_dssim"], lambda_dist=hp["lambda_dist"] if distortion else 0.0,
            rates=hp["rates"]), out_shardings=parallel.replicated(mesh), donate_argnums=(0, 1, 2))

    def _batch_call(self, entry: StepEntry) -> Callable[..., Any]:
        mesh = self.data_mesh()

        def fn(*args):
            return self._call(entry, (), f"batches of {self.cfg.batch_size} views", *args)

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
