"""The README's headline figures of the main job, regenerated from the run they come from.

    python -m experiments.headline SOURCE [--save benchmarks/main_job_tiny.json --conditions TEXT]
    python -m experiments.headline STUDY --budgets LABEL [--save FILE --conditions TEXT]
    python -m experiments.headline STUDY --zoom LABEL [--save FILE --conditions TEXT]
    python -m experiments.headline STUDY --tables LABEL [--save FILE --conditions TEXT]
    python -m experiments.headline STUDY --paper LABEL [--save FILE --conditions TEXT]

SOURCE is a main-job output folder (``python -m experiments.mipnerf360 --out DIR``: its
``results.json``) or a benchmark file written by ``--save``. The command prints the README's
headline sentence (test PSNR of 2DGS and PATexGS at full size and at 1/8, PATexGS's Gaussians,
texels and storage), a small table of the same figures, and docs/results.md's provenance row (commit,
date, CPU, conditions, wall time). ``--save`` keeps the study's
results with their provenance (commit, date, machine: :mod:`experiments.provenance`) and
``--conditions``, a few words on how the machine was loaded and whether the compile cache was warm,
as a file under ``benchmarks/``: the README quotes that file, and ``tests/unit/test_repo.py`` fails
when the README's sentence no longer matches it. ``--budgets LABEL`` prints instead the README's
Gaussian-budget rows of a ``--budgets`` study (``benchmarks/budgets_*.json``), ``--zoom LABEL``
the README's zoom-out rows of any study (``benchmarks/zoom_*.json``), and ``--tables LABEL`` the
README's rows of the paper's Tables 1 and 2 (ours beside the paper's figures) and, for a
``--zoom-in`` study, of the zoom-in table (:func:`table1_rows`, :func:`table2_rows`,
:func:`zoom_in_rows`; means over the study's scenes), each block under its header, checked the same
way; ``--paper LABEL`` the rows of docs/results.md's side-by-side of ``patexgs``, ``patexgs-literal``
and ``patexgs-paper-sigma`` (:func:`paper_rows`; ``benchmarks/paper_*.json``); with ``--save`` any of
them keeps the study as a benchmark file first.

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
    """The README's headline sentence (one line; the README may wrap it anywhere): the figures only.
    Where and when they were measured is :func:`provenance_row`'s, in docs/results.md."""
    f = figures(data)
    return (f"test PSNR {f['psnr'][BASELINE]:.2f} dB (2DGS) and {f['psnr'][METHOD]:.2f} dB (PATexGS, "
            f"{f['gaussians']:,} Gaussians, {f['texels']:,} texels, {f['storage_mb']:.2f} MB) at full size, "
            f"{f['psnr_8'][BASELINE]:.2f} / {f['psnr_8'][METHOD]:.2f} dB at 1/8.")


#: The header of docs/results.md's provenance table (:func:`provenance_row`).
PROVENANCE_HEADER = "| figures | file | commit | date | CPU | conditions | wall time |"


def provenance_row(data: dict, label: str, file: str) -> str:
    """docs/results.md's provenance row of a benchmark file (``| label | file | commit | date | CPU |
    conditions | wall time |``): where the README's figures were measured."""
    git = (data.get("version") or {}).get("git") or data.get("git") or "?"
    date = str(data.get("date") or "?")[:10]
    cpu = data.get("cpu") or data.get("machine") or "?"
    return (f"| {label} | `{file}` | `{git}` | {date} | {cpu} | {data.get('conditions') or '-'} | "
            f"{duration(data.get('elapsed_seconds'))} |")


def _zoomed_entries(data: dict):
    """(method, entry) of the record's first scene, in the study's order, for the methods evaluated at
    1, 1/2, 1/4 and 1/8."""
    per = next(iter(data["results"].values()))
    return [(m, e) for m, e in per.items() if all(isinstance(e.get(str(s)), dict) for s in (1, 2, 4, 8))]


def _psnr_cells(entry: dict) -> list[str]:
    """The entry's PSNR at 1, 1/2, 1/4, 1/8, two decimals."""
    return [f"{entry[str(s)]['psnr']:.2f}" for s in (1, 2, 4, 8)]


#: The header of the README's results-at-a-glance table (:func:`glance_rows`).
GLANCE_HEADER = "| scene | method | PSNR full | 1/2 | 1/4 | 1/8 | MB |"

#: The methods the README's results-at-a-glance table shows, in its order: the paper read literally
#: beside ours, so that a reader sees where the zoom-out gain comes from.
GLANCE_METHODS = ("2dgs", "patexgs-literal", "patexgs")


def glance_rows(data: dict, scene_label: str, methods: tuple[str, ...] = GLANCE_METHODS) -> list[str]:
    """The README's results-at-a-glance rows (``| scene_label | method | PSNR full | 1/2 | 1/4 | 1/8 |
    MB |``) of a study's record, one per method of ``methods`` evaluated at every zoom-out scale, in
    that order; the record's first scene."""
    entries = dict(_zoomed_entries(data))
    return [f"| {scene_label} | `{m}` | " + " | ".join(_psnr_cells(entries[m])) + f" | {entries[m]['storage_mb']:.2f} |"
            for m in methods if m in entries]


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
    rows = []
    for method, entry in _zoomed_entries(data):
        alias = [f"{entry[str(s)]['alias_psnr']:.2f}" for s in (2, 4, 8)]
        rows.append(f"| {scene_label} | {method} | " + " | ".join(_psnr_cells(entry) + alias) + " |")
    return rows


def paper_rows(data: dict, scene_label: str) -> list[str]:
    """docs/results.md's rows of the paper read literally (``| scene_label | method | sigma | texels |
    storage MB | PSNR full | 1/8 | alias 1/8 |``) of a study's record, one per method evaluated at 1 and
    1/8 in the study's order; the record's first scene. ``sigma`` is the Eq. 7 sigma (``-`` where none)."""
    per = next(iter(data["results"].values()))
    rows = []
    for method, entry in per.items():
        if not all(isinstance(entry.get(s), dict) for s in ("1", "8")):
            continue
        sigma = "-" if entry.get("sigma") is None else f"{entry['sigma']:.4g}"
        cells = [sigma, f"{int(entry['texels']):,}", f"{entry['storage_mb']:.2f}", f"{entry['1']['psnr']:.2f}",
                 f"{entry['8']['psnr']:.2f}", f"{entry['8']['alias_psnr']:.2f}"]
        rows.append(f"| {scene_label} | {method} | " + " | ".join(cells) + " |")
    return rows


def _mean(data: dict, key: str, field):
    from experiments.study_tables import _mean_over_scenes

    return _mean_over_scenes(data["results"], key, field)


def _f(v, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _keys(data: dict, table) -> list[str]:
    from experiments.paper import ordered
    from experiments.study_tables import _labels

    return ordered(_labels(data["results"]), table)


#: The headers of the README's blocks (``--tables``).
TABLE1_HEADER = ("| scene | method | paper row | PSNR | paper | SSIM | paper | LPIPS | paper | Gaussians | MB | "
                 "train s |")
TABLE2_HEADER = ("| scene | method | paper row | full | 1/2 | 1/4 | 1/8 | paper full | paper 1/2 | paper 1/4 | "
                 "paper 1/8 |")
ZOOM_IN_HEADER = "| scene | method | PSNR train res. | x2 | x4 | x8 | SSIM x8 |"


def table1_rows(data: dict, scene_label: str) -> list[str]:
    """The README's Table 1 rows of a study (``| scene_label | method | paper row | PSNR | paper |
    SSIM | paper | LPIPS | paper | Gaussians | MB | train s |``, means over its scenes), every entry
    evaluated at full size, the paper's rows first in its order; ``paper`` is the paper's Mip-NeRF 360
    figure (blank without)."""
    from experiments.paper import PAPER_TABLE1, TABLE1_METHODS, paper_name

    rows = []
    for key in _keys(data, TABLE1_METHODS):
        if _mean(data, key, lambda e: e.get("1", {}).get("psnr")) is None:
            continue
        fig = PAPER_TABLE1.get(key, (None, None, None))
        cells = []
        for i, (name, digits) in enumerate((("psnr", 2), ("ssim", 3), ("lpips", 3))):
            cells += [_f(_mean(data, key, lambda e, n=name: e.get("1", {}).get(n)), digits),
                      "" if fig[i] is None else f"{fig[i]:.{digits}f}"]
        g, mb, t = (_mean(data, key, lambda e, f=f: e.get(f)) for f in ("num_gaussians", "storage_mb", "train_seconds"))
        cells += ["-" if g is None else f"{int(round(g)):,}", _f(mb), _f(t, 0)]
        rows.append(f"| {scene_label} | {key} | {paper_name(key) or ''} | " + " | ".join(cells) + " |")
    return rows


def table2_rows(data: dict, scene_label: str) -> list[str]:
    """The README's Table 2 rows (``| scene_label | method | paper row | full | 1/2 | 1/4 | 1/8 | paper
    full | paper 1/2 | paper 1/4 | paper 1/8 |``: PSNR, ours then the paper's) of the entries evaluated
    at every zoom-out scale, the paper's rows first."""
    from experiments.paper import PAPER_TABLE2, TABLE2_METHODS, paper_name

    rows = []
    for key in _keys(data, TABLE2_METHODS):
        ours = [_mean(data, key, lambda e, s=s: e.get(str(s), {}).get("psnr")) for s in (1, 2, 4, 8)]
        if any(v is None for v in ours):
            continue
        fig = PAPER_TABLE2.get(key, {})
        theirs = ["" if s not in fig else f"{fig[s][0]:.2f}" for s in (1, 2, 4, 8)]
        rows.append(f"| {scene_label} | {key} | {paper_name(key) or ''} | " + " | ".join(map(_f, ours)) + " | "
                    + " | ".join(theirs) + " |")
    return rows


def zoom_in_rows(data: dict, scene_label: str) -> list[str]:
    """The README's zoom-in rows (Mip-Splatting's protocol: ``| scene_label | method | PSNR train res. |
    x2 | x4 | x8 | SSIM x8 |``) of the entries evaluated with ``--zoom-in``; none without."""
    from experiments.paper import ZOOM_IN_METHODS

    rows = []
    for key in _keys(data, ZOOM_IN_METHODS):
        if not any("zoom_in" in per.get(key, {}) for per in data["results"].values()):
            continue
        psnr = [_mean(data, key, lambda e: e.get("1", {}).get("psnr"))]
        psnr += [_mean(data, key, lambda e, z=z: (e.get("zoom_in") or {}).get(z, {}).get("psnr")) for z in "248"]
        ssim = _mean(data, key, lambda e: (e.get("zoom_in") or {}).get("8", {}).get("ssim"))
        rows.append(f"| {scene_label} | {key} | " + " | ".join(map(_f, psnr)) + f" | {_f(ssim, 3)} |")
    return rows


def tables_blocks(data: dict, scene_label: str) -> list[str]:
    """The ``--tables`` output: Table 1's, Table 2's and (when there are any) the zoom-in rows, each
    block a title line, its header and separator, and its rows; empty when no entry has a full-size
    figure."""
    out = []
    for title, head, text, rows in (("Table 1", TABLE1_HEADER, 3, table1_rows(data, scene_label)),
                                      ("Table 2 (zoom-out PSNR)", TABLE2_HEADER, 3, table2_rows(data, scene_label)),
                                      ("Zoom-in (Mip-Splatting's protocol, PSNR)", ZOOM_IN_HEADER, 2,
                                       zoom_in_rows(data, scene_label))):
        if rows:
            sep = "| " + " | ".join("---" if i < text else "---:" for i in range(head.count("|") - 1)) + " |"
            out += ([""] if out else []) + [f"{title}:", head, sep, *rows]
    return out if table1_rows(data, scene_label) else []


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
                    "recorded in the file for docs/results.md's provenance table")
    kind = ap.add_mutually_exclusive_group()
    kind.add_argument("--budgets", default=None, metavar="LABEL",
                    help="SOURCE is a --budgets study (any scene): print the README's budget-table rows, "
                    "with LABEL in the scene column")
    kind.add_argument("--zoom", default=None, metavar="LABEL",
                    help="SOURCE is any study (its first scene): print the README's zoom-out rows, with LABEL "
                    "in the scene column")
    kind.add_argument("--tables", default=None, metavar="LABEL",
                    help="SOURCE is any study (means over its scenes): print the README's rows of the paper's "
                    "Tables 1 and 2, ours beside the paper's figures, and the zoom-in rows of a --zoom-in study, "
                    "with LABEL in the scene column")
    kind.add_argument("--paper", default=None, metavar="LABEL",
                    help="SOURCE is any study (its first scene): print docs/results.md's rows of the paper read "
                    "literally (sigma, texels, storage, PSNR full and 1/8, alias 1/8), with LABEL in the scene column")
    args = ap.parse_args(argv)
    if args.budgets is not None or args.zoom is not None or args.tables is not None or args.paper is not None:
        try:
            data = read(args.source)
            if args.tables is not None:
                rows = tables_blocks(data, args.tables)
            elif args.paper is not None:
                rows = paper_rows(data, args.paper)
            else:
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
                    else "no entry evaluated at full size" if args.tables is not None
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
    print()
    print(PROVENANCE_HEADER)
    print(provenance_row(data, "main job (README)", args.save or str(args.source)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
