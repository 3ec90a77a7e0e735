"""Viewer benchmark: milliseconds per frame of the browser viewer's render path on the CPU.

    python -m experiments.bench_viewer [--run PATH] [--sizes 320x240 640x480 1280x720]
                                       [--gaussians 50000] [--repeats 5] [--preview 4] [--json out.json]

Two models: ``tiny``, a trained run (``--run``: a run folder or checkpoint; default: the embedded
scene trained with the ``tiny`` preset into ``runs/bench_viewer/patexgs``, resumed or reused when
there), seen from its first test view's pose; and a synthetic ``N``-Gaussian scene (``--gaussians``,
built as :mod:`experiments.bench_render` builds it: 8 x 8 RGB and alpha textures, SH degree 3),
seen from bench_render's camera. Both render as the viewer does (:class:`patexgs_jax.viewer.frames.FrameRenderer`,
PATexGS coverage, RGB view): for each canvas size, the median over ``--repeats`` poses on a small
orbit (a moving camera: new poses, no compile) of

  * ``frame_ms``: a full-size frame, camera to uint8 image (render at the padded size, colouring);
  * ``frame_cpu_ms``: the CPU time this process spent on it, over all its threads (on a machine
    shared with other jobs the wall time grows, the CPU time much less: on an idle 2-core machine
    a frame takes between half of it and all of it);
  * ``preview_ms``: the frame rendered ``--preview`` times smaller a side (what a moving camera gets);
  * ``jpeg_ms``: encoding the full-size frame as a quality-90 JPEG with Pillow (what viser sends
    without OpenCV installed);

and ``fps`` = 1000 / (frame_ms + jpeg_ms), ``preview_fps`` likewise for the preview. ``recompiles``
counts frames after the first that compiled anything (must be 0). The machine's load average is
recorded: the figures are only comparable on a quiet machine.
"""

from __future__ import annotations

import argparse
import io
import math
import os
import time
from pathlib import Path

import numpy as np

from experiments.provenance import write_benchmark_json

SCHEMA = 1


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 640x480, got {text!r}") from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"a frame needs at least 16 x 16 pixels, got {text!r}")
    return w, h


#: Where the ``tiny`` model is trained (or reused) when ``--run`` is not given.
DEFAULT_RUN = "runs/bench_viewer/patexgs"


def tiny_model(run: str | None):
    """(name, scene, render config, (wxyz, position, fov)) of the trained ``tiny`` model."""
    from patexgs_jax.data import load
    from patexgs_jax.data.synthetic import ensure_default_scene
    from patexgs_jax.viewer import frames as vw

    data = load(ensure_default_scene(verbose=False), verbose=False)
    if run is None:
        from patexgs_jax.training import preset_config, train

        out = Path(DEFAULT_RUN)
        if not (out / "summary.json").exists():
            print(f"training the tiny patexgs model on the embedded scene into {out} (minutes) ...", flush=True)
            train(data, preset_config("tiny", method="patexgs"), out, resume=True, verbose=False)
        run = out
    loaded = vw.load_run(vw.find_runs(run)[0])
    return "tiny", loaded.scene, loaded.config, vw.viewer_pose(data.test_views[0].camera)


def synthetic_model(n: int):
    """(name, scene, render config, pose) of bench_render's textured n-Gaussian scene and camera."""
    from experiments.bench_render import make_scene
    from patexgs_jax.camera import Camera, look_at
    from patexgs_jax.render import RenderConfig
    from patexgs_jax.viewer import frames as vw

    scene = make_scene(n, 8)
    cam = Camera.from_intrinsics([0.9 * 640, 0.9 * 640, 320, 240], look_at((0.0, 0.0, -5.0), (0.0, 0.0, 0.0)), 640, 480)
    return "synthetic", scene, RenderConfig(coverage="prefilter"), vw.viewer_pose(cam)


def orbit(pose, k: int, step_deg: float = 2.0):
    """Pose ``k`` of a small orbit: the camera turned by k * step_deg about its own y axis."""
    from patexgs_jax.viewer import frames as vw

    wxyz, pos, fov = pose
    a = math.radians(step_deg * k)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    return vw.matrix_to_quat(vw.quat_to_matrix(wxyz) @ turn), pos, fov


def jpeg_ms(image: np.ndarray) -> float:
    from PIL import Image

    t = time.perf_counter()
    Image.fromarray(image).save(io.BytesIO(), format="JPEG", quality=90)
    return 1e3 * (time.perf_counter() - t)


def bench(name, scene, config, pose, sizes, repeats: int, preview: int) -> list[dict]:
    from patexgs_jax.viewer import frames as vw

    fr = vw.FrameRenderer(scene, config)
    mode = vw.own_mode(config)
    stats = vw.scene_stats(scene)
    rows = []
    for w, h in sizes:
        cams = [vw.camera_from_viewer(*orbit(pose, k), w, h) for k in range(repeats + 1)]
        p = preview
        while p > 1 and min(w, h) // p < 8:
            p //= 2
        full, small, enc, cpu, recompiles = [], [], [], [], 0
        for k, cam in enumerate(cams):
            c0 = time.process_time()
            f = fr.render(cam, mode=mode)
            c1 = time.process_time()
            s = fr.render(cam, mode=mode, scale=p, enlarge=False)
            if k == 0:
                t_compile = f.ms + s.ms
                continue  # the first frame compiles
            recompiles += int(f.compiled or s.compiled)
            full.append(f.ms)
            cpu.append(1e3 * (c1 - c0))
            small.append(s.ms)
            enc.append(jpeg_ms(f.image))
        r = dict(model=name, gaussians=stats["gaussians"], texels=stats["texels"], storage_mb=stats["storage_mb"],
                 width=w, height=h, frame_ms=float(np.median(full)), frame_cpu_ms=float(np.median(cpu)),
                 preview_ms=float(np.median(small)),
                 preview_size=[w // p, h // p], jpeg_ms=float(np.median(enc)), first_frame_ms=t_compile,
                 recompiles=recompiles, repeats=repeats)
        r["fps"] = 1e3 / (r["frame_ms"] + r["jpeg_ms"])
        r["preview_fps"] = 1e3 / r["preview_ms"]
        rows.append(r)
        print(f"{name:9s} {r['gaussians']:7d} {f'{w}x{h}':>9s} {r['frame_ms']:9.1f} {r['frame_cpu_ms']:8.1f} "
              f"{r['jpeg_ms']:7.1f} "
              f"{r['fps']:6.1f} {f'{w // p}x{h // p}':>9s} {r['preview_ms']:9.1f} {r['preview_fps']:6.1f} "
              f"{t_compile / 1e3:8.1f} {recompiles:6d}", flush=True)
    fr.release()
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=None, help="the tiny model's run folder or checkpoint (default: train it)")
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[(320, 240), (640, 480), (1280, 720)],
                    help="canvas sizes WxH (default 320x240 640x480 1280x720)")
    ap.add_argument("--gaussians", type=int, default=50_000, help="the synthetic model's size (0: skip it)")
    ap.add_argument("--repeats", type=int, default=5, help="timed frames per row (default 5)")
    ap.add_argument("--preview", type=int, default=4,
                    help="the preview frames' downscale a side, as the viewer's (default 4)")
    ap.add_argument("--models", default="tiny,synthetic", help="comma-separated: tiny, synthetic")
    ap.add_argument("--json", default=None, help="write the results here (e.g. benchmarks/viewer.json)")
    args = ap.parse_args(argv)
    models = args.models.split(",")
    if any(m not in ("tiny", "synthetic") for m in models) or args.repeats < 1 or args.preview < 1:
        ap.error("--models takes tiny and/or synthetic; --repeats and --preview must be >= 1")
    load = os.getloadavg()
    print(f"load average {load[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'model':9s} {'N':>7s} {'size':>9s} {'frame ms':>9s} {'CPU ms':>8s} {'jpeg ms':>7s} {'fps':>6s} "
          f"{'preview':>9s} "
          f"{'prev. ms':>9s} {'fps':>6s} {'first s':>8s} {'recomp':>6s}")
    rows = []
    if "tiny" in models:
        tiny = bench(*tiny_model(args.run), args.sizes, args.repeats, args.preview)
        for r in tiny:  # which trained model: the figures depend on its splats' screen sizes
            r["run"] = args.run or DEFAULT_RUN
        rows += tiny
    if "synthetic" in models and args.gaussians > 0:
        rows += bench(*synthetic_model(args.gaussians), args.sizes, args.repeats, args.preview)
    if args.json:
        write_benchmark_json(args.json, rows, SCHEMA, load_average_before=list(load),
                             load_average_after=list(os.getloadavg()))
        print(f"written to {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
