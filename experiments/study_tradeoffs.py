"""A ``python -m experiments.mipnerf360`` study seen as accuracy against time: every entry (each
method at each budget, means over the study's scenes) a labelled point of
:func:`experiments.tradeoffs.plot` and a row of :func:`experiments.tradeoffs.markdown`, whatever
methods the study ran (3D Gaussians and BBSplat variants included).

    python -m experiments.tradeoffs --from-study runs/mipnerf360/results.json [--out DIR]
"""

from __future__ import annotations

import functools
from pathlib import Path

from experiments.study_tables import SCALES, _labels, _mean_over_scenes, split_label


def study_as_tradeoffs(data: dict, source: str = "study") -> dict:
    """A study's ``results.json`` data as a tradeoffs record (the fields ``markdown`` and ``plot``
    read): one run per entry, keyed by its label; the unbudgeted entries under the knob
    ``methods``, each budget's under ``budget <b>``. A study records its render time at full size
    only, so the render-time panels of the zoomed-out scales are empty."""
    from experiments.tradeoffs import pareto_sets

    results = data.get("results", {})
    runs, knobs = {}, {}
    for key in _labels(results):
        method, budget = split_label(key)
        mean = functools.partial(_mean_over_scenes, results, key)

        def per_scale(name, mean=mean):
            return {str(s): mean(lambda e, s=s: e.get(str(s), {}).get(name)) for s in SCALES}

        gaussians = mean(lambda e: e.get("num_gaussians"))
        methods = {per[key].get("method") for per in results.values() if key in per} - {None}
        runs[key] = dict(run=key, method=", ".join(sorted(methods)) or method,
                         train_seconds=mean(lambda e: e.get("train_seconds")),
                         render_ms={"1": mean(lambda e: e.get("render_ms"))}, psnr=per_scale("psnr"),
                         ssim=per_scale("ssim"), alias_psnr=per_scale("alias_psnr"),
                         num_gaussians=None if gaussians is None else int(round(gaussians)),
                         storage_mb=mean(lambda e: e.get("storage_mb")), steps=mean(lambda e: e.get("steps")))
        knobs.setdefault("methods" if budget is None else f"budget {budget}", []).append(
            dict(label=key, value=method, run=key))
    version, cfg = data.get("version") or {}, data.get("config") or {}
    scenes = ", ".join(results) or "-"
    record = dict(data=f"{source} ({scenes})", preset=cfg.get("preset"), scales=list(SCALES), runs=runs,
                  knobs=knobs, machine=cfg.get("machine"), jax=version.get("jax"), git=version.get("git"),
                  date="-")
    record["pareto"] = pareto_sets(runs, SCALES)
    return record


def write_from_study(results_path, out_dir=None) -> tuple[Path, Path]:
    """Writes ``tradeoffs.md`` and ``tradeoffs.png`` of a study's ``results.json`` (or its folder)
    into ``out_dir`` (default: the study's ``plots/``); returns their paths."""
    from experiments.headline import HeadlineError, read
    from experiments.tradeoffs import markdown, plot

    path = Path(results_path)
    if path.is_dir():
        path = path / "results.json"
    try:
        data = read(path)
    except HeadlineError as e:
        raise ValueError(f"cannot read --from-study {path} ({e}): pass a results.json that "
                         "python -m experiments.mipnerf360 wrote.") from None
    record = study_as_tradeoffs(data, source=str(path.parent))
    out = Path(out_dir) if out_dir is not None else path.parent / "plots"
    out.mkdir(parents=True, exist_ok=True)
    md = out / "tradeoffs.md"
    md.write_text(markdown(record))
    return md, plot(record, out / "tradeoffs.png")
