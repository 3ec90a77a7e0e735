"""A run's time estimate and what it tells its user at the start and as it goes: the start line,
the estimate after the first clean steps of each stage, the note that says how to shorten a long
run, and the window of losses a progress line averages (the bars and the printing itself:
:mod:`patexgs_jax.progress`).
"""

from __future__ import annotations

import collections
import os
import time
from collections.abc import Callable

import jax
import numpy as np

from .config import PRESETS, TrainConfig

__all__ = ["LONG_RUN_SECONDS", "TEXTURED_STEP_COST", "Estimate", "device_description", "format_seconds",
           "long_run_note", "preset_name", "run_estimate", "start_line", "step_seconds", "typical_size", "StepWindow"]

#: A textured step's cost in 2DGS steps, for the time estimate made before the texture stage is
#: measured (the measured ratios: docs/performance.md).
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


def preset_name(config: TrainConfig) -> str | None:
    """The preset whose step counts ``config`` has, or None."""
    for name, kw in PRESETS.items():
        steps = tuple(kw.get(k, getattr(TrainConfig, k)) for k in ("iters_2dgs", "iters_tex"))
        if steps == (config.iters_2dgs, config.iters_tex):
            return name
    return None


def start_line(dataset, config: TrainConfig, step: int = 0, preset: str | None = None) -> str:
    """What a run will do, in one line: method, images, views, preset, schedule, Gaussian cap,
    device; ``step``: where it starts. ``preset``: the preset the config was made from (default: the
    one with its step counts)."""
    n_sizes = len({(v.camera.width, v.camera.height) for v in dataset.train_views})
    size = "{}x{} px".format(*typical_size(dataset.train_views)) + (
        f" (and {n_sizes - 1} other size{'s' if n_sizes > 2 else ''})" if n_sizes > 1 else "")
    preset = preset or preset_name(config)
    spec = config.spec
    steps = (f"{config.iters_2dgs} {spec.stage1_name} steps" if spec.textures is None and not config.continue_2dgs
             else f"{config.iters_2dgs} + {config.total_steps - config.iters_2dgs} steps")
    cap = "no Gaussian cap" if config.max_gaussians is None else f"at most {config.max_gaussians:,} Gaussians"
    where = "" if step == 0 else f", from step {step}"
    return (f"training {config.method}: {len(dataset.train_views)} training and {len(dataset.test_views)} test "
            f"views of {size}; {'preset ' + preset + ', ' if preset else ''}{steps}{where}; {cap}; "
            f"on {device_description()}")


class Estimate:
    """The time estimate of a run: the durations of steps that compiled nothing, per stage; after
    the first few steps of each stage it says (``say``) how long the rest of the run will take, and
    the first time, when the whole run takes over :data:`LONG_RUN_SECONDS`, how to shorten it.
    ``views``: the training views; ``factor``: the images' downsampling."""

    def __init__(self, config: TrainConfig, views, factor: float, say: Callable[[str], None]):
        self.cfg, self.views, self.factor, self.say = config, views, factor, say
        self.clean_steps: dict[int, list[float]] = {1: [], 2: []}
        self.estimated: set[int] = set()  # the stages whose steps gave an estimate

    def measure(self, step: int, seconds: float) -> None:
        """Records ``seconds``, the duration of step ``step`` (one that compiled nothing)."""
        cfg = self.cfg
        stage = 1 if cfg.in_stage1(step) else 2
        times = self.clean_steps[stage]
        times.append(seconds)
        if stage in self.estimated or not (len(times) >= 10 or (len(times) >= 2 and sum(times) >= 20.0)):
            return
        first = not self.estimated
        self.estimated.add(stage)
        per = float(np.median(times))
        textured = cfg.spec.textures is not None
        left, whole = run_estimate(cfg, textured, step, stage, per)
        guess = (f", a textured step taken as {TEXTURED_STEP_COST:g}x that"
                 if stage == 1 and textured and cfg.iters_tex else "")
        self.say(f"estimated time: {format_seconds(left)} for the {cfg.total_steps - step} steps left "
                 f"({1e3 * per:.0f} ms a {cfg.stage_name(step)} step{guess}), plus compiles and the evaluation")
        if first and whole > LONG_RUN_SECONDS:
            width, height = typical_size(self.views)
            self.say(long_run_note(cfg, step_seconds(textured, stage, per), width, height, self.factor))


class StepWindow:
    """The losses and PSNRs of the good steps since the last progress line, and its time."""

    def __init__(self, log_every: int):
        self.log_every = log_every
        self.values: collections.deque = collections.deque(maxlen=max(1, log_every))
        self.t_last = time.perf_counter()

    def add(self, m: dict) -> None:
        self.values.append((float(m["loss"]), float(m["psnr"])))

    def take(self) -> tuple[float, float, float]:
        """(mean loss, mean PSNR, ms per step over ``log_every`` steps) since the last call; restarts."""
        now = time.perf_counter()
        means = [float(np.mean([v[k] for v in self.values])) if self.values else float("nan") for k in (0, 1)]
        ms = 1e3 * (now - self.t_last) / self.log_every
        self.t_last = now
        self.values.clear()
        return means[0], means[1], ms
