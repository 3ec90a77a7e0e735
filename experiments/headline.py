"""The README's headline figures of the main job, regenerated from the run they come from.

    python -m experiments.headline SOURCE [--save benchmarks/main_job_tiny.json --conditions TEXT]
    python -m experiments.headline STUDY --budgets LABEL [--save FILE --conditions TEXT]
    python -m experiments.headline STUDY --zoom LABEL [--save FILE --conditions TEXT]

SOURCE is a main-job output folder (``python -m experiments.mipnerf360 --out DIR``: its
``results.json``) or a benchmark file written by ``--save``. The command prints the README's
headline sentence (time, test PSNR of 2DGS and PATexGS at full size and at 1/8, PATexGS's
Gaussians, texels and storage) and a small table of the same figures. ``--save`` keeps the study's
results with their provenance (commit, date, machine: :mod:`experiments.provenance`) and
``--conditions``, a few words on how the machine was loaded and whether the compile cache was warm,
as a file under ``benchmarks/``: the README quotes that file, and ``tests/unit/test_repo.py`` fails
when the README's sentence no longer matches it. ``--budgets LABEL`` prints instead the README's
Gaussian-budget rows of a ``--budgets`` study (``benchmarks/budgets_*.json``), and ``--zoom LABEL``
the README's zoom-out rows of any study (``benchmarks/zoom_*.json``), checked the same way; with
``--save`` either keeps the study as a benchmark file first.

Benchmark file schema (``schema`` 1)::

    {provenance header (experiments.provenance), "conditions": str, "elapsed_seconds": float | null,
     "version": {...}, "config": {...}, "lpips": {...} | null, "results": {scene: {label: {...}}}}

``version``, ``config``, ``lpips`` and ``results`` are the study's ``results.json``'s;
``elapsed_seconds`` its wall-clock time (``results.json``'s own, summed over the invocations that
wrote it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from experiments.provenance import header, write_json

SCHEMA = 1
#: The scene and methods of the main job (``python -m experiments.mipnerf360`` without ``--data``).
SCENE = "synthetic-v1-seed0"
BASELINE, METHOD = "2dgs", "patexgs"


class HeadlineError(ValueError):
    """The source holds no main-job results."""


def load(source) -> dict:
    """The study record of ``source``: a folder holding ``results.json``, a ``results.json``, or a
    benchmark file written by :func:`save`."""
    data = read(source)
    per = data.get("results", {}).get(SCENE, {})
    missing = [k for k in (BASELINE, METHOD) if k not in per]
    if missing:
        raise HeadlineError(f"{source} has no {', '.join(missing)} results for the scene {SCENE}: is it the "
                            "main job's (python -m experiments.mipnerf360 without --data)?")
    return data


def figures(data: dict) -> dict:
    """The headline figures: ``psnr`` and ``psnr_8`` per method (full size and 1/8), PATexGS's
    ``gaussians``, ``texels`` and ``storage_mb``, ``seconds`` (None when not recorded) and ``git``."""
    per = data["results"][SCENE]
    ours = per[METHOD]
    return dict(psnr={k: per[k]["1"]["psnr"] for k in (BASELINE, METHOD)},
                psnr_8={k: per[k]["8"]["psnr"] for k in (BASELINE, METHOD)},
                gaussians=int(ours["num_gaussians"]), texels=int(ours["texels"]), storage_mb=ours["storage_mb"],
                seconds=data.get("elapsed_seconds"), git=(data.get("version") or {}).get("git"))


def duration(seconds: float | None) -> str:
    """``7 min 17 s`` (``?`` when unknown)."""
    if seconds is None:
        return "?"
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s} s" if m else f"{s} s"


def sentence(data: dict) -> str:
    """The README's headline sentence (one line; the README may wrap it anywhere)."""
    f = figures(data)
    conditions = data.get("conditions")
    where = f"At commit `{f['git']}`" + (f", {conditions}" if conditions else "")
    return (f"{where}: {duration(f['seconds'])}; test PSNR {f['psnr'][BASELINE]:.2f} dB (2DGS) and "
            f"{f['psnr'][METHOD]:.2f} dB (PATexGS, {f['gaussians']:,} Gaussians, {f['texels']:,} texels, "
            f"{f['storage_mb']:.2f} MB) at full size, {f['psnr_8'][BASELINE]:.2f} / {f['psnr_8'][METHOD]:.2f} dB "
            "at 1/8.")


def table(data: dict) -> str:
    """The same figures as a Markdown table."""
    f = figures(data)
    per = data["results"][SCENE]
    lines = ["| method | PSNR full | PSNR 1/8 | Gaussians | texels | MB | train s |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for k in (BASELINE, METHOD):
        e = per[k]
        lines.append(f"| {k} | {f['psnr'][k]:.2f} | {f['psnr_8'][k]:.2f} | {int(e['num_gaussians']):,} | "
                     f"{int(e['texels']):,} | {e['storage_mb']:.2f} | {e['train_seconds']:.0f} |")
    return "\n".join(lines + [f"\nmain job: {duration(f['seconds'])} (commit {f['git']})"])


def budget_rows(data: dict, scene_label: str) -> list[str]:
    """The README's budget-table rows (``| scene_label | budget | 2DGS | PATexGS (gain) | 2DGS 1/8 |
    PATexGS 1/8 | Gaussians | PATexGS MB |``) of a ``--budgets`` study's record (its
    ``results.json`` or a benchmark file such as ``benchmarks/budgets_tiny.json``), one per budget
    that has both methods, in the study's order; the record's first scene."""
    per = next(iter(data["results"].values()))
    rows = []
    for budget in ("100%", "10%", "1%"):
        suffix = "" if budget == "100%" else f"({budget})"
        base, ours = per.get(BASELINE + suffix), per.get(METHOD + suffix)
        if base is None or ours is None:
            continue
        b, o = base["1"]["psnr"], ours["1"]["psnr"]
        rows.append(f"| {scene_label} | {budget} | {b:.2f} | {o:.2f} ({o - b:+.2f}) | {base['8']['psnr']:.2f} | "
                    f"{ours['8']['psnr']:.2f} | {int(ours['num_gaussians']):,} | {ours['storage_mb']:.2f} |")
    return rows


def zoom_rows(data: dict, scene_label: str) -> list[str]:
    """The README's zoom-out rows (``| scene_label | method | PSNR full | 1/2 | 1/4 | 1/8 | alias 1/2 |
    alias 1/4 | alias 1/8 |``) of a study's record (its ``results.json`` or a benchmark file such as
    ``benchmarks/zoom_tiny.json``), one per method in the study's order; the record's first scene.
    Methods without a zoomed-out evaluation are left out."""
    per = next(iter(data["results"].values()))
    rows = []
    for method, entry in per.items():
        if not all(isinstance(entry.get(str(s)), dict) for s in (1, 2, 4, 8)):
            continue
        psnr = [f"{entry[str(s)]['psnr']:.2f}" for s in (1, 2, 4, 8)]
        alias = [f"{entry[str(s)]['alias_psnr']:.2f}" for s in (2, 4, 8)]
        rows.append(f"| {scene_label} | {method} | " + " | ".join(psnr + alias) + " |")
    return rows


def read(source) -> dict:
    """The record of any study: a folder holding ``results.json``, a ``results.json`` or a benchmark
    file (no check of its scene or methods; :func:`load` checks them for the main job)."""
    path = Path(source)
    if path.is_dir():
        path = path / "results.json"
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise HeadlineError(f"cannot read {path}: {e}") from None
    if not isinstance(data, dict) or not data.get("results"):
        raise HeadlineError(f"{path} holds no study results (results.json of python -m experiments.mipnerf360)")
    return data


def save(data: dict, path, conditions: str) -> Path:
    """Writes the study's results with their provenance to ``path`` (see the module docstring)."""
    keep = {k: data.get(k) for k in ("version", "config", "lpips", "results")}
    return write_json(path, dict(header(SCHEMA), conditions=conditions, elapsed_seconds=data.get("elapsed_seconds"),
                                 **keep))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.headline", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", help="a study's output folder (results.json) or a benchmark file written by --save")
    ap.add_argument("--save", default=None, help="write the results with their provenance to this JSON file")
    ap.add_argument("--conditions", default="", help="with --save: how the machine was (load, compile cache), "
                    "quoted in the sentence")
    kind = ap.add_mutually_exclusive_group()
    kind.add_argument("--budgets", default=None, metavar="LABEL",
                    help="SOURCE is a --budgets study (any scene): print the README's budget-table rows, "
                    "with LABEL in the scene column")
    kind.add_argument("--zoom", default=None, metavar="LABEL",
                    help="SOURCE is any study (its first scene): print the README's zoom-out rows, with LABEL "
                    "in the scene column")
    args = ap.parse_args(argv)
    if args.budgets is not None or args.zoom is not None:
        try:
            data = read(args.source)
            rows = budget_rows(data, args.budgets) if args.budgets is not None else zoom_rows(data, args.zoom)
        except HeadlineError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except (KeyError, TypeError, AttributeError) as e:
            print(f"error: {args.source} is not a {'--budgets ' if args.budgets is not None else ''}study's "
                  f"results (no {e})", file=sys.stderr)
            return 2
        if not rows:
            what = ("no budget with both 2dgs and patexgs" if args.budgets is not None
                    else "no method evaluated at 1, 1/2, 1/4 and 1/8")
            print(f"error: {args.source} has {what}", file=sys.stderr)
            return 2
        if args.save:
            save(data, args.save, args.conditions)
            print(f"written to {args.save}")
        print("\n".join(rows))
        return 0
    try:
        data = load(args.source)
    except HeadlineError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.save:
        save(data, args.save, args.conditions)
        data = load(args.save)
        print(f"written to {args.save}")
    print(sentence(data))
    print()
    print(table(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
