"""Keeping a long-lived process within the kernel's limit on memory mappings.

XLA's CPU backend keeps every compiled executable's machine code in memory mappings of its own (about
20 for a small function, hundreds for a training step) for as long as the executable lives, and JAX's
caches keep executables alive after the functions that made them are gone. Linux caps the mappings
of a process (``vm.max_map_count``, 65,530 by default). A process that compiles many distinct
functions - studies that train many runs in one process, a notebook session, a test suite - reaches
the cap. The next compile then fails inside XLA, and on the CPU that was seen to end as a crash (or a
hang) rather than as a Python error.

:func:`release_compiled_code` drops JAX's caches when the process holds more than a given share of
the cap. Functions compiled before are then compiled again when next used. :func:`patexgs_jax.train.train`
calls it on entry, so in-process studies stay within the cap.
"""

from __future__ import annotations

import gc

import jax


def memory_maps() -> tuple[int, int] | None:
    """(mappings this process holds, the kernel's cap), or None where /proc does not say (not Linux)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            count = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read().strip())
    except (OSError, ValueError):
        return None
    return count, limit


def release_compiled_code(threshold: float = 0.5) -> bool:
    """Clears JAX's compilation caches (``jax.clear_caches``) and collects garbage when this process
    holds more than ``threshold`` of its memory-map cap; returns whether it did. ``threshold=0``
    always clears."""
    maps = memory_maps()
    if threshold > 0 and (maps is None or maps[0] <= threshold * maps[1]):
        return False
    jax.clear_caches()
    gc.collect()
    return True
