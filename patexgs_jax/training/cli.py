"""Training: the 2DGS stage, then the PATexGS texture stage (or a baseline), with checkpoints.

    python -m patexgs_jax.train [--data PATH] --method patexgs --out DIR [--factor F] [--preset P]
        [--iters-2dgs N] [--iters-tex N] [--max-gaussians N] [--resume] [--skip-unreadable]
        [--batch-size B [--devices D]] [--coordinator HOST:PORT --num-processes N --process-id I]

``--batch-size`` trains data-parallel over devices and, with the last three flags (or under SLURM
``srun`` / Open MPI ``mpirun``), over several processes: see :mod:`patexgs_jax.parallel` and
docs/parallel.md.

Without ``--data`` it trains on the embedded synthetic scene (generated once into the cache).

Stages (every method trains ``--iters-2dgs`` + ``--iters-tex`` steps in all)
  1. 2DGS (3D Gaussians for ``3dgs`` and ``mip-splatting``), every method: SfM-point
     initialisation, per-group Adam (:mod:`patexgs_jax.optim`), loss ``0.8 L1 + 0.2 (1 - SSIM)``
     plus the normal-consistency (from ``normal_from``; 2D splats only) and depth-distortion
     regularisers, one SH band every ``sh_interval`` steps, adaptive density control
     (:mod:`patexgs_jax.densify`; the 3D methods prune below opacity 0.005, as 3DGS).
  2. Textures (all methods but ``2dgs``): ``patexgs*`` start every Gaussian with a 5x5 alpha
     texture (ones) and a 1x1 RGB offset (zeros) - the first render equals the 2DGS one - warm up
     ``warmup_tex`` steps, then allocate Eq. 7 sizes from the max-contribution counts over all
     training views and grow them by Eqs. 8-10 every ``growth_interval`` steps
     (:mod:`patexgs_jax.adaptive`, run by :mod:`patexgs_jax.schedule`);
     ``textured-fixed-N`` gives every Gaussian an N x N RGBA texture. The untextured methods
     (``2dgs``, ``3dgs``, ``mip-splatting``) continue stage 1 for these steps instead.

Methods: ``2dgs``, ``textured-fixed-N`` (N in 1, 2, 4, 8, 16, 32; no mipmaps, as Textured
Gaussians), ``patexgs`` (adaptive + RGBA mipmaps), ``patexgs-no-mip``, ``patexgs-no-alpha-mip``,
``patexgs-no-rgb-mip``, ``patexgs-no-adaptive`` (RGBA mipmaps with a fixed 8x8 texture per Gaussian:
the mipmaps without the adaptive allocation), ``patexgs-fixed-N`` (N in 1..32: ``patexgs`` with N x
N textures for every Gaussian at the allocation step and no growth, the fixed rows of the paper's
Table 4), ``patexgs-trilinear`` (mip levels blended trilinearly), ``patexgs-literal`` (the paper
read literally end to end, docs/paper.md: the 2DGS screen-space low-pass under Eq. 13, lambda_mip
0.4, sigma H x W / 1e4, growth through the stage's end), ``patexgs-paper-sigma`` (``patexgs`` with
the paper's sigma; ``--sigma paper|scene|VALUE`` sets Eq. 7's sigma of any method), ``patexgs+filter3d``
(with Mip-Splatting's 3D smoothing filter in each splat's plane from the first step, its own stage
1: for renders zoomed in beyond the training views), the baselines ``bbsplat`` (BBSplat's
billboards, ``RenderConfig(coverage="billboard")``, with 16x16 RGBA textures), ``bbsplat+mip`` (and
RGBA mipmaps), ``bbsplat+adaptive`` (with Eqs. 6-10 sizes), ``textured-gaussians`` (Textured
Gaussians: ``textured-fixed-8``), ``3dgs`` (3DGS) and ``mip-splatting`` (3DGS with Mip-Splatting's
3D and 2D filters); docs/baselines.md. The ``patexgs`` family, but ``patexgs-literal``, renders its
texture stage, and is evaluated, with the prefiltered coverage
(``RenderConfig(coverage="prefilter")``); stage 1 is 2DGS for every method but ``3dgs`` and
``mip-splatting``, which train 3D Gaussians throughout, and is shared by all but those and
``patexgs+filter3d``.

Robustness
  The data order and every random choice are seeded, so ``--resume`` from a checkpoint reaches the
  same result as an uninterrupted run; a step with a non-finite loss or gradient, or an overflowed
  tile capacity, is skipped, never applied; near the kernel's memory-map cap the run checkpoints
  and stops (resume with ``--resume``). The details: :mod:`patexgs_jax.training.trainer`.
  Every image is decoded before anything compiles (``--skip-unreadable`` leaves out the views whose
  file cannot be decoded). Ctrl-C (SIGINT) or SIGTERM stops the run within seconds, at any moment,
  with one line: where it stopped, which checkpoint holds the work (one is written if the newest is
  more than ``--checkpoint-on-stop`` steps old) and the command that continues it; exit status 130
  (SIGINT) or 143 (SIGTERM). See :mod:`patexgs_jax.interrupt`.

Output
  A start line (images, views, schedule, Gaussian cap, device), a time estimate after the first
  measured steps (with the flags that shorten a run of more than an hour), a progress line every
  ``--log-every`` steps, and a line at least every 30 s in every phase (compiles included);
  ``log.jsonl`` records carry their wall-clock time and the seconds since the start.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shlex
import sys
from pathlib import Path

import jax

from .. import checkpoint as ckpt
from .. import interrupt
from ..adaptive import sigma_setting
from .config import PRESETS, default_preset, equal_steps, preset_config
from .run import train

__all__ = ["main"]


def main(argv=None) -> int:
    from .. import parallel

    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="scene folder (COLMAP, LLFF or transforms.json); "
                    "default: the embedded synthetic scene")
    ap.add_argument("--method", default="patexgs", help="what to train (default: patexgs); the methods are "
                    "listed above")
    ap.add_argument("--out", default=None, help="the run's folder: checkpoints/, log.jsonl, scene.ply (+ texture "
                    "sidecar for a textured method) and summary.json (no default: required); --plan needs none")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling (default: the Mip-NeRF 360 "
                    "factors for those scenes, else images wider than 1600 px resized to 1600 wide; 1: full size)")
    ap.add_argument("--preset", default=None, choices=sorted(PRESETS),
                    help="iteration schedule (default: tiny on the embedded scene; with --data, paper on a GPU "
                    "and cpu on a CPU); --iters-* override it")
    ap.add_argument("--iters-2dgs", type=int, default=None, metavar="N",
                    help="steps of the first stage (2DGS splats; 3D Gaussians for 3dgs and mip-splatting), "
                    "densification included (default: the preset's)")
    ap.add_argument("--iters-tex", type=int, default=None, metavar="N",
                    help="steps after the first stage (default: the preset's): the texture stage of a textured "
                    "method (the preset's warm-up and growth interval scale with it); an untextured method "
                    "(2dgs, 3dgs, mip-splatting) continues its first stage for as many steps (no densification, "
                    "the final position learning rate). Every method trains --iters-2dgs + --iters-tex steps in "
                    "all, as experiments.study and experiments.mipnerf360 train them; --iters-tex 0 stops an "
                    "untextured method after its first stage")
    ap.add_argument("--max-gaussians", type=int, default=None, metavar="N",
                    help="cap on the number of Gaussians densification may reach (default: the preset's: 4,000 "
                    "for tiny, 6,000 for cpu, none for small and paper)")
    ap.add_argument("--texture-budget-mb", type=float, default=None, metavar="MB",
                    help="texel budget of the texture stage in MiB of RGBA texels: Eq. 7's sigma is solved so that "
                    "the allocation and growth stay within it (default: no budget)")
    add_sigma_argument(ap)
    ap.add_argument("--seed", type=int, default=0, help="seed of the data order and every random choice "
                    "(default 0); the same seed and data give the same run, resumed or not")
    ap.add_argument("--checkpoint-every", type=int, default=None, help="steps between checkpoints (default: the "
                    "preset's; one is always written at the end)")
    ap.add_argument("--log-every", type=int, default=None, help="steps between progress lines and log.jsonl "
                    "records (default: the preset's)")
    ap.add_argument("--batch-size", type=int, default=None,
                    help="views per step (default 1); > 1 trains data-parallel (see patexgs_jax.parallel)")
    ap.add_argument("--devices", type=int, default=None,
                    help="devices the batch is split over (must divide --batch-size; default: as many as "
                         "divide it); on CPU this many CPU devices are created")
    ap.add_argument("--padding", default=None, choices=["auto", "per-size", "one"],
                    help="padded sizes of the training views: one (every view at the largest tile grid: one step "
                         "program per tile capacity), per-size (each view at its own grid) or auto (default: one "
                         "on a GPU, per-size on a CPU); see TrainConfig.padding")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint")
    ap.add_argument("--skip-unreadable", action="store_true", help="leave out the views whose image file is "
                    "missing or cannot be decoded (default: stop and name them)")
    ap.add_argument("--checkpoint-on-stop", type=int, default=None, metavar="STEPS",
                    help="on Ctrl-C / SIGTERM, write a checkpoint when the newest is more than STEPS steps old "
                    "(default 10)")
    add_plan_arguments(ap)
    parallel.add_cli_arguments(ap)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if args.out is None and not args.plan:
        ap.error("the following arguments are required: --out (the run's folder; or --plan to plan without training)")
    if args.json is not None and not args.plan:
        ap.error("--json writes the plan: pass it with --plan")
    args.resume_command = resume_command("patexgs_jax.train", argv)
    return parallel.run_cli(args, _train_cli, user_errors=(ckpt.CheckpointError,))


def add_plan_arguments(ap) -> None:
    """The ``--plan``, ``--json`` and ``--plan-device`` flags (train's and the study's command lines)."""
    ap.add_argument("--plan", action="store_true", help="print the run's plan and stop: views and padded sizes, "
                    "steps, Gaussians, Eq. 7 texels, each stage's peak memory, step times measured by a few real "
                    "steps, the run's time, and the flags that make it fit (nothing is trained or written)")
    ap.add_argument("--json", default=None, metavar="FILE", help="with --plan: write the plan there as JSON")
    ap.add_argument("--plan-device", action="append", default=[], metavar="DEVICE",
                    help="with --plan: also plan for h100-80gb, rtx4090-24gb, cpu-24gb or a memory size "
                    "(24e9, 24GB, 80GiB: a GPU's; cpu:24GB a CPU's); repeatable")
    ap.add_argument("--plan-steps", type=int, default=5, metavar="N",
                    help="with --plan: steps timed in each stage (default 5; 0: the memory plan alone, in seconds)")


def add_sigma_argument(ap) -> None:
    """The ``--sigma`` flag (train's and the study's command lines): Eq. 7's sigma (``TrainConfig.sigma``)."""
    def setting(text):
        try:
            return sigma_setting(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    ap.add_argument("--sigma", type=setting, default=None, metavar="paper|scene|VALUE",
                    help="Eq. 7's sigma: paper (H x W / 1e4 of the training views, as the paper), scene (half "
                    "the training pixels a Gaussian: the paper's value at its scale of 200 views and a million "
                    "Gaussians) or a number (default: the method's own, scene; paper for patexgs-literal); "
                    "the allocation line and --plan say which")


def print_plans(plans, json_path) -> None:
    """Prints each plan and, with ``json_path``, writes them there (one plan: its object; several: a
    list)."""
    import json as _json

    for p in plans:
        print(p.text(), flush=True)
    if json_path:
        doc = plans[0].to_json() if len(plans) == 1 else [p.to_json() for p in plans]
        Path(json_path).write_text(_json.dumps(doc, indent=1) + "\n")
        print(f"plan written to {json_path}", flush=True)


def resume_command(module: str, argv: list[str]) -> str:
    """The command line that continues a run started with ``argv``: the same, with ``--resume``."""
    return shlex.join(["python", "-m", module, *argv] + ([] if "--resume" in argv else ["--resume"]))


def skip_flag_hint(error: Exception, flag: str = "--skip-unreadable") -> Exception:
    """A loader's error with its Python-API advice (``skip_missing=True``) given as the command-line
    ``flag`` instead."""
    text = re.sub(r"(load with |use )?skip_missing=True", f"pass {flag}", str(error))
    return type(error)(text) if text != str(error) else error


@contextlib.contextmanager
def tidy_output_dir(out):
    """Removes what a run that never got going leaves in ``out``: the folders it created, when they
    are still empty at the end (a failed or stopped start leaves no empty checkpoints/ behind)."""
    out = Path(out)
    made = [d for d in (out, out / "checkpoints", out / "checkpoints" / "stage1") if not d.exists()]

    def tidy():
        for d in reversed(made):
            with contextlib.suppress(OSError):  # (not empty: the run wrote something, keep it)
                os.rmdir(d)

    try:
        with interrupt.cleanup_on_forced_exit(tidy):
            yield
    finally:
        tidy()


def _train_cli(args) -> int:
    if args.plan:
        _plan(args)
        return 0
    with interrupt.guard(resume=args.resume_command):
        try:
            with tidy_output_dir(args.out):
                _train(args)
        except interrupt.Interrupted as stop:
            return interrupt.end_with_stop_line(stop.signum)
    return 0


def _train(args) -> None:
    from .. import memory_maps

    memory_maps.enable_compile_cache()
    interrupt.set_phase("checking the arguments")
    cfg = _config(args)
    if args.data is None:
        from ..data.synthetic import ensure_default_scene

        interrupt.set_phase("making the embedded scene")
        args.data = str(ensure_default_scene())
    if jax.process_index() == 0:  # the process that writes; before the data is loaded
        ckpt.check_output_dir(args.out)
    ds = _load(args)
    interrupt.set_phase("setting up the run")
    train(ds, cfg, args.out, resume=args.resume, end_distributed=True, preset=args.preset)
    if jax.process_index() == 0:  # the dataset, for python -m patexgs_jax.evaluate and render (patexgs_jax.sources)
        from ..sources import write_data_record

        write_data_record(args.out, args.data, args.factor)


def _config(args):
    args.preset = args.preset or default_preset(args.data)
    cfg = preset_config(args.preset, method=args.method, iters_2dgs=args.iters_2dgs,
                         iters_tex=args.iters_tex, max_gaussians=args.max_gaussians,
                         texture_budget_mb=args.texture_budget_mb, sigma=args.sigma, seed=args.seed,
                         checkpoint_every=args.checkpoint_every, log_every=args.log_every,
                         checkpoint_on_stop=args.checkpoint_on_stop, batch_size=args.batch_size,
                         devices=args.devices, padding=args.padding)
    return equal_steps(cfg)  # (an untextured method continues its first stage for the --iters-tex steps)


def _plan(args) -> None:
    """``--plan``: the run's plan (:func:`patexgs_jax.plan.make_plan`), printed and in ``--json``."""
    from .. import memory_maps
    from .. import plan as planning
    from ..plan_steps import Progress

    devices = [planning.parse_device(d) for d in args.plan_device]
    if args.plan_steps < 0:
        raise ValueError(f"--plan-steps {args.plan_steps}: give the steps to time in each stage, 0 or more.")
    memory_maps.enable_compile_cache()
    cfg = _config(args)
    if args.data is None:
        from ..data.synthetic import ensure_default_scene

        args.data = str(ensure_default_scene())
    with Progress() as progress:  # (a line at least every 10 s until the plan is printed)
        progress.phase(f"loading {args.data}")
        ds = _load(args)
        plan = planning.make_plan(ds, cfg, devices=devices, measure=args.plan_steps > 0, steps=args.plan_steps,
                                  progress=progress)
    print_plans([plan], args.json)


def _load(args):
    from ..data import DatasetError, check_images, load

    interrupt.set_phase(f"loading {args.data}")
    try:
        ds = load(args.data, factor=args.factor, skip_missing=args.skip_unreadable)
        interrupt.set_phase(f"checking the {len(ds.views)} images")
        ds = check_images(ds, skip=args.skip_unreadable, skip_hint="pass --skip-unreadable",
                          on_view=lambda n: (interrupt.set_step(n, len(ds.views), "image"), interrupt.check()))
    except DatasetError as e:
        raise skip_flag_hint(e) from None
    interrupt.check()
    return ds


if __name__ == "__main__":
    sys.exit(main())
