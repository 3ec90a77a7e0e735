"""Shared test settings: tests import helpers from this folder; hypothesis keeps examples few
(each new shape costs a JAX compile on CPU) and has no deadline (compiles are slow)."""

import atexit
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time

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

from patexgs_jax import memory_maps  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))

# One persistent XLA compilation cache for the whole session: training runs build new jitted steps
# with the same programs (test_train, the studies), which then load instead of compiling again. Set
# before anything compiles (JAX decides once whether the cache is used). It was once switched off
# after "a hang in the compile-and-write-cache path"; that hang was the memory-map cap (see
# patexgs_jax.memory_maps), which _release_compiled_code below now keeps the session away from.
# The first process to load this file (pytest-xdist's controller, or pytest alone) picks the folder;
# xdist's workers inherit its path, so a program one worker compiled loads in the other. It is
# test-xla/ in the project's cache, $PATEXGS_CACHE (default $XDG_CACHE_HOME/patexgs_jax, i.e.
# ~/.cache/patexgs_jax), and is kept: the README's two test commands (the unit tier, then the
# integration tier) share it, and a developer's next run of a tier loads what the last one compiled
# (the unit tier 5 min 41 s cold, 3 min 18 s warm: docs/performance.md). JAX's keys hold the
# program, the compile options and the versions, so a changed tree only adds programs. CI sets a
# throw-away PATEXGS_CACHE, so it always runs cold. It is apart from the command lines' xla/ there:
# the tests' level-0 programs never serve a user's run. Every program is stored, however quick its
# compile (JAX's default stores those over 1 s): the suite's runs and workers compile many small
# programs again (tests/integration/test_mipnerf360.py alone: 249 -> 234 s).
_XLA_CACHE = os.environ.get("PATEXGS_TEST_XLA_CACHE")
if not _XLA_CACHE or not os.path.isdir(_XLA_CACHE):
    _XLA_CACHE = str(memory_maps.project_cache_root() / "test-xla")
    try:
        os.makedirs(_XLA_CACHE, exist_ok=True)
        # (JAX's own size cap needs the filelock package: a kept folder past 4 GiB starts afresh)
        if sum(e.stat().st_size for e in os.scandir(_XLA_CACHE) if e.is_file()) > 4 << 30:
            shutil.rmtree(_XLA_CACHE, ignore_errors=True)
            os.makedirs(_XLA_CACHE, exist_ok=True)
        memory_maps.drop_empty_entries(_XLA_CACHE)  # (what a killed run left would compile every time)
    except OSError:  # (no writable cache folder: a throw-away one, removed at exit)
        _XLA_CACHE = tempfile.mkdtemp(prefix="patexgs_xla_cache_")
        atexit.register(shutil.rmtree, _XLA_CACHE, ignore_errors=True)
    os.environ["PATEXGS_TEST_XLA_CACHE"] = _XLA_CACHE
jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
# The command lines turn on a per-user cache (patexgs_jax.memory_maps.enable_compile_cache); the ones
# the tests start, in this process or in subprocesses, use the session's instead, never that one.
os.environ["PATEXGS_COMPILE_CACHE"] = _XLA_CACHE

settings.register_profile("default", deadline=None, max_examples=10, derandomize=False)
settings.register_profile("ci", deadline=None, max_examples=10, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """After each module, free JAX's compiled code once the process holds a quarter of its
    memory-map cap (see patexgs_jax.memory_maps): a whole suite in one process compiles far more than
    the cap allows, and reaching it ended in a crash (or, with pycolmap's signal handler, a hang).
    The training steps that runs of one process share are released after every module, and so are
    the programs compiled ahead for runs that never came (a study's), so that what a module counts
    does not depend on which modules ran before it in its worker."""
    yield
    from patexgs_jax.training.steps import PROCESS

    PROCESS.release_steps()
    PROCESS.discard_prepared()
    memory_maps.release_compiled_code(threshold=0.25)


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


class _CompileProfile:
    """Where ``PATEXGS_TEST_PROFILE`` names a file, each test process appends one JSON line per
    test: its wall time (fixtures included) and the seconds JAX spent, while it ran, tracing
    (``trace``), lowering (``lower``), compiling (``compile``) and loading programs from the
    persistent cache (``load``), with their counts (``traces``, ...). Compiles in background threads
    (compiling ahead) count to the running test; subprocesses' are not seen (their time is in
    ``wall`` only). ``python tests/profile_summary.py FILE`` sums it per file (docs/performance.md)."""

    _EVENTS = {"jaxpr_trace_duration": "trace", "jaxpr_to_mlir_module_duration": "lower",
               "backend_compile_duration": "compile", "cache_retrieval_time_sec": "load"}

    def __init__(self, path: str):
        self.path = path
        self.acc: dict[str, float] = {}
        jax.monitoring.register_event_duration_secs_listener(self._event)

    def _event(self, name, secs, **kw):
        key = self._EVENTS.get(name.rsplit("/", 1)[-1])
        if key is not None:
            self.acc[key] = self.acc.get(key, 0.0) + secs
            self.acc[key + "s"] = self.acc.get(key + "s", 0) + 1

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        self.acc, t = {}, time.monotonic()
        yield
        rec = dict(test=item.nodeid, wall=round(time.monotonic() - t, 2), pid=os.getpid(),
                   **{k: round(v, 2) if isinstance(v, float) else v for k, v in self.acc.items()})
        with open(self.path, "a") as f:
            f.write(json.dumps(rec) + "\n")


class _Heartbeat:
    """Prints a line when a minute passes without one (``-q`` prints a dot per test, nothing while
    one runs), naming the tests that are running and for how long: a long test is then told from a
    hung one. Runs in pytest-xdist's controller; ``PATEXGS_TEST_HEARTBEAT_S``
    sets the period."""

    def __init__(self, config, period: float):
        self.reporter = config.pluginmanager.get_plugin("terminalreporter")
        self.period = period
        self.running: dict[str, float] = {}
        self.last = self.last_result = time.monotonic()  # (the last line printed; the last result)
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._beat, name="test-heartbeat", daemon=True)

    def pytest_sessionstart(self, session):
        self.thread.start()

    def pytest_sessionfinish(self, session):
        self.done.set()

    def pytest_runtest_logstart(self, nodeid, location):
        with self.lock:
            self.running[nodeid] = time.monotonic()

    def pytest_runtest_logreport(self, report):
        with self.lock:
            if report.when == "call" or report.outcome != "passed":  # (what -q prints a character for)
                self.last = self.last_result = time.monotonic()
            if report.when == "teardown":
                self.running.pop(report.nodeid, None)

    def _beat(self):
        while not self.done.wait(1.0):
            with self.lock:
                now = time.monotonic()
                if now - self.last < self.period or self.reporter is None:
                    continue
                self.last = now
                tests = ", ".join(f"{n} ({now - t:.0f} s)" for n, t in sorted(self.running.items(), key=lambda x: x[1]))
            self.reporter.write_line(f"[{now - self.last_result:.0f} s without a result; running: "
                                     f"{tests or 'no test yet'}]")


#: XLA's CPU fusion emitters (MLIR, on by default in jax 0.10) take twice the compile time of the
#: older LLVM emitters on the renderer's programs (a float64 render + gradient: 6.6 s with them, 3.3 s
#: without; tests/unit/test_render.py + test_coverage.py 206 -> 116 s in one process, the unit tier
#: 11 min 11 s -> 5 min 47 s with two workers, on this project's 2-core AMD EPYC). The suite's checks
#: hold with either (those comparing two programs allow float32 rounding; docs/performance.md).
#: Users' runs keep XLA's defaults.
OLDER_EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _xla_accepts(flag: str) -> bool:
    """Whether this jaxlib's XLA knows ``flag``: an unknown XLA_FLAGS entry aborts the process that
    starts a backend, so a jaxlib without the older emitters runs the suite with its defaults."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + flag).strip())
    try:
        done = subprocess.run([sys.executable, "-c", "import jax; jax.numpy.zeros(1).block_until_ready()"],
                              env=env, capture_output=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


@pytest.hookimpl(trylast=True)  # (after the terminal reporter is made)
def pytest_configure(config):
    # (before any test starts JAX's backend; pytest-xdist's workers, started later, inherit it, and
    # so do the subprocesses tests start; an explicit setting in XLA_FLAGS is kept)
    flags = os.environ.get("XLA_FLAGS", "")
    if OLDER_EMITTERS_FLAG.split("=")[0] not in flags and _xla_accepts(OLDER_EMITTERS_FLAG):
        os.environ["XLA_FLAGS"] = (flags + " " + OLDER_EMITTERS_FLAG).strip()
    # (pytest-xdist's controller runs no test: the heartbeat runs there, where nothing captures what
    # it prints, and the profile in the processes that run tests)
    controller = bool(getattr(config.option, "numprocesses", None)) and not hasattr(config, "workerinput")
    if controller and config.pluginmanager.get_plugin("terminalreporter") is not None:
        period = float(os.environ.get("PATEXGS_TEST_HEARTBEAT_S", "60"))
        config.pluginmanager.register(_Heartbeat(config, period), "patexgs-heartbeat")
    if os.environ.get("PATEXGS_TEST_PROFILE") and not controller:
        config.pluginmanager.register(_CompileProfile(os.environ["PATEXGS_TEST_PROFILE"]), "patexgs-profile")
