"""Adaptive texture allocation (paper Eqs. 6-10): sizes, growth schedule and re-bucketing.

Everything here is host-side numpy, run between jitted training steps; every function is pure
(it returns new objects and never mutates its inputs).

Units and conventions
  * A Gaussian's texture *side* is an int n >= 1 (an n x n texture), 0 meaning "no texture".
  * The schedule keeps a real-valued size T_i (Eqs. 7 and 10) and uses
    ``side = clip(floor(T + 1/2), 1, max_size)`` (round half up) for the texture it allocates;
    a Gaussian with T = 0 has no texture. Because every Eq. 10 increment ``sqrt(g / tau_low)`` is
    > 1 (the Gaussian was selected with g > tau_low), every growth event adds at least one texel
    to the side, unless the side is already ``max_size``.
  * Budgets count *RGBA texels*: a Gaussian of side n holds n*n RGBA texels = an n x n RGB texture
    (3 floats a texel) plus an n x n alpha texture (1 float), i.e. ``FLOATS_PER_RGBA_TEXEL = 4``
    floats = 16 bytes a texel. :func:`mb_to_texels` converts MiB (``2**20`` bytes, as
    :func:`patexgs_jax.metrics.storage_mb`) to such texels.

Re-bucketing (:func:`resize_textures`)
  A texture whose side changes from n to m is resampled exactly as the renderer samples it
  (:mod:`patexgs_jax.textures`): new texel j sits at splat-plane position ``-3 + 6 j / (m - 1)``
  and, when the texture grows (m > n), takes the bilinear, edge-clamped, align-corners value of
  the old n x n texture there; when it shrinks (m < n), the mean of that interpolant over the new
  texel's cell (an area filter that keeps the texture's mean; see :func:`resample_matrix`). Either
  way the resampling is one separable linear map ``R_{m,n} X R_{m,n}^T`` with non-negative weights
  summing to one per row. Growth from 1 x 1 is therefore exact (a constant), and so is any n -> m
  with (m - 1) a multiple of (n - 1) (the new grid contains the old grid, and the bilinear
  interpolant is unchanged), e.g. 2 -> any m, 3 -> 5, 5 -> 9. The Adam moments ``mu`` and ``nu``
  of the texels are resampled by the same map (``nu`` stays >= 0). A texture appearing (0 -> m) starts as the
  bank's neutral value (RGB offset 0, alpha multiplier 1: rendering is unchanged) with zero
  moments; a texture disappearing (n -> 0) frees its slot.

  Slots are stable: a Gaussian whose bucket does not change keeps its slot (if its side is
  unchanged its whole slot, padding included, is copied bit-exactly); a Gaussian changing bucket
  takes the lowest free slot of its new bucket after all departures are freed. Bucket capacities
  are powers of two that only grow (by doubling) and buckets are never removed, so the set of
  shapes the jitted step sees stays small; :class:`ResizeInfo` says when they changed.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from .metrics import BYTES_PER_MB
from .scene import Scene
from .textures import TextureBank, bucket_of

__all__ = [
    "ALPHA_NEUTRAL",
    "FLOATS_PER_RGBA_TEXEL",
    "GrowthSchedule",
    "MAX_TEXTURE_SIZE",
    "RGB_NEUTRAL",
    "ResizeInfo",
    "TextureScheduleState",
    "add_textures",
    "contribution_sizes",
    "default_sigma",
    "pixel_share_sigma",
    "grow_sizes",
    "initial_texture_sizes",
    "mb_to_texels",
    "resample_matrix",
    "resample_texture",
    "resize_textures",
    "side_of",
    "solve_sigma_for_budget",
    "texels_to_mb",
    "total_texels",
]

#: Largest texture side :func:`resize_textures` accepts by default (bucket 9 = 512 x 512 slots).
MAX_TEXTURE_SIZE = 512
#: Default cap of Eq. 7 / Eq. 10 sizes.
DEFAULT_MAX_SIZE = 32
#: Floats per RGBA texel (3 RGB + 1 alpha); the unit of texel budgets.
FLOATS_PER_RGBA_TEXEL = 4
#: Values of a newly created texture (rendering-neutral: RGB offset 0, alpha multiplier 1).
RGB_NEUTRAL = 0.0
ALPHA_NEUTRAL = 1.0
_BANKS = ("rgb", "alpha")


# =============================================================================================
# Resampling
# =============================================================================================
def _hat_integral(x: np.ndarray) -> np.ndarray:
    """``F(x) = integral_{-inf}^{x} max(0, 1 - |s|) ds``: the antiderivative of a unit hat."""
    x = np.clip(x, -1.0, 1.0)
    return np.where(x <= 0.0, 0.5 * (x + 1.0) ** 2, 1.0 - 0.5 * (1.0 - x) ** 2)


def resample_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) float64 resampling matrix: non-negative weights, each row summing to one.

    Growing or keeping the side (``n_out >= n_in``): row j holds the bilinear weights of the old
    texels at new texel j's position ``-3 + 6 j / (n_out - 1)``, with the renderer's edge clamp
    (the renderer's own sampling; exact integer arithmetic for the positions).

    Shrinking (``n_out < n_in``): an area filter. New texel j is the mean of the old texture's
    bilinear interpolant over its cell, ``[-3 + 6 (j - 1/2) / (n_out - 1), -3 + 6 (j + 1/2) /
    (n_out - 1)]`` cut to [-3, 3] (the whole square when ``n_out == 1``). The cells tile the square
    with the widths the new interpolant's trapezoid rule gives its texels, so the interpolant's mean
    over the square is kept exactly: a texture that shrinks keeps its mean colour and coverage, and
    every old texel contributes (point-sampling a 5 x 5 texture at side 2 would read only its corners).
    """
    n_in, n_out = int(n_in), int(n_out)
    if n_in < 1 or n_out < 1:
        raise ValueError(f"resample sizes must be >= 1, got {n_in} -> {n_out}.")
    R = np.zeros((n_out, n_in))
    if n_in == 1:
        R[:, 0] = 1.0
        return R
    if n_out < n_in:
        # In old-grid units t in [0, n_in - 1]: old texel a is the hat max(0, 1 - |t - a|).
        last = n_in - 1.0
        if n_out == 1:
            lo, hi = np.array([0.0]), np.array([last])
        else:
            h = last / (n_out - 1)
            c = np.arange(n_out) * h
            lo, hi = np.maximum(c - h / 2, 0.0), np.minimum(c + h / 2, last)
        a = np.arange(n_in)[None, :]
        R = (_hat_integral(hi[:, None] - a) - _hat_integral(lo[:, None] - a)) / (hi - lo)[:, None]
        return R / R.sum(axis=1, keepdims=True)  # (sums are one up to rounding; make them exact-er)
    for j in range(n_out):
        # Old-grid coordinate t = j (n_in - 1) / (n_out - 1) = a0 + f.
        num, den = j * (n_in - 1), n_out - 1
        a0, rem = divmod(num, den)
        f = rem / den
        if a0 >= n_in - 1:  # the last texel: clamp like the renderer (a0 = n - 2, f = 1)
            a0, f = n_in - 2, 1.0
        R[j, a0] += 1.0 - f
        R[j, a0 + 1] += f
    return R


def resample_texture(tex, n_out: int) -> np.ndarray:
    """Resamples textures to side ``n_out`` (float64 math, float32 result).

    Args:
      tex: (..., n, n, ch) textures.
      n_out: new side m >= 1.
    Returns:
      (..., m, m, ch) float32.
    """
    tex = np.asarray(tex, np.float64)
    if tex.ndim < 3 or tex.shape[-3] != tex.shape[-2]:
        raise ValueError(f"textures must have shape (..., n, n, ch), got {tex.shape}.")
    R = resample_matrix(tex.shape[-3], n_out)
    return np.einsum("ma,...abc,nb->...mnc", R, tex, R).astype(np.float32)


# =============================================================================================
# Re-bucketing
# =============================================================================================
@dataclasses.dataclass(frozen=True)
class ResizeInfo:
    """What :func:`resize_textures` / :func:`add_textures` did, per bank (keys "rgb", "alpha").

    Attributes:
      changed: textures whose side changed (including appearing / disappearing ones).
      texels_before, texels_after: stored texels (sum of n*n over all textured slots, active or
        not; multiply by 3 for RGB floats).
      capacities_before, capacities_after: bucket capacities (empty tuple: no bank).
      shapes_changed: some bucket was added or grew, or a bank was added: the jitted training
        step will recompile.
    """

    changed: dict
    texels_before: dict
    texels_after: dict
    capacities_before: dict
    capacities_after: dict
    shapes_changed: bool

    @property
    def num_changed(self) -> int:
        """Total number of changed textures over both banks."""
        return int(sum(self.changed.values()))


@dataclasses.dataclass(frozen=True)
class _BankPlan:
    old_size: np.ndarray   # (C,) int64
    new_size: np.ndarray
    old_bucket: np.ndarray
    old_slot: np.ndarray
    new_bucket: np.ndarray
    new_slot: np.ndarray
    capacities: tuple
    channels: int


def _next_pow2(x: int) -> int:
    return 1 if x <= 1 else 1 << (int(x) - 1).bit_length()


def _check_sizes(sizes, C: int, name: str, max_size: int) -> np.ndarray:
    arr = np.asarray(sizes)
    if arr.shape != (C,):
        raise ValueError(f"{name} must have shape (C,) = ({C},), got {arr.shape}.")
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold integer sides, got dtype {arr.dtype}.")
    if arr.dtype.kind == "f" and (not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr))):
        raise ValueError(f"{name} must hold integer sides (exact integers), got non-integers.")
    out = arr.astype(np.int64)
    if np.any(out < 0):
        raise ValueError(f"{name} must be >= 0 (0 = no texture), got min {out.min()}.")
    if np.any(out > max_size):
        raise ValueError(f"{name} has a side {out.max()} > max_size {max_size}.")
    return out


def _bank_indices(bank: TextureBank):
    size = np.asarray(bank.size).astype(np.int64)
    bucket = np.asarray(bank.bucket).astype(np.int64)
    slot = np.asarray(bank.slot).astype(np.int64)
    return size, bucket, slot


def _plan(bank: TextureBank, new_size: np.ndarray, min_capacity: int) -> _BankPlan:
    old_size, old_bucket, old_slot = _bank_indices(bank)
    C = old_size.shape[0]
    # ceil(log2 n) = bit_length(n - 1) = frexp(n - 1) exponent; -1 for no texture.
    new_bucket = np.where(new_size > 0, np.frexp(np.maximum(new_size - 1, 0).astype(np.float64))[1], -1)
    new_bucket = new_bucket.astype(np.int64)
    nb = max([bank.num_buckets] + [int(b) + 1 for b in new_bucket if b >= 0])
    old_caps = list(bank.capacities) + [0] * (nb - bank.num_buckets)
    stay = (new_size > 0) & (new_bucket == old_bucket)
    new_slot = np.zeros(C, np.int64)
    new_slot[stay] = old_slot[stay]
    caps = []
    for b in range(nb):
        staying = np.flatnonzero(stay & (new_bucket == b))
        arriving = np.flatnonzero(~stay & (new_bucket == b))
        count = staying.size + arriving.size
        cap = old_caps[b]
        if count > cap:
            cap = max(cap, _next_pow2(max(min_capacity, 1)))
            while cap < count:
                cap *= 2
        used = np.zeros(cap, bool)
        used[old_slot[staying]] = True
        free = np.flatnonzero(~used)
        new_slot[arriving] = free[: arriving.size]
        caps.append(cap)
    return _BankPlan(old_size, new_size, old_bucket, old_slot, new_bucket, new_slot, tuple(caps),
                     bank.channels)


def _apply_plan(plan: _BankPlan, old_buckets, fresh_value: float):
    """New bucket arrays (list of float32 numpy) from old ones following ``plan``."""
    old = [np.asarray(b) for b in old_buckets]
    ch = plan.channels
    new = [np.zeros((cap, 1 << b, 1 << b, ch), np.float32) for b, cap in enumerate(plan.capacities)]
    n_old, n_new = plan.old_size, plan.new_size
    same = (n_new > 0) & (n_new == n_old)
    for b in range(len(new)):
        idx = np.flatnonzero(same & (plan.new_bucket == b))
        if idx.size:
            new[b][plan.new_slot[idx]] = old[b][plan.old_slot[idx]]  # bit-exact, padding included
    changed = (n_new > 0) & (n_new != n_old)
    fresh = changed & (n_old == 0)
    for m in np.unique(n_new[fresh]):
        idx = np.flatnonzero(fresh & (n_new == m))
        new[bucket_of(m)][plan.new_slot[idx], :m, :m] = fresh_value
    resampled = changed & (n_old > 0)
    pairs = np.stack([n_old[resampled], n_new[resampled]], axis=1) if resampled.any() else np.zeros((0, 2))
    for n, m in np.unique(pairs, axis=0).astype(np.int64):
        idx = np.flatnonzero(resampled & (n_old == n) & (n_new == m))
        src = old[bucket_of(n)][plan.old_slot[idx], :n, :n]
        new[bucket_of(m)][plan.new_slot[idx], :m, :m] = resample_texture(src, m)
    return new


def _bank_from_plan(plan: _BankPlan, buckets, with_indices: bool) -> TextureBank:
    C = plan.new_size.shape[0]
    if with_indices:
        bucket, slot, size = plan.new_bucket, np.where(plan.new_size > 0, plan.new_slot, 0), plan.new_size
    else:  # moment trees: index leaves are zeros
        bucket = slot = size = np.zeros(C)
    return TextureBank(buckets=tuple(jnp.asarray(b) for b in buckets),
                       bucket=jnp.asarray(bucket, jnp.float32), slot=jnp.asarray(slot, jnp.float32),
                       size=jnp.asarray(size, jnp.float32), channels=plan.channels)


def _empty_bank(C: int, channels: int) -> TextureBank:
    return TextureBank(buckets=(), bucket=jnp.full((C,), -1.0, jnp.float32),
                       slot=jnp.zeros((C,), jnp.float32), size=jnp.zeros((C,), jnp.float32),
                       channels=channels)


def _map_scene_nodes(opt_state, fn: Callable[[Scene], Scene]):
    """Applies ``fn`` to every Scene-shaped node (Adam's mu and nu) of an optimiser state."""
    return jax.tree_util.tree_map(lambda x: fn(x) if isinstance(x, Scene) else x, opt_state,
                                  is_leaf=lambda x: isinstance(x, Scene))


def _check_moment_bank(mbank, bank: TextureBank, name: str):
    if mbank is None or tuple(x.shape for x in mbank.buckets) != tuple(x.shape for x in bank.buckets):
        raise ValueError(f"the optimiser state's moments of the {name!r} bank do not match the scene's "
                         "bucket shapes; was opt_state made for this scene?")


def resize_textures(scene: Scene, opt_state, rgb_sizes, alpha_sizes, *, min_capacity: int = 1,
                    max_size: int = MAX_TEXTURE_SIZE):
    """Changes texture sides, resampling texels and their Adam moments (see the module docstring).

    Args:
      scene: the parameters; the banks being resized must exist (use :func:`add_textures` first).
      opt_state: optimiser state whose Scene-shaped nodes (Adam ``mu``, ``nu``) mirror ``scene``,
        or None (e.g. for inference).
      rgb_sizes, alpha_sizes: (C,) integer new sides (0 = no texture, at most ``max_size``), or
        None to leave that bank unchanged.
      min_capacity: a bucket that is created or grows gets at least this capacity (rounded up to a
        power of two).
      max_size: largest side accepted.
    Returns:
      ``(scene, opt_state, ResizeInfo)``; opt_state is None if it was None.
    """
    C = scene.capacity
    if int(min_capacity) < 1:
        raise ValueError(f"min_capacity must be >= 1, got {min_capacity}.")
    plans = {}
    for name, sizes in zip(_BANKS, (rgb_sizes, alpha_sizes)):
        if sizes is None:
            continue
        bank = getattr(scene, name)
        if bank is None:
            raise ValueError(f"the scene has no {name!r} bank; create it with add_textures.")
        plans[name] = _plan(bank, _check_sizes(sizes, C, f"{name}_sizes", int(max_size)), int(min_capacity))

    if opt_state is not None:
        for m in jax.tree_util.tree_leaves(opt_state, is_leaf=lambda x: isinstance(x, Scene)):
            if isinstance(m, Scene):
                for name in plans:
                    _check_moment_bank(getattr(m, name), getattr(scene, name), name)

    def apply(s: Scene, is_params: bool) -> Scene:
        kw = {}
        for name, plan in plans.items():
            fresh = (RGB_NEUTRAL if name == "rgb" else ALPHA_NEUTRAL) if is_params else 0.0
            buckets = _apply_plan(plan, getattr(s, name).buckets, fresh)
            kw[name] = _bank_from_plan(plan, buckets, with_indices=is_params)
        return s.replace(**kw)

    new_scene = apply(scene, True)
    new_state = None if opt_state is None else _map_scene_nodes(opt_state, lambda m: apply(m, False))
    info = _info(scene, new_scene, plans)
    return new_scene, new_state, info


def _info(old: Scene, new: Scene, plans) -> ResizeInfo:
    changed, tb, ta, cb, ca = {}, {}, {}, {}, {}
    shapes_changed = False
    for name in _BANKS:
        bo, bn = getattr(old, name), getattr(new, name)
        cb[name] = () if bo is None else bo.capacities
        ca[name] = () if bn is None else bn.capacities
        tb[name] = 0 if bo is None else bo.texel_count()
        ta[name] = 0 if bn is None else bn.texel_count()
        plan = plans.get(name)
        changed[name] = 0 if plan is None else int(np.sum(plan.old_size != plan.new_size))
        shapes_changed |= (bo is None) != (bn is None) or cb[name] != ca[name]
    return ResizeInfo(changed, tb, ta, cb, ca, bool(shapes_changed))


def add_textures(scene: Scene, opt_state, optimizer, rgb_sizes, alpha_sizes, rgb_init=RGB_NEUTRAL,
                 alpha_init=ALPHA_NEUTRAL, *, min_capacity: int = 1, max_size: int = MAX_TEXTURE_SIZE):
    """Creates texture banks a scene does not have yet (e.g. the stage-2 init: 1x1 RGB, 5x5 alpha).

    Args:
      scene: parameters without the bank(s) being added.
      opt_state: the optimiser state for ``scene`` (or None).
      optimizer: the ``optax.GradientTransformation`` that made ``opt_state``; its ``init`` on the
        new scene provides the new leaves' state (zero moments). May be None, in which case the new
        moment banks are zeros directly.
      rgb_sizes, alpha_sizes: (C,) integer sides (0 = none) of the bank to create, or None to leave
        that bank as it is (absent or present).
      rgb_init: value of every new RGB texel (scalar or (3,)); default 0 (neutral).
      alpha_init: value of every new alpha texel (scalar); default 1 (neutral).
      min_capacity, max_size: as in :func:`resize_textures`.
    Returns:
      ``(scene, opt_state, ResizeInfo)``: existing leaves and their moments and the step count are
      kept unchanged; the new bank's moments are zero.
    """
    C = scene.capacity
    kw, plans = {}, {}
    for name, sizes, init, ch in (("rgb", rgb_sizes, rgb_init, 3), ("alpha", alpha_sizes, alpha_init, 1)):
        if sizes is None:
            continue
        if getattr(scene, name) is not None:
            raise ValueError(f"the scene already has a {name!r} bank; use resize_textures to change it.")
        init = np.asarray(init, np.float64)
        if init.shape not in ((), (ch,)) or not np.all(np.isfinite(init)):
            raise ValueError(f"{name}_init must be a finite scalar or shape ({ch},), got {init.shape}.")
        plan = _plan(_empty_bank(C, ch), _check_sizes(sizes, C, f"{name}_sizes", int(max_size)),
                     int(min_capacity))
        buckets = _apply_plan(plan, [], init.astype(np.float32))  # every texture is new: init
        kw[name] = _bank_from_plan(plan, buckets, with_indices=True)
        plans[name] = plan
    new_scene = scene.replace(**kw)
    info = _info(scene, new_scene, plans)
    if opt_state is None:
        return new_scene, None, info

    is_scene = lambda x: isinstance(x, Scene)  # noqa: E731
    if optimizer is None:
        def merge(m: Scene) -> Scene:
            return m.replace(**{k: jax.tree_util.tree_map(jnp.zeros_like, v) for k, v in kw.items()})
        return new_scene, _map_scene_nodes(opt_state, merge), info

    fresh = optimizer.init(new_scene)
    old_leaves, old_def = jax.tree_util.tree_flatten(opt_state, is_leaf=is_scene)
    new_leaves, new_def = jax.tree_util.tree_flatten(fresh, is_leaf=is_scene)
    if old_def != new_def:
        raise ValueError("optimizer.init(new scene) is not laid out like opt_state (outside the "
                         "Scene-shaped moments); is `optimizer` the one that made opt_state?")
    merged = []
    for o, n in zip(old_leaves, new_leaves):
        if is_scene(o):
            merged.append(o.replace(**{k: getattr(n, k) for k in kw}))
        else:
            if np.shape(o) != np.shape(n):
                raise ValueError("optimiser state leaf shapes differ between the old and new scene.")
            merged.append(o)
    return new_scene, jax.tree_util.tree_unflatten(old_def, merged), info


# =============================================================================================
# Eq. 7: initial sizes from contribution counts
# =============================================================================================
def default_sigma(height: int, width: int) -> float:
    """The paper's Eq. 7 sigma, ``H * W / 1e4`` for training images of H x W pixels.

    It was set for Mip-NeRF 360 captures (about 200 views of about 1 MP) trained to about a million
    Gaussians; :func:`pixel_share_sigma` keeps its meaning at other scales (training uses that).
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height} x {width}.")
    return float(height) * float(width) / 1e4


#: Pixel-views per Gaussian at which Eq. 7 counts one unit of side, as a share of the fair share
#: ``total_pixels / num_gaussians`` (see :func:`pixel_share_sigma`).
SIGMA_PIXEL_SHARE = 0.5


def pixel_share_sigma(total_pixels: float, num_gaussians: int, share: float = SIGMA_PIXEL_SHARE) -> float:
    """Eq. 7 sigma from the scene's size: ``share * total_pixels / num_gaussians``.

    ``total_pixels`` is the sum of H * W over the training views and ``num_gaussians`` the active
    Gaussians, so ``total_pixels / num_gaussians`` is a Gaussian's fair share of the pixel-views
    (what it would dominate if every Gaussian dominated as much). Eq. 7 sums ``log2(1 + S_ij /
    sigma)`` over views: more views and more pixels a view raise every T_i, more Gaussians lower
    each one's S_ij. Where ``S_ij << sigma``, ``T_i ~ sum_j S_ij / (sigma ln 2) = 2 f / ln 2`` for a
    Gaussian that dominates f times its fair share in all: the same T at any scale (where S_ij is
    near sigma or above, the log makes T grow more slowly). With ``share = 0.5`` it equals the paper's
    ``H * W / 1e4`` at the paper's scale (200 views of H * W pixels and 10^6 Gaussians:
    ``0.5 * 200 H W / 10^6``); on a 128 x 96 scene of 21 views and 3,900 Gaussians the paper's value
    (1.2) would give 43% of the Gaussians side >= 8 and 99% of the texels to them (docs/tradeoffs.md).
    """
    if not total_pixels > 0 or num_gaussians < 1 or not share > 0:
        raise ValueError(f"need total_pixels > 0, num_gaussians >= 1 and share > 0, got {total_pixels}, "
                         f"{num_gaussians} and {share}.")
    return float(share) * float(total_pixels) / float(num_gaussians)


def _check_counts(contrib_counts, active=None):
    S = np.asarray(contrib_counts, np.float64)
    if S.ndim != 2:
        raise ValueError(f"contrib_counts must have shape (num_images, C), got {S.shape}.")
    if not np.all(np.isfinite(S)) or np.any(S < 0):
        raise ValueError("contrib_counts must be finite and non-negative (pixel counts S_ij).")
    if active is None:
        act = np.ones(S.shape[1], bool)
    else:
        act = np.asarray(active)
        if act.shape != (S.shape[1],):
            raise ValueError(f"active must have shape (C,) = ({S.shape[1]},), got {act.shape}.")
        act = act > 0
    return S, act


def contribution_sizes(contrib_counts, sigma: float) -> np.ndarray:
    """Real-valued Eq. 7 sizes ``T_i = sum_j log2(1 + S_ij / sigma)``.

    Args:
      contrib_counts: (num_images, C) per-image max-contribution pixel counts S_ij (Eq. 6; the
        renderer's ``max_contrib_count`` of each training view stacked).
      sigma: positive scale (see :func:`default_sigma`).
    Returns:
      (C,) float64.
    """
    S, _ = _check_counts(contrib_counts)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be positive and finite, got {sigma}.")
    return np.sum(np.log2(1.0 + S / float(sigma)), axis=0)


def side_of(T, max_size: int = DEFAULT_MAX_SIZE, min_size: int = 1) -> np.ndarray:
    """Texture sides of real sizes: ``clip(floor(T + 1/2), min_size, max_size)``, 0 where T <= 0.

    Args:
      T: (C,) real sizes (0 or negative: no texture).
    Returns:
      (C,) int64.
    """
    T = np.asarray(T, np.float64)
    side = np.clip(np.floor(T + 0.5), min_size, max_size).astype(np.int64)
    return np.where(T > 0, side, 0)


def initial_texture_sizes(contrib_counts, sigma: float, *, max_size: int = DEFAULT_MAX_SIZE,
                          min_size: int = 1, active=None) -> np.ndarray:
    """Eq. 7 texture sides: ``clip(round_half_up(sum_j log2(1 + S_ij / sigma)), min_size, max_size)``.

    Every (active) Gaussian gets at least ``min_size`` (default 1), even with no contribution.

    Args:
      contrib_counts: (num_images, C) S_ij counts.
      sigma: positive scale.
      max_size, min_size: bounds of the side (1 <= min_size <= max_size).
      active: optional (C,) mask; inactive Gaussians get side 0.
    Returns:
      (C,) int64 sides.
    """
    if not 1 <= min_size <= max_size:
        raise ValueError(f"need 1 <= min_size <= max_size, got {min_size}, {max_size}.")
    _, act = _check_counts(contrib_counts, active)
    side = np.clip(np.floor(contribution_sizes(contrib_counts, sigma) + 0.5), min_size, max_size)
    return np.where(act, side, 0).astype(np.int64)


# =============================================================================================
# Budgets
# =============================================================================================
def mb_to_texels(mb: float, floats_per_texel: int = FLOATS_PER_RGBA_TEXEL, bytes_per_value: int = 4) -> int:
    """Texels that fit in ``mb`` MiB (floor), consistent with :func:`patexgs_jax.metrics.storage_mb`.

    With the default 4 floats (RGBA) a texel costs 16 bytes, so ``storage_mb(0, 0, t, t) <= mb`` for
    ``t = mb_to_texels(mb)``.
    """
    if not mb >= 0 or floats_per_texel <= 0 or bytes_per_value <= 0:
        raise ValueError("mb must be >= 0 and floats_per_texel, bytes_per_value positive.")
    return int(math.floor(mb * BYTES_PER_MB / (floats_per_texel * bytes_per_value) + 1e-9))


def texels_to_mb(texels: int, floats_per_texel: int = FLOATS_PER_RGBA_TEXEL, bytes_per_value: int = 4) -> float:
    """MiB taken by ``texels`` texels of ``floats_per_texel`` floats (inverse of :func:`mb_to_texels`)."""
    return int(texels) * floats_per_texel * bytes_per_value / BYTES_PER_MB


def total_texels(sides, active=None) -> int:
    """RGBA texels of an allocation: ``sum_i side_i^2`` over (active) Gaussians; sides (C,) ints."""
    s = np.asarray(sides, np.int64)
    if active is not None:
        s = s * (np.asarray(active) > 0)
    return int(np.sum(s * s))


def _log_budget_residual(log_sigma, args):
    """log(total texels at sigma) - log(target), the function bisected (module-level: compiled once)."""
    S, log_target, min_size, max_size = args
    T = jnp.sum(jnp.log2(1.0 + S / jnp.exp(log_sigma)), axis=0)
    side = jnp.clip(jnp.floor(T + 0.5), min_size, max_size)
    return jnp.log(jnp.sum(side * side)) - log_target


def solve_sigma_for_budget(contrib_counts, target_texels: int, *, max_size: int = DEFAULT_MAX_SIZE,
                           min_size: int = 1, active=None, rtol: float = 0.01, max_steps: int = 200) -> float:
    """The Eq. 7 sigma whose rounded allocation holds ``target_texels`` RGBA texels (within rtol).

    ``total(sigma) = sum_i initial_texture_sizes(S, sigma)_i^2`` is a non-increasing step function
    of sigma; its root in ``log(total / target)`` over log sigma is found with
    ``optimistix.root_find`` and ``optimistix.Bisection``, then the bracket's end closest to the
    target is returned.

    Args:
      contrib_counts: (num_images, C) S_ij counts.
      target_texels: wanted ``sum_i side_i^2`` (e.g. from :func:`mb_to_texels`).
      max_size, min_size, active: as in :func:`initial_texture_sizes`.
      rtol: relative tolerance on the total (default 1%).
    Returns:
      sigma (float).
    Raises:
      ValueError: the target is outside ``[min_total, max_total]`` (all Gaussians at ``min_size``;
        every contributing Gaussian at ``max_size``), or no sigma lands within ``rtol`` (the total
        jumps over the target, e.g. with very few Gaussians).
    """
    import optimistix as optx

    S, act = _check_counts(contrib_counts, active)
    target = float(target_texels)
    if not target > 0:
        raise ValueError(f"target_texels must be positive, got {target_texels}.")

    def total_np(sigma):
        return total_texels(initial_texture_sizes(S, sigma, max_size=max_size, min_size=min_size, active=act))

    contributing = act & (S.sum(axis=0) > 0)
    lo_total = int(np.sum(act)) * min_size**2
    hi_total = int(np.sum(contributing)) * max_size**2 + int(np.sum(act & ~contributing)) * min_size**2
    if not lo_total * (1 - rtol) <= target <= hi_total * (1 + rtol):
        raise ValueError(f"target of {target_texels} texels is unreachable: the Eq. 7 allocation holds "
                         f"between {lo_total} (every Gaussian at side {min_size}) and {hi_total} texels "
                         f"(every contributing Gaussian at side {max_size}).")
    if not contributing.any():
        return 1.0
    # Bracket: at sigma_lo every contributing Gaussian has T >= max_size + 1/2; at sigma_hi all T < 1/2.
    s_min = S[:, contributing].max(axis=0).min()
    sigma_lo = s_min / (2.0 ** (max_size + 0.5) - 1.0) / 2.0
    sigma_hi = 4.0 * S.sum(axis=0).max() / np.log(2.0) + 1.0
    # total(sigma_lo) = hi_total and total(sigma_hi) = lo_total: targets near the ends need no search.
    if abs(hi_total - target) <= rtol * target:
        return float(sigma_lo)
    if abs(lo_total - target) <= rtol * target:
        return float(sigma_hi)

    args = (jnp.asarray(S[:, act], jnp.float32), jnp.float32(np.log(target)), jnp.float32(min_size),
            jnp.float32(max_size))
    solver = optx.Bisection(rtol=0.0, atol=float(np.log1p(rtol)) / 4)
    y0 = jnp.float32(0.5 * (np.log(sigma_lo) + np.log(sigma_hi)))
    sol = optx.root_find(_log_budget_residual, solver, y0, args,
                         options=dict(lower=np.log(sigma_lo), upper=np.log(sigma_hi)),
                         max_steps=max_steps, throw=False)
    candidates = [float(np.exp(sol.value)), float(np.exp(sol.state.lower)), float(np.exp(sol.state.upper))]
    totals = [total_np(s) for s in candidates]
    best = int(np.argmin([abs(t - target) for t in totals]))
    if abs(totals[best] - target) > rtol * target:
        raise ValueError(f"no sigma gives {target_texels} texels within {rtol:.1%}: the allocation jumps "
                         f"from {max(totals)} to {min(totals)} texels near sigma = {candidates[best]:.6g} "
                         "(too few Gaussians for this tolerance?).")
    return candidates[best]


# =============================================================================================
# Eqs. 8-10: progressive growth
# =============================================================================================
@dataclasses.dataclass(frozen=True, kw_only=True)
class GrowthSchedule:
    """Eqs. 8-10 hyper-parameters.

    Attributes:
      t0, t_final: first and last growth iterations (t_final > t0).
      interval: grow every ``interval`` steps from t0 (:meth:`is_growth_step`).
      tau_preset: Eq. 9's initial threshold, in the units of the gradient statistic passed to
        :func:`grow_sizes` (2DGS measures it in NDC units; the renderer's ``screen_offset``
        gradient is in pixels, i.e. smaller by a factor of about W/2).
      max_size: largest texture side growth can reach.
    """

    t0: int
    t_final: int
    interval: int = 100
    tau_preset: float = 1e-5
    max_size: int = DEFAULT_MAX_SIZE

    def __post_init__(self):
        if not self.t_final > self.t0:
            raise ValueError(f"t_final ({self.t_final}) must be larger than t0 ({self.t0}).")
        if self.interval < 1 or self.max_size < 1:
            raise ValueError("interval and max_size must be >= 1.")
        if not self.tau_preset >= 0:
            raise ValueError(f"tau_preset must be >= 0, got {self.tau_preset}.")

    def is_growth_step(self, step: int) -> bool:
        """Whether ``step`` is in [t0, t_final] and a multiple of ``interval`` after t0."""
        return self.t0 <= step <= self.t_final and (step - self.t0) % self.interval == 0

    def tau_high(self, step: int, tau_max: float) -> float:
        """Eq. 9: ``tau_preset + r^3 (tau_max - tau_preset)``, ``r = clip((t - t0)/(t_final - t0), 0, 1)``."""
        r = min(max((step - self.t0) / (self.t_final - self.t0), 0.0), 1.0)
        return float(self.tau_preset + r**3 * (tau_max - self.tau_preset))


def grow_sizes(sizes_float, grad, step: int, schedule: GrowthSchedule, *, active=None,
               texel_budget: int | None = None):
    """One Eq. 8-10 growth event.

    Eligible Gaussians are active ones with a texture (T > 0). ``tau_max`` is the largest gradient
    among them; a Gaussian is selected when ``tau_low < g < tau_high`` (Eq. 8) and its side is below
    ``schedule.max_size``; its real size grows by ``sqrt(g / tau_low)`` (Eq. 10), capped at
    ``max_size``. With ``texel_budget`` (RGBA texels, ``sum side^2`` over active Gaussians), the
    selected Gaussians are taken in order of decreasing gradient and growth stops at the first
    one that would take the total above the budget.

    Args:
      sizes_float: (C,) real sizes T (0 = no texture).
      grad: (C,) non-negative position-gradient statistic (or (C, 2) per-axis values, whose norm
        is used).
      step: the iteration t.
      schedule: the :class:`GrowthSchedule`.
      active: optional (C,) mask.
      texel_budget: optional cap on the total texels after growth.
    Returns:
      ``(new_sizes_float (C,) float64, selected (C,) bool, tau_low, tau_high)``.
    """
    T = np.asarray(sizes_float, np.float64)
    if T.ndim != 1 or not np.all(np.isfinite(T)) or np.any(T < 0):
        raise ValueError("sizes_float must be a (C,) array of finite, non-negative sizes.")
    C = T.shape[0]
    g = np.asarray(grad, np.float64)
    if g.shape == (C, 2):
        g = np.linalg.norm(g, axis=1)
    if g.shape != (C,):
        raise ValueError(f"grad must have shape (C,) or (C, 2) with C = {C}, got {g.shape}.")
    if not np.all(np.isfinite(g)) or np.any(g < 0):
        raise ValueError("grad must be finite and non-negative.")
    act = np.ones(C, bool) if active is None else np.asarray(active) > 0
    if act.shape != (C,):
        raise ValueError(f"active must have shape ({C},), got {act.shape}.")
    eligible = act & (T > 0)
    tau_max = float(g[eligible].max()) if eligible.any() else 0.0
    tau_high = schedule.tau_high(step, tau_max)
    tau_low = 0.9 * tau_high
    side = side_of(T, schedule.max_size)
    sel = eligible & (g > tau_low) & (g < tau_high) & (side < schedule.max_size)
    new_T = T.copy()
    if sel.any():
        new_T[sel] = np.minimum(T[sel] + np.sqrt(g[sel] / tau_low), schedule.max_size)
    if texel_budget is not None and sel.any():
        new_side = side_of(new_T, schedule.max_size)
        order = np.flatnonzero(sel)[np.argsort(-g[sel], kind="stable")]
        extra = np.cumsum(new_side[order] ** 2 - side[order] ** 2)
        room = int(texel_budget) - total_texels(side, act)
        # extra is increasing (each selected side grows), so this is the longest fitting prefix.
        take = order[: int(np.searchsorted(extra, room, side="right"))]
        drop = np.setdiff1d(np.flatnonzero(sel), take)
        new_T[drop] = T[drop]
        sel = np.zeros(C, bool)
        sel[take] = True
    return new_T, sel, float(tau_low), float(tau_high)


@dataclasses.dataclass(frozen=True)
class TextureScheduleState:
    """Checkpointable state of the texture schedule.

    Attributes:
      sizes: (C,) float64 real sizes T (Eqs. 7 and 10); texture sides are :func:`side_of` them.
      last_growth_step: iteration of the last growth event (-1: none yet).
      num_growth_events: growth events run so far.
      num_grown: total selections over all events.
    """

    sizes: np.ndarray
    last_growth_step: int = -1
    num_growth_events: int = 0
    num_grown: int = 0

    @classmethod
    def create(cls, initial_sides) -> "TextureScheduleState":
        """State starting from integer sides (C,), e.g. :func:`initial_texture_sizes`."""
        s = np.asarray(initial_sides)
        if s.ndim != 1 or np.any(s < 0):
            raise ValueError("initial_sides must be a (C,) array of non-negative sides.")
        return cls(sizes=s.astype(np.float64))

    def sides(self, max_size: int = DEFAULT_MAX_SIZE) -> np.ndarray:
        """(C,) int64 texture sides (round half up, clipped to [1, max_size], 0 for no texture)."""
        return side_of(self.sizes, max_size)

    def step(self, grad, step: int, schedule: GrowthSchedule, *, active=None,
             texel_budget: int | None = None):
        """Grows if ``schedule.is_growth_step(step)`` (else no change).

        Returns:
          ``(new_state, sides (C,) int64, selected (C,) bool)``; pass the sides to
          :func:`resize_textures` (for both banks) when ``selected.any()``.
        """
        if not schedule.is_growth_step(step):
            return self, self.sides(schedule.max_size), np.zeros(self.sizes.shape, bool)
        new_T, sel, _, _ = grow_sizes(self.sizes, grad, step, schedule, active=active,
                                      texel_budget=texel_budget)
        new = dataclasses.replace(self, sizes=new_T, last_growth_step=int(step),
                                  num_growth_events=self.num_growth_events + 1,
                                  num_grown=self.num_grown + int(sel.sum()))
        return new, new.sides(schedule.max_size), sel

    def to_dict(self) -> dict[str, Any]:
        """Plain numpy arrays and ints (for ``np.savez`` or a checkpoint's metadata)."""
        return {"sizes": np.asarray(self.sizes, np.float64), "last_growth_step": int(self.last_growth_step),
                "num_growth_events": int(self.num_growth_events), "num_grown": int(self.num_grown)}

    @classmethod
    def from_dict(cls, d) -> "TextureScheduleState":
        """Inverse of :meth:`to_dict` (accepts 0-d arrays for the ints, as ``np.load`` returns)."""
        return cls(sizes=np.asarray(d["sizes"], np.float64), last_growth_step=int(d["last_growth_step"]),
                   num_growth_events=int(d["num_growth_events"]), num_grown=int(d["num_grown"]))

    def __eq__(self, other):
        if not isinstance(other, TextureScheduleState):
            return NotImplemented
        return (np.array_equal(self.sizes, other.sizes) and self.last_growth_step == other.last_growth_step
                and self.num_growth_events == other.num_growth_events and self.num_grown == other.num_grown)

    __hash__ = None
