"""The checkpoint archive's bytes, written and read with the work spread over two threads
(:mod:`patexgs_jax.checkpoint`'s file format is unchanged).

Writing. ``zipfile`` computes each member's CRC-32 and writes it to its file object, one after the
other; :class:`BackgroundFile` is that file object, copying each chunk into the page cache in a
thread of its own (``os.pwrite``) while the caller's thread computes the next chunk's CRC (both
release the interpreter lock), and starting the disk's writeback of each chunk as it lands
(``sync_file_range`` where Linux has it), so that the final ``fsync`` finds little left to write.
The members are fed in chunks of :data:`~patexgs_jax.checkpoint_members.CHUNK` bytes
(:func:`~patexgs_jax.checkpoint_members.write_chunked`).

Reading. :func:`read_archive` maps the file and returns each stored member as a view of the map
without checking it; the CRCs are computed on a thread pool while the caller decodes, and
:meth:`Checks.verify` (which the caller runs before handing anything out) waits for them and raises
:class:`~patexgs_jax.checkpoint_members.CorruptCheckpointError` for the first member that fails.
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import json
import mmap
import os
import queue
import re
import threading
import zipfile
import zlib
from pathlib import Path

from . import checkpoint_members
from .checkpoint_members import CorruptCheckpointError

__all__ = ["BackgroundFile", "Checks", "fsync_dir", "make_public", "read_archive"]

_DEPTH = 4  # chunks queued for the writing thread at most (views of the caller's arrays, not copies)
_SYNC_FILE_RANGE_WRITE = 2


def _sync_file_range():
    try:
        fn = ctypes.CDLL(None, use_errno=True).sync_file_range
    except (OSError, AttributeError):  # not Linux
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint)
    return fn


_start_writeback = _sync_file_range()


def _umask() -> int:
    """The process's umask, read without changing it where the kernel says it (``/proc/self/status``,
    Linux 4.7+; elsewhere set and restored at once)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def make_public(fd: int) -> None:
    """Gives the file open as ``fd`` the mode ``open()`` would have created it with (0666 less the
    umask: 0644 under the usual 022), where :func:`tempfile.mkstemp` makes it 0600. Outputs written
    through a temporary file and a rename (checkpoints, PLY, summaries) are then as readable in a
    shared results folder as any other file."""
    os.fchmod(fd, 0o666 & ~_umask())


def fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # e.g. platforms without directory fds
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class BackgroundFile:
    """A write-only, seekable file object over the descriptor ``fd`` whose writes run in one thread
    of their own, in order (see the module docstring). ``write`` keeps a reference to its buffer
    until the write is done: the caller must not change it (the archive's members and headers never
    are). An error in the thread is raised by the next ``write``, ``flush`` or ``close``."""

    def __init__(self, fd: int):
        self.fd = fd
        self._pos = 0
        self._queue: queue.Queue = queue.Queue(maxsize=_DEPTH)
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="checkpoint-write", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                data, offset = item
                if self._error is None:
                    start, mv = offset, memoryview(data)
                    while len(mv):
                        n = os.pwrite(self.fd, mv, offset)
                        mv, offset = mv[n:], offset + n
                    if _start_writeback is not None and offset > start:
                        _start_writeback(self.fd, start, offset - start, _SYNC_FILE_RANGE_WRITE)
            except BaseException as e:  # raised on the caller's thread
                self._error = e
            finally:
                self._queue.task_done()

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def write(self, data) -> int:
        self._raise()
        if self._closed:
            raise ValueError("write to a closed BackgroundFile")
        n = memoryview(data).nbytes
        if n:
            self._queue.put((data, self._pos))
            self._pos += n
        return n

    def tell(self) -> int:
        return self._pos

    def seek(self, pos: int, whence: int = 0) -> int:
        if whence != 0:
            raise OSError("BackgroundFile seeks from the start only")
        self._pos = int(pos)
        return self._pos

    def seekable(self) -> bool:
        return True

    def flush(self) -> None:
        """Waits for every write queued so far."""
        self._queue.join()
        self._raise()

    def close(self, raise_error: bool = True) -> None:
        """Finishes the writes queued and ends the thread (the descriptor stays open: the caller's);
        ``raise_error=False`` where another error is already on its way."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join()
        if raise_error:
            self._raise()


class Checks:
    """The CRC-32 checks of a read archive's members, running on a pool (see the module docstring)."""

    def __init__(self, pool: concurrent.futures.Executor | None):
        self.pool = pool
        self.pending: list[tuple[str, concurrent.futures.Future]] = []

    def add(self, name: str, view: memoryview, crc: int) -> None:
        if self.pool is None:
            if zlib.crc32(view) != crc:
                raise CorruptCheckpointError(f"member {name} fails its CRC check")
            return
        self.pending.append((name, self.pool.submit(lambda: zlib.crc32(view) == crc)))

    def verify(self) -> None:
        """Raises CorruptCheckpointError for the first member whose CRC does not match."""
        for name, fut in self.pending:
            if not fut.result():
                raise CorruptCheckpointError(f"member {name} fails its CRC check")


def _member_view(mapped, info: zipfile.ZipInfo) -> memoryview:
    """The bytes of an uncompressed member as a view of the mapped file (not yet CRC-checked)."""
    start = info.header_offset
    local = bytes(mapped[start:start + 30])
    if len(local) < 30 or local[:4] != b"PK\x03\x04":
        raise CorruptCheckpointError(f"member {info.filename} has no local header")
    start += 30 + int.from_bytes(local[26:28], "little") + int.from_bytes(local[28:30], "little")
    if start + info.compress_size > len(mapped):
        raise CorruptCheckpointError(f"member {info.filename} is truncated")
    return memoryview(mapped)[start:start + info.compress_size]


def read_archive(path: Path, format_name: str, versions: tuple, with_arrays: bool = True,
                 pool: concurrent.futures.Executor | None = None):
    """(spec dict, {index: array}, :class:`Checks`) of a checkpoint file. Stored members (every one
    :mod:`patexgs_jax.checkpoint` writes) are views of the memory-mapped file whose CRCs are checked
    on ``pool`` (at once without one): the caller runs ``verify`` before using them. Raises
    CorruptCheckpointError (the caller names the file)."""
    checks = Checks(pool)
    with open(path, "rb") as f, zipfile.ZipFile(f, "r") as zf:
        names = set(zf.namelist())
        if "spec.json" not in names:
            raise CorruptCheckpointError("no spec.json member")
        spec = json.loads(zf.read("spec.json").decode("utf-8"))
        if not isinstance(spec, dict) or spec.get("format") != format_name:
            raise CorruptCheckpointError("not a patexgs checkpoint")
        if spec.get("version") not in versions:
            raise CorruptCheckpointError(f"unsupported format version {spec.get('version')!r} "
                                         f"(this code reads versions {versions})")
        arrays = {}
        if not with_arrays:
            bad = zf.testzip()
            if bad is not None:
                raise CorruptCheckpointError(f"member {bad} fails its CRC check")
            return spec, arrays, checks
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # (kept open by its views)
        for info in zf.infolist():
            m = re.fullmatch(r"arrays/(\d+)\.npy", info.filename)
            if m is None:
                continue
            if info.compress_type == zipfile.ZIP_STORED:
                data = _member_view(mapped, info)
                checks.add(info.filename, data, info.CRC)
            else:
                data = zf.read(info.filename)  # (checks the CRC)
            try:
                arrays[int(m.group(1))] = checkpoint_members.npy_view(data)
            except CorruptCheckpointError:
                checks.verify()  # (a damaged header: its CRC names it)
                raise
    return spec, arrays, checks
