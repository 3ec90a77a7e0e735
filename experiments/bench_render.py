"""Renderer benchmark: forward and forward+backward time, throughput, memory, compile time.

    python -m experiments.bench_render [--gaussians 50000 ...] [--sizes 640x480 ...] [--repeats 3]
                                       [--configs 2dgs,tex8,tex8-mip,tex8-trilinear] [--json out.json]
                                       (3D Gaussians: --configs 2dgs,3dgs,mip-splatting)
                                       [--compositor xla,pallas]

A fixed random scene (seeded) seen by a fixed camera, for every Gaussian count and image size
given. For each configuration it prints: forward ms; its ratio to the 2DGS forward (``x2DGS``,
when 2dgs is among the configurations; configurations are timed round-robin); forward+backward ms
(gradient of a photometric-style loss w.r.t. the whole scene); the projection + binning + sort
time on its own (``bin ms``, inside the forward); (pixel, splat) pairs listed per second in the
forward pass
(binned (splat, tile) pairs x pixels per tile: the work a renderer without early termination would
do; ours stops saturated tiles early); binned (splat, tile) pairs; the longest tile list; compile
time; recompiles during the timed calls (must be 0); XLA's temporary-buffer size of the backward
(its peak working memory beyond inputs/outputs); and the share of the machine's arithmetic peak
the forward reaches, ``pairs/s x FLOPs per pair / peak``.

``--compositor xla,pallas`` times every configuration with each compositor
(``RenderConfig.compositor``: the XLA compositor, the Pallas kernel), side by side in one process
and round-robin; each row names its compositor, and ``x2DGS`` is against the 2DGS row of the same
compositor. Off a GPU the Pallas kernel runs in Pallas's interpreter (a test path: its CPU times
measure the interpreter, not the kernel).

FLOPs per (pixel, splat) pair, counted by hand from ``patexgs_jax.rendering`` (adds, multiplies,
divisions, comparisons feeding arithmetic, exp/log/sqrt each 1; selects and integer address
arithmetic not counted): the homogeneous intersection (3 plane equations 12, the division and its
parallel-ray test 6), rho3d 3, the low-pass rho2d 6 (the prefilter's quadratic form replaces both: 7),
G 3, depth 4, alpha 3, transmittance and
weight 8, colour 6, depth/normal/distortion accumulators 16, the transmittance sum 1: about 70 for
2DGS. An RGB + alpha bilinear lookup adds 2 x 21 (coordinates, clamping, fractions) + 4 x 9 (per
channel) + 7 (applying them): about 85 (RGB alone 54, alpha alone 31: configurations
``tex8-rgb`` and ``tex8-alpha`` report each bank's cost on its own). Mip selection adds the two
footprint rays and Eq. 11: about 60. Trilinear reads a second level in both banks and blends them:
about 90 more. These are what a renderer evaluating every pair would spend; ours spends the texture
part only on the pairs that can reach alpha 1/255 (a few percent of them here), except in
``tex8-mip-dense``, so for the other textured configurations the share of the peak is of that
dense-equivalent work, not of the arithmetic done. The peak is measured (``--peak``): the float32
throughput of a large ``jnp.dot`` on all cores, the best this machine's XLA does on dense arithmetic.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.provenance import write_benchmark_json
from patexgs_jax import Camera, Capacity, RenderConfig, look_at, random_scene
from patexgs_jax.render import TRACE_COUNTS, count_pairs, render_jit
from patexgs_jax.rendering import binning, gaussian3d, projection, tiling

#: The layout of the --json file (experiments.provenance's header plus peak_gflops, timing, results).
SCHEMA = 1


#: name -> (texture side or None, banks textured, render configuration). ``tex8-rgb`` and
#: ``tex8-alpha`` texture one bank only, so each effect's cost is reported on its own;
#: ``tex8-mip-dense`` looks textures up for every (pixel, splat) pair (``texture_pairs=1``), the
#: renderer before lookups were limited to the pairs that can contribute; ``tex8-mip-prefilter-dense``
#: does so with the ``patexgs`` renderer (on a GPU, gathering the contributing pairs may cost more
#: than looking every pair up).
CONFIGS = {
    "2dgs": (None, (), RenderConfig(mip="none")),
    "tex8-rgb": (8, ("rgb",), RenderConfig(mip="none")),
    "tex8-alpha": (8, ("alpha",), RenderConfig(mip="none")),
    "tex8": (8, ("rgb", "alpha"), RenderConfig(mip="none")),
    "tex8-mip": (8, ("rgb", "alpha"), RenderConfig(mip="nearest")),
    "tex8-trilinear": (8, ("rgb", "alpha"), RenderConfig(mip="trilinear")),
    "tex8-mip-dense": (8, ("rgb", "alpha"), RenderConfig(mip="nearest", texture_pairs=1.0)),
    "2dgs-prefilter": (None, (), RenderConfig(mip="none", coverage="prefilter")),
    "tex8-mip-prefilter": (8, ("rgb", "alpha"), RenderConfig(mip="nearest", coverage="prefilter")),
    "tex8-mip-prefilter-dense": (8, ("rgb", "alpha"), RenderConfig(mip="nearest", coverage="prefilter",
                                                                   texture_pairs=1.0)),
    # 3D Gaussians (the 3dgs and mip-splatting methods; THREE_D): the same splats with a third scale
    # from the same range, 3DGS's dilation, or Mip-Splatting's 2D filter with a 3D filter of about a
    # pixel at the camera's distance.
    "3dgs": (None, (), RenderConfig(mip="none")),
    "mip-splatting": (None, (), RenderConfig(mip="none", coverage="prefilter")),
}
#: The configurations of 3D Gaussians, and whether they carry Mip-Splatting's 3D filter.
THREE_D = {"3dgs": False, "mip-splatting": True}
DEFAULT_CONFIGS = ("2dgs", "tex8", "tex8-mip", "tex8-mip-prefilter", "tex8-trilinear")


#: Hand-counted FLOPs per (pixel, splat) pair (see the module docstring).
FLOPS_PER_PAIR = {"2dgs": 70, "tex8-rgb": 124, "tex8-alpha": 101, "tex8": 155, "tex8-mip": 215,
                  "tex8-trilinear": 305, "tex8-mip-dense": 215, "2dgs-prefilter": 68, "tex8-mip-prefilter": 213,
                  "tex8-mip-prefilter-dense": 213, "3dgs": 68, "mip-splatting": 68}


def peak_gflops(n=2048, repeats=5) -> float:
    """Measured float32 matmul throughput of the default device, GFLOP/s."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    f = jax.jit(lambda x: jnp.matmul(x, x, precision=jax.lax.Precision.HIGHEST))  # float32, not TF32
    jax.block_until_ready(f(a))
    return 2.0 * n ** 3 / (timeit(lambda: f(a), repeats) / 1e3) / 1e9


def make_scene(n, tex, seed=0, banks=("rgb", "alpha"), dims=2, filter3d=False):
    """The benchmark's scene: ``dims`` 3 for 3D Gaussians (with ``filter3d``, a 3D filter of
    (0.9 / 640 of the camera's distance)^2: about a pixel at 640 px wide)."""
    sizes = None if tex is None else [tex] * n
    # Splats spread through a 4x4x4 box in front of the camera, sized so a view has a realistic
    # ~ 10-40 splats per pixel of overlap for 50k splats at 640x480.
    scene = random_scene(seed, n, sh_degree=3, extent=2.0, scale_range=(0.005, 0.04),
                         center=(0.0, 0.0, 0.0), rgb_sizes=sizes if "rgb" in banks else None,
                         alpha_sizes=sizes if "alpha" in banks else None, scale_dims=dims)
    if filter3d:
        scene = scene.replace(filter3d=jnp.full(scene.capacity, (5.0 / (0.9 * 640)) ** 2, jnp.float32))
    return scene


def _time_once(fn):
    """ms of one call of ``fn``, to its results' completion."""
    t = time.perf_counter()
    jax.block_until_ready(fn())
    return 1e3 * (time.perf_counter() - t)


def timeit(fn, repeats):
    """Median ms of ``repeats`` calls of ``fn``."""
    return float(np.median([_time_once(fn) for _ in range(repeats)]))


def prepare(name, n, width, height, compositor="xla"):
    """Scene, camera and compiled forward / forward+backward / binning of one configuration with
    ``compositor``, with its compile times, memory, recompile count and pair counts (everything but
    the timings)."""
    tex, banks, cfg = CONFIGS[name]
    cfg = dataclasses.replace(cfg, compositor=compositor)
    scene = make_scene(n, tex, banks=banks, dims=3 if name in THREE_D else 2, filter3d=THREE_D.get(name, False))
    cam = Camera.from_intrinsics([0.9 * width, 0.9 * width, width / 2, height / 2],
                                 look_at((0.0, 0.0, -5.0), (0.0, 0.0, 0.0)), width, height)
    needed, max_tile = count_pairs(scene, cam, cfg)
    cap = Capacity.fit(float(needed))

    fwd = jax.jit(lambda s, c: render_jit(s, c, config=cfg, capacity=cap).rgb)

    def bin_view(s, c):  # the renderer's projection, tile ranges, one sort and per-tile starts
        if s.is_3d:
            proj = gaussian3d.project3d(s, c, cfg, None, None)
        else:
            proj = projection.project(s, c, cfg, None, None, projection.alpha_peak(s))
        ts = cfg.tile_size
        tx, ty = -(-c.width // ts), -(-c.height // ts)
        ranges = binning.tile_ranges(proj.bounds, proj.visible, ts, tx, ty)
        return binning.bin_projection(proj, ranges, tx, tx * ty, cap.pairs, gaussian3d.kernel_config(cfg, s))

    bin_c = jax.jit(bin_view).lower(scene, cam).compile()
    jax.block_until_ready(bin_c(scene, cam))

    def loss(s, c):
        out = render_jit(s, c, config=cfg, capacity=cap)
        return jnp.mean(jnp.abs(out.rgb - 0.5))

    bwd = jax.jit(jax.grad(loss))
    t = time.perf_counter()
    fwd_c = fwd.lower(scene, cam).compile()
    compile_fwd = time.perf_counter() - t
    t = time.perf_counter()
    bwd_c = bwd.lower(scene, cam).compile()
    compile_bwd = time.perf_counter() - t
    mem = bwd_c.memory_analysis()
    temp_bwd = getattr(mem, "temp_size_in_bytes", float("nan")) if mem is not None else float("nan")
    mem_f = fwd_c.memory_analysis()
    temp_fwd = getattr(mem_f, "temp_size_in_bytes", float("nan")) if mem_f is not None else float("nan")
    jax.block_until_ready(fwd_c(scene, cam))
    jax.block_until_ready(bwd_c(scene, cam))
    # The public entry point in steady state: same shapes, no new trace.
    jax.block_until_ready(render_jit(scene, cam, config=cfg, capacity=cap).rgb)
    before = sum(TRACE_COUNTS.values())
    for _ in range(2):
        jax.block_until_ready(render_jit(scene, cam, config=cfg, capacity=cap).rgb)
    recompiles = sum(TRACE_COUNTS.values()) - before
    tiles = -(-width // cfg.tile_size) * -(-height // cfg.tile_size)
    batch = tiling.resolve_tile_batch(cfg.tile_batch, tiles, tile_size=cfg.tile_size, chunk=cfg.chunk)
    row = dict(config=name, compositor=compositor, gaussians=n, width=width, height=height, tiles=tiles,
               tile_batch=batch, recompiles=recompiles,
               flops_per_pair=FLOPS_PER_PAIR[name], binned_pairs=float(needed), max_tile=int(max_tile),
               compile_forward_s=compile_fwd, compile_backward_s=compile_bwd,
               temp_forward_mib=temp_fwd / 2**20, temp_backward_mib=temp_bwd / 2**20)
    calls = dict(fwd=lambda: fwd_c(scene, cam), fb=lambda: bwd_c(scene, cam), bin=lambda: bin_c(scene, cam))
    return row, calls, float(needed) * cfg.tile_size ** 2


def bench_interleaved(names, n, width, height, repeats, compositors=("xla",)):
    """Rows of :func:`prepare`, one per configuration and compositor, with
    timings taken round-robin: each of ``repeats`` rounds times every case's forward, then every
    one's forward+backward, then binning, so a drift of the machine's speed (this VM's runs vary by
    up to 2x) falls on all cases alike. Times are medians over the rounds; ``forward_over_2dgs``
    and ``forward_backward_over_2dgs`` (when "2dgs" is among ``names``) are medians of the
    per-round ratios to the 2dgs case of the same compositor."""
    cases = [(name, comp) for comp in compositors for name in names]
    prepared = [prepare(name, n, width, height, comp) for name, comp in cases]
    times = {key: [[] for _ in cases] for key in ("fwd", "fb", "bin")}
    for _ in range(repeats):
        for key in times:
            for i, (_, calls, _) in enumerate(prepared):
                times[key][i].append(_time_once(calls[key]))
    rows = []
    for i, (row, _, listed) in enumerate(prepared):
        f_ms, b_ms = float(np.median(times["fwd"][i])), float(np.median(times["fb"][i]))
        row.update(forward_ms=f_ms, forward_backward_ms=b_ms, backward_over_forward=b_ms / f_ms,
                   bin_ms=float(np.median(times["bin"][i])),
                   listed_pixel_pairs_per_s=listed / (f_ms / 1e3))
        ref = cases.index(("2dgs", cases[i][1])) if ("2dgs", cases[i][1]) in cases else None
        if ref is not None:
            for key, out in (("fwd", "forward_over_2dgs"), ("fb", "forward_backward_over_2dgs")):
                row[out] = float(np.median(np.asarray(times[key][i]) / np.asarray(times[key][ref])))
        rows.append(row)
    return rows


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None
    return w, h


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[50_000], help="scene sizes to time (default 50000)")
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[(640, 480)], help="WxH, e.g. 160x120 1920x1080")
    ap.add_argument("--repeats", type=int, default=3, help="timed renders per row, after the compiling one (default 3)")
    ap.add_argument("--configs", default=",".join(DEFAULT_CONFIGS),
                    help=f"comma-separated, from {', '.join(CONFIGS)}")
    ap.add_argument("--no-peak", action="store_true", help="skip measuring the matmul peak")
    ap.add_argument("--json", default=None, help="also write the figures here (with the commit and machine)")
    ap.add_argument("--compositor", default="xla",
                    help="comma-separated compositors to time side by side: xla, pallas (RenderConfig.compositor)")
    args = ap.parse_args(argv)
    names = args.configs.split(",")
    compositors = args.compositor.split(",")
    if any(c not in ("xla", "pallas") for c in compositors):
        ap.error(f"--compositor takes xla and/or pallas, got {args.compositor!r}")
    unknown = [n for n in names if n not in CONFIGS]
    if unknown:
        ap.error(f"unknown config(s) {unknown}; choose from {', '.join(CONFIGS)}")
    rows = []
    print(f"jax {jax.__version__} on {platform.processor() or platform.machine()}, "
          f"{jax.device_count()} {jax.devices()[0].platform} device(s)")
    peak = None if args.no_peak else peak_gflops()
    if peak is not None:
        print(f"peak (float32 2048^2 matmul): {peak:.1f} GFLOP/s")
    hdr = (f"{'config':22s} {'N':>8s} {'size':>9s} {'fwd ms':>8s} {'x2DGS':>6s} {'f+b ms':>8s} {'b/f':>5s} "
           f"{'bin ms':>7s} {'binned':>9s} {'maxtile':>7s} {'Mpair/s':>8s} {'%peak':>6s} {'compile s':>9s} "
           f"{'recomp':>6s} {'bwd tmp MiB':>11s}")
    print(hdr)
    for (w, h) in args.sizes:
        for n in args.gaussians:
            for r in bench_interleaved(names, n, w, h, args.repeats, compositors):
                name = r["config"] + ("" if r["compositor"] == "xla" else f"@{r['compositor']}")
                r["peak_gflops"] = peak
                r["fraction_of_peak"] = (None if peak is None else
                                         r["listed_pixel_pairs_per_s"] * r["flops_per_pair"] / (peak * 1e9))
                rows.append(r)
                frac = "-" if peak is None else f"{100 * r['fraction_of_peak']:.1f}"
                x2 = f"{r['forward_over_2dgs']:.2f}" if "forward_over_2dgs" in r else "-"
                print(f"{name:22s} {n:8d} {f'{w}x{h}':>9s} {r['forward_ms']:8.1f} {x2:>6s} "
                      f"{r['forward_backward_ms']:8.1f} {r['backward_over_forward']:5.2f} {r['bin_ms']:7.1f} "
                      f"{r['binned_pairs']:9.0f} {r['max_tile']:7d} "
                      f"{r['listed_pixel_pairs_per_s'] / 1e6:8.1f} {frac:>6s} "
                      f"{r['compile_forward_s'] + r['compile_backward_s']:9.1f} {r['recompiles']:6d} "
                      f"{r['temp_backward_mib']:11.1f}", flush=True)
            if args.json:  # after every case: a long sweep keeps what it measured
                write_benchmark_json(args.json, rows, SCHEMA, peak_gflops=peak, timing="interleaved")


if __name__ == "__main__":
    main()
