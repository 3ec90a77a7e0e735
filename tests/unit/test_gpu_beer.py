"""experiments.gpu_beer (scripts/gpu_beer.sh): the per-stage step times it reads from a run's
log.jsonl and the layout of gpu_beer.json (:func:`assemble`), documented in docs/benchmarks.md. The
command itself is rehearsed on the CPU with PATEXGS_GPU_CHECK_REHEARSE=1 (minutes: not a test)."""

from __future__ import annotations

import json

from experiments import gpu_beer


def _log(path, records):
    path.write_text("\n".join(json.dumps(r) for r in records) + "\n")


def test_stage_step_ms_leaves_out_compiling_windows_and_the_stage_boundary(tmp_path):
    log = tmp_path / "log.jsonl"
    _log(log, [dict(step=50, ms_per_step=900.0, recompiles=3),    # (first window: compiles)
               dict(step=100, ms_per_step=20.0, recompiles=3),
               dict(step=150, ms_per_step=400.0, recompiles=4),   # (a compile in it)
               dict(step=190, ms_per_step=22.0, recompiles=4),
               dict(step=240, ms_per_step=80.0, recompiles=4),    # (steps 190-239: across the boundary, 200)
               dict(step=290, ms_per_step=60.0, recompiles=4),
               dict(step=340, ms_per_step=64.0, recompiles=4),
               dict(event="growth", step=360)])
    assert gpu_beer.stage_step_ms(log, 200) == dict(stage1=21.0, stage2=62.0)
    assert gpu_beer.stage_step_ms(tmp_path / "missing.jsonl", 200) == dict(stage1=None, stage2=None)


def test_assemble_keeps_the_documented_layout():
    summary = dict(steps=180, wall_s=12.5, train_seconds=9.0, step_ms=dict(stage1=21.0, stage2=62.0),
                   compiles=dict(step_programs=3, step_seconds=4.5, xla_programs=40, xla_seconds=6.0),
                   compiled_at_steps=[0, 55, 120], padding=dict(policy="one"), num_gaussians=4000, texels=9000,
                   storage_mb=1.2, skipped_steps=0, stage1_from="runs/2dgs/checkpoints/x.ckpt")
    ev = {"1": dict(psnr=20.0, ssim=0.7, lpips=None, alias_psnr=None, views=2, supersampled_psnr=None),
          "8": dict(psnr=22.0, ssim=0.8, lpips=0.1, alias_psnr=30.0, views=2, supersampled_psnr=21.0)}
    report = gpu_beer.assemble(dict(schema=gpu_beer.SCHEMA, git="abc"), rehearsal=True, budget_s=540.0,
                               card=dict(backend="cpu", device="cpu"), setup=dict(factor=8),
                               runs={"patexgs": summary}, evals={"patexgs": ev},
                               memory=dict(peak_bytes=None, limit_bytes=None, host_peak_rss_bytes=1),
                               phases={"train patexgs": 12.5}, benchmarks={"render": dict(rc=0)},
                               figures={"render_50k.2dgs.forward_ms": 3.0}, wall_s=20.04)
    assert set(report) == {"schema", "git", "rehearsal", "budget_s", "card", "setup", "runs", "scales", "memory",
                           "phases", "benchmarks", "figures", "wall_s"}
    run = report["runs"]["patexgs"]
    assert (run["compile_programs"], run["compile_seconds"], run["step_ms"]) == (3, 4.5, summary["step_ms"])
    assert (run["xla_programs"], run["gaussians"], run["compiled_at_steps"]) == (40, 4000, [0, 55, 120])
    assert report["scales"]["patexgs"]["8"] == dict(psnr=22.0, ssim=0.8, lpips=0.1, alias_psnr=30.0, views=2)
    assert report["wall_s"] == 20.0 and json.loads(json.dumps(report)) == report
