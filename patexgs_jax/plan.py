"""A run's plan before it trains: sizes, steps, Gaussians, Eq. 7 texels, peak memory, time, fit.

``python -m patexgs_jax.train ... --plan`` (and ``python -m experiments.mipnerf360 ... --plan``)
calls :func:`make_plan`: the views' padded sizes, the steps of each stage, the Gaussian count the
run plans for and the texels Eq. 7 gives at that count (:mod:`patexgs_jax.plan_counts`), the peak
memory of the 2DGS stage, the texture stage and evaluation (on this process's device and, when
asked, on another: :func:`parse_device`; :mod:`patexgs_jax.plan_memory`), the time per step of
each stage measured by a few real steps (:func:`measure_steps`, saying what it measures at least
every 10 s; on a CPU, a run whose 2DGS steps alone take days times nothing else and estimates the
rest from them), the whole run's time, what would not fit with the flag that makes it fit
(:func:`fixes`), for a run of days on a CPU its time on an H100 and what trains here in an hour or
a night (:mod:`patexgs_jax.plan_advice`), and which of these figures are measured, extrapolated,
estimated or modelled (:attr:`Plan.figures`).

The memory model (:mod:`patexgs_jax.plan_memory`, pure functions; docs/memory.md has its terms and
its measured error):

  peak = base + per-pixel bytes x padded pixels of the largest view + per-Gaussian bytes x
         Gaussians + texture bytes x RGBA texels (+ on a CPU, the images the dataset caches)

* CPU (the process's peak resident memory, ``ru_maxrss``): the per-stage base
  (:data:`CPU_BASE_BYTES`) is calibrated on the short real runs of ``python -m
  experiments.plan_check`` (fresh processes), the per-pixel term on :mod:`patexgs_jax.memory`'s
  measurements at 1-12 MP; the per-Gaussian and texture terms are counted. (The memory check of
  :mod:`patexgs_jax.memory` keeps its own base, above every training-step peak it was calibrated on.)
* GPU (the device's peak bytes in use): the per-Gaussian and per-texel terms measured on one H100
  (:data:`GPU_BYTES_PER_GAUSSIAN`, :data:`GPU_BYTES_PER_TEXEL`: ``experiments.bench_scale``'s
  training steps at 1M and 3M Gaussians); the rest counted. Per pixel: the CPU's per-pixel
  arrays (accumulators and their cotangents, outputs, loss terms), and, with the XLA compositor
  (the Pallas kernel, a GPU's default, keeps its per-pair state on the chip), the compositor's working
  memory, :data:`patexgs_jax.rendering.tiling.PAIR_BYTES` per (tile pixel, chunk slot) of the
  tiles it advances at once (all of them, up to a quarter of the device:
  :func:`patexgs_jax.rendering.tiling.choose_tile_batch`). Per Gaussian: parameters, gradients, two
  Adam moments and the updated copy, the projection's per-splat rows and their cotangents.
  Textures: RGBA float32 texels as parameter, gradient and two Adam moments, the mip levels
  (another third) for the forward and its cotangent, and the texture buckets' headroom.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os

from . import memory, plan_advice
from .padding import padded_shape
from .plan_counts import UNCAPPED_GAUSSIANS, densify_events, eq7_texels, mean_stage1_gaussians, planned_gaussians
from .plan_devices import DEVICES, GB, Device, parse_device, this_device
from .plan_memory import (
    CPU_BASE_BYTES,
    CPU_SIZE_BYTES,
    GPU_BYTES_PER_GAUSSIAN,
    GPU_BYTES_PER_TEXEL,
    fixes,
    gaussian_bytes,
    memory_plan,
    padded_pixels,
    pixel_bytes,
    stage_peaks,
    texture_bytes,
)
from .plan_steps import Progress, hms, measure_steps, short_seconds

__all__ = [
    "CPU_BASE_BYTES",
    "CPU_SIZE_BYTES",
    "DEVICES",
    "GPU_BYTES_PER_GAUSSIAN",
    "GPU_BYTES_PER_TEXEL",
    "Device",
    "Plan",
    "UNCAPPED_GAUSSIANS",
    "check_fits",
    "eq7_texels",
    "fixes",
    "gaussian_bytes",
    "make_plan",
    "mean_stage1_gaussians",
    "memory_plan",
    "measure_steps",
    "padded_pixels",
    "parse_device",
    "pixel_bytes",
    "planned_gaussians",
    "stage1_method",
    "stage_peaks",
    "texture_bytes",
    "this_device",
]

# -- the plan ------------------------------------------------------------------------------------


@dataclasses.dataclass
class Plan:
    """A run's plan: what :func:`make_plan` found (see :meth:`to_json` for the units)."""

    method: str
    views: list  # [{"name", "split", "width", "height", "padded_width", "padded_height"}]
    steps: dict  # {"stage1", "texture"}
    gaussians: int
    gaussians_from: str
    texels_eq7: int
    texels_max: int
    sigma: float | None
    sigma_from: str
    devices: list  # [{"device", "kind", "memory_bytes", "peak_bytes", "fits", "fixes"}]
    step_seconds: dict
    measured: dict
    total_seconds: float | None
    time_terms: dict
    advice: list = dataclasses.field(default_factory=list)  # lines: where the run belongs, what fits here
    ahead_steps: int = 0  # 2DGS steps beside the texture stage's compile ahead (:func:`ahead_steps`)
    # the texture stage's step programs: {"layouts", "growth_events", "growth_layouts", "seconds_each",
    # "warmup_ahead_steps"} (:func:`texture_layouts`, :func:`growth_layouts`)
    compiles: dict = dataclasses.field(default_factory=dict)
    # {figure: {"how": "measured" | "extrapolated" | "estimated" | "modelled" | "not measured", "from": words}}
    figures: dict = dataclasses.field(default_factory=dict)

    @property
    def fits(self) -> bool:
        """Whether the run fits on this device (the first of :attr:`devices`)."""
        return bool(self.devices[0]["fits"])

    def to_json(self) -> dict:
        """The plan as JSON: every figure's unit in its name or beside it, and in ``figures`` how
        each was found (measured here, extrapolated from a measurement, estimated without one,
        modelled)."""
        here = self.devices[0]
        return dict(
            method=self.method, units=dict(bytes="B", seconds="s", texels="RGBA texels (float32 x 4 each)"),
            views=self.views, steps=self.steps, gaussians=self.gaussians, gaussians_from=self.gaussians_from,
            texels_eq7=self.texels_eq7, texels_max=self.texels_max, sigma=self.sigma, sigma_from=self.sigma_from,
            device=here["device"], memory_bytes=here["memory_bytes"], peak_bytes=here["peak_bytes"],
            fits=self.fits, fixes=here["fixes"], devices=self.devices, step_seconds=self.step_seconds,
            measured=self.measured, total_seconds=self.total_seconds, time_terms_seconds=self.time_terms,
            advice=self.advice, ahead_steps=self.ahead_steps, compiles=self.compiles, figures=self.figures)

    def text(self) -> str:
        """The plan as lines for a terminal."""
        sizes: dict[tuple, int] = {}
        for v in self.views:
            k = (v["split"], v["width"], v["height"], v["padded_width"], v["padded_height"])
            sizes[k] = sizes.get(k, 0) + 1
        lines = [f"plan for {self.method} (nothing is trained or written):"]
        for (split, w, h, pw, ph), n in sorted(sizes.items()):
            lines.append(f"  {n:4d} {split} views {w}x{h}, padded {pw}x{ph}")
        lines.append(f"  steps: {self.steps['stage1']} (2DGS stage) + {self.steps['texture']} (texture stage)")
        lines.append(f"  Gaussians: {self.gaussians:,} ({self.gaussians_from})")
        if self.texels_max:
            lines.append(f"  texels (RGBA): {self.texels_eq7:,} after Eq. 7 ({self.sigma_from}), up to "
                         f"{self.texels_max:,} with growth ({self.texels_max * 16 / 2**20:.1f} MiB)")
        if self.total_seconds is None:
            lines.append("  step time: not measured (--plan-steps 0)")
        else:
            lines.extend(self._time_lines())
            lines.extend(f"  {a}" for a in self.advice)
        for d in self.devices:
            p = d["peak_bytes"]
            lines.append(f"  peak memory on {d['device']}: 2DGS {p['stage1'] / GB:.2f} GB, texture "
                         f"{p['texture'] / GB:.2f} GB, evaluation {p['eval'] / GB:.2f} GB of "
                         f"{d['memory_bytes'] / GB:.1f} GB: {'fits' if d['fits'] else 'does NOT fit'}")
            if d["fixes"]:
                lines.append("    to fit, pass " + "; or ".join(d["fixes"]))
            elif not d["fits"]:
                lines.append("    no flag alone makes it fit: fewer or smaller images, or a larger device")
        lines.extend(self._figure_lines())
        return "\n".join(lines)

    def _time_lines(self) -> list[str]:
        m, lines = self.measured, []
        at = f" at {m['padded_size'][1]}x{m['padded_size'][0]} px, 1 of {m['padded_sizes']} sizes" if m.get(
            "padded_size") else ""
        t1, t2 = short_seconds(self.step_seconds["stage1"]), short_seconds(self.step_seconds["texture"])
        tex = "texture" if not m.get("texture_estimated") else "texture (estimated)"
        beside = (f"; {self.ahead_steps:,} of its {self.steps['stage1']:,} steps beside the texture stage's compile "
                  f"ahead, at {AHEAD_SLOWDOWN:g}x") if self.ahead_steps else ""
        trained = (f"; a mean step: its first {m['settled_steps']:,} as the plan trained its scene untimed, "
                   "then the timed ones") if m.get("settled_steps") else ""
        lines.append(f"  step time (this device, {_timed(m)}{at}, {m['seconds']:.0f} s): 2DGS "
                     f"{t1} (at {m.get('stage1_gaussians', m['gaussians']):,} Gaussians, the stage's mean"
                     f"{trained}{beside}), "
                     f"{tex} {t2} (at {m['gaussians']:,}){'; ' + m['note'] if m.get('note') else ''}")
        tt, c = self.time_terms, self.compiles
        lines.append(f"  whole run: {hms(self.total_seconds or 0.0)} ({hms(tt['stage1'])} 2DGS + "
                     f"{hms(tt['texture'])} textures + {hms(tt['compile'])} compiling + "
                     f"{hms(tt['eval'])} evaluation)")
        if c.get("growth_events"):
            lines.append(f"  texture step compiles: {c['layouts']} layouts and {c['growth_layouts']:.1f} new ones "
                         f"from {c['growth_events']} growth events ({GROWTH_LAYOUT_SHARE:.0%} of them overflow a "
                         f"bucket), {short_seconds(c['seconds_each'])} each")
        return lines

    def _figure_lines(self) -> list[str]:
        """One line per kind of figure: which are measured, extrapolated, estimated, modelled."""
        by: dict[str, list[str]] = {}
        for name, f in self.figures.items():
            by.setdefault(f["how"], []).append(f"{name} ({f['from']})")
        return [f"  {how}: " + "; ".join(names) for how, names in by.items()]


#: On a CPU the plan times steps at no more than this many Gaussians and padded pixels, and scales.
MEASURE_MAX_GAUSSIANS = 10_000
MEASURE_MAX_PIXELS = 1 << 20
#: Steps timed a stage where the plan extrapolates anyway (the count scaled linearly); its Eq. 7
#: allocation then runs at the texture stage's start (no warm-up step: one compile less).
EXTRAPOLATED_STEPS = 2
#: Where the 2DGS stage's timed steps alone put a CPU run beyond :data:`ESTIMATE_BEYOND` (every
#: textured step costs at least a 2DGS one), the plan times nothing else and estimates the
#: rest from that stage, at ratios inside the spreads measured on this project's CPU (docs/memory.md,
#: "The plan's own time"): a textured step over a 2DGS step;
TEXTURE_STEP_RATIO = 2.0
#: The run's time here past which the plan estimates the texture stage rather than timing it: the
#: longest CPU budget the advice names (a night). Beyond it the run fits no budget here, so the
#: advice does not hang on the texture stage's exact cost; a threshold at a day flips with the step's
#: noise on captures whose floor lies near it (docs/memory.md, "The plan's own time").
ESTIMATE_BEYOND = plan_advice.BUDGETS[-1][0]
#: a texture layout's compiles (its step; at the allocation, Eq. 6's counter and counts too) over
#: the 2DGS stage's;
TEXTURE_COMPILE_RATIO = 2.0
#: an evaluation render (a forward pass of the textured scene) over a 2DGS step;
EVAL_STEP_SHARE = 0.3
#: and its compile over the 2DGS step's.
EVAL_COMPILE_SHARE = 0.5


#: On a CPU a textured run compiles its texture stage's first programs ahead, in the background,
#: from its 2DGS stage's last densification (:mod:`patexgs_jax.training.compile_ahead`): the 2DGS
#: steps beside that compile take this many times as long (2.0: the embedded scene's last 50 steps
#: of stage 1, against the same steps of its ``2dgs`` run, docs/memory.md), and the compile they share
#: the cores with is not waited for at the texture stage's start.
AHEAD_SLOWDOWN = 2.0
#: Each padded size of the training views past the first adds this share of one layout's compile
#: (the plan's measured compile of a texture layout) to what a textured run's 2DGS stage compiles
#: ahead: Eq. 7's pair counter and renderer are compiled for every padded size
#: (:meth:`patexgs_jax.padding.ViewRenderer.compile`), the start's textured step for one. 0.6: beer
#: at 1/4 (three padded sizes; benchmarks/plan_check_cpu_idle_cold_2f15410.json, the calibration
#: row, docs/memory.md): Eq. 7's programs took 40 s ahead there, 13 s a size, against the plan's
#: 21.7 s a layout; and its 98 steps beside the compile ahead at 2 x 249 ms make 49 s, 2.25 layouts'
#: compile, (2.25 - 1) / 2 = 0.63 a size. (The main thread's compiles of the other sizes' 2DGS
#: steps fall in that window too, 17 + 15 s: they lengthen the compile ahead by about their own time
#: and take no steps, so they add no steps beside it.)
AHEAD_SIZE_SHARE = 0.6


#: The share of a run's Eqs. 8-10 growth events that overflow a texture bucket: the layout is made
#: anew and the textured step compiles again, in the main thread (docs/memory.md, "Measured error
#: (CPU)": the calibration runs' events, counted from their ``summary.json``).
GROWTH_LAYOUT_SHARE = 0.14


def texture_layouts(config) -> int:
    """The texture stage's layouts whose textured step a run compiles, growth aside: its start's
    (5x5 alpha and 1x1 RGB, or a fixed method's N x N) and, for an adaptive method with a warm-up,
    Eq. 7's allocation's (without a warm-up the allocation runs at the start: one layout). 0 without
    textures."""
    spec = config.spec
    if spec.textures is None:
        return 0
    return 2 if spec.textures == "adaptive" and config.warmup_tex > 0 else 1


def growth_layouts(config) -> tuple[int, float]:
    """(the run's Eqs. 8-10 growth events, the new layouts they are expected to make:
    :data:`GROWTH_LAYOUT_SHARE` of them); (0, 0.0) for a method that does not grow."""
    from .schedule import growth_steps

    if not config.spec.grows:
        return 0, 0.0
    events = len(growth_steps(config))
    return events, GROWTH_LAYOUT_SHARE * events


def warmup_ahead_steps(config, t2: float | None, compile_seconds: float, kind: str) -> int:
    """How many texture warm-up steps share this device's cores with compiling the step of Eq. 7's
    predicted layout ahead (from the stage's start until ``compile_seconds`` of compiling are done, at
    :data:`AHEAD_SLOWDOWN` x ``t2`` a step; at most the warm-up): as :func:`ahead_steps`, for an
    adaptive method with a warm-up."""
    from . import background

    if (kind != "cpu" or texture_layouts(config) < 2 or config.batch_size != 1 or not background.enabled()
            or not t2 or compile_seconds <= 0):
        return 0
    return int(min(config.warmup_tex, compile_seconds / (AHEAD_SLOWDOWN * t2)))


def ahead_seconds(compile_seconds: float, sizes: int = 1) -> float:
    """The seconds a textured run's 2DGS stage compiles ahead beside its steps: one layout's
    ``compile_seconds`` at one padded size, and :data:`AHEAD_SIZE_SHARE` of it for each of the
    training views' other ``sizes`` (Eq. 7's pair counter and renderer, compiled for each)."""
    return compile_seconds * (1.0 + AHEAD_SIZE_SHARE * max(int(sizes) - 1, 0))


def ahead_steps(config, t1: float | None, compile_seconds: float, kind: str, sizes: int = 1) -> int:
    """How many 2DGS steps share this device's cores with compiling the texture stage's first
    programs ahead: from the stage's last densification event (from its start without one) until
    :func:`ahead_seconds` of compiling (``compile_seconds`` a layout, the views in ``sizes`` padded
    sizes) are done, at :data:`AHEAD_SLOWDOWN` x ``t1`` seconds a step. 0 on a GPU (the host
    compiles beside the device's steps), without textures, with a batch, or with compiling ahead
    off (``PATEXGS_COMPILE_AHEAD=0``)."""
    from . import background

    if (kind != "cpu" or config.spec.textures is None or config.batch_size != 1 or not background.enabled()
            or not t1 or compile_seconds <= 0):
        return 0
    events = densify_events(config)
    window = config.iters_2dgs - (events[-1] if events else 0)
    return int(min(window, ahead_seconds(compile_seconds, sizes) / (AHEAD_SLOWDOWN * t1)))


def stage1_method(config) -> str | None:
    """The method whose run is ``config``'s 2DGS stage alone (the same step program: every 2D
    method's first stage renders as 2DGS), or None when there is none (a 2D method with the 3D
    filter has its own first stage)."""
    spec = config.spec
    if spec.textures is None:
        return config.method
    return "2dgs" if spec.primitive == "2d" and not spec.filter3d else None


def make_plan(dataset, config, *, devices=(), measure: bool = True, steps: int = 5,
              measured: dict | None = None, progress: bool | Progress = True) -> Plan:
    """The plan of training ``config`` on ``dataset`` (see the module docstring).

    Args:
      dataset: a loaded :class:`patexgs_jax.data.Dataset`.
      config: the run's TrainConfig.
      devices: other :class:`Device` s to plan for (this process's device comes first).
      measure: time real steps (:func:`measure_steps`); False leaves the step times None.
      steps: timed steps a stage.
      measured: step times already measured for this dataset and config (skips measuring).
      progress: say what is measured while measuring (:class:`patexgs_jax.plan_steps.Progress`: a line
        at least every 10 s), or a Progress to say it with; False: silent.
    """
    spec = config.spec
    n, n_from = planned_gaussians(config, len(dataset.points))
    train_px = [v.camera.width * v.camera.height for v in dataset.train_views]
    texels, texels_max, sigma, sigma_from = eq7_texels(train_px, n, config)
    views = []
    for split, vs in (("train", dataset.train_views), ("test", dataset.test_views)):
        for v in vs:
            w, h = v.camera.width, v.camera.height
            ph, pw = padded_shape(h, w)
            views.append(dict(name=v.name, split=split, width=w, height=h, padded_width=pw, padded_height=ph))
    here = this_device()
    images = memory.cached_image_bytes(dataset)
    plans = [memory_plan(dataset, config, n, texels_max, d, images) for d in (here, *devices)]
    steps1 = config.iters_2dgs + (config.continue_2dgs if spec.textures is None else 0)
    steps2 = config.iters_tex if spec.textures is not None else 0
    if measured is None and measure:
        pr = progress if isinstance(progress, Progress) else Progress() if progress else None
        with pr if pr is not None else contextlib.nullcontext():
            measured = _measure(dataset, config, n, plans[0]["fits"], here, steps, steps1 + steps2, pr)
    elif measured is None:
        measured = dict(stage1=None, texture=None, compile_stage1=0.0, compile_texture=0.0, eval_view=0.0,
                        eval_compile=0.0, steps=0,
                        seconds=0.0, gaussians=n, scale=1.0, note="not measured")
    sc = measured.get("scale", 1.0)
    t1 = None if measured["stage1"] is None else measured["stage1"] * sc
    t2 = None if measured.get("texture") is None else measured["texture"] * sc
    n_eval = len(dataset.test_views) + min(len(dataset.train_views), 32)  # as train() evaluates
    dens = config.densify
    doublings = max(0, math.ceil(math.log2(max(n, 1) / max(len(dataset.points), 1)))) if dens.stop > dens.start else 0
    sizes = measured.get("padded_sizes", 1)  # (each padded size of the training views compiles its steps)
    # The texture stage's step compiles: the measured compile of one layout (the plan times one or two:
    # ``texture_layouts``, one where older or stubbed) for each layout the run makes, growth's included.
    each = measured["compile_texture"] / max(int(measured.get("texture_layouts") or 1), 1)
    events, grown = growth_layouts(config)
    layouts = texture_layouts(config) + grown
    # The 2DGS steps beside the start's compile ahead and the warm-up's beside the Eq. 7 layout's: slower,
    # and those compiles are done by the stages' ends.
    k = ahead_steps(config, t1, each, here.kind, sizes)
    k2 = warmup_ahead_steps(config, t2, each, here.kind)
    beside, beside2 = k * (t1 or 0.0), k2 * (t2 or 0.0)
    compiles = sizes * (measured["compile_stage1"] * (1 + doublings) + each * layouts)
    # The run's first 2DGS steps as the plan trained its scene before timing it (``settled_ms``: a scene's
    # steps get cheaper as it trains), the others at the timed step; the stage's step is their mean.
    first = [x * 1e-3 * sc for x in (measured.get("settled_ms") or [])][:steps1]
    stage1 = sum(first) + (steps1 - len(first)) * (t1 or 0.0)
    terms = dict(stage1=stage1 + beside * (AHEAD_SLOWDOWN - 1),
                 texture=steps2 * (t2 or 0.0) + beside2 * (AHEAD_SLOWDOWN - 1),
                 compile=max(0.0, compiles - (beside + beside2) * AHEAD_SLOWDOWN),
                 eval=n_eval * measured["eval_view"] * sc + _eval_compiles(dataset, config, measured))
    compiled = dict(layouts=texture_layouts(config), growth_events=events, growth_layouts=grown, seconds_each=each,
                    warmup_ahead_steps=k2) if spec.textures is not None else {}
    if t1 is not None and (first or k):  # (the stage's step: the mean of its steps, those beside the compile
        t1 = terms["stage1"] / max(steps1, 1)  # ahead slower: a median flips between the two at half the stage)
    total = None if t1 is None else float(sum(terms.values()))
    advice = []
    if total is not None and here.kind == "cpu" and total > plan_advice.ABSURD_SECONDS:
        advice = plan_advice.advice_lines(dataset, config, measured, total, n=n, steps1=steps1, steps2=steps2,
                                          n_eval=n_eval, compile_seconds=terms["compile"], sizes=sizes,
                                          texels=texels_max)
    figures = _figures(measured, textured=spec.textures is not None, n=n, n_from=n_from, sigma_from=sigma_from,
                       advice=bool(advice))
    return Plan(method=config.method, views=views, steps=dict(stage1=steps1, texture=steps2), gaussians=n,
                gaussians_from=n_from, texels_eq7=texels, texels_max=texels_max, sigma=sigma, sigma_from=sigma_from,
                devices=plans, step_seconds=dict(stage1=t1, texture=t2), measured=measured,
                total_seconds=total, time_terms=terms, advice=advice, ahead_steps=k, compiles=compiled,
                figures=figures)


def _eval_compiles(dataset, config, measured: dict) -> float:
    """Seconds the run's evaluation compiles: its renderer and pair counter once a padded size of
    the views it evaluates (32 training, every test view: one renderer for both), SSIM once a view
    size (:func:`patexgs_jax.evaluation.eval_programs`), at the plan's measured compiles
    (``eval_compile`` holds one of each; ``ssim_compile``, SSIM's alone, 0 where not measured)."""
    from .evaluation import eval_programs

    renders, ssims = eval_programs((dataset.train_views[:32], dataset.test_views), config.render_config())
    each, ssim = measured.get("eval_compile", 0.0) or 0.0, measured.get("ssim_compile", 0.0) or 0.0
    return renders * (each - ssim) + ssims * ssim


def _measure(dataset, config, n: int, fits: bool, here: Device, steps: int, all_steps: int, pr) -> dict:
    """:func:`measure_steps` as the plan uses it: at the planned count, or, on a CPU above
    :data:`MEASURE_MAX_GAUSSIANS` (or past its memory), at that count scaled linearly, timing the
    2DGS stage first and, when its steps alone make the run longer than a night here, nothing else
    (the texture stage, the evaluation and their compiles then estimated from it)."""
    m_n, scale, note = n, 1.0, ""
    px = max(padded_pixels(v.camera.width, v.camera.height) for v in dataset.train_views)
    timed, quick = steps, False
    if here.kind == "cpu" and (n > MEASURE_MAX_GAUSSIANS or px > MEASURE_MAX_PIXELS or not fits):
        m_n = min(n, MEASURE_MAX_GAUSSIANS)
        scale = max(n / m_n, 1.0)
        timed, quick = min(steps, EXTRAPOLATED_STEPS), True  # (scaled anyway: fewer steps, one compile less)
        note = f"measured at {m_n:,} Gaussians and scaled by {scale:.3g} (linear in the count: an extrapolation)"
    mean = mean_stage1_gaussians(config, len(dataset.points), n) * m_n // max(n, 1)
    first = stage1_method(config) if quick else None
    if first is not None:
        alone = dataclasses.replace(config, method=first, continue_2dgs=0)
        got = measure_steps(dataset, alone, m_n, steps=timed, stage1_gaussians=mean, quick=quick, progress=pr,
                            evaluate=False)
        floor = got["stage1"] * all_steps  # (unscaled: a step of more Gaussians takes no less)
        if floor > ESTIMATE_BEYOND:
            if pr is not None:
                pr.phase(f"the 2DGS step's {short_seconds(got['stage1'])} makes {all_steps:,} steps at least "
                         f"{hms(floor)} here, past a night: nothing else is timed (the texture stage, the "
                         "evaluation and their compiles are estimated from the 2DGS step)")
            return dict(_estimated_rest(got, config), gaussians=m_n, scale=scale, note=note)
        if pr is not None:
            pr.phase(f"the run's {all_steps:,} steps take at least {hms(floor)} here (each at least a 2DGS step): "
                     "timing the rest")
    got = measure_steps(dataset, config, m_n, steps=timed, stage1_gaussians=mean, quick=quick, progress=pr)
    return dict(got, gaussians=m_n, scale=scale, note=note)


def _estimated_rest(got: dict, config) -> dict:
    """``got`` (the 2DGS stage timed alone) with the texture stage and the evaluation estimated
    from its step and compile (:data:`TEXTURE_STEP_RATIO` and the rest)."""
    textured = config.spec.textures is not None
    return dict(got, texture=TEXTURE_STEP_RATIO * got["stage1"] if textured else None,
                compile_texture=TEXTURE_COMPILE_RATIO * got["compile_stage1"] if textured else 0.0,
                texture_layouts=1 if textured else 0,
                eval_view=EVAL_STEP_SHARE * got["stage1"], eval_compile=EVAL_COMPILE_SHARE * got["compile_stage1"],
                texture_estimated=textured, eval_estimated=True, eq6_views=0)


def _timed(m: dict) -> str:
    """The steps timed, in words: ``"5 timed steps a stage"``, ``"31 + 12 timed steps"`` (2DGS +
    texture) or ``"31 timed steps"`` (the 2DGS stage alone)."""
    k = m.get("timed_steps")
    if k is None:  # (measured by an older plan, or stubbed: ``steps`` a stage)
        return f"{m['steps']} timed steps a stage"
    k1, k2 = k["stage1"], k.get("texture")
    if not k2:
        return f"{k1} timed steps"
    return f"{k1} timed steps a stage" if k1 == k2 else f"{k1} + {k2} timed steps"


def _figures(m: dict, *, textured: bool, n: int, n_from: str, sigma_from: str, advice: bool) -> dict:
    """How each figure of the plan was found: ``{name: {"how", "from"}}``."""
    def f(how, words):
        return dict(how=how, **{"from": words})

    out = dict(gaussians=f("modelled", n_from.split(":")[0]),
               peak_bytes=f("modelled", "docs/memory.md's terms at the planned counts and sizes"))
    if textured:
        out["texels"] = f("modelled", f"Eq. 7 with every Gaussian the same share of every view's pixels; {sigma_from}")
    if m.get("stage1") is None:
        out["step_seconds"] = f("not measured", "--plan-steps 0")
        return out
    sc, size = m.get("scale", 1.0), m.get("padded_size")
    at = f"{size[1]}x{size[0]} px" if size else "the views' size"
    timed = f"median of {_timed(m)} at {at}"
    if sc > 1:
        how, words = "extrapolated", f"{timed}, {m['gaussians']:,} Gaussians timed, scaled x{sc:.3g} to {n:,}"
    else:
        how, words = "measured", timed
    out["step_seconds.stage1"] = f(how, words)
    if textured:
        out["step_seconds.texture"] = (f("estimated", f"{TEXTURE_STEP_RATIO:g} x the 2DGS step; not timed")
                                       if m.get("texture_estimated") else f(how, words))
    first = "the first steps' time beyond a steady step"
    out["time_terms.compile"] = (f("estimated", f"the 2DGS stage's measured; the texture stage's "
                                                f"{TEXTURE_COMPILE_RATIO:g} x it") if m.get("texture_estimated")
                                 else f("measured", first))
    out["time_terms.eval"] = (f("estimated", f"a render {EVAL_STEP_SHARE:g} x the 2DGS step, its compile "
                                             f"{EVAL_COMPILE_SHARE:g} x the step's; not timed")
                              if m.get("eval_estimated") else f(how if sc > 1 else "measured",
                                                                "one render timed after its compile; the "
                                                                "compile once a padded size, SSIM's once a "
                                                                "view size"))
    if advice:
        out["advice"] = f("extrapolated", "the timed steps scaled linearly in Gaussians and pixels; the H100 "
                                          "from its measured steps")
    return out


def check_fits(dataset, config, gaussians: int, device: Device | None = None) -> dict:
    """Raises :class:`patexgs_jax.memory.NotEnoughMemory` when the run would not fit: on this
    process's CPU (``device`` None), its step beside what the process holds already
    (:func:`patexgs_jax.memory.check_training_memory`); then on ``device`` (default
    :func:`this_device`, CPU or GPU), a stage of the run (2DGS, texture, evaluation) at its peak,
    with the flags of :func:`fixes`. ``PATEXGS_SKIP_MEMORY_CHECK=1`` skips both.

    Args:
      dataset, config: the run's.
      gaussians: the Gaussian slots the run holds (its cap, else its scene's capacity).
    Returns:
      :func:`memory_plan`'s dict.
    """
    spec = config.spec
    if device is None:
        memory.check_training_memory(dataset, gaussians=gaussians, textured=spec.textures is not None)
    images = memory.cached_image_bytes(dataset)
    device = device or this_device()
    texels = 0
    if spec.textures is not None:
        texels = eq7_texels([v.camera.width * v.camera.height for v in dataset.train_views], gaussians, config)[1]
    mp = memory_plan(dataset, config, gaussians, texels, device, images)
    if mp["fits"] or os.environ.get(memory._ENV_SKIP, "") not in ("", "0"):
        return mp
    stage, peak = max(mp["peak_bytes"].items(), key=lambda kv: kv[1])
    name = dict(stage1="the 2DGS stage", texture="the texture stage", eval="evaluation")[stage]
    hint = "; or ".join(mp["fixes"]) or "fewer or smaller images (no flag alone fits)"
    raise memory.NotEnoughMemory(
        f"Not enough memory to train {config.method}: {name} needs about {peak / GB:.1f} GB at its peak "
        f"({gaussians:,} Gaussians, {texels:,} RGBA texels) and {device.name} has {device.memory_bytes / GB:.1f} GB. "
        f"To fit, pass {hint}; or set {memory._ENV_SKIP}=1 to train anyway. "
        "(python -m patexgs_jax.train ... --plan shows the whole plan.)")
