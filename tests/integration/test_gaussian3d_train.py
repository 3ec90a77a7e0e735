"""``3dgs`` and ``mip-splatting`` end to end on test_train's tiny synthetic scene (48 x 32 images, 400
SfM points): both learn with densification, keep 3D Gaussians and no normal loss, write their own
stage-1 checkpoint, export a 3DGS PLY (Mip-Splatting's with the 3D filter baked in) that loads back
and renders as the trained scene, and a resumed ``mip-splatting`` run equals an uninterrupted one."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from backends import NOT_BITWISE, bitwise_reproducible
from patexgs_jax import checkpoint as ckpt
from patexgs_jax.data import load
from patexgs_jax.evaluation import evaluate
from patexgs_jax.export import load_ply
from patexgs_jax.filter3d import filter_variance
from patexgs_jax.training.config import stage1_key, stage1_part
from patexgs_jax.training.run import train
from patexgs_jax.training.trainer import STAGE1_DIR, Trainer, init_scene
from train_configs import tiny_config


@pytest.fixture(scope="module")
def dataset(synthetic_scene_dir, tmp_path_factory):
    return load(synthetic_scene_dir, factor=1, test_every=5, cache_dir=tmp_path_factory.mktemp("cache"), verbose=False)


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory):
    out = {}
    for method in ("3dgs", "mip-splatting"):
        cfg = tiny_config(method=method, iters_2dgs=30, continue_2dgs=10)
        d = tmp_path_factory.mktemp(method)
        init = init_scene(dataset.points, dataset.colors, cfg)
        if cfg.spec.filter3d:
            init = init.replace(filter3d=filter_variance(init.means, [v.camera for v in dataset.train_views]))
        psnr_init = evaluate(init, dataset.train_views, cfg.render_config())["psnr"]
        out[method] = dict(cfg=cfg, out=d, psnr_init=psnr_init, result=train(dataset, cfg, d, verbose=False))
    return out


@pytest.mark.parametrize("method", ["3dgs", "mip-splatting"])
def test_learns_densifies_and_exports(runs, dataset, method):
    r = runs[method]
    cfg, s, scene = r["cfg"], r["result"].summary, r["result"].scene
    assert s["steps"] == 40 and s["skipped_steps"] == 0 and s["texels"] == 0
    assert s["train_psnr"] > r["psnr_init"] + 1.0, (s["train_psnr"], r["psnr_init"])
    assert scene.is_3d and scene.rgb is None and s["num_gaussians"] > 400  # densified from 400 points
    if method == "mip-splatting":  # recomputed for the densified scene, last at step 36 (the means move after)
        act = np.asarray(scene.active) > 0
        f = np.asarray(scene.filter3d)[act]
        assert np.all(f > 0)
        np.testing.assert_allclose(f, filter_variance(np.asarray(scene.means)[act],
                                                      [v.camera for v in dataset.train_views]), rtol=1e-3)
    else:
        assert scene.filter3d is None
    # Its own stage 1: the stage-1 checkpoint carries the method in its key.
    s1 = ckpt.list_checkpoints(r["out"] / "checkpoints" / STAGE1_DIR)
    assert s1 and stage1_part(ckpt.read_metadata(s1[-1])["config"]) == stage1_key(cfg)
    assert stage1_key(cfg) != stage1_key(tiny_config(method="2dgs", iters_2dgs=30))
    # The PLY (3DGS layout, filter baked) renders as the trained scene.
    back = load_ply(r["out"] / "scene.ply")
    assert back.is_3d and back.num_active() == s["num_gaussians"] and back.filter3d is None
    ev = evaluate(back, dataset.test_views, cfg.render_config())
    assert abs(ev["psnr"] - s["test_psnr"]) < 1e-3, (ev["psnr"], s["test_psnr"])


def test_mip_splatting_resume_equals_uninterrupted(runs, dataset, tmp_path):
    """Killed after step 22 (the newest checkpoint: step 21, between two recomputations of the 3D
    filter at 18 and 24), resumed: the same scene as the uninterrupted run."""
    if not bitwise_reproducible():
        pytest.skip(NOT_BITWISE)
    r = runs["mip-splatting"]
    out = tmp_path / "resumed"
    orig = Trainer.after_step

    def after_step(self, step):
        orig(self, step)
        if step == 22:
            raise Killed

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Trainer, "after_step", after_step)
        with pytest.raises(Killed):
            train(dataset, r["cfg"], out, verbose=False)
    assert ckpt.read_metadata(ckpt.latest_checkpoint(out / "checkpoints"))["step"] == 21
    again = train(dataset, r["cfg"], out, resume=True, verbose=False).scene
    for a, b in zip(jax.tree_util.tree_leaves(again), jax.tree_util.tree_leaves(r["result"].scene)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6, rtol=0)


def test_checkpoint_of_one_primitive_refused_by_the_other(runs, dataset, tmp_path):
    """A 3D run's checkpoint resumed, or taken as stage 1, by a method of 2D splats: one line naming
    both primitives and methods, before any work."""
    import shutil

    src = runs["3dgs"]["out"]
    out = tmp_path / "run"
    shutil.copytree(src / "checkpoints", out / "checkpoints")
    cfg = tiny_config(method="patexgs")
    want = r"holds 3D Gaussians \(method 3dgs\), but patexgs trains 2D splats"
    with pytest.raises(ValueError, match=want):
        train(dataset, cfg, out, resume=True, verbose=False)
    with pytest.raises(ValueError, match=want):
        train(dataset, cfg, tmp_path / "other", verbose=False, stage1=ckpt.latest_checkpoint(src / "checkpoints"))


class Killed(Exception):
    """Stands in for the process being killed (raised from a hook, in-process)."""
