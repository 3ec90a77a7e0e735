"""The host-side schedule of a training run as strategies: densification (stage 1) here, and the
texture schedule (stage 2, :class:`patexgs_jax.schedule.TextureSchedule`).

A strategy is a host-side object called between jitted steps, as gsplat's densification strategies
are: ``before_step(state, step)`` and ``after_step(state, step)`` take the
:class:`~patexgs_jax.schedule.TrainState` and return the new one. The trainer calls them in order,
:class:`Densification` first.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .. import densify as dens
from ..schedule import TrainState
from .config import TrainConfig

__all__ = ["Densification"]


class Densification:
    """Adaptive density control of the 2DGS stage (:mod:`patexgs_jax.densify`): clone, split and
    prune, and the opacity resets, at the steps of ``config.densify`` before ``iters_2dgs``; every
    random choice is seeded by (seed, step)."""

    def __init__(self, config: TrainConfig, radius: float):
        self.config = dataclasses.replace(config.densify, max_gaussians=config.max_gaussians)
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
                prune_large=dc.prune_large(step))
        if dc.reset_opacity_at(step):
            scene, opt_state = dens.reset_opacity(scene, opt_state, dc.opacity_reset_value)
        return TrainState(scene, opt_state, stats)
