"""The baselines from the training command line: every method trains ``--iters-2dgs`` +
``--iters-tex`` steps (as the studies train them), a 3D method's stage is named after its primitive,
``summary.json`` records the configuration the run trained with, a run without textures writes no
texture sidecar, and outputs are written with the mode ``open()`` gives (0644 under umask 022).

No step is trained here: :meth:`Trainer.run` and the evaluation are stubbed, so each test takes
well under a second of compute beyond loading a 40 x 30 scene."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from data_builders import make_colmap_scene
from patexgs_jax import checkpoint as ckpt
from patexgs_jax import progress
from patexgs_jax.data import load
from patexgs_jax.export import export_ply, load_ply, sidecar_path
from patexgs_jax.training import cli as train_cli
from patexgs_jax.training import run as run_module
from patexgs_jax.training.config import TrainConfig, effective_config, equal_steps, preset_config
from patexgs_jax.training.trainer import Trainer


@pytest.fixture
def scene_dir(tmp_path):
    make_colmap_scene(tmp_path / "scene", n_images=6)
    return tmp_path / "scene"


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def _cli_config(monkeypatch, scene_dir, out, *flags) -> TrainConfig:
    """The TrainConfig the command line hands to :func:`train` for ``flags`` (nothing trained)."""
    seen = {}
    monkeypatch.setattr(train_cli, "train", lambda ds, cfg, out, **kw: seen.setdefault("cfg", cfg))
    code = train_cli.main(["--data", str(scene_dir), "--out", str(out), "--preset", "tiny", *flags])
    assert code == 0
    return seen["cfg"]


@pytest.mark.parametrize("method", ["3dgs", "mip-splatting", "2dgs", "patexgs", "bbsplat"])
def test_cli_trains_the_study_steps(monkeypatch, scene_dir, tmp_path, method):
    """``--iters-2dgs 600 --iters-tex 200`` is 800 steps for every method, as in the study's
    Table 1 rows; ``--iters-tex 0`` stops an untextured method after its first stage."""
    from experiments.study import StudyConfig

    cfg = _cli_config(monkeypatch, scene_dir, tmp_path / "out", "--method", method, "--iters-2dgs", "600",
                      "--iters-tex", "200")
    assert cfg.total_steps == 800
    assert cfg == StudyConfig(preset="tiny", iters_2dgs=600, iters_tex=200).train_config(method)
    if cfg.spec.textures is None:
        assert cfg.continue_2dgs == 200
        short = _cli_config(monkeypatch, scene_dir, tmp_path / "out", "--method", method, "--iters-tex", "0")
        assert short.total_steps == short.iters_2dgs == 600


def test_help_says_what_the_step_flags_mean(capsys):
    with pytest.raises(SystemExit):
        train_cli.main(["-h"])
    text = " ".join(capsys.readouterr().out.split())
    assert "3D Gaussians for 3dgs and mip-splatting" in text
    assert "(2dgs, 3dgs, mip-splatting) continues its first stage for as many steps" in text
    assert "Every method trains --iters-2dgs + --iters-tex steps in all" in text


def test_effective_config_of_the_3d_methods():
    for name in ("3dgs", "mip-splatting"):
        cfg = preset_config("tiny", method=name)
        used = effective_config(cfg)
        assert cfg.densify.prune_opacity == 0.05 and cfg.lambda_normal == 0.05  # the general defaults
        assert used.densify.prune_opacity == 0.005 and used.lambda_normal == 0.0
    patexgs = preset_config("tiny", method="patexgs")
    assert effective_config(patexgs) is patexgs and equal_steps(patexgs) is patexgs


def _stub_training(monkeypatch, measured=None):
    """Trainer.run and the evaluation as no-ops (the run ends at its initial state); ``measured``
    collects what the run says."""
    monkeypatch.setattr(Trainer, "run", lambda self: None)
    monkeypatch.setattr(run_module, "evaluate", lambda *a, **k: dict(psnr=0.0, ssim=0.0))
    if measured is not None:
        monkeypatch.setattr(progress, "say", lambda msg: measured.append(msg))


def test_3dgs_run_names_its_stage_records_its_config_and_writes_no_sidecar(monkeypatch, scene_dir, tmp_path,
                                                                           umask_022):
    said: list[str] = []
    _stub_training(monkeypatch, said)
    ds = load(scene_dir, factor=1, verbose=False)
    cfg = equal_steps(preset_config("tiny", method="3dgs", iters_2dgs=6, iters_tex=4, checkpoint_every=1))
    out = tmp_path / "run"
    result = run_module.train(ds, cfg, out, check_memory=False)
    assert "6 + 4 steps" in said[-1] and "training 3dgs" in said[-1]
    # The recorded configuration is the one the run trained with (the 3D methods' own settings).
    saved = json.loads((out / "summary.json").read_text())["config"]
    assert saved["densify"]["prune_opacity"] == 0.005 and saved["lambda_normal"] == 0.0
    assert saved["continue_2dgs"] == 4 and result.summary["config"] == saved
    # No empty texture sidecar; the PLY loads without one.
    assert {"scene.ply", "summary.json"} <= {p.name for p in out.iterdir()}
    assert not sidecar_path(out / "scene.ply").exists()
    assert load_ply(out / "scene.ply").is_3d
    for f in (out / "scene.ply", out / "summary.json"):
        assert stat.S_IMODE(f.stat().st_mode) == 0o644, f

    # The stage's name in the time estimate and the phase: the primitive's.
    run = Trainer(ds, cfg, None, verbose=True)
    assert {run.cfg.stage_name(s) for s in (0, 5, 6, 9)} == {"3DGS"}
    said.clear()
    for step in range(10):
        run.estimate.measure(step, 0.17)
    assert any("(170 ms a 3DGS step)" in s for s in said) and not any("2DGS" in s for s in said), said
    tex = Trainer(ds, preset_config("tiny", method="patexgs", iters_2dgs=6, iters_tex=4), None, verbose=False)
    assert [tex.cfg.stage_name(s) for s in (5, 6)] == ["2DGS", "textured"]


def test_sidecar_only_with_textures_and_outputs_0644(tmp_path, umask_022):
    from patexgs_jax.scene import Scene

    rng = np.random.default_rng(0)
    n = 5
    plain = Scene.from_arrays(rng.normal(size=(n, 3)), np.full((n, 2), 0.1), np.tile([1.0, 0, 0, 0], (n, 1)),
                              np.full(n, 0.5), rng.uniform(size=(n, 1, 3)))
    path = tmp_path / "scene.ply"
    sidecar_path(path).write_bytes(b"left by an earlier textured export")
    export_ply(plain, path)
    assert not sidecar_path(path).exists()  # (no stale sidecar beside the new PLY)
    assert load_ply(path).rgb is None
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    c = ckpt.save_checkpoint(tmp_path / "ckpt" / "c.ckpt", {"x": np.zeros(3)})
    assert stat.S_IMODE(c.stat().st_mode) == 0o644
    os.umask(0o077)  # the umask is respected, as open() does
    export_ply(plain, path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
