"""Compiling ahead's missed predictions (:mod:`patexgs_jax.training.compile_ahead`): before the main
thread compiles a textured step the run did not predict, it waits for the prediction's background
compile still running, so that a CPU process compiles one textured step at a time (the peak the
plan and the memory check count); a GPU run does not wait."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import jax

from patexgs_jax import background
from patexgs_jax.training.compile_ahead import CompileAhead
from patexgs_jax.training.config import TrainConfig
from patexgs_jax.training.steps import step_identity


def _ahead_with_a_running_prediction(cfg, release: threading.Event):
    """A stand-in of a run's CompileAhead whose one prediction's compile runs until ``release``."""
    started = threading.Event()

    def compile_prediction():
        started.set()
        release.wait(10)

    job = background.submit("the textured step for Eq. 7's predicted layout", compile_prediction)
    assert job is not None and started.wait(10)
    said = []
    ahead = SimpleNamespace(cfg=cfg, prepared=[SimpleNamespace(identity=step_identity(cfg), step_job=job)],
                            say=said.append)
    return ahead, job, said


def test_a_miss_waits_for_the_wrong_predictions_compile_on_a_cpu():
    cfg, release = TrainConfig(method="patexgs"), threading.Event()
    ahead, job, said = _ahead_with_a_running_prediction(cfg, release)
    threading.Timer(0.5, release.set).start()
    t = time.monotonic()
    CompileAhead._one_compile_at_a_time(ahead, 320)
    assert job.done and time.monotonic() - t >= 0.4
    assert len(said) == 1 and "one compile at a time" in said[0] and job.what in said[0]
    CompileAhead._one_compile_at_a_time(ahead, 321)  # (done: nothing to wait for, nothing said)
    assert len(said) == 1


def _assert_not_waited_for(ahead, job, said, release):
    try:
        CompileAhead._one_compile_at_a_time(ahead, 320)
        assert job.running and said == []
    finally:
        release.set()
        job.wait(10)


def test_a_miss_on_a_gpu_does_not_wait(monkeypatch):
    cfg, release = TrainConfig(method="patexgs"), threading.Event()
    ahead, job, said = _ahead_with_a_running_prediction(cfg, release)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    _assert_not_waited_for(ahead, job, said, release)


def test_another_runs_prediction_is_not_waited_for():
    cfg, release = TrainConfig(method="patexgs"), threading.Event()
    other = TrainConfig(method="patexgs", lambda_dist=0.0 if cfg.lambda_dist > 0 else 0.1)  # (another step)
    ahead, job, said = _ahead_with_a_running_prediction(other, release)
    ahead.cfg = cfg
    _assert_not_waited_for(ahead, job, said, release)
