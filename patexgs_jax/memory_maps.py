"""Keeping a long-lived process within the kernel's limit on memory mappings.

XLA's CPU backend keeps every compiled executable's machine code in memory mappings of its own (a
training step's are thousands, docs/performance.md) for as long as the executable lives, and JAX's
caches keep executables alive after the functions that made them are gone. Linux caps the mappings
of a process (``vm.max_map_count``, 65,530 by default). A process that compiles many distinct
programs - a training run over images of many sizes, an evaluation at many sizes, studies that train
many runs in one process, a notebook session, a test suite - reaches the cap. The next compile then
fails inside XLA ("LLVM ERROR: Unable to allocate section memory"), and on the CPU that ends as a
crash or a segfault rather than as a Python error.

What keeps the count bounded: few programs (views rendered at a few padded sizes,
:mod:`patexgs_jax.padding`); the programs of retired layouts released once the process holds
:data:`KEEP_SHARE` of the cap (:func:`retire_programs`; :func:`trim_programs` bounds a per-shape
cache); and a guard (:class:`MapGuard`) that drops all of JAX's compiled code above
``release_share`` of the cap and, above ``stop_share`` even so, makes training checkpoint and stop
with :class:`MapLimitReached` instead of crashing in the next compile. Programs also outlive the
process: the command lines turn on JAX's persistent compilation cache (:func:`enable_compile_cache`),
so a second or resumed run loads what the first compiled.
"""

from __future__ import annotations

import dataclasses
import gc
import os
from pathlib import Path

import jax

#: The kernel's default ``vm.max_map_count``.
DEFAULT_MAP_LIMIT = 65_530

#: Environment variable naming the persistent compilation cache's folder; ``off`` (or ``0``, ``no``,
#: ``none``, ``false``, empty) turns the cache off.
COMPILE_CACHE_ENV = "PATEXGS_COMPILE_CACHE"
_OFF = frozenset({"", "0", "off", "no", "none", "false"})


def compile_cache_dir() -> Path | None:
    """The folder of the persistent compilation cache the command lines use, or None when it is off.

    ``$PATEXGS_COMPILE_CACHE`` if set (``off`` disables the cache), else ``$PATEXGS_CACHE/xla``
    (the project's cache, shared with the synthetic scene and undistorted images), else
    ``$XDG_CACHE_HOME/patexgs_jax/xla`` (``~/.cache/patexgs_jax/xla``): one per user, since a
    program compiled by one checkout serves every other with the same JAX and XLA flags (JAX's
    cache keys hold the program, the compile options and the versions).
    """
    value = os.environ.get(COMPILE_CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in _OFF else Path(value).expanduser()
    return project_cache_root() / "xla"


def project_cache_root() -> Path:
    """The project's cache folder: ``$PATEXGS_CACHE``, else ``$XDG_CACHE_HOME/patexgs_jax``
    (``~/.cache/patexgs_jax``). The command lines' compiled programs live in its ``xla/``, the
    test suite's in its ``test-xla/``."""
    root = os.environ.get("PATEXGS_CACHE")
    if root:
        return Path(root).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "patexgs_jax"


def enable_compile_cache(path=None) -> Path | None:
    """Turns on JAX's persistent compilation cache in ``path`` (default :func:`compile_cache_dir`);
    returns the folder in use, or None when the cache stays off.

    A folder already configured (``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``) is kept, so a
    user's own cache and the test suite's win. JAX decides at the first compile whether a cache is
    used, so call this before anything compiles. JAX stores only programs that took at least
    ``jax_persistent_cache_min_compile_time_secs`` (1 s by default) to compile. A folder that
    cannot be created leaves the cache off (compiling still works). Empty entries found there are
    removed (:func:`drop_empty_entries`).
    """
    current = getattr(jax.config, "jax_compilation_cache_dir", None)
    if current:
        return Path(current)
    folder = compile_cache_dir() if path is None else Path(path)
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    drop_empty_entries(folder)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    return folder


def drop_empty_entries(folder) -> int:
    """Removes the empty files of the persistent compilation cache in ``folder``; returns how many.

    JAX never replaces an entry it finds, so one left empty by a process killed between creating
    and writing it (a run stopped while it compiled) would be read, fail with a warning and compile
    again in every later run. A written entry is never empty (a compressed executable).
    """
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return 0
    for entry in entries:
        try:
            if entry.is_file(follow_symlinks=False) and entry.stat().st_size == 0:
                os.remove(entry.path)
                removed += 1
        except OSError:  # (gone already, or not ours to remove: JAX will warn about it)
            continue
    return removed


#: JAX's event for an XLA program being compiled, or loaded from the persistent cache.
_BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"

#: XLA programs this process has compiled or loaded from the persistent cache (every thread, every
#: jitted function and eager op), and their seconds, from JAX's monitoring events: what
#: :func:`xla_compiles` reads.
_XLA_COMPILES = [0, 0.0]


def _on_duration(event: str, duration_secs: float, **_) -> None:
    if event == _BACKEND_COMPILE_EVENT:
        _XLA_COMPILES[0] += 1
        _XLA_COMPILES[1] += float(duration_secs)


jax.monitoring.register_event_duration_secs_listener(_on_duration)


def xla_compiles() -> tuple[int, float]:
    """(programs, seconds) XLA has compiled or loaded from the persistent cache in this process so
    far (see :data:`_XLA_COMPILES`): differences of two readings count a run's."""
    return int(_XLA_COMPILES[0]), float(_XLA_COMPILES[1])


class MapLimitReached(OSError):
    """The process holds nearly as many memory mappings as the kernel allows (see :class:`MapGuard`)."""


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


#: Callbacks run whenever this module clears JAX's caches: registries of jitted functions (e.g.
#: training's shared steps) forget what they hold, whose programs are then gone.
_ON_CLEAR: list = []


def on_clear(callback) -> None:
    """Registers ``callback()`` to run whenever :func:`release_compiled_code` or a :class:`MapGuard`
    clears JAX's compiled code."""
    _ON_CLEAR.append(callback)


def _clear_all() -> None:
    for callback in _ON_CLEAR:
        callback()
    jax.clear_caches()
    gc.collect()


#: Share of the memory-map cap under which the programs of a finished evaluation, or of a training
#: layout left behind, are kept for reuse (the next evaluation of a scene of the same shapes, a resumed
#: run, a study's next run take them instead of tracing and compiling again); above it they are
#: released (:func:`retire_programs`).
KEEP_SHARE = 0.25


def over_share(share: float) -> bool:
    """Whether this process holds more than ``share`` of its memory-map cap (False where /proc does
    not say)."""
    maps = memory_maps()
    return maps is not None and maps[0] > share * maps[1]


def release_compiled_code(threshold: float = 0.5) -> bool:
    """Clears JAX's compilation caches (``jax.clear_caches``, and the registries of :func:`on_clear`)
    and collects garbage when this process holds more than ``threshold`` of its memory-map cap;
    returns whether it did. ``threshold=0`` always clears."""
    if threshold > 0 and not over_share(threshold):
        return False
    _clear_all()
    return True


def program_count(fn) -> int:
    """Compiled programs a ``jax.jit`` function holds (0 where JAX does not say)."""
    size = getattr(fn, "_cache_size", None)
    n = size() if callable(size) else 0
    return int(n) if isinstance(n, int) else 0


def release_programs(*fns) -> None:
    """Drops the compiled programs of the given ``jax.jit`` functions (they compile again when next
    called); their mappings are returned to the kernel."""
    for fn in fns:
        clear = getattr(fn, "clear_cache", None)
        if callable(clear):
            clear()


def retire_programs(*fns) -> bool:
    """Releases the programs of ``fns`` (:func:`release_programs`) when this process holds more than
    :data:`KEEP_SHARE` of its memory-map cap, else keeps them for reuse; returns whether it released."""
    if not over_share(KEEP_SHARE):
        return False
    release_programs(*fns)
    return True


def trim_programs(*fns, max_programs: int = 8) -> bool:
    """Releases the programs of each function holding more than ``max_programs`` (JAX cannot drop
    single entries, so all of that function's); returns whether any was released. Bounds what a
    per-shape cache keeps, e.g. LPIPS or SSIM at every image size of an evaluation."""
    released = False
    for fn in fns:
        if program_count(fn) > max_programs:
            release_programs(fn)
            released = True
    return released


@dataclasses.dataclass
class MapGuard:
    """Watches this process's mapping count against the cap.

    Attributes:
      release_share: above this share of the cap, :meth:`check` drops all of JAX's compiled code
        (and calls ``on_release``, which should drop the caller's own jitted functions).
      stop_share: above this share even after releasing, :meth:`check` reports that the caller
        must stop.
      limit: the cap; None reads ``vm.max_map_count`` (a smaller value simulates a lower cap).
    """

    release_share: float = 0.5
    stop_share: float = 0.9
    limit: int | None = None

    def __post_init__(self):
        if not 0 < self.release_share <= self.stop_share:
            raise ValueError(f"MapGuard needs 0 < release_share <= stop_share, got {self.release_share} and "
                             f"{self.stop_share}.")

    def counts(self) -> tuple[int, int] | None:
        """(mappings held, the cap this guard applies), or None without /proc."""
        maps = memory_maps()
        if maps is None:
            return None
        return maps[0], self.limit if self.limit is not None else maps[1]

    def check(self, on_release=None) -> tuple[int, int] | None:
        """None while the process is within ``stop_share`` of the cap (after releasing compiled code
        above ``release_share``); else (mappings held, cap): the caller should save and stop."""
        maps = self.counts()
        if maps is None or maps[0] <= self.release_share * maps[1]:
            return None
        if on_release is not None:
            on_release()
        _clear_all()
        maps = self.counts()
        if maps is None or maps[0] <= self.stop_share * maps[1]:
            return None
        return maps


def limit_message(count: int, limit: int, what: str) -> str:
    """The explanation :class:`MapLimitReached` carries: what happened, ``what`` was done about it
    (e.g. where the checkpoint is and how to resume), and how to raise the cap."""
    return (f"this process holds {count:,} memory mappings, close to the kernel's limit of {limit:,} "
            "(vm.max_map_count): XLA keeps each compiled program's machine code in mappings of its own, and "
            f"one more compile could crash the process. {what} To allow more, raise the limit, e.g. "
            "`sudo sysctl -w vm.max_map_count=262144` (persist it in /etc/sysctl.d/), or run fewer runs "
            "per process.")
