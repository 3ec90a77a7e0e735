"""Training across processes (``jax.distributed``): two processes on 127.0.0.1, one CPU device each.

Every run is the training CLI on a small synthetic scene (the training tests' 48 x 32, 10 views; method 2dgs,
``--batch-size 2``, STEPS steps, a checkpoint every 2 steps, a log record every step), started by
the test with a bounded wait and killed by it on any failure; the runs share one persistent
compilation cache. Three runs (the fewest that cover the checks; the first two run at the same time):

* ``ref``: one process with 2 CPU devices (``--devices 2``);
* ``killed``: two processes (``--coordinator 127.0.0.1:PORT --num-processes 2 --process-id 0/1``);
  process 1 is SIGKILLed once process 0 has written the checkpoint of step 2, and process 0 must
  stop with a clear error within KILL_TIMEOUT seconds;
* ``resumed``: the same two processes started again with ``--resume``, run to the end in the same
  output folder. Its losses and final state are compared with ``ref``'s: two processes, through a
  kill and a resume, must give what one process with two devices gives uninterrupted.

Tolerances: one process with 2 devices and two processes with 1 device each run the same
per-device program and add the same two gradients (an all-reduce of two terms is exact whatever
its order), so losses and parameters agree to float32 rounding; the bounds allow 1e-6 relative.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from locations import REPO
from patexgs_jax import checkpoint as ckpt
from train_configs import SCENE_H, SCENE_W

STEPS = 6
RUN_TIMEOUT = 600.0  # seconds for one run (compiles on a loaded 2-core machine)
KILL_TIMEOUT = 60.0  # seconds for the survivor to stop after the other process was killed
TRAIN_ARGS = ["--method", "2dgs", "--iters-2dgs", STEPS, "--iters-tex", 0, "--max-gaussians", 500, "--batch-size", 2,
              "--checkpoint-every", 2, "--log-every", 1]


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(cache: Path) -> dict:
    env = dict(os.environ)
    # One CPU device per process: no forced device count (the suite's other XLA flags stay).
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split()
                                if not f.startswith("--xla_force_host_platform_device_count"))
    # The repository first on the path: the processes import this checkout wherever the package is installed.
    path = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=path, JAX_COMPILATION_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")
    return env


@contextlib.contextmanager
def _processes(argvs, cache: Path, log_dir: Path):
    """Starts one ``python -m patexgs_jax.train`` per argument list (stdout and stderr to files in
    ``log_dir``); yields the Popen objects; kills whatever still runs on the way out."""
    procs = []
    try:
        for i, argv in enumerate(argvs):
            out = open(log_dir / f"p{i}.out", "w")
            err = open(log_dir / f"p{i}.err", "w")
            procs.append(subprocess.Popen([sys.executable, "-m", "patexgs_jax.train", *map(str, argv)], cwd=REPO,
                                          env=_env(cache), stdout=out, stderr=err))
            out.close(), err.close()
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        for p in procs:
            p.wait(timeout=30)


def _wait(procs, timeout: float) -> list[int]:
    deadline = time.monotonic() + timeout
    for p in procs:
        p.wait(timeout=max(1.0, deadline - time.monotonic()))
    return [p.returncode for p in procs]


def _outputs(log_dir: Path, i: int) -> tuple[str, str]:
    return (log_dir / f"p{i}.out").read_text(), (log_dir / f"p{i}.err").read_text()


def _pair_args(args: list, out: Path, port: int, *extra) -> list[list]:
    return [[*args, "--out", out, "--coordinator", f"127.0.0.1:{port}", "--num-processes", 2,
             "--process-id", i, "--distributed-timeout", 120, *extra] for i in (0, 1)]


def _records(out: Path) -> list[dict]:
    path = out / "log.jsonl"
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()] if path.exists() else []


def _losses(out: Path) -> dict[int, float]:
    """The loss logged for each step (the last record of a step, as a resumed run may log some again)."""
    return {r["step"]: r["loss"] for r in _records(out) if "loss" in r}


def _final(out: Path):
    tree, meta = ckpt.load_checkpoint(ckpt.latest_checkpoint(out / "checkpoints"))
    return tree, meta


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from patexgs_jax.data.synthetic import generate

    root = tmp_path_factory.mktemp("multiprocess")
    # (a scene this small shows everything checked here; each run also evaluates its training views
    # at its end, 21 of them on the embedded scene)
    scene = generate(root / "scene", seed=0, num_views=10, width=SCENE_W, height=SCENE_H, num_points=400)
    args = [*TRAIN_ARGS, "--data", scene]
    cache = root / "xla_cache"
    res = dict(root=root, times={})
    for name in ("ref", "killed", "resumed"):
        (root / name).mkdir()
    out = root / "killed" / "out"
    t = time.monotonic()
    # The reference (one process, two devices) and two processes, of which process 1 is killed after
    # the checkpoint of step 2.
    with _processes([[*args, "--out", root / "ref" / "out", "--devices", 2]], cache, root / "ref") as ref:
        with _processes(_pair_args(args, out, _free_port()), cache, root / "killed") as procs:
            first = ckpt.checkpoint_path(out / "checkpoints", 2)
            deadline = time.monotonic() + RUN_TIMEOUT
            while not first.exists() and time.monotonic() < deadline and all(p.poll() is None for p in procs):
                time.sleep(0.05)
            res["killed_first_ckpt"] = first.exists()
            res["killed_alive_before_kill"] = [p.poll() for p in procs]
            procs[1].send_signal(signal.SIGKILL)
            t_kill = time.monotonic()
            try:
                procs[0].wait(timeout=KILL_TIMEOUT)
            except subprocess.TimeoutExpired:
                pass
            res["killed_survivor_rc"] = procs[0].poll()
            res["killed_survivor_seconds"] = time.monotonic() - t_kill
        res["times"]["killed"] = time.monotonic() - t
        res["ref_rc"] = _wait(ref, RUN_TIMEOUT)
        res["times"]["ref"] = time.monotonic() - t
    latest = ckpt.latest_checkpoint(out / "checkpoints")
    res["killed_ckpt_step"] = None if latest is None else ckpt.read_metadata(latest)["step"]
    res["killed_log_steps"] = [r["step"] for r in _records(out)]
    # The killed run resumed by two processes.
    t = time.monotonic()
    with _processes(_pair_args(args, out, _free_port(), "--resume"), cache, root / "resumed") as procs:
        res["resumed_rc"] = _wait(procs, RUN_TIMEOUT)
    res["times"]["resumed"] = time.monotonic() - t
    print("run times (s):", {k: round(v, 1) for k, v in res["times"].items()},
          f"survivor stopped {res['killed_survivor_seconds']:.1f} s after the kill")
    return res


def _ok(runs, name: str, n: int):
    rcs = runs[f"{name}_rc"]
    logs = "\n".join(f"--- process {i}\n{o[-2000:]}\n{e[-4000:]}" for i in range(n)
                     for o, e in [_outputs(runs["root"] / name, i)])
    assert rcs == [0] * n, f"{name}: exit codes {rcs}\n{logs}"


def _compare_states(a, b, rtol=1e-6, atol=1e-6):
    """Every array of ``a["scene"]`` within ``rtol`` |b| + ``atol`` max(1, max|b of the leaf|)."""
    import jax

    la, lb = jax.tree_util.tree_leaves(a["scene"]), jax.tree_util.tree_leaves(b["scene"])
    assert len(la) == len(lb)
    print("largest |difference| over", len(la), "arrays:",
          max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)), initial=0.0))
              for x, y in zip(la, lb)))
    for x, y in zip(la, lb):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        assert x.shape == y.shape
        np.testing.assert_allclose(x, y, rtol=rtol, atol=atol * max(1.0, float(np.max(np.abs(y), initial=0.0))))


def test_two_processes_equal_one_process_with_two_devices(runs):
    _ok(runs, "ref", 1)
    _ok(runs, "resumed", 2)
    ref, pair = runs["root"] / "ref" / "out", runs["root"] / "killed" / "out"
    lr, lp = _losses(ref), _losses(pair)
    assert sorted(lr) == sorted(lp) == list(range(1, STEPS + 1))
    np.testing.assert_allclose([lp[s] for s in sorted(lp)], [lr[s] for s in sorted(lr)], rtol=1e-6, atol=0)
    (tr, mr), (tp, mp) = _final(ref), _final(pair)
    assert mr["step"] == mp["step"] == STEPS
    _compare_states(tp, tr)
    # The whole replicated state, optimiser moments and densification statistics included.
    _compare_states(dict(scene=(tp["opt_state"], tp["stats"])), dict(scene=(tr["opt_state"], tr["stats"])))
    sr = json.loads((ref / "summary.json").read_text())
    sp = json.loads((pair / "summary.json").read_text())
    assert sp["num_gaussians"] == sr["num_gaussians"] and sp["steps"] == STEPS
    np.testing.assert_allclose(sp["train_psnr"], sr["train_psnr"], rtol=1e-5)


def test_one_set_of_outputs(runs):
    _ok(runs, "resumed", 2)
    out = runs["root"] / "killed" / "out"
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    assert files == ["checkpoints", "checkpoints/ckpt_000000004.ckpt", "checkpoints/ckpt_000000006.ckpt",
                     "data.json", "log.jsonl", "scene.ply", "summary.json"], files
    # One writer: the killed run logged steps 1..k once each (k >= its last checkpoint, c), the
    # resumed run c+1..STEPS once each (two writers would log every step twice).
    c, before = runs["killed_ckpt_step"], runs["killed_log_steps"]
    assert before == list(range(1, len(before) + 1)) and len(before) >= c, (before, c)
    steps = [r["step"] for r in _records(out)]
    assert steps == before + list(range(c + 1, STEPS + 1)), steps
    for name in ("killed", "resumed"):
        o1, _ = _outputs(runs["root"] / name, 1)
        # Process 1 prints no progress lines and no result (a heartbeat of a slow compile may show).
        assert not re.search(r"^step +\d+/\d+", o1, re.M) and "done:" not in o1, o1
    o0, _ = _outputs(runs["root"] / "resumed", 0)
    assert "done:" in o0 and f"step      {STEPS}/{STEPS}" in o0


def test_killing_a_process_stops_the_other_with_a_clear_error(runs):
    assert runs["killed_first_ckpt"] and runs["killed_alive_before_kill"] == [None, None], runs
    _, err = _outputs(runs["root"] / "killed", 0)
    assert runs["killed_survivor_rc"] == 3, (runs["killed_survivor_rc"], err[-3000:])
    assert runs["killed_survivor_seconds"] < KILL_TIMEOUT
    assert "error:" in err and "another process has probably stopped" in err and "--resume" in err, err[-3000:]
    assert "Traceback" not in err


def test_resume_with_two_processes(runs):
    _ok(runs, "resumed", 2)
    o0, _ = _outputs(runs["root"] / "resumed", 0)
    assert 2 <= runs["killed_ckpt_step"] < STEPS
    assert "resuming from" in o0 and f"at step {runs['killed_ckpt_step']}" in o0


def test_join_failures_end_with_a_clear_error(tmp_path):
    """No coordinator within the time-out; processes started with different process counts; a
    malformed coordinator address (the study's command line)."""
    cache = tmp_path / "cache"
    port = _free_port()
    args = [*TRAIN_ARGS, "--out", tmp_path / "a", "--coordinator", f"127.0.0.1:{port}", "--num-processes", 2,
            "--process-id", 1, "--distributed-timeout", 3]
    t = time.monotonic()
    with _processes([args], cache, tmp_path) as procs:
        rc = _wait(procs, 120)
    seconds = time.monotonic() - t
    _, err = _outputs(tmp_path, 0)
    assert rc == [3] and seconds < 60, (rc, seconds, err[-2000:])
    assert f"could not reach the coordinator at 127.0.0.1:{port} within 3 s" in err and "Traceback" not in err
    port = _free_port()
    argvs = [[*TRAIN_ARGS, "--out", tmp_path / "b", "--coordinator", f"127.0.0.1:{port}", "--num-processes", n,
              "--process-id", i, "--distributed-timeout", 60] for n, i in ((2, 0), (3, 1))]
    with _processes(argvs, cache, tmp_path) as procs:
        rcs = _wait(procs, 120)
    for i in (0, 1):
        _, err = _outputs(tmp_path, i)
        assert rcs[i] == 3, (rcs, err[-2000:])
        assert "different --num-processes (process 0: 2, process 1: 3" in err and "Traceback" not in err
    assert not (tmp_path / "b").exists()  # nothing written
    # The study's command line takes the same flags and checks them the same way.
    bad = subprocess.run([sys.executable, "-m", "experiments.mipnerf360", "--out", tmp_path / "c", "--coordinator",
                          "no-port", "--num-processes", "2", "--process-id", "0"], cwd=REPO, env=_env(cache),
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 3 and "--coordinator must be HOST:PORT" in bad.stderr and "Traceback" not in bad.stderr


def test_processes_join_from_a_slurm_environment(tmp_path):
    """Without the flags, the coordinator, process count and id come from the variables SLURM's
    ``srun`` sets (read by JAX; the coordinator port is derived from the job id)."""
    port = next(p for p in range(65535, 61439, -1) if _port_is_free(p))
    script = ("import jax; from patexgs_jax import parallel; several = parallel.initialize(timeout=60); "
              "print('JOINED', several, jax.process_index(), jax.process_count(), len(jax.devices()))")
    procs = []
    try:
        for i in (0, 1):
            env = dict(_env(tmp_path / "cache"), SLURM_JOB_ID=str(port - 61440), SLURM_STEP_NODELIST="localhost",
                       SLURM_NTASKS="2", SLURM_PROCID=str(i), SLURM_LOCALID=str(i), SLURM_STEP_NUM_NODES="1")
            procs.append(subprocess.Popen([sys.executable, "-c", script], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, text=True))
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=30)
    for i, (out, err) in enumerate(outs):
        assert procs[i].returncode == 0, err[-3000:]
        assert f"JOINED True {i} 2 2" in out, (out, err[-3000:])


def _port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True
