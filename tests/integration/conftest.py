"""Fixtures the integration tests share: the small synthetic capture the training and study tests
train on, and a guard that fails a test if anything trains."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def synthetic_scene_dir(tmp_path_factory):
    """A 10-view synthetic capture (train_configs.SCENE_W x SCENE_H) with 400 points, in COLMAP layout
    (generated once per test process). With the Mip-NeRF 360 protocol's every-8th hold-out it has 2
    test views (0 and 8)."""
    from patexgs_jax.data.synthetic import generate
    from train_configs import SCENE_H, SCENE_W

    return generate(tmp_path_factory.mktemp("synthetic") / "scene", seed=0, num_views=10, width=SCENE_W,
                    height=SCENE_H, num_points=400)


@pytest.fixture
def no_training(monkeypatch):
    """Makes any call of ``patexgs_jax.training.train`` fail the test: for resumes that must reuse
    every finished run (the studies import ``train`` when they run, so patching the package is enough)."""
    from patexgs_jax import training

    def train(*args, **kwargs):
        raise AssertionError("a finished run was trained again")

    monkeypatch.setattr(training, "train", train)
