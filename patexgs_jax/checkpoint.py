"""Atomic, self-describing checkpoints of arbitrary pytrees (scene, optimiser state, RNG, schedule).

File format (version 3; versions 1 and 2, without repeated values or zero rows, are read too)
  A ZIP archive (stored, no compression; every member CRC-checked on read) with
  * ``spec.json``: ``{"format": "patexgs-checkpoint", "version": 2, "metadata": {...},
    "tree": <node>}``, where a node is one of
      ``{"t": "none"}``; ``{"t": "py", "v": value}`` (bool, int, float, str);
      ``{"t": "array", "i": k, "kind": "jax"|"numpy"|"scalar", "dtype": name}`` (array member k),
      with ``"shape": [...]`` when member k is the array's one repeated value (see below);
      ``{"t": "key", "i": k, "impl": name}`` (a typed JAX PRNG key; member k holds its key data);
      ``{"t": "list"|"tuple", "v": [nodes]}``;
      ``{"t": "dict", "k": [keys], "v": [nodes]}`` (keys are str or int, JSON-typed);
      ``{"t": "namedtuple", "cls": "module:QualName", "v": [nodes]}``;
      ``{"t": "dataclass", "cls": "module:QualName", "f": {field: node}}``;
      ``{"t": "np_generator", "bit_generator": name, "state": node}`` (a numpy Generator).
  * ``arrays/<k>.npy``: the array leaves in numpy's ``.npy`` format (no pickles). Dtypes numpy
    cannot name (bfloat16 etc.) are stored as unsigned integers of the same width and viewed back.
    An array that is bitwise one value is stored as that value (shape (1, ..., 1)) and broadcast
    back to its ``"shape"`` on reading (the zero ages of every parameter but the texels, whose ages
    :mod:`patexgs_jax.optim` stores one per texture; the frozen leaves' zero moments). An array
    with many all-zero rows (texture buckets' free slots) is stored without them, ``"rows": j``
    naming the member that flags the stored ones (:mod:`patexgs_jax.checkpoint_rows`).

  So a checkpoint rebuilds itself without a template (Scenes of any capacity, texture banks with
  any bucket shapes, optax states). Classes are re-imported by name only from the modules in
  :data:`ALLOWED_MODULE_PREFIXES` (extend with :func:`allow_module`), never arbitrary code.

Atomicity
  :func:`save_checkpoint` writes ``.<name>.tmp-<random>`` in the target directory, fsyncs it,
  ``os.replace``-s it onto the final name and fsyncs the directory; an interrupted save leaves the
  previous checkpoint untouched and at most a hidden temp file, which :func:`latest_checkpoint`
  never considers. With ``keep=k`` older ``*.ckpt`` files of the directory are deleted, newest k
  kept, only after the new one is complete. :class:`patexgs_jax.checkpoint_writer.CheckpointWriter`
  writes the same file in a background thread (:func:`prepare_checkpoint` on the caller's thread,
  :func:`write_prepared` on its own).

Naming and order
  :func:`checkpoint_path` gives ``<dir>/ckpt_<step:09d>.ckpt``; "newest" is the largest number in
  the file name (files without one come first), ties broken by modification time.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import importlib
import json
import os
import re
import shutil
import tempfile
import warnings
import zipfile
from pathlib import Path
from typing import Any, cast

import jax
import jax.numpy as jnp
import numpy as np

from . import checkpoint_io, checkpoint_members, checkpoint_rows
from .checkpoint_io import fsync_dir as _fsync_dir
from .checkpoint_io import make_public
from .checkpoint_members import CheckpointError, CorruptCheckpointError
from .checkpoint_members import repeated_block as _repeated_block
from .checkpoint_members import storable as _storable

FORMAT = "patexgs-checkpoint"
VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
SUFFIX = ".ckpt"
ALLOWED_MODULE_PREFIXES: list[str] = ["patexgs_jax", "optax", "experiments"]


def allow_module(prefix: str) -> None:
    """Lets :func:`load_checkpoint` rebuild NamedTuples / dataclasses defined under ``prefix``."""
    if prefix not in ALLOWED_MODULE_PREFIXES:
        ALLOWED_MODULE_PREFIXES.append(prefix)


def checkpoint_path(directory, step: int) -> Path:
    """The conventional checkpoint file name for a training step."""
    return Path(directory) / f"ckpt_{int(step):09d}{SUFFIX}"


# ------------------------------------------------------------------------------------------------
# Encoding.

def _class_name(cls) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _is_namedtuple(x) -> bool:
    return isinstance(x, tuple) and hasattr(type(x), "_fields")


def _is_key_array(x) -> bool:
    return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


class _Encoder:
    """Walks a tree into its spec (:meth:`encode`), taking each array leaf to the host; the costly
    part, finding repeated values and zero rows, waits for :meth:`finish`, which numbers the members
    in leaf order (what a background writer runs off the training thread)."""

    def __init__(self, copy: bool = False, pool: dict | None = None):
        self.copy = copy  # host copies the caller may not change: the source may be donated or mutated
        self.pool = pool if pool is not None else {}  # (shape, dtype) -> free host buffers to copy into
        self.copies: list[np.ndarray] = []  # the host copies made (a later save's pool)
        self.pending: list[tuple[dict, np.ndarray, bool]] = []  # (node to fill, host array, analyse it)
        self.arrays: list[np.ndarray] = []
        self.kept_rows: dict[int, np.ndarray] = {}  # member -> (R,) mask of the rows it stores

    def _add(self, arr: np.ndarray) -> int:
        self.arrays.append(arr)
        return len(self.arrays) - 1

    def _host(self, x) -> np.ndarray:
        arr = np.asarray(x)
        # A jax array in an accelerator's memory arrives as a fresh host buffer; on the CPU (or in a
        # host memory space) it can be a view of the buffer itself, which a donating step reuses.
        transferred = (isinstance(x, jax.Array) and all(d.platform != "cpu" for d in x.devices())
                       and getattr(x.sharding, "memory_kind", None) in (None, "device"))
        if self.copy and not transferred:
            # Into a buffer of an earlier save where one fits: fresh pages cost more to fault in than
            # the copy itself (benchmarks.md).
            free = self.pool.get((arr.shape, arr.dtype.str))
            if free:
                buf = free.pop()
                np.copyto(buf, arr)
                arr = buf
            else:
                arr = np.array(arr, copy=True)
            self.copies.append(arr)
        return arr

    def finish(self) -> None:
        for node, stored, analyse in self.pending:
            if not analyse:  # a key's data
                node["i"] = self._add(stored)
                continue
            kind, dtype = node.pop("kind"), node.pop("dtype")
            block = _repeated_block(stored)
            keep = None if block is not None else checkpoint_rows.zero_rows(stored)
            if keep is not None:
                i = self._add(stored)
                self.kept_rows[i] = keep
                node.update(i=i, kind=kind, dtype=dtype, shape=list(stored.shape), rows=self._add(np.packbits(keep)))
            elif block is None:
                node.update(i=self._add(stored), kind=kind, dtype=dtype)
            else:
                node.update(i=self._add(block), kind=kind, dtype=dtype, shape=list(stored.shape))
        self.pending = []

    def encode(self, x, path: str = "tree"):
        if x is None:
            return {"t": "none"}
        if isinstance(x, (bool, int, float, str)) and not isinstance(x, np.generic):
            return {"t": "py", "v": x}
        if _is_key_array(x):
            key = cast(jax.Array, x)
            node = {"t": "key", "i": -1, "impl": str(jax.random.key_impl(key))}
            self.pending.append((node, self._host(jax.random.key_data(key)), False))
            return node
        if isinstance(x, (jax.Array, np.ndarray, np.generic)):
            kind = "jax" if isinstance(x, jax.Array) else ("scalar" if isinstance(x, np.generic) else "numpy")
            try:
                stored, dtype = _storable(self._host(x))
            except TypeError as e:
                raise TypeError(f"{path}: {e}") from None
            node = {"t": "array", "kind": kind, "dtype": dtype}  # (the member fields follow "t" in finish)
            self.pending.append((node, stored, True))
            return node
        if isinstance(x, np.random.Generator):
            bg = x.bit_generator
            return {"t": "np_generator", "bit_generator": type(bg).__name__,
                    "state": self.encode(bg.state, path + ".state")}
        if _is_namedtuple(x):
            return {"t": "namedtuple", "cls": _class_name(type(x)),
                    "v": [self.encode(v, f"{path}.{f}") for f, v in zip(type(x)._fields, x)]}
        if isinstance(x, (list, tuple)):
            return {"t": "list" if isinstance(x, list) else "tuple",
                    "v": [self.encode(v, f"{path}[{i}]") for i, v in enumerate(x)]}
        if isinstance(x, dict):
            keys = list(x.keys())
            for k in keys:
                if not isinstance(k, (str, int)) or isinstance(k, bool):
                    raise TypeError(f"{path}: dict keys must be str or int, got {k!r}.")
            return {"t": "dict", "k": keys, "v": [self.encode(x[k], f"{path}[{k!r}]") for k in keys]}
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            return {"t": "dataclass", "cls": _class_name(type(x)),
                    "f": {f.name: self.encode(getattr(x, f.name), f"{path}.{f.name}")
                          for f in dataclasses.fields(x)}}
        raise TypeError(f"{path}: cannot checkpoint a {type(x).__module__}.{type(x).__qualname__}; "
                        "use arrays, Python scalars, lists/tuples/dicts, NamedTuples or dataclasses.")


def _resolve_class(name: str) -> Any:
    module, _, qual = name.partition(":")
    if not any(module == p or module.startswith(p + ".") for p in ALLOWED_MODULE_PREFIXES):
        raise CheckpointError(f"class {name} is not from an allowed module "
                              f"({ALLOWED_MODULE_PREFIXES}); see checkpoint.allow_module.")
    obj = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part)
    return obj


class _Decoder:
    def __init__(self, arrays: dict, pool: concurrent.futures.Executor | None = None):
        self.arrays = arrays
        self.pool = pool
        self.filled: dict = {}  # member -> Future of its array with the zero rows put back

    def prefill(self, node) -> None:
        """Starts, on the pool, the fill of every array stored without its zero rows under ``node``."""
        if isinstance(node, list):
            for v in node:
                self.prefill(v)
        elif isinstance(node, dict):
            if node.get("t") == "array" and "rows" in node and self.pool is not None:
                i, r = node.get("i"), node.get("rows")
                if i in self.arrays and r in self.arrays:
                    self.filled[i] = self.pool.submit(checkpoint_rows.fill_rows, self.arrays[i], self.arrays[r],
                                                      tuple(node["shape"]))
            for k in ("v", "f", "state"):
                if k in node:
                    self.prefill(list(node[k].values()) if isinstance(node[k], dict) else node[k])

    def _array(self, i):
        if i not in self.arrays:
            raise CorruptCheckpointError(f"array member {i} is missing")
        return self.arrays[i]

    def decode(self, node):
        t = node["t"]
        if t == "none":
            return None
        if t == "py":
            return node["v"]
        if t == "array":
            arr = self._array(node["i"])
            if "rows" in node:  # stored without its zero rows
                try:
                    fill = self.filled.get(node["i"])
                    arr = (fill.result() if fill is not None
                           else checkpoint_rows.fill_rows(arr, self._array(node["rows"]), tuple(node["shape"])))
                except ValueError as e:
                    raise CorruptCheckpointError(f"array member {node['i']}: {e}") from None
            elif "shape" in node:  # a repeated block (see the module docstring)
                shape = tuple(node["shape"])
                if arr.ndim != len(shape) or any(b not in (1, s) for b, s in zip(arr.shape, shape)):
                    raise CorruptCheckpointError(f"array member {node['i']} of shape {arr.shape} is not a block "
                                                 f"of shape {shape}")
                if node["kind"] == "jax":
                    dtype = np.dtype(jnp.dtype(node["dtype"]))
                    if jax.default_backend() == "cpu" and not arr.view(np.uint8).any():
                        # Zeros: untouched pages, which the CPU client aliases (the device broadcast
                        # compiled a program a shape: 1.5 s of a 1M load).
                        return jax.device_put(checkpoint_rows.aligned_zeros(shape, dtype))
                    # Broadcast on the device: no host copy of the whole array.
                    return jnp.broadcast_to(jax.device_put(arr if arr.dtype == dtype else arr.view(dtype)), shape)
                arr = np.array(np.broadcast_to(arr, shape))
            dtype = np.dtype(jnp.dtype(node["dtype"]))
            if arr.dtype != dtype:
                arr = arr.view(dtype)
            if node["kind"] == "jax":  # (jnp.asarray would compile a copy per new shape)
                # A view of the mapped file is copied, never aliased: the array may be donated and
                # written in place, and the mapping is read-only.
                return jax.device_put(arr, may_alias=None if arr.flags.writeable else False)
            if node["kind"] == "scalar":
                return arr[()]
            return arr.copy() if not arr.flags.writeable else arr  # (a view of the file's bytes)
        if t == "key":
            return jax.random.wrap_key_data(jax.device_put(self._array(node["i"])), impl=node["impl"])
        if t == "list":
            return [self.decode(v) for v in node["v"]]
        if t == "tuple":
            return tuple(self.decode(v) for v in node["v"])
        if t == "dict":
            return {k: self.decode(v) for k, v in zip(node["k"], node["v"])}
        if t == "namedtuple":
            return _resolve_class(node["cls"])(*[self.decode(v) for v in node["v"]])
        if t == "dataclass":
            cls = _resolve_class(node["cls"])
            values = {k: self.decode(v) for k, v in node["f"].items()}
            fields = {f.name: f for f in dataclasses.fields(cls)}
            # A field added to the class since the checkpoint was written takes its default (e.g.
            # Scene.filter3d, None in every older checkpoint); any other mismatch is an error.
            added = {k for k in set(fields) - set(values) if fields[k].init
                     and fields[k].default is not dataclasses.MISSING}
            if set(values) != set(fields) - added:
                raise CheckpointError(f"{node['cls']}: stored fields {sorted(values)} do not match the "
                                      f"class's fields {sorted(fields)}.")
            obj = cls(**{k: v for k, v in values.items() if fields[k].init})
            for k, v in values.items():
                if not fields[k].init:
                    object.__setattr__(obj, k, v)
            return obj
        if t == "np_generator":
            bg = getattr(np.random, node["bit_generator"])()
            bg.state = self.decode(node["state"])
            return np.random.Generator(bg)
        raise CorruptCheckpointError(f"unknown node type {t!r}")


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, (np.ndarray, jax.Array)):
        return np.asarray(o).tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"metadata value of type {type(o).__name__} is not JSON-serialisable")


# ------------------------------------------------------------------------------------------------
def _sort_key(p: Path):
    nums = re.findall(r"\d+", p.stem)
    try:
        mtime = p.stat().st_mtime_ns
    except OSError:
        mtime = 0
    return (int(nums[-1]) if nums else -1, mtime, p.name)


def list_checkpoints(directory) -> list[Path]:
    """``*.ckpt`` files of a directory (temp files excluded), oldest first."""
    d = Path(directory)
    if not d.is_dir():
        return []
    files = [p for p in d.iterdir() if p.name.endswith(SUFFIX) and not p.name.startswith(".")
             and p.is_file()]
    return sorted(files, key=_sort_key)


def save_checkpoint(path, tree, metadata: dict | None = None, *, keep: int | None = None) -> Path:
    """Writes ``tree`` and JSON ``metadata`` to ``path`` atomically (see the module docstring).

    Args:
      path: destination file (conventionally :func:`checkpoint_path`; parents are created).
      tree: any pytree of arrays / Python scalars / containers / NamedTuples / dataclasses.
      metadata: JSON-serialisable dict (numpy scalars and arrays are converted).
      keep: if given, afterwards delete older ``*.ckpt`` files in the directory, keeping the newest
        ``keep`` (the new one always survives).
    Returns:
      The path written.
    """
    return write_prepared(prepare_checkpoint(path, tree, metadata), keep)


@dataclasses.dataclass
class PreparedCheckpoint:
    """A checkpoint taken to the host (:func:`prepare_checkpoint`), not yet analysed or written."""
    path: Path
    encoder: _Encoder
    spec: dict


def prepare_checkpoint(path, tree, metadata: dict | None = None, *, copy: bool = False,
                       pool: dict | None = None) -> PreparedCheckpoint:
    """The synchronous half of :func:`save_checkpoint`: ``tree``'s arrays on the host (with ``copy``,
    host copies nothing else shares, so that the source may be donated or changed at once; into the
    buffers of ``pool``, ``{(shape, dtype.str): [arrays]}``, where they fit) and its spec. Raises at
    once on a leaf or metadata that cannot be checkpointed."""
    path = Path(path)
    try:  # (a JSON round trip: the same text later, whatever the caller does to its dict)
        meta = json.loads(json.dumps(dict(metadata or {}), default=_json_default))
    except (TypeError, ValueError) as e:
        raise TypeError(f"save_checkpoint({path}): metadata is not JSON-serialisable: {e}") from None
    enc = _Encoder(copy=copy, pool=pool)
    tree_spec = enc.encode(tree)
    return PreparedCheckpoint(path, enc, {"format": FORMAT, "version": VERSION, "metadata": meta, "tree": tree_spec})


def write_prepared(prepared: PreparedCheckpoint, keep: int | None = None) -> Path:
    """The rest of :func:`save_checkpoint`: repeated values and zero rows found, the file written,
    fsynced and renamed into place, then ``keep`` applied."""
    if keep is not None and keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}.")
    path, enc = prepared.path, prepared.encoder
    enc.finish()
    spec_bytes = json.dumps(prepared.spec).encode("utf-8")

    directory = path.parent
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=directory)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as f:
            make_public(f.fileno())
            out = checkpoint_io.BackgroundFile(f.fileno())  # (the CRCs here, the page-cache copies there)
            try:
                with zipfile.ZipFile(cast(Any, out), "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
                    zf.writestr("spec.json", spec_bytes)
                    for i, arr in enumerate(enc.arrays):
                        with zf.open(f"arrays/{i}.npy", "w", force_zip64=arr.nbytes > (1 << 30)) as m:
                            if i in enc.kept_rows:
                                checkpoint_rows.write_rows(m, arr, enc.kept_rows[i])
                            else:
                                checkpoint_members.write_npy(m, arr)
            except BaseException:
                out.close(raise_error=False)
                raise
            out.close()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            tmp.unlink()
        except OSError:
            pass
        if isinstance(e, OSError):
            raise CheckpointError(f"could not write checkpoint {path}: {e}") from e
        raise
    _fsync_dir(directory)

    if keep is not None:
        others = [p for p in list_checkpoints(directory) if p.resolve() != path.resolve()]
        for old in others[: max(0, len(others) - (keep - 1))]:
            try:
                old.unlink()
            except OSError as e:
                warnings.warn(f"could not delete old checkpoint {old}: {e}", stacklevel=2)
    return path


def _read(path: Path, with_arrays: bool = True, pool=None):
    """(spec dict, {index: array}, CRC checks to ``verify``: see
    :func:`patexgs_jax.checkpoint_io.read_archive`); raises CorruptCheckpointError naming the file."""
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist.")
    return _named(path, lambda: checkpoint_io.read_archive(path, FORMAT, READABLE_VERSIONS, with_arrays, pool))


def _named(path: Path, fn):
    """``fn()``, any error of a damaged file raised as CorruptCheckpointError naming ``path``."""
    try:
        return fn()
    except CorruptCheckpointError as e:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: {e}") from None
    except (OSError, MemoryError) as e:
        if isinstance(e, (PermissionError, IsADirectoryError)):
            raise
        raise CorruptCheckpointError(f"checkpoint {path} is truncated or corrupt: {e}") from e
    except Exception as e:  # zipfile, json, npy parsing: anything means a damaged file
        raise CorruptCheckpointError(f"checkpoint {path} is truncated or corrupt "
                                     f"({type(e).__name__}: {e}).") from e


def _leaf_desc(x) -> str:
    if hasattr(x, "shape") and hasattr(x, "dtype"):
        return f"an array of shape {tuple(x.shape)} and dtype {x.dtype}"
    return f"{type(x).__name__} {x!r}"


def load_checkpoint(path, template=None, *, check_shapes: bool = True):
    """Reads a checkpoint written by :func:`save_checkpoint`.

    Args:
      path: the file.
      template: optional pytree; the loaded tree must have its structure (same containers, classes
        and static fields), and with ``check_shapes`` its array leaves' shapes and dtypes; leaves are
        returned as the template's leaf types (jax or numpy arrays). Without a template the file
        rebuilds itself (use this after capacity growth).
    Returns:
      (tree, metadata dict).
    """
    path = Path(path)
    # The members' CRCs and zero-row fills on two threads beside the decoding (numpy and zlib release
    # the interpreter lock); nothing is returned before every CRC has matched.
    with concurrent.futures.ThreadPoolExecutor(2, thread_name_prefix="checkpoint-read") as pool:
        spec, arrays, checks = _read(path, pool=pool)
        try:
            decoder = _Decoder(arrays, pool)
            decoder.prefill(spec["tree"])
            tree = decoder.decode(spec["tree"])
        except CheckpointError as e:
            _named(path, checks.verify)  # (a damaged member: its CRC names it)
            raise type(e)(f"checkpoint {path}: {e}") from None
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            _named(path, checks.verify)
            raise CorruptCheckpointError(f"checkpoint {path} has an invalid tree description "
                                         f"({type(e).__name__}: {e}).") from e
        _named(path, checks.verify)
    metadata = spec.get("metadata", {})
    if template is None:
        return tree, metadata

    leaves_t, def_t = jax.tree_util.tree_flatten_with_path(template)
    leaves_l, def_l = jax.tree_util.tree_flatten(tree)
    if def_l != def_t:
        raise CheckpointError(f"checkpoint {path}: its tree structure does not match the template.\n"
                              f"  checkpoint: {def_l}\n  template:   {def_t}")
    out = []
    for (kp, t), v in zip(leaves_t, leaves_l):
        name = jax.tree_util.keystr(kp)
        if hasattr(t, "shape") and hasattr(t, "dtype"):
            if not (hasattr(v, "shape") and hasattr(v, "dtype")):
                raise CheckpointError(f"checkpoint {path}: leaf {name} is {_leaf_desc(v)}, "
                                      f"template has {_leaf_desc(t)}.")
            if check_shapes and (tuple(v.shape) != tuple(t.shape) or np.dtype(v.dtype) != np.dtype(t.dtype)):
                raise CheckpointError(f"checkpoint {path}: leaf {name} is {_leaf_desc(v)}, template has "
                                      f"{_leaf_desc(t)} (pass template=None to restore other shapes).")
            if isinstance(t, jax.Array):
                v = v if isinstance(v, jax.Array) else jax.device_put(np.asarray(v))
            else:
                v = np.asarray(v)
        out.append(v)
    return jax.tree_util.tree_unflatten(def_l, out), metadata


def read_metadata(path) -> dict:
    """The metadata of a checkpoint (reads only its spec; the CRCs are checked too)."""
    spec, _, _ = _read(Path(path), with_arrays=False)
    return spec.get("metadata", {})


def verify_checkpoint(path) -> None:
    """Raises CorruptCheckpointError unless ``path`` is a complete, readable checkpoint."""
    _read(Path(path), with_arrays=False)


def latest_checkpoint(directory) -> Path | None:
    """The newest complete checkpoint in ``directory`` (None if there is none).

    Corrupt or truncated files are skipped with a warning naming them; temp files are ignored.
    """
    for p in reversed(list_checkpoints(directory)):
        try:
            verify_checkpoint(p)
        except (CorruptCheckpointError, OSError) as e:
            warnings.warn(f"skipping unreadable checkpoint {p}: {e}", stacklevel=2)
            continue
        return p
    return None


def check_writable(directory, required_bytes: int = 0) -> Path:
    """Fails early, with a clear message, if checkpoints cannot be written to ``directory``.

    Creates the directory if needed, writes, fsyncs and deletes a probe file, and checks that at
    least ``required_bytes`` are free (e.g. twice the expected checkpoint size: a new checkpoint is
    written before the old one is deleted).
    """
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CheckpointError(f"cannot create checkpoint directory {d}: {e.strerror or e}") from e
    if not d.is_dir():
        raise CheckpointError(f"checkpoint path {d} exists and is not a directory.")
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=d)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(b"\0" * 4096)
                f.flush()
                os.fsync(f.fileno())
        finally:
            os.unlink(probe)
    except OSError as e:
        raise CheckpointError(f"checkpoint directory {d} is not writable: {e.strerror or e} "
                              f"(read-only file system, permissions or disk full?)") from e
    free = shutil.disk_usage(d).free
    if free < int(required_bytes):
        raise CheckpointError(f"checkpoint directory {d} has {free / 2**20:.1f} MiB free, "
                              f"{int(required_bytes) / 2**20:.1f} MiB are needed.")
    return d


def check_output_dir(directory, flag: str = "--out") -> Path:
    """:func:`check_writable` for a command line's output folder, run before any data is loaded or
    code compiled: the error names the flag, the folder, the reason and the fix."""
    try:
        return check_writable(directory)
    except CheckpointError as e:
        cause = e.__cause__
        reason = (cause.strerror or str(cause)) if isinstance(cause, OSError) else "it exists and is not a folder"
        raise CheckpointError(f"cannot write to {flag} {directory} ({reason}): pass {flag} a folder "
                              f"you can write to.") from None
