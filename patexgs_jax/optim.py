"""The optimiser: Adam with per-parameter-group learning rates, over a whole :class:`Scene`.

The optimiser state is ``(ScaleByAdamState(count, mu, nu), GroupLRState(count))`` where ``mu`` and
``nu`` are Scenes of the same structure and shapes as the parameters. Anything that reshapes the
scene between steps (densification, texture growth and re-bucketing, capacity growth) applies the
same host-side change to ``mu`` and ``nu`` (see :func:`map_moments`), so no moment is lost or mixed
between Gaussians.

Groups and learning rates (2DGS / 3DGS defaults):
  means: 1.6e-4 x scene radius, decayed exponentially to 1.6e-6 x radius over ``means_steps``;
  log_scales 5e-3; quats 1e-3; opacity_logits 5e-2; SH DC 2.5e-3, higher SH bands 2.5e-3 / 20;
  RGB texture texels 2.5e-3, alpha texture texels 2.5e-3 (configurable);
  the active mask and texture indices are frozen (zero update).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .scene import Scene


@dataclasses.dataclass(frozen=True)
class LearningRates:
    """Per-group Adam learning rates (see the module docstring)."""

    means_init: float = 1.6e-4    # times the scene radius
    means_final: float = 1.6e-6   # times the scene radius
    means_steps: int = 30_000     # steps of the exponential decay from init to final
    scales: float = 5e-3
    rotation: float = 1e-3
    opacity: float = 5e-2
    sh_dc: float = 2.5e-3
    sh_rest_divisor: float = 20.0
    texture_rgb: float = 2.5e-3
    texture_alpha: float = 2.5e-3


class GroupLRState(NamedTuple):
    count: jax.Array


def _group(path) -> str:
    names = [getattr(k, "name", None) for k in path]
    if names[0] in ("rgb", "alpha"):
        return f"texture_{names[0]}" if "buckets" in names else "frozen"
    return {"means": "means", "log_scales": "scales", "quats": "rotation",
            "opacity_logits": "opacity", "sh": "sh"}.get(names[0], "frozen")


def scale_by_group_lr(lr: LearningRates, scene_radius: float, step_offset: int = 0
                      ) -> optax.GradientTransformation:
    """Multiplies each leaf's (Adam-normalised) update by minus its group's learning rate."""
    radius = float(scene_radius)

    def means_lr(count):
        # (in float: count + step_offset in int32 wraps to negative near 2^31, restarting the decay)
        t = jnp.clip((count.astype(jnp.float32) + step_offset) / max(lr.means_steps, 1), 0.0, 1.0)
        return radius * jnp.exp((1 - t) * np.log(lr.means_init) + t * np.log(lr.means_final))

    def init_fn(params):
        del params
        return GroupLRState(count=jnp.zeros([], jnp.int32))

    def update_fn(updates, state, params=None):
        del params

        def scale(path, u):
            g = _group(path)
            if g == "frozen":
                return jnp.zeros_like(u)
            if g == "means":
                return -means_lr(state.count).astype(u.dtype) * u
            if g == "sh":
                k = jnp.arange(u.shape[1])
                f = jnp.where(k == 0, lr.sh_dc, lr.sh_dc / lr.sh_rest_divisor).astype(u.dtype)
                return -f[None, :, None] * u
            return -getattr(lr, g) * u

        return (jax.tree_util.tree_map_with_path(scale, updates),
                GroupLRState(count=optax.safe_int32_increment(state.count)))

    return optax.GradientTransformation(init_fn, update_fn)


def make_optimizer(scene_radius: float, lr: LearningRates = LearningRates(),
                   step_offset: int = 0) -> optax.GradientTransformation:
    """Adam (eps 1e-15, as 3DGS) followed by per-group learning rates.

    ``step_offset`` shifts the means' learning-rate decay (for a stage that continues a run).
    """
    return optax.chain(optax.scale_by_adam(eps=1e-15), scale_by_group_lr(lr, scene_radius, step_offset))


def adam_moments(opt_state):
    """The (mu, nu) Scenes of an optimiser state made by :func:`make_optimizer`."""
    return opt_state[0].mu, opt_state[0].nu


def map_moments(opt_state, fn: Callable[[Scene], Scene]):
    """Applies a host-side Scene -> Scene function to both Adam moment trees (mu and nu).

    ``fn`` must treat a moment tree as data laid out like the parameters (it is the same change the
    caller applies to the parameters, e.g. gathering rows for a prune or moving texels between
    buckets); index leaves of moment trees hold zeros and should be produced as zeros.
    """
    adam, group = opt_state
    return (adam._replace(mu=fn(adam.mu), nu=fn(adam.nu)), group)
