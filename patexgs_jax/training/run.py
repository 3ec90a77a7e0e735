"""One training run from start to outputs: :func:`train`, with resume and stage-1 sharing."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .. import checkpoint as ckpt
from .. import interrupt, memory_maps, parallel, progress
from ..evaluation import evaluate, shared_renderer
from ..metrics import scene_storage
from ..scene import Scene
from ..schedule import side_histogram
from .config import (
    STAGE2_FIELDS,
    Method,
    TrainConfig,
    comparable_config,
    config_dict,
    effective_config,
    stage1_key,
    stage1_part,
)
from .estimate import start_line
from .trainer import STAGE1_DIR, Trainer

__all__ = ["STAGE2_FIELDS", "TrainResult", "load_stage1", "stage1_checkpoint", "train"]


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns: the trained scene and the summary written to ``summary.json``."""

    scene: Scene
    summary: dict
    out_dir: Path | None


def stage1_checkpoint(run_dir, config: TrainConfig) -> Path | None:
    """The end-of-2DGS-stage checkpoint of the run in ``run_dir`` usable by ``config``, or None: the
    run's final checkpoint if it ended there, else the copy kept in ``checkpoints/stage1/``."""
    directory = Path(run_dir) / "checkpoints"
    paths = list(reversed(ckpt.list_checkpoints(directory))) + list(reversed(ckpt.list_checkpoints(
        directory / STAGE1_DIR)))
    for path in paths:
        try:
            meta = ckpt.read_metadata(path)
        except ckpt.CheckpointError:
            continue
        cfg = meta.get("config") or {}
        if meta.get("step") == config.iters_2dgs and stage1_part(cfg) == stage1_key(config):
            return path
    return None


def _primitive_clash(path: Path, saved: dict, config: TrainConfig) -> str | None:
    """A one-line error when the checkpoint at ``path`` (its saved config ``saved``) holds another
    primitive than ``config``'s method trains (3D Gaussians against 2D splats), naming both."""
    name = saved.get("method")
    try:
        theirs = Method.from_name(name).primitive if isinstance(name, str) else None
    except ValueError:
        return None
    ours = config.spec.primitive
    if theirs is None or theirs == ours:
        return None
    kind = {"2d": "2D splats", "3d": "3D Gaussians"}
    return (f"checkpoint {path} holds {kind[theirs]} (method {name}), but {config.method} trains {kind[ours]}; "
            f"choose a method of {kind[theirs]} or another output directory / checkpoint.")


def load_stage1(run: Trainer, path: Path, config: TrainConfig) -> None:
    """Starts ``run`` from the stage-1 checkpoint ``path``, after checking that it was trained with
    ``config``'s 2DGS-stage settings and ended at the end of that stage."""
    meta = ckpt.read_metadata(path)
    clash = _primitive_clash(path, meta.get("config") or {}, config)
    if clash:
        raise ValueError(clash)
    cfg = stage1_part(meta.get("config") or {})
    want = stage1_key(config)
    if cfg != want:
        diff = sorted(k for k in set(cfg) | set(want) if cfg.get(k) != want.get(k))
        raise ValueError(f"stage-1 checkpoint {path} was trained with different {config.spec.stage1_name}-stage "
                         f"settings ({', '.join(diff)}); train stage 1 again or pass a matching checkpoint.")
    if meta.get("step") != config.iters_2dgs:
        raise ValueError(f"stage-1 checkpoint {path} is at step {meta.get('step')}, not at the end of the "
                         f"{config.spec.stage1_name} stage (step {config.iters_2dgs}).")
    tree, _ = ckpt.load_checkpoint(path)
    run.load_state(tree)
    run.tiles.current = run.tiles.floor = None  # refit for this method's render configuration, from none
    run.say(f"stage 1 from {path} ({run.t_train:.0f} s of {run.spec.stage1_name} training)")


def train(dataset, config: TrainConfig = TrainConfig(), out_dir=None, *, resume: bool = False,  # noqa: B008 (frozen)
          verbose: bool = True, stage1=None, map_guard: memory_maps.MapGuard | None = None,
          evaluate_everywhere: bool = False, end_distributed: bool = False,
          check_memory: bool = True, preset: str | None = None, prepare=()) -> TrainResult:
    """Trains ``config.method`` on ``dataset`` (see :func:`patexgs_jax.data.load`).

    Args:
      dataset: a loaded dataset (train/test views, points).
      config: :class:`TrainConfig`.
      out_dir: where checkpoints, ``log.jsonl``, ``scene.ply`` (+ texture sidecar) and
        ``summary.json`` go; None keeps everything in memory.
      resume: continue from the newest complete checkpoint in ``out_dir`` if there is one.
      verbose: print progress.
      stage1: start from the end of another run's 2DGS stage instead of training it again: a
        checkpoint file written at step ``config.iters_2dgs`` by a run whose config agrees with
        ``config`` outside :data:`STAGE2_FIELDS` (see :func:`stage1_checkpoint`). The stage-1
        training time is carried over into ``train_seconds``. Ignored when resuming.
      map_guard: when the process nears the kernel's memory-map cap, compiled code is released and,
        if that is not enough, the run checkpoints and raises :class:`memory_maps.MapLimitReached`
        (default ``memory_maps.MapGuard()``: release at half the cap, stop at 90%).
      evaluate_everywhere, end_distributed: with several processes (``jax.distributed``, see
        :mod:`patexgs_jax.parallel`) every process trains and process 0 alone writes the outputs
        and, by default, evaluates (the others' summaries have None metrics). With
        ``evaluate_everywhere`` every process evaluates (the processes stay in step for what
        follows); with ``end_distributed`` ``jax.distributed`` is shut down once training is done,
        so the other processes can exit while process 0 evaluates and writes (the command line's
        choice; nothing cross-process can follow).
      check_memory: before the first step, compare the run's estimated memory with the memory
        available (:func:`patexgs_jax.plan.check_fits`: the step beside what the process holds on a
        CPU, then every stage's peak on this device, CPU or GPU).
      preset: the name of the preset ``config`` was made from, for the start line.
      prepare: configs of runs this process will start from this run's stage-1 checkpoint
        (``stage1=``): when this run reaches the end of its 2DGS stage, their texture stage's first
        programs are compiled ahead in a background thread (:mod:`patexgs_jax.background`,
        ``PATEXGS_COMPILE_AHEAD=0`` turns it off), so that their first steps do not wait for them.
    Returns:
      :class:`TrainResult`. Its summary's ``train_seconds`` is the wall-clock time of the training
      steps of both stages (with ``stage1=``, that run's stage-1 seconds carried over), including
      the compiles a step waits for, not the host work between steps (densification, texture
      allocation and growth, checkpoints), data loading or evaluation; its ``config`` is the
      configuration the run trained with (:func:`~patexgs_jax.training.config.effective_config`).
    Raises:
      memory_maps.MapLimitReached: near the memory-map cap (the message says how to resume).
      parallel.DistributedError: with several processes, they do not start from the same state, or
        one of them stopped (the message says what to do).
      memory.NotEnoughMemory: the step would not fit in memory (the message names a factor that fits).
    """
    # A process that trains many runs keeps their programs (steps shared between runs, the renderer's)
    # until half the kernel's memory-map cap is reached: then free them (see patexgs_jax.memory_maps).
    memory_maps.release_compiled_code()
    if jax.process_count() > 1:  # the batch must split evenly over every process's devices
        parallel.num_batch_devices(config.batch_size, config.devices)
    out = None if out_dir is None else Path(out_dir)
    main = parallel.is_main_process()
    if out is not None and main:
        ckpt.check_writable(out)
        ckpt.check_writable(out / "checkpoints")
    run = Trainer(dataset, config, out, verbose, map_guard)
    run.ahead.prepare_for = tuple(prepare)
    latest = ckpt.latest_checkpoint(out / "checkpoints") if (out is not None and resume) else None
    if latest is not None:
        tree, meta = ckpt.load_checkpoint(latest)
        clash = _primitive_clash(latest, meta.get("config") or {}, config)
        if clash:
            raise ValueError(clash)
        saved, wanted = comparable_config(meta.get("config") or {}), comparable_config(config_dict(config))
        if saved != wanted:
            differ = sorted(k for k in wanted if saved.get(k) != wanted[k])
            raise ValueError(f"checkpoint {latest} was written with a different configuration ({', '.join(differ)} "
                             "differ); resume with the same settings or choose a new output directory.")
        run.load_state(tree)
        run.note_saved(run.step)
        run.say(f"resuming from {latest} at step {run.step}")
    else:
        if out is not None and not resume and ckpt.latest_checkpoint(out / "checkpoints") is not None:
            raise FileExistsError(f"{out} already holds checkpoints; pass resume=True (--resume) to continue "
                                  "that run, or choose another output directory.")
        if stage1 is not None:
            load_stage1(run, Path(stage1), config)
        else:
            run.fresh()
    if out is not None and main:  # fail now if checkpoints cannot fit (two kept + one being written), not hours later
        # (about a checkpoint's size: it holds these arrays, the texels' optimiser ages one per slot)
        ckpt.check_writable(out / "checkpoints", required_bytes=3 * sum(
            np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(run.state)))
    if jax.process_count() > 1:  # every process starts from the same state (data; checkpoint when resuming)
        parallel.check_same("the starting state (step and a checksum of the scene); every process needs the same "
                            "--data and, to resume, must see process 0's --out folder (a shared filesystem)",
                            [run.step, parallel.tree_checksum(run.scene)])
    if check_memory:  # a clear stop now rather than the kernel's OOM kill mid-step (on a GPU too)
        from .. import plan

        plan.check_fits(dataset, config, max(run.scene.capacity, config.max_gaussians or 0))
    if verbose and main:
        progress.say(start_line(dataset, config, run.step, preset))
    xla_before = memory_maps.xla_compiles()
    run.run()
    xla_programs, xla_seconds = (a - b for a, b in zip(memory_maps.xla_compiles(), xla_before, strict=True))
    interrupt.check()
    scene, compiles = run.scene, run.steps.compiles
    size = scene_storage(scene)
    summary: dict[str, Any] = dict(
        method=config.method, steps=run.step, train_seconds=run.t_train, num_gaussians=size["gaussians"],
        texels=size["texels"], texels_rgb=size["texels_rgb"], texels_alpha=size["texels_alpha"],
        storage_mb=size["storage_mb"], recompiles=compiles.count, compiled_at_steps=compiles.at,
        # The step's programs this process traced for the run (``recompiles`` also counts those of a
        # run resumed or started from a stage-1 checkpoint) and the seconds those steps took; every
        # XLA program the process compiled or loaded while it trained.
        compiles=dict(step_programs=len(compiles.at), step_seconds=round(compiles.seconds, 3),
                      xla_programs=xla_programs, xla_seconds=round(xla_seconds, 3)),
        padding=run.pad.summary(run.render_cfg.tile_size),
        compile_ahead=run.ahead.summary(), skipped_steps=run.skipped,
        allocation=run.textures.allocation, growth_events=run.textures.growth_events,
        sides_final=None if scene.rgb is None else side_histogram(np.asarray(scene.rgb.size),
                                                                  np.asarray(scene.active) > 0),
        stage1_from=None if stage1 is None else str(stage1))
    if end_distributed and jax.process_count() > 1:
        jax.distributed.shutdown()  # the processes are done with each other (every one calls this)
    if main or evaluate_everywhere:
        # (the final checkpoint holds the trained scene: a stop from here on loses no training)
        # (one renderer for both sets: a padded size compiles once for the two)
        sets = (run.train_views[:32], list(dataset.test_views))
        interrupt.set_phase("evaluating the training views")
        with shared_renderer(scene, run.render_cfg, sets) as renderer:
            train_eval = evaluate(scene, sets[0], run.render_cfg, renderer=renderer)
            interrupt.set_phase("evaluating the test views")
            test_eval = evaluate(scene, sets[1], run.render_cfg, renderer=renderer)
    else:  # evaluation and outputs are process 0's
        train_eval = test_eval = dict(psnr=None, ssim=None)
    summary.update(train_psnr=train_eval["psnr"], test_psnr=test_eval["psnr"], test_ssim=test_eval["ssim"],
                   config=config_dict(effective_config(config)))  # (what the run trained with)
    if out is not None and main:
        from ..export import export_ply

        interrupt.check()
        interrupt.set_phase(f"writing {out / 'scene.ply'}")
        export_ply(scene, out / "scene.ply")
        tmp = out / "summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=1))
        tmp.replace(out / "summary.json")
    if verbose and main:
        print(f"done: train PSNR {summary['train_psnr']:.2f}, test PSNR "
              f"{summary['test_psnr'] if summary['test_psnr'] is None else round(summary['test_psnr'], 2)}, "
              f"{summary['num_gaussians']} Gaussians, {summary['texels']} texels, "
              f"{summary['storage_mb']:.2f} MB, {summary['train_seconds']:.0f} s", flush=True)
    return TrainResult(scene=scene, summary=summary, out_dir=out)
