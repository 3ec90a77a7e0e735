"""The background thread that compiles ahead (:mod:`patexgs_jax.training.compile_ahead` decides
what): :func:`submit` hands it a compile (``jax.jit(f).lower(...).compile()``, which fills the
same in-memory cache a later ``f(x)`` hits), so a program whose shapes are known before it is
needed is compiled off the critical path; it is the one the main thread would have compiled, so
results are bit-identical with and without it.

* One job runs at a time, in submission order; a queued job can be cancelled (:meth:`Job.cancel`);
  a running one cannot (XLA's compile cannot be stopped) and is waited for (:meth:`Job.wait`) or
  left to finish.
* ``PATEXGS_COMPILE_AHEAD=0`` (or ``off``, ``no``, ``false``) turns it off: nothing is submitted.
* Exit: a process must not be torn down while XLA compiles in another thread (the interpreter's
  finalisation under a running compile crashes). A stop signal's exit
  (:func:`patexgs_jax.interrupt.end_with_stop_line`) ends the process with :func:`os._exit` right
  after the stop line when a compile is running (the work is already checkpointed); any other exit
  waits for the running compile (it always ends, within a minute or two), saying so.
* Traces made by a background job are counted by the thread (:func:`in_background`), so that the
  main thread's counters (``training.step.STEP_TRACES``) count only what the steps themselves trace.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["AHEAD_ENV", "Job", "busy", "enabled", "in_background", "submit", "wait_all"]

#: Environment variable that turns compiling ahead off (``0``, ``off``, ``no``, ``false``).
AHEAD_ENV = "PATEXGS_COMPILE_AHEAD"
_OFF = frozenset({"0", "off", "no", "none", "false"})


def enabled() -> bool:
    """Whether compiling ahead is on (the default; ``PATEXGS_COMPILE_AHEAD=0`` turns it off)."""
    return os.environ.get(AHEAD_ENV, "1").strip().lower() not in _OFF


_local = threading.local()


def in_background() -> bool:
    """Whether the calling thread is running a background job (its traces are not the steps')."""
    return bool(getattr(_local, "background", False))


class Job:
    """One background job: ``fn()`` run in the worker thread; its value or exception kept."""

    def __init__(self, what: str, fn: Callable[[], Any], say: Callable[[str], None] | None):
        self.what, self.say = what, say
        self.fn: Callable[[], Any] | None = fn
        self.value: Any = None
        self.error: BaseException | None = None
        self.started: float | None = None  # time.monotonic()
        self.seconds: float | None = None  # how long it ran, once done
        self.cancelled = False
        self._done = threading.Event()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def running(self) -> bool:
        return self.started is not None and not self.done

    @property
    def ok(self) -> bool:
        """Done without an error (and not cancelled)."""
        return self.done and self.error is None and not self.cancelled

    def cancel(self) -> bool:
        """Cancels the job if it has not started; returns whether it will not run (or has not run)."""
        with _cond:
            if self.started is None and not self.done:
                self.cancelled = True
                self._done.set()
                with contextlib.suppress(ValueError):
                    _queue.remove(self)
                return True
        return self.cancelled

    def wait(self, timeout: float | None = None, poll: Callable[[], None] | None = None) -> bool:
        """Waits until the job is done (at most ``timeout`` seconds); ``poll`` is called about every
        0.2 s while waiting (e.g. :func:`patexgs_jax.interrupt.check`). Returns whether it is done."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._done.wait(0.2):
            if poll is not None:
                poll()
            if end is not None and time.monotonic() >= end:
                return False
        return True

    def __repr__(self):
        state = ("cancelled" if self.cancelled else "failed" if self.error is not None else "done" if self.done
                 else "running" if self.running else "queued")
        return f"Job({self.what!r}, {state})"


_cond = threading.Condition()
_queue: collections.deque[Job] = collections.deque()
_current: list[Job] = []  # the running job (at most one)
_thread: threading.Thread | None = None


def submit(what: str, fn: Callable[[], Any], say: Callable[[str], None] | None = None) -> Job | None:
    """Queues ``fn`` (a compile: ``what`` names it, for the progress lines ``say`` prints when it
    starts and ends) for the background thread; None when compiling ahead is off."""
    global _thread
    if not enabled():
        return None
    job = Job(what, fn, say)
    with _cond:
        _queue.append(job)
        if _thread is None or not _thread.is_alive():
            _thread = threading.Thread(target=_worker, name="patexgs-compile-ahead", daemon=True)
            _thread.start()
        _cond.notify()
    return job


def busy() -> Job | None:
    """The job running now, or None."""
    return _current[0] if _current else None


def _worker() -> None:
    _local.background = True
    while True:
        with _cond:
            while not _queue:
                _cond.wait()
            job = _queue.popleft()
            job.started = time.monotonic()
            _current.append(job)
        if job.say is not None:
            with contextlib.suppress(Exception):
                job.say(f"[compile ahead] compiling {job.what} in the background")
        try:
            assert job.fn is not None
            job.value = job.fn()
        except Exception as e:  # never fatal: the main thread compiles the program itself when it needs it
            job.error = e
        job.seconds = time.monotonic() - job.started
        job.fn = None  # (drops the arguments it held)
        with _cond:
            _current.clear()
            job._done.set()
        if job.say is not None:
            with contextlib.suppress(Exception):
                how = (f"failed ({type(job.error).__name__}: {job.error}); it compiles when needed"
                       if job.error is not None else "done")
                job.say(f"[compile ahead] {job.what}: {how} ({job.seconds:.0f} s)")


def wait_all(timeout: float | None = None) -> bool:
    """Cancels the queued jobs and waits for the running one; returns whether none is running."""
    with _cond:
        queued = list(_queue)
    for job in queued:
        job.cancel()
    job = busy()
    return job is None or job.wait(timeout)


@atexit.register
def _at_exit() -> None:
    """A normal exit (or one by an exception) with a compile running waits for it: tearing the
    interpreter down under XLA's compiler crashes. A second Ctrl-C ends the process at once."""
    job = busy()
    if job is None:
        wait_all(0)
        return
    try:
        with contextlib.suppress(Exception):
            print(f"waiting for the background compile of {job.what} to end before exiting "
                  f"({time.monotonic() - (job.started or time.monotonic()):.0f} s so far)", file=sys.stderr, flush=True)
        wait_all()
    except KeyboardInterrupt:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(130)
