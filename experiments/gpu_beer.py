"""One command for a short GPU session: beer at full size with the ``small`` preset, ``2dgs`` and
``patexgs`` from one shared stage 1, evaluated at 1, 1/2, 1/4 and 1/8, then the renderer and viewer
benchmarks while the budget lasts; every figure in one JSON file.

    python -m experiments.gpu_beer --data BEER --out DIR [--budget-s 540] [--factor 1] [--preset small]
    PATEXGS_GPU_CHECK_REHEARSE=1 python -m experiments.gpu_beer --data BEER --out DIR   # the CPU rehearsal

``scripts/gpu_beer.sh`` runs it on a GPU machine. The ``2dgs`` run is the shared stage 1 (its
``iters_2dgs`` steps, not continued: the study's ``continue_2dgs`` would not fit the session);
``patexgs`` starts from its end-of-stage-1 checkpoint, its texture stage's first programs compiled
ahead while ``2dgs`` is evaluated (``train(..., prepare=)``). Training keeps the padding policy's
default (``TrainConfig.padding`` "auto": one padded size on a GPU). The benchmarks run as
subprocesses (:func:`experiments.device_check.stage_commands`), each limited to the budget left.

``PATEXGS_GPU_CHECK_REHEARSE=1`` (or ``--rehearse``) runs the same phases at a small factor (8), the
``tiny`` preset cut to :data:`REHEARSAL_STEPS`, two test views and the benchmarks' toy sizes, writing
the same JSON: what a CPU can run in minutes, so that the GPU run cannot fail for a reason the CPU
would have shown.

Output in DIR: ``runs/{2dgs,patexgs}/`` (checkpoints, ``log.jsonl``, ``summary.json``), the
benchmarks' JSON and logs, and ``gpu_beer.json`` (written after every phase: a cut session keeps what
it measured), its layout in docs/benchmarks.md ("The beer GPU check"): :func:`assemble`.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
import types
from pathlib import Path

from experiments.provenance import header, write_json

#: The layout of gpu_beer.json.
SCHEMA = 1
REHEARSE_ENV = "PATEXGS_GPU_CHECK_REHEARSE"
#: The rehearsal's schedule: (iters_2dgs, iters_tex); the tiny preset's texture schedule scales with it.
REHEARSAL_STEPS = (120, 60)
#: The rehearsal's default budget: a shared CPU takes tens of minutes for what a GPU does in 9, and
#: the benchmarks must still run.
REHEARSAL_BUDGET_S = 4 * 3600.0
METHODS = ("2dgs", "patexgs")
#: The benchmarks run after training while the budget lasts (device_check's stages).
BENCHMARKS = ("render", "viewer")


def stage_step_ms(log_path: Path, iters_2dgs: int) -> dict:
    """Median ms a step per stage (``stage1``, ``stage2``) over the log windows (``log.jsonl``) in
    which no step compiled and no stage boundary fell; None for a stage without such a window."""
    out: dict[str, list] = {"stage1": [], "stage2": []}
    try:
        records = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    except OSError:
        records = []
    prev = None
    for r in records:
        if "ms_per_step" not in r or "step" not in r:
            continue
        if prev is not None and r.get("recompiles") == prev.get("recompiles"):
            if r["step"] <= iters_2dgs:
                out["stage1"].append(r["ms_per_step"])
            elif prev["step"] >= iters_2dgs:
                out["stage2"].append(r["ms_per_step"])
        prev = r
    return {k: (round(statistics.median(v), 3) if v else None) for k, v in out.items()}


def device_memory() -> dict:
    """The first device's memory statistics: ``peak_bytes`` and ``limit_bytes`` (None where the
    backend keeps none, e.g. a CPU), and this process's peak resident host memory."""
    import jax

    stats = jax.local_devices()[0].memory_stats() or {}
    return dict(peak_bytes=stats.get("peak_bytes_in_use"), limit_bytes=stats.get("bytes_limit"),
                host_peak_rss_bytes=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)


def assemble(head: dict, *, rehearsal: bool, budget_s: float, card: dict, setup: dict, runs: dict, evals: dict,
             memory: dict, phases: dict, benchmarks: dict, figures: dict, wall_s: float) -> dict:
    """gpu_beer.json's content (its layout: docs/benchmarks.md, "The beer GPU check"). ``runs``:
    method -> a run's summary.json (with ``step_ms``, :func:`stage_step_ms`, and ``wall_s``);
    ``evals``: method -> :func:`patexgs_jax.evaluation.evaluate_scales`'s result."""
    out_runs = {}
    for method, s in runs.items():
        compiles = s.get("compiles") or {}
        out_runs[method] = dict(
            steps=s.get("steps"), wall_s=s.get("wall_s"), train_seconds=s.get("train_seconds"),
            step_ms=s.get("step_ms"), compile_programs=compiles.get("step_programs"),
            compile_seconds=compiles.get("step_seconds"), xla_programs=compiles.get("xla_programs"),
            xla_seconds=compiles.get("xla_seconds"), compiled_at_steps=s.get("compiled_at_steps"),
            padding=s.get("padding"), gaussians=s.get("num_gaussians"), texels=s.get("texels"),
            storage_mb=s.get("storage_mb"), skipped_steps=s.get("skipped_steps"),
            stage1_from=s.get("stage1_from"))
    scales = {}
    for method, ev in evals.items():
        scales[method] = {k: {m: v.get(m) for m in ("psnr", "ssim", "lpips", "alias_psnr", "views")}
                          for k, v in ev.items() if isinstance(v, dict)}
    return dict(head, rehearsal=rehearsal, budget_s=budget_s, card=card, setup=setup, runs=out_runs,
                scales=scales, memory=memory, phases=phases, benchmarks=benchmarks, figures=figures,
                wall_s=round(wall_s, 1))


def _card() -> dict:
    import jax

    dev = jax.local_devices()[0]
    stats = dev.memory_stats() or {}
    return dict(backend=jax.default_backend(), device=dev.device_kind, devices=jax.device_count(),
                memory_bytes=stats.get("bytes_limit"), jax=jax.__version__)


def _configs(preset: str, rehearsal: bool) -> dict:
    from patexgs_jax.training import preset_config

    steps = dict(iters_2dgs=REHEARSAL_STEPS[0], iters_tex=REHEARSAL_STEPS[1]) if rehearsal else {}
    return {m: preset_config(preset, method=m, **steps) for m in METHODS}


def run_benchmarks(out: Path, deadline: float, rehearsal: bool, viewer_run: Path | None) -> dict:
    """The renderer's and the viewer's benchmarks (device_check's stages; the viewer draws the
    ``viewer_run`` model, the trained patexgs run), each limited to the time left before
    ``deadline`` (time.monotonic()); a stage with under 20 s left is skipped."""
    from experiments.device_check import run_stage

    args = types.SimpleNamespace(quick=rehearsal, viewer_run=viewer_run, compositors=None, beer=None,
                                 render_configs="2dgs,tex8-mip-prefilter", train_configs=None)
    recs = {}
    for stage in BENCHMARKS:
        left = deadline - time.monotonic()
        if left < 20:
            recs[stage] = dict(rc=None, skipped=f"{max(left, 0):.0f} s of the budget left")
            continue
        recs[stage] = run_stage(stage, out, args, left)
    return recs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the beer capture (COLMAP layout)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--budget-s", type=float, default=None, help="wall-clock budget (default 540; rehearsal "
                    f"{REHEARSAL_BUDGET_S:.0f}, a loaded CPU's minutes): the benchmarks run only in what training "
                    "and evaluation leave of it")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling (default 1; rehearsal 8)")
    ap.add_argument("--preset", default=None, help="training preset (default small; rehearsal tiny, cut to "
                    f"{REHEARSAL_STEPS[0]} + {REHEARSAL_STEPS[1]} steps)")
    ap.add_argument("--test-views", type=int, default=None, help="test views evaluated (default all; rehearsal 2)")
    ap.add_argument("--no-lpips", action="store_true")
    ap.add_argument("--rehearse", action="store_true", help=f"the CPU rehearsal (as {REHEARSE_ENV}=1)")
    args = ap.parse_args(argv)
    rehearsal = args.rehearse or os.environ.get(REHEARSE_ENV, "") not in ("", "0")
    factor = args.factor or (8 if rehearsal else 1)
    preset = args.preset or ("tiny" if rehearsal else "small")
    test_views = args.test_views or (2 if rehearsal else None)
    if not args.data.is_dir():
        ap.error(f"--data {args.data}: no such folder (the beer capture, COLMAP layout)")

    if args.budget_s is None:
        args.budget_s = REHEARSAL_BUDGET_S if rehearsal else 540.0
    t0 = time.monotonic()
    deadline = t0 + args.budget_s
    from patexgs_jax import data, memory_maps
    from patexgs_jax.evaluation import LPIPS, evaluate_scales
    from patexgs_jax.training import stage1_checkpoint, train

    memory_maps.enable_compile_cache()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    head = header(SCHEMA)
    cfgs = _configs(preset, rehearsal)
    setup = dict(data=str(args.data), factor=factor, preset=preset, test_views=test_views,
                 iters_2dgs=cfgs["patexgs"].iters_2dgs, iters_tex=cfgs["patexgs"].iters_tex,
                 padding=cfgs["patexgs"].padding)
    phases: dict = {}
    runs: dict = {}
    evals: dict = {}
    state = dict(benchmarks={}, figures={})

    def write():
        report = assemble(head, rehearsal=rehearsal, budget_s=args.budget_s, card=_card(), setup=setup, runs=runs,
                          evals=evals, memory=device_memory(), phases=phases, benchmarks=state["benchmarks"],
                          figures=state["figures"], wall_s=time.monotonic() - t0)
        write_json(out / "gpu_beer.json", report)
        return report

    def phase(name, fn):
        t = time.monotonic()
        print(f"[gpu_beer] {name} ...", flush=True)
        value = fn()
        phases[name] = round(time.monotonic() - t, 1)
        print(f"[gpu_beer] {name}: {phases[name]} s", flush=True)
        write()
        return value

    ds = phase("load", lambda: data.load(args.data, factor=factor, verbose=True))
    views = list(ds.test_views)[:test_views] if test_views else list(ds.test_views)
    lpips = LPIPS(enabled=not args.no_lpips)
    run_dir = {m: out / "runs" / m for m in METHODS}

    def train_one(method):
        cfg = cfgs[method]
        stage1 = None if method == "2dgs" else stage1_checkpoint(run_dir["2dgs"], cfg)
        prepare = (cfgs["patexgs"],) if method == "2dgs" else ()
        t = time.monotonic()
        result = train(ds, cfg, run_dir[method], resume=True, verbose=True, stage1=stage1, prepare=prepare)
        step_ms = stage_step_ms(run_dir[method] / "log.jsonl", cfg.iters_2dgs)
        if method == "patexgs":  # (its stage 1 is 2dgs's: the same steps)
            step_ms["stage1"] = (runs.get("2dgs", {}).get("step_ms") or {}).get("stage1")
        runs[method] = dict(result.summary, wall_s=round(time.monotonic() - t, 1), step_ms=step_ms)
        return result

    def evaluate_one(method, result):
        evals[method] = evaluate_scales(result.scene, views, cfgs[method].render_config(), lpips=lpips)

    for method in METHODS:
        result = phase(f"train {method}", lambda m=method: train_one(m))
        phase(f"evaluate {method}", lambda m=method, r=result: evaluate_one(m, r))
    memory = device_memory()  # (the benchmarks are other processes)

    def benchmarks():
        from experiments.device_check import collect

        viewer_run = run_dir["patexgs"] if (run_dir["patexgs"] / "summary.json").exists() else None
        state["benchmarks"] = run_benchmarks(out, deadline, rehearsal, viewer_run)
        state["figures"] = collect(out)[0]

    phase("benchmarks", benchmarks)
    report = write()
    report["memory"] = memory
    write_json(out / "gpu_beer.json", report)
    print(json.dumps({m: {k: report["runs"][m][k] for k in ("steps", "wall_s", "step_ms", "compile_programs",
                                                             "compile_seconds")} for m in report["runs"]}, indent=1))
    print(f"[gpu_beer] done in {report['wall_s']:.0f} s: {out / 'gpu_beer.json'}", flush=True)
    failed = [k for k, v in state["benchmarks"].items() if v.get("rc") not in (0, None)]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
