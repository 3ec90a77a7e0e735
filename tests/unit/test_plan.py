"""The run plan (:mod:`patexgs_jax.plan`, ``--plan``): its JSON and units, its memory model, the flag
it names when a run does not fit, and training's refusal before step 1 with the same advice.

Step times are stubbed here (``measured=``): the real steps are timed by the one integration test
(tests/integration/test_plan_cli.py) and checked against real runs by ``python -m experiments.plan_check``.
"""

from __future__ import annotations

import dataclasses
import json

import pytest

import patexgs_jax.data as data
from data_builders import make_colmap_scene  # noqa: E402
from patexgs_jax import memory, plan
from patexgs_jax.plan_steps import hms
from patexgs_jax.training import cli
from patexgs_jax.training.config import TrainConfig, preset_config
from patexgs_jax.training.run import train

MEASURED = dict(stage1=0.05, texture=0.08, compile_stage1=3.0, compile_texture=2.0, eval_view=0.01, eval_compile=1.0,
                steps=3, seconds=9.0, gaussians=500, scale=1.0, note="")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("plan") / "scene"
    make_colmap_scene(root, n_images=6, W=64, H=48, n_points=40)
    return root


@pytest.fixture
def ds(scene):
    return data.load(scene, test_every=3, verbose=False)


def test_plan_json_keeps_every_figure_with_its_unit(ds):
    cfg = preset_config("tiny", method="patexgs", max_gaussians=500)
    p = plan.make_plan(ds, cfg, devices=[plan.parse_device("rtx4090-24gb")], measured=dict(MEASURED))
    doc = json.loads(json.dumps(p.to_json()))
    assert doc["units"] == dict(bytes="B", seconds="s", texels="RGBA texels (float32 x 4 each)")
    assert set(doc["peak_bytes"]) == {"stage1", "texture", "eval"}
    assert all(isinstance(v, int) and v > 0 for v in doc["peak_bytes"].values())
    assert doc["peak_bytes"]["texture"] > doc["peak_bytes"]["stage1"]  # textures on top
    # (the 2DGS stage's step: the mean of its steps, those beside the compile ahead slower)
    assert doc["step_seconds"]["texture"] == 0.08 and doc["step_seconds"]["stage1"] == pytest.approx(
        doc["time_terms_seconds"]["stage1"] / 600) and doc["step_seconds"]["stage1"] > 0.05
    assert isinstance(doc["fits"], bool) and doc["fits"] and doc["fixes"] == []
    t = doc["time_terms_seconds"]
    k = doc["ahead_steps"]  # (the 2DGS steps beside the texture stage's compile ahead: 2 s of it at 2 x 50 ms)
    assert k == plan.ahead_steps(cfg, 0.05, 2.0, "cpu") == 20
    k2 = doc["compiles"]["warmup_ahead_steps"]  # (the warm-up's steps beside Eq. 7's layout's compile: 2 x 80 ms)
    assert k2 == plan.warmup_ahead_steps(cfg, 0.08, 2.0, "cpu") == 12
    assert t["stage1"] == pytest.approx((600 + k) * 0.05) and t["texture"] == pytest.approx((200 + k2) * 0.08)
    assert doc["total_seconds"] == pytest.approx(sum(t.values()))
    assert doc["steps"] == dict(stage1=600, texture=200)
    assert doc["gaussians"] == 500 and "cap" in doc["gaussians_from"]
    assert doc["texels_eq7"] > 0 and doc["texels_max"] >= doc["texels_eq7"] and doc["sigma"] > 0
    views = {(v["split"], v["padded_width"], v["padded_height"]) for v in doc["views"]}
    assert views == {("train", 64, 48), ("test", 64, 48)}
    assert [d["kind"] for d in doc["devices"]] == ["cpu", "gpu"]
    assert doc["devices"][1]["memory_bytes"] == int(0.75 * 24e9)
    # An untextured method has no texture stage.
    p2 = plan.make_plan(ds, TrainConfig(method="2dgs", max_gaussians=500), measured=dict(MEASURED, texture=None))
    assert p2.to_json()["peak_bytes"]["texture"] == 0 and p2.steps["texture"] == 0 and p2.texels_max == 0


def test_eq7_texels_use_the_real_allocation():
    """Every Gaussian the same share of every view: sigma is the pixel share, the side Eq. 7's."""
    from patexgs_jax import adaptive

    cfg = TrainConfig(method="patexgs")
    px = [128 * 96] * 20
    t, t_max, sigma, _ = plan.eq7_texels(px, 4000, cfg)
    assert sigma == pytest.approx(adaptive.pixel_share_sigma(sum(px), 4000))
    assert t == 4000 * 3 ** 2 and t_max > t  # 20 log2(1 + 2/20) = 2.75 -> side 3
    budget = plan.eq7_texels(px, 4000, TrainConfig(method="patexgs", texture_budget_mb=1.0))
    assert budget[0] == round(0.8 * (2**20 // 16)) and budget[1] == 2**20 // 16
    assert plan.eq7_texels(px, 10, TrainConfig(method="textured-fixed-8"))[:2] == (640, 640)


def test_memory_model_terms():
    px = plan.padded_pixels(1237, 822)
    kw = dict(train_pixels=px, eval_pixels=px, rgba_texels=9_000_000, textured=True)
    small = plan.stage_peaks("gpu", gaussians=1_000_000, device_bytes=int(18e9), **kw)
    large = plan.stage_peaks("gpu", gaussians=3_000_000, device_bytes=int(18e9), **kw)
    assert large["stage1"] - small["stage1"] == pytest.approx(2e6 * plan.GPU_BYTES_PER_GAUSSIAN, rel=1e-6)
    assert small["texture"] - small["stage1"] == pytest.approx(9_000_000 * plan.GPU_BYTES_PER_TEXEL, rel=1e-6)
    assert plan.texture_bytes(1) == pytest.approx(16 * (4 + 2 / 3) * 1.25)
    assert small["eval"] < small["stage1"]
    # The H100's measured step peaks (bench_scale, 1237x822, 1.1M / 3.3M slots) within 25%.
    for slots, texels, two_d, textured in ((1_100_000, 13_506_982, 1.76, 5.24), (3_300_000, 40_704_722, 4.70, 15.79)):
        p = plan.stage_peaks("gpu", gaussians=slots, device_bytes=int(60e9), train_pixels=px, eval_pixels=px,
                             rgba_texels=texels, textured=True)
        assert p["stage1"] == pytest.approx(two_d * 2**30, rel=0.25)
        assert p["texture"] == pytest.approx(textured * 2**30, rel=0.25)
    cpu = plan.stage_peaks("cpu", gaussians=4000, **kw)
    assert cpu["stage1"] == pytest.approx(plan.CPU_BASE_BYTES["stage1_textured"] + memory.BYTES_PER_PIXEL * px
                                          + memory.BYTES_PER_GAUSSIAN * 4000, rel=1e-6)
    assert cpu["eval"] == max(cpu["stage1"], cpu["texture"])  # the allocator keeps what training freed


def test_cpu_bases_give_the_peaks_of_the_runs_they_were_calibrated_on():
    """The CPU bases (2DGS stage, a textured run's 2DGS stage, texture stage) against the runs of
    ``experiments.plan_check`` on the embedded scene in empty compile caches that set them
    (docs/memory.md, "Measured error (CPU)"): every stage's peak within 10%."""
    from pathlib import Path

    calibration = Path(__file__).parents[2] / "benchmarks" / "plan_check_cpu_idle_cold_tiny_498959c.json"
    doc = json.loads(calibration.read_text())
    px = plan.padded_pixels(128, 96)
    for row in doc["results"]:
        textured = row["texels_eq7"] > 0
        p = plan.stage_peaks("cpu", train_pixels=px, eval_pixels=px, gaussians=row["gaussians"],
                             rgba_texels=int(row["texels_eq7"] * 1.1), textured=textured)
        for stage in ("stage1", "texture") if textured else ("stage1",):
            assert p[stage] == pytest.approx(row["measured"]["peak_bytes"][stage], rel=0.10), (row["case"], stage)


def test_the_2dgs_steps_beside_the_compile_ahead_are_slower(monkeypatch):
    """A textured run on a CPU compiles its texture stage's first programs ahead from its last
    densification: its 2DGS steps beside that compile take 2x as long (the plan's stage term), the
    compile is done by the stage's end (its term less), and where most of the stage shares the cores
    (beer's 150-step check never densifies: ahead from step 0) the stage's step, their mean, is slower."""
    tiny = preset_config("tiny", method="patexgs", iters_2dgs=300)  # last densification at 250: 50 steps at most
    assert plan.ahead_steps(tiny, 0.08, 30.0, "cpu") == 50
    assert plan.ahead_steps(tiny, 0.08, 4.0, "cpu") == 25  # 4 s at 2 x 80 ms a step
    assert plan.ahead_steps(tiny, 0.08, 30.0, "gpu") == 0
    assert plan.ahead_steps(dataclasses.replace(tiny, method="2dgs"), 0.08, 30.0, "cpu") == 0
    short = preset_config("cpu", method="patexgs", iters_2dgs=150, iters_tex=100)
    assert plan.ahead_steps(short, 0.13, 37.0, "cpu") == 142  # 37 s at 2 x 130 ms
    monkeypatch.setenv("PATEXGS_COMPILE_AHEAD", "0")
    assert plan.ahead_steps(short, 0.13, 37.0, "cpu") == 0


def test_more_padded_sizes_more_seconds_compiled_ahead_beside_the_2dgs_steps(ds):
    """A textured run's 2DGS stage compiles ahead Eq. 7's pair counter and renderer for each padded
    size of its training views: each size past the first adds AHEAD_SIZE_SHARE of a layout's compile
    to the compile ahead, so more of the stage's steps share the cores with it (slower: the stage's
    term and its step). One size: one layout's compile, as before."""
    assert plan.ahead_seconds(10.0) == plan.ahead_seconds(10.0, 1) == 10.0
    assert plan.ahead_seconds(10.0, 3) == pytest.approx(10.0 * (1 + 2 * plan.AHEAD_SIZE_SHARE))
    short = preset_config("cpu", method="patexgs", iters_2dgs=150, iters_tex=100)  # (ahead from step 0: 150 steps)
    assert plan.ahead_steps(short, 0.25, 21.7, "cpu", 1) == plan.ahead_steps(short, 0.25, 21.7, "cpu") == 43
    assert plan.ahead_steps(short, 0.25, 21.7, "cpu", 3) == int(21.7 * (1 + 2 * plan.AHEAD_SIZE_SHARE) / 0.5) > 43
    assert plan.ahead_steps(short, 0.25, 21.7, "cpu", 9) == 150  # (at most the window)
    assert plan.ahead_steps(dataclasses.replace(short, method="2dgs"), 0.25, 21.7, "cpu", 3) == 0
    cfg = preset_config("tiny", method="patexgs", max_gaussians=500)
    one, three = (plan.make_plan(ds, cfg, measured=dict(MEASURED, padded_sizes=n)) for n in (1, 3))
    assert one.ahead_steps == plan.ahead_steps(cfg, 0.05, 2.0, "cpu") and three.ahead_steps > one.ahead_steps
    assert three.time_terms["stage1"] > one.time_terms["stage1"]
    assert three.step_seconds["stage1"] > one.step_seconds["stage1"]


def test_more_padded_sizes_a_higher_cpu_peak_for_a_textured_run():
    """Each padded size of the training views past the first keeps its compiled programs resident
    on a CPU: CPU_SIZE_BYTES more in a textured run's stages (and so its evaluation's peak). One
    size: the bases alone, as before; an untextured run and a GPU's peaks do not change."""
    from patexgs_jax.plan_memory import padded_sizes

    kw = dict(train_pixels=320 * 176, eval_pixels=320 * 176, gaussians=4414, rgba_texels=40_000)
    one = plan.stage_peaks("cpu", textured=True, **kw)
    assert plan.stage_peaks("cpu", textured=True, sizes=1, **kw) == one
    three = plan.stage_peaks("cpu", textured=True, sizes=3, **kw)
    assert three["stage1"] - one["stage1"] == 2 * plan.CPU_SIZE_BYTES["stage1_textured"] > 0
    assert three["texture"] - one["texture"] == 2 * plan.CPU_SIZE_BYTES["texture"] > 0
    assert three["eval"] > one["eval"]
    assert plan.stage_peaks("cpu", textured=False, sizes=3, **kw) == plan.stage_peaks("cpu", textured=False, **kw)
    gpu = dict(kw, device_bytes=int(18e9))
    assert plan.stage_peaks("gpu", textured=True, sizes=3, **gpu) == plan.stage_peaks("gpu", textured=True, **gpu)
    # 64x48 and 64x33 pad to 64x48; 70x48 to 80x48.
    assert padded_sizes([(64, 48), (64, 33)]) == 1 and padded_sizes([(64, 48), (64, 33), (70, 48)]) == 2


def test_growth_events_that_overflow_a_bucket_compile_the_textured_step_again(ds, monkeypatch):
    """The texture stage compiles its step once for each layout: the start's, Eq. 7's after a warm-up,
    and the new layouts of the growth events that overflow a bucket (GROWTH_LAYOUT_SHARE of them),
    each at the plan's measured compile of one layout. More events, more compiling; no growth (fixed
    sizes), the layouts alone; no textures, none."""
    from patexgs_jax.schedule import growth_steps

    monkeypatch.setenv("PATEXGS_COMPILE_AHEAD", "0")  # (the compiles alone, nothing beside the steps)
    m = dict(MEASURED, texture_layouts=2)  # compile_texture 2.0 s timed over two layouts: 1.0 s each

    def compile_s(cfg):
        return plan.make_plan(ds, cfg, measured=dict(m)).time_terms["compile"]

    base = preset_config("tiny", method="patexgs", max_gaussians=500)
    events, grown = plan.growth_layouts(base)
    assert events == len(growth_steps(base)) == 8 and grown == pytest.approx(plan.GROWTH_LAYOUT_SHARE * 8)
    fewer = dataclasses.replace(base, growth_interval=2 * base.growth_interval)
    assert 0 < plan.growth_layouts(fewer)[0] < events
    more = plan.GROWTH_LAYOUT_SHARE * (events - plan.growth_layouts(fewer)[0])
    assert compile_s(base) - compile_s(fewer) == pytest.approx(1.0 * more) and more > 0
    first = compile_s(dataclasses.replace(base, method="2dgs"))  # (the 2DGS stage's compiles alone)
    fixed = dataclasses.replace(base, method="patexgs-fixed-8")
    assert plan.growth_layouts(fixed) == (0, 0.0) and plan.texture_layouts(fixed) == 2
    p = plan.make_plan(ds, fixed, measured=dict(m))
    assert p.time_terms["compile"] == pytest.approx(first + 1.0 * 2) and first > 0
    assert compile_s(base) == pytest.approx(first + 1.0 * (2 + grown))
    assert plan.texture_layouts(dataclasses.replace(base, warmup_tex=0)) == 1  # (Eq. 7 at the start: one layout)
    assert p.compiles["growth_events"] == 0 and plan.make_plan(ds, base, measured=dict(m)).compiles["layouts"] == 2


def test_the_run_s_first_steps_are_the_ones_the_plan_trained_untimed(ds, monkeypatch):
    """A scene's steps get cheaper as it trains: the plan trains its scene untimed before it times
    the 2DGS stage, and the run's first steps are those steps as they took, the others the timed
    (trained) step; the stage's step is their mean. Nothing settled: every step the timed one."""
    monkeypatch.setenv("PATEXGS_COMPILE_AHEAD", "0")
    cfg = preset_config("tiny", method="2dgs", max_gaussians=500)
    plain = plan.make_plan(ds, cfg, measured=dict(MEASURED, texture=None))
    slow = dict(MEASURED, texture=None, settled_steps=100, settled_ms=[80.0] * 100)  # untrained: 80 ms, timed 50
    p = plan.make_plan(ds, cfg, measured=slow)
    steps1 = p.steps["stage1"]
    assert plain.time_terms["stage1"] == pytest.approx(steps1 * 0.05)
    assert p.time_terms["stage1"] == pytest.approx(100 * 0.08 + (steps1 - 100) * 0.05)
    assert p.step_seconds["stage1"] == pytest.approx(p.time_terms["stage1"] / steps1)
    assert p.time_terms["compile"] == pytest.approx(plain.time_terms["compile"])
    assert "its first 100 as the plan trained its scene untimed" in p.text()


def test_the_evaluation_compiles_once_a_padded_size_and_ssim_once_a_view_size(ds):
    """The run's evaluation (32 training views, then the test views, one renderer for both) compiles
    its renderer once a padded size and SSIM once a view size, again where SSIM's programs were
    trimmed meanwhile; the plan's evaluation term counts both at its measured compiles."""
    from types import SimpleNamespace

    from patexgs_jax.camera import Camera
    from patexgs_jax.evaluation import MAX_METRIC_PROGRAMS, eval_programs

    rc = TrainConfig().render_config()
    K = [[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]]

    def view(w, h):
        return SimpleNamespace(camera=Camera(K=K, world_to_camera=[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                                     [0, 0, 0, 1]], width=w, height=h))

    # 64x48 and 60x40 pad to 64x48, 70x48 to 80x48: two padded sizes, three view sizes.
    assert eval_programs(([view(64, 48), view(60, 40)], [view(70, 48), view(64, 48)]), rc) == (2, 3)
    # More view sizes than SSIM keeps: the first ones compile again once the programs were trimmed.
    # (heights 20 to 28 all pad to two tiles: one padded size)
    many = [view(64, 20 + i) for i in range(MAX_METRIC_PROGRAMS + 1)]
    assert eval_programs((many, many[:2]), rc) == (1, MAX_METRIC_PROGRAMS + 1 + 2)
    # The embedded-size scene: one size, one renderer and one SSIM for both sets.
    assert eval_programs((ds.train_views[:32], ds.test_views), rc) == (1, 1)
    cfg = preset_config("tiny", method="patexgs", max_gaussians=500)
    m = dict(MEASURED, eval_compile=1.0, ssim_compile=0.25)
    n_eval = len(ds.test_views) + min(len(ds.train_views), 32)
    assert plan.make_plan(ds, cfg, measured=m).time_terms["eval"] == pytest.approx(n_eval * 0.01 + 0.75 + 0.25)
    # (a plan without SSIM's own compile: each padded size its measured evaluation compile)
    assert plan.make_plan(ds, cfg, measured=dict(MEASURED)).time_terms["eval"] == pytest.approx(n_eval * 0.01 + 1.0)


def test_the_plan_says_how_many_steps_it_timed(ds):
    """Cheap steps are timed until they add up to a few seconds: the plan names the count of each stage."""
    cfg = preset_config("tiny", method="patexgs", max_gaussians=500)
    timed = dict(MEASURED, timed_steps=dict(stage1=40, texture=22))
    assert "40 + 22 timed steps" in plan.make_plan(ds, cfg, measured=timed).text()
    same = dict(MEASURED, timed_steps=dict(stage1=5, texture=5))
    assert "5 timed steps a stage" in plan.make_plan(ds, cfg, measured=same).text()
    assert "3 timed steps a stage" in plan.make_plan(ds, cfg, measured=dict(MEASURED)).text()  # (an older plan's)
    alone = plan.make_plan(ds, TrainConfig(method="2dgs", max_gaussians=500),
                           measured=dict(MEASURED, texture=None, timed_steps=dict(stage1=31, texture=0)))
    assert "31 timed steps at" in alone.figures["step_seconds.stage1"]["from"]


@pytest.mark.parametrize("text,kind,size", [("h100-80gb", "gpu", 60e9), ("24GB", "gpu", 24e9),
                                            ("80GiB", "gpu", 80 * 2**30), ("cpu:16e9", "cpu", 16e9),
                                            ("25769803776", "gpu", 25769803776)])
def test_parse_device(text, kind, size):
    d = plan.parse_device(text)
    assert d.kind == kind and d.memory_bytes == int(size)


def test_parse_device_bad_input_names_the_forms():
    with pytest.raises(ValueError, match="h100-80gb, rtx4090-24gb, cpu-24gb or a memory size"):
        plan.parse_device("a100")


def test_a_plan_that_does_not_fit_names_the_flag(ds):
    cfg = preset_config("tiny", method="patexgs", max_gaussians=500_000)
    tight = plan.Device("tiny gpu", "gpu", int(1.2e9))
    p = plan.make_plan(ds, cfg, devices=[tight], measured=dict(MEASURED))
    d = p.devices[1]
    assert not d["fits"] and max(d["peak_bytes"].values()) > tight.memory_bytes
    assert any(f.startswith("--max-gaussians ") for f in d["fixes"]), d["fixes"]
    n = int(next(f for f in d["fixes"] if f.startswith("--max-gaussians")).split()[1])
    assert 0 < n < 500_000
    smaller = plan.make_plan(ds, preset_config("tiny", method="patexgs", max_gaussians=n), devices=[tight],
                             measured=dict(MEASURED))
    assert smaller.devices[1]["fits"]  # the named cap fits
    assert "to fit, pass --max-gaussians" in p.text()


def test_plan_cli_writes_nothing_but_its_json(scene, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(plan, "measure_steps", lambda *a, **k: {k_: v for k_, v in MEASURED.items()
                                                                 if k_ not in ("gaussians", "scale", "note")})
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "plan.json"
    code = cli.main(["--data", str(scene), "--method", "patexgs", "--preset", "tiny", "--plan", "--json", str(out),
                     "--max-gaussians", "100000", "--plan-device", "400MB"])
    text = capsys.readouterr().out
    assert code == 0 and "plan for patexgs" in text and "does NOT fit" in text and "to fit, pass" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.json"]
    doc = json.loads(out.read_text())
    assert {"peak_bytes", "step_seconds", "total_seconds", "fits"} <= set(doc)
    assert not doc["devices"][1]["fits"] and doc["devices"][1]["fixes"]


def test_plan_flags_need_plan(scene, tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["--data", str(scene), "--json", str(tmp_path / "x.json"), "--out", str(tmp_path / "o")])
    assert "--json writes the plan" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["--data", str(scene)])
    assert "--out" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_training_refuses_before_step_one_with_the_plans_advice(ds, tmp_path, monkeypatch):
    """A device too small: train() stops before its first step with the flags the plan names."""
    tight = plan.Device("tiny gpu", "gpu", int(0.5e9))
    monkeypatch.setattr(plan, "this_device", lambda: tight)
    monkeypatch.delenv("PATEXGS_SKIP_MEMORY_CHECK", raising=False)
    cfg = TrainConfig(method="2dgs", iters_2dgs=5, max_gaussians=400_000, checkpoint_every=1)
    advice = plan.memory_plan(ds, cfg, 400_000, 0, tight, 0)["fixes"]
    assert advice
    with pytest.raises(memory.NotEnoughMemory) as err:
        train(ds, cfg, tmp_path / "run", verbose=False)
    msg = str(err.value)
    assert "To fit, pass " + "; or ".join(advice) in msg and "PATEXGS_SKIP_MEMORY_CHECK=1" in msg
    assert not list((tmp_path / "run").glob("checkpoints/*.npz"))


def test_study_plan_covers_every_method_and_writes_nothing_else(scene, tmp_path, monkeypatch, capsys):
    from experiments import mipnerf360

    calls = []

    def measure(*a, **k):
        calls.append(a[1].method)
        return {k_: v for k_, v in MEASURED.items() if k_ not in ("gaussians", "scale", "note")}

    monkeypatch.setattr(plan, "measure_steps", measure)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "plans.json"
    code = mipnerf360.main(["--data", str(scene), "--methods", "2dgs,textured-fixed-4,patexgs", "--preset", "tiny",
                            "--plan", "--json", str(out)])
    assert code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plans.json"]  # no runs/mipnerf360
    docs = json.loads(out.read_text())
    assert [d["label"] for d in docs] == ["2dgs", "textured-fixed-4", "patexgs"]
    assert all({"scene", "peak_bytes", "step_seconds", "total_seconds", "fits"} <= set(d) for d in docs)
    assert docs[0]["steps"] == dict(stage1=800, texture=0)  # 2dgs continues its stage: equal steps
    assert calls == ["2dgs", "textured-fixed-4"]  # step times shared by the textured methods
    assert "plan for patexgs" in capsys.readouterr().out


def test_stage1_is_timed_at_the_mean_of_its_densification_ramp():
    cfg = preset_config("tiny", method="patexgs")  # 600 steps, densification from step 100 to 450
    assert plan.mean_stage1_gaussians(cfg, 3000, 4000) == round((3000 * 100 + 3500 * 350 + 4000 * 150) / 600)
    assert plan.mean_stage1_gaussians(cfg, 9000, 4000) == 4000  # the points are sampled down to the cap
    # A study's 2DGS run continues its stage at the final count.
    cont = preset_config("tiny", method="2dgs", continue_2dgs=200)
    assert plan.mean_stage1_gaussians(cont, 3000, 4000) == round((3000 * 100 + 3500 * 350 + 4000 * 350) / 800)


def test_a_stage_that_ends_before_its_first_densification_plans_for_its_points():
    """Densification acts strictly after ``start`` and before the stage's end (as the run's
    strategy): beer's 150-step check (``cpu`` preset, from step 100 every 50) never densifies, and
    its run kept its 4,414 points where the plan once planned the 6,000 cap."""
    from patexgs_jax.plan_counts import densify_events

    short = preset_config("cpu", method="2dgs", iters_2dgs=150, continue_2dgs=400)
    assert densify_events(short) == []
    assert plan.planned_gaussians(short, 4414)[0] == 4414
    assert plan.mean_stage1_gaussians(short, 4414, 4414) == 4414
    tiny = preset_config("tiny", method="patexgs", iters_2dgs=300)
    assert densify_events(tiny) == [150, 200, 250]
    assert plan.planned_gaussians(tiny, 3000)[0] == 4000  # the cap: densification fills it
    paper = densify_events(preset_config("paper"))  # (500 to 15,000 every 100: 600, ..., 14,900)
    assert paper[:2] == [600, 700] and len(paper) == 144


def test_steps_are_timed_on_views_of_one_padded_size(ds, monkeypatch):
    """A run compiles its step once per padded size: the plan's timed steps use the views of one
    size (the most common; ties: the largest), else they would time compiles, and the whole run's
    compile term counts every size."""
    from types import SimpleNamespace

    from patexgs_jax import plan_steps

    def view(w, h):
        return SimpleNamespace(camera=SimpleNamespace(width=w, height=h))

    views = [view(64, 48), view(70, 48), view(70, 50), view(64, 33)]
    cfg = preset_config("tiny", method="patexgs", max_gaussians=500)
    size, n, chosen = plan_steps._one_size(views, cfg)
    # 64x48 and 64x33 pad to 64x48; 70x48 and 70x50 to 80x48 and 80x64.
    assert (size, n) == ((48, 64), 3) and [v.camera.width for v in chosen] == [64, 64]
    size, n, chosen = plan_steps._one_size(views[1:3], cfg)  # one view each: the largest
    assert (size, n, len(chosen)) == ((64, 80), 2, 1)
    monkeypatch.setenv("PATEXGS_COMPILE_AHEAD", "0")  # (no compile ahead beside stage 1: the compiles alone)
    one = plan.make_plan(ds, cfg, measured=dict(MEASURED, padded_sizes=1)).time_terms["compile"]
    three = plan.make_plan(ds, cfg, measured=dict(MEASURED, padded_sizes=3)).time_terms["compile"]
    assert three == pytest.approx(3 * one) and one > 0


def test_progress_says_the_phase_at_least_every_interval():
    """The plan's progress lines: one when a phase starts, then one each time ``every`` seconds pass
    without a line (the clock mocked; the background thread calls :meth:`tick`)."""
    from patexgs_jax.plan_steps import Progress

    now, lines = [100.0], []
    pr = Progress(every=10.0, say=lines.append, clock=lambda: now[0])
    pr.tick()
    assert lines == []  # no phase yet: nothing to say
    pr.phase("compiling the 2DGS step")
    now[0] += 9.0
    pr.tick()
    assert lines == ["plan: compiling the 2DGS step"]
    now[0] += 1.0
    pr.tick()
    now[0] += 4.0
    pr.tick()  # (4 s after the last line: quiet)
    assert lines[1:] == ["plan: compiling the 2DGS step (10 s so far)"]
    now[0] += 6.0
    pr.tick()
    pr.phase("timing 3 steps of the 2DGS stage")
    assert lines[2:] == ["plan: compiling the 2DGS step (20 s so far)", "plan: timing 3 steps of the 2DGS stage"]
    with pr, pr:  # (entered again inside: one thread, stopped at the outer exit)
        assert pr._thread is not None and pr._thread.is_alive()
    assert not pr._thread.is_alive()


def test_eq6_is_counted_on_a_sample_of_the_views_and_scaled():
    """The plan's Eq. 7 allocation counts Eq. 6 on EQ6_SAMPLE_VIEWS views (evenly spaced), not all:
    the schedule renders the sample, its Eq. 7 sums are scaled by all / sampled views, and sigma is
    the pixel share of every view's pixels; on views that repeat, the sides equal the full count's."""
    from types import SimpleNamespace

    import numpy as np

    from patexgs_jax import adaptive, plan_steps
    from patexgs_jax.schedule import TextureSchedule

    views = [SimpleNamespace(name=f"v{i}", camera=SimpleNamespace(width=64, height=48)) for i in range(40)]
    sample = plan_steps.eq6_sample(views)
    assert len(sample) == plan_steps.EQ6_SAMPLE_VIEWS < len(views)
    assert [v.name for v in sample] == [f"v{i * 5}" for i in range(8)]
    assert plan_steps.eq6_sample(views[:5]) == views[:5]
    cfg = TrainConfig(method="patexgs")
    schedule = TextureSchedule(cfg, None, views, None)
    plan_steps.sample_eq6_counts(schedule, views, sample)
    assert schedule.train_views == sample  # what allocate() renders the counts of
    rng = np.random.default_rng(0)
    row = rng.integers(0, 60, size=500).astype(np.float32)  # one view's counts, every view alike
    act = np.ones(500, bool)
    sampled, sigma, _ = schedule.allocation_sides(adaptive.ContributionCounts.from_views([row] * 8, 500), act)
    assert schedule.train_views == sample
    full = TextureSchedule(cfg, None, views, None)
    want, want_sigma, _ = full.allocation_sides(adaptive.ContributionCounts.from_views([row] * 40, 500), act)
    assert sigma == pytest.approx(want_sigma) == pytest.approx(adaptive.pixel_share_sigma(40 * 64 * 48, 500))
    np.testing.assert_array_equal(sampled, want)
    unscaled = full.allocation_sides(adaptive.ContributionCounts.from_views([row] * 8, 500), act)[0]
    assert unscaled.sum() < want.sum()  # (without the scaling the sample would allocate less)


def _absurd(ds, stage1=4.0, texture=8.0):
    """A plan of the paper preset with step times of days on this CPU (the step timer stubbed)."""
    cfg = preset_config("paper", method="patexgs")
    measured = dict(MEASURED, stage1=stage1, texture=texture, gaussians=20_000, stage1_gaussians=12_000,
                    padded_size=[48, 64], padded_sizes=1, scale=150.0, note="scaled")
    return plan.make_plan(ds, cfg, measured=measured)


def test_a_plan_of_days_on_a_cpu_says_where_it_belongs_and_what_fits_here(ds, monkeypatch):
    from patexgs_jax import plan_devices

    monkeypatch.setattr(plan, "this_device", lambda: plan.Device("this CPU", "cpu", int(64e9)))
    p = _absurd(ds)
    assert p.total_seconds > 86400 and p.advice
    text = p.text()
    assert "days on this CPU: it belongs on a GPU" in text
    h100 = next(a for a in p.advice if "NVIDIA H100" in a)
    assert "bench_scale_h100" in h100 and "fits in its memory" in h100
    gpu = plan_devices.h100_run_seconds(steps1=30_000, steps2=30_000, gaussians=p.gaussians, pixels=64 * 48,
                                        stage1_gaussians=plan.mean_stage1_gaussians(preset_config("paper"),
                                                                                    len(ds.points), p.gaussians))
    assert f"about {hms(gpu['total'])}" in h100
    assert gpu["texture"] == pytest.approx(30_000 * (0.0889 + (0.2100 - 0.0889) / 2e6 * (p.gaussians - 1e6)))
    hour, night = [a for a in p.advice if a.startswith("here ")]
    assert hour.startswith("here in an hour: --preset ") and night.startswith("here in a night (10 h): --preset ")
    for line, budget in ((hour, 3600), (night, 36000)):
        preset, factor, cap = line.split("--preset ")[1].split()[0], int(line.split("--factor ")[1].split()[0]), \
            int(line.split("--max-gaussians ")[1].split()[0])
        # That command's own plan, with the same step timer, takes no more than the budget here.
        cfg = preset_config(preset, method="patexgs", max_gaussians=cap)
        secs = plan.plan_advice.scaled_seconds(
            dict(MEASURED, stage1=4.0, texture=8.0, gaussians=20_000, stage1_gaussians=12_000), cfg,
            points=len(ds.points), pixel_scale=plan.padded_pixels(round(64 / factor), round(48 / factor)) / (48 * 64),
            n_eval=len(ds.test_views) + min(len(ds.train_views), 32), compile_seconds=p.time_terms["compile"])
        assert secs <= budget and f"about {hms(secs)}" in line
    assert p.to_json()["advice"] == p.advice
    # A plan of hours says nothing of the kind.
    short = _absurd(ds, stage1=0.0005, texture=0.001)
    assert short.total_seconds < 86400 and not short.advice


def _stub_steps(stage1):
    """A step timer that records its calls and times every step at ``stage1`` s (texture twice)."""
    calls = []

    def measure(ds, cfg, gaussians, *, steps, stage1_gaussians=None, quick=False, progress=None, evaluate=True,
                **kw):
        calls.append(dict(method=cfg.method, gaussians=gaussians, steps=steps, quick=quick, evaluate=evaluate))
        textured = cfg.spec.textures is not None
        return dict(stage1=stage1, texture=2 * stage1 if textured else None, stage1_gaussians=stage1_gaussians,
                    compile_stage1=30.0, compile_texture=50.0 if textured else 0.0,
                    eval_view=0.1 if evaluate else None, eval_compile=5.0 if evaluate else None, steps=steps,
                    padded_size=[48, 64], padded_sizes=1, eq6_views=0, seconds=1.0)

    return calls, measure


def test_a_cpu_plan_of_days_times_the_2dgs_stage_alone_and_says_what_it_estimates(ds, monkeypatch):
    monkeypatch.setattr(plan, "this_device", lambda: plan.Device("this CPU", "cpu", int(64e9)))
    calls, measure = _stub_steps(4.0)  # 60,000 steps of 4 s: at least 2.8 days, unscaled
    monkeypatch.setattr(plan, "measure_steps", measure)
    p = plan.make_plan(ds, preset_config("paper", method="patexgs"), progress=False)
    assert calls == [dict(method="2dgs", gaussians=plan.MEASURE_MAX_GAUSSIANS, steps=plan.EXTRAPOLATED_STEPS,
                          quick=True, evaluate=False)]
    sc = p.gaussians / plan.MEASURE_MAX_GAUSSIANS
    assert p.step_seconds["stage1"] == pytest.approx(4.0 * sc)
    assert p.step_seconds["texture"] == pytest.approx(plan.TEXTURE_STEP_RATIO * 4.0 * sc)
    assert p.measured["eval_view"] == pytest.approx(plan.EVAL_STEP_SHARE * 4.0)
    assert p.measured["compile_texture"] == pytest.approx(plan.TEXTURE_COMPILE_RATIO * 30.0)
    f = p.to_json()["figures"]
    assert f["step_seconds.stage1"]["how"] == "extrapolated" and f["step_seconds.texture"]["how"] == "estimated"
    assert f["time_terms.eval"]["how"] == "estimated" and f["texels"]["how"] == "modelled"
    text = p.text()
    assert "texture (estimated)" in text and "  estimated: step_seconds.texture" in text
    assert "  extrapolated: step_seconds.stage1" in text and "days on this CPU: it belongs on a GPU" in text


def test_a_cpu_plan_of_less_than_days_goes_on_to_time_the_texture_stage(ds, monkeypatch):
    monkeypatch.setattr(plan, "this_device", lambda: plan.Device("this CPU", "cpu", int(64e9)))
    calls, measure = _stub_steps(0.01)  # 60,000 steps of 10 ms: 10 minutes at least
    monkeypatch.setattr(plan, "measure_steps", measure)
    p = plan.make_plan(ds, preset_config("paper", method="patexgs"), progress=False)
    assert [(c["method"], c["evaluate"]) for c in calls] == [("2dgs", False), ("patexgs", True)]
    f = p.to_json()["figures"]
    assert f["step_seconds.texture"]["how"] == "extrapolated" and "texture_estimated" not in p.measured
    # A plan at its own count (no extrapolation) times everything at once.
    calls.clear()
    p = plan.make_plan(ds, preset_config("tiny", method="patexgs", max_gaussians=500), progress=False)
    assert [(c["method"], c["quick"], c["evaluate"]) for c in calls] == [("patexgs", False, True)]
    assert p.to_json()["figures"]["step_seconds.stage1"]["how"] == "measured"


@pytest.mark.parametrize("method, first", [("patexgs", "2dgs"), ("bbsplat", "2dgs"), ("2dgs", "2dgs"),
                                           ("3dgs", "3dgs"), ("patexgs+filter3d", None)])
def test_stage1_method(method, first):
    assert plan.stage1_method(TrainConfig(method=method)) == first
