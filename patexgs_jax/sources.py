"""Trained models on disk as the command lines read them: a run folder, a checkpoint file or a PLY
with its texture sidecar becomes a :class:`Source` (the scene, its method's render configuration,
the training configuration, and the dataset it trained on where that is recorded).

What each path holds
  * a run folder (``python -m patexgs_jax.train --out RUN``, or a study's ``runs/<scene>/<label>``):
    the newest complete checkpoint in ``checkpoints/`` (else ``scene.ply``) and its configuration
    (the checkpoint's, else ``summary.json``'s);
  * a ``.ckpt`` file: its scene and configuration;
  * a ``.ply`` file (:func:`patexgs_jax.export.export_ply`, or any 2DGS / 3DGS PLY): its scene,
    with the configuration of the run folder it lies in (its ``summary.json``), else none: the
    method is then read from the scene (3D Gaussians: ``3dgs``; textured: ``patexgs``; else ``2dgs``).

The dataset of a run (:func:`data_record`)
  ``RUN/data.json`` (``{"data", "factor", "test_every"}``, written by the training command line);
  else, for a study's run, the study's ``results.json`` (its ``scenes`` record: the scene's folder,
  factor, hold-out and the study's ``test_views``); a scene named ``synthetic-v<V>-seed<N>`` without
  a folder recorded is the embedded synthetic scene of that seed
  (:func:`patexgs_jax.data.synthetic.ensure_default_scene`).
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

from .render import RenderConfig

__all__ = ["DATA_RECORD", "DataRecord", "Source", "SourceError", "data_record", "is_run", "load_source",
           "render_config_of", "write_data_record"]

#: The file a run folder records its dataset in.
DATA_RECORD = "data.json"

#: What a source path may be, for the error messages.
EXPECTED = ("a run folder (checkpoints/ or scene.ply, as python -m patexgs_jax.train --out writes, or a "
            "study's runs/<scene>/<method>), a checkpoint (.ckpt) or a PLY (.ply, with its .textures.npz sidecar)")


class SourceError(ValueError):
    """A path that is not a trained model, or one that cannot be read; the message says what was expected."""


@dataclasses.dataclass(frozen=True)
class DataRecord:
    """The dataset a run trained on: ``path`` (a scene folder), the loader's ``factor`` (None: its
    default) and ``test_every`` (the hold-out), and ``test_views`` (a study's cap on the test views
    it evaluates; None: all)."""

    path: Path
    factor: int | None = None
    test_every: int = 8
    test_views: int | None = None
    embedded_seed: int | None = None  # the embedded synthetic scene of this seed: generated on load if missing

    def load(self, verbose: bool = False):
        """The :class:`patexgs_jax.data.Dataset` (loaded as the run's training loaded it)."""
        from .data import load

        if self.embedded_seed is not None:
            from .data.synthetic import ensure_default_scene

            ensure_default_scene(self.embedded_seed, verbose=verbose)
        return load(self.path, factor=self.factor, test_every=self.test_every, verbose=verbose)


@dataclasses.dataclass
class Source:
    """A trained model read from disk.

    Attributes:
      name: a display name (the run folder's name: a study's run's method label).
      path: what was read (the checkpoint or PLY file).
      scene: the :class:`patexgs_jax.Scene`.
      render_config: its method's :class:`RenderConfig` (what evaluation renders with).
      train_config: the training configuration (a dict, as checkpoints save it), or None.
      method: the method's name.
      data: the dataset it trained on (:class:`DataRecord`), or None where none is recorded.
      summary: the run's ``summary.json``, or None.
    """

    name: str
    path: Path
    scene: Any
    render_config: RenderConfig
    train_config: dict | None
    method: str
    data: DataRecord | None = None
    summary: dict | None = None


def render_config_of(train_config: dict) -> RenderConfig:
    """The render configuration of a run's method from its saved training configuration (a dict)."""
    from .training.config import Method

    lam = train_config.get("lambda_mip")
    return Method.from_name(train_config.get("method", "patexgs")).render_config(
        lambda_mip=None if lam is None else float(lam), background=train_config.get("background", (0.0, 0.0, 0.0)))


def is_run(folder: Path) -> bool:
    """Whether ``folder`` is a run folder (a complete checkpoint in ``checkpoints/``, or ``scene.ply``)."""
    from .checkpoint import latest_checkpoint

    ck = folder / "checkpoints"
    return (ck.is_dir() and latest_checkpoint(ck) is not None) or (folder / "scene.ply").is_file()


def _run_folder_of(path: Path) -> Path | None:
    """The run folder a checkpoint or PLY file lies in, or None."""
    for parent in path.parents[:3]:  # RUN/scene.ply, RUN/checkpoints/x.ckpt, RUN/checkpoints/stage1/x.ckpt
        if (parent / "summary.json").is_file() or (parent / "checkpoints").is_dir():
            return parent
    return None


def _study_of(run: Path) -> tuple[Path, str, str] | None:
    """``(study folder, scene, label)`` of a study's run ``STUDY/runs/<scene>/<label>``, or None."""
    run = run.resolve()
    if len(run.parents) >= 3 and run.parents[1].name == "runs" and (run.parents[2] / "results.json").is_file():
        return run.parents[2], run.parent.name, run.name
    return None


def _embedded_seed(name: str) -> int | None:
    """The seed of the embedded synthetic scene when ``name`` is its name (``synthetic-v<V>-seed<N>``)."""
    from .data import synthetic

    m = re.fullmatch(r"synthetic-v(\d+)-seed(\d+)", name)
    return None if m is None or int(m.group(1)) != synthetic.FORMAT_VERSION else int(m.group(2))


def write_data_record(run: Path, data, factor: int | None, test_every: int = 8) -> Path:
    """Writes ``RUN/data.json``: the dataset the run in ``run`` trained on (see :func:`data_record`)."""
    path = Path(run) / DATA_RECORD
    path.write_text(json.dumps(dict(data=str(Path(data).resolve()), factor=factor, test_every=test_every), indent=1)
                    + "\n")
    return path


def data_record(run: Path) -> DataRecord | None:
    """The dataset the run in folder ``run`` trained on, where it is recorded (see the module
    docstring); None otherwise. Raises :class:`SourceError` for a record that cannot be read."""
    rec = run / DATA_RECORD
    if rec.is_file():
        try:
            d = json.loads(rec.read_text())
            return DataRecord(Path(d["data"]), d.get("factor"), int(d.get("test_every", 8)))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SourceError(f"{rec} is unreadable ({type(e).__name__}: {e}); delete it and pass --data.") from None
    study = _study_of(run)
    if study is None:
        return None
    folder, scene, _ = study
    try:
        results = json.loads((folder / "results.json").read_text())
    except (OSError, ValueError) as e:
        raise SourceError(f"{folder / 'results.json'} is unreadable ({e}); pass --data.") from None
    proto = (results.get("scenes") or {}).get(scene) or {}
    views = (results.get("config") or {}).get("test_views")
    factor, every = proto.get("factor"), int(proto.get("test_every") or 8)
    if proto.get("path"):
        return DataRecord(Path(proto["path"]), factor, every, views)
    seed = _embedded_seed(scene)
    if seed is None:
        return None
    from .data.synthetic import default_scene_dir

    return DataRecord(default_scene_dir(seed), factor, every, views, embedded_seed=seed)


def _method_of_scene(scene) -> str:
    if scene.log_scales.shape[-1] == 3:
        return "3dgs"
    return "patexgs" if (scene.rgb is not None or scene.alpha is not None) else "2dgs"


def load_source(path, name: str | None = None) -> Source:
    """Reads a trained model (see the module docstring).

    Args:
      path: a run folder, a ``.ckpt`` file or a ``.ply`` file.
      name: the display name (default: the run folder's name, else the file's).
    Raises:
      SourceError: ``path`` is none of these, or cannot be read (the message says what was expected).
    """
    from . import checkpoint as ckpt
    from .export import PlyFormatError, load_ply

    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path} does not exist: pass {EXPECTED}.")
    if path.is_dir():
        if not is_run(path):
            raise SourceError(f"{path} is not a run folder (no checkpoint in checkpoints/, no scene.ply): pass "
                              f"{EXPECTED}.")
        run: Path | None = path
    elif path.suffix in (".ckpt", ".ply"):
        run = _run_folder_of(path)
    else:
        raise SourceError(f"{path} is neither a checkpoint (.ckpt) nor a PLY (.ply): pass {EXPECTED}.")
    try:
        summary = None
        if run is not None and (run / "summary.json").is_file():
            summary = json.loads((run / "summary.json").read_text())
        if path.is_dir():
            ck = ckpt.latest_checkpoint(path / "checkpoints") if (path / "checkpoints").is_dir() else None
            file = ck if ck is not None else path / "scene.ply"
        else:
            file = path
        if file.suffix == ".ckpt":
            tree, meta = ckpt.load_checkpoint(file)
            if not isinstance(tree, dict) or "scene" not in tree:
                raise SourceError(f"cannot read the run {file}: it holds no scene; pass a training checkpoint.")
            scene, cfg = tree["scene"], meta.get("config") or None
        else:
            scene, cfg = load_ply(file), (summary or {}).get("config") or None
        method = (cfg or {}).get("method") or _method_of_scene(scene)
        rc = render_config_of(dict(cfg or {}, method=method))
        data = data_record(run) if run is not None else None
    except (OSError, ValueError, json.JSONDecodeError, ckpt.CheckpointError, PlyFormatError) as e:
        if isinstance(e, SourceError):
            raise
        raise SourceError(f"cannot read the run {path}: {e}") from None
    if name is None:
        name = (run or path).resolve().name
    return Source(name=name, path=file, scene=scene, render_config=rc, train_config=cfg, method=method, data=data,
                  summary=summary)
