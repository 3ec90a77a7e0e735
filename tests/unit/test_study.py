"""The study's paper side without training: ``--methods`` groups, the rule that decides which
methods share the 2DGS stage 1, Tables 1 and 2 beside the paper's figures, the zoom-in table, and
the zoom-in evaluation (Mip-Splatting's protocol) on a tiny synthetic scene."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from experiments import mipnerf360 as mn
from experiments import paper
from experiments import study_tables as tbl
from experiments.study import Study, StudyConfig
from patexgs_jax.training import Method


def _known(name):
    try:
        Method.from_name(name)
        return True
    except ValueError:
        return False


def test_method_groups_expand_and_unknown_rows_fail_early(monkeypatch):
    for group, rows in (("table1", paper.TABLE1_METHODS), ("table2", paper.TABLE2_METHODS),
                        ("tables", paper.TABLES_METHODS)):
        missing = [m for m in rows if not _known(m)]
        if missing:  # the tree lacks a row: the error names the method and the group
            with pytest.raises(ValueError, match=rf"unknown method '{missing[0]}'.*--methods {group}"):
                mn.expand_methods([group])
        else:
            assert mn.expand_methods([group]) == list(rows)
    assert mn.expand_methods(["table4"]) == list(mn.TABLE4_METHODS)
    with pytest.raises(ValueError, match="unknown method 'nerf'"):
        mn.expand_methods(["patexgs", "nerf"])
    with pytest.raises(mn.StudyError, match="twice"):
        mn.expand_methods(["2dgs", "patexgs", "2dgs"])
    # With every method known (as when the other methods land), groups expand in place, each once.
    monkeypatch.setattr(Method, "from_name", classmethod(lambda cls, name: cls()))
    assert mn.expand_methods(["tables"]) == list(paper.TABLES_METHODS)
    assert set(paper.TABLES_METHODS) == set(paper.TABLE1_METHODS) | set(paper.TABLE2_METHODS)
    assert mn.expand_methods(["patexgs-no-mip", "table2", "2dgs"]) == ["patexgs-no-mip", *paper.TABLE2_METHODS]
    assert mn.expand_methods(["table1", "table2"]) == [*paper.TABLE1_METHODS, "bbsplat+mip"]
    assert mn.expand_methods(["zoom-in"]) == ["3dgs", "2dgs", "mip-splatting", "patexgs", "patexgs+filter3d"]


def test_paper_figures_are_the_papers():
    assert {m: f[0] for m, f in paper.PAPER_TABLE1.items() if "(" not in m} == {
        "3dgs": 27.21, "2dgs": 27.16, "mip-splatting": 27.79, "bbsplat": 26.92, "bbsplat+adaptive": 27.11,
        "textured-gaussians": 27.26, "patexgs": 27.71}
    assert {m: f[8][0] for m, f in paper.PAPER_TABLE2.items()} == {
        "2dgs": 18.20, "bbsplat": 25.12, "bbsplat+mip": 27.20, "textured-gaussians": 19.00, "patexgs": 27.12}
    assert set(paper.PAPER_NAMES) == set(paper.TABLES_METHODS)
    assert paper.paper_name("patexgs(10%)") == "Ours(10%)" and paper.paper_name("patexgs-no-mip") is None


class _Run:
    def __init__(self, cfg):
        self.cfg = cfg
        self.scene = None
        self.summary = dict(num_gaussians=10)


def test_a_method_with_its_own_stage1_trains_from_scratch(monkeypatch, tmp_path):
    """The stage-1 rule: a method whose stage1_key differs from 2DGS's (here patexgs-no-mip given
    another normal-loss weight, a stage-1 field) trains from scratch in its own folder, is not
    compiled ahead from the 2DGS stage, and keeps the budget's cap; the others share stage 1."""
    import patexgs_jax.training as training

    calls = []

    def train(ds, cfg, out, **kw):
        calls.append((cfg, out, kw))
        return _Run(cfg)

    monkeypatch.setattr(training, "train", train)
    monkeypatch.setattr(training, "stage1_checkpoint", lambda run, cfg: run / "checkpoints" / "stage1" / "ck")
    base = StudyConfig.train_config

    def train_config(self, method, max_gaussians=None):
        cfg = base(self, method, max_gaussians)
        return dataclasses.replace(cfg, lambda_normal=0.5) if method == "patexgs-no-mip" else cfg

    monkeypatch.setattr(StudyConfig, "train_config", train_config)
    study = Study(tmp_path / "out", StudyConfig(iters_2dgs=12, iters_tex=8), use_lpips=False, verbose=False)
    monkeypatch.setattr(study, "evaluate", lambda *a: {s: dict(psnr=20.0, ssim=0.5, lpips=None, alias_psnr=None)
                                                       for s in "1248"} | dict(num_gaussians=10, storage_mb=1.0,
                                                                                train_seconds=1.0, render_ms=1.0))
    monkeypatch.setattr(study, "save", lambda: None)
    assert study.shares_stage1("patexgs") and not study.shares_stage1("patexgs-no-mip")
    runs = tmp_path / "runs"
    study._run_budget("a", None, runs, "10%", 30, ["2dgs", "patexgs", "patexgs-no-mip"])
    (s1, s1_out, s1_kw), (tex, tex_out, tex_kw), (own, own_out, own_kw) = calls
    assert s1.method == "2dgs" and s1_out == runs / "2dgs(10%)"
    assert [c.method for c in s1_kw["prepare"]] == ["patexgs"]  # not the method with its own stage 1
    assert tex.method == "patexgs" and tex_out == runs / "patexgs(10%)" and "stage1" in tex_kw
    assert own.method == "patexgs-no-mip" and own_out == runs / "patexgs-no-mip(10%)"
    assert "stage1" not in own_kw and own_kw["resume"] is True
    assert own.max_gaussians == 30 and tex.max_gaussians == 30 and own.lambda_normal == 0.5
    assert set(study.data["results"]["a"]) == {"2dgs(10%)", "patexgs(10%)", "patexgs-no-mip(10%)"}
    # Only methods with their own stage 1: the shared 2DGS stage is not trained at all.
    calls.clear()
    study._run_budget("b", None, runs, None, None, ["patexgs-no-mip"])
    assert [(c.method, o.name) for c, o, _ in calls] == [("patexgs-no-mip", "patexgs-no-mip")]


def _entry(p, zoom_in=None):
    e = {s: dict(psnr=p + i, ssim=0.8, lpips=0.2, alias_psnr=30.0 if s != "1" else None)
         for i, s in enumerate("1248")}
    e.update(storage_mb=1.5, num_gaussians=100, texels=10, train_seconds=3.0, render_ms=4.0, method="x")
    if zoom_in is not None:
        e["zoom_in"] = zoom_in
    return e


def test_tables_beside_the_paper_and_the_zoom_in_table():
    zoom = {z: dict(psnr=30.0 - int(z), ssim=0.9, lpips=None, views=2, source="images at factor 1")
            for z in ("2", "4", "8")}
    keys = ["patexgs", "2dgs", "patexgs-no-mip", "2dgs(10%)"]
    data = {"config": {"preset": "tiny"},
            "results": {"a": {k: _entry(20.0 + i, zoom if k in ("2dgs", "patexgs") else None)
                              for i, k in enumerate(keys)}}}
    md = tbl.tables_markdown(data)
    t1 = md.split("## Table 1 beside the paper")[1].split("##")[0]
    rows = [line for line in t1.splitlines() if line.startswith("| ") and "---" not in line][1:]
    # the paper's rows first, in its order, then the others; every row that ran
    assert [r.split(" | ")[0][2:] for r in rows] == ["2dgs", "patexgs", "patexgs-no-mip", "2dgs(10%)"]
    assert rows[0] == ("| 2dgs | 2DGS* | 21.00 | 27.16 | 0.800 | 0.802 | 0.200 | 0.237 | 100 | 1.50 | 3 | 4.0 |")
    assert rows[1].startswith("| patexgs | Ours | 20.00 | 27.71 | 0.800 | 0.816 | 0.200 | 0.197 |")
    assert rows[2].startswith("| patexgs-no-mip |  | 22.00 |  | 0.800 |  |")
    assert rows[3].startswith("| 2dgs(10%) | 2DGS*(10%) | 23.00 | 25.62 | 0.800 | 0.722 | 0.200 | 0.358 |")
    t2 = md.split("## Table 2 beside the paper")[1].split("##")[0]
    row = next(line for line in t2.splitlines() if line.startswith("| 2dgs |"))
    assert row == ("| 2dgs | 2DGS* | 21.00 | 27.16 | 0.800 | 0.802 | 22.00 | 25.82 | 0.800 | 0.805 | 23.00 | 21.31 "
                   "| 0.800 | 0.661 | 24.00 | 18.20 | 0.800 | 0.502 | 30.00 |")
    zi = md.split("## Zoom-in (Mip-Splatting's protocol)")[1].split("##")[0]
    rows = [line for line in zi.splitlines() if line.startswith("| ") and "---" not in line]
    assert rows[0] == ("| method | train res. PSNR | SSIM | LPIPS | x2 PSNR | SSIM | LPIPS | x4 PSNR | SSIM | LPIPS "
                       "| x8 PSNR | SSIM | LPIPS |")
    zoomed_in = "| 28.00 | 0.900 | - | 26.00 | 0.900 | - | 22.00 | 0.900 | - |"
    assert rows[1:] == [f"| patexgs | 20.00 | 0.800 | 0.200 {zoomed_in}", f"| 2dgs | 21.00 | 0.800 | 0.200 {zoomed_in}"]
    assert "a x2, a x4, a x8: images at factor 1" in zi
    # Studies without zoom-in entries (older files) have no zoom-in table.
    del data["results"]["a"]["2dgs"]["zoom_in"], data["results"]["a"]["patexgs"]["zoom_in"]
    assert "Zoom-in" not in tbl.tables_markdown(data)


def test_zoom_in_views_and_their_evaluation(tmp_path):
    """Zoomed-in test views come from the scene's finer images when the study's factor allows,
    else (the synthetic scene) from its analytic ground truth, pixel for pixel the same images; a
    model evaluated on them scores finite PSNR / SSIM at each zoom."""
    from experiments.study_zoom_in import evaluate_zoom_in, upscaled, zoom_in_views
    from patexgs_jax.data import load
    from patexgs_jax.data.synthetic import generate
    from patexgs_jax.padding import ViewRenderer
    from patexgs_jax.training.config import preset_config
    from patexgs_jax.training.trainer import init_scene

    path = generate(tmp_path / "scene", seed=0, num_views=9, width=32, height=24, supersample=2, num_points=200)
    ds = load(path, factor=2, verbose=False)
    views = list(ds.test_views)  # img_0000 and img_0008, 16 x 12
    zoomed = zoom_in_views(ds, views, (2, 4))
    (two, src2), (four, src4) = zoomed[2], zoomed[4]
    assert src2 == "images at factor 1" and src4.startswith("analytic ground truth")
    assert [v.name for v in two] == [v.name for v in views] and two[0].image.shape == (24, 32, 3)
    assert four[0].image.shape == (48, 64, 3)
    np.testing.assert_allclose(np.asarray(upscaled(views[0].camera, 2).K), np.asarray(two[0].camera.K), rtol=1e-6)
    # the analytic images are the generator's: at x2 (factor 1 on disk) they agree exactly
    full = load(path, verbose=False)
    analytic = zoom_in_views(full, [v.scaled(2) for v in full.test_views], (2,))[2][0]
    assert analytic is not None
    np.testing.assert_allclose(analytic[0].image, full.test_views[0].image, atol=1e-6, rtol=0)
    # a scene whose factor cannot be divided and which is not synthetic: unavailable, with the reason
    other = types.SimpleNamespace(factor=1.5, path=tmp_path, normalization=ds.normalization)
    (none, why), = zoom_in_views(other, views, (2,)).values()
    assert none is None and "not 2 times an integer factor" in why
    cfg = preset_config("tiny", method="2dgs", iters_2dgs=10, iters_tex=0, max_gaussians=200, sh_degree=0)
    scene = init_scene(ds.points, ds.colors, cfg)
    with ViewRenderer(scene, cfg.render_config()) as renderer:
        got = evaluate_zoom_in(renderer, {**zoomed, 8: (None, "why not")})
    assert list(got) == ["2", "4", "8"]
    for z in ("2", "4"):
        assert np.isfinite(got[z]["psnr"]) and -1 <= got[z]["ssim"] <= 1 and got[z]["views"] == 2
        assert got[z]["lpips"] is None
    assert got["8"] == dict(psnr=None, ssim=None, lpips=None, views=0, source="why not")


def test_a_studys_entries_are_labelled_points_of_the_tradeoffs_plot(tmp_path, capsys):
    """``python -m experiments.tradeoffs --from-study``: every entry of a study, whatever its method
    (names this tree may not have included), is a labelled point and a table row; one colour a budget."""
    from experiments import study_tradeoffs, tradeoffs
    from experiments.provenance import write_json

    keys = ["3dgs", "2dgs", "mip-splatting", "patexgs", "patexgs(10%)"]
    results = {"a": {k: _entry(20.0 + i) | dict(method=k.partition("(")[0], steps=20)
                     for i, k in enumerate(keys)}}
    data = {"version": {"git": "abc"}, "config": {"preset": "tiny", "machine": "x86_64"}, "results": results}
    record = study_tradeoffs.study_as_tradeoffs(data)
    assert list(record["runs"]) == keys and record["runs"]["3dgs"]["psnr"]["8"] == 23.0
    assert [e["label"] for e in record["knobs"]["methods"]] == keys[:4]
    assert [e["label"] for e in record["knobs"]["budget 10%"]] == ["patexgs(10%)"]
    md = tradeoffs.markdown(record)
    for k in keys:
        assert f"| {k} | {k.partition('(')[0]} | 3 | 4.0 |" in md
    write_json(tmp_path / "study" / "results.json", data)
    assert tradeoffs.main(["--from-study", str(tmp_path / "study"), "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "tradeoffs.png").read_bytes()[:4] == b"\x89PNG"
    assert "| mip-splatting |" in (tmp_path / "o" / "tradeoffs.md").read_text()
    assert tradeoffs.main(["--from-study", str(tmp_path / "nope")]) == 2
    assert "cannot read --from-study" in capsys.readouterr().err
