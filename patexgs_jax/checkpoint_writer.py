"""Checkpoints written off the training thread.

:class:`CheckpointWriter` splits :func:`patexgs_jax.checkpoint.save_checkpoint` in two: ``save``
takes the tree's arrays to host memory nothing else shares (so that the next step may donate or
overwrite the device buffers) and returns; one background thread then finds the repeated values and
zero rows, writes, CRCs, fsyncs and renames the file into place and applies ``keep``, with the same
bytes on disk as ``save_checkpoint``'s. The host copies of a finished write are the next ``save``'s
buffers where shapes and dtypes match (a run's checkpoints mostly do), so that only the first save
faults fresh pages in; they stay allocated until ``close``. At most one write is in flight: a
``save`` waits for the previous write first. A failed write (disk full, permissions) leaves the
previous checkpoint untouched (the rename comes last) and is raised, naming the file, by the next
``save``, ``wait`` or ``close``. The thread is not a daemon: a process that ends normally finishes
its write first; one killed mid-write leaves only a hidden temp file, which ``list_checkpoints``
and ``latest_checkpoint`` never consider.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

from . import checkpoint as ckpt
from .checkpoint_members import CheckpointError

__all__ = ["CheckpointWriter"]


class CheckpointWriter:
    """Writes checkpoints one at a time in a background thread; a context manager (``close`` on
    exit).

    Args:
      write: writes a :class:`~patexgs_jax.checkpoint.PreparedCheckpoint` with ``keep`` (default
        :func:`~patexgs_jax.checkpoint.write_prepared`; tests inject slow or failing ones).
    """

    def __init__(self, write: Callable[..., Path] | None = None):
        self._write = write or ckpt.write_prepared
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._failed: Path | None = None  # the file of the failed write
        self._prepared: ckpt.PreparedCheckpoint | None = None  # the write in flight
        self._pool: dict = {}  # the finished write's host copies, reused by the next save
        self._closed = False
        self.last_path: Path | None = None  # the newest checkpoint written completely

    @property
    def in_flight(self) -> bool:
        """Whether a write is still running."""
        return self._thread is not None and self._thread.is_alive()

    def save(self, path, tree, metadata: dict | None = None, *, keep: int | None = None,
             on_written: Callable[[Path], None] | None = None) -> Path:
        """Waits for the previous write (raising its error, if any), takes ``tree`` to the host and
        starts writing it to ``path``; returns ``path`` once the source may change. Arguments as
        :func:`~patexgs_jax.checkpoint.save_checkpoint`'s; bad leaves, metadata or ``keep`` raise
        here, before anything is written. ``on_written(path)`` runs in the writer's thread once the
        file is in place (e.g. to record which checkpoint holds the work; an error in it counts as
        the write's)."""
        if self._closed:
            raise CheckpointError(f"cannot save checkpoint {path}: the writer is closed.")
        if keep is not None and keep < 1:
            raise ValueError(f"keep must be >= 1, got {keep}.")
        self.wait()
        prepared = ckpt.prepare_checkpoint(path, tree, metadata, copy=True, pool=self._pool)
        self._pool, self._prepared = {}, prepared
        self._thread = threading.Thread(target=self._run, args=(prepared, keep, on_written), daemon=False,
                                        name=f"checkpoint-writer {prepared.path.name}")
        self._thread.start()
        return prepared.path

    def _run(self, prepared: ckpt.PreparedCheckpoint, keep: int | None, on_written) -> None:
        try:
            self.last_path = self._write(prepared, keep)
            if on_written is not None:
                on_written(self.last_path)
        except BaseException as e:  # raised in the training thread by the next call
            self._error = e
            self._failed = prepared.path

    def wait(self) -> Path | None:
        """Blocks until the write in flight is done; raises its error, if it failed. Returns the
        newest checkpoint written completely (None before the first)."""
        thread = self._thread
        if thread is not None:
            thread.join()
            self._thread = None
        if self._prepared is not None:  # its buffers are free now
            for buf in self._prepared.encoder.copies:
                self._pool.setdefault((buf.shape, buf.dtype.str), []).append(buf)
            self._prepared = None
        error, self._error = self._error, None
        if error is not None:
            if isinstance(error, CheckpointError) and str(self._failed) in str(error):
                raise error  # (its message names the file)
            raise CheckpointError(f"could not write checkpoint {self._failed}: "
                                  f"{type(error).__name__}: {error}") from error
        return self.last_path

    def release(self) -> Path | None:
        """:meth:`wait`, then frees the host copies kept for the next save (a later save allocates
        afresh): the end of a run, whose trainer may outlive it."""
        try:
            return self.wait()
        finally:
            self._pool = {}

    def close(self) -> Path | None:
        """:meth:`release`, then refuses further saves."""
        self._closed = True
        return self.release()

    def __enter__(self) -> CheckpointWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        try:  # (the body's exception is the one raised; a failed write is then only chained)
            self.close()
        except Exception as write_error:
            if exc is not None:
                exc.__context__ = write_error
