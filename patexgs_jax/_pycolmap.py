"""The one place this package imports pycolmap, undoing two of its import side effects.

* zlib / Pillow first (checked with pycolmap 4.2.1, pillow 13, CPython 3.11): pycolmap's extension
  module contains and exports its own zlib symbols. If the system ``libz.so.1`` is first loaded
  *after* pycolmap (by Pillow's ``_imaging`` or Python's ``zlib`` module), libz's internal calls
  bind to pycolmap's copies and the first deflate (saving a PNG, ``zlib.compress``) aborts with
  ``free(): invalid pointer``. This module loads zlib and PIL.Image before pycolmap, so every module
  that gets pycolmap from here is safe in any import order (and so is a caller's own pycolmap
  imported after :mod:`patexgs_jax`, whose jax loads libz). If the caller imported pycolmap before
  zlib / PIL, nothing can be repaired any more and a RuntimeWarning says so (detected from the
  dynamic linker's load order).
* Fatal-signal handlers kept: importing pycolmap (4.2) installs glog's failure-signal handler for
  SIGSEGV, SIGBUS, SIGFPE, SIGILL and SIGABRT. That handler calls ``backtrace()``, which deadlocks
  when the signal arrives inside the C++ unwinder (e.g. an XLA compile error unwinding through
  JIT-compiled frames), turning a crash into a process that hangs at 100% CPU. The handlers in place
  before the import (Python's ``faulthandler`` or the default action) are restored, so a fatal
  error crashes with Python's traceback instead. glog takes SIGTERM too (printing a native stack
  dump for an ordinary ``kill``); its handler before the import is restored as well, so a command
  line's clean stop (:mod:`patexgs_jax.interrupt`) or the default action stays in place.

Other modules use ``from patexgs_jax._pycolmap import pycolmap``.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import warnings
import zlib  # noqa: F401  -- before pycolmap, see the module docstring

import PIL.Image  # noqa: F401  -- before pycolmap (it loads libz)

FATAL_SIGNALS = tuple(getattr(signal, n) for n in ("SIGSEGV", "SIGBUS", "SIGFPE", "SIGILL", "SIGABRT")
                      if hasattr(signal, n))
#: The signals whose handlers the import of pycolmap replaces (glog's failure-signal handler).
GLOG_SIGNALS = FATAL_SIGNALS + (signal.SIGTERM,)


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
    """The current C-level actions of :data:`GLOG_SIGNALS` (None where they cannot be read)."""
    libc = _libc()
    if libc is None:
        return None
    out = {}
    for sig in GLOG_SIGNALS:
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


def pycolmap_loaded_before_libz() -> bool:
    """Whether pycolmap's extension was loaded before the system libz (the state that crashes).

    Uses the dynamic linker's load order (``dl_iterate_phdr``, Linux/glibc); False where unavailable.
    """
    names = []

    def collect(info, size, data):
        names.append(os.fsdecode(info.contents.name or b""))
        return 0

    try:
        class _Info(ctypes.Structure):
            _fields_ = [("addr", ctypes.c_void_p), ("name", ctypes.c_char_p), ("phdr", ctypes.c_void_p),
                        ("phnum", ctypes.c_uint16)]

        callback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(_Info), ctypes.c_size_t, ctypes.c_void_p)(collect)
        ctypes.CDLL(None).dl_iterate_phdr(callback, None)
    except Exception:
        return False
    core = next((i for i, n in enumerate(names) if "pycolmap" in n and "_core" in os.path.basename(n)), None)
    libz = next((i for i, n in enumerate(names) if os.path.basename(n).startswith("libz.so")), None)
    return core is not None and (libz is None or core < libz)


if pycolmap_loaded_before_libz():
    warnings.warn(
        "pycolmap was imported before zlib / PIL / jax: with pycolmap 4.2.1 the process may abort "
        "('free(): invalid pointer') when saving a PNG or compressing with zlib. Import patexgs_jax "
        "(or PIL.Image) before pycolmap.", RuntimeWarning, stacklevel=2)

_saved = fatal_handlers()
import pycolmap  # noqa: E402

restore_fatal_handlers(_saved)

__all__ = ["pycolmap"]
