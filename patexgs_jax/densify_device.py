"""Densification's row writes on the device: the rows a densification changes, written in place.

:func:`patexgs_jax.densify.densify_and_prune` decides on the host from small arrays (active flags,
log scales, opacity logits, the statistics); when the capacity is kept, only the rows that change
(clones, split children, pruned rows: a few percent of them) are written here, on the device, into
the parameter Scene and each Adam moment Scene, instead of a copy of every leaf through the host.

Each tree is one jitted program: row ``idx[j]`` of every per-Gaussian leaf becomes row ``src[j]``
of that leaf (its fill value where ``src[j] < 0``), or ``over[leaf][0][j]`` where
``over[leaf][1][j]`` (the split children's means and log scales, computed on the host). ``idx`` is
padded to a power of 8 (at least 64, at most the capacity) with the capacity, which writes
nothing, so that a run compiles the program a few times, not once an event. With ``donate`` the old
leaves are donated and written in place (one copy of the scene in memory); the caller must not read
them afterwards. Textured rows' texels are zeroed in their bucket slots the same way.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .scene import Scene
from .textures.rebucket import pad_pow8

_PARAM_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh", "active")
_BANKS = ("rgb", "alpha")
_BANK_INDEX_FIELDS = ("bucket", "slot", "size")


def row_leaves(tree: Scene) -> dict:
    """The per-Gaussian (C, ...) leaves of a parameter or moment Scene by name (bank index leaves as
    ``"rgb.bucket"`` etc.)."""
    out = {f: getattr(tree, f) for f in _PARAM_FIELDS}
    if tree.filter3d is not None:
        out["filter3d"] = tree.filter3d
    for name in _BANKS:
        bank = getattr(tree, name)
        if bank is not None:
            out.update({f"{name}.{f}": getattr(bank, f) for f in _BANK_INDEX_FIELDS})
    return out


def _write(leaves: dict, idx, src, over: dict, fills: tuple) -> dict:
    fill = dict(fills)
    miss = src < 0
    out = {}
    for k, a in leaves.items():
        col = (-1,) + (1,) * (a.ndim - 1)
        v = jnp.take(a, src, axis=0, mode="clip")
        v = jnp.where(miss.reshape(col), jnp.asarray(fill[k], a.dtype), v)
        if k in over:
            vals, use = over[k]
            v = jnp.where(use.reshape(col), vals.astype(a.dtype), v)
        out[k] = a.at[idx].set(v, mode="drop")
    return out


_write_donated = jax.jit(_write, static_argnames="fills", donate_argnums=0)
_write_kept = jax.jit(_write, static_argnames="fills")


def _zero_slots(bucket, slots):
    return bucket.at[slots].set(0, mode="drop")


_zero_donated = jax.jit(_zero_slots, donate_argnums=0)
_zero_kept = jax.jit(_zero_slots)


@jax.jit
def _take_rows(arrays, rows):
    return tuple(jnp.take(a, rows, axis=0, mode="clip") for a in arrays)


def take_rows(arrays, rows: np.ndarray) -> list[np.ndarray]:
    """Host copies of ``a[rows]`` for each device array (a padded gather: few compiled shapes)."""
    C = int(np.shape(arrays[0])[0])
    got = _take_rows(tuple(arrays), jax.device_put(pad_pow8(rows.astype(np.int32), 0, limit=C)))
    return [np.asarray(g)[: rows.size] for g in got]


def texel_slots(scene: Scene, rows: np.ndarray) -> dict:
    """{bank: {bucket: slots}} of the texels the parameter banks assign to ``rows`` (bool, C)."""
    out = {}
    for name in _BANKS:
        bank = getattr(scene, name)
        if bank is None or not np.any(rows):
            continue
        bucket = np.asarray(bank.bucket).astype(np.int64)
        slot = np.asarray(bank.slot).astype(np.int64)
        per = {b: slot[rows & (bucket == b)] for b in range(len(bank.buckets))}
        out[name] = {b: s for b, s in per.items() if s.size}
    return out


def _static(fill):
    """A fill value as a hashable constant of the compiled program."""
    return float(fill) if np.ndim(fill) == 0 else tuple(float(x) for x in np.ravel(fill))


def _key(a):
    try:
        return ("buffer", a.unsafe_buffer_pointer())
    except Exception:  # not a single-device jax array: its identity
        return ("object", id(a))


def can_donate(trees) -> bool:
    """Whether every per-Gaussian leaf and bucket of these Scenes is a live jax array of its own
    (donating one buffer twice in a call, or across two calls, would fail)."""
    arrays = []
    for t in trees:
        arrays += list(row_leaves(t).values())
        arrays += [b for n in _BANKS if getattr(t, n) is not None for b in getattr(t, n).buckets]
    if not all(isinstance(a, jax.Array) and not a.is_deleted() for a in arrays):
        return False
    return len({_key(a) for a in arrays}) == len(arrays)


def write_rows(tree: Scene, idx: np.ndarray, src: np.ndarray, fill_of: Callable[[str], Any], over: dict,
               texels: dict, donate: bool) -> Scene:
    """``tree`` with rows ``idx`` (sorted, unique) rewritten from rows ``src`` (the leaf's
    ``fill_of(field)`` where -1, or ``over`` where it says), and the bucket slots ``texels``
    (:func:`texel_slots`) zeroed."""
    leaves = row_leaves(tree)
    C = int(np.shape(leaves["active"])[0])
    args = {key: (jax.device_put(pad_pow8(vals, 0, limit=C)), jax.device_put(pad_pow8(use, False, limit=C)))
            for key, (vals, use) in over.items()}
    new = (_write_donated if donate else _write_kept)(
        leaves, jax.device_put(pad_pow8(idx.astype(np.int32), C, limit=C)),
        jax.device_put(pad_pow8(src.astype(np.int32), 0, limit=C)), args,
        tuple(sorted((key, _static(fill_of(key.split(".")[-1]))) for key in leaves)))
    kw = {f: new[f] for f in _PARAM_FIELDS}
    if tree.filter3d is not None:
        kw["filter3d"] = new["filter3d"]
    for name in _BANKS:
        bank = getattr(tree, name)
        if bank is None:
            continue
        buckets = list(bank.buckets)
        for b, slots in texels.get(name, {}).items():
            cap = int(np.shape(buckets[b])[0])
            buckets[b] = (_zero_donated if donate else _zero_kept)(
                buckets[b], jax.device_put(pad_pow8(slots.astype(np.int32), cap, limit=cap)))
        kw[name] = dataclasses.replace(bank, buckets=tuple(buckets),
                                       **{f: new[f"{name}.{f}"] for f in _BANK_INDEX_FIELDS})
    return tree.replace(**kw)


def apply_in_place(scene: Scene, opt_state, src, mom_src, prune, children, clone_slots, child_means,
                   child_ls, fill_of: Callable[[str, bool], Any], donate: bool):
    """A densification that keeps the capacity, applied: the rows that move or are new (``src`` or
    ``mom_src`` not the identity), split or pruned are written (parameters from ``src``, each moment
    tree from ``mom_src``, -1 and pruned rows: ``fill_of(field, moments)``; split ``children``'s
    means and log scales and every new row's active flag from the host); every other row is untouched.
    Returns (scene, opt_state)."""
    from .optim import map_moments

    C = scene.capacity
    ar = np.arange(C)
    idx = np.flatnonzero((src != ar) | (mom_src != ar) | prune)
    if idx.size == 0:
        return scene, opt_state
    pr = prune[idx]
    is_child = np.zeros(C, bool)
    is_child[children.ravel()] = True
    is_new = is_child.copy()
    is_new[clone_slots] = True
    # (the same three overrides every time: one program for the parameters, split or not)
    over = {"active": (np.ones(idx.size, scene.active.dtype), is_new[idx] & ~pr)}
    pos = np.searchsorted(idx, children.ravel())
    use = is_child[idx] & ~pr
    for field, vals in (("means", child_means), ("log_scales", child_ls)):
        leaf = getattr(scene, field)
        v = np.zeros((idx.size,) + leaf.shape[1:], leaf.dtype)
        if vals is not None:
            v[pos] = vals.reshape((-1,) + leaf.shape[1:])
        over[field] = (v, use)
    texels = texel_slots(scene, prune)  # read before the scene's buffers are donated
    trees = [scene] + ([] if opt_state is None else _moment_trees(opt_state))
    donate = donate and can_donate(trees)
    new_scene = write_rows(scene, idx, np.where(pr, -1, src[idx]), lambda f: fill_of(f, False), over, texels,
                           donate)
    m_src = np.where(pr, -1, mom_src[idx])
    new_state = None if opt_state is None else map_moments(opt_state, lambda m: write_rows(
        m, idx, m_src, lambda f: fill_of(f, True), {}, texels, donate))
    return new_scene, new_state


def _moment_trees(opt_state) -> list:
    from .optim import map_moments

    trees = []

    def keep(m):
        trees.append(m)
        return m

    map_moments(opt_state, keep)
    return trees
