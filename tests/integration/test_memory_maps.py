"""The process-level safeguards: compiled code is released before the memory-map cap, the persistent
compilation cache of the command lines is where the environment says, and importing
pycolmap leaves the fatal-signal handlers as they were."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

from patexgs_jax import memory_maps


@pytest.mark.skipif(memory_maps.memory_maps() is None, reason="needs /proc (Linux)")
def test_release_compiled_code_frees_mappings():
    memory_maps.release_compiled_code(threshold=0)
    base = memory_maps.memory_maps()[0]
    fns = [jax.jit(lambda x, k=k: jnp.cumsum(jnp.sin(x) * k)) for k in range(30)]
    for k, f in enumerate(fns):
        f(jnp.ones(64 + k)).block_until_ready()
    peak = memory_maps.memory_maps()[0]
    assert peak > base + 150, (base, peak)  # each executable holds mappings of its own
    assert not memory_maps.release_compiled_code(threshold=1.0)  # under the whole cap: nothing to do
    assert memory_maps.release_compiled_code(threshold=0)
    after = memory_maps.memory_maps()[0]
    # Released although the jitted functions are still alive: most of their mappings are returned.
    assert after < base + 0.3 * (peak - base), (base, peak, after)
    assert float(fns[3](jnp.ones(67))[-1]) == pytest.approx(3 * 67 * float(jnp.sin(1.0)), rel=1e-5)


_HANDLER = textwrap.dedent("""
    import ctypes, faulthandler, signal
    faulthandler.enable()

    class Act(ctypes.Structure):
        _fields_ = [("handler", ctypes.c_void_p), ("mask", ctypes.c_ulong * 16), ("flags", ctypes.c_int),
                    ("restorer", ctypes.c_void_p)]

    def handler(sig=signal.SIGSEGV):
        a = Act()
        assert ctypes.CDLL(None).sigaction(int(sig), None, ctypes.byref(a)) == 0
        return a.handler

    before = handler()
    before_term = handler(signal.SIGTERM)
    """)


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads glibc's sigaction")
def test_pycolmap_import_keeps_fatal_signal_handlers():
    # A bare import replaces faulthandler's SIGSEGV handler (the control: the check can fail) ...
    r = _python(_HANDLER + "import pycolmap\nprint(handler() == before)\n")
    assert r.returncode == 0 and r.stdout.strip() == "False", (r.stdout, r.stderr[-2000:])
    # ... the package's import keeps it.
    r = _python(_HANDLER + "import patexgs_jax.data.colmap, patexgs_jax.sfm\nprint(handler() == before)\n")
    assert r.returncode == 0 and r.stdout.strip() == "True", (r.stdout, r.stderr[-2000:])
    # SIGTERM too: glog's handler prints a native stack dump for a plain `kill` (the control first).
    r = _python(_HANDLER + "import pycolmap\nprint(handler(signal.SIGTERM) == before_term)\n")
    assert r.returncode == 0 and r.stdout.strip() == "False", (r.stdout, r.stderr[-2000:])
    r = _python(_HANDLER + "import patexgs_jax.data.colmap\nprint(handler(signal.SIGTERM) == before_term)\n")
    assert r.returncode == 0 and r.stdout.strip() == "True", (r.stdout, r.stderr[-2000:])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals")
def test_segfault_after_importing_the_loaders_crashes_with_a_python_traceback():
    r = _python(_HANDLER + "import patexgs_jax.data\nimport patexgs_jax.data.colmap\nctypes.string_at(0)\n")
    assert r.returncode == -11, (r.returncode, r.stderr[-2000:])
    assert "Fatal Python error: Segmentation fault" in r.stderr, r.stderr[-2000:]


def test_compile_cache_folder_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(memory_maps.COMPILE_CACHE_ENV, str(tmp_path / "mine"))
    assert memory_maps.compile_cache_dir() == tmp_path / "mine"
    for off in ("off", "0", "", "None"):
        monkeypatch.setenv(memory_maps.COMPILE_CACHE_ENV, off)
        assert memory_maps.compile_cache_dir() is None
    monkeypatch.delenv(memory_maps.COMPILE_CACHE_ENV)
    monkeypatch.setenv("PATEXGS_CACHE", str(tmp_path / "project"))
    assert memory_maps.compile_cache_dir() == tmp_path / "project" / "xla"
    monkeypatch.delenv("PATEXGS_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert memory_maps.compile_cache_dir() == tmp_path / "xdg" / "patexgs_jax" / "xla"


_CACHED_COMPILE = textwrap.dedent("""
    import jax, jax.numpy as jnp
    from patexgs_jax import memory_maps
    print(memory_maps.enable_compile_cache())
    jax.jit(lambda x: jnp.cumsum(jnp.sin(x)))(jnp.ones(8)).block_until_ready()
    """)


@pytest.mark.parametrize("setting", ["folder", "off"])
def test_command_lines_keep_compiled_programs(tmp_path, setting):
    """What the command lines call first: compiled programs are written to the per-user folder
    (empty entries found there removed), or nowhere with PATEXGS_COMPILE_CACHE=off; a folder JAX
    was already given wins."""
    import os

    folder = tmp_path / "cache"
    if setting == "folder":  # an entry a killed run left empty (JAX would never replace it) goes
        folder.mkdir()
        (folder / "jit_f-0123-cache").write_bytes(b"")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(PATEXGS_COMPILE_CACHE=str(folder) if setting == "folder" else "off",
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    r = subprocess.run([sys.executable, "-c", _CACHED_COMPILE], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    if setting == "off":
        assert r.stdout.strip() == "None" and not folder.exists()
        return
    assert r.stdout.strip() == str(folder)
    assert any(folder.iterdir()), "nothing was written to the cache folder"
    assert not (folder / "jit_f-0123-cache").exists()
    env.update(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "theirs"))
    r = subprocess.run([sys.executable, "-c", _CACHED_COMPILE], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0 and r.stdout.strip() == str(tmp_path / "theirs"), (r.stdout, r.stderr[-2000:])
