"""Adaptive density control (3DGS / 2DGS clone, split, prune, opacity reset) on fixed-capacity scenes.

Where it runs. :func:`accumulate` is written with ``jax.numpy`` and runs inside the jitted step.
The rest runs between steps. The decisions (which Gaussians clone, split or go; where new ones
go) are made on the host from small arrays: the active flags, log scales and opacity logits (one
float a Gaussian, or two or three) and the statistics, plus the split Gaussians' means and
rotations, gathered on the device. When the capacity is kept (the common case) the rows that change
are then written on the device in place (:mod:`patexgs_jax.densify_device`), in the parameters and
in each Adam moment tree, so that a densification moves a few percent of the rows, not a copy of
every leaf through the host and back (seconds at a million Gaussians); the statistics (three floats
a Gaussian) are rebuilt on the host. When the capacity doubles
(a few times a run) the shapes change anyway and every leaf is gathered on the host; that path
(also reachable with ``in_place=False`` of the private ``_densify_and_prune``) gives the same
result bit for bit. :func:`resize_capacity`, :func:`prune_gaussians` and :func:`reset_opacity`
work on the host.

Gradient statistic
  The renderer's ``screen_offset`` gradient ``g = (gx, gy)`` is in loss per *pixel*. 3DGS and 2DGS
  threshold the gradient with respect to the projected mean in *NDC* (x_ndc in [-1, 1] across the
  image width W, so ``x_pix = ((x_ndc + 1) W - 1) / 2`` and ``dx_pix / dx_ndc = W / 2``). Hence
  ``g_ndc = (gx * W / 2, gy * H / 2)`` and each view where a Gaussian is visible adds
  ``|g_ndc|`` to its sum and 1 to its count. The densification statistic is the mean
  ``sum / count`` (0 where count is 0), compared with ``grad_threshold`` (>=, as 3DGS).

Densify and prune (one call of :func:`densify_and_prune`, in this order, as 3DGS)
  * Candidates: active Gaussians with mean gradient >= ``grad_threshold``. With ``max_gaussians``
    set, candidates are taken in order of decreasing gradient while the active count after cloning
    and splitting stays <= ``max_gaussians`` (clone costs 1 slot, split ``split_count - 1``).
  * Clone: max scale <= ``percent_dense * scene_radius``: an exact copy in a free slot.
  * Split: max scale above that: ``split_count`` children replace the Gaussian (child 0 reuses
    its slot, the others take free slots). Child means are ``mean + u t_u + v t_v`` with
    ``u ~ N(0, s_u)``, ``v ~ N(0, s_v)`` along the tangent axes t_u, t_v (rotation columns 0, 1),
    i.e. samples of the 2D Gaussian in its own plane (of a 3D Gaussian, along its three axes, as
    3DGS); child scales are the parent's divided by
    ``0.8 * split_count`` (1.6 for the default 2, as 3DGS/2DGS); rotation, opacity, SH are copied.
  * Prune (applied after growth, to old and new Gaussians): opacity < ``prune_opacity``; with
    ``prune_large`` (3DGS: after the first opacity reset, see :meth:`DensifyConfig.prune_large`)
    also max screen radius over the interval > ``max_screen_radius`` px, or max scale >
    ``max_world_scale * scene_radius``. New Gaussians have no screen radius yet (never
    screen-pruned). (The 3DGS reference code zeroes its radius buffer when it appends clones,
    before pruning, so its screen-size test never fires; the authors confirm this was also the case
    in their evaluation, graphdeco-inria/gaussian-splatting issue #123. Here the test is applied as
    the paper describes; set ``max_screen_radius=None`` to match the reference code.)
  * Slots: new Gaussians go into inactive slots, lowest index first; if there are too few, the
    capacity is doubled (repeatedly) so compiled shapes stay few. Pruned slots become inactive and
    their parameters are reset to the inactive fill values (means 0, log scales 0, identity
    quaternion, opacity logit -20, SH 0, no texture). No compaction: slots never move.

Optimiser moments (Adam ``mu`` and ``nu``, see :func:`patexgs_jax.optim.map_moments`)
  Every row follows its Gaussian through the same index mapping as the parameters: unchanged
  Gaussians keep theirs, new Gaussians (clones and all split children) start from zero moments
  (as 3DGS, which appends zero state for new points; ``copy_clone_moments=True`` copies the
  parent's instead for clones), pruned rows are zeroed. The Adam step count is kept.

Statistics
  After a densification the statistics restart (all rows zero, as 3DGS) unless
  ``reset_all_stats=False``, in which case only the rows of clones and their parents, split
  children and pruned Gaussians are zeroed.

Textures
  Densification belongs to the untextured 2DGS stage. For a textured scene, pruning works (the
  pruned rows lose their texture: bank index -1, size 0, and their texels and texel moments are
  zeroed so a later allocation of that bucket slot starts clean; bucket shapes are unchanged) but
  cloning or splitting raises NotImplementedError; call with ``grow=False`` (or use
  :func:`prune_gaussians`) on textured scenes.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import densify_device as _dev
from .scene import Scene
from .textures import TextureBank

INACTIVE_OPACITY_LOGIT = -20.0
_PARAM_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh", "active")
_BANK_INDEX_FIELDS = ("bucket", "slot", "size")


# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control settings (3DGS / 2DGS defaults; see the module docstring).

    Attributes:
      grad_threshold: threshold on the mean NDC-space positional gradient norm.
      percent_dense: times the scene radius: clone if max scale <= it, else split.
      split_count: children per split.
      prune_opacity: prune below this opacity.
      max_screen_radius: prune above this screen radius in pixels (None: never), when
        ``prune_large``.
      max_world_scale: times the scene radius: prune larger max scales (None: never), when
        ``prune_large``.
      start, stop, interval: densify at steps ``start < step < stop`` with ``step % interval == 0``.
      opacity_reset_interval: reset opacities at multiples of it (while ``step < stop``).
      opacity_reset_value: the opacity cap the reset applies.
      max_gaussians: optional cap on the active count (budgets); highest gradients win.
      copy_clone_moments: clones copy their parent's Adam moments instead of starting at zero.
      reset_all_stats: zero all statistics after a densification (3DGS); else only touched rows.
    """

    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    split_count: int = 2
    prune_opacity: float = 0.05
    max_screen_radius: float | None = 20.0
    max_world_scale: float | None = 0.1
    start: int = 500
    stop: int = 15000
    interval: int = 100
    opacity_reset_interval: int = 3000
    opacity_reset_value: float = 0.01
    max_gaussians: int | None = None
    copy_clone_moments: bool = False
    reset_all_stats: bool = True

    def __post_init__(self):
        if self.split_count < 1:
            raise ValueError(f"split_count must be >= 1, got {self.split_count}.")
        if self.interval < 1 or self.opacity_reset_interval < 1:
            raise ValueError("interval and opacity_reset_interval must be positive.")
        if self.max_gaussians is not None and self.max_gaussians < 0:
            raise ValueError(f"max_gaussians must be >= 0 or None, got {self.max_gaussians}.")
        if not 0.0 < self.opacity_reset_value < 1.0:
            raise ValueError(f"opacity_reset_value must lie in (0, 1), got {self.opacity_reset_value}.")

    # Schedule helpers (steps count from 1, as the 3DGS training loop's `iteration`).
    def accumulate_at(self, step: int) -> bool:
        """Whether statistics are gathered at this step (3DGS: while step < stop)."""
        return step < self.stop

    def densify_at(self, step: int) -> bool:
        """Whether to call :func:`densify_and_prune` after this step."""
        return self.start < step < self.stop and step % self.interval == 0

    def densify_steps(self, until: int) -> list[int]:
        """The steps before ``until`` after which :meth:`densify_at` densifies, in order."""
        return [t for t in range(self.interval, until, self.interval) if self.densify_at(t)]

    def reset_opacity_at(self, step: int) -> bool:
        """Whether to call :func:`reset_opacity` after this step (after densifying, if both)."""
        return 0 < step < self.stop and step % self.opacity_reset_interval == 0

    def prune_large(self, step: int) -> bool:
        """Size pruning is on once the first opacity reset has happened (3DGS)."""
        return step > self.opacity_reset_interval

    @property
    def split_scale_divisor(self) -> float:
        return 0.8 * self.split_count


# ------------------------------------------------------------------------------------------------
@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DensifyStats:
    """Per-slot densification statistics (C,) each; a pytree, so it can live inside jit.

    Attributes:
      grad_sum: sum over views of the NDC positional gradient norm (visible views only).
      count: number of views in which the Gaussian was visible.
      max_radius: largest screen radius (pixels) seen.
    """

    grad_sum: Any
    count: Any
    max_radius: Any

    @classmethod
    def zeros(cls, capacity: int) -> DensifyStats:
        # Three distinct buffers: the training step donates the statistics.
        z = [jax.device_put(np.zeros((int(capacity),), np.float32)) for _ in range(3)]
        return cls(grad_sum=z[0], count=z[1], max_radius=z[2])

    @property
    def capacity(self) -> int:
        return int(np.shape(self.grad_sum)[0])

    def mean_grad(self) -> np.ndarray:
        """Host-side (C,) mean gradient norm, 0 where never visible."""
        s, c = np.asarray(self.grad_sum, np.float64), np.asarray(self.count, np.float64)
        return np.where(c > 0, s / np.maximum(c, 1.0), 0.0)


def accumulate(stats: DensifyStats, screen_grad, visible, radius, width: int, height: int) -> DensifyStats:
    """Adds one view to the statistics (jit-compatible).

    Args:
      stats: the running statistics.
      screen_grad: (C, 2) gradient of the loss w.r.t. the renderer's ``screen_offset`` (pixels).
      visible: (C,) bool (``RenderOutput.visible``).
      radius: (C,) screen radius in pixels (``RenderOutput.radius_px``).
      width, height: image size W, H of this view (pixel -> NDC: x by W/2, y by H/2).
    """
    g = jnp.asarray(screen_grad, jnp.float32)
    scale = jnp.asarray([0.5 * width, 0.5 * height], jnp.float32)
    norm = jnp.sqrt(jnp.sum(jnp.square(g * scale), axis=-1))
    vis = jnp.asarray(visible).astype(bool)
    r = jnp.asarray(radius, jnp.float32)
    return DensifyStats(
        grad_sum=stats.grad_sum + jnp.where(vis, norm, 0.0),
        count=stats.count + vis.astype(jnp.float32),
        max_radius=jnp.where(vis, jnp.maximum(stats.max_radius, r), stats.max_radius))


@dataclasses.dataclass(frozen=True)
class DensifyInfo:
    """What one :func:`densify_and_prune` call did."""

    cloned: int
    split: int            # Gaussians split (each replaced by split_count children)
    pruned: int           # rows deactivated (including new ones pruned right away)
    dropped_by_cap: int   # candidates skipped because of max_gaussians
    num_active_before: int
    num_active_after: int
    capacity_before: int
    capacity_after: int

    @property
    def shapes_changed(self) -> bool:
        return self.capacity_before != self.capacity_after


# ------------------------------------------------------------------------------------------------
# Host-side row operations on Scenes (parameters or moments).

def _fill_value(field: str, moments: bool):
    if moments:
        return 0.0
    return {"quats": np.asarray([1.0, 0.0, 0.0, 0.0], np.float32),
            "opacity_logits": INACTIVE_OPACITY_LOGIT, "bucket": -1.0}.get(field, 0.0)


def _take(a, src, fill):
    """``a[src]`` with ``fill`` where ``src < 0``. ``src`` is mostly the identity (a densification
    moves a few percent of the rows): the rows are copied whole and only the others gathered."""
    a = np.asarray(a)
    n, m = src.shape[0], min(src.shape[0], a.shape[0])
    out = np.empty((n,) + a.shape[1:], a.dtype)
    out[:m] = a[:m]
    out[m:] = fill
    moved = np.flatnonzero(src != np.arange(n))
    from_row = src[moved]
    ok = from_row >= 0
    out[moved[ok]] = a[from_row[ok]]
    out[moved[~ok]] = fill
    return out


def _map_rows(tree: Scene, fn) -> Scene:
    """Applies ``fn(field_name, array) -> array`` to every per-Gaussian leaf (incl. bank indices)."""
    kw = {f: fn(f, getattr(tree, f)) for f in _PARAM_FIELDS}
    if tree.filter3d is not None:  # Mip-Splatting's 3D filter (recomputed after densification)
        kw["filter3d"] = fn("filter3d", tree.filter3d)
    for name in ("rgb", "alpha"):
        bank = getattr(tree, name)
        if bank is not None:
            kw[name] = dataclasses.replace(bank, **{f: fn(f, getattr(bank, f)) for f in _BANK_INDEX_FIELDS})
    return tree.replace(**kw)


def _gather_scene(tree: Scene, src: np.ndarray, moments: bool) -> Scene:
    """Row i of the result is row ``src[i]`` of ``tree``; ``src[i] < 0`` gives the fill value."""
    return _map_rows(tree, lambda f, a: _take(a, src, _fill_value(f, moments)))


def _to_device(tree):
    # device_put, not jnp.asarray: the latter compiles a copy per new shape on first use.
    return jax.tree_util.tree_map(lambda a: jax.device_put(np.asarray(a)), tree)


def resize_capacity(tree, new_capacity: int, *, moments: bool = False):
    """Grows (or shrinks) the per-Gaussian (C, ...) leaves of a Scene or DensifyStats.

    New slots are inactive: identity quaternion, opacity logit -20, texture bank index -1, zeros
    elsewhere; with ``moments=True`` (for Adam ``mu`` / ``nu`` Scenes) every new entry is zero.
    Texture bucket arrays are left as they are. Shrinking is allowed only if every dropped slot of
    a parameter Scene is inactive.
    """
    new_capacity = int(new_capacity)
    if new_capacity < 0:
        raise ValueError(f"capacity must be >= 0, got {new_capacity}.")
    if isinstance(tree, DensifyStats):
        src = np.arange(new_capacity)
        src[src >= tree.capacity] = -1
        return _to_device(DensifyStats(*(_take(getattr(tree, f), src, 0.0)
                                         for f in ("grad_sum", "count", "max_radius"))))
    if not isinstance(tree, Scene):
        raise TypeError(f"resize_capacity expects a Scene or DensifyStats, got {type(tree).__name__}.")
    C = tree.capacity
    if new_capacity < C and not moments and np.any(np.asarray(tree.active)[new_capacity:] > 0):
        raise ValueError(f"cannot shrink capacity {C} -> {new_capacity}: active Gaussians in the "
                         "dropped slots.")
    src = np.arange(new_capacity)
    src[src >= C] = -1
    return _to_device(_gather_scene(tree, src, moments))


def resize_opt_state(opt_state, new_capacity: int):
    """:func:`resize_capacity` applied to both Adam moment Scenes of an optimiser state."""
    from .optim import map_moments

    return map_moments(opt_state, lambda m: resize_capacity(m, new_capacity, moments=True))


def _zero_texels(bank_params: TextureBank, bank_tree: TextureBank, rows: np.ndarray) -> TextureBank:
    """Zeroes the bucket slots that the parameter bank assigns to ``rows`` (bool mask)."""
    if bank_tree is None or not np.any(rows):
        return bank_tree
    bucket = np.asarray(bank_params.bucket).astype(np.int64)
    slot = np.asarray(bank_params.slot).astype(np.int64)
    buckets = list(bank_tree.buckets)
    for b in range(len(buckets)):
        sel = rows & (bucket == b)
        if np.any(sel):
            data = np.array(buckets[b])
            data[slot[sel]] = 0.0
            buckets[b] = data
    return dataclasses.replace(bank_tree, buckets=tuple(buckets))


def _deactivate(tree: Scene, rows: np.ndarray, moments: bool, banks: dict) -> Scene:
    """Resets ``rows`` (bool, C) of a parameter or moment Scene to the inactive fill values and
    zeroes their texels, located through the parameter banks ``banks`` (taken before the reset)."""
    if not np.any(rows):
        return tree
    tree = _gather_scene(tree, np.where(rows, -1, np.arange(rows.shape[0])), moments)
    return tree.replace(**{n: _zero_texels(b, getattr(tree, n), rows) for n, b in banks.items()
                           if b is not None and getattr(tree, n) is not None})


def _remap_state(opt_state, mom_src: np.ndarray, rows: np.ndarray, banks: dict):
    from .optim import map_moments

    if opt_state is None:
        return None
    return map_moments(opt_state, lambda m: _to_device(
        _deactivate(_gather_scene(m, mom_src, moments=True), rows, True, banks)))


def _quat_to_rotmat_np(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-30)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _row_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=1)`` of a (C, 2 or 3) array, column by column: the same values, without numpy's
    slow reduction over a short axis (docs/performance.md)."""
    return functools.reduce(np.maximum, [a[:, k] for k in range(a.shape[1])])


def _has_textures(scene: Scene) -> bool:
    return scene.rgb is not None or scene.alpha is not None


def _check_stats(stats: DensifyStats, C: int):
    if stats.capacity != C:
        raise ValueError(f"statistics have capacity {stats.capacity} but the scene has {C}; "
                         "resize them with resize_capacity.")


# ------------------------------------------------------------------------------------------------
def densify_and_prune(scene: Scene, opt_state, stats: DensifyStats, config: DensifyConfig,
                      scene_radius: float, rng, *, prune_large: bool = True, grow: bool = True,
                      donate: bool = False):
    """Clone, split and prune (see the module docstring).

    Args:
      scene: the parameters (capacity C).
      opt_state: optimiser state from :func:`patexgs_jax.optim.make_optimizer` (or None).
      stats: statistics accumulated since the last densification (capacity C).
      config: :class:`DensifyConfig`.
      scene_radius: the scene extent (camera-based radius, as 3DGS).
      rng: numpy Generator (or an int seed) for the split samples.
      prune_large: also prune by screen radius and world scale (pass ``config.prune_large(step)``).
      grow: clone and split (False: prune only).
      donate: the scene's and moments' device buffers may be reused for the result (written in
        place); ``scene`` and ``opt_state`` must not be used afterwards (the trainer's way).
    Returns:
      (scene, opt_state, stats, DensifyInfo); shapes change only when the capacity doubled.
    """
    return _densify_and_prune(scene, opt_state, stats, config, scene_radius, rng, prune_large=prune_large,
                              grow=grow, in_place=True, donate=donate)


def _split_children(quats, means, log_scales, N: int, divisor: float, rng, dtypes):
    """Means (S, N, 3) and log scales (S, N, d) of the children of S split Gaussians, from their
    quaternions, means and (float64) log scales; one normal draw (S, N, d) from ``rng``."""
    rot = _quat_to_rotmat_np(quats)                                               # (S, 3, 3)
    s = np.exp(log_scales)                                                         # (S, d): 2, or 3 (3D)
    d = s.shape[1]
    uv = rng.normal(size=(s.shape[0], N, d)) * s[:, None, :]                      # (S, N, d)
    offset = sum(uv[..., k:k + 1] * rot[:, None, :, k] for k in range(d))
    base = np.asarray(means, np.float64)
    ls = np.broadcast_to(log_scales[:, None, :] - math.log(divisor), (s.shape[0], N, d))
    return (base[:, None, :] + offset).astype(dtypes[0]), ls.astype(dtypes[1])


def _prune_mask(act_new, logits, grown_log_scales, stats, radius_src, config, radius, prune_large):
    """The prune mask on the grown layout (new Gaussians included, as 3DGS); ``grown_log_scales()``
    gives the grown layout's log scales (read only when needed)."""
    prune = act_new & (1.0 / (1.0 + np.exp(-logits)) < config.prune_opacity)
    if prune_large:
        if config.max_screen_radius is not None:
            max_r = _take(np.asarray(stats.max_radius), radius_src, 0.0)
            prune |= act_new & (max_r > config.max_screen_radius)
        if config.max_world_scale is not None and act_new.size:
            ms = np.exp(_row_max(np.asarray(grown_log_scales(), np.float64)))
            prune |= act_new & (ms > config.max_world_scale * radius)
    return prune


def _densify_and_prune(scene: Scene, opt_state, stats: DensifyStats, config: DensifyConfig,
                       scene_radius: float, rng, *, prune_large: bool, grow: bool, in_place: bool,
                       donate: bool):
    """:func:`densify_and_prune`; ``in_place=False`` takes the host path even when the capacity is
    kept (every leaf through numpy: the reference the device path is tested against)."""
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    C = scene.capacity
    _check_stats(stats, C)
    radius = float(scene_radius)
    N = config.split_count

    active_f = np.asarray(scene.active)
    active = active_f > 0
    ls32 = np.asarray(scene.log_scales)
    log_scales = ls32.astype(np.float64)
    max_scale = np.exp(_row_max(log_scales))
    grads = stats.mean_grad()
    n_active = int(active.sum())

    cand = active & (grads >= config.grad_threshold) & grow
    small = max_scale <= config.percent_dense * radius
    clone_m, split_m = cand & small, cand & ~small
    dropped = 0
    if config.max_gaussians is not None:
        budget = max(0, int(config.max_gaussians) - n_active)
        idx = np.flatnonzero(cand)
        order = idx[np.argsort(-grads[idx], kind="stable")]
        cost = np.where(split_m[order], N - 1, 1)
        take = order[np.cumsum(cost) <= budget]
        keep = np.zeros(C, bool)
        keep[take] = True
        dropped = int(cand.sum() - keep.sum())
        clone_m, split_m = clone_m & keep, split_m & keep
    clone_rows, split_rows = np.flatnonzero(clone_m), np.flatnonzero(split_m)
    if (clone_rows.size or split_rows.size) and _has_textures(scene):
        raise NotImplementedError(
            "densify_and_prune: cloning or splitting textured Gaussians is not supported "
            "(densification belongs to the untextured 2DGS stage); pass grow=False to prune only.")

    n_new = clone_rows.size + split_rows.size * (N - 1)
    free = np.flatnonzero(~active)
    new_C = C
    while free.size + (new_C - C) < n_new:
        new_C = max(2 * new_C, 1)
    free = np.concatenate([free, np.arange(C, new_C)])

    src = np.arange(new_C)
    src[C:] = -1
    mom_src = src.copy()
    stats_src = src.copy()
    clone_slots = free[:clone_rows.size]
    src[clone_slots] = clone_rows
    mom_src[clone_slots] = clone_rows if config.copy_clone_moments else -1
    stats_src[clone_slots] = -1
    extra = free[clone_rows.size:n_new].reshape(split_rows.size, N - 1)
    children = np.concatenate([split_rows[:, None], extra], axis=1)  # (S, N), child 0 in place
    parents = np.repeat(split_rows, N)
    src[children.ravel()] = parents
    mom_src[children.ravel()] = -1
    stats_src[children.ravel()] = -1

    radius_src = stats_src.copy()  # screen radius for the prune test: none yet for new rows
    stats_src[clone_rows] = -1      # kept statistics: a clone's parent restarts too

    in_place = in_place and new_C == C
    child_means = child_ls = None
    if split_rows.size:
        dtypes = (scene.means.dtype, scene.log_scales.dtype)
        if in_place:  # only the split rows cross to the host
            quats_s, means_s = _dev.take_rows((scene.quats, scene.means), split_rows)
        else:
            quats_s, means_s = np.asarray(scene.quats)[split_rows], np.asarray(scene.means)[split_rows]
        child_means, child_ls = _split_children(quats_s, means_s, log_scales[split_rows], N,
                                                config.split_scale_divisor, rng, dtypes)
    changed = bool(n_new or split_rows.size)

    if in_place:
        act_g = _take(active_f, src, 0.0)
        act_g[clone_slots] = 1.0
        act_g[children.ravel()] = 1.0
        act_new = act_g > 0
        logits = _take(np.asarray(scene.opacity_logits), src, INACTIVE_OPACITY_LOGIT).astype(np.float64)

        def grown_ls():
            ls = _take(ls32, src, 0.0)
            if child_ls is not None:
                ls[children] = child_ls
            return ls

        prune = _prune_mask(act_new, logits, grown_ls, stats, radius_src, config, radius, prune_large)
        new_scene, new_state = _dev.apply_in_place(scene, opt_state, src, mom_src, prune, children, clone_slots,
                                                   child_means, child_ls, _fill_value, donate)
    else:
        def post(p: Scene) -> Scene:
            act = np.array(p.active)
            act[clone_slots] = 1.0
            act[children.ravel()] = 1.0
            p = p.replace(active=act)
            if split_rows.size == 0:
                return p
            means = np.array(p.means)
            ls = np.array(p.log_scales)
            means[children] = child_means
            ls[children] = child_ls
            return p.replace(means=means, log_scales=ls)

        grown = post(_gather_scene(scene, src, moments=False)) if changed else scene
        act_new = np.asarray(grown.active) > 0
        logits = np.asarray(grown.opacity_logits, np.float64)
        prune = _prune_mask(act_new, logits, lambda: grown.log_scales, stats, radius_src, config, radius,
                            prune_large)
        if changed or np.any(prune):
            banks = {n: getattr(grown, n) for n in ("rgb", "alpha")}
            new_scene = _to_device(_deactivate(grown, prune, False, banks))
            new_state = _remap_state(opt_state, mom_src, prune, banks)
        else:
            new_scene, new_state = scene, opt_state

    if config.reset_all_stats:
        new_stats = DensifyStats.zeros(new_C)
    else:
        keep_src = np.where(prune, -1, stats_src)
        new_stats = _to_device(DensifyStats(*(_take(getattr(stats, f), keep_src, 0.0)
                                              for f in ("grad_sum", "count", "max_radius"))))
    info = DensifyInfo(cloned=int(clone_rows.size), split=int(split_rows.size), pruned=int(prune.sum()),
                       dropped_by_cap=dropped, num_active_before=n_active,
                       num_active_after=int((act_new & ~prune).sum()), capacity_before=C,
                       capacity_after=new_C)
    return new_scene, new_state, new_stats, info


def prune_gaussians(scene: Scene, opt_state, stats: DensifyStats | None, mask):
    """Deactivates the rows where ``mask`` is true (works with textures; shapes unchanged).

    Returns (scene, opt_state, stats, num_pruned); pruned rows' parameters, moments, texels and
    statistics are reset.
    """
    mask = np.asarray(mask, bool) & (np.asarray(scene.active) > 0)
    banks = {n: getattr(scene, n) for n in ("rgb", "alpha")}
    new_scene = _to_device(_deactivate(scene, mask, False, banks))
    new_state = _remap_state(opt_state, np.arange(scene.capacity), mask, banks)
    if stats is not None:
        _check_stats(stats, scene.capacity)
        stats = _to_device(DensifyStats(*(
            np.where(mask, 0.0, np.asarray(getattr(stats, f))).astype(np.float32)
            for f in ("grad_sum", "count", "max_radius"))))
    return new_scene, new_state, stats, int(mask.sum())


def reset_opacity(scene: Scene, opt_state, value: float = 0.01):
    """Caps every opacity at ``value`` (in logit space: ``min(logit, logit(value))``, exact) and
    zeroes the Adam moments of the opacity logits (as 3DGS). With Mip-Splatting's 3D filter
    (``scene.filter3d``) the cap applies to the filtered opacity, as its reference code does.
    Returns (scene, opt_state)."""
    from .optim import map_moments

    if not 0.0 < value < 1.0:
        raise ValueError(f"reset value must lie in (0, 1), got {value}.")
    cap = np.float32(math.log(value) - math.log1p(-value))
    logits = np.asarray(scene.opacity_logits)
    if scene.filter3d is not None:  # Mip-Splatting caps the opacity the 3D filter leaves
        from .filter3d import opacity_factor

        v = np.minimum(value / opacity_factor(scene.log_scales, scene.filter3d), 1.0 - 1e-7)
        cap = (np.log(v) - np.log1p(-v)).astype(np.float32)
    scene = scene.replace(opacity_logits=jax.device_put(np.minimum(logits, cap.astype(logits.dtype))))
    if opt_state is not None:
        opt_state = map_moments(opt_state, lambda m: m.replace(opacity_logits=jax.device_put(
            np.zeros(np.shape(m.opacity_logits), np.asarray(m.opacity_logits).dtype))))
    return scene, opt_state
