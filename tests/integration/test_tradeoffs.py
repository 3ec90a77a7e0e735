"""experiments/tradeoffs.py: the plan of a study, Pareto fronts, the Markdown table, a study end to
end on the embedded scene (few iterations, a third of its resolution: 42 x 32) with shared stage 1 and resume, and the
effect study with its reduced export.

The end-to-end tests share one module-scoped study (compiles dominate); its training settings match
the notebook test's, so in one pytest process the two reuse compiled steps.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from experiments import effects
from experiments import tradeoffs as tr
from patexgs_jax.training.config import preset_config, stage1_key

# The notebook's PATEXGS_NOTEBOOK_TINY settings (see notebooks/explore.ipynb).
TINY = dict(iters_2dgs=20, iters_tex=8, warmup_tex=3, growth_interval=1000, normal_from=10, sh_interval=5,
            checkpoint_every=1000, log_every=10, max_gaussians=600)


def base_config(**kw):
    return preset_config("tiny", method="patexgs", **dict(TINY, **kw))


# ------------------------------------------------------------------------------------------------
# Pure functions
# ------------------------------------------------------------------------------------------------
def brute_front(costs, quals):
    ok = [i for i in range(len(costs)) if np.isfinite(costs[i]) and np.isfinite(quals[i])]
    keep = []
    for i in ok:
        dominated = any((costs[j] <= costs[i] and quals[j] >= quals[i]) and (costs[j] < costs[i] or quals[j] > quals[i])
                        for j in ok)
        duplicate_before = any(costs[j] == costs[i] and quals[j] == quals[i] and j < i for j in ok)
        if not dominated and not duplicate_before:
            keep.append(i)
    return sorted(keep, key=lambda i: costs[i])


def test_pareto_front_hand_made():
    costs = [1.0, 2.0, 3.0, 4.0, 2.0, 5.0, 0.5]
    quals = [1.0, 3.0, 2.0, 5.0, 3.0, 5.0, np.nan]
    # 2 is dominated by 1 (cheaper, better); 4 duplicates 1; 5 costs more than 3 for the same quality;
    # 6 has no quality.
    assert tr.pareto_front(costs, quals) == [0, 1, 3]
    assert tr.pareto_front([1.0, 1.0], [1.0, 2.0]) == [1]  # same cost: only the better one
    assert tr.pareto_front([3.0, None, 1.0], [1.0, 9.0, 0.5]) == [2, 0]  # sorted by cost, None ignored
    assert tr.pareto_front([], []) == []


def test_pareto_front_matches_definition():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 12))
        c = rng.integers(0, 5, n).astype(float)  # ties on purpose
        q = rng.integers(0, 5, n).astype(float)
        assert tr.pareto_front(c, q) == brute_front(c, q)


def test_plan_shares_stage1_where_only_stage2_differs():
    base = preset_config("tiny", method="patexgs", iters_tex=60)
    entries = tr.plan(base, tr.KNOBS, base_gaussians=3900)
    by = {(e.knob, e.label): e.config for e in entries}
    assert entries[0].config == base
    key = stage1_key(base)
    for knob in ("mip", "texture"):
        for (k, _), cfg in by.items():
            if k == knob:
                assert stage1_key(cfg) == key
    modes = ("none", "nearest", "trilinear")
    assert {by[("mip", m)].render_config().mip for m in modes} == set(modes)
    assert by[("texture", "fixed 1x1")].method == "textured-fixed-1"
    assert by[("budget", "10%")].max_gaussians == 390 and by[("budget", "1%")].max_gaussians == 39
    assert by[("budget", "100%")] == base
    half = by[("iters", "50%")]
    assert (half.iters_2dgs, half.iters_tex, half.densify.stop, half.sh_interval) == (300, 30, 225, 75)
    assert by[("iters", "100%")] == base
    assert [by[("sh", f"degree {d}")].sh_degree for d in range(4)] == [0, 1, 2, 3]
    for (k, _), cfg in by.items():
        if k in ("budget", "iters", "sh") and cfg != base:
            assert stage1_key(cfg) != key
    # Without the base run's count only the 100 % budget entry is planned.
    assert [e.label for e in tr.plan(base, ["budget"])] == ["100%"]
    # The stage-1 run of a textured entry is the texture knob's 2DGS entry.
    assert tr.run_id(tr.stage1_config(by[("mip", "none")], base)) == tr.run_id(by[("texture", "none (2DGS)")])
    with pytest.raises(ValueError, match="unknown knob"):
        tr.plan(base, ["speed"])


def test_markdown_table():
    def run(rid, method, ts, ms, p1, p2):
        return dict(run=rid, method=method, train_seconds=ts, render_ms={"1": ms, "2": ms / 4},
                    psnr={"1": p1, "2": p2}, ssim={"1": 0.5, "2": 0.5}, num_gaussians=100, storage_mb=1.5)

    study = dict(data="/x/scene", preset="tiny", scales=[1, 2], machine="test",
                 runs={"a": run("a", "patexgs", 100.0, 50.0, 25.0, 24.0),
                       "b": run("b", "2dgs", 50.0, 10.0, 22.0, 24.5)},
                 knobs={"texture": [dict(label="adaptive", value="adaptive", run="a"),
                                    dict(label="none (2DGS)", value=0, run="b"),
                                    dict(label="fixed 4x4", value=4, run="c")]})
    study["pareto"] = tr.pareto_sets(study["runs"], study["scales"])
    assert study["pareto"]["train_seconds"] == {"1": ["b", "a"], "2": ["b"]}
    text = tr.markdown(study)
    lines = text.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("| setting"))
    assert lines[head].count("|") == lines[head + 1].count("|") == lines[head + 2].count("|")
    row_a = next(line for line in lines if line.startswith("| adaptive"))
    row_b = next(line for line in lines if line.startswith("| none (2DGS)"))
    assert "| 25.00 | 24.00 |" in row_a and "Tx1,Rx1" in row_a and "x2" not in row_a.split("|")[-2]
    assert "| 22.00 | 24.50 |" in row_b and "Tx1,Rx1,Tx2,Rx2" in row_b
    assert "(not run yet)" in next(line for line in lines if line.startswith("| fixed 4x4"))


# ------------------------------------------------------------------------------------------------
# End to end
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dataset():
    from patexgs_jax.data import load
    from patexgs_jax.data.synthetic import ensure_default_scene

    return load(str(ensure_default_scene()), factor=3)  # as the notebook's PATEXGS_NOTEBOOK_TINY


@pytest.fixture(scope="module")
def study(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("tradeoffs")
    st = tr.Study(dataset, base_config(), out, data_name="embedded", preset="tiny", scales=(1, 2), verbose=False,
                  render_views=1)
    state = st.run(["texture"], fixed_sizes=(1,))
    return st, state


@pytest.mark.slow
def test_study_end_to_end(study):
    st, state = study
    saved = json.loads(st.path.read_text())
    assert saved == json.loads(json.dumps(state))
    assert saved["schema"] == tr.SCHEMA and saved["scales"] == [1, 2] and saved["base"] == tr.config_json(st.base)
    labels = [e["label"] for e in saved["knobs"]["texture"]]
    assert labels == ["none (2DGS)", "fixed 1x1", "adaptive"]
    runs = saved["runs"]
    assert len(runs) == 3
    s1 = next(r for r in runs.values() if r["method"] == "2dgs")
    for r in runs.values():
        assert set(r["psnr"]) == set(r["ssim"]) == set(r["render_ms"]) == {"1", "2"}
        assert all(5.0 < v < 60.0 for v in r["psnr"].values())
        assert r["alias_psnr"]["1"] is None and 10.0 < r["alias_psnr"]["2"] < 80.0
        assert all(v > 0 for v in r["render_ms"].values())
        extra = dict(continue_2dgs=st.base.iters_tex) if r["method"] == "2dgs" else {}
        assert r["config"] == tr.config_json(dataclasses.replace(st.base, method=r["method"], **extra))
        assert r["steps"] == st.base.iters_2dgs + st.base.iters_tex  # equal steps: 2dgs continues its stage
        if r["method"] != "2dgs":
            # Stage 1 shared: started from the 2DGS run's checkpoint, its time counted.
            assert r["stage1_run"] == s1["run"] and 0 < r["stage1_seconds"] < s1["train_seconds"]
            assert r["train_seconds"] > r["stage1_seconds"]
            summary = json.loads((st.out / "runs" / r["run"] / "summary.json").read_text())
            assert summary["stage1_from"].startswith(str(st.out / "runs" / s1["run"]))
            assert r["texels"] > 0
    # Pareto fronts hold evaluated runs and agree with pareto_front on the stored numbers.
    ids = list(runs)
    for s in ("1", "2"):
        front = tr.pareto_front([runs[r]["render_ms"][s] for r in ids], [runs[r]["psnr"][s] for r in ids])
        want = [ids[i] for i in front]
        assert saved["pareto"]["render_ms"][s] == want
    assert (st.out / "tradeoffs.png").stat().st_size > 10_000
    md = (st.out / "tradeoffs.md").read_text()
    assert "## texture" in md and "textured-fixed-1" in md and "(not run yet)" not in md
    assert "alias x2" in md and f"{runs[ids[-1]]['alias_psnr']['2']:.2f}" in md


@pytest.mark.slow
def test_study_resume_skips_finished(study, dataset, no_training):
    st, state = study
    again = tr.Study(dataset, st.base, st.out, data_name="embedded", preset="tiny", scales=(1, 2), verbose=False,
                     render_views=1)
    assert again.run(["texture"], fixed_sizes=(1,))["runs"] == state["runs"]
    # A run trained but not yet evaluated (killed during evaluation) is evaluated from its checkpoint,
    # not trained again.
    saved = json.loads(st.path.read_text())
    rid = next(r for r, v in saved["runs"].items() if v["method"] == "textured-fixed-1")
    del saved["runs"][rid]
    st.path.write_text(json.dumps(saved))
    third = tr.Study(dataset, st.base, st.out, data_name="embedded", preset="tiny", scales=(1, 2), verbose=False,
                     render_views=1)
    rec = third.run(["texture"], fixed_sizes=(1,))["runs"][rid]
    assert rec["psnr"] == pytest.approx(state["runs"][rid]["psnr"], abs=1e-5)
    assert rec["train_seconds"] == state["runs"][rid]["train_seconds"]
    # Another base configuration in the same folder is refused.
    with pytest.raises(ValueError, match="another base configuration"):
        tr.Study(dataset, base_config(seed=1), st.out, data_name="embedded", preset="tiny", scales=(1, 2))


@pytest.mark.slow
def test_notebook_executes_on_the_study_run(study, tmp_path, monkeypatch):
    """notebooks/explore.ipynb top to bottom on the study's PATexGS run (embedded scene)."""
    from test_notebook import execute_notebook

    st, state = study
    rid = next(r for r, v in state["runs"].items() if v["method"] == "patexgs")
    ns = execute_notebook(tmp_path, monkeypatch, st.out / "runs" / rid)
    assert ns["scene"].num_active() == state["runs"][rid]["num_gaussians"]


@pytest.mark.slow
def test_effects_and_reduced_export(study, dataset, tmp_path):
    from patexgs_jax.export import load_ply

    st, state = study
    rid = next(r for r, v in state["runs"].items() if v["method"] == "patexgs")
    run_dir = st.out / "runs" / rid
    scene, rc, _ = effects.load_trained(run_dir)
    assert effects.present_effects(scene, rc) == list(effects.EFFECTS)
    res = effects.run_effects(run_dir, dataset, tmp_path, scales=(1,), drop_below=1e9, verbose=False, max_views=1)
    assert json.loads((tmp_path / "effects.json").read_text())["reduced"]["dropped"] == list(effects.EFFECTS)
    full = res["full"]["psnr"]["1"]
    for v in res["effects"].values():
        assert v["gain_db"]["1"] == pytest.approx(full - v["off"]["psnr"]["1"], abs=1e-9)
    # The reduced export: no textures, DC colour only, no mipmaps; it loads and renders the same
    # image as switching the effects off in memory, with no more work.
    red = res["reduced"]
    sc = load_ply(red["path"])
    assert sc.rgb is None and sc.alpha is None and sc.sh.shape[1] == 1
    assert effects.load_render_config(red["path"]).mip == "none"
    off_scene, off_rc = effects.without(scene, rc, effects.EFFECTS)
    direct = effects.measure(off_scene, dataset.test_views, off_rc, scales=(1,), max_views=1)
    assert red["measure"]["psnr"]["1"] == pytest.approx(direct["psnr"]["1"], abs=1e-3)
    assert red["flops"]["reduced"] is not None and red["flops"]["reduced"] <= red["flops"]["full"]
    # Nothing contributes less than -inf dB: nothing is dropped.
    assert effects.droppable(res, -np.inf) == []
