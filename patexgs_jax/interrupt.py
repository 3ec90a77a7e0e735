"""Stopping a command line cleanly on SIGINT / SIGTERM, and saying what it does while it works.

The signal handler only records the signal: a KeyboardInterrupt raised inside XLA's compiler can
leave the process to crash later, and one raised in the middle of the host loop leaves a traceback
and no word about what was saved. The host loops call :func:`check` between steps, views and phases;
it raises :class:`Interrupted`, which the loop that holds unsaved work turns into a checkpoint and
the command line into one line (:func:`stop_line`: where it stopped, what holds the work, the
command that continues it) and exit status 128 + the signal (130 for SIGINT, 143 for SIGTERM).

Python runs a signal handler only when the main thread is between bytecodes, so a compile of a
minute would hold the stop for a minute. The C-level handler also writes the signal's number to a
pipe (:func:`signal.set_wakeup_fd`), which a watchdog thread reads at once: when the main thread has
not started to stop within :data:`GRACE_ENV` seconds (default 3), or has not finished within
:data:`SAVE_GRACE` seconds once it has, the watchdog prints the same line, naming the newest
checkpoint on disk, and ends the process with :func:`os._exit` (no interpreter shutdown under XLA's
running threads). A second signal ends it at once the same way.

While :func:`guard` is active, a heartbeat thread prints ``<phase>, N s so far`` whenever nothing
was printed for :data:`HEARTBEAT_ENV` seconds (default 30): a compile, a slow step, an evaluation
or an export never leaves a minute of silence.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator

from . import _startup, progress

__all__ = [
    "GRACE_ENV",
    "HEARTBEAT_ENV",
    "SIGNALS",
    "Interrupted",
    "check",
    "cleanup_on_forced_exit",
    "end_with_stop_line",
    "exit_code",
    "guard",
    "handle_stop_signals",
    "requested",
    "set_phase",
    "set_resume",
    "set_saved",
    "set_step",
    "stop_line",
]

#: The signals that stop a command line.
SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: Seconds the main thread has to start stopping after a signal before the watchdog ends the process.
GRACE_ENV = "PATEXGS_STOP_GRACE"
#: Seconds of silence after which the heartbeat prints the current phase.
HEARTBEAT_ENV = "PATEXGS_HEARTBEAT"
#: Seconds the main thread has, once it has started stopping, to write its checkpoint and finish.
SAVE_GRACE = 60.0


class Interrupted(BaseException):  # noqa: N818  (like KeyboardInterrupt: not an error, never caught by `except Exception`)
    """Raised by :func:`check` after SIGINT / SIGTERM; ``signum`` is the signal."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def exit_code(signum: int) -> int:
    """The shell's exit status for a process stopped by ``signum`` (130 for SIGINT, 143 for SIGTERM)."""
    return 128 + int(signum)


@dataclasses.dataclass
class _Status:
    """What the process is doing, for the heartbeat and the stop line (written by the main thread)."""

    phase: str | None = None
    since: float = 0.0  # time.monotonic() when the phase began
    step: tuple[int, int, str] | None = None  # (done, total, unit) within the phase
    saved: str | None = None  # what holds the work so far, e.g. "the checkpoint of step 500 in DIR"
    resume: str | None = None  # the command that continues the work
    signum: int | None = None  # the first stop signal received
    stopping: bool = False  # the main thread has seen the signal and is stopping
    ended: bool = False  # the stop line was printed (by whichever thread got there first)
    # What the watchdog runs before it ends the process (the main thread's `finally` blocks do not run).
    cleanups: list[Callable[[], None]] = dataclasses.field(default_factory=list)


_status = _Status()
_lock = threading.Lock()


def set_phase(phase: str | None) -> bool:
    """What the process does now (``"compiling the textured step"``); the heartbeat counts the
    seconds from the first call with this text, so calling it again with the same text is free.
    Returns whether the phase changed (its progress is then unknown until :func:`set_step`)."""
    if phase == _status.phase:
        return False
    _status.phase, _status.since, _status.step = phase, time.monotonic(), None
    return True


def set_step(done: int, total: int, unit: str = "step") -> None:
    """The progress within the current phase, ``done`` of ``total`` ``unit``\\ s (shown by the
    heartbeat and the stop line)."""
    _status.step = (int(done), int(total), unit)


def set_saved(what: str | None) -> None:
    """What holds the work so far (``"the checkpoint of step 500 in runs/x/checkpoints"``)."""
    _status.saved = what


def set_resume(command: str | None) -> None:
    """The command that continues the work after a stop."""
    _status.resume = command


@contextlib.contextmanager
def cleanup_on_forced_exit(fn: Callable[[], None]) -> Iterator[None]:
    """Runs ``fn`` if the watchdog ends the process inside this block (it skips ``finally`` blocks:
    a block that tidies up on its way out also registers its tidying here)."""
    _status.cleanups.append(fn)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            _status.cleanups.remove(fn)


def requested() -> int | None:
    """The stop signal received, or None."""
    return _status.signum


def check() -> None:
    """Raises :class:`Interrupted` if a stop signal arrived (and marks the stop as under way, which
    gives the main thread :data:`SAVE_GRACE` seconds to save its work and return)."""
    if _status.signum is not None:
        _status.stopping = True
        raise Interrupted(_status.signum)


def _where() -> str:
    st = _status
    where = st.phase or "starting"
    if st.step is not None:
        done, total, unit = st.step
        where += f" (step {done} of {total})" if unit == "step" else f" ({done} of {total} {unit}s done)"
    return where


def stop_line(signum: int) -> str:
    """The one line a stopped command prints: the signal, where it stopped, what holds the work and
    how to continue."""
    st = _status
    name = signal.Signals(signum).name
    kept = f"the work is in {st.saved}" if st.saved else "nothing was saved yet"
    nxt = f"; continue with: {st.resume}" if st.resume else ""
    return f"stopped by {name} while {_where()}; {kept}{nxt}"


def _end(signum: int) -> None:
    """Prints the stop line, once (whichever thread comes first)."""
    with _lock:
        if _status.ended:
            return
        _status.ended = True
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    with contextlib.suppress(Exception):
        print(stop_line(signum), file=sys.stderr, flush=True)


def _forced_exit(signum: int) -> None:
    """The watchdog's end: the stop line, the registered clean-ups, then :func:`os._exit`."""
    _end(signum)
    for fn in list(_status.cleanups):
        with contextlib.suppress(Exception):
            fn()
    os._exit(exit_code(signum))


def end_with_stop_line(signum: int) -> int:
    """For the command line that caught :class:`Interrupted`: prints the stop line and returns the
    exit status. When a background compile (:mod:`patexgs_jax.background`) is running, the process ends
    here, with :func:`os._exit` and that status, after the registered clean-ups: the work is saved,
    and neither waiting for XLA's compiler nor tearing the interpreter down under it is safe
    (the latter crashes)."""
    from . import background

    _end(signum)
    if background.busy() is not None:
        _forced_exit(signum)
    return exit_code(signum)


def handle_stop_signals(handler: Callable[[int, object], None]) -> dict:
    """Installs ``handler`` for SIGINT and SIGTERM and unblocks them; returns the previous handlers.

    A process started with SIGINT ignored (a job started with ``&`` from a script) or blocked (a
    test runner's worker) inherits that through exec, and Ctrl-C would then never reach it."""
    _startup.uninstall()  # the command line handles its signals from here on
    old = {sig: signal.signal(sig, handler) for sig in SIGNALS}
    signal.pthread_sigmask(signal.SIG_UNBLOCK, set(SIGNALS))
    return old


def _float_env(name: str, default: float) -> float:
    try:
        return float(os.environ.get(name, "") or default)
    except ValueError:
        return default


def _watchdog(read_fd: int, grace: float, done: threading.Event) -> None:
    """Reads signal numbers from the wakeup pipe; ends the process if the main thread does not stop
    in time (see the module docstring)."""
    deadline = None
    while not done.is_set():
        if deadline is None:
            data = _read(read_fd, None)
        else:
            data = _read(read_fd, 0.1)
        if data is None:  # the pipe was closed: guard() is over
            return
        sigs = [b for b in data if b in {int(s) for s in SIGNALS}]
        if sigs and deadline is not None:  # a second signal: stop now
            _forced_exit(_status.signum or sigs[0])
        if sigs and deadline is None:
            if _status.signum is None:  # the Python-level handler may not have run yet
                _status.signum = sigs[0]
            deadline = time.monotonic() + grace
            if len(sigs) > 1:  # two signals read at once: the second is a second signal
                _forced_exit(_status.signum)
        if deadline is not None and not done.is_set():
            limit = deadline + (SAVE_GRACE if _status.stopping else 0.0)
            if time.monotonic() > limit:
                _forced_exit(_status.signum or signal.SIGINT)


def _read(fd: int, timeout: float | None) -> bytes | None:
    """Bytes from ``fd`` (b"" after ``timeout`` seconds with nothing to read), or None once closed."""
    import select

    try:
        ready, _, _ = select.select([fd], [], [], timeout)
        if not ready:
            return b""
        data = os.read(fd, 64)
    except OSError:
        return None
    return data if data else None


def _heartbeat(interval: float, done: threading.Event) -> None:
    while not done.wait(min(1.0, interval / 4)):
        st = _status
        if st.phase is None or st.signum is not None:
            continue
        now = time.monotonic()
        if now - progress.last_line() >= interval and now - st.since >= interval:
            with contextlib.suppress(Exception):  # (a closed stdout must not end the thread with a traceback)
                progress.say(f"{_where()}, {now - st.since:.0f} s so far")


@contextlib.contextmanager
def guard(resume: str | None = None) -> Iterator[None]:
    """For a command line's body (main thread): SIGINT / SIGTERM set the stop flag that
    :func:`check` raises on, with the watchdog and heartbeat threads running (module docstring).
    ``resume``: the command that continues the work. The previous handlers are restored on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    global _status
    _status = _Status(resume=resume)
    grace = max(0.0, _float_env(GRACE_ENV, 3.0))
    interval = max(0.5, _float_env(HEARTBEAT_ENV, 30.0))
    done = threading.Event()
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)

    def on_signal(signum, frame):
        if _status.signum is None:
            _status.signum = signum

    old_handlers = handle_stop_signals(on_signal)
    old_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threads = [threading.Thread(target=_watchdog, args=(read_fd, grace, done), name="patexgs-stop-watchdog",
                                daemon=True),
               threading.Thread(target=_heartbeat, args=(interval, done), name="patexgs-heartbeat", daemon=True)]
    for t in threads:
        t.start()
    try:
        yield
    finally:
        done.set()
        signal.set_wakeup_fd(old_fd)
        for sig, h in old_handlers.items():
            signal.signal(sig, h if h is not None else signal.SIG_DFL)
        os.close(write_fd)
        for t in threads:
            t.join(timeout=2.0)
        os.close(read_fd)
        _status = _Status()  # library calls after the command line's body see no stop request
