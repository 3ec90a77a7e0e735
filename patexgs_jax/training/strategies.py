"""The host-side schedule of a training run as strategies: densification (stage 1), Mip-Splatting's
3D filter and the tile capacity's refits here, and the texture schedule (stage 2,
:class:`patexgs_jax.schedule.TextureSchedule`); and where stage 1 starts from (:func:`init_scene`).

A strategy (:class:`Strategy`) is a host-side object called between jitted steps, as gsplat's
densification strategies are: ``before_step(state, step)`` and ``after_step(state, step)`` take the
:class:`~patexgs_jax.schedule.TrainState` and return the new one. The trainer calls them in order,
:class:`Densification` first, and only through these two.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np

from .. import densify as dens
from .. import filter3d
from ..render import RenderConfig
from ..scene import Scene
from ..schedule import TrainState
from .config import TrainConfig, effective_config
from .steps import TileCapacity, refits_at

__all__ = ["Densification", "SmoothingFilter", "Strategy", "TileRefit", "init_scene"]


class Strategy(Protocol):
    """Host-side work between jitted steps: each call takes the training state and returns the new
    one (the input is not used again). The trainer calls its strategies through these two only."""

    def before_step(self, state: TrainState, step: int) -> TrainState:
        """Before the step that starts at ``step``."""
        ...

    def after_step(self, state: TrainState, step: int) -> TrainState:
        """Once ``step`` steps are complete."""
        ...


class Densification:
    """Adaptive density control of the 2DGS stage (:mod:`patexgs_jax.densify`): clone, split and
    prune, and the opacity resets, at the steps of ``config.densify`` before ``iters_2dgs``; every
    random choice is seeded by (seed, step)."""

    def __init__(self, config: TrainConfig, radius: float):
        # (the method's own prune threshold: 3DGS's 0.005 for the 3D methods)
        self.config = dataclasses.replace(effective_config(config).densify, max_gaussians=config.max_gaussians)
        self.iters_2dgs, self.seed, self.radius = config.iters_2dgs, config.seed, radius

    def before_step(self, state: TrainState, step: int) -> TrainState:
        return state

    def after_step(self, state: TrainState, step: int) -> TrainState:
        dc = self.config
        if step >= self.iters_2dgs:
            return state
        scene, opt_state, stats = state
        if dc.densify_at(step):
            scene, opt_state, stats, _ = dens.densify_and_prune(
                scene, opt_state, stats, dc, self.radius, np.random.default_rng([self.seed, step]),
                prune_large=dc.prune_large(step), donate=True)  # (the old state is not used again)
        if dc.reset_opacity_at(step):
            scene, opt_state = dens.reset_opacity(scene, opt_state, dc.opacity_reset_value)
        return TrainState(scene, opt_state, stats)


class SmoothingFilter:
    """Mip-Splatting's 3D filter (:mod:`patexgs_jax.filter3d`) of a method with one (``mip-splatting``,
    ``patexgs+filter3d``), from the training cameras, at its reference code's steps: before the first
    step, after every densification (this strategy runs after :class:`Densification`) and, once
    densification has stopped, every densification interval up to one interval before the end.
    Does nothing for other methods. No state of its own (the filter is part of the scene)."""

    def __init__(self, config: TrainConfig, views):
        self.on = config.spec.filter3d
        self.cameras = [v.camera for v in views] if self.on else []
        self.dc, self.iters, self.total = config.densify, config.iters_2dgs, config.total_steps

    def recomputes_at(self, step: int) -> bool:
        """Whether :meth:`after_step` recomputes the filter after ``step`` steps."""
        dc = self.dc
        if step < self.iters and dc.densify_at(step):
            return True
        return step % dc.interval == 0 and step > min(dc.stop, self.iters) and step < self.total - dc.interval

    def before_step(self, state: TrainState, step: int) -> TrainState:
        if not self.on or step != 0:
            return state
        return state._replace(scene=filter3d.with_filter(state.scene, self.cameras))

    def after_step(self, state: TrainState, step: int) -> TrainState:
        if not self.on or not self.recomputes_at(step):
            return state
        return state._replace(scene=filter3d.with_filter(state.scene, self.cameras))


class TileRefit:
    """Keeps the run's tile capacity (:class:`~.steps.TileCapacity`) fitted to its scene: after a
    densification that changed the scene's shapes, a refit before the next step from the capacity it
    had (then its floor); every 100 steps of the 2DGS stage (:func:`~.steps.refits_at`), a refit to
    the next step's view. It runs after the strategies that change the scene and before compiling
    ahead, which prepares the texture stage's first step at the capacity it leaves. ``render_cfgs``:
    the two stages' render configurations."""

    def __init__(self, config: TrainConfig, tiles: TileCapacity, views,
                 render_cfgs: tuple[RenderConfig, RenderConfig]):
        self.cfg, self.tiles, self.views, self.render_cfgs = config, tiles, views, render_cfgs
        self.capacity: int | None = None  # the scene's Gaussian capacity before this step

    def before_step(self, state: TrainState, step: int) -> TrainState:
        self.capacity = state.scene.capacity
        return state

    def after_step(self, state: TrainState, step: int) -> TrainState:
        cfg = self.cfg
        if state.scene.capacity != self.capacity:
            self.tiles.scene_grew()
        elif refits_at(cfg, step, self.tiles.current):
            view = self.views[cfg.view_index(step, len(self.views))]
            self.tiles.fit(state.scene, view.camera, self.render_cfgs[0 if step < cfg.iters_2dgs else 1],
                           batch=cfg.batch_size > 1)
        return state


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
