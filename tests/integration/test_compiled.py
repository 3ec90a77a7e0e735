"""The process-level safeguards: compiled code is released before the memory-map cap, and importing
pycolmap leaves the fatal-signal handlers as they were."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

from patexgs_jax import compiled


@pytest.mark.skipif(compiled.memory_maps() is None, reason="needs /proc (Linux)")
def test_release_compiled_code_frees_mappings():
    compiled.release_compiled_code(threshold=0)
    base = compiled.memory_maps()[0]
    fns = [jax.jit(lambda x, k=k: jnp.cumsum(jnp.sin(x) * k)) for k in range(30)]
    for k, f in enumerate(fns):
        f(jnp.ones(64 + k)).block_until_ready()
    peak = compiled.memory_maps()[0]
    assert peak > base + 150, (base, peak)  # each executable holds mappings of its own
    assert not compiled.release_compiled_code(threshold=1.0)  # under the whole cap: nothing to do
    assert compiled.release_compiled_code(threshold=0)
    after = compiled.memory_maps()[0]
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
    r = _python(_HANDLER + "import patexgs_jax.data.colmap, patexgs_jax.prepare\nprint(handler() == before)\n")
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
