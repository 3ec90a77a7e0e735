"""The optimiser: Adam with per-parameter-group learning rates, over a whole :class:`Scene`.

The optimiser state is ``(AdamState(count, mu, nu, age), GroupLRState(count))`` where ``mu``,
``nu`` and ``age`` are Scenes of the same structure and shapes as the parameters. Anything that
reshapes the scene between steps (densification, texture growth and re-bucketing, capacity growth)
applies the same host-side change to all three (see :func:`map_moments`), so no moment is lost or
mixed between Gaussians.

Texels have their own bias correction. Adam divides ``mu`` by ``1 - b1^t`` and ``nu`` by
``1 - b2^t``, with t the global step count. A texture that appears in the middle of a run starts
with zero moments while t is large, so without correction its first updates would be up to
``(1 - b1^k) / sqrt(1 - b2^k)`` = 3.2 (k = 1) to 6.5 (k = 10) times the nominal rate, for hundreds
of steps. ``age`` counts the steps each texture has been trained (0 for a new texture, carried
through a resize by the same resampling as the moments, which keeps a texture's age up to rounding
because the weights of each new texel sum to one; each step then takes the age of a slot's first
texel for the whole slot, so a texture's texels share one age exactly), and texels are corrected
with their texture's age; every other group uses the global count, as plain Adam (``age`` stays
zero there).

Groups and learning rates (2DGS / 3DGS defaults):
  means: 1.6e-4 x scene radius, decayed exponentially to 1.6e-6 x radius over ``means_steps``;
  log_scales 5e-3; quats 1e-3; opacity_logits 5e-2; SH DC 2.5e-3, higher SH bands 2.5e-3 / 20;
  RGB texture texels 2.5e-3, alpha texture texels 2.5e-3 (configurable);
  the active mask and texture indices are frozen (zero update).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

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
    names = [str(getattr(k, "name", "")) for k in path]
    if names[0] in ("rgb", "alpha"):
        return f"texture_{names[0]}" if "buckets" in names else "frozen"
    return {"means": "means", "log_scales": "scales", "quats": "rotation",
            "opacity_logits": "opacity", "sh": "sh"}.get(names[0], "frozen")


def _rate_values(lr: LearningRates, scene_radius: float, step_offset: int = 0) -> dict[str, float]:
    """:func:`step_rates` as Python numbers (what an update without ``rates`` uses)."""
    return dict(means_radius=float(scene_radius), means_log_init=float(np.log(lr.means_init)),
                means_log_final=float(np.log(lr.means_final)), means_steps=float(max(lr.means_steps, 1)),
                step_offset=float(step_offset), scales=lr.scales, rotation=lr.rotation, opacity=lr.opacity,
                sh_dc=lr.sh_dc, sh_rest=lr.sh_dc / lr.sh_rest_divisor, texture_rgb=lr.texture_rgb,
                texture_alpha=lr.texture_alpha)


#: The names of :func:`step_rates`' entries (for abstract arguments of a step lowered ahead).
RATE_NAMES = tuple(_rate_values(LearningRates(), 1.0))


def step_rates(lr: LearningRates, scene_radius: float, step_offset: int = 0) -> dict[str, np.float32]:
    """The learning rates of :func:`make_optimizer` ``(scene_radius, lr, step_offset)`` as () float32
    arrays, to pass to its update as ``rates=`` from inside a jitted step: as arguments rather than
    constants of the program, one compiled step serves every scene radius, schedule length and
    learning rate (runs on other scenes, of other lengths, or a study's methods share programs, in
    one process and through the persistent compilation cache). The update computes the same
    float32 values either way."""
    return {k: np.float32(v) for k, v in _rate_values(lr, scene_radius, step_offset).items()}


def scale_by_group_lr(lr: LearningRates, scene_radius: float, step_offset: int = 0
                      ) -> optax.GradientTransformationExtraArgs:
    """Multiplies each leaf's (Adam-normalised) update by minus its group's learning rate: those of
    ``lr`` and ``scene_radius``, or the update's ``rates=`` (:func:`step_rates`, traced)."""
    defaults = _rate_values(lr, scene_radius, step_offset)

    def means_lr(count, r):
        # (in float: count + step_offset in int32 wraps to negative near 2^31, restarting the decay)
        t = jnp.clip((count.astype(jnp.float32) + r["step_offset"]) / r["means_steps"], 0.0, 1.0)
        return r["means_radius"] * jnp.exp((1 - t) * r["means_log_init"] + t * r["means_log_final"])

    def init_fn(params):
        del params
        return GroupLRState(count=jnp.zeros([], jnp.int32))

    def update_fn(updates, state, params=None, rates=None, **extra_args):
        del params, extra_args
        r = defaults if rates is None else rates

        def scale(path, u):
            g = _group(path)
            if g == "frozen":
                return jnp.zeros_like(u)
            if g == "means":
                return -means_lr(state.count, r).astype(u.dtype) * u
            if g == "sh":
                k = jnp.arange(u.shape[1])
                f = jnp.where(k == 0, r["sh_dc"], r["sh_rest"]).astype(u.dtype)
                return -f[None, :, None] * u
            return -r[g] * u

        return (jax.tree_util.tree_map_with_path(scale, updates),
                GroupLRState(count=jnp.asarray(optax.safe_int32_increment(state.count))))

    # optax's stub types states as ArrayTree, which a NamedTuple of arrays is at run time.
    return optax.GradientTransformationExtraArgs(init_fn, update_fn)  # pyright: ignore[reportArgumentType]


class AdamState(NamedTuple):
    """Adam's state with per-texel ages (see the module docstring).

    Attributes:
      count: () int32, steps taken (the bias correction of every group but the texels).
      mu, nu: first and second moments, laid out like the parameters.
      age: like the parameters, float32: steps each texel has been trained (zero elsewhere).
    """

    count: jax.Array
    mu: object
    nu: object
    age: object


def _is_texel_path(path) -> bool:
    return _group(path) in ("texture_rgb", "texture_alpha")


def _older(a: jax.Array) -> jax.Array:
    """A bucket's texel ages (cap, P, P, ch) one step on: each slot's age is its first texel's + 1,
    on every texel of the slot. A resize resamples a uniform age to a uniform one only up to
    rounding (and pads a slot with zeros); one value per slot keeps a texture's age exact, and
    a checkpoint stores it once per slot (:mod:`patexgs_jax.checkpoint`)."""
    return jnp.broadcast_to(a[:, :1, :1, :1] + 1.0, a.shape)


def scale_by_adam_with_texel_age(b1: float = 0.9, b2: float = 0.999, eps: float = 1e-15
                                 ) -> optax.GradientTransformation:
    """Adam's normalised update ``mu_hat / (sqrt(nu_hat) + eps)``, bias-corrected with the global
    step count, except texels, which are corrected with their own age (see the module docstring)."""

    def init_fn(params):
        def zeros(dtype=None):  # a new tree each time: the training step donates the state's buffers
            return jax.tree_util.tree_map(lambda x: jnp.zeros_like(x, dtype), params)

        return AdamState(count=jnp.zeros([], jnp.int32), mu=zeros(), nu=zeros(), age=zeros(jnp.float32))

    def update_fn(updates, state, params=None):
        del params
        mu = jax.tree_util.tree_map(lambda g, m: b1 * m + (1 - b1) * g, updates, state.mu)
        nu = jax.tree_util.tree_map(lambda g, v: b2 * v + (1 - b2) * jnp.square(g), updates, state.nu)
        count = jnp.asarray(optax.safe_int32_increment(state.count))
        t = count.astype(jnp.float32)
        age = jax.tree_util.tree_map_with_path(lambda path, a: _older(a) if _is_texel_path(path) else a, state.age)

        def normalised(path, m, v, a):
            steps = a if _is_texel_path(path) else t
            c1 = 1.0 - jnp.power(jnp.float32(b1), steps)
            c2 = 1.0 - jnp.power(jnp.float32(b2), steps)
            return ((m / c1) / (jnp.sqrt(v / c2) + eps)).astype(m.dtype)

        out = jax.tree_util.tree_map_with_path(normalised, mu, nu, age)
        return out, AdamState(count=count, mu=mu, nu=nu, age=age)

    return optax.GradientTransformation(init_fn, update_fn)  # pyright: ignore[reportArgumentType]  (as above)


def make_optimizer(scene_radius: float, lr: LearningRates = LearningRates(),
                   step_offset: int = 0) -> optax.GradientTransformationExtraArgs:
    """Adam (eps 1e-15, as 3DGS; texels with their own bias correction) followed by per-group
    learning rates.

    ``step_offset`` shifts the means' learning-rate decay (for a stage that continues a run). Its
    ``update`` takes ``rates=`` (:func:`step_rates`, the same arguments) to use traced learning
    rates instead of constants: every optimiser :func:`make_optimizer` makes then runs the same
    program.
    """
    return optax.chain(scale_by_adam_with_texel_age(eps=1e-15), scale_by_group_lr(lr, scene_radius, step_offset))


def ages_per_slot(opt_state):
    """The state with each bucket's texel ages (cap, P, P, ch) as one age per slot (cap, 1, 1, 1),
    host arrays: what a checkpoint stores. The step reads only a slot's first texel (``_older``),
    so :func:`upgrade_state` broadcasting it back gives a state that trains exactly as this one."""
    adam, group = opt_state
    if not isinstance(adam, AdamState) or not isinstance(adam.age, Scene):
        return opt_state
    age = jax.tree_util.tree_map_with_path(
        lambda path, a: np.ascontiguousarray(np.asarray(a)[:, :1, :1, :1]) if _is_texel_path(path) else a, adam.age)
    return (adam._replace(age=age), group)


def _ages_in_full(adam: AdamState) -> AdamState:
    """:func:`ages_per_slot` undone: each slot's age on every texel of the slot, as a device array."""
    def full(a, m):
        if np.shape(a) == np.shape(m):
            return a
        return jax.device_put(np.array(np.broadcast_to(np.asarray(a, np.float32), np.shape(m))))

    return adam._replace(age=jax.tree_util.tree_map(full, adam.age, adam.mu))


def upgrade_state(opt_state):
    """An optimiser state as a checkpoint holds it, as :func:`make_optimizer` makes it: texel ages
    stored one per slot (:func:`ages_per_slot`) back on every texel; and a state of an earlier
    version (optax's ``ScaleByAdamState``, without ages) with every texel's age at the global count,
    which is the bias correction that state was trained with. Other states are returned as they are."""
    adam, group = opt_state
    if isinstance(adam, AdamState):
        leaves = jax.tree_util.tree_leaves
        per_slot = isinstance(adam.age, Scene) and any(
            np.shape(a) != np.shape(m) for a, m in zip(leaves(adam.age), leaves(adam.mu)))
        return (_ages_in_full(adam), group) if per_slot else opt_state
    if not isinstance(adam, optax.ScaleByAdamState):
        return opt_state
    count = jnp.asarray(adam.count)
    age = jax.tree_util.tree_map_with_path(
        lambda path, m: jnp.full(jnp.shape(m), count, jnp.float32) if _is_texel_path(path)
        else jnp.zeros(jnp.shape(m), jnp.float32), adam.mu)
    return (AdamState(count=count, mu=adam.mu, nu=adam.nu, age=age), group)


def adam_moments(opt_state):
    """The (mu, nu) Scenes of an optimiser state made by :func:`make_optimizer`."""
    return opt_state[0].mu, opt_state[0].nu


def map_moments(opt_state, fn: Callable[[Scene], Scene]):
    """Applies a host-side Scene -> Scene function to every Scene-shaped tree of Adam's state (mu,
    nu and, with :class:`AdamState`, the texel ages).

    ``fn`` must treat such a tree as data laid out like the parameters (it is the same change the
    caller applies to the parameters, e.g. gathering rows for a prune or moving texels between
    buckets); index leaves of these trees hold zeros and should be produced as zeros.
    """
    adam, group = opt_state
    trees = {k: fn(getattr(adam, k)) for k in ("mu", "nu", "age") if isinstance(getattr(adam, k, None), Scene)}
    return (adam._replace(**trees), group)
