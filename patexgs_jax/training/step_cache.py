"""The jitted training steps of a run (:class:`StepCache`), and those the runs of one process share.

A run's step is one jitted function per (render config, tile capacity, ...) and scene layout, with
one program per padded view size. The single-view steps are also kept for the other runs of the
process (:data:`_SHARED_STEPS`), keyed by what else defines them (the step identity of
:func:`~patexgs_jax.training.compile_ahead.step_identity`; the scene radius, learning rates and
loss weights are the step's arguments): a resumed run, a study's runs, a run on another scene of
the same shapes or a notebook's second run then call the executables an earlier run compiled
instead of tracing, lowering and compiling them again.

Programs hold memory mappings (see :mod:`patexgs_jax.compiled`): when a run leaves a layout in a
process holding more than :data:`patexgs_jax.compiled.KEEP_SHARE` of its cap, the steps of the
layouts left behind are released with the renderer's programs; every clear of JAX's caches also
empties the shared steps (their programs are gone).
"""

from __future__ import annotations

import collections
from collections.abc import Callable
from typing import Any

from .. import ahead, compiled, padding

__all__ = ["StepCache", "StepEntry", "release_steps", "shared_step"]

#: Jitted steps (capacities) a run keeps for one scene layout.
_MAX_STEP_FNS = 4

#: Shared steps kept at most (the least recently used released first).
_MAX_SHARED_STEPS = 16

#: A jitted step as a run keeps it: the function, the padded sizes it has been called with (a new
#: one compiles), and the background jobs compiling it ahead, per padded size.
StepEntry = tuple[Callable, set, dict[tuple[int, int], "ahead.Job | None"]]

#: The steps the runs of this process share: (step identity, key, scene layout) -> (the jitted step,
#: the padded sizes it has compiled).
_SHARED_STEPS: collections.OrderedDict[tuple, tuple[Callable, set]] = collections.OrderedDict()


def release_steps() -> None:
    """Releases the jitted steps the runs of this process share and their programs: the next run
    traces and compiles its own."""
    for fn, _ in _SHARED_STEPS.values():
        compiled.release_programs(fn)
    _SHARED_STEPS.clear()


def shared_step(identity: tuple, key, layout: tuple, padded: tuple[int, int]) -> Callable | None:
    """The jitted step an earlier run of this process shared for this step identity, key and scene
    layout, if it has compiled the padded view size ``padded`` (else None): what compiling ahead
    finds instead of compiling it again (safe from its thread: a lookup)."""
    entry = _SHARED_STEPS.get((identity, key, layout))
    return entry[0] if entry is not None and padded in entry[1] else None


compiled.on_clear(_SHARED_STEPS.clear)  # (JAX's caches cleared: the steps hold no programs any more)


class StepCache:
    """One run's jitted steps of its current scene layout, per key (render config, capacity, ...).

    Args:
      identity: what defines the run's step besides the key and the layout (shared steps are
        matched by it).
    """

    def __init__(self, identity: tuple):
        self.identity = identity
        self.entries: dict[Any, StepEntry] = {}
        self.layout: tuple | None = None

    def clear(self) -> None:
        """Forgets this run's steps (near the memory-map cap, with JAX's caches)."""
        self.entries.clear()

    def get(self, layout: tuple, key, make: Callable[[], Callable],
            claim: Callable[[tuple], Any] | None = None, shared: bool = False) -> StepEntry:
        """The jitted step for ``key`` and the scene layout ``layout``, made by ``make()`` when new
        (or taken from a step compiled ahead, ``claim(layout)``); returns (the jitted step, the padded
        sizes it has been called with, the background jobs compiling it ahead per padded size).
        Within a layout at most :data:`_MAX_STEP_FNS` steps are kept, the oldest dropped first.

        With ``shared``, the step is also kept for the other runs of this process, and taken from
        there when another run (or this run's earlier attempt, before a resume) made it. A layout,
        once left, is rarely met again within a run (the Gaussian capacity only grows; texture
        buckets are sized afresh when one overflows), so when the layout changes in a process
        holding more than :data:`compiled.KEEP_SHARE` of its memory-map cap, the steps of the
        layouts left are released, with the renderer's and pair counter's programs."""
        if self.layout != layout:
            if self.entries:
                self.entries.clear()
                if padding.release_scene_programs(retire=True):
                    release_steps()
            self.layout = layout
        if key in self.entries:
            return self.entries[key]
        while len(self.entries) >= _MAX_STEP_FNS:
            self.entries.pop(next(iter(self.entries)))
        process_key = (self.identity, key, layout) if shared else None
        if process_key in _SHARED_STEPS:
            _SHARED_STEPS.move_to_end(process_key)
            fn, seen = _SHARED_STEPS[process_key]
            self.entries[key] = (fn, seen, {})
            return self.entries[key]
        prepared = None if claim is None else claim(layout)
        if prepared is not None:
            self.entries[key] = (prepared.fn, set(), {prepared.padded: prepared.step_job})
        else:
            self.entries[key] = (make(), set(), {})
        if process_key is not None:
            _SHARED_STEPS[process_key] = self.entries[key][:2]
            while len(_SHARED_STEPS) > _MAX_SHARED_STEPS:
                compiled.release_programs(_SHARED_STEPS.popitem(last=False)[1][0])
        return self.entries[key]
