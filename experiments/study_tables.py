"""The study's tables (``tables.md``): the layouts of the paper's Tables 1-4, the budget rows and a
cost table, from ``results.json``'s data; and the labels that name a study's runs (method and budget).
"""

from __future__ import annotations

import functools

import numpy as np

from experiments.paper import (
    PAPER_TABLE1_BY_DATASET,
    PAPER_TABLE2,
    TABLE1_METHODS,
    TABLE2_METHODS,
    ordered,
    paper_name,
)
from patexgs_jax.camera import ZOOM_SCALES
from patexgs_jax.data.benchmarks import DATASET_NAMES, DATASETS
from patexgs_jax.data.benchmarks import SCENES as PAPER_SCENES

SCALES = ZOOM_SCALES
#: The fixed-size row whose storage matches the adaptive run's ("similar parameters" in the paper's
#: Table 4): ``patexgs-fixed-N`` with N the side whose N * N texels per Gaussian are closest to the
#: ``patexgs`` run's mean (trained after it).
MATCHED = "patexgs-matched"


class StudyError(ValueError):
    """The study cannot run as asked (bad arguments, no scenes, mismatched output directory)."""


def parse_budget(text: str | None):
    """``None``, ``("fraction", f)`` from ``"10%"``, or ``("count", n)`` from ``"5000"``."""
    if text is None or text in ("", "100%"):
        return None
    t = text.strip()
    try:
        if t.endswith("%"):
            f = float(t[:-1]) / 100.0
            if not 0 < f <= 1:
                raise ValueError
            return ("fraction", f)
        n = int(t)
        if n < 1:
            raise ValueError
        return ("count", n)
    except ValueError:
        raise StudyError(f"--budget takes a percentage in (0, 100] such as 10% or a Gaussian count such as "
                         f"5000, got {text!r}.") from None


def parse_budgets(text) -> list[str | None]:
    """The budgets of ``--budgets 100%,10%,1%`` (a comma-separated string, a list, or None), each
    checked by :func:`parse_budget`, in order: None stands for the unbudgeted run (``100%``)."""
    if text is None:
        return [None]
    items = [x.strip() for x in (text.split(",") if isinstance(text, str) else text) if x is not None]
    out: list[str | None] = []
    for t in items or [""]:
        b = None if parse_budget(t) is None else t
        if b in out:
            raise StudyError(f"--budgets lists a budget twice: {text!r}.")
        out.append(b)
    return out


def join_budgets(budgets) -> str | None:
    """The inverse of :func:`parse_budgets` (None: the unbudgeted run alone)."""
    budgets = list(budgets)
    return None if budgets == [None] else ",".join(b or "100%" for b in budgets)


def label(method: str, budget: str | None) -> str:
    """The results key of a method: ``patexgs`` or, under a budget, ``patexgs(10%)``."""
    return method if parse_budget(budget) is None else f"{method}({budget.strip()})"


def split_label(key: str) -> tuple[str, str | None]:
    """``("patexgs", "10%")`` from ``patexgs(10%)``; ``("patexgs", None)`` from ``patexgs``."""
    base, paren, rest = key.partition("(")
    return (base, rest[:-1]) if paren and rest.endswith(")") else (key, None)


def _fmt(v, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _mean_over_scenes(results: dict, key: str, field) -> float | None:
    vals = []
    for per in results.values():
        if key in per:
            v = field(per[key])
            if v is None:
                return None
            vals.append(v)
    return float(np.mean(vals)) if vals else None


def _labels(results: dict) -> list[str]:
    seen = []
    for per in results.values():
        for k in per:
            if k not in seen:
                seen.append(k)
    return seen


def _row_name(key: str, names: dict) -> str:
    base, _, rest = key.partition("(")
    return names.get(base, base) + (f"({rest}" if rest else "")


def _lpips_note(record: dict | None) -> str:
    """The line saying which LPIPS the tables' LPIPS columns are."""
    if not record:
        return "LPIPS: not computed (no weights installed, or --no-lpips)."
    return (f"LPIPS: v{record.get('version', '0.1')}, {record.get('trunk', record.get('net'))} trunk "
            f"(`{record.get('net')}`, weights {record.get('weights')}).")


_TABLE3 = {"patexgs": "Full", "patexgs-no-mip": "w/o mip.", "patexgs-no-alpha-mip": "w/o alpha mip.",
           "patexgs-no-rgb-mip": "w/o RGB mip."}


_TABLE4 = {"patexgs": "Full (adaptive)", "patexgs-no-adaptive": "8 x 8 + mip (no adaptive)",
           MATCHED: "similar storage",
           **{f"patexgs-fixed-{n}": f"{n} x {n} + mip" for n in range(1, 33)},
           **{f"textured-fixed-{n}": f"{n} x {n} (Textured Gaussians: no mip, low-pass)" for n in (1, 2, 4, 8, 16, 32)}}


#: Zoom-out scales of the Table 4 layout (the paper's full resolution, and two zoomed-out ones).
TABLE4_SCALES = (1, 4, 8)


def tables_markdown(data: dict) -> str:
    """The study's tables in Markdown: the layouts of the paper's Tables 1 and 2, Tables 3 and 4 when at
    least two of their rows were run (else a line naming the methods that make them), a cost table.

    Values are means over the scenes that have the entry (Table 1 also lists each scene).
    """
    results = data.get("results", {})
    labels = _labels(results)
    scenes = list(results)
    cfg = data.get("config", {})
    out = [f"# Results: preset {cfg.get('preset')}, budget {cfg.get('budget') or '100%'}, "
           f"{len(scenes)} scene(s): {', '.join(scenes) or '-'}", "", _lpips_note(data.get("lpips")), ""]
    if not labels:
        return "\n".join(out + ["(no results yet)", ""])

    def metric(key, scale, name):
        return _mean_over_scenes(results, key, lambda e: e.get(str(scale), {}).get(name))

    # Table 1: quality at full resolution, per scene and mean.
    cols = scenes + (["mean"] if len(scenes) > 1 else [])
    out += ["## Table 1: quality at full resolution", "",
            "| method | " + " | ".join(f"{c} PSNR | {c} SSIM | {c} LPIPS" for c in cols) + " |",
            "| --- |" + " ---: |" * (3 * len(cols))]
    for key in labels:
        cells = []
        for c in cols:
            if c == "mean":
                vals = [metric(key, 1, m) for m in ("psnr", "ssim", "lpips")]
            else:
                e = results[c].get(key, {}).get("1", {})
                vals = [e.get("psnr"), e.get("ssim"), e.get("lpips")]
            cells += [_fmt(vals[0], 2), _fmt(vals[1], 3), _fmt(vals[2], 3)]
        out.append(f"| {key} | " + " | ".join(cells) + " |")
    out.append("")

    def scale_table(title, rows, alias=False):
        """PSNR | SSIM | LPIPS against the ground truth at each scale; with ``alias``, the alias PSNR
        beside them at each zoomed-out scale."""
        head = [f"{'Full' if s == 1 else f'1/{s}'} PSNR | SSIM | LPIPS" + (" | alias PSNR" if alias and s != 1 else "")
                for s in SCALES]
        ncols = 3 * len(SCALES) + (len(SCALES) - 1 if alias else 0)
        lines = [title, "", "| method | " + " | ".join(head) + " |", "| --- |" + " ---: |" * ncols]
        for key, name in rows:
            cells = []
            for s in SCALES:
                cells += [_fmt(metric(key, s, "psnr"), 2), _fmt(metric(key, s, "ssim"), 3),
                          _fmt(metric(key, s, "lpips"), 3)]
                if alias and s != 1:
                    cells.append(_fmt(metric(key, s, "alias_psnr"), 2))
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        return lines + [""]

    out += scale_table("## Table 2: zoom-out (anti-aliasing)", [(k, k) for k in labels], alias=True)
    out += ["alias PSNR: the render at 1/s against the same model's full-resolution render box-downsampled "
            "by s (the renderer's zoom-out coherence, apart from the fit).", ""]
    t3 = [(k, _row_name(k, _TABLE3)) for k in labels if k.partition("(")[0] in _TABLE3]
    t4 = [(k, _row_name(k, _TABLE4)) for k in labels if k.partition("(")[0] in _TABLE4]
    absent = [f"Table {n} ({what}) needs two of its rows; run e.g. `--methods {how}`"
              for n, rows, what, how in ((3, t3, "mipmap ablation", ",".join(_TABLE3)),
                                         (4, t4, "adaptive texture allocation", "table4")) if len(rows) < 2]
    if absent:
        out += ["Not in this study: " + "; ".join(absent) + ".", ""]
    if len(t3) >= 2:
        out += scale_table("## Table 3: mipmap ablation", t3)
    if len(t4) >= 2:
        head = " | ".join(f"{'Full' if sc == 1 else f'1/{sc}'} PSNR | SSIM | LPIPS" for sc in TABLE4_SCALES)
        out += ["## Table 4: adaptive texture allocation", "",
                f"| method | sides | {head} | storage MB |", "| --- | --- |" + " ---: |" * (3 * len(TABLE4_SCALES) + 1)]
        for key, name in t4:
            methods = {per[key].get("method") for per in results.values() if key in per}
            cells = [_fmt(metric(key, sc, m), 2 if m == "psnr" else 3) for sc in TABLE4_SCALES
                     for m in ("psnr", "ssim", "lpips")]
            out.append(f"| {name} | {', '.join(sorted(m for m in methods if m)) or '-'} | " + " | ".join(cells) +
                       f" | {_fmt(_mean_over_scenes(results, key, lambda e: e['storage_mb']), 2)} |")
        out += ["", "Rows named `+ mip` and the adaptive row differ only in their texture sizes (same warm-up, "
                "mipmaps and prefiltered coverage); the Textured Gaussians rows render without mipmaps, with the "
                "2DGS low-pass.", ""]
    out += paper_tables(results, data.get("scenes"))
    out += zoom_in_table(results)
    out += budget_table(results)
    out += ["## Cost: what the accuracy costs", "",
            "| method | PSNR | Gaussians | texels | storage MB | steps | train s | render ms |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for key in labels:
        m = functools.partial(_mean_over_scenes, results, key)
        out.append(f"| {key} | {_fmt(metric(key, 1, 'psnr'), 2)} | {_fmt(m(lambda e: e['num_gaussians']), 0)} | "
                   f"{_fmt(m(lambda e: e['texels']), 0)} | {_fmt(m(lambda e: e['storage_mb']), 2)} | "
                   f"{_fmt(m(lambda e: e.get('steps')), 0)} | "
                   f"{_fmt(m(lambda e: e['train_seconds']), 0)} | {_fmt(m(lambda e: e['render_ms']), 1)} |")
    out += ["", "Every method trains the same number of steps: an untextured method (`2dgs`, `3dgs`, "
            "`mip-splatting`) continues its first stage for the texture stage's steps. `train s`: the training "
            "steps of both stages, with the compiles they wait for; not the evaluation (docs/results.md).", ""]
    return "\n".join(out)


def _budget_order(budget: str | None) -> tuple[int, float]:
    """Sorts budgets as the paper's Table 1: unbudgeted, then fractions from the largest, then counts."""
    spec = parse_budget(budget)
    if spec is None:
        return (0, 0.0)
    return (1, -spec[1]) if spec[0] == "fraction" else (2, -float(spec[1]))


def budget_table(results: dict) -> list[str]:
    """The budget rows of the paper's Table 1 (method x budget) as Markdown lines; none without a
    budgeted entry. Means over the scenes that have the entry; ``vs 2dgs`` is the PSNR gain at full
    size over the ``2dgs`` entry of the same budget (per scene, then the mean)."""
    labels = _labels(results)
    if not any(split_label(k)[1] is not None for k in labels):
        return []
    rows = sorted(labels, key=lambda k: _budget_order(split_label(k)[1]))  # stable: methods keep their order

    def mean(key, field):
        return _mean_over_scenes(results, key, field)

    def gain(key):
        method, budget = split_label(key)
        base = label("2dgs", budget)
        if method == "2dgs":
            return None
        diffs = []
        for per in results.values():
            if key in per and base in per:
                a, b = per[key].get("1", {}).get("psnr"), per[base].get("1", {}).get("psnr")
                if a is None or b is None:
                    return None
                diffs.append(a - b)
        return float(np.mean(diffs)) if diffs else None

    zoom = " | ".join(f"1/{s} PSNR | SSIM" for s in SCALES[1:])
    out = ["## Table 1 budget rows: Gaussian budgets", "",
           f"| method | budget | PSNR | vs 2dgs | SSIM | LPIPS | {zoom} | Gaussians | cap | storage MB | train s | "
           "render ms |", "| --- | --- |" + " ---: |" * (4 + 2 * (len(SCALES) - 1) + 5)]
    for key in rows:
        method, budget = split_label(key)
        g = gain(key)
        cells = [_fmt(mean(key, lambda e: e.get("1", {}).get("psnr")), 2), "-" if g is None else f"{g:+.2f}",
                 _fmt(mean(key, lambda e: e.get("1", {}).get("ssim")), 3),
                 _fmt(mean(key, lambda e: e.get("1", {}).get("lpips")), 3)]
        for sc in SCALES[1:]:
            cells += [_fmt(mean(key, lambda e, sc=sc: e.get(str(sc), {}).get("psnr")), 2),
                      _fmt(mean(key, lambda e, sc=sc: e.get(str(sc), {}).get("ssim")), 3)]
        cells += [_fmt(mean(key, lambda e: e.get("num_gaussians")), 0),
                  _fmt(mean(key, lambda e: e.get("max_gaussians")), 0),
                  _fmt(mean(key, lambda e: e.get("storage_mb")), 2),
                  _fmt(mean(key, lambda e: e.get("train_seconds")), 0),
                  _fmt(mean(key, lambda e: e.get("render_ms")), 1)]
        out.append(f"| {method} | {budget or '100%'} | " + " | ".join(cells) + " |")
    return out + ["", "A budget of p% caps every method at p% of the Gaussians the unbudgeted 2DGS run reached "
                  "(`cap`; the paper's Table 1); every method trains the same steps.", ""]


def _paper(v, digits: int) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def dataset_groups(results: dict, scenes: dict | None = None) -> dict[str | None, list[str]]:
    """``{dataset: [scene, ...]}`` of a study's scenes, by the dataset ``results.json``'s ``scenes``
    records for each (:mod:`patexgs_jax.data.benchmarks`), in the paper's order (Mip-NeRF 360,
    Tanks and Temples, Deep Blending), then None: scenes of none of them (and those of files
    written before the record existed)."""
    of = {name: (scenes or {}).get(name, {}).get("dataset") for name in results}
    groups = {d: [n for n in results if of[n] == d] for d in (*DATASETS, None)}
    return {d: names for d, names in groups.items() if names}


def paper_tables(results: dict, scenes: dict | None = None) -> list[str]:
    """Tables 1 and 2 with every row that ran, ours beside the paper's figure for the same method
    (:mod:`experiments.paper`; blank where the paper has no such row), the paper's rows first in its
    order. Table 1 has one column group per dataset of the study (:func:`dataset_groups`): our mean
    over its scenes beside the paper's mean for that dataset (scenes of none of the paper's datasets
    beside its Mip-NeRF 360 figures, for reference), then each row's cost (means over every scene).
    Table 2, the paper's zoom-out table, is Mip-NeRF 360's: ours over the study's Mip-NeRF 360 scenes
    when it has some, else over all its scenes."""
    labels = _labels(results)
    if not labels:
        return []
    groups = dataset_groups(results, scenes)

    def mean(key, field, names=None):
        return _mean_over_scenes({n: results[n] for n in (names or results)}, key, field)

    def at(scale, name):
        return lambda e: e.get(str(scale), {}).get(name)

    plain = list(groups) == [None]  # no scene of the paper's datasets: one group, as before they were told apart
    heads = []
    for d in groups:
        what = "" if plain else (DATASET_NAMES[d] if d else "other scenes") + " "
        heads.append(f"{what}PSNR | paper | SSIM | paper | LPIPS | paper")
    out = ["## Table 1 beside the paper", "",
           f"| method | paper row | {' | '.join(heads)} | Gaussians | storage MB | train s | render ms |",
           "| --- | --- |" + " ---: |" * (6 * len(groups) + 4)]
    for key in ordered(labels, TABLE1_METHODS):
        cells = []
        for d, names in groups.items():
            fig = PAPER_TABLE1_BY_DATASET.get(d or "mipnerf360", {}).get(key, (None, None, None))
            for i, (name, digits) in enumerate((("psnr", 2), ("ssim", 3), ("lpips", 3))):
                cells += [_fmt(mean(key, at(1, name), names), digits), _paper(fig[i], digits)]
        cells += [_fmt(mean(key, lambda e, f=f: e.get(f)), digits)
                  for f, digits in (("num_gaussians", 0), ("storage_mb", 2), ("train_seconds", 0), ("render_ms", 1))]
        out.append(f"| {key} | {paper_name(key) or ''} | " + " | ".join(cells) + " |")
    if plain:
        note = ["", "`paper`: the paper's Mip-NeRF 360 means (nine scenes, its resolutions, 30k + 30k steps; "
                "Tables 1 and 2 of the paper); ours: this study's scenes, preset and steps. Compare the order "
                "of the rows and the gaps between them, not the absolute values.", ""]
    else:
        said = [f"{DATASET_NAMES[d] if d else 'other scenes'}: {', '.join(names)}"
                + (f" ({len(names)} of its {len(PAPER_SCENES[d])})" if d else "") for d, names in groups.items()]
        note = ["", "Each column group: our mean over the study's scenes of that dataset (" + "; ".join(said)
                + ") beside the paper's mean for the dataset (its Table 1; its resolutions, 30k + 30k steps"
                + ("; other scenes beside its Mip-NeRF 360 figures, for reference" if None in groups else "")
                + "); cost columns: means over every scene. Compare the order of the rows and the gaps between "
                "them, not the absolute values.", ""]
    out += note
    t2_names = groups.get("mipnerf360") or list(results)
    head = " | ".join(f"{'Full' if s == 1 else f'1/{s}'} PSNR | paper | SSIM | paper" for s in SCALES)
    out += ["## Table 2 beside the paper (zoom-out)", "",
            f"| method | paper row | {head} | alias PSNR 1/8 |", "| --- | --- |" + " ---: |" * (4 * len(SCALES) + 1)]
    for key in ordered(labels, TABLE2_METHODS):
        fig = PAPER_TABLE2.get(key, {})
        cells = []
        for s in SCALES:
            p = fig.get(s, (None, None, None))
            cells += [_fmt(mean(key, at(s, "psnr"), t2_names), 2), _paper(p[0], 2),
                      _fmt(mean(key, at(s, "ssim"), t2_names), 3), _paper(p[1], 3)]
        cells.append(_fmt(mean(key, at(SCALES[-1], "alias_psnr"), t2_names), 2))
        out.append(f"| {key} | {paper_name(key) or ''} | " + " | ".join(cells) + " |")
    if plain:
        return out + note
    return out + ["", "`paper`: the paper's Table 2, Mip-NeRF 360 means; ours: "
                  + ("the study's Mip-NeRF 360 scenes" if "mipnerf360" in groups else "every scene of the study")
                  + ".", ""]


def zoom_in_table(results: dict) -> list[str]:
    """The zoom-in table (Mip-Splatting's protocol) of the entries evaluated with ``--zoom-in``: PSNR,
    SSIM and LPIPS at the training resolution and zoomed in x2, x4, x8; none without such entries."""
    labels = [k for k in _labels(results) if any("zoom_in" in per.get(k, {}) for per in results.values())]
    if not labels:
        return []
    zooms = []
    for per in results.values():
        for e in per.values():
            zooms += [z for z in e.get("zoom_in", {}) if z not in zooms]
    zooms.sort(key=int)
    head = " | ".join(f"{'train res.' if z == '1' else f'x{z}'} PSNR | SSIM | LPIPS" for z in ["1"] + zooms)
    out = ["## Zoom-in (Mip-Splatting's protocol)", "", f"| method | {head} |",
           "| --- |" + " ---: |" * (3 * (len(zooms) + 1))]
    for key in labels:
        cells = []
        for z in ["1"] + zooms:
            for name, digits in (("psnr", 2), ("ssim", 3), ("lpips", 3)):
                def field(e, z=z, n=name):
                    return (e if z == "1" else e.get("zoom_in") or {}).get(z, {}).get(n)

                cells.append(_fmt(_mean_over_scenes(results, key, field), digits))
        out.append(f"| {key} | " + " | ".join(cells) + " |")
    sources: dict[str, list[str]] = {}  # where each scene's finer images came from, and the zooms
    for scene, per in results.items():
        for e in per.values():
            for z, m in (e.get("zoom_in") or {}).items():
                at = sources.setdefault(str(m.get("source")), [])
                if f"{scene} x{z}" not in at:
                    at.append(f"{scene} x{z}")
    return out + ["", "Trained at the study's resolution, rendered at x times its pixel density (the camera "
                  "intrinsics of that resolution) against the finer images: "
                  + "; ".join(f"{', '.join(at)}: {src}" for src, at in sources.items()) + ".", ""]
