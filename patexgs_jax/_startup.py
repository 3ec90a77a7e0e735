"""Ctrl-C while a command line of this project is still importing its modules: one line, status 130.

``python -m patexgs_jax.train`` (or ``experiments.mipnerf360``, ...) imports the parent package,
and with it JAX, before the command line's own code can install its signal handlers
(:mod:`patexgs_jax.interrupt`). A KeyboardInterrupt raised there ends in a traceback through
runpy, or, when it surfaces inside an extension module's initialisation (jaxlib's), in a
segmentation fault. The package's ``__init__`` imports this module first thing, which, only under
``python -m`` (runpy sets ``sys.argv[0]`` to ``"-m"`` while it imports the parent packages),
installs :func:`quiet_interrupt_while_starting`'s two guards:

* a SIGINT handler that, while the interpreter is inside an import (or runpy has not yet started
  the module), prints :data:`STARTING` and ends the process at once with 130, so no exception
  ever unwinds through a half-initialised extension; elsewhere it raises KeyboardInterrupt as
  Python's own handler does;
* a ``sys.excepthook`` that turns an uncaught KeyboardInterrupt into the same line and status.

A script or a notebook that imports the package as a library gets neither, and
:func:`patexgs_jax.interrupt.handle_stop_signals` removes both once the command line handles
signals itself. Standard library only: it must be importable before anything heavy.
"""

from __future__ import annotations

import os
import signal
import sys

__all__ = ["STARTING", "installed", "quiet_interrupt_while_starting", "uninstall"]

#: What a Ctrl-C before the command line's own handlers prints.
STARTING = "stopped by SIGINT while starting; nothing was saved yet"

_previous = None
_installed_handler = False


def _starting(frame) -> bool:
    """Whether the main thread is still loading code: inside an import, or before runpy has set
    ``__main__.__spec__`` (the parent packages' imports)."""
    main = sys.modules.get("__main__")
    if getattr(main, "__spec__", None) is None:
        return True
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _sigint(signum, frame) -> None:
    if _starting(frame):
        print(STARTING, file=sys.stderr, flush=True)
        os._exit(130)  # 128 + SIGINT; nothing to save, and no exception through an extension's init
    raise KeyboardInterrupt


def _hook(kind, value, tb) -> None:
    if issubclass(kind, KeyboardInterrupt):
        print(STARTING, file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(130)  # 128 + SIGINT, as the command lines' own stop; nothing to clean up yet
    (_previous or sys.__excepthook__)(kind, value, tb)


def quiet_interrupt_while_starting() -> None:
    """Installs the quiet Ctrl-C hook when Python is starting a module of this project with ``-m``."""
    global _previous, _installed_handler
    if sys.argv[:1] != ["-m"] or sys.excepthook is _hook:
        return
    _previous = sys.excepthook
    sys.excepthook = _hook
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # (an inherited SIG_IGN stays)
        signal.signal(signal.SIGINT, _sigint)
        _installed_handler = True


def installed() -> bool:
    """Whether the guards are in place."""
    return sys.excepthook is _hook


def uninstall() -> None:
    """Restores the previous ``sys.excepthook`` and, unless something else replaced it since,
    Python's SIGINT handler (a no-op when the guards are not installed)."""
    global _previous, _installed_handler
    if sys.excepthook is _hook:
        sys.excepthook = _previous or sys.__excepthook__
    if _installed_handler and signal.getsignal(signal.SIGINT) is _sigint:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    _previous, _installed_handler = None, False


quiet_interrupt_while_starting()

if sys.argv[:1] == ["-m"]:
    # ``python -m patexgs_jax.render`` runs the renderer's module as ``__main__`` after the package has
    # imported it (it is the package's API); its ``__main__`` block only hands over to
    # patexgs_jax.render_cli, so runpy's warning about the second copy has nothing to act on.
    import warnings

    warnings.filterwarnings("ignore", message=r"'patexgs_jax\.render' found in sys\.modules", category=RuntimeWarning)
