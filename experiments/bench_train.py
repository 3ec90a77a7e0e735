"""Training-step benchmark: ms per step in steady state, compile time, recompiles, data parallelism,
and the step's peak memory at real image sizes.

    python -m experiments.bench_train [--gaussians 1000 4000] [--sizes 128x96] [--steps 5]
                                      [--configs 2dgs,tex8,tex8-mip] [--devices N [--batch-size B]]
                                      [--compositor xla,pallas] [--json out.json]
    python -m experiments.bench_train --memory [--gaussians 4000] [--sizes 1152x864 2304x1728 4032x3024]
                                      [--configs 2dgs,tex8-mip-prefilter] [--steps 3] [--json out.json]

Each case trains a fixed random scene (seeded; ``--gaussians`` splats around the synthetic scene's
centre, SH degree 3) on the fixed views of the embedded synthetic scene
(:mod:`patexgs_jax.data.synthetic`: its cameras at ``--sizes``, its analytic ground truth), through
the real training loop (:class:`patexgs_jax.training.trainer.Trainer`: view order, the jitted step with donated
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
sharded step). ``--compositor xla,pallas`` runs every case with each compositor
(``RenderConfig.compositor``) in this process, a row each (the Pallas kernel is interpreted off
a GPU). Results go to ``--json`` (as
``experiments.bench_render``) and a Markdown table.

``--memory`` measures memory instead: each (size, Gaussian count, configuration) runs in a fresh
process, started through ``sh`` so that it does not inherit this process's resident-set high-water
mark (a child forked directly from Python starts with its parent's ``ru_maxrss``). The child builds
the views (the synthetic scene's ground truth rendered at 1/8 and enlarged: only the image's size
matters here), trains ``--steps`` + 1 steps and reports its peak resident memory
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``: setup, compilation and the steps), the peak within
the first step (which compiles) and within each later step (the high-water mark reset between
steps through /proc/self/clear_refs), its resident memory before the first step and the bytes of
one image.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
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


def make_views(width, height, seed=0, num_views=NUM_VIEWS, enlarge=1):
    """The synthetic scene's first ``num_views`` cameras at this size and their ground truth
    (rendered at 1/``enlarge`` and enlarged by pixel repetition when ``enlarge`` > 1, which needs
    sides divisible by it)."""
    import numpy as np

    from patexgs_jax.data.synthetic import make_cameras, render_ground_truth

    cams = make_cameras(seed, num_views=num_views, width=width, height=height)
    views = []
    for i, c in enumerate(cams):
        if enlarge > 1:
            small = np.asarray(render_ground_truth(c.scaled(enlarge), 1, seed), np.float32)
            image = np.repeat(np.repeat(small, enlarge, axis=0), enlarge, axis=1)
        else:
            image = np.asarray(render_ground_truth(c, 1, seed), np.float32)
        views.append(types.SimpleNamespace(camera=c, image=image, name=f"view{i}"))
    return views


def make_scene(n, tex, seed=0):
    from patexgs_jax import random_scene
    from patexgs_jax.data.synthetic import SCENE_CENTER

    sizes = None if tex is None else [tex] * n
    return random_scene(seed, n, sh_degree=3, extent=1.2, scale_range=(0.01, 0.08), center=tuple(SCENE_CENTER),
                        rgb_sizes=sizes, alpha_sizes=sizes)


def bench(name, n, views, steps, batch_size=1, devices=None, on_step=None, compositor="xla", scene=None):
    """Times ``steps + 1`` training steps rendering with ``compositor`` (``RenderConfig.compositor``);
    returns one result row. ``on_step()`` is called after each step, once its results are ready.
    ``scene``: the scene to train (default: :func:`make_scene` of ``n`` and the configuration's
    texture side)."""

    import jax
    import numpy as np

    from patexgs_jax import RenderConfig
    from patexgs_jax.densify import DensifyConfig, DensifyStats
    from patexgs_jax.training import TrainConfig
    from patexgs_jax.training.step import STEP_TRACES
    from patexgs_jax.training.strategies import TileRefit
    from patexgs_jax.training.trainer import Trainer

    tex, mip, coverage = CONFIGS[name]
    off = DensifyConfig(start=10**9, stop=10**9 + 1, opacity_reset_interval=10**9)
    cfg = TrainConfig(method="2dgs", iters_2dgs=steps + 1, sh_interval=1, normal_from=0, densify=off,
                        log_every=10**9, checkpoint_every=10**9, batch_size=batch_size, devices=devices)
    ds = types.SimpleNamespace(train_views=views, test_views=[], points=None, colors=None,
                               normalization=types.SimpleNamespace(radius=2.0))
    stamps = []
    traces = {}

    class Run(Trainer):
        def before_step(self, step):
            traces.setdefault(step, sum(STEP_TRACES.values()))  # (the traces before the step at ``step``)
            super().before_step(step)

        def after_step(self, step):
            super().after_step(step)
            jax.block_until_ready(self.scene.means)
            stamps.append(time.perf_counter())
            if on_step is not None:
                on_step()

    run = Run(ds, cfg, None, verbose=False)
    run.render_cfgs = (RenderConfig(mip=mip, coverage=coverage, compositor=compositor),) * 2
    for strategy in run.strategies:  # (the tile refits count pairs as the steps render)
        if isinstance(strategy, TileRefit):
            strategy.render_cfgs = run.render_cfgs
    run.scene = make_scene(n, tex) if scene is None else scene
    run.opt_state = run.optimizer.init(run.scene)
    run.stats = DensifyStats.zeros(run.scene.capacity)
    for v in views:  # one capacity that fits every view: no overflow retry inside the timed steps
        run.tiles.fit(run.scene, v.camera, run.render_cfg, batch=batch_size > 1)
    t0 = time.perf_counter()
    run.run()
    first = stamps[0] - t0
    steady = np.diff(np.asarray(stamps))
    ms = 1e3 * float(np.median(steady)) if len(steady) else float("nan")  # steps=0: the first step only
    recompiles = sum(STEP_TRACES.values()) - traces[1] if 1 in traces else 0
    n_dev = 1 if batch_size == 1 else len(run.data_mesh().devices.flat)
    return dict(config=name, compositor=compositor, gaussians=n, width=views[0].camera.width,
                height=views[0].camera.height,
                batch_size=batch_size, devices=n_dev, ms_per_step=ms, ms_per_view=ms / batch_size,
                compile_s=first - ms / 1e3, first_step_s=first, steps=len(steady),
                recompiles_steady=recompiles, skipped=run.skipped, capacity=run.tiles.current.pairs)


MEMORY_SIZES = [(1152, 864), (2304, 1728), (4032, 3024)]
MEMORY_VIEWS = 2


def _rss_bytes() -> int:
    """This process's resident memory now (bytes), from /proc/self/statm."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _high_water_bytes(reset: bool = False) -> int:
    """This process's resident-memory high-water mark (VmHWM, bytes); ``reset`` then lowers it to
    the current resident memory (Linux's /proc/self/clear_refs), so the next reading is the peak
    since now."""
    with open("/proc/self/status") as f:
        hwm = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) * 1024
    if reset:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    return hwm


def memory_case(name, n, width, height, steps):
    """Runs in its own process: trains ``steps + 1`` steps at ``width x height`` and returns the
    process's peak resident memory (``ru_maxrss``), the peak within each step (the first one
    compiles) and the case's figures."""
    import resource

    def maxrss():
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux

    views = make_views(width, height, num_views=MEMORY_VIEWS, enlarge=8)
    rss_setup = _rss_bytes()
    # A reset of the high-water mark lowers ru_maxrss too: the process's peak is the largest
    # reading taken just before each reset.
    peaks = [maxrss()]
    _high_water_bytes(reset=True)
    per_step = []

    def on_step():
        peaks.append(maxrss())
        per_step.append(_high_water_bytes(reset=True))

    row = bench(name, n, views, steps, on_step=on_step)
    peak = max(peaks + [maxrss()])
    row.update(megapixels=width * height / 1e6, views=len(views), peak_rss_mib=peak / 2**20,
               rss_before_steps_mib=rss_setup / 2**20, image_mib=views[0].image.nbytes / 2**20,
               first_step_peak_mib=per_step[0] / 2**20, step_peak_mib=max(per_step[1:]) / 2**20 if steps else None,
               step_peaks_mib=[b / 2**20 for b in per_step])
    return row


def run_memory_case(name, n, width, height, steps) -> dict:
    """:func:`memory_case` in a fresh process (through ``sh``: see the module docstring)."""
    cmd = [sys.executable, "-m", "experiments.bench_train", "--memory-case",
           json.dumps(dict(name=name, n=n, width=width, height=height, steps=steps))]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    # `; exit $?` keeps sh from exec-ing the command in its own process (which keeps the high-water mark).
    proc = subprocess.run(["sh", "-c", shlex.join(cmd) + "; exit $?"], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        return dict(config=name, gaussians=n, width=width, height=height, megapixels=width * height / 1e6,
                    error=f"exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:] or ''}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main_memory(args, names):
    sizes = args.sizes if args.sizes_given else MEMORY_SIZES
    gaussians = args.gaussians if args.gaussians_given else [4_000]
    rows = []
    for w, h in sizes:
        for n in gaussians:
            for name in names:
                r = run_memory_case(name, n, w, h, args.steps)
                rows.append(r)
                if "error" in r:
                    print(f"{name:18s} N={n:6d} {w}x{h}: failed ({r['error']})", flush=True)
                    continue
                print(f"{name:18s} N={n:6d} {w}x{h} ({r['megapixels']:.1f} MP): peak RSS {r['peak_rss_mib']:7.0f} MiB "
                      f"(first step {r['first_step_peak_mib']:6.0f}, "
                      f"later steps {r['step_peak_mib'] or 0:6.0f}, before "
                      f"the steps {r['rss_before_steps_mib']:6.0f}, one image {r['image_mib']:5.0f}), "
                      f"{r['ms_per_step']:8.0f} ms/step", flush=True)
    print()
    print("| config | Gaussians | size | MP | peak RSS MiB | first step MiB | later steps MiB | before steps MiB "
          "| image MiB | ms/step |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        if "error" in r:
            print(f"| {r['config']} | {r['gaussians']} | {r['width']}x{r['height']} | {r['megapixels']:.1f} | "
                  f"failed | | | | | |")
            continue
        print(f"| {r['config']} | {r['gaussians']} | {r['width']}x{r['height']} | {r['megapixels']:.1f} | "
              f"{r['peak_rss_mib']:.0f} | {r['first_step_peak_mib']:.0f} | {r['step_peak_mib'] or 0:.0f} | "
              f"{r['rss_before_steps_mib']:.0f} | {r['image_mib']:.0f} | {r['ms_per_step']:.0f} |")
    if args.json:
        write_benchmark_json(args.json, rows, SCHEMA, steps=args.steps, mode="memory", views=MEMORY_VIEWS)
    return 1 if any("error" in r for r in rows) else 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[1_000, 4_000],
                    help="scene sizes to time (default 1000 4000)")
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[(128, 96)],
                    help="image sizes WxH (default 128x96)")
    ap.add_argument("--steps", type=int, default=5, help="timed steps after the first (compiling) one")
    ap.add_argument("--configs", default=",".join(CONFIGS),
                    help=f"comma-separated, from {', '.join(CONFIGS)} (default all)")
    ap.add_argument("--devices", type=int, default=None,
                    help="also time the data-parallel step over this many devices (CPU devices are forced)")
    ap.add_argument("--batch-size", type=int, default=None, help="views per data-parallel step (default --devices)")
    ap.add_argument("--json", default=None, help="also write the figures here (with the commit and machine)")
    ap.add_argument("--compositor", default="xla",
                    help="comma-separated compositors to time side by side in this process: xla, pallas "
                         "(RenderConfig.compositor; pallas is interpreted off a GPU)")
    ap.add_argument("--memory", action="store_true",
                    help="measure each case's peak resident memory in a fresh process instead (default sizes "
                         "1152x864, 2304x1728, 4032x3024; 4000 Gaussians)")
    ap.add_argument("--memory-case", default=None, help=argparse.SUPPRESS)
    raw = sys.argv[1:] if argv is None else list(argv)
    args = ap.parse_args(raw)
    args.sizes_given = "--sizes" in raw
    args.gaussians_given = "--gaussians" in raw
    if args.memory_case is not None:
        c = json.loads(args.memory_case)
        print(json.dumps(memory_case(c["name"], c["n"], c["width"], c["height"], c["steps"])))
        return 0
    names = args.configs.split(",")
    unknown = [c for c in names if c not in CONFIGS]
    if unknown:
        ap.error(f"unknown configs {unknown}; choose from {', '.join(CONFIGS)}")
    compositors = args.compositor.split(",")
    if any(c not in ("xla", "pallas") for c in compositors):
        ap.error(f"--compositor takes xla and/or pallas, got {args.compositor!r}")
    if args.memory:
        return main_memory(args, names)
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
            for comp, name in ((c, m) for c in compositors for m in names):
                cases = [(1, None)] + ([(batch, args.devices)] if args.devices else [])
                label = name + ("" if comp == "xla" else f"@{comp}")
                for b, d in cases:
                    r = bench(name, n, views, args.steps, b, d, compositor=comp)
                    rows.append(r)
                    print(f"{label:9s} N={n:6d} {w}x{h} batch {b} on {r['devices']} device(s): "
                          f"{r['ms_per_step']:8.1f} ms/step, {r['ms_per_view']:8.1f} ms/view, "
                          f"compile {r['compile_s']:5.1f} s, steady recompiles {r['recompiles_steady']}",
                          flush=True)
                    if args.json:  # after every case: a run cut short keeps what it measured
                        write_benchmark_json(args.json, rows, SCHEMA, steps=args.steps)
    print()
    print("| config | compositor | Gaussians | size | batch | devices | ms/step | ms/view | compile s | recompiles |")
    print("|---|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['config']} | {r['compositor']} | {r['gaussians']} | {r['width']}x{r['height']} | "
              f"{r['batch_size']} | "
              f"{r['devices']} | {r['ms_per_step']:.1f} | {r['ms_per_view']:.1f} | {r['compile_s']:.1f} | "
              f"{r['recompiles_steady']} |")
    if args.json:
        write_benchmark_json(args.json, rows, SCHEMA, steps=args.steps)
    bad = [r for r in rows if r["recompiles_steady"]]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
