"""Arrays stored without their all-zero rows, for :mod:`patexgs_jax.checkpoint` (format version 3).

A texture bucket's free slots (the headroom a layout keeps for growth) and a scene's unused
capacity rows are zeros in the parameters and in every Adam moment; a checkpoint stores such an
array as its rows that are not bitwise zero (the member ``i``) and a bit mask of them (the member
``rows``, ``np.packbits`` of the (R,) mask), and reading puts them back into zeros. Only arrays of
at least :data:`MIN_BYTES` with at least :data:`MIN_ZERO_SHARE` of their rows zero are stored so
(only the rows whose first element is zero are read whole: an array without zero rows costs one
strided look).
"""

from __future__ import annotations

import numpy as np

from .checkpoint_members import write_chunked

__all__ = ["MIN_BYTES", "MIN_ZERO_SHARE", "aligned_zeros", "fill_rows", "write_rows", "zero_rows"]

#: Smallest array (bytes) whose zero rows are looked for.
MIN_BYTES = 1 << 20
#: Share of zero rows from which an array is stored without them.
MIN_ZERO_SHARE = 0.125
_CHUNK = 1 << 24  # bytes compared at a time (a bounded temporary)


def _row_bits(arr: np.ndarray) -> np.ndarray:
    return arr.view(np.dtype(f"u{arr.dtype.itemsize}")).reshape(arr.shape[0], -1)


def zero_rows(arr: np.ndarray) -> np.ndarray | None:
    """(R,) bool mask of the rows of ``arr`` (R, ...) that are not bitwise zero where enough of them
    are (see the module docstring), else None."""
    if (arr.ndim < 1 or arr.nbytes < MIN_BYTES or arr.dtype.kind not in "biuf"
            or arr.dtype.itemsize not in (1, 2, 4, 8) or not arr.flags.c_contiguous or arr.shape[0] < 2):
        return None
    bits = _row_bits(arr)
    R = bits.shape[0]
    # Candidates: the rows whose first element is zero (one strided look); only they are read whole.
    cand = np.flatnonzero(bits[:, 0] == 0)
    if cand.size < MIN_ZERO_SHARE * R:
        return None
    step = max(1, _CHUNK // max(1, bits.shape[1] * bits.itemsize))
    zero = np.zeros(R, bool)
    for i in range(0, cand.size, step):
        rows = cand[i:i + step]
        zero[rows] = bits[rows].max(axis=1) == 0  # (the unsigned bits' max: zero iff all are)
    return ~zero if zero.mean() >= MIN_ZERO_SHARE else None


def write_rows(f, arr: np.ndarray, keep: np.ndarray) -> None:
    """Writes ``arr[keep]`` to ``f`` in ``.npy`` format: run by run of kept rows where the runs are
    long (no copy of them), else gathered in chunks."""
    import numpy.lib.format as fmt

    header = {"descr": fmt.dtype_to_descr(arr.dtype), "fortran_order": False,
              "shape": (int(keep.sum()),) + tuple(arr.shape[1:])}
    fmt.write_array_header_1_0(f, header)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], keep.view(np.int8), [0]])))
    flat = arr.reshape(arr.shape[0], -1)
    if int(keep.sum()) * flat.shape[1] * arr.itemsize >= (1 << 16) * (edges.size // 2):  # runs of 64 KiB on average
        for a, b in zip(edges[::2], edges[1::2]):
            write_chunked(f, flat[a:b].data)
        return
    rows = np.flatnonzero(keep)
    step = max(1, _CHUNK // max(1, flat.shape[1] * arr.itemsize))
    for i in range(0, rows.size, step):
        f.write(flat[rows[i:i + step]].data.cast("B"))


def aligned_zeros(shape: tuple, dtype) -> np.ndarray:
    """``np.zeros(shape, dtype)`` at a 64-byte aligned address: the CPU client's ``jax.device_put``
    then aliases the array instead of copying it into fresh memory (``np.zeros``' large arrays sit
    16 bytes past a page start); its untouched pages stay the kernel's zero pages until written."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    buf = np.zeros(n + 64, np.uint8)
    at = -buf.ctypes.data % 64
    return buf[at:at + n].view(dtype).reshape(shape)


def fill_rows(rows: np.ndarray, mask_bits: np.ndarray, shape: tuple) -> np.ndarray:
    """The array of ``shape`` whose rows flagged in ``mask_bits`` (``np.packbits`` of the mask) are
    ``rows``, in order, and whose other rows are zeros (run by run of flagged rows where the runs are
    long, as :func:`write_rows` writes them). Raises ValueError if they do not fit."""
    keep = np.unpackbits(np.asarray(mask_bits, np.uint8), count=shape[0]).astype(bool)
    if rows.shape != (int(keep.sum()),) + tuple(shape[1:]):
        raise ValueError(f"{rows.shape[0]} stored rows of shape {rows.shape[1:]} do not fill the "
                         f"{int(keep.sum())} flagged rows of an array of shape {tuple(shape)}")
    out = aligned_zeros(shape, rows.dtype)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], keep.view(np.int8), [0]])))
    flat, src = out.reshape(shape[0], -1), rows.reshape(rows.shape[0], -1)
    if src.size * rows.itemsize < (1 << 16) * (edges.size // 2):  # short runs: one masked assignment
        out[keep] = rows
        return out
    at = 0  # long runs (a bucket's slots filled from the first): slice by slice, no index array
    for a, b in zip(edges[::2], edges[1::2]):
        flat[a:b] = src[at:at + b - a]
        at += b - a
    return out
