"""``python -m patexgs_jax.train --plan`` on the embedded scene (at a third of its resolution), with
its real timed steps: the plan is printed and written to ``--json`` only, with each stage's measured
step time and peak memory, after the lines that say what it measures."""

from __future__ import annotations

import json

from patexgs_jax.training import cli


def test_plan_on_the_embedded_scene_times_real_steps_and_writes_only_its_json(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "plan.json"
    # (--factor 3: the same steps timed on fewer pixels)
    code = cli.main(["--method", "textured-fixed-2", "--max-gaussians", "500", "--factor", "3", "--plan",
                     "--json", str(out), "--plan-device", "rtx4090-24gb"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.json"]  # no run folder, no checkpoints
    doc = json.loads(out.read_text())
    assert doc["measured"]["steps"] == 5 and doc["measured"]["gaussians"] == 500
    # Steps of a few ms: more than 5 timed a stage (until 4 s of them, at most 40), each one's time kept.
    timed = doc["measured"]["timed_steps"]
    assert 5 <= timed["stage1"] <= 40 and 5 <= timed["texture"] <= 40
    assert len(doc["measured"]["step_ms"]["stage1"]) == timed["stage1"]
    assert doc["step_seconds"]["stage1"] > 0 and doc["step_seconds"]["texture"] > 0
    assert doc["total_seconds"] > 600 * doc["step_seconds"]["stage1"]  # the tiny preset's 600 + 200 steps
    assert doc["fits"] is True and set(doc["peak_bytes"]) == {"stage1", "texture", "eval"}
    assert doc["devices"][1]["kind"] == "gpu" and doc["devices"][1]["fits"]
    assert "2DGS" in text and "texture" in text and "whole run" in text
    lines = text.splitlines()
    said = [line for line in lines if line.startswith("plan: ")]
    assert said[0].startswith("plan: loading ") and lines.index(said[-1]) < lines.index(
        next(line for line in lines if line.startswith("plan for ")))  # every progress line before the plan
    for what in ("compiling the 2DGS step (500 active Gaussians",
                 "timing 5 to 40 steps (at least 4 s) of the 2DGS stage", "compiling the texture stage's first step",
                 "timing 5 to 40 steps (at least 4 s) of the texture stage",
                 "timing an evaluation render"):
        assert any(line.startswith(f"plan: {what}") for line in said), (what, said)
    assert doc["measured"]["eq6_views"] == 0  # (fixed sizes: no Eq. 7 allocation)
    # Every step time measured here, at the run's own count (nothing extrapolated or estimated).
    kinds = {k: f["how"] for k, f in doc["figures"].items()}
    assert kinds["step_seconds.stage1"] == kinds["step_seconds.texture"] == "measured", kinds
    assert kinds["time_terms.eval"] == "measured" and kinds["peak_bytes"] == "modelled"
    assert "  measured: step_seconds.stage1" in text and "  modelled: " in text


def test_a_plan_of_days_on_a_cpu_times_the_2dgs_stage_alone(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "plan.json"
    # 30 million 2DGS steps: days here whatever a step costs (a millisecond or more), with real steps.
    code = cli.main(["--method", "patexgs", "--preset", "paper", "--iters-2dgs", "30000000", "--factor", "3",
                     "--plan", "--json", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    doc = json.loads(out.read_text())
    m = doc["measured"]
    assert m["gaussians"] == 10_000 and m["steps"] == 2 and m["texture_estimated"] and m["eval_estimated"]
    assert doc["step_seconds"]["texture"] == 2 * doc["step_seconds"]["stage1"] > 0
    kinds = {k: f["how"] for k, f in doc["figures"].items()}
    assert kinds["step_seconds.stage1"] == "extrapolated" and kinds["step_seconds.texture"] == "estimated"
    said = [line for line in text.splitlines() if line.startswith("plan: ")]
    assert any("nothing else is timed" in line for line in said), said
    assert not any("texture stage" in line and line.startswith("plan: timing") for line in said), said
    assert "it belongs on a GPU" in text and "  estimated: step_seconds.texture" in text
