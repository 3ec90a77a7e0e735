"""The one place this package imports pycolmap, undoing two of its import side effects.

* zlib / Pillow first: pycolmap's extension exports its own zlib symbols; loaded before the system
  libz they corrupt the heap on the first deflate (see :mod:`patexgs_jax.data`).
* Fatal-signal handlers kept: importing pycolmap (4.2) installs glog's failure-signal handler for
  SIGSEGV, SIGBUS, SIGFPE, SIGILL and SIGABRT. That handler calls ``backtrace()``, which deadlocks
  when the signal arrives inside the C++ unwinder (seen here: an XLA compile error unwinding
  through JIT-compiled frames). A crash then became a process that hangs forever at 100% CPU. The
  handlers in place before the import (Python's ``faulthandler`` or the default action) are
  restored, so a fatal error crashes with Python's traceback instead.

Other modules use ``from patexgs_jax._pycolmap import pycolmap``.
"""

from __future__ import annotations

import ctypes
import signal
import sys
import zlib  # noqa: F401  -- before pycolmap (heap corruption otherwise)

import PIL.Image  # noqa: F401  -- before pycolmap (it loads libz)

FATAL_SIGNALS = tuple(getattr(signal, n) for n in ("SIGSEGV", "SIGBUS", "SIGFPE", "SIGILL", "SIGABRT")
                      if hasattr(signal, n))


class _SigAction(ctypes.Structure):
    """glibc's ``struct sigaction`` on Linux (handler, 1024-bit mask, flags, restorer)."""

    _fields_ = [("handler", ctypes.c_void_p), ("mask", ctypes.c_ulong * (1024 // (8 * ctypes.sizeof(ctypes.c_ulong)))),
                ("flags", ctypes.c_int), ("restorer", ctypes.c_void_p)]


def _libc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def fatal_handlers() -> dict | None:
    """The current C-level actions of :data:`FATAL_SIGNALS` (None where they cannot be read)."""
    libc = _libc()
    if libc is None:
        return None
    out = {}
    for sig in FATAL_SIGNALS:
        act = _SigAction()
        if libc.sigaction(int(sig), None, ctypes.byref(act)) != 0:
            return None
        out[sig] = act
    return out


def restore_fatal_handlers(saved: dict | None) -> None:
    """Reinstalls actions saved by :func:`fatal_handlers`."""
    libc = _libc()
    if libc is None or saved is None:
        return
    for sig, act in saved.items():
        libc.sigaction(int(sig), ctypes.byref(act), None)


_saved = fatal_handlers()
import pycolmap  # noqa: E402

restore_fatal_handlers(_saved)

__all__ = ["pycolmap"]
