"""Where derived data (undistorted images) is cached, and folders built atomically there."""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import time
import uuid
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_build_dir", "fingerprint", "is_complete_dir", "resolve_cache_dir"]

_CACHE_ENV = "PATEXGS_CACHE"
_SCENE_CACHE_NAME = ".patexgs_cache"


def _is_writable_dir(path: Path) -> bool:
    """Writable by permission bits *and* by access check (root ignores bits; we do not)."""
    try:
        st = path.stat()
    except OSError:
        return False
    if not stat.S_ISDIR(st.st_mode):
        return False
    if not st.st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH):
        return False
    return os.access(path, os.W_OK)


def _user_cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "patexgs_jax"


def resolve_cache_dir(scene: Path, cache_dir=None) -> Path:
    """The folder where derived data (undistorted images) of ``scene`` is cached.

    In order of precedence:

    1. ``cache_dir`` (argument) -> ``<cache_dir>/<scene name>-<hash of the absolute scene path>``;
    2. the ``PATEXGS_CACHE`` environment variable, used the same way;
    3. ``<scene>/.patexgs_cache`` when the scene folder is writable (by its permission bits too: a
       read-only dataset folder is never written, even by root);
    4. ``$XDG_CACHE_HOME/patexgs_jax/<scene name>-<hash>`` (default ``~/.cache/patexgs_jax/...``).

    The folder is not created here.
    """
    scene = Path(scene).resolve()
    key = f"{scene.name}-{hashlib.sha1(str(scene).encode()).hexdigest()[:12]}"
    if cache_dir is not None:
        return Path(cache_dir).expanduser().resolve() / key
    env = os.environ.get(_CACHE_ENV)
    if env:
        return Path(env).expanduser().resolve() / key
    own = scene / _SCENE_CACHE_NAME
    if own.is_dir() and _is_writable_dir(own):
        return own
    if not own.exists() and _is_writable_dir(scene):
        return own
    return _user_cache_root() / key


def atomic_build_dir(final: Path, build: Callable[[Path], None]) -> Path:
    """Creates folder ``final`` by running ``build(tmp)`` into a temporary sibling, then renaming.

    Nothing partial is left at ``final`` if ``build`` fails or the process is interrupted (a stray
    ``.tmp-*`` sibling may remain after a hard kill; it is ignored and removed by later builds).
    If another process created ``final`` first, its result is kept.

    Returns:
      ``final``.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    for stale in final.parent.glob(f".tmp-{final.name}-*"):
        # Remove leftovers of interrupted builds that are older than an hour (others may be live).
        try:
            if time.time() - stale.stat().st_mtime > 3600:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:
            pass
    tmp = final.parent / f".tmp-{final.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        build(tmp)
        (tmp / "COMPLETE").write_text("ok\n")
        try:
            os.rename(tmp, final)
        except OSError:
            if (final / "COMPLETE").is_file():  # lost a race: keep the other result
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def is_complete_dir(path: Path) -> bool:
    """Whether ``path`` is a finished :func:`atomic_build_dir` result."""
    return (Path(path) / "COMPLETE").is_file()


def fingerprint(*parts) -> str:
    """Short stable hash of strings / paths (files contribute name, size and mtime)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, Path):
            try:
                st = p.stat()
                h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
            except OSError:
                h.update(f"{p}|missing".encode())
        else:
            h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()[:16]
