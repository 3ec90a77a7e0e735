"""What a run plan adds when its run would take days on this CPU (:mod:`patexgs_jax.plan`): the
run's time on one H100 (:func:`patexgs_jax.plan_devices.h100_run_seconds`), and what trains here in
an hour or in a night: a preset, a ``--factor`` and a ``--max-gaussians`` cap, each timed by scaling
the plan's own timed steps (:func:`scaled_seconds`)."""

from __future__ import annotations

import dataclasses

from .plan_counts import mean_stage1_gaussians, planned_gaussians
from .plan_devices import DEVICES, H100_STEPS, h100_run_seconds
from .plan_memory import memory_plan, padded_pixels
from .plan_steps import hms

__all__ = ["ABSURD_SECONDS", "BUDGETS", "CAPS", "PRESETS_TRIED", "advice_lines", "best_options", "scaled_seconds"]

#: A planned run longer than this on a CPU is said to belong on a GPU.
ABSURD_SECONDS = 24 * 3600
#: The time budgets the plan names a run for: (seconds, words).
BUDGETS = ((3600, "in an hour"), (10 * 3600, "in a night (10 h)"))
#: The presets tried for them (more steps first) and the Gaussian caps.
PRESETS_TRIED = ("small", "cpu")
CAPS = (1_000_000, 300_000, 100_000, 50_000, 30_000, 20_000, 10_000, 6_000, 3_000)
#: Downsampling factors tried, as multiples of the plan's own, down to views of MIN_SIDE px.
FACTOR_STEPS = (1, 2, 4, 8)
MIN_SIDE = 128


def scaled_seconds(measured: dict, config, *, points: int, pixel_scale: float, n_eval: int,
                   compile_seconds: float) -> float:
    """A run's seconds from the plan's timed steps, scaled linearly in the Gaussians and in the
    pixels (an estimate, smaller runs' fixed costs included at the same rate).

    Args:
      measured: :func:`patexgs_jax.plan_steps.measure_steps`'s figures (steps timed at
        ``stage1_gaussians`` and ``gaussians``).
      config: the run's TrainConfig.
      points: the initial points; ``pixel_scale``: the run's pixels over the timed ones.
      n_eval: views evaluated; ``compile_seconds``: the plan's compile term (the same programs).
    """
    n = planned_gaussians(config, points)[0]
    m1 = max(int(measured.get("stage1_gaussians") or measured["gaussians"]), 1)
    m = max(int(measured["gaussians"]), 1)
    textured = config.spec.textures is not None
    steps1 = config.iters_2dgs + (0 if textured else config.continue_2dgs)
    steps2 = config.iters_tex if textured else 0
    t1 = steps1 * measured["stage1"] * mean_stage1_gaussians(config, points, n) / m1 * pixel_scale
    t2 = steps2 * (measured.get("texture") or 0.0) * n / m * pixel_scale
    ev = n_eval * measured["eval_view"] * n / m * pixel_scale + 2 * measured.get("eval_compile", 0.0)
    return float(t1 + t2 + ev + compile_seconds)


def best_options(estimate, factor: int, *, budgets=BUDGETS) -> list[dict]:
    """For each budget, the candidate run that fits it with the most Gaussians times pixels (ties:
    the preset with more steps): ``{"budget", "seconds_budget", "preset", "factor", "max_gaussians",
    "seconds"}`` (a budget nothing fits is left out).

    Args:
      estimate: ``estimate(preset, factor, cap)`` -> seconds of that run here.
      factor: the plan's ``--factor`` (the candidates' are its multiples).
    """
    out = []
    for seconds, words in budgets:
        best, key = None, None
        for rank, preset in enumerate(PRESETS_TRIED):
            for k in FACTOR_STEPS:
                for cap in CAPS:
                    t = estimate(preset, factor * k, cap)
                    if t <= seconds:
                        this = (cap / k ** 2, -rank)
                        if key is None or this > key:
                            best, key = dict(budget=words, seconds_budget=seconds, preset=preset,
                                             factor=factor * k, max_gaussians=cap, seconds=t), this
                        break  # (the largest cap that fits at this factor)
        if best is not None:
            out.append(best)
    return out


def candidate_config(config, preset: str, cap: int):
    """``config``'s method on ``preset`` with the cap ``cap`` (an untextured method continuing its
    stage for the texture steps when ``config`` does)."""
    from .training.config import preset_config

    cfg = preset_config(preset, method=config.method, max_gaussians=cap, seed=config.seed)
    if config.spec.textures is None and config.continue_2dgs:
        cfg = dataclasses.replace(cfg, continue_2dgs=cfg.iters_tex)
    return cfg


def advice_lines(dataset, config, measured, total, *, n, steps1, steps2, n_eval, compile_seconds, sizes,
                 texels) -> list[str]:
    """The lines of a plan whose run takes days on this CPU: that it belongs on a GPU, its time on an
    H100, and what trains here in an hour or a night (the figures as :func:`patexgs_jax.plan.make_plan`
    has them)."""
    points = len(dataset.points)
    px = max(v.camera.width * v.camera.height for v in dataset.train_views)
    lines = [f"this run takes {total / 86400:.1f} days on this CPU: it belongs on a GPU"]
    gpu = h100_run_seconds(steps1=steps1, stage1_gaussians=mean_stage1_gaussians(config, points, n), steps2=steps2,
                           gaussians=n, pixels=px, sizes=sizes)
    h100 = DEVICES["h100-80gb"]
    fit = memory_plan(dataset, config, n, texels, h100, 0)  # (the images are in host memory there)
    lines.append(f"on one {h100.name.split(' (')[0]} (NVIDIA H100): about {hms(gpu['total'])} ({hms(gpu['stage1'])} "
                 f"2DGS + {hms(gpu['texture'])} textures + {hms(gpu['compile'])} compiling; from its measured "
                 f"steps at 1M and 3M Gaussians, {H100_STEPS.source}), "
                 + ("fits in its memory" if fit["fits"] else "does NOT fit: pass " + "; or ".join(fit["fixes"])))
    m = measured.get("padded_size") or [1, 1]
    timed_px = max(int(m[0]) * int(m[1]), 1)
    factor = int(round(float(getattr(dataset, "factor", 1) or 1)))

    def estimate(preset, f, cap):
        size = _scaled_size(dataset, factor, f)
        if f != factor and min(size) < MIN_SIDE:
            return float("inf")
        cfg = candidate_config(config, preset, cap)
        scale = padded_pixels(*size) / timed_px
        return scaled_seconds(measured, cfg, points=points, pixel_scale=scale, n_eval=n_eval,
                              compile_seconds=compile_seconds)

    options = best_options(estimate, factor)
    for o in options:
        lines.append(f"here {o['budget']}: --preset {o['preset']} --factor {o['factor']} --max-gaussians "
                     f"{o['max_gaussians']} (about {hms(o['seconds'])}, scaled from the steps timed above, linear "
                     "in Gaussians and pixels; --plan on that command line times it)")
    if not options:
        lines.append("here: no preset, factor and cap tried trains in a night (smaller images or a GPU)")
    return lines


def _scaled_size(dataset, factor: int, f: int) -> tuple[int, int]:
    """The largest training view's (width, height) at ``--factor f`` instead of ``factor``."""
    w, h = max(((v.camera.width, v.camera.height) for v in dataset.train_views), key=lambda s: s[0] * s[1])
    return max(round(w * factor / f), 1), max(round(h * factor / f), 1)
