"""What the "one" training padding costs a step: the single-view 2DGS step at each padding policy
(``TrainConfig.padding``), timed in one process, interleaved view by view.

    python -m experiments.bench_padding --data BEER [--factor 4] [--views 12] [--repeats 3]
                                        [--variants per-size,one,one@1.25] [--json F]

Runs of one configuration start from the same initial scene; each pads as its variant says
("per-size": every view at its own tile grid; "one": every view at the largest grid of all the
training views, its tile capacity with 2x headroom; "one@1.25": the same with the per-size
headroom, to tell the padding's cost from the capacity's). Each run fits its capacity over every
training view; the timed views (the first ``--views``) are taken in the same order by every run,
one after the other for each view, after every padded size has compiled (so only steps that
compile nothing are timed). Reported: the training views' pixel shares
(:func:`patexgs_jax.padding.extra_pixel_share`) and the timed views' padded sizes, each variant's
median ms a step, its tile capacity, and each over the first variant.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from experiments.provenance import write_benchmark_json

SCHEMA = 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--factor", type=int, default=4)
    ap.add_argument("--views", type=int, default=12, help="training views timed (default 12)")
    ap.add_argument("--repeats", type=int, default=3, help="passes over the views (default 3)")
    ap.add_argument("--variants", default="per-size,one", help="comma-separated: per-size, one, one@1.25")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    if not variants or any(v not in ("per-size", "one", "one@1.25") for v in variants):
        ap.error(f"--variants takes per-size, one and one@1.25, got {args.variants!r}")

    import jax
    import jax.numpy as jnp

    from patexgs_jax import data, padding
    from patexgs_jax.training import preset_config
    from patexgs_jax.training.trainer import Trainer

    ds = data.load(args.data, factor=args.factor, verbose=False)
    runs = {}
    for variant in variants:
        policy = variant.split("@")[0]
        run = Trainer(ds, preset_config("tiny", method="2dgs", padding=policy), None, verbose=False)
        if "@" in variant:
            run.pad.headroom = float(variant.split("@")[1])
        run.fresh()
        for v in run.train_views:
            run.tiles.fit(run.scene, v.camera, run.render_cfg, batch=False)
        runs[variant] = run
    views = ds.train_views[: args.views]
    sh, wn = jnp.int32(0), jnp.float32(0.0)

    def step(run, v):
        t = time.perf_counter()
        run.scene, run.opt_state, run.stats, m = run.step_fn()(run.scene, run.opt_state, run.stats, v.camera,
                                                               v.image, sh, wn)
        jax.block_until_ready(m["loss"])
        return time.perf_counter() - t

    for v in views:  # (compiles every padded size first)
        for run in runs.values():
            step(run, v)
    times: dict[str, list] = {p: [] for p in variants}
    for _ in range(args.repeats):
        for v in views:
            for p in variants:
                times[p].append(step(runs[p], v))
    share = padding.extra_pixel_share([v.camera for v in ds.train_views])
    timed = sorted({padding.padded_shape(v.camera.height, v.camera.width) for v in views})
    rows = []
    for p in variants:
        ms = 1e3 * statistics.median(times[p])
        rows.append(dict(variant=p, ms_per_step=round(ms, 2), capacity=runs[p].capacity.pairs,
                         headroom=runs[p].pad.headroom, factor=args.factor, views=len(views), steps=len(times[p]),
                         over_first=round(ms / (1e3 * statistics.median(times[variants[0]])), 4)))
        print(f"{p:9s} {ms:8.1f} ms/step  capacity {runs[p].capacity.pairs}  x{rows[-1]['over_first']:.3f}",
              flush=True)
    print(f"training views' pixels: {share}; timed views' padded sizes (per-size): {timed}", flush=True)
    if args.json:
        write_benchmark_json(args.json, rows, SCHEMA, pixels=share, timed_padded_sizes=timed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
