"""One command that checks the project on an accelerator: the renderer's float32 tests, the render,
training-step and viewer benchmarks, and a real-capture study, within a time budget, with the
figures written as JSON (with provenance) and compared with the GPU targets.

    python -m experiments.device_check --out DIR [--budget-s 540] [--beer PATH] [--viewer-run RUN]
                                       [--stages tests,render,train,viewer,beer,schedule] [--quick]
                                       [--compositors xla,pallas] [--render-configs C,..] [--train-configs C,..]
    python -m experiments.device_check --report DIR/device_check.json   # the Markdown tables again
    python -m experiments.device_check --bundle .device [--beer ../shared/data/beer]

``--bundle`` prepares, on a machine with pycolmap, what the check needs on one without it (GPU
machines often lack pycolmap, and have no network): ``cache/`` (a ``PATEXGS_CACHE`` holding the
embedded scene), ``viewer_run/`` (the tiny ``patexgs`` model bench_viewer draws) and, with
``--beer``, ``beer/``: that capture undistorted at full size into a pinhole COLMAP scene, which loads
without pycolmap. The device command then reads (``.device`` carried with the working tree)::

    PATEXGS_CACHE=.device/cache BEER=.device/beer VIEWER_RUN=.device/viewer_run scripts/gpu_check.sh "$OUT"

The render and train stages time every configuration with each of ``--compositors`` (default
both: the XLA compositor and the Pallas kernel, ``RenderConfig.compositor``) side by side in one
process, a row each; their figures are named
``<stage>.<config>@pallas.<figure>`` beside the XLA compositor's ``<stage>.<config>.<figure>``,
with ``..._over_xla`` the kernel's time over the XLA compositor's. ``--render-configs`` and
``--train-configs`` narrow the configurations (a short device session: ``2dgs`` alone).

``scripts/gpu_check.sh`` runs it on a GPU machine. Every stage is a subprocess with its own share of
the budget (:data:`STAGES`); a stage that fails or runs out of time is recorded as such and the
others still run. ``--quick`` runs the same stages at toy sizes (a CPU can run it in minutes; the
tests do, to keep the script working where no GPU is at hand).

Output in DIR: each stage's JSON (``render_50k.json``, ``render_1m.json``, ``train.json``,
``viewer.json``, ``beer/results.json``, ``schedule_<B>.json``: the 1M render with B tiles a batch),
its log (``<stage>.log``), and ``device_check.json``::

    {header (experiments.provenance: commit, date, machine, backend, device kind), "budget_s", "quick",
     "stages": {name: {"rc", "wall_s", "timed_out", "limit_s"}},
     "tests": {"passed", "failed", "skipped", "errors"} | null,
     "figures": {name: value}, "targets": [{"name", "value", "limit", "met"}]}

and ``device_check.md``: the figures and the targets as Markdown tables (for docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

from experiments.provenance import header, write_json

#: The layout of device_check.json.
SCHEMA = 1
REPO = Path(__file__).resolve().parent.parent

#: Stage -> share of the budget (of the time left when it starts, over the shares left).
STAGES = {"tests": 1.0, "render": 1.4, "train": 1.0, "viewer": 0.6, "beer": 2.0, "schedule": 1.0}

#: Tile batches the ``schedule`` stage tries at 1M Gaussians and 1920x1080 (8,160 tiles: 4 and 16
#: batches), beside the device's own choice in the ``render`` stage: whether fewer, longer-listed
#: batches pay where tiles' lists differ in length (a batch loops until its longest list is done).
SCHEDULE_BATCHES = (2048, 512)

#: The renderer's float32 tests that must pass on the accelerator at the CPU's tolerances (the
#: Pallas compositor's compiled for the GPU there, against the XLA compositor).
TEST_FILES = ("tests/unit/test_render.py", "tests/unit/test_device_path.py", "tests/unit/test_pallas_composite.py")

#: The GPU targets: (name, figure, limit, "max" or "min"); a figure may be a ratio.
TARGETS = [
    ("2dgs fwd, 50k 640x480 (ms)", "render_50k.2dgs.forward_ms", 3.5, "max"),
    ("2dgs fwd+bwd, 50k 640x480 (ms)", "render_50k.2dgs.forward_backward_ms", 10.0, "max"),
    ("patexgs fwd, 50k 640x480 (ms)", "render_50k.patexgs.forward_ms", 10.0, "max"),
    ("patexgs fwd+bwd, 50k 640x480 (ms)", "render_50k.patexgs.forward_backward_ms", 36.0, "max"),
    ("2dgs fwd+bwd, 1M 1920x1080 (ms)", "render_1m.2dgs.forward_backward_ms", 80.0, "max"),
    ("patexgs / 2dgs fwd+bwd, 1M 1920x1080", "render_1m.patexgs.forward_backward_over_2dgs", 3.0, "max"),
    ("viewer 640x480, tiny model (fps)", "viewer.tiny.fps", 30.0, "min"),
    ("bench_train 2dgs, 100k 1280x960 (ms/step)", "train.2dgs.ms_per_step", 60.0, "max"),
    ("bench_train patexgs / 2dgs (ms/step)", "train.patexgs.over_2dgs", 3.0, "max"),
    # The Pallas compositor's rows.
    ("pallas 2dgs fwd+bwd, 1M 1920x1080 (ms)", "render_1m.2dgs@pallas.forward_backward_ms", 40.0, "max"),
    ("pallas patexgs / 2dgs fwd+bwd, 1M 1920x1080", "render_1m.patexgs@pallas.forward_backward_over_2dgs", 3.0,
     "max"),
    ("pallas 2dgs fwd, 50k 640x480 (ms)", "render_50k.2dgs@pallas.forward_ms", 1.0, "max"),
]

#: bench configuration names -> the names used in the figures.
_CONFIG_NAMES = {"2dgs": "2dgs", "tex8-mip-prefilter": "patexgs", "tex8-mip-prefilter-dense": "patexgs-dense"}


def _name(row) -> str:
    """A row's figure name: its configuration's, with ``@pallas`` for the Pallas compositor's rows
    (rows without a compositor are the XLA compositor's)."""
    comp = row.get("compositor") or "xla"
    return _CONFIG_NAMES.get(row["config"], row["config"]) + ("" if comp == "xla" else f"@{comp}")


def _sizes(quick: bool) -> dict:
    if quick:
        # One scene for both render rows: the second command loads the first's programs from the
        # persistent compilation cache (gpu_check.sh sets one).
        return dict(render_50k=(300, "48x32"), render_1m=(300, "48x32"), train=(500, "64x48"),
                    viewer="160x120", beer_factor=8, beer_preset="tiny")
    return dict(render_50k=(50_000, "640x480"), render_1m=(1_000_000, "1920x1080"), train=(100_000, "1280x960"),
                viewer="640x480", beer_factor=1, beer_preset="cpu")


def stage_commands(stage: str, out: Path, args) -> list[list[str]]:
    """The commands of a stage (run one after the other, in the repository's root)."""
    py = [sys.executable, "-m"]
    s = _sizes(args.quick)
    configs = "2dgs,tex8-mip-prefilter"
    comps = ["--compositor", getattr(args, "compositors", None) or "xla,pallas"]
    if stage == "tests":
        files = TEST_FILES if not args.quick else (TEST_FILES[1],)
        return [py + ["pytest", "-q", "-n", "0", "-p", "no:cacheprovider", f"--junitxml={out / 'tests.xml'}",
                      *files]]
    if stage == "render":
        # The dense lookups as well: which of the two texture paths a GPU runs faster.
        render = getattr(args, "render_configs", None) or configs + ",tex8-mip-prefilter-dense"
        return [py + ["experiments.bench_render", "--gaussians", str(s[key][0]), "--sizes", s[key][1],
                      "--configs", render, "--no-peak", "--repeats", "3", *comps,
                      "--json", str(out / f"{key}.json")]
                for key in ("render_50k", "render_1m")]
    if stage == "train":
        return [py + ["experiments.bench_train", "--gaussians", str(s["train"][0]), "--sizes", s["train"][1],
                      "--configs", getattr(args, "train_configs", None) or configs, "--steps", "5", *comps,
                      "--json", str(out / "train.json")]]
    if stage == "viewer":
        cmd = py + ["experiments.bench_viewer", "--models", "tiny", "--sizes", s["viewer"], "--repeats", "5",
                    "--json", str(out / "viewer.json")]
        return [cmd + (["--run", str(args.viewer_run)] if args.viewer_run else [])]
    if stage == "schedule":
        n, size = s["render_1m"]
        return [["env", f"PATEXGS_TILE_BATCH={tb if not args.quick else 1}", *py, "experiments.bench_render",
                 "--gaussians", str(n), "--sizes", size, "--configs", configs, "--no-peak", "--repeats", "3",
                 "--json", str(out / f"schedule_{tb}.json")] for tb in SCHEDULE_BATCHES]
    if stage == "beer":
        if not args.beer:
            return []
        return [py + ["experiments.mipnerf360", "--data", str(args.beer), "--factor", str(s["beer_factor"]),
                      "--preset", s["beer_preset"], "--methods", "2dgs,patexgs", "--out", str(out / "beer"),
                      "--renders", "1", "--no-lpips"]]
    raise ValueError(f"unknown stage {stage!r}; stages: {', '.join(STAGES)}")


def run_stage(stage: str, out: Path, args, limit_s: float) -> dict:
    """Runs a stage's commands with a shared time limit; output to ``out/<stage>.log``."""
    cmds = stage_commands(stage, out, args)
    t0 = time.monotonic()
    rec = dict(rc=0, wall_s=0.0, timed_out=False, limit_s=round(limit_s, 1), commands=len(cmds))
    if not cmds:
        rec.update(rc=None, skipped="no --beer capture given")
        return rec
    env = dict(os.environ, PATEXGS_PROGRESS="0", XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONUNBUFFERED="1")
    with open(out / f"{stage}.log", "w") as log:
        for cmd in cmds:
            left = limit_s - (time.monotonic() - t0)
            if left <= 1:
                rec.update(timed_out=True, rc=rec["rc"] or 124)
                break
            log.write(f"$ {' '.join(cmd)}\n")
            log.flush()
            try:
                p = subprocess.run(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=left)
                rec["rc"] = rec["rc"] or p.returncode
            except subprocess.TimeoutExpired:
                rec.update(timed_out=True, rc=124)
                break
    rec["wall_s"] = round(time.monotonic() - t0, 1)
    return rec


def _rows(path: Path) -> list[dict]:
    try:
        return json.loads(path.read_text()).get("results", [])
    except (OSError, ValueError):
        return []


def collect(out: Path) -> tuple[dict, dict | None]:
    """The figures (flat name -> value) from the stages' JSON in ``out``, and the test counts."""
    fig: dict = {}
    for key in ("render_50k", "render_1m"):
        rows = _rows(out / f"{key}.json")
        xla = {r["config"]: r for r in rows if (r.get("compositor") or "xla") == "xla"}
        for r in rows:
            name = _name(r)
            base = xla.get(r["config"])
            if base is not None and base is not r:  # the Pallas kernel against the XLA compositor
                for f in ("forward_ms", "forward_backward_ms"):
                    fig[f"{key}.{name}.{f[:-3]}_over_xla"] = r[f] / base[f]
            for f in ("forward_ms", "forward_backward_ms", "forward_over_2dgs", "forward_backward_over_2dgs",
                      "compile_forward_s", "compile_backward_s", "temp_backward_mib", "binned_pairs", "max_tile",
                      "tile_batch"):
                if f in r:
                    fig[f"{key}.{name}.{f}"] = r[f]
            fig[f"{key}.size"] = f"{r['gaussians']} Gaussians, {r['width']}x{r['height']}"
    for tb in SCHEDULE_BATCHES:
        for r in _rows(out / f"schedule_{tb}.json"):
            name = _name(r)
            for f in ("forward_ms", "forward_backward_ms", "tile_batch"):
                if f in r:
                    fig[f"schedule_{tb}.{name}.{f}"] = r[f]
    train = {_name(r): r for r in _rows(out / "train.json")}
    for name, r in train.items():
        fig[f"train.{name}.ms_per_step"] = r["ms_per_step"]
        fig[f"train.{name}.compile_s"] = r["compile_s"]
        fig["train.size"] = f"{r['gaussians']} Gaussians, {r['width']}x{r['height']}"
        xla = train.get(name.split("@")[0])
        if "@" in name and xla is not None:
            fig[f"train.{name}.over_xla"] = r["ms_per_step"] / xla["ms_per_step"]
    for suffix in ("", "@pallas"):
        if f"2dgs{suffix}" in train and f"patexgs{suffix}" in train:
            fig[f"train.patexgs{suffix}.over_2dgs"] = (train[f"patexgs{suffix}"]["ms_per_step"]
                                                     / train[f"2dgs{suffix}"]["ms_per_step"])
    for r in _rows(out / "viewer.json"):
        for f in ("frame_ms", "fps", "preview_ms", "first_frame_ms"):
            fig[f"viewer.{r['model']}.{f}"] = r[f]
        fig["viewer.size"] = f"{r['width']}x{r['height']}"
    try:
        beer = json.loads((out / "beer" / "results.json").read_text())
        for methods in beer.get("results", {}).values():
            for method, m in methods.items():
                full = m.get("1", {})
                for f in ("psnr", "ssim"):
                    if f in full:
                        fig[f"beer.{method}.{f}"] = full[f]
                for f in ("train_seconds", "num_gaussians", "storage_mb", "render_ms"):
                    if f in m:
                        fig[f"beer.{method}.{f}"] = m[f]
    except (OSError, ValueError):
        pass
    tests = None
    try:
        root = ET.parse(out / "tests.xml").getroot()
        suite = root if root.tag == "testsuite" else root.find("testsuite")
        if suite is not None:
            n = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
            tests = dict(passed=n["tests"] - n["failures"] - n["errors"] - n["skipped"], failed=n["failures"],
                         errors=n["errors"], skipped=n["skipped"])
    except (OSError, ET.ParseError):
        pass
    return fig, tests


def check_targets(fig: dict, tests: dict | None) -> list[dict]:
    """Each target with its measured value (None where not measured) and whether it is met."""
    rows = []
    for name, key, limit, kind in TARGETS:
        v = fig.get(key)
        met = None if v is None else (v <= limit if kind == "max" else v >= limit)
        rows.append(dict(name=name, figure=key, value=v, limit=limit, kind=kind, met=met))
    if tests is not None:
        rows.append(dict(name="renderer float32 tests on the device", figure="tests", value=tests["passed"],
                         limit=0, kind="no failures", met=tests["failed"] == 0 and tests["errors"] == 0))
    return rows


def markdown(report: dict) -> str:
    """The report's targets and figures as Markdown."""
    dev = report.get("device") or report.get("backend")
    lines = [f"Device check: {dev} ({report.get('backend')}), jax {report.get('jax')}, commit {report.get('git')}, "
             f"{report.get('date')}{' (quick sizes)' if report.get('quick') else ''}.", "",
             "| target | measured | limit | met |", "| --- | ---: | ---: | --- |"]
    for t in report["targets"]:
        v = "-" if t["value"] is None else (f"{t['value']:.2f}" if isinstance(t["value"], float) else str(t["value"]))
        lim = f"{'<=' if t['kind'] == 'max' else '>=' if t['kind'] == 'min' else ''} {t['limit']}"
        met = "not measured" if t["met"] is None else ("yes" if t["met"] else "**no**")
        lines.append(f"| {t['name']} | {v} | {lim} | {met} |")
    lines += ["", "| stage | rc | wall s | limit s | timed out |", "| --- | ---: | ---: | ---: | --- |"]
    for name, s in report["stages"].items():
        lines.append(f"| {name} | {s['rc']} | {s['wall_s']} | {s['limit_s']} | {s['timed_out']} |")
    lines += ["", "| figure | value |", "| --- | ---: |"]
    for k, v in sorted(report["figures"].items()):
        lines.append(f"| {k} | {f'{v:.4g}' if isinstance(v, float) else v} |")
    return "\n".join(lines) + "\n"


def bundle(out: Path, beer: Path | None) -> None:
    """Prepares ``out`` (see the module docstring): the embedded scene, its tiny model, the capture."""
    import shutil

    out = out.resolve()
    os.environ["PATEXGS_CACHE"] = str(out / "cache")
    from patexgs_jax.data import load
    from patexgs_jax.data.synthetic import ensure_default_scene
    from patexgs_jax.training import preset_config, train

    scene = ensure_default_scene(verbose=True)
    if not (out / "viewer_run" / "summary.json").exists():
        print("[device_check] training the tiny patexgs model for the viewer stage (minutes) ...", flush=True)
        train(load(scene, verbose=False), preset_config("tiny", method="patexgs"), out / "viewer_run", resume=True,
              verbose=False)
    # The viewer draws the newest checkpoint: the others would only fill the device's 64 MiB.
    ckpts = out / "viewer_run" / "checkpoints"
    shutil.rmtree(ckpts / "stage1", ignore_errors=True)
    for old in sorted(ckpts.glob("*.ckpt"))[:-1]:
        old.unlink()
    if beer is not None:
        ds = load(beer, factor=1, verbose=True)  # undistorts into out/cache (pycolmap, here)
        folders = sorted((out / "cache").glob(f"{Path(beer).resolve().name}-*/undistorted/*"))
        if not folders:
            raise SystemExit(f"{beer}: no undistorted copy was made (its cameras are pinhole already?): "
                             f"pass --beer a capture with a distorted camera model, or carry it as it is.")
        dst = out / "beer"
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(folders[-1] / "images", dst / "images")
        shutil.copytree(folders[-1] / "sparse", dst / "sparse" / "0")
        shutil.rmtree(folders[-1].parent.parent)  # the cache's copy: carried once is enough
        print(f"[device_check] {beer}: {len(ds.train_views) + len(ds.test_views)} views undistorted into {dst}")
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"[device_check] {out}: {size / 2**20:.1f} MiB (the device's working tree takes 64 MiB in all)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="folder for the figures and logs")
    ap.add_argument("--budget-s", type=float, default=540.0, help="wall-clock budget of all stages (default 540)")
    ap.add_argument("--stages", default=",".join(STAGES), help=f"comma-separated, from {', '.join(STAGES)}")
    ap.add_argument("--beer", type=Path, default=None, help="a real capture (COLMAP layout) for the beer stage")
    ap.add_argument("--viewer-run", type=Path, default=None,
                    help="the tiny model's run folder for the viewer stage (default: bench_viewer trains it)")
    ap.add_argument("--quick", action="store_true", help="toy sizes: checks the script, not the device")
    ap.add_argument("--compositors", default="xla,pallas",
                    help="the compositors the render and train stages time side by side (default xla,pallas)")
    ap.add_argument("--render-configs", default=None,
                    help="bench_render configurations of the render stage (default 2dgs,tex8-mip-prefilter,"
                         "tex8-mip-prefilter-dense)")
    ap.add_argument("--train-configs", default=None,
                    help="bench_train configurations of the train stage (default 2dgs,tex8-mip-prefilter)")
    ap.add_argument("--report", type=Path, default=None, help="print the Markdown of a device_check.json and stop")
    ap.add_argument("--bundle", type=Path, default=None, help="prepare this folder for a machine without pycolmap")
    args = ap.parse_args(argv)
    if args.bundle:
        bundle(args.bundle, args.beer)
        return 0
    if args.report:
        print(markdown(json.loads(args.report.read_text())), end="")
        return 0
    if args.out is None:
        ap.error("--out DIR is required (or --report FILE)")
    stages = [s for s in args.stages.split(",") if s]
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        ap.error(f"unknown stage(s) {unknown}; choose from {', '.join(STAGES)}")
    if args.beer is not None and not args.beer.is_dir():
        ap.error(f"--beer {args.beer}: no such folder (a scene in COLMAP layout)")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    report = dict(header(SCHEMA), budget_s=args.budget_s, quick=args.quick, stages={})
    for i, stage in enumerate(stages):
        left = args.budget_s - (time.monotonic() - t0)
        share = STAGES[stage] / sum(STAGES[s] for s in stages[i:])
        limit = max(0.0, left * share)
        print(f"[device_check] {stage}: up to {limit:.0f} s ...", flush=True)
        rec = report["stages"][stage] = run_stage(stage, out, args, limit)
        print(f"[device_check] {stage}: rc {rec['rc']}, {rec['wall_s']} s{' (timed out)' if rec['timed_out'] else ''}",
              flush=True)
        report["figures"], report["tests"] = collect(out)
        report["targets"] = check_targets(report["figures"], report["tests"])
        write_json(out / "device_check.json", report)  # after every stage: a cut run keeps what it measured
    (out / "device_check.md").write_text(markdown(report))
    print(markdown(report), end="")
    print(f"[device_check] done in {time.monotonic() - t0:.0f} s: {out / 'device_check.json'}")
    return 0 if all(s["rc"] in (0, None) for s in report["stages"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
