"""The training loop end to end on a tiny synthetic COLMAP scene (48 x 32 images, 400 SfM points):
both stages learn, resume equals an uninterrupted run, optimiser state follows densification,
recompiles are counted and absent in steady state, non-finite steps are skipped (and repeated ones
stop the run), the texture budget is met, the CLI, the method names, and a real capture.

Compiles dominate the runtime, so the tests share one scene (fixed image size) and one main run
(``run_p``, patexgs with densification, Eq. 7 allocation and growth), and use few steps. Within one
process JAX reuses the executables of identical step functions, so the resumed runs and the small
runs mostly hit compiled code; the CLI subprocesses share a persistent compilation cache.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from backends import NOT_BITWISE, bitwise_reproducible
from locations import BEER
from patexgs_jax import adaptive, losses
from patexgs_jax import checkpoint as ckpt
from patexgs_jax import densify as dens
from patexgs_jax import schedule as texture_schedule
from patexgs_jax.data import load
from patexgs_jax.densify import DensifyConfig
from patexgs_jax.evaluation import evaluate
from patexgs_jax.metrics import mb_to_texels
from patexgs_jax.optim import adam_moments
from patexgs_jax.schedule import TextureSchedule, growth_schedule, growth_steps
from patexgs_jax.training.config import FIXED_SIZES, PRESETS, Method, TrainConfig, preset_config
from patexgs_jax.training.run import stage1_checkpoint, train
from patexgs_jax.training.step import AHEAD_STEP_TRACES, STEP_TRACES
from patexgs_jax.training.steps import PROCESS, StepProvider
from patexgs_jax.training.trainer import STAGE1_DIR, Trainer, init_scene
from train_configs import tiny_config

PER_GAUSSIAN = ("means", "log_scales", "quats", "opacity_logits", "sh", "active")
NO_DENSIFY = DensifyConfig(start=10_000, stop=10_001, opacity_reset_interval=10_000)


class Killed(Exception):
    """Stands in for the process being killed (raised from a hook, in-process)."""


def train_killed(dataset, config, out, kill_after: int, resume: bool):
    """Trains until ``kill_after`` steps are complete (after their host-side work, before a
    checkpoint of that step is written), then 'dies'."""
    orig = Trainer.after_step

    def after_step(self, step):
        orig(self, step)
        if step == kill_after:
            raise Killed(step)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Trainer, "after_step", after_step)
        with pytest.raises(Killed):
            train(dataset, config, out, resume=resume, verbose=False)


def ckpt_step(out) -> int:
    latest = ckpt.latest_checkpoint(Path(out) / "checkpoints")
    return -1 if latest is None else int(ckpt.read_metadata(latest)["step"])


def host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def assert_trees_equal(a, b, what: str, atol: float = 1e-6):
    """Same structure, shapes and dtypes; values within ``atol`` (NaNs equal)."""
    chex.assert_trees_all_equal_shapes_and_dtypes(a, b, custom_message=what)
    chex.assert_trees_all_close(a, b, rtol=0, atol=atol, custom_message=what)


def all_finite(tree) -> bool:
    return all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(host(tree)))


def alignment_problems(scene, opt_state) -> list[str]:
    """Adam moments laid out like the scene, and zero on inactive slots."""
    problems = []
    inactive = np.asarray(scene.active) == 0
    for name, m in zip(("mu", "nu"), adam_moments(opt_state)):
        ls, ds = jax.tree_util.tree_flatten(scene)
        lm, dm = jax.tree_util.tree_flatten(m)
        if ds != dm:
            problems.append(f"{name}: structure differs from the scene")
            continue
        if [np.shape(x) for x in ls] != [np.shape(x) for x in lm]:
            problems.append(f"{name}: shapes differ from the scene")
        for f in PER_GAUSSIAN:
            v = np.asarray(getattr(m, f))
            if v.shape[0] != inactive.shape[0] or np.any(v[inactive] != 0):
                problems.append(f"{name}.{f}: non-zero moments on inactive slots")
    return problems


# ------------------------------------------------------------------------------------------------
# Shared data and the main run
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def compile_cache():
    """The session's persistent compilation cache folder (tests/conftest.py), for this module's CLI
    subprocesses: they load the programs this process already compiled."""
    return Path(jax.config.jax_compilation_cache_dir)


@pytest.fixture(scope="module")
def dataset(synthetic_scene_dir, tmp_path_factory):
    ds = load(synthetic_scene_dir, factor=1, test_every=5, cache_dir=tmp_path_factory.mktemp("cache"), verbose=False)
    assert len(ds.train_views) == 8 and len(ds.test_views) == 2 and len(ds.points) == 400
    return ds


@pytest.fixture(scope="module")
def run_p(dataset, tmp_path_factory):
    """The main run (uninterrupted), instrumented: PSNR before training and at the end of stage 1,
    every (capacity, scene layout) key the provider gives a step for, moment alignment after every
    step's host-side work (densification, growth), pruned slots."""
    cfg = tiny_config()
    out = tmp_path_factory.mktemp("run_p")
    rec = dict(keys=set(), problems=[], capacities=set(), pruned=0, checks=0, traced=[], resizes=[])
    init = init_scene(dataset.points, dataset.colors, cfg)
    rec["psnr_init"] = evaluate(init, dataset.train_views, cfg.render_config())["psnr"]
    orig_get, orig_after, orig_start = StepProvider.get, Trainer.after_step, TextureSchedule.start
    orig_resize = texture_schedule.resize_textures

    def get_step(self, layout, render_cfg, capacity):  # (the provider's step for the scene's shapes)
        rec["keys"].add((capacity, layout))
        return orig_get(self, layout, render_cfg, capacity)

    def after_step(self, step):
        if sum(STEP_TRACES.values()) > rec.setdefault("seen", traces):  # the step just run traced
            rec["traced"].append(step - 1)
            rec["seen"] = sum(STEP_TRACES.values())
        rec["step"] = step
        before = np.asarray(self.scene.active) > 0
        orig_after(self, step)
        after = np.asarray(self.scene.active) > 0
        rec["pruned"] += int(np.sum(before & ~after[: before.size]))
        rec["capacities"].add(self.scene.capacity)
        rec["problems"] += [f"step {step}: {p}" for p in alignment_problems(self.scene, self.opt_state)]
        rec["checks"] += 1

    def resize(*args, **kwargs):
        out = orig_resize(*args, **kwargs)
        rec["resizes"].append((rec["step"], out[2].shapes_changed))
        return out

    def start_textures(self, state):
        rec["psnr_stage1"] = evaluate(state.scene, self.train_views, self.render_config)["psnr"]
        return orig_start(self, state)

    traces, ahead_traces = sum(STEP_TRACES.values()), sum(AHEAD_STEP_TRACES.values())
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(StepProvider, "get", get_step)
        mp.setattr(Trainer, "after_step", after_step)
        mp.setattr(TextureSchedule, "start", start_textures)
        mp.setattr(texture_schedule, "resize_textures", resize)
        result = train(dataset, cfg, out, verbose=False)
    rec["traces"] = sum(STEP_TRACES.values()) - traces
    rec["ahead_traces"] = sum(AHEAD_STEP_TRACES.values()) - ahead_traces
    tree, meta = ckpt.load_checkpoint(ckpt.latest_checkpoint(out / "checkpoints"))
    return dict(cfg=cfg, out=out, result=result, rec=rec, final=tree, meta=meta)


# ------------------------------------------------------------------------------------------------
# 1. Both stages learn
# ------------------------------------------------------------------------------------------------
def test_both_stages_improve(run_p):
    rec, s, final = run_p["rec"], run_p["result"].summary, run_p["final"]
    assert s["steps"] == run_p["cfg"].total_steps == 54 and s["skipped_steps"] == 0
    assert rec["psnr_stage1"] > rec["psnr_init"] + 1.0, rec
    assert s["train_psnr"] >= rec["psnr_stage1"] - 0.25, (s["train_psnr"], rec)
    assert s["train_psnr"] > rec["psnr_init"] + 1.0
    assert s["test_psnr"] is not None and np.isfinite(s["test_psnr"])
    # Stage 2: textures exist, Eq. 7 ran at step 33 = 30 + warm-up 3, growth events happened.
    alloc = s["allocation"]
    assert alloc is not None and alloc["step"] == 33 and alloc["budget_texels"] is None
    assert alloc["texels"] > s["num_gaussians"]  # sizes above 1 x 1 (Eq. 7 with the default sigma)
    sizes, counters = np.asarray(final["tex_sizes"]), np.asarray(final["tex_counters"])
    assert counters[1] == 5 and counters[0] == 48  # growth at 36, 39, 42, 45, 48
    assert counters[2] > 0, "no texture grew in five growth events"
    assert s["texels"] > 0 and s["texels_rgb"] == s["texels_alpha"] >= alloc["texels"] // 2
    scene = run_p["result"].scene
    act = np.asarray(scene.active) > 0
    np.testing.assert_array_equal(np.asarray(scene.rgb.size)[act], adaptive.side_of(sizes, 6)[act])
    assert np.all(np.asarray(scene.rgb.size)[act] >= 1) and np.all(np.asarray(scene.rgb.size)[~act] == 0)
    assert all_finite(scene)
    stamped = [json.loads(line) for line in (run_p["out"] / "log.jsonl").read_text().splitlines()]
    # Every record carries its wall-clock time and the seconds since the run started, in order.
    assert all(r["time"].endswith("Z") for r in stamped)
    assert all(0 < a["elapsed_s"] <= b["elapsed_s"] for a, b in zip(stamped, stamped[1:]))
    log = [{k: v for k, v in r.items() if k not in ("time", "elapsed_s")} for r in stamped]
    assert [r for r in log if r.get("event") == "allocation"] == [dict(event="allocation", **alloc)]
    # What the schedule did: the Eq. 7 sides, each growth event that grew textures, the final sides.
    assert sum(alloc["sides"].values()) == s["num_gaussians"]
    assert 2 * sum(int(k) ** 2 * v for k, v in alloc["sides"].items()) == alloc["texels"]  # RGB + alpha
    events = s["growth_events"]
    assert [r for r in log if r.get("event") == "growth"] == [dict(event="growth", **e) for e in events]
    assert len(events) >= 1 and all(e["step"] in (36, 39, 42, 45, 48) and e["grown"] > 0 for e in events)
    assert sum(e["grown"] for e in events) == counters[2]
    # An event that overflowed a bucket says so, and its next step compiled (this process's record).
    assert all(isinstance(e["layout_changed"], bool) for e in events)
    assert {e["step"] for e in events if e["layout_changed"]} <= set(s["compiled_at_steps"]), (events, s)
    texels = alloc["texels"]
    for e in events:
        assert e["texels_added"] > 0 and e["texels"] == texels + e["texels_added"]
        texels = e["texels"]
    assert texels == s["texels"] == s["texels_rgb"] + s["texels_alpha"]
    assert s["sides_final"] == {str(int(k)): int(v) for k, v in zip(*np.unique(np.asarray(scene.rgb.size)[act],
                                                                        return_counts=True))}
    assert log[-1]["step"] == 54 and log[-1]["texels"] == s["texels"]
    # The progress lines count texels as the texture-stage lines do (RGB and alpha texels, sides shared).
    assert log[-1]["texels"] == s["texels"] == texels


# ------------------------------------------------------------------------------------------------
# 2. Resume equals uninterrupted
# ------------------------------------------------------------------------------------------------
def test_resume_equals_uninterrupted(run_p, dataset, tmp_path):
    if not bitwise_reproducible():
        pytest.skip(NOT_BITWISE)
    cfg, out = run_p["cfg"], tmp_path / "run_b"
    ahead_traces = sum(AHEAD_STEP_TRACES.values())
    # Killed in stage 1 at step 5: the newest checkpoint (step 3) was written right after the
    # densification that doubled the capacity (no tile capacity fitted yet).
    train_killed(dataset, cfg, out, kill_after=5, resume=False)
    assert ckpt_step(out) == 3
    tree, _ = ckpt.load_checkpoint(ckpt.latest_checkpoint(out / "checkpoints"))
    assert tree["scene"].capacity == 1024 and int(tree["capacity"][0]) == 0
    # ... but the tile capacity of the steps before is kept as the refit's floor (a scene that grew
    # needs no fewer pairs: a smaller capacity would overflow and compile again).
    assert int(tree["capacity_floor"][0]) >= 1024
    # Killed in stage 2 before the Eq. 7 allocation (resumes from step 33, allocation redone) ...
    train_killed(dataset, cfg, out, kill_after=35, resume=True)
    assert ckpt_step(out) == 33
    # ... and after two growth events (resumes with a texture schedule state).
    train_killed(dataset, cfg, out, kill_after=41, resume=True)
    assert ckpt_step(out) == 39
    result = train(dataset, cfg, out, resume=True, verbose=False)
    assert result.summary["steps"] == 54
    # The same executables on the same inputs (see tests/backends.py): expect bitwise equality.
    chex.assert_trees_all_equal(result.scene, run_p["result"].scene, custom_message="scene")  # bitwise
    final, _ = ckpt.load_checkpoint(ckpt.latest_checkpoint(out / "checkpoints"))
    for key in ("opt_state", "stats", "tex_sizes", "tex_counters", "capacity", "capacity_floor"):
        assert_trees_equal(final[key], run_p["final"][key], key)
    assert np.asarray(final["counters"])[0] == 54
    for key in ("allocation", "growth_events", "sides_final"):
        assert result.summary[key] == run_p["result"].summary[key], key
    # Every step these runs took was one run_p's compiled (the steps of one process are shared), so
    # compiling ahead, which found them there, traced none.
    assert sum(AHEAD_STEP_TRACES.values()) == ahead_traces
    # A finished run resumes to itself; without resume the directory is refused.
    again = train(dataset, cfg, out, resume=True, verbose=False)
    assert_trees_equal(again.scene, result.scene, "scene after a no-op resume")
    with pytest.raises(FileExistsError, match="resume"):
        train(dataset, cfg, out, verbose=False)
    with pytest.raises(ValueError, match=r"different configuration \(seed differ"):
        train(dataset, dataclasses.replace(cfg, seed=1), out, resume=True, verbose=False)
    # Fields that only change how a run executes may differ on resume.
    other = dataclasses.replace(cfg, log_every=7, checkpoint_every=cfg.checkpoint_every + 1, devices=1)
    assert_trees_equal(train(dataset, other, out, resume=True, verbose=False).scene, result.scene, "log_every")


# ------------------------------------------------------------------------------------------------
# 3. Optimiser state follows densification
# ------------------------------------------------------------------------------------------------
def test_optimizer_state_aligned_through_densification(run_p):
    rec = run_p["rec"]
    assert rec["checks"] == 54 and rec["problems"] == []
    assert rec["capacities"] == {512, 1024}  # doubled at the first densification (step 3)
    assert rec["pruned"] > 0, "no Gaussian was pruned: the inactive-slot check saw no freed slots"
    final = run_p["final"]
    assert alignment_problems(final["scene"], final["opt_state"]) == []
    assert final["stats"].capacity == final["scene"].capacity
    mu, _ = adam_moments(final["opt_state"])
    # Texel moments have the texture buckets' shapes.
    for name in ("rgb", "alpha"):
        assert ([b.shape for b in getattr(mu, name).buckets]
                == [b.shape for b in getattr(final["scene"], name).buckets])


# ------------------------------------------------------------------------------------------------
# 4. Recompiles
# ------------------------------------------------------------------------------------------------
def test_recompiles_counted(run_p):
    rec, s = run_p["rec"], run_p["result"].summary
    # One trace per distinct (tile capacity, scene / optimiser / statistics shapes) the step saw:
    # at least 512 -> 1024 Gaussians, the texture banks' appearance, the allocation's buckets; the
    # texture stage's first one may have been traced and compiled ahead, in the background
    # (patexgs_jax.background, test_ahead), and then the step itself traces nothing.
    assert s["recompiles"] == rec["traces"] and len(rec["keys"]) >= 4
    assert rec["traces"] <= len(rec["keys"]) <= rec["traces"] + rec["ahead_traces"], rec
    # Growth events that fit the texture buckets' headroom keep the layout and compile nothing.
    growth = [(step, changed) for step, changed in rec["resizes"] if step in growth_steps(run_p["cfg"])]
    kept = [step for step, changed in growth if not changed]
    assert kept, growth
    assert not set(kept) & set(rec["traced"]), (kept, rec["traced"])


def test_steady_state_has_one_trace(dataset):
    cfg = tiny_config(method="2dgs", iters_2dgs=12, densify=NO_DENSIFY)
    PROCESS.release_steps()  # (the main run's first steps have these shapes: its program would serve this run)
    traces = sum(STEP_TRACES.values())
    result = train(dataset, cfg, None, verbose=False)
    assert result.summary["recompiles"] == 1
    assert sum(STEP_TRACES.values()) - traces == 1



def test_runs_of_other_lengths_and_rates_share_the_step_and_train_as_alone(dataset, tmp_path):
    """The step's learning rates (the means' decay over the stage's length included), scene radius
    and loss weights are its arguments: a run with another stage length, other rates and another
    SSIM weight traces no step where an earlier run compiled its shapes, and ends exactly where it
    ends with a step of its own."""
    first = tiny_config(method="2dgs", iters_2dgs=12, densify=NO_DENSIFY)
    other = dataclasses.replace(tiny_config(method="2dgs", iters_2dgs=8, densify=NO_DENSIFY, lambda_dssim=0.3),
                                lr=dataclasses.replace(first.lr, means_init=4e-4, opacity=2e-2))
    train(dataset, first, None, verbose=False)
    traces = sum(STEP_TRACES.values())
    train(dataset, other, tmp_path / "shared", verbose=False)
    assert sum(STEP_TRACES.values()) == traces
    PROCESS.release_steps()
    train(dataset, other, tmp_path / "alone", verbose=False)
    assert sum(STEP_TRACES.values()) == traces + 1
    final = [ckpt.load_checkpoint(ckpt.latest_checkpoint(tmp_path / run / "checkpoints"))[0]
             for run in ("shared", "alone")]
    assert_trees_equal(final[0]["scene"], final[1]["scene"], "scene", atol=0)
    assert_trees_equal(final[0]["opt_state"], final[1]["opt_state"], "optimiser state", atol=0)

def test_progress_bar_when_forced(dataset, capfd, monkeypatch):
    """PATEXGS_PROGRESS=1 draws the step bar (method, count, ETA) on stderr, progress lines intact."""
    from patexgs_jax import progress

    monkeypatch.setenv(progress.ENV_VAR, "1")
    cfg = tiny_config(method="2dgs", iters_2dgs=8, densify=NO_DENSIFY, checkpoint_every=4, log_every=4)
    train(dataset, cfg, None, verbose=True)
    out, err = capfd.readouterr()
    assert re.search(r"train 2dgs: +\d+%\|.*\| [0-8]/8 \[\d\d:\d\d<", err), err
    assert [line.split()[:2] for line in out.splitlines() if line.startswith("step ")] == [["step", "4/8"],
                                                                                           ["step", "8/8"]]


# ------------------------------------------------------------------------------------------------
# 5. Non-finite steps
# ------------------------------------------------------------------------------------------------
class BadView:
    def __init__(self, camera, image, name):
        self.camera, self.image, self.name = camera, image, name


def test_bad_views_are_skipped(dataset, tmp_path, capsys):
    views = list(dataset.train_views)
    perm = np.random.default_rng([0, 0]).permutation(len(views))  # the first epoch's order (seed 0)
    nan_img = views[perm[2]].image.copy()
    nan_img[10:20, 5:30] = np.nan
    views[perm[2]] = BadView(views[perm[2]].camera, nan_img, "nan-pixels")
    views[perm[4]] = BadView(views[perm[4]].camera, np.zeros((0, 0, 3), np.float32), "empty")
    cam = views[perm[6]].camera
    bad_pose = dataclasses.replace(cam, world_to_camera=jnp.asarray(cam.world_to_camera).at[:3, 3].set(jnp.nan))
    views[perm[6]] = BadView(bad_pose, views[perm[6]].image, "nan-pose")
    ds = dataclasses.replace(dataset, train_views=tuple(views))
    cfg = tiny_config(method="2dgs", iters_2dgs=8, densify=NO_DENSIFY, checkpoint_every=4, log_every=4)
    result = train(ds, cfg, tmp_path / "out", verbose=True)
    said, err = capsys.readouterr()
    assert "train 2dgs" not in err  # no progress bar: stderr is not a terminal
    for step, name in ((2, "nan-pixels"), (4, "empty"), (6, "nan-pose")):
        assert f"[step {step}] view {name!r}" in said and "update skipped" in said
    s = result.summary
    assert s["steps"] == 8 and s["skipped_steps"] == 3
    assert all_finite(result.scene) and np.isfinite(s["train_psnr"])  # evaluated on the usable views
    log = [json.loads(line) for line in (tmp_path / "out" / "log.jsonl").read_text().splitlines()]
    assert [(r["step"], r["skipped"]) for r in log] == [(4, 1), (8, 3)]
    assert ckpt_step(tmp_path / "out") == 8
    tree, _ = ckpt.load_checkpoint(ckpt.latest_checkpoint(tmp_path / "out" / "checkpoints"))
    assert all_finite(tree["scene"]) and all_finite(tree["opt_state"])
    assert int(tree["opt_state"][0].count) == 5  # only the good steps moved Adam


def test_repeated_nonfinite_steps_stop_the_run(dataset, tmp_path):
    out = tmp_path / "out"
    cfg = tiny_config(method="2dgs", iters_2dgs=12, densify=NO_DENSIFY, checkpoint_every=2, max_bad_steps=3)
    train_killed(dataset, cfg, out, kill_after=5, resume=False)
    assert ckpt_step(out) == 4
    good = ckpt.latest_checkpoint(out / "checkpoints")
    good_bytes = good.read_bytes()

    def nan_loss(rgb, target, lambda_dssim=0.2, valid=None):
        l1 = jnp.mean(jnp.abs(rgb - target))
        return l1 * jnp.nan, l1

    # (the loss is traced into the step: the steps shared by this process's runs are released before
    # and after, so that the patched loss is traced, and then is not reused)
    PROCESS.release_steps()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(losses, "photometric", nan_loss)
            with pytest.raises(FloatingPointError, match="3 consecutive non-finite steps"):
                train(dataset, cfg, out, resume=True, verbose=False)
    finally:
        PROCESS.release_steps()
    assert ckpt.latest_checkpoint(out / "checkpoints") == good and good.read_bytes() == good_bytes
    tree, _ = ckpt.load_checkpoint(good)
    assert all_finite(tree["scene"]) and all_finite(tree["opt_state"])
    # The kept checkpoint resumes normally once the cause is gone.
    result = train(dataset, cfg, out, resume=True, verbose=False)
    assert result.summary["steps"] == 12 and all_finite(result.scene)


# ------------------------------------------------------------------------------------------------
# 6. Texture budget
# ------------------------------------------------------------------------------------------------
def test_texture_budget_leaves_growth_room_and_is_met(dataset):
    """Eq. 7 spends budget_eq7_share of the budget (within 1%), growth the rest: it grows into the
    room left and the total never passes the budget; spending the room meets it within 1%."""
    mb = 0.09
    budget = mb_to_texels(mb)
    cfg = tiny_config(texture_budget_mb=mb, budget_eq7_share=0.6)
    run = Trainer(dataset, cfg, None, verbose=False)
    run.fresh()
    tex = run.textures
    run.state = tex.start(run.state)
    run.state = tex.allocate(run.state, run.step)
    texels = run.scene.texel_count()
    assert texels["rgb"] + texels["alpha"] == tex.allocation["texels"] and texels["rgb"] == texels["alpha"]
    assert abs(texels["rgb"] - 0.6 * budget) <= 0.01 * 0.6 * budget, (texels, budget)
    assert tex.allocation["budget_texels"] == 2 * tex.texel_budget == 2 * budget  # (texels: RGB + alpha)
    # Growth with a gradient that selects every textured Gaussian at every event: it fills the room.
    act = np.asarray(run.scene.active) > 0
    schedule = tex.schedule
    state = tex.state
    top = int(np.flatnonzero(act)[0])
    for t in growth_steps(cfg):
        grad = np.where(act, 0.95 * schedule.tau_high(t, 1.0), 0.0)  # inside Eq. 8's band ...
        grad[top] = 1.0  # ... under tau_max = 1
        state, sides, sel = state.step(grad, t, schedule, active=act, texel_budget=tex.texel_budget)
        assert adaptive.total_texels(sides, act) <= budget
    grown = adaptive.total_texels(state.sides(cfg.max_texture_size), act)
    assert grown > texels["rgb"] and abs(grown - budget) <= 0.01 * budget, (grown, budget)


def test_patexgs_fixed_differs_from_patexgs_only_in_sizes(dataset):
    """patexgs-fixed-N: the patexgs warm-up and render settings, N x N at the allocation, no growth."""
    assert Method.from_name("patexgs-fixed-3") == dataclasses.replace(Method.from_name("patexgs"), size=3)
    cfg = tiny_config(method="patexgs-fixed-3")
    assert cfg.render_config() == tiny_config().render_config()
    run = Trainer(dataset, cfg, None, verbose=False)
    run.fresh()
    run.state = run.textures.start(run.state)
    act = np.asarray(run.scene.active) > 0
    assert np.all(np.asarray(run.scene.alpha.size)[act] == 5)  # the same warm-up textures as patexgs
    run.state = run.textures.allocate(run.state, run.step)
    for bank in (run.scene.rgb, run.scene.alpha):
        assert np.all(np.asarray(bank.size)[act] == 3) and np.all(np.asarray(bank.size)[~act] == 0)
    assert run.textures.allocation["sigma"] is None and run.textures.allocation["sides"] == {"3": int(act.sum())}
    scene = run.scene
    run.after_step(growth_schedule(cfg).t0)  # a growth step of patexgs: nothing grows
    assert run.scene is scene and run.textures.growth_events == []
    with pytest.raises(ValueError, match="patexgs-fixed-N"):
        TrainConfig(method="patexgs-fixed-33")


# ------------------------------------------------------------------------------------------------
# 7. Command line
# ------------------------------------------------------------------------------------------------
def run_cli(*args, cache):
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, "-m", "patexgs_jax.train", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=600)


def test_cli(synthetic_scene_dir, tmp_path, compile_cache):
    cache, out = compile_cache, tmp_path / "out"
    bad = run_cli("--data", synthetic_scene_dir, "--method", "4dgs", "--out", tmp_path / "bad", cache=cache)
    assert bad.returncode == 2 and "unknown method '4dgs'" in bad.stderr and "Traceback" not in bad.stderr
    first = run_cli("--data", synthetic_scene_dir, "--method", "2dgs", "--out", out, "--iters-2dgs", 30,
                    "--iters-tex", 0, cache=cache)
    assert first.returncode == 0, first.stderr
    summary = json.loads((out / "summary.json").read_text())
    for key in ("train_psnr", "test_psnr", "num_gaussians", "texels", "storage_mb", "train_seconds"):
        assert key in summary, key
    assert summary["steps"] == 30 and summary["texels"] == 0 and summary["num_gaussians"] > 0
    assert np.isfinite(summary["train_psnr"]) and summary["train_seconds"] > 0
    assert (out / "scene.ply").is_file() and not (out / "scene.textures.npz").exists()  # (2dgs: no textures)
    assert ckpt_step(out) == 30
    from patexgs_jax.sources import load_source

    rec = load_source(out).data  # (RUN/data.json: how python -m patexgs_jax.evaluate and render find the test views)
    assert rec is not None and rec.path == Path(synthetic_scene_dir).resolve() and rec.factor is None
    plain = ("--method", "2dgs", "--iters-2dgs", 30, "--iters-tex", 0)  # (30 steps: no continued stage)
    again = run_cli("--data", synthetic_scene_dir, "--out", out, *plain, cache=cache)
    assert again.returncode == 2 and "already holds checkpoints" in again.stderr and "--resume" in again.stderr
    assert "Traceback" not in again.stderr
    not_dir = tmp_path / "a_file"
    not_dir.write_text("")
    blocked = run_cli("--data", synthetic_scene_dir, "--out", not_dir, *plain, cache=cache)
    assert blocked.returncode == 2 and "error: cannot write to --out" in blocked.stderr
    assert "Traceback" not in blocked.stderr
    resumed = run_cli("--data", synthetic_scene_dir, "--out", out, *plain, "--resume", cache=cache)
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming from" in resumed.stdout and "at step 30" in resumed.stdout
    summary2 = json.loads((out / "summary.json").read_text())
    assert summary2["steps"] == 30 and summary2["train_seconds"] == summary["train_seconds"]  # no new steps


# ------------------------------------------------------------------------------------------------
# 8. Methods
# ------------------------------------------------------------------------------------------------
ALL_METHODS = (["2dgs", "patexgs", "patexgs-no-mip", "patexgs-no-alpha-mip", "patexgs-no-rgb-mip",
                "patexgs-no-adaptive"] + [f"textured-fixed-{n}" for n in FIXED_SIZES])


@pytest.mark.parametrize("method", ALL_METHODS)
def test_method_names_parse(method):
    spec = Method.from_name(method)
    cfg = TrainConfig(method=method)
    rc = cfg.render_config()
    assert spec.textures in (None, "fixed", "adaptive")
    assert (spec.textures is None) == (method == "2dgs") == (cfg.total_steps == cfg.iters_2dgs)
    assert (rc.mip == "none") == (method == "2dgs" or method.startswith("textured-fixed") or method.endswith("no-mip"))
    if spec.textures == "fixed":
        assert spec.size == (8 if method == "patexgs-no-adaptive" else int(method.rsplit("-", 1)[1]))


@pytest.mark.parametrize("method", ["textured-fixed-5", "textured-fixed-", "textured-fixed-x", "patexgs-no",
                                    "4dgs", ""])
def test_bad_method_names(method):
    with pytest.raises(ValueError, match="method|textured-fixed-N"):
        TrainConfig(method=method)


def test_iteration_overrides_scale_the_texture_schedule_or_are_refused():
    """--iters-tex scales the preset's warm-up and growth interval (Eq. 7 and growth still happen);
    an explicit schedule whose warm-up outlasts the texture stage is refused with the fix."""
    tiny = PRESETS["tiny"]
    cfg = preset_config("tiny", iters_tex=2 * tiny["iters_tex"])
    assert (cfg.warmup_tex, cfg.growth_interval) == (2 * tiny["warmup_tex"], 2 * tiny["growth_interval"])
    paper = preset_config("paper", iters_tex=600)  # the paper's 1,000-step warm-up, scaled to 20
    assert (paper.warmup_tex, paper.growth_interval) == (20, 2) and paper.warmup_tex < paper.iters_tex
    kept = preset_config("tiny", iters_tex=60, warmup_tex=7)  # given fields are kept
    assert (kept.warmup_tex, kept.growth_interval) == (7, 4)  # 15 * 60 / 200 = 4.5, rounded half to even
    assert preset_config("tiny") == TrainConfig(**tiny)
    with pytest.raises(ValueError, match=r"warm-up.*only 30 steps.*--iters-tex"):
        TrainConfig(method="patexgs", iters_tex=30, warmup_tex=30)
    TrainConfig(method="textured-fixed-4", iters_tex=30, warmup_tex=30)  # no Eq. 7: nothing to skip
    with pytest.raises(ValueError, match="growth_interval"):
        TrainConfig(growth_interval=0)


@pytest.mark.parametrize("preset", ["tiny", "cpu"])
def test_presets_give_every_texture_stage_room(preset):
    """Warm-up, then Eq. 7, then several growth events, each followed by a whole interval of training
    (the run_p fixture checks that the events fire and grow textures)."""
    cfg = preset_config(preset, method="patexgs")
    alloc = cfg.iters_2dgs + cfg.warmup_tex
    steps = growth_steps(cfg)
    assert cfg.iters_2dgs < alloc < steps[0] and len(steps) >= 5, steps
    assert np.all(np.diff(steps) == cfg.growth_interval)
    assert steps[-1] + cfg.growth_interval <= cfg.total_steps  # the last event's textures are trained
    for fixed in ("patexgs-fixed-4", "textured-fixed-4", "2dgs"):
        assert growth_steps(preset_config(preset, method=fixed)) == []


def test_2dgs_continues_its_stage_and_keeps_its_stage1_checkpoint(dataset, tmp_path, monkeypatch):
    """continue_2dgs: the 2DGS baseline trains as many steps as a textured run (no densification
    after its stage), and keeps its end-of-stage-1 checkpoint out of the rotation for the others."""
    late = DensifyConfig(start=7, stop=12, interval=1, opacity_reset_interval=10_000)  # due after step 6 only
    calls = []
    real = dens.densify_and_prune
    monkeypatch.setattr(dens, "densify_and_prune", lambda *a, **k: calls.append(1) or real(*a, **k))
    cfg = tiny_config(method="2dgs", iters_2dgs=6, continue_2dgs=4, densify=late, checkpoint_every=2)
    assert cfg.total_steps == 10
    res = train(dataset, cfg, tmp_path / "2dgs", verbose=False)
    assert res.summary["steps"] == 10 and res.summary["texels"] == 0 and calls == []
    assert ckpt_step(tmp_path / "2dgs") == 10
    tex = tiny_config(method="textured-fixed-2", iters_2dgs=6, iters_tex=4, densify=late, checkpoint_every=2)
    s1 = stage1_checkpoint(tmp_path / "2dgs", tex)
    assert s1 is not None and s1.parent.name == STAGE1_DIR and ckpt.read_metadata(s1)["step"] == 6
    tree, _ = ckpt.load_checkpoint(s1)
    assert 0 < float(tree["t_train"]) < res.summary["train_seconds"]
    with pytest.raises(ValueError, match="continue_2dgs.*untextured methods only"):
        tiny_config(method="patexgs", continue_2dgs=4)


def test_textured_fixed_8(dataset):
    cfg = tiny_config(method="textured-fixed-8", iters_2dgs=3, iters_tex=3, densify=NO_DENSIFY)
    run = Trainer(dataset, cfg, None, verbose=False)  # the loop of train(), without the final evaluation
    run.fresh()
    run.run()
    scene = run.scene
    assert run.step == 6 and run.skipped == 0 and run.textures.state is None and all_finite(scene)
    act = np.asarray(scene.active) > 0
    for name in ("rgb", "alpha"):
        bank = getattr(scene, name)
        assert np.all(np.asarray(bank.size)[act] == 8) and np.all(np.asarray(bank.bucket)[act] == 3), name
        assert np.all(np.asarray(bank.size)[~act] == 0), name
    assert scene.texel_count() == dict(rgb=64 * int(act.sum()), alpha=64 * int(act.sum()))
    assert run.render_cfg.mip == "none"


# ------------------------------------------------------------------------------------------------
# Real capture
# ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_real_capture_beer(tmp_path):
    if not (BEER / "sparse").is_dir():
        pytest.skip(f"real capture not found at {BEER} (set PATEXGS_REAL_DATA to the folder holding beer/)")
    ds = load(BEER, factor=16, cache_dir=tmp_path, verbose=False)
    assert "SIMPLE_RADIAL" in ds.info["undistorted_from"], ds.info
    # Undistortion gives per-image sizes (43..45 x 76..80 px here); every size is a new compile of the
    # step, so train on the views of the most common size (the loader path is the same for all).
    sizes = [(v.camera.width, v.camera.height) for v in ds.train_views]
    common = max(set(sizes), key=sizes.count)
    ds = dataclasses.replace(ds, train_views=tuple(v for v, s in zip(ds.train_views, sizes) if s == common),
                             test_views=tuple(v for v in ds.test_views
                                              if (v.camera.width, v.camera.height) == common))
    cfg = TrainConfig(method="2dgs", iters_2dgs=30, max_gaussians=1000, densify=NO_DENSIFY, log_every=10)
    result = train(ds, cfg, None, verbose=False)
    s = result.summary
    assert s["steps"] == 30 and s["skipped_steps"] == 0 and s["num_gaussians"] == 1000
    assert all_finite(result.scene) and np.isfinite(s["train_psnr"])
