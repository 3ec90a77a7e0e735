"""The BBSplat baselines train end to end (docs/baselines.md): ``bbsplat+mip`` (billboards, fixed
16 x 16 RGBA textures, mipmaps) and ``bbsplat+adaptive`` (billboards, Eq. 7 sizes and Eqs. 8-10
growth) from one shared 2DGS stage 1 on test_train's tiny synthetic scene, a few steps each."""

from __future__ import annotations

import numpy as np
import pytest

from patexgs_jax.data import load
from patexgs_jax.evaluation import evaluate
from patexgs_jax.schedule import TextureSchedule
from patexgs_jax.training.run import stage1_checkpoint, train
from train_configs import tiny_config


@pytest.fixture(scope="module")
def stage1(synthetic_scene_dir, tmp_path_factory):
    ds = load(synthetic_scene_dir, factor=1, test_every=5, cache_dir=tmp_path_factory.mktemp("cache"), verbose=False)
    cfg = tiny_config(method="2dgs")
    out = tmp_path_factory.mktemp("bb_2dgs")
    result = train(ds, cfg, out, verbose=False)
    return ds, stage1_checkpoint(out, cfg), result.summary


@pytest.mark.parametrize("method", ["bbsplat+mip", "bbsplat+adaptive"])
def test_bbsplat_trains_from_the_shared_stage1(stage1, method, tmp_path):
    ds, ckpt, base = stage1
    cfg = tiny_config(method=method, iters_tex=12)  # Eq. 7 at step 33, growth at 36 and 39
    rec = {}
    orig = TextureSchedule.start

    def start(self, state):  # the 2DGS render and the first billboard render of the same splats
        rec["before"] = evaluate(state.scene, self.train_views, cfg.render_config(stage=1))["psnr"]
        new = orig(self, state)
        rec["after"] = evaluate(new.scene, self.train_views, self.render_config)["psnr"]
        return new

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(TextureSchedule, "start", start)
        result = train(ds, cfg, tmp_path / "run", verbose=False, stage1=ckpt)
    s = result.summary
    assert s["skipped_steps"] == 0 and s["steps"] == cfg.total_steps
    assert np.isfinite(s["train_psnr"]) and np.isfinite(s["test_psnr"])
    # The billboards' Gaussian alpha textures start from the 2DGS image (bilinear texels, no low-pass).
    assert abs(rec["after"] - rec["before"]) < 0.5, rec
    assert s["train_psnr"] > rec["after"] - 0.1, (s["train_psnr"], rec)
    act = np.asarray(result.scene.active) > 0
    sides = np.asarray(result.scene.alpha.size)[act]
    if method == "bbsplat+mip":
        assert s["sides_final"] == {"16": int(act.sum())} and s["allocation"] is None
    else:
        assert s["allocation"] is not None and s["growth_events"], s
        assert sides.max() > sides.min()
