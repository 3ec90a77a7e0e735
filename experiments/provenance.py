"""Where a measurement comes from: the code's git commit, the date, the machine and the JAX version.

Every benchmark JSON file is written by :func:`write_benchmark_json`, so each carries the same
header (a figure without the commit and machine it was measured on cannot be compared later)::

    {"schema": int, "git": str | null, "date": "YYYY-MM-DDTHH:MM:SSZ", "machine": str,
     "cpu": str, "cpus": int, "jax": str, "backend": str, "devices": int, "device": str, ...extra,
     "results": [...]}

``device`` is the first device's kind (e.g. "NVIDIA H100 80GB HBM3", or "cpu"). ``git`` is the
short commit hash, with ``-dirty`` when tracked files differ from it (the figures then measure
uncommitted code), null outside a git checkout.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from pathlib import Path

__all__ = ["git_commit", "header", "write_benchmark_json", "write_json"]

_REPO = Path(__file__).resolve().parent


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=_REPO, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_commit() -> str | None:
    """The checkout's short commit hash, ``-dirty`` appended when tracked files are modified; None
    outside a git checkout (an installed copy)."""
    head = _git("rev-parse", "--short", "HEAD")
    if not head:
        return None
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return head + ("-dirty" if dirty else "")


def _cpu_name() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux), else what ``platform`` says."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def header(schema: int) -> dict:
    """The provenance fields of a benchmark file (see the module docstring)."""
    import jax

    now = datetime.datetime.now(datetime.UTC).replace(microsecond=0)
    return dict(schema=schema, git=git_commit(), date=now.strftime("%Y-%m-%dT%H:%M:%SZ"),
                machine=platform.platform(), cpu=_cpu_name(), cpus=os.cpu_count(), jax=jax.__version__,
                backend=jax.default_backend(), devices=len(jax.devices()),
                device=str(getattr(jax.devices()[0], "device_kind", jax.default_backend())))


def write_json(path, obj) -> Path:
    """Writes ``obj`` as JSON to ``path`` atomically: a reader never sees half a file, and an
    interrupted study or sweep keeps its last complete write. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1))
    os.replace(tmp, path)
    return path


def write_benchmark_json(path, results: list, schema: int, **extra) -> Path:
    """Writes ``{header(schema), **extra, "results": results}`` to ``path`` with :func:`write_json`.
    Returns the path."""
    return write_json(path, dict(header(schema), **extra, results=results))
