"""Zoom-out A/B of render settings on trained runs: how close each setting's render at 1/s is to the
same model's supersampled render, and to the ground truth.

For every trained run in a :mod:`experiments.mipnerf360` output folder, the test views are rendered
under each named :class:`RenderConfig` variant, in one process (the machines are noisy, so timing
comparisons belong in one run). For each scale s it prints

  * ``alias``: PSNR of the render at 1/s against this variant's own full-resolution render
    box-downsampled by s (what a perfectly anti-aliased renderer of the same model shows);
  * ``gt``: PSNR against the test image box-downsampled by s;
  * ``bound``: the own full-resolution render box-downsampled by s against that test image (what
    a perfectly anti-aliased renderer of the model would score);
  * ``ms``: the median full-resolution render time.

  python -m experiments.zoom_ab --study runs/mipnerf360 [--data ROOT] [--variants a,b] [--views N] [--methods a,b]

The variants are the keys of :data:`VARIANTS`. A model is judged with the settings it was not trained
with too (a render-time switch), which shows what the renderer itself does, separately from what
training does with it. The readings of the paper's Eq. 13 (docs/zoom_out.md) are ``lowpass`` (the 2DGS
low-pass, ``patexgs-literal``'s), ``object`` (Eq. 2's G as written), ``texel-grid`` (G x A on the texel
grid, in the alpha pyramid; textured runs only) and ``prefilter`` (ours). ``--json`` writes the figures
with the provenance header of :mod:`experiments.provenance`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax

from patexgs_jax import memory_maps
from patexgs_jax.camera import ZOOM_SCALES
from patexgs_jax.checkpoint import CheckpointError, check_output_dir, latest_checkpoint, load_checkpoint
from patexgs_jax.evaluation import evaluate_scales, render_ms, usable
from patexgs_jax.render import RenderConfig

SCALES = ZOOM_SCALES

#: Named render settings (mip flags of the run's method are applied on top: see :func:`_config`).
VARIANTS = {
    "lowpass": dict(coverage="lowpass", lambda_mip=0.4),
    "object": dict(coverage="object", lambda_mip=0.4),
    "texel-grid": dict(coverage="texel-grid", lambda_mip=0.4),
    "prefilter": dict(coverage="prefilter"),
    "prefilter-v.083": dict(coverage="prefilter", pixel_var=1.0 / 12.0),
    "prefilter-v.2": dict(coverage="prefilter", pixel_var=0.2),
    "prefilter-v.25": dict(coverage="prefilter", pixel_var=0.25),
    "prefilter-v.3": dict(coverage="prefilter", pixel_var=0.3),
    "prefilter-m0": dict(coverage="prefilter", min_var=0.0),
    "prefilter-m.25": dict(coverage="prefilter", min_var=0.25),
    "prefilter-m.3": dict(coverage="prefilter", min_var=0.3),
    "prefilter-v.083-m.3": dict(coverage="prefilter", pixel_var=1.0 / 12.0, min_var=0.3),
    "prefilter-m.5": dict(coverage="prefilter", min_var=0.5),
    "prefilter-lam.4": dict(coverage="prefilter", lambda_mip=0.4),
    "prefilter-lam.33": dict(coverage="prefilter", lambda_mip=1.0 / 3.0),
    "prefilter-lam.083": dict(coverage="prefilter", lambda_mip=1.0 / 12.0),
    "prefilter-trilinear": dict(coverage="prefilter", mip="trilinear"),
    "prefilter-nomip": dict(coverage="prefilter", mip="none"),
}


def _config(base: RenderConfig, variant: dict) -> RenderConfig:
    kw = dict(mip=base.mip, rgb_mip=base.rgb_mip, alpha_mip=base.alpha_mip, background=base.background)
    if base.mip == "none":  # a method without mipmaps stays without them
        variant = {k: v for k, v in variant.items() if k != "mip"}
    kw.update(variant)
    return RenderConfig(**kw)


def _runs(study: Path):
    """(scene, label, run folder) of every finished run of a study."""
    for scene_dir in sorted((study / "runs").iterdir()):
        for run in sorted(scene_dir.iterdir()):
            if (run / "summary.json").exists():
                yield scene_dir.name, run.name, run


def probe(scene, views, config: RenderConfig, scales=SCALES) -> dict:
    """{str(s): {"alias", "gt", "bound"}} means over ``views`` for one render setting (alias and
    bound None at s = 1; the studies' ``alias_psnr``, ``psnr`` and ``supersampled_psnr``)."""
    ev = evaluate_scales(scene, views, config, scales=scales)
    return {str(s): dict(alias=ev[str(s)]["alias_psnr"], gt=ev[str(s)]["psnr"], bound=ev[str(s)]["supersampled_psnr"])
            for s in scales}


def reading_rows(data: dict, scene_label: str, runs=None) -> list[str]:
    """docs/results.md's rows of a ``--json`` file (``| scene_label | run | variant | PSNR full | 1/2 | 1/4 |
    1/8 | alias 1/2 | 1/4 | 1/8 |``), one per (run, variant) in the file's order; its first scene, the
    ``runs`` named (default all)."""
    per = next(iter(data["results"].values()))
    rows = []
    for run, variants in per.items():
        if runs is not None and run not in runs:
            continue
        for name, res in variants.items():
            cells = [f"{res[str(s)]['gt']:.2f}" for s in SCALES] + [f"{res[str(s)]['alias']:.2f}" for s in SCALES[1:]]
            rows.append(f"| {scene_label} | {run} | {name} | " + " | ".join(cells) + " |")
    return rows


def main(argv=None) -> int:
    from patexgs_jax.data import load
    from patexgs_jax.training import TrainConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--study", required=True, help="an experiments.mipnerf360 output folder")
    ap.add_argument("--data", default=None, help="the study's --data (default: the embedded scene)")
    ap.add_argument("--variants", default="lowpass,prefilter", help="comma-separated renderer settings to compare, "
                    f"from {', '.join(VARIANTS)} (default lowpass,prefilter)")
    ap.add_argument("--views", type=int, default=None, help="at most this many test views")
    ap.add_argument("--methods", default=None, help="only these runs (comma-separated labels; default all)")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    memory_maps.enable_compile_cache()
    study = Path(args.study)
    names = args.variants.split(",")
    for n in names:
        if n not in VARIANTS:
            ap.error(f"unknown variant {n!r}; choose from {', '.join(VARIANTS)}")
    if not (study / "results.json").is_file():
        print(f"error: no results.json in --study {study}: pass a folder that python -m experiments.mipnerf360 "
              "--out wrote.", file=sys.stderr)
        return 2
    if args.json:
        try:
            check_output_dir(Path(args.json).parent, "--json's folder")
        except CheckpointError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    cfg = json.loads((study / "results.json").read_text())["config"]
    if args.data is None:
        from patexgs_jax.data.synthetic import ensure_default_scene

        root = Path(ensure_default_scene(verbose=False))
    else:
        root = Path(args.data)
    figures = {}
    only = None if args.methods is None else set(args.methods.split(","))
    for scene_name, label, run in _runs(study):
        if only is not None and label not in only:
            continue
        one_scene = (root / "sparse").exists() or scene_name not in {p.name for p in root.iterdir()}
        path = root if one_scene else root / scene_name
        ds = load(path, factor=cfg.get("factor"))
        views = [v for v in ds.test_views if usable(v)][: args.views]
        tree, meta = load_checkpoint(latest_checkpoint(run / "checkpoints"))
        tc = TrainConfig(method=meta["config"]["method"], lambda_mip=meta["config"].get("lambda_mip"))
        base = tc.render_config()
        scene = tree["scene"]
        for n in names:
            rc = _config(base, VARIANTS[n])
            if rc.coverage == "texel-grid" and scene.alpha is None:
                print(f"{scene_name} {label:>10} {n:>20}: not rendered (no alpha textures to weight)", flush=True)
                continue
            t = time.perf_counter()
            res = probe(scene, views, rc)
            res["ms"] = render_ms(scene, views, rc, max_views=4)
            figures.setdefault(scene_name, {}).setdefault(label, {})[n] = res
            cells = " | ".join(f"{res[str(s)]['gt']:.2f}" + (
                "" if s == 1 else f" / {res[str(s)]['alias']:.2f} / {res[str(s)]['bound']:.2f}") for s in SCALES)
            print(f"{scene_name} {label:>10} {n:>20}: gt / alias / bound  {cells} | {res['ms']:.1f} ms "
                  f"({time.perf_counter() - t:.0f} s)", flush=True)
            if args.json:  # after every variant: a stopped comparison keeps what it measured
                from experiments.provenance import header, write_json

                write_json(args.json, {**header(1), "study": str(study), "study_config": cfg,
                                       "variants": {n: VARIANTS[n] for n in names}, "results": figures})
        jax.clear_caches()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
