"""Re-bucketing: texture banks resized (or created) with their Adam moments, for texture growth.

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

  Capacities (the layout). Bucket capacities are static shapes of the jitted training step, so a
  change recompiles it (seconds to a minute on a CPU). While every bucket still holds its textures,
  capacities are kept and slots are stable: a Gaussian whose bucket does not change keeps its slot
  (if its side is unchanged its whole slot, padding included, is copied bit-exactly) and one
  changing bucket takes the lowest free slot of its new bucket after all departures are freed. When
  some bucket overflows (or a bank or bucket appears), the layout is made anew: each bucket that
  overflows (or appears) is sized afresh, the power of two at or above its count plus ``headroom``
  (a share of the count, at least ``min_spare`` slots), never above the scene's capacity; a bucket
  whose textures fit keeps its capacity unless that is over :data:`KEEP_WITHIN` times its afresh
  size (it mostly emptied: it shrinks, and stayers beyond the new capacity move to free slots, a
  copy). So an event that overflows one bucket changes that bucket's shape alone, and the programs
  it runs for it are compiled ahead (:func:`prepare_growth`). A growth event moves a few Gaussians a
  bucket up, so with headroom most events fit the layout they find and compile nothing. Buckets are
  never removed. :class:`ResizeInfo` says when the shapes changed.

The buckets stay on the device: only the old slots of the textures that are resampled come to the
host, and the new blocks and the zeros of the slots left go back (:mod:`.rebucket_device`). Where
the layout is kept they are written in place with ``donate`` (the layout's programs compiled ahead
by :func:`prepare_growth`); where it is made anew, the slots below both capacities are written
through the old layout's program, the buckets whose capacity changes are made anew on the device
(the slots that stay, and the textures moved past a shrunk capacity, copied there) and a grown
bucket's arrivals written through its own program (compiled ahead for the capacity it overflows
to). The resampling is
host-side float64 numpy either way; ``on_device=False`` makes every bucket on the host instead (the
reference, bit for bit the same). Between jitted steps; every function is pure but for
``donate``. Which sizes to give is decided by :mod:`patexgs_jax.adaptive` (the paper's Eqs. 6-10).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..scene import Scene
from . import rebucket_device as rd
from .bank import TextureBank, bucket_of
from .resample import resample_matrix, resample_texture

__all__ = [
    "ALPHA_NEUTRAL",
    "MAX_TEXTURE_SIZE",
    "RGB_NEUTRAL",
    "ResizeInfo",
    "add_textures",
    "prepare_growth",
    "resample_matrix",
    "resample_texture",
    "resize_textures",
]

#: Largest texture side :func:`resize_textures` accepts by default (bucket 9 = 512 x 512 slots).
MAX_TEXTURE_SIZE = 512
#: Values of a newly created texture (rendering-neutral: RGB offset 0, alpha multiplier 1).
RGB_NEUTRAL = 0.0
ALPHA_NEUTRAL = 1.0
_BANKS = ("rgb", "alpha")


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


def _check_headroom(min_capacity, headroom, min_spare) -> None:
    if int(min_capacity) < 1:
        raise ValueError(f"min_capacity must be >= 1, got {min_capacity}.")
    if not float(headroom) >= 0 or int(min_spare) < 0:
        raise ValueError(f"headroom and min_spare must be >= 0, got {headroom} and {min_spare}.")


def _bank_indices(bank: TextureBank):
    size = np.asarray(bank.size).astype(np.int64)
    bucket = np.asarray(bank.bucket).astype(np.int64)
    slot = np.asarray(bank.slot).astype(np.int64)
    return size, bucket, slot


def _capacity(count: int, headroom: float, min_spare: int, min_capacity: int, limit: int) -> int:
    """A bucket's capacity when the layout is made afresh: a power of two holding ``count`` plus
    ``max(headroom * count, min_spare)`` spare slots (at least ``min_capacity``), at most ``limit``
    (a power of two at or above the scene's capacity: a bucket never holds more Gaussians)."""
    if count == 0:
        return 0
    spare = max(int(np.ceil(headroom * count)), int(min_spare))
    return max(min(_next_pow2(max(count + spare, min_capacity)), limit), _next_pow2(count))


#: A new layout keeps a bucket whose textures fit unless its capacity is over this many times the
#: one it would be sized afresh to (the bucket mostly emptied: it shrinks).
KEEP_WITHIN = 4


def _new_capacity(count: int, old: int, headroom: float, min_spare: int, min_capacity: int, limit: int) -> int:
    """A bucket's capacity in a new layout: kept where its ``count`` textures fit and it is at most
    :data:`KEEP_WITHIN` times its afresh size (so that an event that overflows one bucket changes
    that bucket's shape alone, whose programs are compiled ahead), else sized afresh."""
    fresh = _capacity(count, headroom, min_spare, min_capacity, limit)
    return old if count <= old <= KEEP_WITHIN * fresh else fresh


def _plan(bank: TextureBank, new_size: np.ndarray, min_capacity: int, headroom: float = 0.0,
          min_spare: int = 0) -> _BankPlan:
    old_size, old_bucket, old_slot = _bank_indices(bank)
    C = old_size.shape[0]
    # ceil(log2 n) = bit_length(n - 1), looked up per side; -1 for no texture.
    lut = np.array([-1] + [bucket_of(n) for n in range(1, int(new_size.max(initial=0)) + 1)], np.int64)
    new_bucket = lut[new_size]
    nb = max(bank.num_buckets, int(new_bucket.max(initial=-1)) + 1)
    old_caps = list(bank.capacities) + [0] * (nb - bank.num_buckets)
    counts = np.bincount(new_bucket[new_bucket >= 0], minlength=nb)
    if all(int(c) <= cap for c, cap in zip(counts, old_caps)):
        caps = old_caps
    else:  # the shapes change anyway: the buckets that overflow sized afresh (see the module docstring)
        caps = [_new_capacity(int(c), int(cap), headroom, min_spare, min_capacity, _next_pow2(C))
                for c, cap in zip(counts, old_caps)]
    cap_of = np.asarray(list(caps) + [0], np.int64)[np.maximum(old_bucket, 0)]  # (C,) the old bucket's new capacity
    stay = (new_size > 0) & (new_bucket == old_bucket) & (old_slot < cap_of)
    new_slot = np.where(stay, old_slot, 0)
    # Each arrival (index order) takes the lowest free slot of its bucket: one occupancy mask over
    # every bucket's slots, then a pass over the buckets that receive arrivals.
    arriving = np.flatnonzero(~stay & (new_bucket >= 0))
    if arriving.size:
        offsets = np.concatenate([[0], np.cumsum(caps)]).astype(np.int64)
        used = np.zeros(int(offsets[-1]), bool)
        st = np.flatnonzero(stay)
        used[offsets[new_bucket[st]] + old_slot[st]] = True
        to = new_bucket[arriving]
        for b in np.unique(to):
            rows = arriving[to == b]
            free = np.flatnonzero(~used[offsets[b]:offsets[b + 1]])
            new_slot[rows] = free[: rows.size]
    return _BankPlan(old_size, new_size, old_bucket, old_slot, new_bucket, new_slot, tuple(caps),
                     bank.channels)


def _groups(rows: np.ndarray, n_old: np.ndarray, n_new: np.ndarray):
    """``(n, m, idx)`` for each (old side, new side) pair among ``rows``, sorted once by n * 2^20 + m
    (a unique over (n, m) rows sorts slowly)."""
    codes = n_old[rows] * (1 << 20) + n_new[rows]
    order = np.argsort(codes, kind="stable")
    rows, codes = rows[order], codes[order]
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]]) if rows.size else np.zeros(0, np.int64)
    for a, b in zip(starts, np.r_[starts[1:], rows.size].astype(np.int64)):
        yield int(codes[a] >> 20), int(codes[a] & ((1 << 20) - 1)), rows[a:b]


def _new_texels(n: int, m: int, src, fresh_value) -> np.ndarray:
    """(k, m, m, ch) texels of k textures going from side n to m; ``src`` (k, n, n, ch) their old
    texels (unused for n = 0: new textures take ``fresh_value``)."""
    if n == 0:
        return np.broadcast_to(np.asarray(fresh_value, np.float32), (src.shape[0], m, m, src.shape[-1]))
    if n == 1:  # a constant stays one: no resampling needed
        return np.broadcast_to(np.asarray(src, np.float32), (src.shape[0], m, m, src.shape[-1]))
    return resample_texture(src, m)


def _layout_kept(plan: _BankPlan, old_buckets) -> bool:
    return len(old_buckets) == len(plan.capacities) and all(
        o.shape[0] == c for o, c in zip(old_buckets, plan.capacities))


def _apply_plan(plan: _BankPlan, old_buckets, fresh_value: float | np.ndarray):
    """New bucket arrays (numpy) from old ones following ``plan``, on the host: every stayer copied to
    its new slot (the layout made afresh; also the reference the in-place path is tested against)."""
    old = [np.asarray(b) for b in old_buckets]
    ch = plan.channels
    n_old, n_new = plan.old_size, plan.new_size
    new = [np.zeros((cap, 1 << b, 1 << b, ch), np.float32) for b, cap in enumerate(plan.capacities)]
    same = (n_new > 0) & (n_new == n_old)
    for b in np.unique(plan.new_bucket[same]):
        idx = np.flatnonzero(same & (plan.new_bucket == b))
        new[b][plan.new_slot[idx]] = old[b][plan.old_slot[idx]]  # bit-exact, padding included
    for n, m, idx in _groups(np.flatnonzero((n_new > 0) & (n_new != n_old)), n_old, n_new):
        src = np.zeros((idx.size, 1, 1, ch), np.float32) if n == 0 else old[bucket_of(n)][plan.old_slot[idx], :n, :n]
        new[bucket_of(m)][plan.new_slot[idx], :m, :m] = _new_texels(n, m, src, fresh_value)
    return new


def pad_pow8(x: np.ndarray, fill, floor: int = 64, limit: int | None = None) -> np.ndarray:
    """``x`` padded along its first axis to a power of 8 (at least ``floor``) with ``fill``, cut to
    ``limit`` when given (never below ``x``'s length): it bounds the shapes, so that the programs
    fed with it (here, and densification's row writes) compile a few times in a run, not once an
    event (powers of two still compiled 16 programs at the seventh event of a 1M-Gaussian scene)."""
    k = x.shape[0]
    size = floor
    while size < k:
        size *= 8
    if limit is not None:
        size = max(min(size, int(limit)), k)
    out = np.empty((size,) + x.shape[1:], x.dtype)
    out[:k] = x
    out[k:] = fill
    return out


@dataclasses.dataclass(frozen=True)
class _Moves:
    """What a resize reads and writes on the device, the same for every tree of the bank (parameters and
    moments): the textures whose side changes; where a bucket shrinks, those past its capacity move."""

    reads: dict       # old bucket -> (k,) slots of the textures resampled (side n >= 1 -> m >= 1)
    resampled: list   # (n, m, old bucket, rows of reads[old bucket], new bucket, positions in writes)
    fresh: list       # (m, new bucket, positions in writes): textures appearing (0 -> m), fresh values
    writes: dict      # new bucket -> (k,) unique slots written whole (blocks zero but for the above)
    copies: dict      # bucket -> ((k,) old slots, (k,) new slots): unchanged textures that move


def _moves(plan: _BankPlan) -> _Moves:
    n_old, n_new = plan.old_size, plan.new_size
    caps = np.asarray(plan.capacities, np.int64)
    changed = np.flatnonzero(n_old != n_new)
    left = changed[n_old[changed] > 0]       # their old slots are zeroed (or rewritten below)
    left = left[plan.old_slot[left] < caps[plan.old_bucket[left]]]  # (past a shrunk capacity: gone)
    arrive = changed[n_new[changed] > 0]
    moved = np.flatnonzero((n_new > 0) & (n_new == n_old) & (plan.new_slot != plan.old_slot))
    copies = {int(b): (plan.old_slot[r], plan.new_slot[r])
              for b in np.unique(plan.new_bucket[moved]) for r in [moved[plan.new_bucket[moved] == b]]}
    slots: dict[int, list] = {}
    for rows, bucket, slot in ((left, plan.old_bucket, plan.old_slot), (arrive, plan.new_bucket, plan.new_slot)):
        for b in np.unique(bucket[rows]):
            slots.setdefault(int(b), []).append(slot[rows[bucket[rows] == b]])
    writes = {b: np.unique(np.concatenate(parts)) for b, parts in slots.items()}
    for b, (_, dst) in copies.items():  # a moved texture may take a slot another left: not zeroed
        if b in writes:
            writes[b] = np.setdiff1d(writes[b], dst)

    def positions(rows):
        b = bucket_of(int(n_new[rows[0]]))
        return b, np.searchsorted(writes[b], plan.new_slot[rows])

    reads: dict[int, list] = {}
    resampled, fresh = [], []
    for n, m, idx in _groups(arrive, n_old, n_new):
        b_new, pos = positions(idx)
        if n == 0:
            fresh.append((m, b_new, pos))
            continue
        b_old = bucket_of(n)
        parts = reads.setdefault(b_old, [])
        start = sum(p.size for p in parts)
        parts.append(plan.old_slot[idx])
        resampled.append((n, m, b_old, slice(start, start + idx.size), b_new, pos))
    return _Moves({b: np.concatenate(p) for b, p in reads.items()}, resampled, fresh, writes, copies)


#: Share of a bank's textures up to which a new layout is made on the device (a growth event's few percent);
DEVICE_MAX_SHARE = 0.05  # above it (the Eq. 7 allocation) the host's whole copy costs less than chunked moves


def _few_change(plan: _BankPlan) -> bool:
    return bool(np.count_nonzero(plan.old_size != plan.new_size) <= DEVICE_MAX_SHARE * max(1, np.count_nonzero(
        (plan.old_size > 0) | (plan.new_size > 0))))


def _apply_plan_device(plan: _BankPlan, old_buckets, fresh_value, moves: _Moves, donate: bool):
    """The buckets stay on the device and only the slots that change are read and written there (a
    few percent of them; :mod:`patexgs_jax.textures.rebucket_device`), instead of a copy of every
    bucket through the host. Where the layout is made afresh, the buckets whose capacity changes are
    first made anew on the device (their old slots that stay, the textures that move). Written: the
    textures resized or new (their whole slot, zero padding included) and the slots left (zeros);
    every other slot is unchanged, bit for bit: :func:`_apply_plan`'s result."""
    ch = plan.channels
    got = rd.read_slots(old_buckets, moves.reads) if moves.reads else {}
    blocks = {b: np.zeros((s.size, 1 << b, 1 << b, ch), np.float32) for b, s in moves.writes.items()}
    for n, m, b_old, rows, b_new, pos in moves.resampled:
        blocks[b_new][pos, :m, :m] = _new_texels(n, m, got[b_old][rows, :n, :n], fresh_value)
    for m, b_new, pos in moves.fresh:
        blocks[b_new][pos, :m, :m] = np.asarray(fresh_value, np.float32)
    writes = {b: (s, blocks[b]) for b, s in moves.writes.items()}
    if _layout_kept(plan, old_buckets):
        return rd.write_slots(old_buckets, writes, donate)
    return rd.relayout_and_write(old_buckets, plan.capacities, moves.copies, ch, writes, donate)


def _bank_from_plan(plan: _BankPlan, buckets, with_indices: bool, old: TextureBank | None = None) -> TextureBank:
    """The new bank; a moment tree's index leaves (zeros) are ``old``'s where given, else new zeros."""
    C = plan.new_size.shape[0]
    if not with_indices and old is not None:
        return dataclasses.replace(old, buckets=tuple(buckets))
    if with_indices:
        bucket, slot, size = plan.new_bucket, np.where(plan.new_size > 0, plan.new_slot, 0), plan.new_size
    else:  # moment trees: index leaves are zeros
        bucket = slot = size = np.zeros(C)
    # (converted on the host: jnp.asarray of an int64 array converts with an XLA program)
    bucket, slot, size = jax.device_put([np.asarray(x, np.float32) for x in (bucket, slot, size)])
    return TextureBank(buckets=tuple(jnp.asarray(b) for b in buckets), bucket=bucket, slot=slot, size=size,
                       channels=plan.channels)


def _empty_bank(C: int, channels: int) -> TextureBank:
    return TextureBank(buckets=(), bucket=jnp.full((C,), -1.0, jnp.float32),
                       slot=jnp.zeros((C,), jnp.float32), size=jnp.zeros((C,), jnp.float32),
                       channels=channels)


def _is_scene(x) -> bool:
    """Whether an optimiser-state node is a :class:`Scene` of moments (a leaf for tree maps)."""
    return isinstance(x, Scene)


def _map_scene_nodes(opt_state, fn: Callable[[Scene], Scene]):
    """Applies ``fn`` to every Scene-shaped node (Adam's mu and nu) of an optimiser state."""
    return jax.tree_util.tree_map(lambda x: fn(x) if _is_scene(x) else x, opt_state,
                                  is_leaf=_is_scene)


def _check_moment_bank(mbank, bank: TextureBank, name: str):
    if mbank is None or tuple(x.shape for x in mbank.buckets) != tuple(x.shape for x in bank.buckets):
        raise ValueError(f"the optimiser state's moments of the {name!r} bank do not match the scene's "
                         "bucket shapes; was opt_state made for this scene?")


def resize_textures(scene: Scene, opt_state, rgb_sizes, alpha_sizes, *, min_capacity: int = 1,
                    headroom: float = 0.0, min_spare: int = 0, max_size: int = MAX_TEXTURE_SIZE,
                    donate: bool = False, on_device: bool = True):
    """Changes texture sides, resampling texels and their Adam moments (see the module docstring).

    Args:
      scene: the parameters; the banks being resized must exist (use :func:`add_textures` first).
      opt_state: optimiser state whose Scene-shaped nodes (Adam ``mu``, ``nu``) mirror ``scene``,
        or None (e.g. for inference).
      rgb_sizes, alpha_sizes: (C,) integer new sides (0 = no texture, at most ``max_size``), or
        None to leave that bank unchanged.
      min_capacity: a bucket sized afresh (see the module docstring) gets at least this capacity
        (rounded up to a power of two).
      headroom, min_spare: a bucket sized afresh gets ``max(headroom * count, min_spare)`` free
        slots beyond its count (then rounded up to a power of two), so that the next resizes that
        move a few textures into it keep the layout (and the jitted step's program).
      max_size: largest side accepted.
      donate: the banks' buckets (parameters and moments) are written in place where their
        capacity is kept, their old buffers reused: the caller must not read ``scene``'s or
        ``opt_state``'s texture buckets afterwards (the trainer's growth events; ignored where a
        buffer is shared).
      on_device: the buckets stay on the device and only the slots that change cross to the host
        (the default, where the layout is kept or at most :data:`DEVICE_MAX_SHARE` of a bank's
        textures change); False
        makes every bucket on the host (the reference the device path is
        tested against, and what it is measured against: the same result, bit for bit).
    Returns:
      ``(scene, opt_state, ResizeInfo)``; opt_state is None if it was None.
    """
    C = scene.capacity
    _check_headroom(min_capacity, headroom, min_spare)
    plans = {}
    for name, sizes in zip(_BANKS, (rgb_sizes, alpha_sizes)):
        if sizes is None:
            continue
        bank = getattr(scene, name)
        if bank is None:
            raise ValueError(f"the scene has no {name!r} bank; create it with add_textures.")
        plans[name] = _plan(bank, _check_sizes(sizes, C, f"{name}_sizes", int(max_size)), int(min_capacity),
                            float(headroom), int(min_spare))

    if opt_state is not None:
        for m in jax.tree_util.tree_leaves(opt_state, is_leaf=_is_scene):
            if isinstance(m, Scene):
                for name in plans:
                    _check_moment_bank(getattr(m, name), getattr(scene, name), name)

    trees = [scene] + [m for m in jax.tree_util.tree_leaves(opt_state, is_leaf=_is_scene) if _is_scene(m)]
    moves = {name: _moves(plan) for name, plan in plans.items()
             if on_device and (_few_change(plan) or _layout_kept(plan, getattr(scene, name).buckets))}
    donate = bool(donate) and rd.can_donate([b for t in trees for name in moves for b in getattr(t, name).buckets])

    def apply(s: Scene, is_params: bool) -> Scene:
        kw = {}
        for name, plan in plans.items():
            fresh = (RGB_NEUTRAL if name == "rgb" else ALPHA_NEUTRAL) if is_params else 0.0
            old = getattr(s, name)
            if name in moves:
                buckets = _apply_plan_device(plan, old.buckets, fresh, moves[name], donate)
                kw[name] = _bank_from_plan(plan, buckets, with_indices=is_params, old=old)
            else:
                kw[name] = _bank_from_plan(plan, _apply_plan(plan, old.buckets, fresh), with_indices=is_params)
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
                 alpha_init=ALPHA_NEUTRAL, *, min_capacity: int = 1, headroom: float = 0.0, min_spare: int = 0,
                 max_size: int = MAX_TEXTURE_SIZE):
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
      min_capacity, headroom, min_spare, max_size: as in :func:`resize_textures`.
    Returns:
      ``(scene, opt_state, ResizeInfo)``: existing leaves and their moments and the step count are
      kept unchanged; the new bank's moments are zero.
    """
    C = scene.capacity
    _check_headroom(min_capacity, headroom, min_spare)
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
                     int(min_capacity), float(headroom), int(min_spare))
        buckets = _apply_plan(plan, [], init.astype(np.float32))  # every texture is new: init
        kw[name] = _bank_from_plan(plan, buckets, with_indices=True)
        plans[name] = plan
    new_scene = scene.replace(**kw)
    info = _info(scene, new_scene, plans)
    if opt_state is None:
        return new_scene, None, info

    if optimizer is None:
        def merge(m: Scene) -> Scene:
            return m.replace(**{k: jax.tree_util.tree_map(jnp.zeros_like, v) for k, v in kw.items()})
        return new_scene, _map_scene_nodes(opt_state, merge), info

    fresh = optimizer.init(new_scene)
    old_leaves, old_def = jax.tree_util.tree_flatten(opt_state, is_leaf=_is_scene)
    new_leaves, new_def = jax.tree_util.tree_flatten(fresh, is_leaf=_is_scene)
    if old_def != new_def:
        raise ValueError("optimizer.init(new scene) is not laid out like opt_state (outside the "
                         "Scene-shaped moments); is `optimizer` the one that made opt_state?")
    merged = []
    for o, n in zip(old_leaves, new_leaves):
        if _is_scene(o):
            merged.append(o.replace(**{k: getattr(n, k) for k in kw}))
        else:
            if np.shape(o) != np.shape(n):
                raise ValueError("optimiser state leaf shapes differ between the old and new scene.")
            merged.append(o)
    return new_scene, jax.tree_util.tree_unflatten(old_def, merged), info


def prepare_growth(scene: Scene, *, min_capacity: int = 1, headroom: float = 0.0, min_spare: int = 0) -> None:
    """Compiles, in a background thread, the programs with which :func:`resize_textures` (``donate=True``,
    with these layout arguments) writes ``scene``'s bucket layout in place
    (:func:`patexgs_jax.textures.rebucket_device.prepare`), and those an event that overflows one
    bucket runs for that bucket (:func:`~patexgs_jax.textures.rebucket_device.prepare_overflow`: the
    capacity the bucket takes when one texture more than it holds arrives): called when a layout is
    made and growth events will follow, so that the events compile nothing."""
    limit = _next_pow2(scene.capacity)
    for name in _BANKS:
        bank = getattr(scene, name)
        if bank is not None:
            rd.prepare(bank.buckets, donate=True)
            caps = bank.capacities
            rd.prepare_overflow(bank.buckets, lambda b, caps=caps: _new_capacity(
                int(caps[b]) + 1, int(caps[b]), headroom, min_spare, min_capacity, limit))
