"""The BBSplat baselines train end to end (docs/baselines.md): ``bbsplat+mip`` (billboards, fixed
16 x 16 RGBA textures, mipmaps) and ``bbsplat+adaptive`` (billboards, Eq. 7 sizes and Eqs. 8-10
growth) from one shared 2DGS stage 1 on test_train's tiny synthetic scene, a few steps each; and
``patexgs+filter3d`` (Mip-Splatting's 3D filter in the splats' planes), which trains its own."""

from __future__ import annotations

import numpy as np
import pytest

from patexgs_jax.data import load
from patexgs_jax.evaluation import evaluate
from patexgs_jax.export import load_ply
from patexgs_jax.filter3d import filter_variance
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


def test_patexgs_with_the_3d_filter_trains_and_exports(stage1, tmp_path):
    """``patexgs+filter3d`` trains its own stage 1 with the filter (recomputed after each
    densification, then every 3 steps up to 36), which the texture stage keeps: the final filter is
    that of the means after step 36, not the last ones; the PLY carries it and renders as the
    trained scene. (Resuming a run whose scene carries a filter: test_gaussian3d_train's
    mip-splatting run, the same leaf.)"""
    ds = stage1[0]
    cfg = tiny_config(method="patexgs+filter3d", iters_tex=12)
    result = train(ds, cfg, tmp_path / "run", verbose=False)
    s, sc = result.summary, result.scene
    assert s["skipped_steps"] == 0 and np.isfinite(s["test_psnr"]) and s["allocation"] is not None
    act = np.asarray(sc.active) > 0
    f = np.asarray(sc.filter3d)
    assert np.all(f[act] > 0)
    cams = [v.camera for v in ds.train_views]
    assert not np.allclose(f, filter_variance(sc.means, cams))  # (the means moved after step 36)
    back = load_ply(tmp_path / "run" / "scene.ply")
    np.testing.assert_allclose(np.asarray(back.filter3d)[:act.sum()], f[act], rtol=1e-6)  # (kept as sqrt(f))
    ev = evaluate(back, ds.test_views, cfg.render_config())
    assert abs(ev["psnr"] - s["test_psnr"]) < 1e-3, (ev["psnr"], s["test_psnr"])
