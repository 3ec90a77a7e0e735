"""Shared test settings: tests import helpers from this folder; hypothesis keeps examples few
(each new shape costs a JAX compile on CPU) and has no deadline (compiles are slow)."""

import atexit
import os
import shutil
import sys
import tempfile

# The suite compiles far more than it runs (hundreds of small programs, most run a few times), and
# on the CPU most of a compile is LLVM optimising the generated code. Level 0 gives the same
# programs (XLA's graph passes still run; only the machine code is less optimised): the slowest
# files took 27% less CPU time, and results agree to float32 rounding (the literal-mode golden
# test's tolerance covers it). Set before JAX starts its backend; subprocesses inherit it; an
# explicit level in XLA_FLAGS (e.g. 3, what users get) is kept.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

# On a GPU every process would otherwise reserve 75% of its memory at start, and the second test
# worker (or a subprocess a test starts) would fail with out-of-memory: allocate on demand instead.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

from patexgs_jax import compiled  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))

# One persistent XLA compilation cache for the whole session: training runs build new jitted steps
# with the same programs (test_train, the studies), which then load instead of compiling again. Set
# before anything compiles (JAX decides once whether the cache is used). It was once switched off
# after "a hang in the compile-and-write-cache path"; that hang was the memory-map cap (see
# patexgs_jax.compiled), which _release_compiled_code below now keeps the session away from.
# The first process to load this file (pytest-xdist's controller, or pytest alone) makes the cache
# and removes it at exit; xdist's workers inherit its path, so a program one worker compiled loads in
# the other.
_XLA_CACHE = os.environ.get("PATEXGS_TEST_XLA_CACHE")
if not _XLA_CACHE or not os.path.isdir(_XLA_CACHE):
    _XLA_CACHE = os.environ["PATEXGS_TEST_XLA_CACHE"] = tempfile.mkdtemp(prefix="patexgs_xla_cache_")
    atexit.register(shutil.rmtree, _XLA_CACHE, ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
# The command lines turn on a per-user cache (patexgs_jax.compiled.enable_compile_cache); the ones
# the tests start, in this process or in subprocesses, use the session's instead, never ~/.cache.
os.environ["PATEXGS_COMPILE_CACHE"] = _XLA_CACHE

settings.register_profile("default", deadline=None, max_examples=10, derandomize=False)
settings.register_profile("ci", deadline=None, max_examples=10, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """After each module, free JAX's compiled code once the process holds a quarter of its
    memory-map cap (see patexgs_jax.compiled): a whole suite in one process compiles far more than
    the cap allows, and reaching it ended in a crash (or, with pycolmap's signal handler, a hang)."""
    yield
    compiled.release_compiled_code(threshold=0.25)


@pytest.fixture(scope="module")
def viewer_scene():
    """The viewer tests' textured scene (tests/viewer_scenes.py)."""
    from viewer_scenes import textured_scene

    return textured_scene()


@pytest.fixture(scope="module")
def viewer_run_dir(viewer_scene, tmp_path_factory):
    """A study of two runs holding ``viewer_scene``: its ``runs/toy/patexgs`` folder."""
    from viewer_scenes import study_of_two_runs

    return study_of_two_runs(tmp_path_factory.mktemp("viewer"), viewer_scene)
