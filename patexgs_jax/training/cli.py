"""Training: the 2DGS stage, then the PATexGS texture stage (or a baseline), with checkpoints.

    python -m patexgs_jax.train --data PATH --method patexgs --out DIR [--factor F]
        [--iters-2dgs N] [--iters-tex N] [--max-gaussians N] [--resume]
        [--batch-size B [--devices D]] [--coordinator HOST:PORT --num-processes N --process-id I]

``--batch-size`` trains data-parallel over devices and, with the last three flags (or under SLURM
``srun`` / Open MPI ``mpirun``), over several processes: see :mod:`patexgs_jax.parallel` and
docs/parallel.md.

Without ``--data`` it trains on the embedded synthetic scene (generated once into the cache).

Stages
  1. 2DGS (every method): SfM-point initialisation, per-group Adam (:mod:`patexgs_jax.optim`),
     loss ``0.8 L1 + 0.2 (1 - SSIM)`` plus the normal-consistency (from ``normal_from``) and
     depth-distortion regularisers, one SH band every ``sh_interval`` steps, adaptive density
     control (:mod:`patexgs_jax.densify`).
  2. Textures (all methods but ``2dgs``): ``patexgs*`` start every Gaussian with a 5x5 alpha
     texture (ones) and a 1x1 RGB offset (zeros) - the first render equals the 2DGS one - warm up
     ``warmup_tex`` steps, then allocate Eq. 7 sizes from the max-contribution counts over all
     training views and grow them by Eqs. 8-10 every ``growth_interval`` steps
     (:mod:`patexgs_jax.adaptive`, run by :mod:`patexgs_jax.training.strategies`);
     ``textured-fixed-N`` gives every Gaussian an N x N RGBA texture.

Methods: ``2dgs``, ``textured-fixed-N`` (N in 1, 2, 4, 8, 16, 32; no mipmaps, as Textured Gaussians),
``patexgs`` (adaptive + RGBA mipmaps), ``patexgs-no-mip``, ``patexgs-no-alpha-mip``,
``patexgs-no-rgb-mip``, ``patexgs-no-adaptive`` (RGBA mipmaps with a fixed 8x8 texture per Gaussian:
the mipmaps without the adaptive allocation), ``patexgs-fixed-N`` (N in 1..32: ``patexgs`` with N x N
textures for every Gaussian at the allocation step and no growth, the fixed rows of the paper's
Table 4), ``patexgs-trilinear`` (mip levels blended trilinearly),
``patexgs-literal`` (the paper's Eqs. 11-13 read literally: the 2DGS screen-space low-pass and
lambda_mip 0.4). The ``patexgs`` family, but ``patexgs-literal``, renders its texture stage, and
is evaluated, with the prefiltered coverage (``RenderConfig(coverage="prefilter")``); stage 1 is
2DGS for every method.

Robustness
  The data order and every random choice are seeded, so ``--resume`` from a checkpoint reaches the
  same result as an uninterrupted run; a step with a non-finite loss or gradient, or an overflowed
  tile capacity, is skipped, never applied; near the kernel's memory-map cap the run checkpoints
  and stops (resume with ``--resume``). The details: :mod:`patexgs_jax.training.trainer`.
"""

from __future__ import annotations

import argparse
import sys

import jax

from .. import checkpoint as ckpt
from .config import PRESETS, preset_config
from .run import train

__all__ = ["main"]


def main(argv=None) -> int:
    from .. import parallel

    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="scene folder (COLMAP, LLFF or transforms.json); "
                    "default: the embedded synthetic scene")
    ap.add_argument("--method", default="patexgs")
    ap.add_argument("--out", required=True)
    ap.add_argument("--factor", type=int, default=None, help="image downsampling (default: the Mip-NeRF 360 "
                    "factors for those scenes, else images wider than 1600 px resized to 1600 wide; 1: full size)")
    ap.add_argument("--preset", default="paper", choices=sorted(PRESETS),
                    help="iteration schedule (default: paper); --iters-* override it")
    ap.add_argument("--iters-2dgs", type=int, default=None)
    ap.add_argument("--iters-tex", type=int, default=None,
                    help="texture-stage steps; the preset's warm-up and growth interval scale with it")
    ap.add_argument("--max-gaussians", type=int, default=None)
    ap.add_argument("--texture-budget-mb", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint-every", type=int, default=None, help="steps between checkpoints (default: the "
                    "preset's; one is always written at the end)")
    ap.add_argument("--log-every", type=int, default=None, help="steps between progress lines and log.jsonl "
                    "records (default: the preset's)")
    ap.add_argument("--batch-size", type=int, default=None,
                    help="views per step (default 1); > 1 trains data-parallel (see patexgs_jax.parallel)")
    ap.add_argument("--devices", type=int, default=None,
                    help="devices the batch is split over (must divide --batch-size; default: as many as "
                         "divide it); on CPU this many CPU devices are created")
    ap.add_argument("--resume", action="store_true")
    parallel.add_cli_arguments(ap)
    return parallel.run_cli(ap.parse_args(argv), _train_cli, user_errors=(ckpt.CheckpointError,))


def _train_cli(args) -> None:
    from .. import compiled
    from ..data import load

    compiled.enable_compile_cache()

    if args.data is None:
        from ..data.synthetic import ensure_default_scene

        args.data = str(ensure_default_scene())
    if jax.process_index() == 0:  # the process that writes; before the data is loaded
        ckpt.check_output_dir(args.out)
    cfg = preset_config(args.preset, method=args.method, iters_2dgs=args.iters_2dgs,
                        iters_tex=args.iters_tex, max_gaussians=args.max_gaussians,
                        texture_budget_mb=args.texture_budget_mb, seed=args.seed,
                        checkpoint_every=args.checkpoint_every, log_every=args.log_every,
                        batch_size=args.batch_size, devices=args.devices)
    ds = load(args.data, factor=args.factor)
    train(ds, cfg, args.out, resume=args.resume, end_distributed=True)


if __name__ == "__main__":
    sys.exit(main())
