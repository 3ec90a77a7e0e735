"""Training-step benchmark: ms per step in steady state, compile time, recompiles, data parallelism.

    python -m experiments.bench_train [--gaussians 1000 4000] [--sizes 128x96] [--steps 5]
                                      [--configs 2dgs,tex8,tex8-mip] [--devices N [--batch-size B]]
                                      [--json out.json]

Each case trains a fixed random scene (seeded; ``--gaussians`` splats around the synthetic scene's
centre, SH degree 3) on the fixed views of the embedded synthetic scene
(:mod:`patexgs_jax.data.synthetic`: its cameras at ``--sizes``, its analytic ground truth), through
the real training loop (``patexgs_jax.train``'s run: view order, the jitted step with donated
state, the host-side checks) with densification off so shapes stay fixed. Configurations:
``2dgs`` (no textures), ``tex8`` (every Gaussian an 8x8 RGBA texture, no mipmaps: Textured
Gaussians), ``tex8-mip`` (8x8 RGBA with per-pixel mipmaps, Eq. 11, and the 2DGS low-pass: the
literal reading of PATexGS) and ``tex8-mip-prefilter`` (the same with the prefiltered coverage:
the ``patexgs`` methods' renderer).

For each case it prints: the median ms per step over ``--steps`` steps after the first (steady
state; wall time between steps, host work included) and per view; the compile time (first step
minus a steady one); and the recompiles in those steady steps (traces of the step function:
must be 0). With ``--devices N`` every case also runs the data-parallel step on batches of
``--batch-size`` views (default N) split over N devices (CPU devices are forced to N; on a CPU
they share the same cores, so expect no speed-up there: the figure is the overhead of the
sharded step). Results go to ``--json`` (as ``experiments.bench_render``) and a Markdown table.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import types

from experiments.bench_render import parse_size
from experiments.provenance import write_benchmark_json

#: The layout of the --json file (experiments.provenance's header plus steps, results).
SCHEMA = 1

CONFIGS = {  # name: (texture side or None, mip mode, coverage mode)
    "2dgs": (None, "none", "lowpass"),
    "tex8": (8, "none", "lowpass"),
    "tex8-mip": (8, "nearest", "lowpass"),
    "tex8-mip-prefilter": (8, "nearest", "prefilter"),
}
NUM_VIEWS = 8


def make_views(width, height, seed=0):
    """The synthetic scene's first ``NUM_VIEWS`` cameras at this size and their ground truth."""
    import numpy as np

    from patexgs_jax.data.synthetic import make_cameras, render_ground_truth

    cams = make_cameras(seed, num_views=NUM_VIEWS, width=width, height=height)
    return [types.SimpleNamespace(camera=c, image=np.asarray(render_ground_truth(c, 1, seed), np.float32),
                                  name=f"view{i}") for i, c in enumerate(cams)]


def make_scene(n, tex, seed=0):
    from patexgs_jax import random_scene
    from patexgs_jax.data.synthetic import SCENE_CENTER

    sizes = None if tex is None else [tex] * n
    return random_scene(seed, n, sh_degree=3, extent=1.2, scale_range=(0.01, 0.08), center=tuple(SCENE_CENTER),
                        rgb_sizes=sizes, alpha_sizes=sizes)


def bench(name, n, views, steps, batch_size=1, devices=None):
    """Times ``steps + 1`` training steps; returns one result row."""
    import importlib

    import jax
    import numpy as np

    from patexgs_jax import RenderConfig
    from patexgs_jax.densify import DensifyConfig, DensifyStats

    T = importlib.import_module("patexgs_jax.train")  # the module (the package's `train` is the function)
    tex, mip, coverage = CONFIGS[name]
    off = DensifyConfig(start=10**9, stop=10**9 + 1, opacity_reset_interval=10**9)
    cfg = T.TrainConfig(method="2dgs", iters_2dgs=steps + 1, sh_interval=1, normal_from=0, densify=off,
                        log_every=10**9, checkpoint_every=10**9, batch_size=batch_size, devices=devices)
    ds = types.SimpleNamespace(train_views=views, test_views=[], points=None, colors=None,
                               normalization=types.SimpleNamespace(radius=2.0))
    stamps = []

    class Run(T._Run):
        def after_step(self, step):
            super().after_step(step)
            jax.block_until_ready(self.scene.means)
            stamps.append(time.perf_counter())

    run = Run(ds, cfg, None, verbose=False)
    run.render_cfgs = (RenderConfig(mip=mip, coverage=coverage),) * 2
    run.scene = make_scene(n, tex)
    run.opt_state = run.optimizer.init(run.scene)
    run.stats = DensifyStats.zeros(run.scene.capacity)
    for v in views:  # one capacity that fits every view: no overflow retry inside the timed steps
        run.fit_capacity(v.camera)
    traces = {}
    orig = run.step_fn

    def step_fn():
        traces.setdefault(run.step, sum(T.STEP_TRACES.values()))
        return orig()

    run.step_fn = step_fn
    t0 = time.perf_counter()
    run.run()
    first = stamps[0] - t0
    steady = np.diff(np.asarray(stamps))
    ms = 1e3 * float(np.median(steady))
    recompiles = sum(T.STEP_TRACES.values()) - traces[1] if 1 in traces else 0
    n_dev = 1 if batch_size == 1 else len(run.data_mesh().devices.flat)
    return dict(config=name, gaussians=n, width=views[0].camera.width, height=views[0].camera.height,
                batch_size=batch_size, devices=n_dev, ms_per_step=ms, ms_per_view=ms / batch_size,
                compile_s=first - ms / 1e3, first_step_s=first, steps=len(steady),
                recompiles_steady=recompiles, skipped=run.skipped, capacity=run.capacity.pairs)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[1_000, 4_000])
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[(128, 96)],
                    help="image sizes WxH (default 128x96)")
    ap.add_argument("--steps", type=int, default=5, help="timed steps after the first (compiling) one")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--devices", type=int, default=None,
                    help="also time the data-parallel step over this many devices (CPU devices are forced)")
    ap.add_argument("--batch-size", type=int, default=None, help="views per data-parallel step (default --devices)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    names = args.configs.split(",")
    unknown = [c for c in names if c not in CONFIGS]
    if unknown:
        ap.error(f"unknown configs {unknown}; choose from {', '.join(CONFIGS)}")
    if args.devices is not None:
        from patexgs_jax.parallel import request_cpu_devices

        request_cpu_devices(args.devices)  # before JAX starts
    import jax

    batch = args.batch_size or args.devices
    print(f"jax {jax.__version__} on {platform.processor() or platform.machine()}, "
          f"{jax.device_count()} {jax.devices()[0].platform} device(s)", flush=True)
    rows = []
    for w, h in args.sizes:
        views = make_views(w, h)
        for n in args.gaussians:
            for name in names:
                cases = [(1, None)] + ([(batch, args.devices)] if args.devices else [])
                for b, d in cases:
                    r = bench(name, n, views, args.steps, b, d)
                    rows.append(r)
                    print(f"{name:9s} N={n:6d} {w}x{h} batch {b} on {r['devices']} device(s): "
                          f"{r['ms_per_step']:8.1f} ms/step, {r['ms_per_view']:8.1f} ms/view, "
                          f"compile {r['compile_s']:5.1f} s, steady recompiles {r['recompiles_steady']}",
                          flush=True)
    print()
    print("| config | Gaussians | size | batch | devices | ms/step | ms/view | compile s | recompiles |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['config']} | {r['gaussians']} | {r['width']}x{r['height']} | {r['batch_size']} | "
              f"{r['devices']} | {r['ms_per_step']:.1f} | {r['ms_per_view']:.1f} | {r['compile_s']:.1f} | "
              f"{r['recompiles_steady']} |")
    if args.json:
        write_benchmark_json(args.json, rows, SCHEMA, steps=args.steps)
    bad = [r for r in rows if r["recompiles_steady"]]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
