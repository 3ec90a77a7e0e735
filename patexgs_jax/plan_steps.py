"""The run plan's step timing (:func:`measure_steps`): a few real training steps of each stage on
this device at the planned size, and an evaluation render (:mod:`patexgs_jax.plan` uses them)."""

from __future__ import annotations

import dataclasses
import os
import statistics
import time

import numpy as np

__all__ = ["measure_steps"]


def measure_steps(dataset, config, gaussians: int, *, steps: int = 5, stage1_gaussians: int | None = None) -> dict:
    """Times a few real training steps of each stage on this device: the 2DGS stage's at
    ``stage1_gaussians`` active Gaussians (default ``gaussians``; the others inactive, so no shape
    changes), the texture stage's at ``gaussians``.

    A scene of ``gaussians`` Gaussians is initialised from the dataset's points (repeated with a
    small jitter when it has fewer), densification is off, and the run's own loop trains ``steps``
    steps of each stage after the ones that compile (the texture stage of adaptive methods runs the
    real Eq. 7 allocation on that scene after one warm-up step), with nothing compiled in the
    background (``PATEXGS_COMPILE_AHEAD=0`` meanwhile). Nothing is written. The steps train on the
    views of one padded size (the most common one; ties: the largest): a run compiles its step once
    per padded size (:mod:`patexgs_jax.padding`), so on views of several sizes the timed steps would
    be compiles (an undistorted capture has several: beer at full size six).

    Returns:
      ``stage1``, ``texture``: median seconds of the last ``steps`` steps of each stage, which
      compile nothing (texture None without textures); ``compile_stage1``, ``compile_texture``:
      seconds the stage's other steps took beyond as many steady ones (compiling);
      ``eval_view``, ``eval_compile``: seconds of one evaluation render and of compiling one
      evaluation; ``steps``; ``seconds``: the time this took (all in seconds); ``padded_size``:
      the (height, width) stepped; ``padded_sizes``: how many padded sizes the training views have
      (each compiles its own steps in a run).
    """
    import jax

    from .ahead import AHEAD_ENV
    from .densify import DensifyConfig
    from .evaluation import evaluate
    from .training.trainer import Trainer

    t_all = time.perf_counter()
    spec = config.spec
    textured = spec.textures is not None
    off = DensifyConfig(start=10**9, stop=10**9 + 1, opacity_reset_interval=10**9)
    n1 = 1 + steps
    n2 = 0 if not textured else (2 + steps if spec.grows else 1 + steps)
    cfg = dataclasses.replace(config, iters_2dgs=n1, iters_tex=max(n2, 2), continue_2dgs=0, warmup_tex=1,
                              growth_interval=10**9, densify=off, max_gaussians=int(gaussians),
                              checkpoint_every=10**9, log_every=10**9, sh_interval=1, normal_from=0)
    pts, cols = _points_for(dataset.points, dataset.colors, int(gaussians), config.seed)
    size, n_sizes, views = _one_size(dataset.train_views, config)
    ds = dataclasses.replace(dataset, points=pts, colors=cols, train_views=views)
    stamps: list[tuple[int, float]] = []

    m = int(gaussians) if stage1_gaussians is None else max(1, min(int(stage1_gaussians), int(gaussians)))

    class Run(Trainer):
        def before_step(self, step):
            if m < gaussians and step in (0, n1):  # stage 1 at m active Gaussians, stage 2 at all of them
                act = np.asarray(self.scene.active).copy()
                act[m:gaussians] = act[0] if step == n1 else 0
                self.scene = self.scene.replace(active=jax.numpy.asarray(act))
            super().before_step(step)

        def after_step(self, step):
            super().after_step(step)
            jax.block_until_ready(self.scene.means)
            stamps.append((step, time.perf_counter()))

    run = Run(ds, cfg, None, verbose=False)
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
    # The last ``steps`` steps of each stage compile nothing (the schedule puts every compile first:
    # the first step, the texture stage's start, Eq. 7's allocation); the others' extra time is compiling.
    spans: dict[int, list[float]] = {1: [], 2: []}
    prev_t = t0
    for step, t in stamps:
        spans[1 if step <= n1 else 2].append(t - prev_t)
        prev_t = t
    med = {k: (statistics.median(v[-steps:]) if len(v) > steps else None) for k, v in spans.items()}
    comp = {k: max(0.0, sum(v[:-steps]) - (len(v) - steps) * (med[k] or 0.0)) if med[k] else 0.0
            for k, v in spans.items()}
    # Evaluation: one compile per call, then a render per view: time 1 view and 3 views.
    view = (list(dataset.test_views) or list(dataset.train_views))[0]
    t = time.perf_counter()
    evaluate(run.scene, [view], run.render_cfg)
    one = time.perf_counter() - t
    t = time.perf_counter()
    evaluate(run.scene, [view] * 3, run.render_cfg)
    three = time.perf_counter() - t
    eval_view = max((three - one) / 2, 1e-4)
    eval_compile = max(one - eval_view, 0.0)
    return dict(stage1=med[1], texture=med[2] if textured else None, stage1_gaussians=m, compile_stage1=comp[1],
                compile_texture=comp[2] if textured else 0.0, eval_view=eval_view, eval_compile=eval_compile,
                steps=steps, padded_size=list(size), padded_sizes=n_sizes,
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


