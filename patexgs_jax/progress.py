"""Progress bars (tqdm, with rate and ETA) for training, evaluation and the studies.

A bar is drawn on stderr only when stderr is a terminal, so logs, CI output and captured test
output stay as they were; ``PATEXGS_PROGRESS=1`` draws bars anyway, ``PATEXGS_PROGRESS=0`` never.
Bars add nothing to what is recorded: the progress lines and ``log.jsonl`` are unchanged, and
:func:`say` prints a line above any bar that is drawn instead of through it.
"""

from __future__ import annotations

import os
import sys
import time

from tqdm import tqdm

__all__ = ["ENV_VAR", "bar", "enabled", "last_line", "say"]

#: ``1`` draws bars whatever stderr is, ``0`` never; unset: only on a terminal.
ENV_VAR = "PATEXGS_PROGRESS"

_last_line = time.monotonic()


def enabled() -> bool:
    """Whether bars are drawn: ``$PATEXGS_PROGRESS`` if set, else whether stderr is a terminal."""
    forced = os.environ.get(ENV_VAR, "").strip().lower()
    if forced:
        return forced not in ("0", "false", "no", "off")
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stderr
        return False


def bar(total: int, desc: str, *, unit: str = "step", initial: int = 0, leave: bool = False,
        show: bool = True) -> tqdm:
    """A progress bar of ``total`` items on stderr, ``initial`` of them already done (a resumed run);
    disabled (every call a no-op) unless :func:`enabled` and ``show``. ``leave=False`` erases it
    when closed, so a study's inner bars (a run's steps, an evaluation's views) leave its own."""
    return tqdm(total=total, desc=desc, unit=unit, initial=initial, leave=leave, file=sys.stderr,
                disable=not (show and enabled()), dynamic_ncols=True, smoothing=0.1)


def say(msg: str) -> None:
    """``print(msg, flush=True)`` to stdout, written above the bars that are drawn (not through them)."""
    global _last_line
    _last_line = time.monotonic()
    if getattr(tqdm, "_instances", None):  # tqdm's registry of open bars; empty when none is drawn
        tqdm.write(msg, file=sys.stdout)
        sys.stdout.flush()
    else:
        print(msg, flush=True)


def last_line() -> float:
    """``time.monotonic()`` when :func:`say` last printed (the import's time before that)."""
    return _last_line
