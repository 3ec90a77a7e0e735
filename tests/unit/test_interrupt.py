"""Stopping on SIGINT / SIGTERM (patexgs_jax.interrupt): the handler only sets a flag that the host
loop's check() raises on, an inherited ignored SIGINT is restored, the watchdog ends a process whose
main thread is stuck (as in a compile) with the stop line and 130 / 143, and the heartbeat speaks
after a silence."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from locations import REPO
from patexgs_jax import interrupt


@pytest.fixture(autouse=True)
def _long_grace(monkeypatch):
    # In this process the watchdog must never end pytest: the main thread has 30 s to reach check().
    monkeypatch.setenv(interrupt.GRACE_ENV, "30")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_sets_the_flag_that_check_raises_on(sig):
    before = signal.getsignal(sig)
    with interrupt.guard(resume="python -m patexgs_jax.train --out x --resume"):
        interrupt.set_phase("training the 2DGS stage")
        interrupt.set_step(7, 40)
        interrupt.set_saved("the checkpoint of step 7 in x/checkpoints")
        interrupt.check()  # nothing received yet: no-op
        os.kill(os.getpid(), sig)
        time.sleep(0.05)  # the Python-level handler runs between bytecodes
        assert interrupt.requested() == sig
        with pytest.raises(interrupt.Interrupted) as stop:
            interrupt.check()
        assert stop.value.signum == sig and interrupt.exit_code(sig) == {signal.SIGINT: 130,
                                                                          signal.SIGTERM: 143}[sig]
        line = interrupt.stop_line(sig)
    assert line == (f"stopped by {sig.name} while training the 2DGS stage (step 7 of 40); the work is in the "
                    "checkpoint of step 7 in x/checkpoints; continue with: python -m patexgs_jax.train --out x "
                    "--resume")
    assert signal.getsignal(sig) == before  # restored on the way out


def test_inherited_ignored_sigint_is_restored():
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with interrupt.guard():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            assert interrupt.requested() == signal.SIGINT
            with pytest.raises(interrupt.Interrupted):
                interrupt.check()
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, old)


def test_heartbeat_names_the_phase_after_a_silence(capsys, monkeypatch):
    monkeypatch.setenv(interrupt.HEARTBEAT_ENV, "0.5")
    with interrupt.guard():
        interrupt.set_phase("compiling the textured step for 48x32 px")
        time.sleep(1.6)
    out = capsys.readouterr().out
    assert re.search(r"^compiling the textured step for 48x32 px, [12] s so far$", out, re.M), out


STUCK = textwrap.dedent("""
    import os, signal, sys, time
    from pathlib import Path
    from patexgs_jax import interrupt
    marker = Path(sys.argv[1])
    with interrupt.guard(resume="python -m patexgs_jax.train --resume"):
        interrupt.set_phase("compiling the 2DGS step")
        with interrupt.cleanup_on_forced_exit(marker.touch):
            print("STUCK", flush=True)
            time.sleep(60)  # a call that does not return to the host loop (a compile)
    print("not reached", flush=True)
""")


@pytest.mark.parametrize("sig,second", [(signal.SIGTERM, False), (signal.SIGINT, True)])
def test_watchdog_ends_a_stuck_process_with_the_stop_line(tmp_path, sig, second):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), JAX_PLATFORMS="cpu",
               **{interrupt.GRACE_ENV: "30" if second else "0.5"})
    marker = tmp_path / "cleaned"
    proc = subprocess.Popen([sys.executable, "-c", STUCK, str(marker)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == "STUCK"
        t = time.time()
        proc.send_signal(sig)
        if second:  # a second signal ends it at once, whatever the grace
            time.sleep(0.3)
            proc.send_signal(sig)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + sig and time.time() - t < 10, (proc.returncode, err)
    assert err.strip() == (f"stopped by {sig.name} while compiling the 2DGS step; nothing was saved yet; "
                           "continue with: python -m patexgs_jax.train --resume"), err
    assert "not reached" not in out and marker.exists()


def test_no_stop_request_outlives_the_guard():
    with interrupt.guard():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        assert interrupt.requested() == signal.SIGTERM
    assert interrupt.requested() is None
    interrupt.check()  # library code after the command line's body (a test, the viewer) runs on


def _python(code: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          cwd=cwd, env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=120)


def test_ctrl_c_while_a_command_line_imports_gives_one_line(tmp_path):
    """Under ``python -m`` (runpy's sys.argv[0] == "-m" while the parent packages import), a
    KeyboardInterrupt before the command line's handlers ends with the one line and 130; a library
    import keeps Python's own behaviour; the command line's handlers take the hook out."""
    started = _python("""
        import sys
        sys.argv[0] = "-m"
        import patexgs_jax
        raise KeyboardInterrupt
    """, tmp_path)
    line = "stopped by SIGINT while starting; nothing was saved yet\n"
    assert started.returncode == 130 and started.stderr == line
    # A SIGINT that arrives inside an import (as in jaxlib's initialisation, where a KeyboardInterrupt
    # can end in a segmentation fault) ends the process from the handler, before any exception.
    (tmp_path / "slow_module.py").write_text("import os, signal, time\nos.kill(os.getpid(), signal.SIGINT)\n"
                                             "time.sleep(30)\nprint('not reached')\n")
    importing = _python("""
        import signal, sys
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as started from a terminal (not with &)
        sys.argv[0] = "-m"
        import patexgs_jax
        sys.path.insert(0, ".")
        import slow_module
    """, tmp_path)
    assert importing.returncode == 130 and importing.stderr == line
    for package in ("patexgs_jax", "experiments"):  # the studies' package installs it too
        probe = _python(f"""
            import sys
            sys.argv[0] = "-m"
            import {package}
            from patexgs_jax import _startup
            print(_startup.installed())
        """, tmp_path)
        assert probe.stdout.split() == ["True"], probe.stderr[-2000:]
    library = _python("""
        import patexgs_jax
        from patexgs_jax import _startup
        assert not _startup.installed()
        raise KeyboardInterrupt
    """, tmp_path)
    assert "Traceback" in library.stderr and library.returncode != 130
    handled = _python("""
        import sys
        sys.argv[0] = "-m"
        from patexgs_jax import _startup, interrupt
        interrupt.handle_stop_signals(lambda *_: None)
        print(_startup.installed())
    """, tmp_path)
    assert handled.stdout.split() == ["False"], handled.stderr[-2000:]
