"""Killing training with SIGKILL: at random points and in the middle of a checkpoint
write, a resumed run always finds a complete checkpoint and continues to the end. Stopping it with
SIGINT / SIGTERM in each phase: one line, exit status 130 / 143, and ``--resume`` reaches the result
of an uninterrupted run.

The runs are real subprocesses (``python -m patexgs_jax.train``-like script below) on a tiny
synthetic scene; they share a persistent compilation cache, so only the first one compiles.
A cheap, JAX-free companion kills a process that saves checkpoints in a loop at random moments.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from locations import REPO
from patexgs_jax import checkpoint as ckpt

TRAIN_SCRIPT = textwrap.dedent("""
    import os, sys, time
    import numpy as np
    from patexgs_jax import checkpoint as ckpt
    from patexgs_jax.data import load
    from patexgs_jax.densify import DensifyConfig
    from patexgs_jax.training import TrainConfig, train
    from patexgs_jax.training.trainer import Trainer

    scene_dir, out = sys.argv[1], sys.argv[2]
    if os.environ.get("SLOW_CHECKPOINT_WRITES"):
        # Stretch every checkpoint write so that a kill can land inside one (announced on stdout).
        from patexgs_jax import checkpoint_members as ckpt_module
        real = ckpt_module.write_npy  # (each array member of a checkpoint is written by it, in the writer's thread)
        def slow(*a, **k):
            print("WRITING", flush=True)
            time.sleep(0.05)
            return real(*a, **k)
        ckpt_module.write_npy = slow
    cfg = TrainConfig(method="2dgs", iters_2dgs=16, checkpoint_every=2, log_every=2, max_gaussians=300,
                        sh_degree=1, sh_interval=4,
                        densify=DensifyConfig(start=10_000, stop=10_001, opacity_reset_interval=10_000))
    ds = load(scene_dir, factor=1, test_every=5, verbose=False)
    orig = Trainer.after_step
    def after_step(self, step):
        orig(self, step)
        print("STEP", step, flush=True)
    Trainer.after_step = after_step
    res = train(ds, cfg, out, resume=True, verbose=False)
    print("DONE", res.summary["steps"], flush=True)
""")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    from patexgs_jax.data.synthetic import generate

    return generate(tmp_path_factory.mktemp("kill_scene") / "scene", seed=0, num_views=6, width=48, height=32,
                    num_points=300)


def start(script: str, args, env_extra: dict, tmp: Path, **popen):
    path = tmp / "child.py"
    path.write_text(script)
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               **env_extra)
    return subprocess.Popen([sys.executable, str(path), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=REPO, **popen)


def kill_when(proc, predicate, timeout=300.0) -> list[str]:
    """Reads the child's stdout lines until ``predicate(lines)`` holds, then SIGKILLs it.
    Returns the lines seen. Fails if the child exits first or the timeout passes."""
    lines = []
    t0 = time.time()
    try:
        for line in proc.stdout:
            lines.append(line.strip())
            if predicate(lines):
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=60)
                assert proc.returncode == -signal.SIGKILL
                return lines
            assert time.time() - t0 < timeout, "child too slow"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    raise AssertionError(f"child exited ({proc.wait()}) before it was killed: {lines[-5:]}\n"
                         f"{proc.stderr.read()[-3000:]}")


def assert_resumable(out: Path) -> int:
    """The newest checkpoint is complete and loadable; returns its step (-1: none yet)."""
    d = out / "checkpoints"
    latest = ckpt.latest_checkpoint(d)
    for p in ckpt.list_checkpoints(d):  # every visible checkpoint is complete: partial ones stay hidden
        ckpt.verify_checkpoint(p)
    if latest is None:
        return -1
    tree, meta = ckpt.load_checkpoint(latest)
    assert int(np.asarray(tree["counters"])[0]) == meta["step"]
    assert all(np.all(np.isfinite(np.asarray(x))) for x in
               __import__("jax").tree_util.tree_leaves(tree["scene"]))
    return int(meta["step"])


@pytest.mark.slow
def test_sigkill_anywhere_then_resume_to_the_end(scene_dir, tmp_path):
    rng = np.random.default_rng(int(os.environ.get("KILL_SEED", "0")))
    out = tmp_path / "run"
    env = dict(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax_cache"), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    # 1. Killed inside a checkpoint write (a random array of one of the first checkpoints).
    writes = {"n": 0, "target": int(rng.integers(2, 30))}  # some array of one of the first checkpoints

    def in_write(lines):
        writes["n"] += lines[-1] == "WRITING"
        return writes["n"] == writes["target"]

    lines = kill_when(start(TRAIN_SCRIPT, [scene_dir, out], dict(env, SLOW_CHECKPOINT_WRITES="1"), tmp_path),
                      in_write)
    assert lines[-1] == "WRITING"
    step1 = assert_resumable(out)
    # 2. Killed at a random step of the resumed run (after its first completed step).
    target = int(rng.integers(max(step1, 0) + 2, 15))
    lines = kill_when(start(TRAIN_SCRIPT, [scene_dir, out], env, tmp_path),
                      lambda ls: ls[-1] == f"STEP {target}")
    step2 = assert_resumable(out)
    assert step2 >= step1 and step2 >= target - 2
    # 3. Resumed to the end.
    proc = start(TRAIN_SCRIPT, [scene_dir, out], env, tmp_path)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr[-3000:]
    assert stdout.strip().splitlines()[-1] == "DONE 16"
    steps = [int(ln.split()[1]) for ln in stdout.splitlines() if ln.startswith("STEP")]
    assert steps == list(range(step2 + 1, 17))  # continued from the checkpoint, not from scratch
    assert assert_resumable(out) == 16
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 16 and np.isfinite(summary["train_psnr"])


SAVE_LOOP = textwrap.dedent("""
    import sys
    import numpy as np
    from patexgs_jax import checkpoint as ckpt
    d = sys.argv[1]
    rng = np.random.default_rng(0)
    big = rng.normal(size=(64, 1024)).astype(np.float32)  # 256 KiB per array
    step = len(ckpt.list_checkpoints(d)) and ckpt.read_metadata(ckpt.latest_checkpoint(d))["step"]
    while True:
        step += 1
        ckpt.save_checkpoint(ckpt.checkpoint_path(d, step), {"a": big + step, "b": [big * step] * 3, "step": step},
                             {"step": step}, keep=2)
        print("SAVED", step, flush=True)
""")


def test_sigkill_during_checkpoint_loop(tmp_path):
    """A process saving checkpoints back to back, killed at random moments (mostly mid-write):
    the newest visible checkpoint is always complete, consistent and at most one save behind."""
    rng = np.random.default_rng(1)
    d = tmp_path / "ckpts"
    last = 0
    for _ in range(4):
        proc = start(SAVE_LOOP, [d], {}, tmp_path)
        try:
            first = proc.stdout.readline()
            assert first.startswith("SAVED"), proc.stderr.read()[-2000:]
            time.sleep(float(rng.uniform(0.0, 0.3)))
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
            seen = [int(first.split()[1])] + [int(ln.split()[1]) for ln in proc.stdout.read().split("\n") if ln]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        latest = ckpt.latest_checkpoint(d)
        assert latest is not None
        tree, meta = ckpt.load_checkpoint(latest)
        step = meta["step"]
        assert step >= max(seen) and step >= last  # reported saves are durable; nothing goes back
        assert tree["step"] == step and np.allclose(tree["a"] - tree["b"][2] / step, step, atol=1e-3)
        assert len(ckpt.list_checkpoints(d)) <= 3
        last = step


# ------------------------------------------------------------------------------------------------
# SIGINT / SIGTERM: the command line stops cleanly in every phase and --resume finishes the run.
# ------------------------------------------------------------------------------------------------
# Runs `python -m patexgs_jax.train` with one phase stretched (announced on stdout) so that a signal
# lands inside it: decoding the images, evaluating the views (after each), writing scene.ply (longer
# than the stop grace, so the watchdog ends it).
STRETCH = textwrap.dedent("""
    import os, runpy, signal, sys, time
    if os.environ.get("IGNORE_SIGINT"):  # as inherited from a script that started the job with `&`
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    phase = os.environ.get("STRETCH_PHASE")
    if phase == "images":
        import patexgs_jax.data as data
        real_decode = data.decode_problem
        def decode(path):
            print("DECODING", flush=True)
            time.sleep(0.3)
            return real_decode(path)
        data.decode_problem = decode
    elif phase == "evaluation":
        import patexgs_jax.evaluation as evaluation
        real_view = evaluation._evaluate_view
        def view(*a, **k):
            real_view(*a, **k)
            print("EVALUATED", flush=True)
            time.sleep(0.5)
        evaluation._evaluate_view = view
    elif phase == "export":
        import patexgs_jax.export as export
        def slow_export(*a, **k):
            print("EXPORTING", flush=True)
            time.sleep(30)
        export.export_ply = slow_export
    module = os.environ.get("STRETCH_MODULE", "patexgs_jax.train")
    sys.argv = [module] + sys.argv[1:]
    runpy.run_module(module, run_name="__main__")
""")

TRAIN_ARGS = ["--method", "2dgs", "--preset", "tiny", "--iters-2dgs", "24", "--iters-tex", "0", "--log-every", "2",
              "--max-gaussians", "300", "--checkpoint-on-stop", "0"]


def _stop_env(cache: Path) -> dict:
    return dict(JAX_COMPILATION_CACHE_DIR=str(cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                PATEXGS_HEARTBEAT="0.5", PATEXGS_STOP_GRACE="1")


def _signal_on(proc, marker: str, sig: int, timeout: float = 300.0) -> tuple[list[str], str, float]:
    """Sends ``sig`` once a stdout line contains ``marker``; returns the stdout lines, the stderr and
    the seconds from the signal to the exit."""
    lines, t0 = [], time.time()
    try:
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            if marker in line:
                sent = time.time()
                proc.send_signal(sig)
                rest, err = proc.communicate(timeout=60)
                return lines + rest.splitlines(), err, time.time() - sent
            assert time.time() - t0 < timeout, "child too slow"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    raise AssertionError(f"child exited ({proc.wait()}) before {marker!r}: {lines[-5:]}\n{proc.stderr.read()[-3000:]}")


def _stopped(err: str, code: int, sig: int, where: str, kept: str) -> str:
    """The stop's stderr holds one line (no traceback, no native stack dump) naming the signal, the
    phase, what holds the work and the resume command; returns that command."""
    assert code == 128 + sig, (code, err[-3000:])
    assert "Traceback" not in err and "SIGTERM received" not in err and "*** " not in err, err[-3000:]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err[-3000:]
    line = lines[0]
    assert line.startswith(f"stopped by {signal.Signals(sig).name} while {where}"), line
    assert kept in line, (kept, line)
    command = line.split("; continue with: ", 1)[1]
    assert command.startswith("python -m patexgs_jax.train ") and command.endswith(" --resume"), line
    return command


def test_stop_before_any_work_leaves_nothing_behind(scene_dir, tmp_path):
    """Stopped while it decodes the images (before anything is compiled or written): one line with
    the command that starts it again, 130, and no --out folder."""
    out = tmp_path / "run"
    args = ["--data", str(scene_dir), "--out", str(out), *TRAIN_ARGS]
    proc = start(STRETCH, args, dict(_stop_env(tmp_path / "cache"), STRETCH_PHASE="images"), tmp_path)
    lines, err, dt = _signal_on(proc, "DECODING", signal.SIGINT)
    command = _stopped(err, 130, signal.SIGINT, "checking the 6 images (1 of 6 images done)", "nothing was saved yet")
    assert command == "python -m patexgs_jax.train " + " ".join(args) + " --resume"
    assert not out.exists() and dt < 10


@pytest.mark.slow
def test_stop_signal_in_every_phase_then_resume_matches_an_uninterrupted_run(scene_dir, tmp_path):
    out, ref = tmp_path / "run", tmp_path / "ref"
    args = ["--data", str(scene_dir), "--out", str(out), *TRAIN_ARGS]
    cache = tmp_path / "jax_cache"

    def child(env_extra, cache_dir=cache, resume=False):
        return start(STRETCH, args + ["--resume"] * resume, dict(_stop_env(cache_dir), **env_extra), tmp_path)

    # Compiling the first step (a cold cache): the watchdog ends it without waiting for XLA.
    lines, err, dt = _signal_on(child({}, cache_dir=tmp_path / "cold_cache"), "compiling the 2DGS step",
                                signal.SIGTERM)
    _stopped(err, 143, signal.SIGTERM, "compiling the 2DGS step", "nothing was saved yet")
    assert not out.exists() and dt < 10
    # Training, started with SIGINT ignored (a job started with `&` by a script): the stop writes a
    # checkpoint of the step it stopped at.
    lines, err, dt = _signal_on(child(dict(IGNORE_SIGINT="1")), "step      4/24", signal.SIGINT)
    _stopped(err, 130, signal.SIGINT, "training the 2DGS stage (step", "the checkpoint of step")
    step = assert_resumable(out)
    assert 4 <= step < 24 and f"the checkpoint of step {step} in {out / 'checkpoints'}" in err
    # Evaluating (after training: the final checkpoint holds the work), resumed.
    lines, err, dt = _signal_on(child(dict(STRETCH_PHASE="evaluation"), resume=True), "EVALUATED", signal.SIGTERM)
    assert f"resuming from {ckpt.checkpoint_path(out / 'checkpoints', step)} at step {step}" in lines
    _stopped(err, 143, signal.SIGTERM, "evaluating the training views", "the checkpoint of step 24")
    assert dt < 10
    # Writing scene.ply (longer than the stop grace: the watchdog ends it).
    lines, err, dt = _signal_on(child(dict(STRETCH_PHASE="export"), resume=True), "EXPORTING", signal.SIGINT)
    command = _stopped(err, 130, signal.SIGINT, f"writing {out / 'scene.ply'}", "the checkpoint of step 24")
    assert dt < 10
    # The printed command finishes the run, as an uninterrupted run does.
    env = dict(os.environ, JAX_PLATFORMS="cpu", **_stop_env(cache),
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, *command.split()[1:]], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    whole = subprocess.run([sys.executable, "-m", "patexgs_jax.train", "--data", str(scene_dir), "--out", str(ref),
                            *TRAIN_ARGS], capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert whole.returncode == 0, whole.stderr[-3000:]
    said = whole.stdout.splitlines()
    start_line = "training 2dgs: 5 training and 1 test views of 48x32 px; preset tiny, 24 2DGS steps; at most 300 " \
                 "Gaussians; on cpu ("
    assert any(ln.startswith(start_line) for ln in said), said
    assert any(ln.startswith("estimated time: ") and " for the " in ln for ln in said), said
    records = [json.loads(ln) for ln in (ref / "log.jsonl").read_text().splitlines()]
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", r["time"]) for r in records)
    assert all(0 < a["elapsed_s"] <= b["elapsed_s"] for a, b in zip(records, records[1:]))
    assert (out / "scene.ply").read_bytes() == (ref / "scene.ply").read_bytes()
    got, want = (json.loads((d / "summary.json").read_text()) for d in (out, ref))
    assert got["steps"] == want["steps"] == 24 and got["train_psnr"] == want["train_psnr"]


def test_study_stops_cleanly_with_the_command_that_continues_it(scene_dir, tmp_path):
    """`python -m experiments.mipnerf360` stopped while it checks a scene's images: one line, 130,
    and the same command (a study continues where it stopped when run again)."""
    args = ["--data", str(scene_dir), "--out", str(tmp_path / "study"), "--no-lpips", "--no-compile-cache"]
    proc = start(STRETCH, args, dict(_stop_env(tmp_path / "cache"), STRETCH_PHASE="images",
                                     STRETCH_MODULE="experiments.mipnerf360"), tmp_path)
    lines, err, dt = _signal_on(proc, "DECODING", signal.SIGINT)
    assert proc.returncode == 130 and "Traceback" not in err and dt < 10, err[-3000:]
    assert err.strip() == ("stopped by SIGINT while checking the 6 images of scene scene (1 of 6 images done); "
                           "nothing was saved yet; continue with: python -m experiments.mipnerf360 " + " ".join(args))
