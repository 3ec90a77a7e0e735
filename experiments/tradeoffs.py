"""Accuracy against time: which settings trade how much quality for how much speed.

    python -m experiments.tradeoffs [--data SCENE] [--preset tiny|small|paper] [--out DIR]
        [--knobs mip,texture,budget,iters,sh] [--iters-2dgs N] [--iters-tex N] [--max-gaussians N]
    python -m experiments.tradeoffs --effects --run RUN_DIR [--data SCENE] [--out DIR]
        [--drop-effects-below DB] [--export PATH]
    python -m experiments.tradeoffs --from-study runs/mipnerf360/results.json [--out DIR]

Study (the first form)
  Every knob that trades quality for speed is varied on its own around one base configuration (the
  preset's, method ``patexgs``), on the same machine in one process:

  * ``mip``: mip mode none / nearest / trilinear (methods ``patexgs-no-mip``, ``patexgs``,
    ``patexgs-trilinear``), trained and rendered with that mode;
  * ``texture``: no textures (``2dgs``), a fixed N x N texture per Gaussian (``textured-fixed-N``,
    N = 1 ... 32, no mipmaps, as Textured Gaussians) and the adaptive sizes (``patexgs``);
  * ``budget``: ``max_gaussians`` at 100 / 10 / 1 % of the Gaussian count the base run reached
    (100 % is the base run itself);
  * ``iters``: 25 / 50 / 100 % of both stages' iterations, the step-based schedule (densification
    window and interval, normal-loss start, SH band interval, texture warm-up and growth interval)
    compressed by the same factor;
  * ``sh``: the final SH degree 0 ... 3.

  Variants that differ only in stage-2 settings (``patexgs_jax.training.config.STAGE2_FIELDS``: mip, texture
  kind) share one 2DGS stage: each distinct stage 1 is trained once, as a ``2dgs`` run, and the
  textured runs start from its end-of-stage-1 checkpoint. That ``2dgs`` run continues its stage for
  the texture stage's steps, so every entry of a knob trains the same number of steps.
  ``train_seconds`` of a run counts both stages (the shared stage 1 included; compilation included,
  as the trainer reports it).

  Each run is evaluated on the test views at zoom-out scales 1, 2, 4, 8 (PSNR, SSIM) and its render
  time measured at each scale (per view the fastest of 3 renders, the median over views;
  compilation excluded). The Pareto
  fronts of PSNR against training time and against render time are drawn per scale.

  Outputs in DIR (default ``runs/tradeoffs``): ``tradeoffs.json`` (written after every run),
  ``tradeoffs.md`` (one table per knob), ``tradeoffs.png`` (PSNR against time, Pareto fronts) and
  ``runs/<method>-<hash>/`` (each training run). An interrupted study resumes: finished runs are
  skipped and an interrupted training run continues from its last checkpoint.

  Without ``--data`` the study runs on the embedded synthetic scene with the ``tiny`` preset, whose
  texture stage it shortens to 60 steps (``--iters-tex`` to change).

From a study (the third form)
  A ``python -m experiments.mipnerf360`` study's entries, whatever methods it ran (3D Gaussians and
  BBSplat variants included), each a labelled point (means over its scenes; one colour per budget)
  of the same plot and a row of the same tables (:mod:`experiments.study_tradeoffs`), written to
  ``tradeoffs.md`` and ``tradeoffs.png`` in DIR (default the study's ``plots/``).

Effects (the second form)
  For one trained run (its ``checkpoints/`` or ``scene.ply``; the render configuration of its method
  from ``summary.json``), each effect - SH bands above 0, RGB textures, alpha textures, mipmaps - is
  switched off on its own; the PSNR it contributes (on minus off) at each scale is set against the
  render time it costs. ``--drop-effects-below DB`` writes the scene without every effect that
  contributes less than DB dB at every scale (PLY + texture sidecar; the render settings to use in
  ``<PLY stem>.render.json``) and reports the render time (and the XLA flop estimate) of the reduced
  scene against the full one: switched-off features are compiled out of the renderer.

``tradeoffs.json`` schema::

    {"schema": 1, "git": str | null, "date": str, "machine": str, "cpu": str, "cpus": int,
     "jax": str, "backend": str, "devices": int,  (experiments.provenance's header, at the study's start)
     "data": str, "preset": str, "scales": [1, 2, 4, 8],
     "base": {TrainConfig as JSON}, "study_seconds": float,
     "runs": {run_id: {"run": run_id, "method": str, "config": {...}, "stage1_run": run_id | null,
                       "steps": int, "train_seconds": float, "stage1_seconds": float | null,
                       "num_gaussians": int,
                       "texels": int, "storage_mb": float, "psnr": {scale: float},
                       "ssim": {scale: float}, "alias_psnr": {scale: float | null},
                       "render_ms": {scale: float}, "wall_seconds": float}},
     "knobs": {knob: [{"label": str, "value": ..., "run": run_id}, ...]},
     "pareto": {"train_seconds" | "render_ms": {scale: [run_id, ...]}}}

Scale keys are strings ("1", "2", ...). ``psnr`` and ``ssim`` compare with the ground truth;
``alias_psnr`` compares the render at 1/s with the run's own full-resolution render box-downsampled
by s (null at scale 1; absent from records written before it existed). Pareto lists are sorted by
increasing cost.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from experiments import provenance
from experiments.effects import _fmt, measure, run_effects
from experiments.provenance import write_json
from patexgs_jax import progress
from patexgs_jax.camera import ZOOM_SCALES
from patexgs_jax.training import FIXED_SIZES

KNOBS = ("mip", "texture", "budget", "iters", "sh")
SCALES = ZOOM_SCALES
MIP_METHODS = {"none": "patexgs-no-mip", "nearest": "patexgs", "trilinear": "patexgs-trilinear"}
BUDGET_FRACTIONS = (1.0, 0.1, 0.01)
ITER_FRACTIONS = (0.25, 0.5, 1.0)
SH_DEGREES = (0, 1, 2, 3)
#: The study's own defaults per preset (applied unless overridden on the command line).
STUDY_DEFAULTS = {"tiny": dict(iters_tex=60)}
SCHEMA = 1


# ------------------------------------------------------------------------------------------------
# Planning
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Entry:
    """One point of one knob: the setting's label and value, and the run's configuration."""

    knob: str
    label: str
    value: object
    config: object  # patexgs_jax.training.TrainConfig


def config_json(cfg) -> dict:
    """A TrainConfig as plain JSON (nested dataclasses as dicts)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))


def run_id(cfg) -> str:
    """``<method>-<10 hex digits>``: equal configurations, equal ids (and run directories)."""
    digest = hashlib.sha1(json.dumps(config_json(cfg), sort_keys=True).encode()).hexdigest()[:10]
    return f"{cfg.method}-{digest}"


def scaled_iterations(cfg, fraction: float):
    """``cfg`` with both stages' iterations and the step-based schedule scaled by ``fraction``."""
    if fraction == 1.0:
        return cfg

    def s(n):
        return max(1, int(round(n * fraction)))

    d = cfg.densify
    return dataclasses.replace(
        cfg, iters_2dgs=s(cfg.iters_2dgs), iters_tex=int(round(cfg.iters_tex * fraction)),
        warmup_tex=s(cfg.warmup_tex), growth_interval=s(cfg.growth_interval), normal_from=s(cfg.normal_from),
        sh_interval=s(cfg.sh_interval),
        densify=dataclasses.replace(d, start=s(d.start), stop=s(d.stop), interval=s(d.interval),
                                    opacity_reset_interval=s(d.opacity_reset_interval)))


def stage1_config(cfg, base):
    """The ``2dgs`` run whose end-of-stage-1 checkpoint is ``cfg``'s stage 1 (stage-2 fields from
    ``base``). It continues its stage for ``base``'s texture steps, so that it is also the study's
    equal-steps 2DGS entry (its stage-1 checkpoint is kept, see ``train.stage1_checkpoint``)."""
    from patexgs_jax.training.config import STAGE2_FIELDS

    fields = {f: getattr(base, f) for f in STAGE2_FIELDS if f not in ("method", "continue_2dgs")}
    return dataclasses.replace(cfg, method="2dgs", continue_2dgs=base.iters_tex, **fields)


def plan(base, knobs: Sequence[str], *, base_gaussians: int | None = None, fixed_sizes=FIXED_SIZES,
         budget_fractions=BUDGET_FRACTIONS, iter_fractions=ITER_FRACTIONS, sh_degrees=SH_DEGREES,
         base_first: bool = True) -> list[Entry]:
    """The study's entries by knob and setting (with ``base_first``, the base run's entries moved to
    the front: the other knobs need its Gaussian count). Budget entries other than 100 % need
    ``base_gaussians`` (the base run's Gaussian count) and are left out without it."""
    unknown = set(knobs) - set(KNOBS)
    if unknown:
        raise ValueError(f"unknown knob(s) {sorted(unknown)}; choose from {', '.join(KNOBS)}.")
    rep = dataclasses.replace
    out = []
    for knob in KNOBS:
        if knob not in knobs:
            continue
        if knob == "mip":
            out += [Entry(knob, m, m, rep(base, method=meth)) for m, meth in MIP_METHODS.items()]
        elif knob == "texture":
            out.append(Entry(knob, "none (2DGS)", 0, stage1_config(base, base)))
            out += [Entry(knob, f"fixed {n}x{n}", n, rep(base, method=f"textured-fixed-{n}")) for n in fixed_sizes]
            out.append(Entry(knob, "adaptive", "adaptive", base))
        elif knob == "budget":
            for f in budget_fractions:
                if f == 1.0:
                    out.append(Entry(knob, "100%", f, base))
                elif base_gaussians is not None:
                    out.append(Entry(knob, f"{100 * f:g}%", f,
                                     rep(base, max_gaussians=max(1, int(round(f * base_gaussians))))))
        elif knob == "iters":
            out += [Entry(knob, f"{100 * f:g}%", f, scaled_iterations(base, f)) for f in iter_fractions]
        elif knob == "sh":
            out += [Entry(knob, f"degree {d}", d, rep(base, sh_degree=d)) for d in sh_degrees]
    if base_first:
        base_id = run_id(base)
        out.sort(key=lambda e: run_id(e.config) != base_id)  # stable
    return out


# ------------------------------------------------------------------------------------------------
# Pareto fronts, tables, plots
# ------------------------------------------------------------------------------------------------
def pareto_front(costs: Sequence[float], qualities: Sequence[float]) -> list[int]:
    """Indices of the points no other point dominates (lower-or-equal cost and higher-or-equal
    quality, one of them strictly), sorted by increasing cost. None / NaN points are ignored; of
    identical points the first is kept."""
    pts = [(float(c), float(q), i) for i, (c, q) in enumerate(zip(costs, qualities))
           if c is not None and q is not None and np.isfinite(c) and np.isfinite(q)]
    pts.sort(key=lambda p: (p[0], -p[1], p[2]))
    front, best = [], -np.inf
    for _, q, i in pts:
        if q > best:
            front.append(i)
            best = q
    return front


def pareto_sets(runs: dict, scales: Sequence[int]) -> dict:
    """``{"train_seconds" | "render_ms": {scale: [run ids on the front]}}`` over evaluated runs."""
    ids = [r for r in runs if runs[r].get("psnr")]
    out = {}
    for cost in ("train_seconds", "render_ms"):
        out[cost] = {}
        for s in scales:
            s = str(s)
            c = [runs[r][cost] if cost == "train_seconds" else runs[r]["render_ms"].get(s) for r in ids]
            q = [runs[r]["psnr"].get(s) for r in ids]
            out[cost][s] = [ids[i] for i in pareto_front(c, q)]
    return out


def markdown(study: dict) -> str:
    """The study as Markdown: one table per knob (PSNR per scale, times, size, Pareto marks)."""
    scales = [str(s) for s in study["scales"]]
    runs, pareto = study["runs"], study.get("pareto") or pareto_sets(study["runs"], study["scales"])
    lines = [f"# Accuracy vs time ({Path(str(study['data'])).name}, preset {study['preset']})", "",
             f"Machine: {study.get('machine', '?')}, jax {study.get('jax', '?')}, code at "
             f"{study.get('git') or '?'} ({study.get('date', '?')}). "
             f"Test views at zoom-out scales {', '.join(scales)}; "
             "train s = both stages' training steps (a shared 2DGS stage counted in full; 2DGS continues its "
             "stage for the texture steps: equal steps); render ms = "
             "per frame (per view the fastest of 3 renders, median over views; no compilation); PSNR against "
             "the ground truth; alias x s = the render at 1/s against the run's own full-resolution render "
             "box-downsampled by s. Pareto: T = on the PSNR-vs-training-time front and "
             "R = on the PSNR-vs-render-time front at that scale (over all runs of the study).", ""]
    head = (["setting", "method", "train s"] + [f"render ms x{s}" for s in scales[:1]]
            + [f"PSNR x{s}" for s in scales] + [f"alias x{s}" for s in scales if s != "1"]
            + ["Gaussians", "MB", "Pareto"])
    for knob, entries in study["knobs"].items():
        lines += [f"## {knob}", "", "| " + " | ".join(head) + " |",
                  "| " + " | ".join(["---"] * 2 + ["---:"] * (len(head) - 3) + ["---"]) + " |"]
        for e in entries:
            r = runs.get(e["run"])
            if r is None or not r.get("psnr"):
                lines.append("| " + " | ".join([e["label"], "(not run yet)"] + [""] * (len(head) - 2)) + " |")
                continue
            marks = ",".join(f"{tag}x{s}" for s in scales for tag, cost in (("T", "train_seconds"), ("R", "render_ms"))
                             if e["run"] in pareto[cost][s])
            lines.append("| " + " | ".join(
                [e["label"], r["method"], _fmt(r["train_seconds"], 0), _fmt(r["render_ms"].get(scales[0]), 1)]
                + [_fmt(r["psnr"].get(s)) for s in scales]
                + [_fmt((r.get("alias_psnr") or {}).get(s)) for s in scales if s != "1"]
                + [str(r["num_gaussians"]), _fmt(r["storage_mb"]), marks or "-"]) + " |")
        lines.append("")
    return "\n".join(lines)


def plot(study: dict, path) -> Path:
    """PSNR against training time (top row) and render time (bottom row) per scale, with the
    Pareto fronts; one colour per knob."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker.NullFormatter below)

    scales = [str(s) for s in study["scales"]]
    runs, pareto = study["runs"], study["pareto"]
    knob_of = {}
    for knob, entries in study["knobs"].items():
        for e in entries:
            knob_of.setdefault(e["run"], (knob, e["label"]))
    names = list(KNOBS) + [k for k in study["knobs"] if k not in KNOBS]  # a study's: methods, budget 10%, ...
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colours = {k: cycle[i % len(cycle)] for i, k in enumerate(names)}
    fig, axes = plt.subplots(2, len(scales), figsize=(4.2 * len(scales), 7.5), squeeze=False)
    for row, cost in enumerate(("train_seconds", "render_ms")):
        for col, s in enumerate(scales):
            ax = axes[row, col]
            seen = set()
            for rid, r in runs.items():
                if not r.get("psnr") or rid not in knob_of:
                    continue
                x = r["train_seconds"] if cost == "train_seconds" else r["render_ms"].get(s)
                y = r["psnr"].get(s)
                if x is None or y is None:
                    continue
                knob, label = knob_of[rid]
                ax.scatter([x], [y], color=colours.get(knob, "k"), s=18,
                           label=None if knob in seen else knob, zorder=3)
                seen.add(knob)
                ax.annotate(label, (x, y), fontsize=6, xytext=(2, 2), textcoords="offset points")
            front = pareto[cost][s]
            fx = [runs[r]["train_seconds"] if cost == "train_seconds" else runs[r]["render_ms"][s] for r in front]
            fy = [runs[r]["psnr"][s] for r in front]
            if fx:
                ax.step(fx, fy, where="post", color="k", lw=1, alpha=0.6)
                ax.scatter(fx, fy, facecolors="none", edgecolors="k", s=70, label="Pareto front", zorder=4)
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_xlabel("training time (s)" if cost == "train_seconds" else "render time per frame (ms)")
            ax.set_ylabel(f"PSNR (dB), zoom-out x{s}")
            ax.grid(alpha=0.3)
            if row == 0 and col == 0:
                ax.legend(fontsize=7)
    fig.suptitle(f"Accuracy vs time: {Path(str(study['data'])).name}, preset {study['preset']}")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------------------
# The study
# ------------------------------------------------------------------------------------------------
def _latest_scene(run_dir: Path):
    from patexgs_jax import checkpoint as ckpt

    latest = ckpt.latest_checkpoint(run_dir / "checkpoints")
    if latest is None:
        raise FileNotFoundError(f"{run_dir} has no checkpoint.")
    tree, _ = ckpt.load_checkpoint(latest)
    return tree["scene"]


class Study:
    """The state of one study directory (``tradeoffs.json`` and the run directories)."""

    def __init__(self, dataset, base, out_dir, *, data_name: str, preset: str, scales=SCALES,
                 verbose: bool = True, render_views: int = 8):
        self.ds, self.base, self.out = dataset, base, Path(out_dir)
        self.scales, self.verbose, self.render_views = tuple(int(s) for s in scales), verbose, render_views
        self.out.mkdir(parents=True, exist_ok=True)
        self.path = self.out / "tradeoffs.json"
        state = json.loads(self.path.read_text()) if self.path.exists() else None
        if state is not None and (state.get("base") != config_json(base) or state.get("scales") != list(self.scales)):
            raise ValueError(f"{self.path} holds a study with another base configuration or scales; choose "
                             "another --out or the same settings.")
        self.state = state or dict(provenance.header(SCHEMA), data=data_name, preset=preset,
                                   scales=list(self.scales), base=config_json(base), study_seconds=0.0,
                                   runs={}, knobs={}, pareto={})
        self.bar = progress.bar(0, "tradeoffs", show=False)  # run() replaces it with the drawn one

    def say(self, msg):
        if self.verbose:
            progress.say(msg)

    def recorded(self, rid: str) -> bool:
        rec = self.state["runs"].get(rid)
        return rec is not None and bool(rec.get("psnr"))

    def run_dir(self, cfg) -> Path:
        return self.out / "runs" / run_id(cfg)

    def _train(self, cfg, stage1=None):
        """Trains (or resumes) ``cfg`` into its run directory; returns (scene, summary)."""
        from patexgs_jax.training import train

        d = self.run_dir(cfg)
        if (d / "summary.json").exists():
            return _latest_scene(d), json.loads((d / "summary.json").read_text())
        self.say(f"--- training {run_id(cfg)}" + (f" from stage 1 {stage1}" if stage1 else ""))
        res = train(self.ds, cfg, d, resume=True, verbose=self.verbose, stage1=stage1)
        return res.scene, res.summary

    def ensure(self, cfg) -> dict:
        """The evaluated record of ``cfg``'s run (trained and evaluated unless already recorded)."""
        from patexgs_jax.training import stage1_checkpoint

        rid = run_id(cfg)
        if self.recorded(rid):
            return self.state["runs"][rid]
        t0 = time.perf_counter()
        s1_id, s1_seconds, stage1 = None, None, None
        if cfg.method != "2dgs":
            s1 = stage1_config(cfg, self.base)
            self._train(s1)
            s1_id = run_id(s1)
            stage1 = stage1_checkpoint(self.run_dir(s1), cfg)
            if stage1 is None and not (self.run_dir(cfg) / "checkpoints").is_dir():
                raise RuntimeError(f"no end-of-stage-1 checkpoint in {self.run_dir(s1)} for {rid}.")
            if stage1 is not None:  # the 2DGS stage's own time (the 2dgs run went on after it)
                from patexgs_jax import checkpoint as ckpt

                s1_seconds = float(ckpt.load_checkpoint(stage1)[0]["t_train"])
        scene, summary = self._train(cfg, stage1)
        self.say(f"--- evaluating {rid} at scales {self.scales}")
        m = measure(scene, self.ds.test_views, cfg.render_config(), self.scales, max_views=self.render_views)
        rec = dict(run=rid, method=cfg.method, config=config_json(cfg), stage1_run=s1_id,
                   steps=int(summary["steps"]), train_seconds=float(summary["train_seconds"]),
                   stage1_seconds=s1_seconds,
                   num_gaussians=int(summary["num_gaussians"]), texels=int(summary["texels"]),
                   storage_mb=float(summary["storage_mb"]), wall_seconds=time.perf_counter() - t0, **m)
        self.state["runs"][rid] = rec
        self.state["study_seconds"] += rec["wall_seconds"]
        self.save()
        self.bar.update(1)
        self.say(f"    {rid}: PSNR " + " / ".join(_fmt(m["psnr"][str(s)]) for s in self.scales)
                 + " dB (alias PSNR " + " / ".join(_fmt(m["alias_psnr"][str(s)]) for s in self.scales if s != 1)
                 + f" dB), {rec['train_seconds']:.0f} s training, {_fmt(m['render_ms']['1'], 1)} ms/frame")
        return rec

    def add(self, entry: Entry) -> dict:
        rec = self.ensure(entry.config)
        entries = self.state["knobs"].setdefault(entry.knob, [])
        item = dict(label=entry.label, value=entry.value, run=rec["run"])
        if item not in entries:
            entries.append(item)
            self.save()
        return rec

    def save(self) -> None:
        self.state["pareto"] = pareto_sets(self.state["runs"], self.scales)
        write_json(self.path, self.state)
        (self.out / "tradeoffs.md").write_text(markdown(self.state))

    def run(self, knobs=KNOBS, **plan_kw) -> dict:
        entries = plan(self.base, knobs, **plan_kw)
        ids = {run_id(e.config) for e in entries}
        with progress.bar(len(ids), "tradeoffs", unit="run", initial=sum(map(self.recorded, ids)), leave=True,
                          show=self.verbose) as self.bar:
            for e in entries:
                self.add(e)
            if "budget" in knobs:
                n = self.ensure(self.base)["num_gaussians"]
                entries = plan(self.base, knobs, base_gaussians=n, **plan_kw)
                more = {run_id(e.config) for e in entries} - ids  # the budgets: known once the base ran
                self.bar.total += len(more)
                self.bar.update(sum(map(self.recorded, more)))
                for e in entries:
                    self.add(e)
        # Each knob's table in the order of its settings (runs were trained base first).
        n = self.state["runs"].get(run_id(self.base), {}).get("num_gaussians")
        order = {(e.knob, e.label): i for i, e in enumerate(plan(self.base, knobs, base_gaussians=n, base_first=False,
                                                                 **plan_kw))}
        for knob, items in self.state["knobs"].items():
            items.sort(key=lambda it: order.get((knob, it["label"]), len(order)))
        self.save()
        plot(self.state, self.out / "tradeoffs.png")
        return self.state


# ------------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------------
def _ints(s):
    return tuple(int(x) for x in s.split(",") if x)


def _floats(s):
    return tuple(float(x) for x in s.split(",") if x)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.tradeoffs", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="scene folder; default: the embedded synthetic scene")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling (default: as train's)")
    ap.add_argument("--out", default=None, help="output folder (default runs/tradeoffs; with --effects RUN/effects)")
    ap.add_argument("--scales", type=_ints, default=SCALES, help="zoom-out factors evaluated, comma-separated "
                    "(default 1,2,4,8)")
    ap.add_argument("--render-views", type=int, default=8, help="test views timed per scale")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    ap.add_argument("--no-compile-cache", action="store_true", help="compile every program (default: compiled "
                    "programs are kept between runs, see PATEXGS_COMPILE_CACHE); training times then include "
                    "every compile")
    g = ap.add_argument_group("study")
    g.add_argument("--preset", default=None, help="tiny (default without --data), small or paper (default with --data)")
    g.add_argument("--knobs", default=",".join(KNOBS), help=f"the knobs turned one at a time, comma-separated, from "
                   f"{', '.join(KNOBS)} (default all)")
    g.add_argument("--iters-2dgs", type=int, default=None, help="steps of the 2DGS stage (default: the preset's)")
    g.add_argument("--iters-tex", type=int, default=None, help="steps of the texture stage (default: the preset's)")
    g.add_argument("--max-gaussians", type=int, default=None, help="Gaussian cap (default: the preset's)")
    g.add_argument("--seed", type=int, default=0, help="seed of every run (default 0)")
    g.add_argument("--fixed-sizes", type=_ints, default=FIXED_SIZES, help="texture sides of the fixed-texture settings "
                   "(the texture knob), comma-separated")
    g.add_argument("--budget-fractions", type=_floats, default=BUDGET_FRACTIONS,
                   help="Gaussian budgets as fractions of "
                   "the base run's count (the budget knob; default 1,0.1,0.01)")
    g.add_argument("--iter-fractions", type=_floats, default=ITER_FRACTIONS, help="run lengths as fractions of the "
                   "preset's (the iters knob; default 0.25,0.5,1)")
    g.add_argument("--sh-degrees", type=_ints, default=SH_DEGREES, help="SH degrees (the sh knob; default 0,1,2,3)")
    e = ap.add_argument_group("effects")
    e.add_argument("--effects", action="store_true", help="the effect study of one trained run (--run)")
    e.add_argument("--run", default=None, help="a training run directory (checkpoints/ or scene.ply)")
    e.add_argument("--drop-effects-below", type=float, default=None, metavar="DB", help="export the run without the "
                   "effects worth less than DB of PSNR (to --export)")
    e.add_argument("--export", default=None, help="reduced PLY path (default OUT/scene_reduced.ply)")
    ap.add_argument("--from-study", default=None, metavar="RESULTS",
                    help="plot a python -m experiments.mipnerf360 study's entries (its results.json or folder) "
                    "as labelled points; nothing is trained")
    args = ap.parse_args(argv)

    from patexgs_jax import memory_maps
    from patexgs_jax.checkpoint import CheckpointError, check_output_dir
    from patexgs_jax.data import load

    if not args.no_compile_cache:
        memory_maps.enable_compile_cache()

    if args.from_study is not None:
        from experiments.study_tradeoffs import write_from_study

        try:
            paths = write_from_study(args.from_study, args.out)
        except (ValueError, OSError) as ex:
            print(f"error: {ex}", file=sys.stderr)
            return 2
        print(f"written: {', '.join(map(str, paths))}")
        return 0
    # Mistakes in the arguments are named before any scene is made or loaded.
    if args.effects and args.run is None:
        ap.error("--effects needs --run RUN_DIR")
    if args.effects and not Path(args.run).is_dir():  # before the scene is loaded
        print(f"error: --run {args.run} is not a folder: pass --run a folder that python -m "
              "patexgs_jax.train --out wrote.", file=sys.stderr)
        return 2
    unknown = [k for k in args.knobs.split(",") if k and k not in KNOBS]
    if unknown:
        print(f"error: unknown knob(s) {', '.join(unknown)}: choose from {', '.join(KNOBS)}.", file=sys.stderr)
        return 2
    synthetic = args.data is None
    if synthetic:
        from patexgs_jax.data.synthetic import ensure_default_scene

        args.data = str(ensure_default_scene())
    try:
        out = args.out or (Path(args.run) / "effects" if args.effects else "runs/tradeoffs")
        check_output_dir(out)
        ds = load(args.data, factor=args.factor)
        if args.effects:
            run_effects(args.run, ds, out, scales=args.scales,
                        drop_below=args.drop_effects_below, export_path=args.export, verbose=not args.quiet,
                        max_views=args.render_views)
            return 0
        from patexgs_jax.training import preset_config

        preset = args.preset or ("tiny" if synthetic else "paper")
        over = dict(STUDY_DEFAULTS.get(preset, {}))
        over.update({k: v for k, v in dict(iters_2dgs=args.iters_2dgs, iters_tex=args.iters_tex,
                                           max_gaussians=args.max_gaussians).items() if v is not None})
        base = preset_config(preset, method="patexgs", seed=args.seed, **over)
        knobs = [k for k in args.knobs.split(",") if k]
        study = Study(ds, base, out, data_name=args.data, preset=preset,
                      scales=args.scales, verbose=not args.quiet, render_views=args.render_views)
        t0 = time.perf_counter()
        study.run(knobs, fixed_sizes=args.fixed_sizes, budget_fractions=args.budget_fractions,
                  iter_fractions=args.iter_fractions, sh_degrees=args.sh_degrees)
        print(f"study done in {time.perf_counter() - t0:.0f} s (this invocation): {study.out / 'tradeoffs.md'}, "
              f"{study.out / 'tradeoffs.png'}")
    except (ValueError, FileNotFoundError, OSError, CheckpointError) as ex:
        print(f"error: {ex}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
