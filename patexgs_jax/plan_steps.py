"""The run plan's step timing (:func:`measure_steps`): a few real training steps of each stage on
this device at the planned size, and an evaluation render (:mod:`patexgs_jax.plan` uses them);
the lines that say what it measures while it does (:class:`Progress`)."""

from __future__ import annotations

import dataclasses
import os
import statistics
import threading
import time

import numpy as np

from . import adaptive, interrupt
from . import progress as bars

__all__ = ["COMPILED_STEP", "EQ6_SAMPLE_VIEWS", "MAX_TIMED_STEPS", "TIMED_SECONDS", "Progress", "eq6_sample", "hms",
           "measure_steps", "sample_eq6_counts", "short_seconds"]

#: Training views the plan's Eq. 6 count renders (evenly spaced); Eq. 7's sums over all views are
#: scaled from them (:func:`sample_eq6_counts`).
EQ6_SAMPLE_VIEWS = 8
#: A stage's steps are timed until they add up to this many seconds (at least ``steps`` of them,
#: at most :data:`MAX_TIMED_STEPS`): on this project's 2-core CPU a run's own step time moves by a
#: third between stretches of a few seconds, so five steps of 70 ms time one such stretch, and
#: the median of the steps of a few seconds is the steadier figure (docs/memory.md, "Measured
#: error (CPU)"). Steps of a second or more are timed ``steps`` times, as before.
TIMED_SECONDS = 4.0
MAX_TIMED_STEPS = 40
#: A timed step longer than this many times the stage's median compiled (a tile capacity's retry,
#: a layout's first step): its time goes to the compile term.
COMPILED_STEP = 5.0
#: Before timing the 2DGS stage the plan trains its scene untimed for this many steps, or for as
#: many as fit in :data:`SETTLE_SECONDS` (none on a quick plan, which scales its figures anyway):
#: a run's steps get cheaper as its scene trains from the initial points (beer at 1/8, which does not
#: densify in its first 150 steps: 182 ms a step over steps 50-100, 110-115 ms from step 150 on, where
#: the plan timed its untrained scene at 145 ms; docs/memory.md, "Measured error (CPU)"), so the timed
#: steps are nearer those most of a run takes.
SETTLE_STEPS = 100
SETTLE_SECONDS = 15.0


class Progress:
    """The plan's progress lines: one when a phase starts (:meth:`phase`), and, while it lasts, one
    at least every ``every`` seconds (:meth:`tick`, called by a background thread inside ``with``)
    saying what is measured and for how long.

    Args:
      every: seconds of silence after which the phase is said again (default 8: the beat looks once a
        second and a compile holds the interpreter for a while, so lines land within 10 s).
      say: prints a line (default :func:`patexgs_jax.progress.say`, above any progress bar).
      clock: seconds (default ``time.monotonic``; tests pass their own).
    """

    def __init__(self, every: float = 8.0, say=None, clock=time.monotonic):
        self.every, self.clock = float(every), clock
        self.say = say or bars.say
        self.what: str | None = None
        self.since = self.last = clock()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._depth = 0

    def phase(self, what: str) -> None:
        """``what`` starts now (e.g. ``"timing 3 steps of the 2DGS stage"``): says it."""
        self.what, self.since = what, self.clock()
        interrupt.set_phase(f"plan: {what}")
        self._line(f"plan: {what}")

    def tick(self) -> None:
        """Says the current phase again (with its seconds so far) when nothing was said for ``every``
        seconds."""
        now = self.clock()
        if self.what is not None and now - self.last >= self.every:
            self._line(f"plan: {self.what} ({now - self.since:.0f} s so far)")

    def _line(self, text: str) -> None:
        self.last = self.clock()
        try:
            self.say(text)
        except (OSError, ValueError):  # (a closed stdout: the plan goes on)
            pass

    def __enter__(self):
        self._depth += 1
        if self._depth == 1:  # (entered again inside: the same thread goes on)
            def beat():
                while not self._done.wait(min(1.0, self.every / 4)):
                    self.tick()

            self._done.clear()
            self._thread = threading.Thread(target=beat, name="patexgs-plan-progress", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._depth -= 1
        if self._depth == 0:
            self._done.set()
            if self._thread is not None:
                self._thread.join(timeout=2.0)
            interrupt.set_phase(None)
        return False


class _Silent(Progress):
    def __init__(self):
        super().__init__(say=lambda text: None)

    def phase(self, what: str) -> None:
        self.what = what


def eq6_sample(views, k: int = EQ6_SAMPLE_VIEWS) -> list:
    """``k`` of ``views`` evenly spaced (all of them when there are no more than ``k``)."""
    views = list(views)
    if len(views) <= k:
        return views
    return [views[int(i * len(views) / k)] for i in range(k)]


@dataclasses.dataclass(frozen=True, eq=False)
class _ScaledCounts(adaptive.ContributionCounts):
    """Eq. 6's counts on a sample of the views, whose Eq. 7 sums (:meth:`sizes`) are scaled by
    ``weight`` (all views / sampled views): an estimate of the sums over every view."""

    weight: float = 1.0

    def sizes(self, sigma: float) -> np.ndarray:
        return super().sizes(sigma) * self.weight


def sample_eq6_counts(schedule, views, sample) -> None:
    """Makes the texture schedule ``schedule`` (a :class:`patexgs_jax.schedule.TextureSchedule`)
    count Eq. 6 on ``sample`` (some of the training views, e.g. :func:`eq6_sample`) instead of all
    of ``views``: its Eq. 7 sums ``T_i = sum_j log2(1 + S_ij / sigma)`` are scaled by
    ``len(views) / len(sample)``, and sigma (the pixel share) still comes from all of ``views``'
    pixels. With a texture budget the sample's allocation is solved for the budget as it is (the
    budget sets the texels)."""
    views, sample = list(views), list(sample)
    weight = len(views) / max(len(sample), 1)
    sides_of = schedule.allocation_sides
    schedule.train_views = sample

    def allocation_sides(S, act):
        if schedule.cfg.texture_budget_mb is None:
            S = adaptive._as_counts(S)
            S = _ScaledCounts(S.values, S.index, S.offsets, S.capacity, weight=weight)
        schedule.train_views = views  # (the pixel share counts every view's pixels)
        try:
            return sides_of(S, act)
        finally:
            schedule.train_views = sample

    schedule.allocation_sides = allocation_sides


def _compiled_apart(seconds: list[float]) -> tuple[list[float], list[float], float]:
    """(the steps within :data:`COMPILED_STEP` x the median, those beyond it: they compiled, the median)."""
    mid = statistics.median(seconds)
    return ([x for x in seconds if x <= COMPILED_STEP * mid], [x for x in seconds if x > COMPILED_STEP * mid], mid)


def measure_steps(dataset, config, gaussians: int, *, steps: int = 5, stage1_gaussians: int | None = None,
                  eq6_views: int = EQ6_SAMPLE_VIEWS, quick: bool = False, progress: Progress | None = None,
                  evaluate: bool = True) -> dict:
    """Times a few real training steps of each stage on this device: the 2DGS stage's at
    ``stage1_gaussians`` active Gaussians (default ``gaussians``; the others inactive, so no shape
    changes), the texture stage's at ``gaussians``.

    A scene of ``gaussians`` Gaussians is initialised from the dataset's points (repeated with a
    small jitter when it has fewer), densification is off, and the run's own loop trains (after
    :data:`SETTLE_STEPS` untimed 2DGS steps, at most :data:`SETTLE_SECONDS` of them; none when
    ``quick``) at least ``steps`` steps of each stage after the ones that compile, more while they add up to less than
    :data:`TIMED_SECONDS` (the steps past them are not run) (the texture stage of adaptive methods runs the
    real Eq. 7 allocation on that scene after one warm-up step, its Eq. 6 count on ``eq6_views`` of
    the training views and scaled to all: :func:`sample_eq6_counts`; ``quick``: at the stage's start,
    without the warm-up step, whose layout compiles a step of its own), with nothing compiled in the
    background (``PATEXGS_COMPILE_AHEAD=0`` meanwhile). Nothing is written. ``progress`` says what
    is measured (:class:`Progress`). The steps train on the
    views of one padded size (the most common one; ties: the largest): a run compiles its step once
    per padded size (:mod:`patexgs_jax.padding`), so on views of several sizes the timed steps would
    be compiles (an undistorted capture has several: beer at full size six). ``evaluate`` False
    leaves the evaluation render untimed (``eval_view`` and ``eval_compile`` None).

    Returns:
      ``stage1``, ``texture``: median seconds of each stage's timed steps, which compile nothing
      (texture None without textures); ``timed_steps``: how many (``steps``, then more up to
      :data:`TIMED_SECONDS` of them, at most :data:`MAX_TIMED_STEPS`; ``quick``: ``steps``), and
      ``step_ms`` each one's milliseconds; ``compile_stage1``, ``compile_texture``:
      seconds the stage's other steps took beyond as many steady ones (compiling);
      ``eval_view``, ``eval_compile``: seconds of one evaluation render and of compiling one
      evaluation (its renderer, pair counter and SSIM); ``ssim_compile``: of compiling SSIM alone;
      ``steps``; ``seconds``: the time this took (all in seconds); ``padded_size``:
      the (height, width) stepped; ``padded_sizes``: how many padded sizes the training views have
      (each compiles its own steps in a run); ``eq6_views``: the views Eq. 6 counted on (0 without
      an Eq. 7 allocation); ``settled_steps``: the 2DGS steps trained untimed before the timed ones
      (:data:`SETTLE_STEPS`) and ``settled_ms`` each one's milliseconds (the run's first steps);
      ``texture_layouts``: the texture layouts whose step ``compile_texture``
      holds (the start's and, after a warm-up step, Eq. 7's; 0 without textures).
    """
    import jax

    from .background import AHEAD_ENV
    from .densify import DensifyConfig
    from .evaluation import evaluate as evaluate_views
    from .metrics import ssim
    from .training.trainer import Trainer

    t_all = time.perf_counter()
    spec = config.spec
    textured = spec.textures is not None
    off = DensifyConfig(start=10**9, stop=10**9 + 1, opacity_reset_interval=10**9)
    allocates = spec.textures == "adaptive"
    warm = 0 if quick else 1
    most = steps if quick else max(steps, MAX_TIMED_STEPS)  # (quick: a few slow steps, scaled anyway)
    settle = 0 if quick else SETTLE_STEPS
    n1 = 1 + settle + most
    first1 = {"step": 1 + settle, "since": None}  # the first timed 2DGS step (earlier when settling runs long)
    first2 = n1 + 1 + (warm if allocates else 0)  # the texture stage's first timed step
    n2 = 0 if not textured else first2 - n1 + most
    cfg = dataclasses.replace(config, iters_2dgs=n1, iters_tex=max(n2, 2), continue_2dgs=0, warmup_tex=warm,
                              growth_interval=10**9, densify=off, max_gaussians=int(gaussians),
                              checkpoint_every=10**9, log_every=10**9, sh_interval=1, normal_from=0)
    pts, cols = _points_for(dataset.points, dataset.colors, int(gaussians), config.seed)
    size, n_sizes, views = _one_size(dataset.train_views, config)
    ds = dataclasses.replace(dataset, points=pts, colors=cols, train_views=views)
    stamps: list[tuple[int, float]] = []
    skipped: set[int] = set()  # steps past a stage's timing (not run: the stage has its figure)
    timed: dict[int, list[float]] = {1: [], 2: []}
    say = progress or _Silent()
    m = int(gaussians) if stage1_gaussians is None else max(1, min(int(stage1_gaussians), int(gaussians)))
    at = f"{size[1]}x{size[0]} px"
    upto = "" if most == steps else f"{steps} to {most} steps (at least {TIMED_SECONDS:g} s) of"
    timing1 = f"timing {upto or f'{steps} steps of'} the 2DGS stage"
    phases = {0: f"compiling the 2DGS step ({m:,} active Gaussians of {int(gaussians):,}, {at})", 1: timing1}
    if settle:
        phases[1] = (f"training the scene untimed for up to {settle} steps or {SETTLE_SECONDS:g} s first (a scene's "
                     "steps get cheaper as it trains)")
    if textured:
        phases[n1] = "compiling the texture stage's first step"
        phases[first2] = f"timing {upto or f'{steps} steps of'} the texture stage ({int(gaussians):,} Gaussians)"

    def stage_of(step):
        return 1 if step < n1 else 2

    def timing(step):  # whether the step that starts at ``step`` is one the figures time
        return first1["step"] <= step < n1 or (textured and step >= first2)

    def settling(step):  # a 2DGS step trained before the timed ones
        return 1 <= step < first1["step"]

    def enough(k):  # (by the median: a timed step that compiled, a tile capacity's retry, counts as one step)
        t = timed[k]
        return len(t) >= most or (len(t) >= steps and len(t) * statistics.median(t) >= TIMED_SECONDS)
    # Eq. 6 on a sample of the views of the stepped size, Eq. 7's sums scaled to all the training views.
    sample = eq6_sample(views, eq6_views) if allocates else []

    class Run(Trainer):
        def before_step(self, step):
            if settle and settling(step):
                if first1["since"] is None:
                    first1["since"] = time.perf_counter()
                elif time.perf_counter() - first1["since"] > SETTLE_SECONDS:
                    first1["step"] = step  # (settled long enough: the timed steps start here)
            if settle and step == first1["step"]:
                say.phase(f"{timing1} (after {step - 1} untimed steps)")
            if step in phases:
                say.phase(phases[step])
            if m < gaussians and step in (0, n1):  # stage 1 at m active Gaussians, stage 2 at all of them
                act = np.asarray(self.scene.active).copy()
                act[m:gaussians] = act[0] if step == n1 else 0
                self.scene = self.scene.replace(active=jax.numpy.asarray(act))
                if step == n1:  # more Gaussians, more tile pairs: refit (its counter is compiled) rather than
                    self.tiles.current = None  # overflow, retry and compile the step twice
            allocation = allocates and self.textures.allocates_at(self.state, step)
            if allocation:
                say.phase(f"Eq. 6 counts on {len(sample)} of the {len(dataset.train_views)} training views "
                          "(Eq. 7's sums scaled to all of them)")
            super().before_step(step)
            if allocation:
                say.phase("compiling the texture step of the allocated sizes")

        def after_step(self, step):
            super().after_step(step)
            jax.block_until_ready(self.scene.means)
            t = time.perf_counter()
            if timing(step - 1) and step - 1 not in skipped:
                timed[stage_of(step - 1)].append(t - (stamps[-1][1] if stamps else t0))
            stamps.append((step, t))

    say.phase(f"setting up a scene of {int(gaussians):,} Gaussians on the {len(views)} training views of {at}")
    run = Run(ds, cfg, None, verbose=False)
    step_run, last = run.steps.run, {}

    def run_step(state, step, views, images, render_cfg):
        # Past a stage's timing nothing runs: the state stays, the last metrics stand in.
        if timing(step) and enough(stage_of(step)) and "m" in last:
            skipped.add(step)
            return state, last["m"], 0.0
        state, m, seconds = step_run(state, step, views, images, render_cfg)
        if m is not None:
            last["m"] = m
        return state, m, seconds

    run.steps.run = run_step
    if allocates:
        sample_eq6_counts(run.textures, dataset.train_views, sample)
    run.fresh()
    # No background compiles: on a few steps they would share the cores with the timed ones.
    saved = os.environ.get(AHEAD_ENV)
    os.environ[AHEAD_ENV] = "0"
    try:
        t0 = time.perf_counter()
        run.run()
    finally:
        if saved is None:
            os.environ.pop(AHEAD_ENV, None)
        else:
            os.environ[AHEAD_ENV] = saved
    # The timed steps compile nothing (the schedule puts every compile first: the first step, the
    # texture stage's start, Eq. 7's allocation); the other steps' extra time is compiling. A timed
    # step of more than COMPILED_STEP x the median compiled after all (beer's texture stage at 1/8: its
    # first timed step, 19 s against 287 ms): it counts as compiling, not as a step.
    untimed: dict[int, list[float]] = {1: [], 2: []}
    settled: list[float] = []
    prev_t = t0
    for step, t in stamps:
        if settling(step - 1):
            settled.append(t - prev_t)
        elif not timing(step - 1):
            untimed[stage_of(step - 1)].append(t - prev_t)
        prev_t = t
    if settled:  # (as the timed steps; a compiling one counts as the median step, so the count stays the run's)
        _, compiled, mid = _compiled_apart(settled)
        untimed[1] += compiled
        settled = [x if x <= COMPILED_STEP * mid else mid for x in settled]
    for k, v in timed.items():
        if v:
            timed[k], compiled, _ = _compiled_apart(v)
            untimed[k] += compiled
    med = {k: (statistics.median(v) if v else None) for k, v in timed.items()}
    comp = {k: max(0.0, sum(untimed[k]) - len(untimed[k]) * (med[k] or 0.0)) if med[k] else 0.0 for k in timed}
    out = dict(stage1=med[1], texture=med[2] if textured else None, stage1_gaussians=m, compile_stage1=comp[1],
               compile_texture=comp[2] if textured else 0.0, eval_view=None, eval_compile=None, steps=steps,
               timed_steps=dict(stage1=len(timed[1]), texture=len(timed[2])),
               step_ms=dict(stage1=[round(x * 1e3, 1) for x in timed[1]],
                            texture=[round(x * 1e3, 1) for x in timed[2]]),
               settled_ms=[round(x * 1e3, 1) for x in settled],
               padded_size=list(size), padded_sizes=n_sizes, eq6_views=len(sample),
               texture_layouts=(1 + (warm if allocates else 0)) if textured else 0, settled_steps=first1["step"] - 1)
    if not evaluate:
        return dict(out, seconds=time.perf_counter() - t_all)
    # Evaluation: a call fits its views' tile capacity and compiles its renderer for it, then renders
    # each view. 1 view: the compile and a render; the same view 3 times: the same capacity, so the
    # program is compiled already and the call is 3 renders.
    view = (list(dataset.test_views) or list(dataset.train_views))[0]
    say.phase(f"timing an evaluation render ({view.camera.width}x{view.camera.height} px, compiling it first)")
    t = time.perf_counter()
    evaluate_views(run.scene, [view], run.render_cfg)
    one = time.perf_counter() - t
    t = time.perf_counter()
    evaluate_views(run.scene, [view] * 3, run.render_cfg)
    three = time.perf_counter() - t
    eval_view = max(three / 3, 1e-4)
    eval_compile = max(one - eval_view, 0.0)
    # SSIM runs on the cropped image, so an evaluation compiles it once a view size: one compile more
    # (at a size beside the view's), timed on its own.
    h, w = view.camera.height, view.camera.width
    t = time.perf_counter()
    float(ssim(np.zeros((h + 1, w, 3), np.float32), np.zeros((h + 1, w, 3), np.float32)))
    ssim_compile = min(time.perf_counter() - t, eval_compile)
    return dict(out, eval_view=eval_view, eval_compile=eval_compile, ssim_compile=ssim_compile,
                seconds=time.perf_counter() - t_all)


def _one_size(views, config):
    """((height, width), number of distinct sizes, the views of that size): the training views'
    most common padded size (as the trainer pads them: the exact tile grid; ties: the largest)."""
    from collections import Counter

    from .padding import padded_shape

    tile = config.render_config(1).tile_size
    sizes = [padded_shape(v.camera.height, v.camera.width, tile) for v in views]
    counts = Counter(sizes)
    size = max(counts, key=lambda s: (counts[s], s[0] * s[1]))
    return size, len(counts), [v for v, s in zip(views, sizes) if s == size]


def _points_for(points, colors, n: int, seed: int):
    """``n`` initial points: a sample of ``points`` (M, 3), or all of them repeated with a jitter of a
    thousandth of their extent when M < n."""
    points = np.asarray(points, np.float32)
    if len(points) >= n:
        return points, colors
    rng = np.random.default_rng(seed)
    idx = np.concatenate([np.arange(len(points)), rng.integers(0, len(points), n - len(points))])
    extent = float(np.ptp(points, axis=0).max()) if len(points) > 1 else 1.0
    jitter = rng.normal(scale=1e-3 * extent, size=(len(idx), 3)).astype(np.float32)
    jitter[: len(points)] = 0
    return points[idx] + jitter, None if colors is None else np.asarray(colors)[idx]




def hms(seconds: float) -> str:
    """``seconds`` as ``"1h02m"`` (an hour or more) or ``"3m05s"``."""
    s = int(round(seconds))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def short_seconds(x: float | None) -> str:
    """A step's seconds as ``"120 ms"`` or ``"12.5 s"`` (``"-"`` for None)."""
    return "-" if x is None else (f"{x * 1e3:.0f} ms" if x < 10 else f"{x:.1f} s")
