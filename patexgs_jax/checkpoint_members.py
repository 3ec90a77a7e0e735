"""How :mod:`patexgs_jax.checkpoint` lays array members into its ZIP archive and reads them back:
``.npy`` members written without a copy of their data, and read as views of the memory-mapped file
(stored members: the pages are the page cache's own, with each member's CRC-32 checked), so that a
load copies each array once, into its JAX buffer.
"""

from __future__ import annotations

import io

import numpy as np

__all__ = ["CheckpointError", "CorruptCheckpointError", "npy_view", "repeated_block", "storable",
           "write_chunked", "write_npy"]


class CheckpointError(Exception):
    """A checkpoint cannot be written or read."""


class CorruptCheckpointError(CheckpointError, ValueError):
    """A checkpoint file is truncated, corrupt or not a checkpoint."""


def write_npy(f, arr: np.ndarray) -> None:
    """``np.lib.format.write_array`` without its ``tobytes()`` copy of a numeric array's data."""
    arr = np.asarray(arr)
    if arr.dtype.kind not in "biuf" or not arr.flags.c_contiguous or arr.size == 0:
        np.lib.format.write_array(f, np.asarray(arr, order="C"), allow_pickle=False)
        return
    header = np.lib.format.header_data_from_array_1_0(arr)
    try:
        np.lib.format.write_array_header_1_0(f, header)
    except ValueError:  # a header of over 64 KiB (never for this package's shapes)
        np.lib.format.write_array_header_2_0(f, header)
    write_chunked(f, arr.data)


#: Bytes handed to an archive member at a time (:mod:`patexgs_jax.checkpoint_io` CRCs one chunk while
#: the one before is written).
CHUNK = 16 << 20


def write_chunked(f, data) -> None:
    """``f.write(data)`` (a contiguous buffer) in chunks of :data:`CHUNK` bytes."""
    mv = memoryview(data)
    mv = mv if mv.format == "B" and mv.ndim == 1 else mv.cast("B")
    for i in range(0, max(1, len(mv)), CHUNK):
        f.write(mv[i:i + CHUNK])


def npy_view(data) -> np.ndarray:
    """The array of a ``.npy`` member as a read-only view of ``data`` (bytes, or a memoryview of the
    mapped file: read_array would copy it in chunks, 1.3 s of a 3 s load at 300 MB); only the header
    is copied to be parsed. Object arrays are refused as read_array refuses them."""
    mv = memoryview(data)
    head = bytes(mv[:12])
    if len(head) < 10 or head[:6] != b"\x93NUMPY":
        raise CorruptCheckpointError("an array member is not in .npy format")
    total = (10 + int.from_bytes(head[8:10], "little") if head[6] == 1
             else 12 + int.from_bytes(head[8:12], "little"))
    fp = io.BytesIO(bytes(mv[:total]))
    version = np.lib.format.read_magic(fp)
    header = (np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0)
    shape, fortran, dtype = header(fp)
    if dtype.hasobject:
        raise CorruptCheckpointError("an array member holds Python objects")
    count = int(np.prod(shape, dtype=np.int64))
    arr = np.frombuffer(mv, dtype=dtype, count=count, offset=fp.tell())
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def storable(arr: np.ndarray) -> tuple[np.ndarray, str]:
    """(array numpy can save without pickles, dtype name to restore)."""
    name = str(arr.dtype)
    if arr.dtype.kind in "biufc" and arr.dtype.isbuiltin:
        return arr, name
    if arr.dtype.kind == "O":
        raise TypeError("object arrays cannot be checkpointed.")
    if arr.dtype.kind in "SU":
        return arr, name
    # Extension dtypes (bfloat16, float8, ...): raw bits.
    return arr.view(np.dtype(f"u{arr.dtype.itemsize}")), name


_PROBE = 64


def repeated_block(arr: np.ndarray) -> np.ndarray | None:
    """``arr``'s one value (shape (1, ..., 1)) where it is bitwise one value, else None. The first
    elements are compared first, so that an array that varies (most parameters and moments) costs
    one short comparison."""
    if (arr.ndim == 0 or arr.size < 2 or arr.dtype.kind not in "biuf" or arr.dtype.itemsize not in (1, 2, 4, 8)
            or not arr.flags.c_contiguous):
        return None
    bits = arr.view(np.dtype(f"u{arr.dtype.itemsize}")).reshape(-1)  # (-0.0 is not 0.0, a NaN is its own payload)
    step = 1 << 24  # compared in chunks of 16M elements
    chunks = [(0, _PROBE)] + [(i, i + step) for i in range(_PROBE, bits.size, step)]
    if all(np.all(bits[i:j] == bits[0]) for i, j in chunks):
        return np.ascontiguousarray(arr.reshape(-1)[:1].reshape((1,) * arr.ndim))
    return None
