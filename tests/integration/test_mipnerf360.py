"""The main job, ``experiments.mipnerf360``: end to end on a small synthetic scene (few steps), the
results.json schema, the tables, plots and renders, resume, and argument errors.

One study (two methods, stage 1 shared) is run once per module; the other tests read it, re-run it
(everything finished: nothing may train) or call the pure table/argument functions.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from experiments import mipnerf360 as mn
from experiments import study_figures as figs
from experiments import study_tables as tbl
from experiments.provenance import write_json
from experiments.study import RESULTS_SCHEMA
from patexgs_jax.training.config import TrainConfig, config_dict, stage1_key
from patexgs_jax.training.run import load_stage1, stage1_checkpoint
from patexgs_jax.training.trainer import Trainer
from train_configs import SCENE_H as H
from train_configs import SCENE_W as W
from train_configs import TINY_STUDY

STUDY = TINY_STUDY
METHODS = ["2dgs", "patexgs"]


@pytest.fixture(scope="module")
def study(synthetic_scene_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    data = mn.run(str(synthetic_scene_dir), methods=METHODS, out=str(out), renders=1, use_lpips=False, verbose=False,
                  **STUDY)
    return out, data


def _finite(x):
    return isinstance(x, float) and math.isfinite(x)


@pytest.mark.slow
def test_results_schema_and_values(study):
    out, data = study
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(data))
    assert set(on_disk) == {"version", "config", "lpips", "results", "elapsed_seconds", "scenes"}
    assert on_disk["elapsed_seconds"] > 0  # the study's wall-clock time
    assert on_disk["lpips"] is None  # switched off: no network named
    assert on_disk["version"]["results_schema"] == RESULTS_SCHEMA
    assert on_disk["config"]["preset"] == "tiny" and on_disk["config"]["iters_2dgs"] == 12
    (scene,) = on_disk["results"]
    entries = on_disk["results"][scene]
    assert list(entries) == METHODS
    # the scene's protocol: none of the paper's datasets, so the 3DGS width rule (W px: kept)
    proto = on_disk["scenes"][scene]
    assert proto["dataset"] is None and proto["factor"] is None and "1600" in proto["why"]
    assert proto["training_size"] == [W, H] and proto["test_views"] == 2 and proto["test_every"] == 8
    for key, e in entries.items():
        for s in ("1", "2", "4", "8"):
            m = e[s]
            assert _finite(m["psnr"]) and 5.0 < m["psnr"] < 60.0, (key, s, m)
            assert _finite(m["ssim"]) and -1.0 <= m["ssim"] <= 1.0
            assert m["lpips"] is None  # LPIPS switched off
            assert m["views"] == 2
            if s == "1":
                assert m["alias_psnr"] is None and m["supersampled_psnr"] is None
            else:  # the render at 1/s against its own supersampled render; that against the truth
                assert _finite(m["alias_psnr"]) and 10.0 < m["alias_psnr"] < 80.0, (key, s, m)
                assert _finite(m["supersampled_psnr"]) and 5.0 < m["supersampled_psnr"] < 60.0, (key, s, m)
        assert 0 < e["num_gaussians"] <= 300
        assert e["storage_mb"] > 0 and e["train_seconds"] > 0 and e["render_ms"] > 0
        assert e["method"] == key and e["steps"] == 20  # equal steps: 2dgs continues its stage for 8
    assert entries["2dgs"]["texels"] == 0 and entries["patexgs"]["texels"] > 0
    assert entries["patexgs"]["storage_mb"] > entries["2dgs"]["storage_mb"]
    # Stage 1 is shared: the textured run started from the 2DGS run's end-of-stage-1 checkpoint and
    # carries its training time.
    summary = json.loads((out / "runs" / scene / "patexgs" / "summary.json").read_text())
    assert summary["stage1_from"] is not None and "/2dgs/checkpoints/stage1/" in summary["stage1_from"]
    from patexgs_jax import checkpoint as ckpt

    stage1_seconds = float(ckpt.load_checkpoint(summary["stage1_from"])[0]["t_train"])
    assert 0 < stage1_seconds < entries["patexgs"]["train_seconds"]
    assert stage1_seconds < entries["2dgs"]["train_seconds"]
    assert "same number of steps" in (out / "tables.md").read_text()


@pytest.mark.slow
def test_tables_plots_and_renders_are_written(study):
    out, data = study
    (scene,) = data["results"]
    md = (out / "tables.md").read_text()
    assert "## Table 1" in md and "## Table 2" in md and "## Cost" in md
    # Tables 3 and 4 need two of their rows each: the tables say so, and which methods make them.
    assert "## Table 3" not in md and "## Table 4" not in md
    assert "Not in this study: Table 3 (mipmap ablation)" in md and "`--methods table4`" in md
    for key in METHODS:
        row = next(line for line in md.splitlines() if line.startswith(f"| {key} |"))
        assert f"{data['results'][scene][key]['1']['psnr']:.2f}" in row
    assert "alias PSNR" in md
    row = next(line for line in md.split("## Table 2")[1].splitlines() if line.startswith("| patexgs |"))
    assert f"{data['results'][scene]['patexgs']['8']['alias_psnr']:.2f}" in row
    for name in ("psnr_vs_scale.png", "accuracy_vs_time.png"):
        assert (out / "plots" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from PIL import Image

    for key in METHODS:
        for s in (1, 8):
            im = Image.open(out / "renders" / scene / f"{key}_x{s}.png")
            # a header, then one view, ground truth | gap | render, enlarged s times: (14 + H + gap) x (2 W + gap)
            assert im.size == (2 * W + 4, 14 + H + 4)
            if s == 8:  # nearest neighbour: 8 x 8 blocks of the saved 1/8 render
                px = np.asarray(im.convert("RGB"))[14:14 + H, W + 4:]
                small = np.asarray(Image.open(out / "renders" / scene / "first" / f"{key}_x8.png").convert("RGB"))
                np.testing.assert_array_equal(px[4::8, 4::8], small)
    # ground truth | 2dgs | patexgs, at full size and at 1/8 enlarged to full size, the sheet enlarged
    # to readable tiles, under a header and beside a band of row labels (figs.sheet_layout)
    im = Image.open(out / "renders" / scene / "compare.png")
    lay = figs.sheet_layout((H, W), ["ground-truth", *METHODS], [figs.row_label(s) for s in (1, 8)])
    assert im.size == lay["size"][::-1] and min(lay["tile"]) >= figs.MIN_TILE
    px = np.asarray(im.convert("RGB"))
    first = np.asarray(Image.open(out / "renders" / scene / "first" / "patexgs_x8.png").convert("RGB"))
    (y0, x0), b = lay["origin"](1, 2), 8 * lay["enlarge"]
    np.testing.assert_array_equal(px[y0 + b // 2:y0 + H * lay["enlarge"]:b, x0 + b // 2:x0 + W * lay["enlarge"]:b],
                                  first)


@pytest.mark.slow
def test_resume_skips_finished_entries(study, synthetic_scene_dir, no_training):
    out, data = study
    again = mn.run(str(synthetic_scene_dir), methods=METHODS, out=str(out), renders=1, use_lpips=False, verbose=False,
                   **STUDY)
    assert again["results"] == data["results"]


@pytest.mark.slow
def test_entry_lost_after_training_is_re_evaluated_without_training(study, synthetic_scene_dir, tmp_path):
    """An interruption between a run's end and its results entry: the run is finished on disk, so
    the entry comes back from it (no training step taken) with the same metrics."""
    out, data = study
    path = out / "results.json"
    saved = json.loads(path.read_text())
    (scene,) = saved["results"]
    lost = saved["results"][scene].pop("patexgs")
    path.write_text(json.dumps(saved))
    again = mn.run(str(synthetic_scene_dir), methods=METHODS, out=str(out), renders=1, use_lpips=False, verbose=False,
                   **STUDY)
    back = again["results"][scene]["patexgs"]
    for s in ("1", "2", "4", "8"):
        assert back[s]["psnr"] == pytest.approx(lost[s]["psnr"], abs=1e-6)
    assert back["train_seconds"] == pytest.approx(lost["train_seconds"], rel=1e-9)


@pytest.mark.slow
def test_changed_protocol_is_refused(study, synthetic_scene_dir):
    out, _ = study
    with pytest.raises(mn.StudyError, match="iters_2dgs"):
        mn.run(str(synthetic_scene_dir), methods=METHODS, out=str(out), use_lpips=False, verbose=False,
               **dict(STUDY, iters_2dgs=13))


@pytest.mark.slow
def test_budgets_share_the_unbudgeted_run_and_respect_their_caps(study, synthetic_scene_dir, tmp_path):
    """``--budgets 100%,95%`` added to a finished study: the unbudgeted entries are kept, the budget
    caps every method at its share of the unbudgeted 2DGS run's count, the textured run starts from
    its own budget's stage 1, and tables.md has the budget rows of Table 1, method x budget. (One
    budget: each adds two runs; 10% and 1% take the same path. 95% keeps the unbudgeted runs'
    Gaussian capacity, 512 (10% would give 32), so the budget's runs load most of their programs
    instead of compiling them.)"""
    import shutil

    out, _ = study
    copy = tmp_path / "study"
    shutil.copytree(out, copy)
    # The study as it is now (the tests above may have retrained an entry of the module's study).
    before = json.loads((copy / "results.json").read_text())
    got = mn.run(str(synthetic_scene_dir), methods=METHODS, out=str(copy), renders=0, use_lpips=False, verbose=False,
                 **dict(STUDY, budget="100%,95%"))
    (scene,) = got["results"]
    entries = got["results"][scene]
    assert list(entries) == METHODS + ["2dgs(95%)", "patexgs(95%)"]
    assert {k: entries[k] for k in METHODS} == before["results"][scene]  # kept, not retrained
    assert got["config"]["budget"] == "100%,95%"
    ref = entries["2dgs"]["num_gaussians"]
    b, f = "95%", 0.95
    for m in METHODS:
        e = entries[f"{m}({b})"]
        assert e["max_gaussians"] == max(1, round(f * ref)), (m, b, e["max_gaussians"], ref)
        assert 0 < e["num_gaussians"] <= e["max_gaussians"] and e["steps"] == 20
    summary = json.loads((copy / "runs" / scene / f"patexgs({b})" / "summary.json").read_text())
    assert f"/2dgs({b})/checkpoints/stage1/" in summary["stage1_from"]
    md = (copy / "tables.md").read_text().split("## Table 1 budget rows")[1].split("##")[0]
    rows = [line.split(" | ")[:4] for line in md.splitlines() if line.startswith("| 2dgs |") or
            line.startswith("| patexgs |")]
    assert [r[:2] for r in rows] == [["| 2dgs", "100%"], ["| patexgs", "100%"], ["| 2dgs", b], ["| patexgs", b]]
    gain = entries[f"patexgs({b})"]["1"]["psnr"] - entries[f"2dgs({b})"]["1"]["psnr"]
    assert rows[3][2] == f"{entries[f'patexgs({b})']['1']['psnr']:.2f}" and rows[3][3] == f"{gain:+.2f}"


def test_stage1_from_a_mismatched_checkpoint_is_refused(tmp_path):
    cfg = TrainConfig(method="patexgs", iters_2dgs=5, iters_tex=3, warmup_tex=1)
    other = TrainConfig(method="2dgs", iters_2dgs=5, lambda_normal=0.5)
    assert stage1_key(cfg) == stage1_key(TrainConfig(method="2dgs", iters_2dgs=5, iters_tex=99))
    assert stage1_key(cfg) != stage1_key(other)
    # The texels' learning rates act only in stage 2; every other learning rate shapes stage 1.
    lr = cfg.lr
    assert stage1_key(cfg) == stage1_key(dataclasses.replace(
        cfg, lr=dataclasses.replace(lr, texture_rgb=4 * lr.texture_rgb, texture_alpha=lr.texture_alpha / 2)))
    assert stage1_key(cfg) != stage1_key(dataclasses.replace(cfg, lr=dataclasses.replace(lr, sh_dc=2 * lr.sh_dc)))
    from patexgs_jax import checkpoint as ckpt

    path = ckpt.save_checkpoint(ckpt.checkpoint_path(tmp_path / "checkpoints", 5), {"x": 1},
                                dict(config=config_dict(other), step=5))
    assert stage1_checkpoint(tmp_path, cfg) is None
    run = Trainer.__new__(Trainer)
    with pytest.raises(ValueError, match="lambda_normal"):
        load_stage1(run, path, cfg)


def test_tables_follow_the_paper_layouts():
    def e(p):
        return {"1": dict(psnr=p, ssim=0.8, lpips=0.2), "2": dict(psnr=p + 1, ssim=0.85, lpips=None),
                "4": dict(psnr=p + 2, ssim=0.9, lpips=0.1, alias_psnr=30.0),
                "8": dict(psnr=p + 3, ssim=0.9, lpips=0.1),
                "storage_mb": 1.5, "num_gaussians": 100, "texels": 10, "train_seconds": 3.0, "render_ms": 4.0}

    keys = ["2dgs", "patexgs", "patexgs-no-mip", "patexgs-no-rgb-mip", "textured-fixed-8", "patexgs(10%)"]
    data = {"config": {"preset": "tiny"},
            "results": {"a": {k: e(20.0 + i) for i, k in enumerate(keys)},
                        "b": {k: e(22.0 + i) for i, k in enumerate(keys[:2])}}}
    md = mn.tables_markdown(data)
    lines = md.splitlines()
    # Table 1: per scene and the mean over scenes that have the entry.
    row = next(line for line in lines if line.startswith("| patexgs |"))
    assert "| 21.00 | 0.800 | 0.200 | 23.00 | 0.800 | 0.200 | 22.00 | 0.800 | 0.200 |" in row
    assert next(line for line in lines if line.startswith("| patexgs-no-mip |")).count(" - ") == 3  # absent in b
    t3 = md.split("## Table 3")[1].split("##")[0]
    assert "| Full |" in t3 and "| w/o mip. |" in t3 and "| w/o RGB mip. |" in t3 and "| Full(10%) |" in t3
    assert "2dgs" not in t3
    t4 = md.split("## Table 4")[1].split("##")[0]
    # Full, 1/4 and 1/8 (a's values: entry 4 is textured-fixed-8 at 24 dB), and the storage
    assert "| Full PSNR | SSIM | LPIPS | 1/4 PSNR | SSIM | LPIPS | 1/8 PSNR | SSIM | LPIPS | storage MB |" in t4
    row = "| 8 x 8 (Textured Gaussians: no mip, low-pass) | - | 24.00 | 0.800 | 0.200 | 26.00 | 0.900 | 0.100 | 27.00 |"
    assert row in t4
    assert "1.50 |" in t4
    # an LPIPS missing at one scale shows as "-", not as a number
    t2 = md.split("## Table 2")[1].split("##")[0]
    assert "| 2dgs | 21.00 | 0.800 | 0.200 | 22.00 | 0.850 | - |" in t2
    # the alias PSNR beside each zoomed-out scale's metrics ("-" where an entry lacks it)
    assert "| 1/2 PSNR | SSIM | LPIPS | alias PSNR |" in t2
    assert "| 2dgs | 21.00 | 0.800 | 0.200 | 22.00 | 0.850 | - | - | 23.00 | 0.900 | 0.100 | 30.00 |" in t2


def test_table4_rows_and_the_side_distribution(tmp_path):
    """The like-with-like rows (patexgs-fixed-N, the storage-matched row) and the side plot drawn from
    the entries' Eq. 7 and final side histograms."""
    def e(p, method, texels, **kw):
        return {**{s: dict(psnr=p, ssim=0.8, lpips=0.2) for s in "148"}, "storage_mb": 1.0, "train_seconds": 1.0,
                "render_ms": 1.0, "num_gaussians": 100, "texels": texels, "method": method, **kw}
    adaptive = e(21.0, "patexgs", 2 * 1090, sides_allocated={"1": 80, "8": 20}, sides_final={"1": 70, "2": 10, "8": 20},
                 sigma=33.0, growth_events=[dict(step=1, grown=10, texels_added=30, texels=1310)])
    data = {"config": {"preset": "tiny"}, "results": {"a": {"patexgs": adaptive}}}
    study = mn.Study.__new__(mn.Study)
    study.data, study.cfg = data, mn.StudyConfig()
    assert study.matched_method("a") == "patexgs-fixed-3"  # 10.9 RGBA texels a Gaussian: 3 x 3 is closest
    data["results"]["a"].update({"patexgs-fixed-4": e(20.5, "patexgs-fixed-4", 3200),
                                 mn.MATCHED: e(20.0, "patexgs-fixed-3", 1800)})
    t4 = mn.tables_markdown(data).split("## Table 4")[1].split("##")[0]
    assert "| Full (adaptive) | patexgs |" in t4 and "| 4 x 4 + mip | patexgs-fixed-4 |" in t4
    assert "| similar storage | patexgs-fixed-3 |" in t4
    path = figs.plot_sides(data, tmp_path / "sides.png")
    assert path is not None and path.stat().st_size > 0
    only_matched = {"results": {"a": {mn.MATCHED: data["results"]["a"][mn.MATCHED]}}}
    assert figs.plot_sides(only_matched, tmp_path / "x.png") is None
    with pytest.raises(mn.StudyError, match="list patexgs before it"):
        mn.run(methods=[mn.MATCHED, "patexgs"], out=tmp_path / "o")


def test_lpips_network_is_named_and_never_mixed(tmp_path, monkeypatch):
    from patexgs_jax import lpips as lp

    weights = tmp_path / "weights"
    weights.mkdir()
    for net in lp.NETS:
        lp.save_lpips(weights, lp.random_lpips_params(net, seed=0), net)
    monkeypatch.setenv(lp.ENV_VAR, str(weights))
    out, cfg = tmp_path / "out", mn.StudyConfig()
    study = mn.Study(out, cfg, use_lpips=True, verbose=False)
    assert study.data["lpips"] == {"version": "0.1", "net": "alex", "trunk": "AlexNet", "weights": "lpips_alex.npz"}
    assert "LPIPS: v0.1, AlexNet trunk (`alex`, weights lpips_alex.npz)." in mn.tables_markdown(study.data)
    assert "LPIPS: not computed" in mn.tables_markdown({"results": {}})
    study.data["results"] = {"a": {"2dgs": {"1": dict(psnr=20.0, ssim=0.5, lpips=0.3)}}}
    write_json(study.path, study.data)
    # resuming with the other trunk would mix two networks' figures in one table
    with pytest.raises(mn.StudyError, match="--lpips-net alex"):
        mn.Study(out, cfg, use_lpips=True, lpips_net="vgg", verbose=False)
    assert mn.Study(out, cfg, use_lpips=False, verbose=False).data["lpips"]["net"] == "alex"
    vgg = mn.Study(tmp_path / "out_vgg", cfg, use_lpips=True, lpips_net="vgg", verbose=False)
    assert vgg.data["lpips"]["trunk"] == "VGG16" and vgg.lpips._min_side == 16


def test_arguments_are_checked(tmp_path):
    assert tbl.parse_budget("10%") == ("fraction", 0.1) and tbl.parse_budget("5000") == ("count", 5000)
    assert tbl.parse_budget(None) is None and mn.label("patexgs", "1%") == "patexgs(1%)"
    assert mn.parse_budgets("100%, 10%,1%") == [None, "10%", "1%"] and mn.parse_budgets(None) == [None]
    assert mn.join_budgets([None, "10%", "1%"]) == "100%,10%,1%" and mn.join_budgets([None]) is None
    assert tbl.split_label("patexgs(10%)") == ("patexgs", "10%") and tbl.split_label("2dgs") == ("2dgs", None)
    with pytest.raises(mn.StudyError, match="twice"):
        mn.parse_budgets("10%,100%,10%")
    with pytest.raises(mn.StudyError, match="--budget"):
        mn.parse_budgets("10%,ten")
    for bad in ("0%", "150%", "-3", "ten"):
        with pytest.raises(mn.StudyError, match="--budget"):
            tbl.parse_budget(bad)
    with pytest.raises(mn.StudyError, match="no scene"):
        mn.find_scenes(tmp_path)
    with pytest.raises(mn.StudyError, match="does not exist"):
        mn.find_scenes(tmp_path / "nope")
    assert mn.main(["--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--no-compile-cache"]) == 2
    with pytest.raises(ValueError, match="unknown method"):
        mn.run(str(tmp_path), methods=["patexgs", "nerf"], out=str(tmp_path / "o"), verbose=False)
    # Photos without camera poses: the error says how to estimate them.
    photos = tmp_path / "capture" / "images"
    photos.mkdir(parents=True)
    for i in range(3):
        (photos / f"img{i}.JPG").write_bytes(b"")
    with pytest.raises(mn.StudyError, match=r"3 photo\(s\).*python -m patexgs_jax\.sfm"):
        mn.find_scenes(tmp_path / "capture")


@pytest.mark.slow
def test_zoom_ab_agrees_with_the_study(study, synthetic_scene_dir, tmp_path, capsys):
    """experiments.zoom_ab re-renders a study's runs under named settings: under a run's own
    settings its figures are the study's; a render-time switch to the low-pass changes them."""
    from experiments import zoom_ab

    out, data = study
    (scene,) = data["results"]
    path = tmp_path / "ab.json"
    assert zoom_ab.main(["--study", str(out), "--data", str(synthetic_scene_dir), "--variants", "lowpass,prefilter",
                         "--methods", "patexgs", "--json", str(path)]) == 0
    record = json.loads(path.read_text())
    assert record["schema"] == 1 and record["study"] == str(out)  # a benchmark file: provenance, then figures
    figs = record["results"][scene]
    assert set(figs) == {"patexgs"}
    own = data["results"][scene]["patexgs"]
    for s in ("1", "2", "4", "8"):
        got = figs["patexgs"]["prefilter"][s]
        assert got["gt"] == pytest.approx(own[s]["psnr"], abs=1e-4)
        if s == "1":
            assert got["alias"] is None
        else:
            assert got["alias"] == pytest.approx(own[s]["alias_psnr"], abs=1e-4)
    assert figs["patexgs"]["lowpass"]["8"]["alias"] != pytest.approx(own["8"]["alias_psnr"], abs=1e-3)
    assert figs["patexgs"]["prefilter"]["ms"] > 0
    assert "patexgs" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        zoom_ab.main(["--study", str(out), "--variants", "nonsense"])


@pytest.mark.slow
def test_evaluate_and_render_a_study_run(study, tmp_path, capsys):
    """``python -m patexgs_jax.evaluate`` on a study's run finds its scene and test views (the
    study's record) and reproduces its results.json figures; ``python -m patexgs_jax.render --path
    test`` renders those test views, the two methods side by side."""
    from PIL import Image

    from patexgs_jax import evaluate, render_cli

    out, _ = study
    data = json.loads((out / "results.json").read_text())  # (the file as it is now: a test above may re-evaluate)
    (scene,) = data["results"]
    run = out / "runs" / scene / "patexgs"
    path = tmp_path / "figures.json"
    assert evaluate.main([str(run), "--lpips", "none", "--json", str(path)]) == 0
    assert "alias PSNR" in capsys.readouterr().out
    got, own = json.loads(path.read_text()), data["results"][scene]["patexgs"]
    assert got["test_views"] == 2 and got["method"] == "patexgs"
    for s in ("1", "2", "4", "8"):
        for key in ("psnr", "alias_psnr", "supersampled_psnr"):
            if own[s][key] is None:
                assert got["scales"][s][key] is None
            else:
                assert got["scales"][s][key] == pytest.approx(own[s][key], abs=1e-4), (s, key)
        assert got["scales"][s]["ssim"] == pytest.approx(own[s]["ssim"], abs=1e-6)
    for key in ("storage_mb", "num_gaussians", "texels"):
        assert got[key] == own[key], key
    frames = tmp_path / "frames"
    assert render_cli.main([str(run), "--path", "test", "--out", str(frames), "--no-video", "--compare",
                            str(out / "runs" / scene / "2dgs")]) == 0
    pngs = sorted(frames.glob("frame_*.png"))
    assert len(pngs) == 2 and Image.open(pngs[0]).size == (2 * W + render_cli.GAP, render_cli.BAND + H)


@pytest.mark.slow
def test_zoom_in_added_to_a_finished_study(study, synthetic_scene_dir, tmp_path, monkeypatch):
    """``--zoom-in`` added to a finished study: every entry is evaluated again (not retrained) zoomed
    in on the synthetic scene's analytic ground truth (its images are at factor 1), and tables.md
    gains the zoom-in table. (x2 only, for time: tests/unit/test_study.py measures x4 too.)"""
    import shutil

    from experiments import study_zoom_in

    monkeypatch.setattr(study_zoom_in, "ZOOM_IN_SCALES", (2,))

    out, _ = study
    copy = tmp_path / "study"
    shutil.copytree(out, copy)
    before = json.loads((copy / "results.json").read_text())
    got = mn.run(str(synthetic_scene_dir), methods=METHODS, out=str(copy), renders=0, use_lpips=False, verbose=False,
                 **dict(STUDY, zoom_in=True))
    (scene,) = got["results"]
    assert got["config"]["zoom_in"] is True
    for key in METHODS:
        e, old = got["results"][scene][key], before["results"][scene][key]
        assert e["train_seconds"] == old["train_seconds"]  # evaluated again, not retrained
        assert e["1"]["psnr"] == pytest.approx(old["1"]["psnr"], abs=1e-5)
        assert list(e["zoom_in"]) == ["2"]
        for z, m in e["zoom_in"].items():
            assert _finite(m["psnr"]) and 5.0 < m["psnr"] < 60.0 and m["views"] == 2, (key, z, m)
            assert m["source"].startswith("analytic ground truth")
    md = (copy / "tables.md").read_text()
    row = next(line for line in md.split("## Zoom-in")[1].splitlines() if line.startswith("| patexgs |"))
    assert f"{got['results'][scene]['patexgs']['zoom_in']['2']['psnr']:.2f}" in row
