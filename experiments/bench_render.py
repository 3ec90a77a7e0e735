"""Renderer benchmark: forward and forward+backward time, throughput, memory, compile time.

    python -m experiments.bench_render [--gaussians 50000] [--width 640 --height 480] [--repeats 3]
                                       [--configs 2dgs,tex8,tex8-mip,tex8-trilinear] [--json out.json]

A fixed random scene (seeded) seen by a fixed camera. For each configuration it prints:
forward ms, forward+backward ms (gradient of a photometric-style loss w.r.t. the whole scene),
(pixel, splat) pairs listed per second in the forward pass (binned (splat, tile) pairs x pixels per
tile: the work a renderer without early termination would do; ours stops saturated tiles early),
binned (splat, tile) pairs, the longest tile list, compile time of each function,
and XLA's temporary-buffer size of the backward (its peak working memory beyond inputs/outputs).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from patexgs_jax import Camera, Capacity, RenderConfig, look_at, random_scene
from patexgs_jax.render import count_pairs, render_jit

CONFIGS = {
    "2dgs": (None, RenderConfig(mip="none")),
    "tex8": (8, RenderConfig(mip="none")),
    "tex8-mip": (8, RenderConfig(mip="nearest")),
    "tex8-trilinear": (8, RenderConfig(mip="trilinear")),
}


def make_scene(n, tex, seed=0):
    sizes = None if tex is None else [tex] * n
    # Splats spread through a 4x4x4 box in front of the camera, sized so a view has a realistic
    # ~ 10-40 splats per pixel of overlap for 50k splats at 640x480.
    return random_scene(seed, n, sh_degree=3, extent=2.0, scale_range=(0.005, 0.04),
                        center=(0.0, 0.0, 0.0), rgb_sizes=sizes, alpha_sizes=sizes)


def timeit(fn, repeats):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def bench(name, n, width, height, repeats):
    tex, cfg = CONFIGS[name]
    scene = make_scene(n, tex)
    cam = Camera.from_intrinsics([0.9 * width, 0.9 * width, width / 2, height / 2],
                                 look_at((0.0, 0.0, -5.0), (0.0, 0.0, 0.0)), width, height)
    needed, max_tile = count_pairs(scene, cam, cfg)
    cap = Capacity.fit(float(needed))

    fwd = jax.jit(lambda s, c: render_jit(s, c, config=cfg, capacity=cap).rgb)

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
    f_ms = timeit(lambda: fwd_c(scene, cam), repeats)
    b_ms = timeit(lambda: bwd_c(scene, cam), repeats)
    listed = float(needed) * cfg.tile_size ** 2  # (pixel, splat) pairs in the tile lists
    return dict(config=name, gaussians=n, width=width, height=height, forward_ms=f_ms,
                forward_backward_ms=b_ms, backward_over_forward=b_ms / f_ms,
                binned_pairs=float(needed), max_tile=int(max_tile),
                listed_pixel_pairs_per_s=listed / (f_ms / 1e3),
                compile_forward_s=compile_fwd, compile_backward_s=compile_bwd,
                temp_forward_mib=temp_fwd / 2**20, temp_backward_mib=temp_bwd / 2**20)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[50_000])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows = []
    print(f"jax {jax.__version__} on {platform.processor() or platform.machine()}, "
          f"{jax.device_count()} {jax.devices()[0].platform} device(s)")
    hdr = (f"{'config':16s} {'N':>7s} {'size':>9s} {'fwd ms':>8s} {'f+b ms':>8s} {'b/f':>5s} "
           f"{'binned':>9s} {'maxtile':>7s} {'Mpair/s':>8s} {'compile s':>10s} {'bwd tmp MiB':>11s}")
    print(hdr)
    for n in args.gaussians:
        for name in args.configs.split(","):
            r = bench(name, n, args.width, args.height, args.repeats)
            rows.append(r)
            print(f"{name:16s} {n:7d} {args.width}x{args.height:<4d} {r['forward_ms']:8.1f} "
                  f"{r['forward_backward_ms']:8.1f} {r['backward_over_forward']:5.2f} "
                  f"{r['binned_pairs']:9.0f} {r['max_tile']:7d} "
                  f"{r['listed_pixel_pairs_per_s'] / 1e6:8.1f} "
                  f"{r['compile_forward_s'] + r['compile_backward_s']:10.1f} {r['temp_backward_mib']:11.1f}",
                  flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(machine=platform.platform(), jax=jax.__version__, results=rows), f, indent=1)


if __name__ == "__main__":
    main()
