"""CheckpointWriter: save_checkpoint's bytes written in a background thread, the source free to change
once save returns, errors raised by the next call, one write at a time, kills leave whole files."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import types
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import checkpoint as ckpt
from patexgs_jax import random_scene
from patexgs_jax.checkpoint import (
    CheckpointError,
    checkpoint_path,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    save_checkpoint,
)
from patexgs_jax.checkpoint_writer import CheckpointWriter
from patexgs_jax.optim import make_optimizer

REPO = Path(__file__).resolve().parents[2]


def _tree():
    scene = random_scene(0, 5, sh_degree=1, rgb_sizes=[2, 0, 3, 1, 0], alpha_sizes=[0, 4, 0, 0, 2], capacity=8)
    rows = np.zeros((6, 3), np.float32)
    rows[2] = 1.5  # stored without its zero rows
    return {"scene": scene, "opt": make_optimizer(1.0).init(scene), "key": jax.random.key(3),
            "rows": rows, "zeros": jnp.zeros((4, 4)), "bf16": jnp.arange(5, dtype=jnp.bfloat16),
            "rng": np.random.default_rng(5), "step": 7}


def _gated(release: threading.Event, started: threading.Event | None = None):
    """A write that waits for ``release`` before writing."""
    def write(prepared, keep):
        if started is not None:
            started.set()
        release.wait(30)
        return ckpt.write_prepared(prepared, keep)
    return write


def test_same_bytes_as_save_checkpoint(tmp_path, monkeypatch):
    # (the members' ZIP timestamps are the clock's, to 2 s: one instant for both files)
    now = time.time()
    monkeypatch.setattr(zipfile, "time", types.SimpleNamespace(time=lambda: now, localtime=time.localtime))
    tree = _tree()
    a = save_checkpoint(tmp_path / "a" / "x.ckpt", tree, {"step": 7, "psnr": np.float32(21.5)})
    with CheckpointWriter() as w:
        b = w.save(tmp_path / "b" / "x.ckpt", tree, {"step": 7, "psnr": np.float32(21.5)})
    assert a.read_bytes() == b.read_bytes()
    loaded, meta = load_checkpoint(b)
    assert meta == {"step": 7, "psnr": 21.5}
    for x, y in zip(jax.tree_util.tree_leaves(tree["scene"]), jax.tree_util.tree_leaves(loaded["scene"])):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert isinstance(loaded["zeros"], jax.Array) and isinstance(loaded["rows"], np.ndarray)
    np.testing.assert_array_equal(loaded["rows"], tree["rows"])


def test_save_returns_before_the_write_and_copies_the_source(tmp_path):
    release = threading.Event()
    w = CheckpointWriter(write=_gated(release))
    source = np.arange(12, dtype=np.float32).reshape(4, 3)
    device = jnp.arange(6.0)
    meta = {"tags": ["a"]}
    path = w.save(tmp_path / "x.ckpt", {"np": source, "jax": device}, meta)
    assert w.in_flight and not path.exists()
    source[:] = -1  # what a donating step does to its buffers
    meta["tags"].append("b")
    jax.jit(lambda x: x * 0, donate_argnums=0)(device).block_until_ready()
    release.set()
    assert w.wait() == path and not w.in_flight
    loaded, got = load_checkpoint(path)
    np.testing.assert_array_equal(loaded["np"], np.arange(12, dtype=np.float32).reshape(4, 3))
    np.testing.assert_array_equal(np.asarray(loaded["jax"]), np.arange(6.0))
    assert got == {"tags": ["a"]}
    w.close()


def test_a_second_save_waits_and_order_and_keep_hold(tmp_path):
    release, started = threading.Event(), threading.Event()
    w = CheckpointWriter(write=_gated(release, started))
    d = tmp_path / "ckpts"
    save_checkpoint(checkpoint_path(d, 1), {"s": 1})
    w.save(checkpoint_path(d, 2), {"s": 2}, keep=2)
    started.wait(30)
    second = threading.Thread(target=w.save, args=(checkpoint_path(d, 3), {"s": 3}), kwargs=dict(keep=2))
    second.start()
    second.join(0.3)
    assert second.is_alive()  # waiting for the first write
    assert [p.name for p in list_checkpoints(d)] == ["ckpt_000000001.ckpt"]
    release.set()
    second.join(30)
    assert w.close() == checkpoint_path(d, 3)
    assert [p.name for p in list_checkpoints(d)] == ["ckpt_000000002.ckpt", "ckpt_000000003.ckpt"]
    assert load_checkpoint(latest_checkpoint(d))[0] == {"s": 3}
    with pytest.raises(CheckpointError, match="closed"):
        w.save(checkpoint_path(d, 5), {"s": 5})


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores permissions")
def test_a_failed_write_is_raised_by_the_next_call_and_keeps_the_last_checkpoint(tmp_path):
    d = tmp_path / "ckpts"
    w = CheckpointWriter()
    w.save(checkpoint_path(d, 1), {"s": 1})
    w.wait()
    d.chmod(0o500)
    try:
        w.save(checkpoint_path(d, 2), {"s": 2}, keep=1)  # returns: the write fails in the thread
        with pytest.raises(CheckpointError, match="ckpt_000000002.ckpt") as info:
            w.save(checkpoint_path(d, 3), {"s": 3})
        assert "Permission denied" in str(info.value)
        w.wait()  # the third save never started; the error is raised once
    finally:
        d.chmod(0o700)
    assert [p.name for p in list_checkpoints(d)] == ["ckpt_000000001.ckpt"]
    assert load_checkpoint(latest_checkpoint(d))[0] == {"s": 1}


@pytest.mark.parametrize("call", ["wait", "close", "exit"])
def test_an_injected_failure_surfaces_at_wait_close_and_exit(tmp_path, call):
    def fail(prepared, keep):
        raise OSError(28, "No space left on device")

    w = CheckpointWriter(write=fail)
    w.save(tmp_path / "x.ckpt", {"s": 1})
    with pytest.raises(CheckpointError, match=r"x\.ckpt.*No space left on device"):
        if call == "exit":
            with w:
                pass
        else:
            getattr(w, call)()


def test_bad_input_raises_at_save(tmp_path):
    w = CheckpointWriter()
    with pytest.raises(TypeError, match="not JSON-serialisable"):
        w.save(tmp_path / "x.ckpt", {"s": 1}, {"bad": object()})
    with pytest.raises(TypeError, match="cannot checkpoint"):
        w.save(tmp_path / "x.ckpt", {"s": object()})
    with pytest.raises(ValueError, match="keep must be >= 1"):
        w.save(tmp_path / "x.ckpt", {"s": 1}, keep=0)
    assert not w.in_flight and w.close() is None and list(tmp_path.iterdir()) == []


KILLED = """
import sys, time
import numpy as np
from patexgs_jax import checkpoint as ckpt, checkpoint_members
from patexgs_jax.checkpoint_writer import CheckpointWriter
d = sys.argv[1]
ckpt.save_checkpoint(ckpt.checkpoint_path(d, 1), {"a": np.ones(1000)})
original = checkpoint_members.write_npy
def half(m, arr):
    original(m, arr)
    print("WRITING", flush=True)
    time.sleep(120)
checkpoint_members.write_npy = half
CheckpointWriter().save(ckpt.checkpoint_path(d, 2), {"a": np.arange(1000.0), "b": np.arange(9.0)})
time.sleep(120)
"""


def test_a_kill_mid_write_leaves_only_whole_checkpoints(tmp_path):
    d = tmp_path / "ckpts"
    proc = subprocess.Popen([sys.executable, "-c", KILLED, str(d)], cwd=REPO, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "JAX_PLATFORMS": "cpu"})
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "WRITING"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    assert any(p.name.startswith(".ckpt_000000002.ckpt.tmp-") for p in d.iterdir())  # the half-written file
    assert [p.name for p in list_checkpoints(d)] == ["ckpt_000000001.ckpt"]
    assert latest_checkpoint(d) == checkpoint_path(d, 1)


def test_a_disk_full_mid_write_is_raised_and_cleaned_up(tmp_path, monkeypatch):
    from patexgs_jax import checkpoint_members

    d = tmp_path / "ckpts"
    w = CheckpointWriter()
    w.save(checkpoint_path(d, 1), {"a": np.ones(8)})
    w.wait()
    original = checkpoint_members.write_npy

    def full(m, arr):
        original(m, arr[: arr.size // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint_members, "write_npy", full)
    w.save(checkpoint_path(d, 2), {"a": np.arange(8.0)}, keep=1)
    with pytest.raises(CheckpointError, match=r"could not write checkpoint .*ckpt_000000002\.ckpt.*No space left"):
        w.close()
    assert [p.name for p in d.iterdir()] == ["ckpt_000000001.ckpt"]  # no temp file, the old one kept
    np.testing.assert_array_equal(load_checkpoint(latest_checkpoint(d))[0]["a"], np.ones(8))


def test_on_written_runs_once_the_file_is_in_place(tmp_path):
    seen = []
    with CheckpointWriter() as w:
        w.save(tmp_path / "x.ckpt", {"s": 1}, on_written=lambda p: seen.append((p, p.exists())))
    assert seen == [(tmp_path / "x.ckpt", True)]


def test_a_later_save_reuses_the_host_copies_and_keeps_each_file_right(tmp_path):
    w = CheckpointWriter()
    w.save(tmp_path / "a.ckpt", {"x": jnp.arange(6.0), "y": np.ones(3, np.int32), "z": np.zeros(2)})
    w.wait()
    first = {id(b) for b in w._pool[((6,), "<f4")] + w._pool[((3,), "<i4")]}
    w.save(tmp_path / "b.ckpt", {"x": jnp.arange(6.0) * 2, "y": np.full(3, 7, np.int32), "z": np.zeros(5)})
    assert first <= {id(b) for b in w._prepared.encoder.copies}  # (the new shape gets a new buffer)
    w.close()
    a, b = load_checkpoint(tmp_path / "a.ckpt")[0], load_checkpoint(tmp_path / "b.ckpt")[0]
    np.testing.assert_array_equal(np.asarray(a["x"]), np.arange(6.0))
    np.testing.assert_array_equal(np.asarray(b["x"]), np.arange(6.0) * 2)
    np.testing.assert_array_equal(b["y"], np.full(3, 7)) and np.testing.assert_array_equal(a["y"], np.ones(3))
    assert b["z"].shape == (5,) and w._pool == {}


def test_release_frees_the_host_copies_and_saves_go_on(tmp_path):
    """``release`` (the end of a run) waits and frees the kept copies; unlike ``close`` it refuses
    nothing, so a trainer that runs again writes again."""
    w = CheckpointWriter()
    w.save(tmp_path / "a.ckpt", {"x": np.arange(4.0)})
    assert w.release() == tmp_path / "a.ckpt" and w._pool == {} and not w.in_flight
    w.save(tmp_path / "b.ckpt", {"x": np.arange(4.0) + 1})
    w.close()
    np.testing.assert_array_equal(load_checkpoint(tmp_path / "b.ckpt")[0]["x"], np.arange(4.0) + 1)
    with pytest.raises(CheckpointError, match="closed"):
        w.save(tmp_path / "c.ckpt", {"x": np.zeros(1)})
