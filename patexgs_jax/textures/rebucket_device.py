"""Slot reads and writes of a texture bank on the device, for re-bucketing.

A growth event within the buckets' headroom changes a few percent of the slots
(:func:`patexgs_jax.textures.rebucket.resize_textures`): the old slots of the textures being
resampled are read (:func:`read_slots`), the host resamples them, and the new blocks, with zeros
in the slots left, are written (:func:`write_slots`); every other slot stays where it is, bit for
bit. With ``donate`` the buckets are written in place (their old buffers are reused: the caller must
not read them again); without it, each call copies the bank. An event that overflows a bucket
makes a new layout (that bucket grown, the others mostly kept): :func:`relayout_and_write` writes
the slots below both capacities through the old layout's program, :func:`relayout` makes the buckets
whose capacity changes anew (one program a bucket) and the grown buckets' arrivals are written
through their own programs, which :func:`prepare_overflow` compiles ahead for the capacity each
bucket takes when it overflows.

Shapes. Each bucket is read and written in chunks of :func:`chunk_slots` slots (about
:data:`CHUNK_TEXELS` texels; the index padded past the capacity, which writes nothing), every bucket
of a bank in one program, so that a layout has one read and one write program a bank whatever the
event: they compile once per layout, at its first event or ahead of it (:func:`prepare`, in a
background thread, e.g. while the training step that follows a new layout compiles).
"""

from __future__ import annotations

import concurrent.futures
import threading
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["CHUNK_TEXELS", "can_donate", "chunk_slots", "layout_shapes", "prepare", "prepare_overflow", "read_slots",
           "relayout", "relayout_and_write", "write_slots"]

#: Texels a bucket's chunk holds (its slots: this over the slot's texels, at least one, at most the
#: capacity): a chunk's padding costs at most this many texels a bucket and a call.
CHUNK_TEXELS = 1 << 17


def chunk_slots(capacity: int, side: int) -> int:
    """Slots a bucket of ``capacity`` slots of ``side x side`` texels reads or writes in one call."""
    return max(1, min(int(capacity), CHUNK_TEXELS // (int(side) * int(side))))


def _gather(buckets, idx):
    return tuple(jnp.take(b, i, axis=0, mode="clip") for b, i in zip(buckets, idx))


def _scatter(buckets, idx, blocks):
    return tuple(b.at[i].set(v, mode="drop") for b, i, v in zip(buckets, idx, blocks))


_gather_jit = jax.jit(_gather)
_scatter_kept = jax.jit(_scatter)
_scatter_donated = jax.jit(_scatter, donate_argnums=0)

_ahead: dict = {}  # program key -> Future of its compiled program
_ahead_lock = threading.Lock()
_pool: concurrent.futures.ThreadPoolExecutor | None = None
_KEEP = 64  # programs kept (a layout has a few a bank, and one or two a bucket for its overflow)


def _live(buckets: Sequence) -> list:
    """The non-empty buckets (the programs take only these)."""
    return [b for b in buckets if b.shape[0] > 0]


def _placement(b):
    """The sharding a program compiled ahead for bucket ``b`` is given: the array's where it is
    committed to its device (or a ``jax.ShapeDtypeStruct``'s own), else None. A program compiled for
    an explicit sharding returns committed arrays, and the training step's jit keys its programs on
    which of its inputs are committed: buckets written through such a program beside the uncommitted
    arrays of a single-device run would make the textured step compile again, in a layout it has
    (docs/performance.md)."""
    if isinstance(b, jax.ShapeDtypeStruct):
        return b.sharding
    return b.sharding if getattr(b, "committed", True) else None


def _spec(shape, b) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(tuple(shape), b.dtype, sharding=_placement(b))


def _abstract(buckets: Sequence):
    live = _live(buckets)
    sizes = tuple(chunk_slots(b.shape[0], b.shape[1]) for b in live)
    args = (tuple(_spec(b.shape, b) for b in live), tuple(jax.ShapeDtypeStruct((k,), jnp.int32) for k in sizes))
    blocks = tuple(jax.ShapeDtypeStruct((k,) + tuple(b.shape[1:]), b.dtype) for b, k in zip(live, sizes))
    # (the chunk sizes too: CHUNK_TEXELS may change between layouts)
    key = tuple((tuple(b.shape), str(b.dtype), _placement(b), k) for b, k in zip(live, sizes))
    return key, args, blocks


def _single_device(buckets: Sequence) -> bool:
    """Whether every bucket (an array, or a ``jax.ShapeDtypeStruct`` of a layout to come) lives on one
    device (a layout to come without a sharding: the default device, as its uncommitted arrays)."""
    def one(b):
        if isinstance(b, jax.ShapeDtypeStruct) and b.sharding is None:
            return True
        return isinstance(getattr(b, "sharding", None), jax.sharding.SingleDeviceSharding)

    return all(isinstance(b, (jax.Array, jax.ShapeDtypeStruct)) and one(b) for b in buckets)


def prepare(buckets: Sequence, donate: bool = True, kinds: Sequence[str] = ("write", "read")) -> None:
    """Compiles a bank's read and write programs for its layout in a background thread (once a layout;
    single-device banks only: others compile at first use, through ``jax.jit``). ``buckets`` may be
    ``jax.ShapeDtypeStruct``-s with a sharding: a layout :func:`relayout` is about to make, whose
    event needs only its ``kinds=("write",)`` (the reads come at the next event)."""
    global _pool
    if not _live(buckets) or not _single_device(_live(buckets)):
        return
    key, args, blocks = _abstract(buckets)
    with _ahead_lock:
        if _pool is None:
            _pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="rebucket-compile")
        write = _scatter_donated if donate else _scatter_kept
        # (the write first: an event that makes a new layout waits for it; the reads come at the next)
        for kind, don, fn, fargs in (("write", donate, write, args + (blocks,)), ("read", False, _gather_jit, args)):
            k = (kind, don, key)  # (reads never donate)
            if kind in kinds and k not in _ahead:
                _ahead[k] = _pool.submit(lambda fn=fn, fargs=fargs: fn.lower(*fargs).compile())
        while len(_ahead) > 2 * _KEEP:
            _ahead.pop(next(iter(_ahead)))


def _program(kind: str, donate: bool, buckets: Sequence):
    """The compiled program prepared for this layout, or the jitted function (compiled at first use)."""
    fn = {"read": _gather_jit, "write": _scatter_donated if donate else _scatter_kept}[kind]
    if not _single_device(buckets):
        return fn
    with _ahead_lock:
        fut = _ahead.get((kind, donate, _abstract(buckets)[0]))
    return fn if fut is None else fut.result()


def can_donate(buckets: Sequence) -> bool:
    """Whether every bucket is a live jax array with a buffer of its own (donating one buffer twice in
    a call would fail)."""
    if not all(isinstance(b, jax.Array) and not b.is_deleted() for b in buckets):
        return False
    keys = []
    for b in buckets:
        try:
            keys.append(b.unsafe_buffer_pointer())
        except Exception:  # not a single-device array: its identity
            keys.append(id(b))
    return len(set(keys)) == len(keys)


def _chunks(buckets: Sequence, counts: dict) -> tuple[list, list, int]:
    """(live bucket indices, their chunk sizes, number of calls) for ``counts`` slots per bucket."""
    live = [b for b, x in enumerate(buckets) if x.shape[0] > 0]
    sizes = [chunk_slots(buckets[b].shape[0], buckets[b].shape[1]) for b in live]
    calls = max([-(-int(counts.get(b, 0)) // k) for b, k in zip(live, sizes)], default=0)
    return live, sizes, calls


def read_slots(buckets: Sequence, slots: dict) -> dict:
    """Host copies of some slots of a bank.

    Args:
      buckets: the bank's buckets; ``buckets[b]`` (cap_b, P_b, P_b, ch).
      slots: {bucket b: (k_b,) int slots to read}.
    Returns:
      {b: (k_b, P_b, P_b, ch) numpy array} in the order of ``slots[b]``.
    """
    live, sizes, calls = _chunks(buckets, {b: len(s) for b, s in slots.items()})
    got: dict = {b: [] for b in slots}
    for c in range(calls):
        idx = []
        for b, k in zip(live, sizes):
            s = np.asarray(slots.get(b, ()), np.int32)[c * k:(c + 1) * k]
            idx.append(np.concatenate([s, np.zeros(k - s.size, np.int32)]))  # (padding reads slot 0)
        out = _program("read", False, buckets)(tuple(buckets[b] for b in live), tuple(jax.device_put(idx)))
        for b, k, o in zip(live, sizes, out):
            if b in got:
                n = min(k, len(slots[b]) - c * k)
                if n > 0:
                    got[b].append(np.asarray(o)[:n])
    return {b: (parts[0] if len(parts) == 1 else np.concatenate(parts)) if parts
            else np.zeros((0,) + tuple(buckets[b].shape[1:]), np.float32) for b, parts in got.items()}


def write_slots(buckets: Sequence, writes: dict, donate: bool) -> list:
    """A bank with some slots rewritten whole.

    Args:
      buckets: the bank's buckets; ``buckets[b]`` (cap_b, P_b, P_b, ch).
      writes: {bucket b: ((k_b,) int unique slots, (k_b, P_b, P_b, ch) float32 blocks)}.
      donate: write in place (the old buckets' buffers are reused; see :func:`can_donate`).
    Returns:
      The new buckets (a list; with no write at all, the old arrays).
    """
    live, sizes, calls = _chunks(buckets, {b: len(s) for b, (s, _) in writes.items()})
    new = list(buckets)
    for c in range(calls):
        idx, blocks = [], []
        for b, k in zip(live, sizes):
            cap = int(buckets[b].shape[0])
            s, v = writes.get(b, ((), None))
            s = np.asarray(s, np.int32)[c * k:(c + 1) * k]
            # Padding: distinct indices past the capacity, which write nothing.
            idx.append(np.concatenate([s, cap + np.arange(k - s.size, dtype=np.int32)]))
            block = np.zeros((k,) + tuple(buckets[b].shape[1:]), np.float32)
            if s.size:
                block[: s.size] = v[c * k: c * k + s.size]
            blocks.append(block)
        idx, blocks = jax.device_put((idx, blocks))  # (one batched transfer)
        out = _program("write", donate, new)(tuple(new[b] for b in live), tuple(idx), tuple(blocks))
        for b, o in zip(live, out):
            new[b] = o
    return new


def layout_shapes(capacities: Sequence[int], channels: int, like: Sequence) -> list:
    """A layout to come, as ``jax.ShapeDtypeStruct``-s on the device of the arrays ``like`` (what
    :func:`prepare` compiles for), or [] where ``like`` holds no array to take the device from."""
    live = [b for b in like if isinstance(b, jax.Array)]
    if not live:
        return []
    return [jax.ShapeDtypeStruct((int(cap), 1 << b, 1 << b, int(channels)), jnp.float32,
                                 sharding=_placement(live[0])) for b, cap in enumerate(capacities)]


def _pow8(k: int, floor: int = 64) -> int:
    size = floor
    while size < k:
        size *= 8
    return size


def _relayout(olds, caps, src, dst):
    """New buckets of capacities ``caps``: each old bucket cut or zero-padded to its new capacity,
    then (where ``src`` is given) slots ``src`` of the old bucket copied to ``dst`` (padded: ``dst``
    past the capacity writes nothing)."""
    out = []
    for o, cap, s, d in zip(olds, caps, src, dst):
        grow = int(cap) - int(o.shape[0])
        new = o[:cap] if grow <= 0 else jnp.pad(o, ((0, grow),) + ((0, 0),) * (o.ndim - 1))
        if s is not None:  # (a small program where nothing moves: the usual bucket that grows)
            new = new.at[d].set(jnp.take(o, s, axis=0, mode="clip"), mode="drop")
        out.append(new)
    return tuple(out)


_relayout_jit = jax.jit(_relayout, static_argnums=1)


def _relayout_program(old, cap: int, src, dst):
    """The program that makes one bucket anew (prepared ahead by :func:`prepare_overflow`, else the
    jitted function, compiled at first use)."""
    key = ("relayout", tuple(old.shape), str(old.dtype), _placement(old), int(cap),
           None if src is None else (int(src.shape[0]),))
    with _ahead_lock:
        fut = _ahead.get(key)
    if fut is not None:
        return fut.result()
    return lambda olds, s, d: _relayout_jit(olds, (int(cap),), s, d)


def relayout(buckets: Sequence, capacities: Sequence[int], copies: dict, channels: int) -> list:
    """A bank's buckets in a new layout, made on the device (a layout made afresh: some bucket
    overflowed, so every bucket was sized again; see :mod:`patexgs_jax.textures.rebucket`).

    Args:
      buckets: the old buckets; ``buckets[b]`` (cap_b, P_b, P_b, ch) (fewer than ``capacities``
        where buckets appear).
      capacities: the new capacity of every bucket.
      copies: {bucket b: ((k,) old slots, (k,) new slots)}: textures that keep their bucket and side
        but move (slots past a shrunk capacity), copied whole.
      channels: the bank's channels (for buckets that appear).
    Returns:
      The new buckets (a list): a bucket whose capacity is unchanged is the old array itself (it has
      nothing to copy); a changed one holds the old slots below both capacities and the copies,
      zeros elsewhere (one program a bucket, so that a bucket's program serves every layout it
      appears in); a new bucket is zeros. Slots whose texture changes are the caller's to write
      (:func:`write_slots`).
    """
    new: list = []
    for b, cap in enumerate(int(c) for c in capacities):
        old = buckets[b] if b < len(buckets) else None
        if old is not None and int(old.shape[0]) == cap:
            if b in copies:
                raise ValueError(f"relayout: bucket {b} keeps its capacity and cannot move textures")
            new.append(old)
        elif old is not None and int(old.shape[0]) > 0 and cap > 0:
            s, d = (np.asarray(x, np.int32) for x in copies.get(b, ((), ())))
            src = dst = None
            if s.size:
                k = _pow8(s.size)  # (bounded shapes: few programs a run)
                src, dst = jax.device_put((np.concatenate([s, np.zeros(k - s.size, np.int32)]),
                                           np.concatenate([d, cap + np.arange(k - d.size, dtype=np.int32)])))
            new.append(_relayout_program(old, cap, src, dst)((old,), (src,), (dst,))[0])
        else:
            new.append(jnp.zeros((cap, 1 << b, 1 << b, int(channels)), jnp.float32))
    return new


def relayout_and_write(buckets: Sequence, capacities: Sequence[int], copies: dict, channels: int, writes: dict,
                       donate: bool) -> list:
    """:func:`relayout` and :func:`write_slots` in the order that needs no program of the new
    layout's whole bank: the writes below both capacities first, through the old layout's program
    (compiled ahead for its growth events), then each changed bucket made anew, then the writes past
    its old capacity (a grown bucket's arrivals) through that bucket's own program (compiled ahead for
    the capacity it takes when it overflows: :func:`prepare_overflow`). The writes and the copies
    touch different slots, so the order leaves every slot as :func:`relayout` then :func:`write_slots`
    would."""
    old_caps = [int(x.shape[0]) for x in buckets] + [0] * (len(capacities) - len(buckets))
    first, rest = {}, {}
    for b, (s, v) in writes.items():
        s = np.asarray(s)
        below = s < min(old_caps[b], int(capacities[b]))
        if below.any():
            first[b] = (s[below], v[below])
        if not below.all():
            rest[b] = (s[~below], v[~below])
    new = write_slots(buckets, first, donate) if first else list(buckets)
    new = relayout(new, capacities, copies, channels)
    for b, w in rest.items():  # (the new arrays are this call's own: written in place)
        new[b] = write_slots([new[b]], {0: w}, donate=True)[0]
    return new


def prepare_overflow(buckets: Sequence, capacity_of) -> None:
    """Compiles, in the background, the programs an event that overflows one of these buckets runs
    for it (single-device banks only): bucket b made anew at ``capacity_of(b)`` (the capacity the
    layout rule gives it when it overflows) and its writes there. With the layout rule keeping the
    buckets that fit, those are the only new shapes of such an event."""
    global _pool
    live = [b for b in buckets if b.shape[0] > 0]
    if not live or not _single_device(live):
        return
    with _ahead_lock:
        if _pool is None:
            _pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="rebucket-compile")
        for i, old in enumerate(buckets):
            cap = int(capacity_of(i))
            if old.shape[0] == 0 or cap <= old.shape[0]:
                continue
            spec = _spec(old.shape, old)
            key = ("relayout", tuple(old.shape), str(old.dtype), _placement(old), cap, None)
            if key not in _ahead:
                _ahead[key] = _pool.submit(lambda spec=spec, cap=cap: _relayout_jit.lower(
                    (spec,), (cap,), (None,), (None,)).compile())
        while len(_ahead) > 2 * _KEEP:
            _ahead.pop(next(iter(_ahead)))
    for i, old in enumerate(buckets):
        cap = int(capacity_of(i))
        if old.shape[0] > 0 and cap > old.shape[0]:
            prepare([_spec((cap,) + tuple(old.shape[1:]), old)],
                    donate=True, kinds=("write",))
