"""Which effects a trained scene calls for: each effect it holds (SH bands, RGB textures, alpha
textures, mipmaps) switched off in turn and the scene measured again at every zoom-out, so a user
sees what each one buys and what it costs (``python -m experiments.tradeoffs --effects RUN``), and
the scene exported without those that buy less than a threshold.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path

from experiments import provenance
from experiments.provenance import write_json
from patexgs_jax.camera import ZOOM_SCALES

SCALES = ZOOM_SCALES
EFFECTS = ("sh_bands", "rgb_textures", "alpha_textures", "mipmaps")
EFFECTS_SCHEMA = 1  # effects.json: experiments.provenance's header, then effect_study's fields


def _fmt(x, digits=2):
    return "-" if x is None else f"{x:.{digits}f}"


def _scaled(views, s):
    return list(views) if int(s) == 1 else [v.scaled(int(s)) for v in views]


def measure(scene, views, render_config, scales=SCALES, *, active_sh_degree=None, max_views=8) -> dict:
    """``{"psnr", "ssim", "alias_psnr", "render_ms": {scale: value}}`` of a scene on ``views`` (full
    resolution; alias PSNR as in :func:`patexgs_jax.evaluation.evaluate_scales`; render time: per
    view the fastest of three renders, robust to other processes on the machine, see
    :func:`patexgs_jax.evaluation.render_ms`)."""
    from patexgs_jax.evaluation import evaluate_scales, render_ms
    from patexgs_jax.padding import ViewRenderer

    # One renderer for the metrics and the timings: its programs (one per padded size) serve both.
    with ViewRenderer(scene, render_config, active_sh_degree=active_sh_degree) as renderer:
        ev = evaluate_scales(scene, views, render_config, scales=scales, active_sh_degree=active_sh_degree,
                             renderer=renderer)
        ms = {str(s): render_ms(scene, _scaled(views, s), render_config, max_views=max_views, repeats=3,
                                active_sh_degree=active_sh_degree, renderer=renderer) for s in scales}
    return dict(psnr={str(s): ev[str(s)]["psnr"] for s in scales}, ssim={str(s): ev[str(s)]["ssim"] for s in scales},
                alias_psnr={str(s): ev[str(s)]["alias_psnr"] for s in scales},
                render_ms=ms)


def load_trained(run_dir):
    """(scene, render config, summary or None) of a training run directory: the newest checkpoint's
    scene (or ``scene.ply`` + sidecar without checkpoints) and its method's render configuration
    (:func:`patexgs_jax.viewer.frames.load_run`)."""
    from patexgs_jax.viewer.frames import RunEntry, load_run

    run_dir = Path(run_dir)
    if not ((run_dir / "checkpoints").is_dir() or (run_dir / "scene.ply").exists()):
        raise FileNotFoundError(f"{run_dir} has neither checkpoints/ nor scene.ply: pass --run a folder "
                                "that python -m patexgs_jax.train --out wrote.")
    run = load_run(RunEntry(run_dir.name, run_dir))
    summary = json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").exists() else None
    return run.scene, run.config, summary


def present_effects(scene, rc) -> list[str]:
    """The effects this scene and configuration use (of :data:`EFFECTS`)."""
    out = []
    if scene.sh.shape[1] > 1:
        out.append("sh_bands")
    if scene.rgb is not None:
        out.append("rgb_textures")
    if scene.alpha is not None:
        out.append("alpha_textures")
    if rc.mip != "none" and (scene.rgb is not None or scene.alpha is not None):
        out.append("mipmaps")
    return out


def without(scene, rc, effects: Sequence[str]):
    """(scene, render config) with ``effects`` switched off - removed from the scene (SH truncated to
    the DC band, texture banks dropped) or the render configuration (mip "none"), so the renderer
    compiles them out."""
    for e in effects:
        if e == "sh_bands":
            scene = scene.replace(sh=scene.sh[:, :1])
        elif e == "rgb_textures":
            scene = scene.replace(rgb=None)
        elif e == "alpha_textures":
            scene = scene.replace(alpha=None)
        elif e == "mipmaps":
            rc = dataclasses.replace(rc, mip="none")
        else:
            raise ValueError(f"unknown effect {e!r}; choose from {', '.join(EFFECTS)}.")
    return scene, rc


def render_flops(scene, camera, rc) -> float | None:
    """XLA's flop estimate of one render (compiled separately; None where XLA gives none)."""
    from patexgs_jax.render import Capacity, count_pairs, render_jit

    needed, _ = count_pairs(scene, camera, rc)
    compiled = render_jit.lower(scene, camera, config=rc, capacity=Capacity.fit(float(needed))).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return None if not cost or "flops" not in cost else float(cost["flops"])


def effect_study(scene, rc, views, scales=SCALES, *, verbose=True, max_views=8) -> dict:
    """Per effect, the PSNR it contributes and the render time it costs, at each scale.

    Returns ``{"full": measure(...), "effects": {name: {"off": measure(...), "gain_db": {scale},
    "ms_cost": {scale}}}}`` with gain = PSNR(full) - PSNR(effect off) and cost = ms(full) - ms(off).
    """
    full = measure(scene, views, rc, scales, max_views=max_views)
    out = dict(full=full, effects={})
    for e in present_effects(scene, rc):
        sc, r = without(scene, rc, [e])
        off = measure(sc, views, r, scales, max_views=max_views)
        gain = {s: full["psnr"][s] - off["psnr"][s] for s in full["psnr"]}
        cost = {s: full["render_ms"][s] - off["render_ms"][s] for s in full["render_ms"]}
        out["effects"][e] = dict(off=off, gain_db=gain, ms_cost=cost)
        if verbose:
            print(f"{e:15s} PSNR gain " + " / ".join(f"{gain[s]:+.2f}" for s in gain) + " dB; render cost "
                  + " / ".join(f"{cost[s]:+.1f}" for s in cost) + " ms (scales " + ", ".join(gain) + ")", flush=True)
    return out


def droppable(study: dict, threshold_db: float) -> list[str]:
    """Effects contributing less than ``threshold_db`` at every scale."""
    return [e for e, v in study["effects"].items() if all(g < threshold_db for g in v["gain_db"].values())]


def export_reduced(scene, rc, effects, path) -> Path:
    """Writes the scene without ``effects`` (PLY + sidecar) and ``<stem>.render.json`` (the render
    configuration to use with it). Returns the PLY path."""
    from patexgs_jax.export import export_ply

    sc, r = without(scene, rc, effects)
    path = export_ply(sc, path)
    write_json(path.with_suffix(".render.json"), dict(dataclasses.asdict(r), dropped_effects=list(effects)))
    return path


def load_render_config(ply_path):
    """The RenderConfig stored next to a reduced export (``<stem>.render.json``)."""
    from patexgs_jax.render import RenderConfig

    d = json.loads(Path(ply_path).with_suffix(".render.json").read_text())
    d.pop("dropped_effects", None)
    return RenderConfig(**{k: tuple(v) if k == "background" else v for k, v in d.items()})


def run_effects(run_dir, dataset, out_dir, *, scales=SCALES, drop_below=None, export_path=None,
                verbose=True, max_views=8) -> dict:
    """The effect study of one run, written to ``out_dir/effects.json``; with ``drop_below``, the
    reduced export and its measured speed-up (also in the JSON, under ``"reduced"``)."""
    scene, rc, _ = load_trained(run_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    views = list(dataset.test_views)
    res = effect_study(scene, rc, views, scales, verbose=verbose, max_views=max_views)
    res = dict(provenance.header(EFFECTS_SCHEMA), **res, run=str(run_dir), scales=[int(s) for s in scales])
    if drop_below is not None:
        from patexgs_jax.export import load_ply

        drop = droppable(res, drop_below)
        path = export_reduced(scene, rc, drop, Path(export_path) if export_path else out_dir / "scene_reduced.ply")
        red_scene, red_rc = load_ply(path), load_render_config(path)
        red = measure(red_scene, views, red_rc, scales, max_views=max_views)
        cam = views[0].camera
        flops = dict(full=render_flops(scene, cam, rc), reduced=render_flops(red_scene, cam, red_rc))
        res["reduced"] = dict(threshold_db=drop_below, dropped=drop, path=str(path), measure=red, flops=flops)
        if verbose:
            s = str(scales[0])
            print(f"dropped (< {drop_below} dB at every scale): {', '.join(drop) or 'nothing'} -> {path}\n"
                  f"render x{s}: {res['full']['render_ms'][s]:.1f} ms -> {red['render_ms'][s]:.1f} ms per frame; "
                  f"XLA flops {_fmt(flops['full'], 0)} -> {_fmt(flops['reduced'], 0)}; PSNR "
                  + " / ".join(f"{res['full']['psnr'][k]:.2f}->{red['psnr'][k]:.2f}" for k in red["psnr"]), flush=True)
    write_json(out_dir / "effects.json", res)
    return res
