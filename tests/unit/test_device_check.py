"""experiments.device_check (scripts/gpu_check.sh): its stages' commands, the figures it reads from
the benchmarks' own JSON files, the targets and the report. The script itself runs in
tests/integration/test_benchmarks.py (quick sizes, on the CPU)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from experiments import device_check as dc
from locations import REPO

BENCH = REPO / "benchmarks"


def _rows(name):
    return json.loads((BENCH / name).read_text())["results"]


def _write(path, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"schema": 1, "results": rows}))


@pytest.fixture
def stage_files(tmp_path):
    """The stages' output files, made of rows the benchmarks wrote (this repository's CPU figures),
    renamed to the configurations the device check runs."""
    render = [dict(r) for r in _rows("render_50k_640x480.json") if r["config"] in ("2dgs", "tex8-mip")]
    for r in render:
        r["config"] = {"2dgs": "2dgs", "tex8-mip": "tex8-mip-prefilter"}[r["config"]]
    _write(tmp_path / "render_50k.json", render)
    train = [dict(r) for r in _rows("train_128x96.json") if r["config"] in ("2dgs", "tex8-mip")]
    train = [dict(r, config="tex8-mip-prefilter") if r["config"] == "tex8-mip" else r for r in train]
    train = [r for r in train if r["gaussians"] == train[0]["gaussians"]]
    _write(tmp_path / "train.json", train)
    viewer = [r for r in _rows("viewer_cpu.json") if r["model"] == "tiny" and r["width"] == 640]
    _write(tmp_path / "viewer.json", viewer)
    (tmp_path / "beer").mkdir()
    (tmp_path / "beer" / "results.json").write_text(json.dumps({"results": {"beer": {
        "2dgs": {"1": {"psnr": 24.1, "ssim": 0.86}, "train_seconds": 100.0, "num_gaussians": 5000},
        "patexgs": {"1": {"psnr": 24.3, "ssim": 0.87}, "train_seconds": 150.0, "storage_mb": 2.1}}}}))
    _write(tmp_path / "schedule_2048.json", [dict(r, tile_batch=2048) for r in render])
    (tmp_path / "tests.xml").write_text('<testsuites><testsuite name="pytest" errors="0" failures="1" '
                                        'skipped="2" tests="40"></testsuite></testsuites>')
    return tmp_path, render, train, viewer


def test_figures_are_read_from_the_benchmarks_files(stage_files):
    out, render, train, viewer = stage_files
    fig, tests = dc.collect(out)
    by = {r["config"]: r for r in render}
    assert fig["render_50k.2dgs.forward_ms"] == by["2dgs"]["forward_ms"]
    tex = by["tex8-mip-prefilter"]
    assert fig["render_50k.patexgs.forward_backward_over_2dgs"] == tex["forward_backward_over_2dgs"]
    assert fig["render_50k.size"] == "50000 Gaussians, 640x480"
    t = {r["config"]: r for r in train}
    ratio = t["tex8-mip-prefilter"]["ms_per_step"] / t["2dgs"]["ms_per_step"]
    assert fig["train.patexgs.over_2dgs"] == pytest.approx(ratio)
    assert fig["viewer.tiny.fps"] == viewer[0]["fps"]
    assert fig["beer.patexgs.psnr"] == 24.3 and fig["beer.2dgs.num_gaussians"] == 5000
    assert tests == dict(passed=37, failed=1, errors=0, skipped=2)
    assert not any(k.startswith("render_1m.") for k in fig)  # that stage wrote nothing: not measured
    assert fig["schedule_2048.patexgs.forward_backward_ms"] == tex["forward_backward_ms"]
    assert fig["schedule_2048.2dgs.tile_batch"] == 2048


def test_targets_and_report(stage_files):
    out, *_ = stage_files
    fig, tests = dc.collect(out)
    targets = {t["name"]: t for t in dc.check_targets(fig, tests)}
    assert len(targets) == len(dc.TARGETS) + 1
    t = targets["2dgs fwd, 50k 640x480 (ms)"]
    assert t["value"] == fig["render_50k.2dgs.forward_ms"] and t["met"] == (t["value"] <= 3.5)
    assert targets["2dgs fwd+bwd, 1M 1920x1080 (ms)"]["met"] is None  # not measured
    assert targets["viewer 640x480, tiny model (fps)"]["met"] is False  # a CPU's 2 fps
    assert targets["renderer float32 tests on the device"]["met"] is False  # one failure
    report = dict(device="cpu", backend="cpu", jax="x", git="abc", date="d", quick=False, figures=fig,
                  tests=tests, targets=list(targets.values()),
                  stages={"render": dict(rc=0, wall_s=1.0, limit_s=2.0, timed_out=False)})
    md = dc.markdown(report)
    assert "| 2dgs fwd, 50k 640x480 (ms) |" in md and "not measured" in md and "**no**" in md
    path = out / "device_check.json"
    path.write_text(json.dumps(report))
    printed = subprocess.run([sys.executable, "-m", "experiments.device_check", "--report", str(path)],
                             cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert printed == md


def test_stage_commands(tmp_path):
    args = argparse.Namespace(quick=False, beer=None, viewer_run=None)
    render = dc.stage_commands("render", tmp_path, args)
    assert [c[c.index("--sizes") + 1] for c in render] == ["640x480", "1920x1080"]
    assert [c[c.index("--gaussians") + 1] for c in render] == ["50000", "1000000"]
    train = dc.stage_commands("train", tmp_path, args)[0]
    assert train[train.index("--sizes") + 1] == "1280x960"
    assert "tex8-mip-prefilter" in train[train.index("--configs") + 1]
    assert dc.stage_commands("beer", tmp_path, args) == []  # no capture given: skipped
    args.beer = tmp_path
    beer = dc.stage_commands("beer", tmp_path, args)[0]
    assert beer[beer.index("--factor") + 1] == "1" and beer[beer.index("--methods") + 1] == "2dgs,patexgs"
    tests = dc.stage_commands("tests", tmp_path, args)[0]
    assert all(f in tests for f in dc.TEST_FILES)
    sched = dc.stage_commands("schedule", tmp_path, args)
    assert [c[1] for c in sched] == [f"PATEXGS_TILE_BATCH={b}" for b in dc.SCHEDULE_BATCHES]
    assert all(c[c.index("--sizes") + 1] == "1920x1080" for c in sched)
    with pytest.raises(ValueError, match="unknown stage"):
        dc.stage_commands("nope", tmp_path, args)


def test_bad_arguments_name_the_fix(tmp_path):
    for argv, msg in ((["--out", str(tmp_path), "--stages", "render,nope"], "unknown stage"),
                      (["--out", str(tmp_path), "--beer", str(tmp_path / "missing")], "no such folder"),
                      ([], "--out DIR is required")):
        p = subprocess.run([sys.executable, "-m", "experiments.device_check", *argv], cwd=REPO,
                           capture_output=True, text=True)
        assert p.returncode == 2 and msg in p.stderr


def test_stages_run_within_their_limits(stage_files, tmp_path, monkeypatch, capsys):
    """The driver itself: a stage's command runs and its figures reach device_check.json; a stage
    that outruns its share of the budget is stopped and recorded as timed out; the report is written."""
    src, *_ = stage_files
    out = tmp_path / "check"

    def commands(stage, out_dir, args):
        if stage == "render":
            return [[sys.executable, "-c", f"import shutil; shutil.copy({str(src / 'render_50k.json')!r}, "
                                           f"{str(out_dir / 'render_50k.json')!r})"]]
        return [[sys.executable, "-c", "import time; time.sleep(60)"]]

    monkeypatch.setattr(dc, "stage_commands", commands)
    assert dc.main(["--out", str(out), "--stages", "render,train", "--budget-s", "4"]) == 1  # a stage failed
    report = json.loads((out / "device_check.json").read_text())
    assert report["stages"]["render"]["rc"] == 0 and not report["stages"]["render"]["timed_out"]
    train = report["stages"]["train"]
    assert train["timed_out"] and train["rc"] == 124 and train["wall_s"] < 5
    assert report["figures"]["render_50k.2dgs.forward_ms"] > 0 and report["device"]
    assert (out / "device_check.md").read_text() == dc.markdown(report)
    assert "[device_check] train: rc 124" in capsys.readouterr().out


def test_compositor_rows_side_by_side(tmp_path):
    """The render and train stages time both compositors; the Pallas kernel's rows get their own
    figures (``@pallas``) and their time over the XLA compositor's."""
    args = argparse.Namespace(quick=False, beer=None, viewer_run=None, compositors="xla,pallas",
                              render_configs="2dgs", train_configs="2dgs")
    for cmd in dc.stage_commands("render", tmp_path, args) + dc.stage_commands("train", tmp_path, args):
        assert cmd[cmd.index("--compositor") + 1] == "xla,pallas" and cmd[cmd.index("--configs") + 1] == "2dgs"
    xla = dict(config="2dgs", gaussians=10, width=64, height=48, forward_ms=4.0, forward_backward_ms=12.0)
    _write(tmp_path / "render_1m.json", [xla,
                                         dict(xla, compositor="pallas", forward_ms=1.0, forward_backward_ms=3.0)])
    step = dict(config="2dgs", gaussians=10, width=64, height=48, compile_s=1.0)
    _write(tmp_path / "train.json", [dict(step, ms_per_step=20.0), dict(step, compositor="pallas", ms_per_step=10.0)])
    fig, _ = dc.collect(tmp_path)
    assert fig["render_1m.2dgs.forward_backward_ms"] == 12.0  # rows without a compositor: the XLA one's
    assert fig["render_1m.2dgs@pallas.forward_backward_ms"] == 3.0
    assert fig["render_1m.2dgs@pallas.forward_backward_over_xla"] == pytest.approx(0.25)
    assert fig["train.2dgs@pallas.over_xla"] == pytest.approx(0.5)
    targets = {t["name"]: t for t in dc.check_targets(fig, None)}
    assert targets["pallas 2dgs fwd+bwd, 1M 1920x1080 (ms)"]["met"] is True
    assert targets["pallas patexgs / 2dgs fwd+bwd, 1M 1920x1080"]["met"] is None  # not measured
