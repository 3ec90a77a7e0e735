"""A run's plan before it trains: sizes, steps, Gaussians, Eq. 7 texels, peak memory, time, fit.

``python -m patexgs_jax.train ... --plan`` (and ``python -m experiments.mipnerf360 ... --plan``)
calls :func:`make_plan`: the views' padded sizes, the steps of each stage, the Gaussian count the
run plans for, the texels Eq. 7 gives at that count, the peak memory of the 2DGS stage, the
texture stage and evaluation (on this process's device and, when asked, on another:
:func:`parse_device`), the time per step of each stage measured by a few real steps
(:func:`measure_steps`, saying what it measures at least every 10 s), the whole run's time, what
would not fit with the flag that makes it fit (:func:`fixes`), and, for a run of days on a CPU,
its time on an H100 and what trains here in an hour or a night (:mod:`patexgs_jax.plan_advice`).

The memory model (pure functions; docs/memory.md has its terms and its measured error):

  peak = base + per-pixel bytes x padded pixels of the largest view + per-Gaussian bytes x
         Gaussians + texture bytes x RGBA texels (+ on a CPU, the images the dataset caches)

* CPU (the process's peak resident memory, ``ru_maxrss``): the per-stage base
  (:data:`CPU_BASE_BYTES`) is calibrated on the short real runs of ``python -m
  experiments.plan_check`` (fresh processes), the per-pixel term on :mod:`patexgs_jax.memory`'s
  measurements at 1-12 MP; the per-Gaussian and texture terms are counted. (The memory check of
  :mod:`patexgs_jax.memory` keeps its own base, above every training-step peak it was calibrated on.)
* GPU (the device's peak bytes in use): the per-Gaussian and per-texel terms measured on one H100
  (:data:`GPU_BYTES_PER_GAUSSIAN`, :data:`GPU_BYTES_PER_TEXEL`: ``experiments.bench_scale``'s
  training steps at 1M and 3M Gaussians); the rest counted. Per pixel: the CPU's per-pixel
  arrays (accumulators and their cotangents, outputs, loss terms), and, with the XLA compositor
  (the Pallas kernel, a GPU's default, keeps its per-pair state on the chip), the compositor's working
  memory, :data:`patexgs_jax.rendering.tiling.PAIR_BYTES` per (tile pixel, chunk slot) of the
  tiles it advances at once (all of them, up to a quarter of the device:
  :func:`patexgs_jax.rendering.tiling.choose_tile_batch`). Per Gaussian: parameters, gradients, two
  Adam moments and the updated copy, the projection's per-splat rows and their cotangents.
  Textures: RGBA float32 texels as parameter, gradient and two Adam moments, the mip levels
  (another third) for the forward and its cotangent, and the texture buckets' headroom.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os

import numpy as np

from . import adaptive, memory, plan_advice
from .metrics import mb_to_texels
from .padding import padded_shape
from .plan_devices import DEVICES, GB, Device, parse_device, this_device
from .plan_steps import Progress, measure_steps
from .rendering import tiling

__all__ = [
    "DEVICES",
    "Device",
    "Plan",
    "UNCAPPED_GAUSSIANS",
    "check_fits",
    "eq7_texels",
    "fixes",
    "gaussian_bytes",
    "make_plan",
    "mean_stage1_gaussians",
    "measure_steps",
    "parse_device",
    "pixel_bytes",
    "planned_gaussians",
    "stage_peaks",
    "texture_bytes",
    "this_device",
]

# -- counts --------------------------------------------------------------------------------------

#: Gaussians planned for when the run has no cap (``max_gaussians`` None): densification is then
#: bounded only by its gradient threshold, and 2DGS on the Mip-NeRF 360 scenes reaches 1 to several
#: million; ``--max-gaussians`` makes the count a cap.
UNCAPPED_GAUSSIANS = 3_000_000


def planned_gaussians(config, num_points: int) -> tuple[int, str]:
    """The Gaussian count a run plans for and where it comes from.

    Args:
      config: the :class:`patexgs_jax.training.TrainConfig`.
      num_points: the initial point cloud's size.
    Returns:
      (count, a phrase saying which: the cap, or what densification may reach).
    """
    dc = config.densify
    densifies = dc.stop > dc.start and config.iters_2dgs > dc.start
    cap = config.max_gaussians
    if cap is not None:
        if not densifies:
            n = min(cap, num_points)
            return n, f"the initial points, {num_points:,}, up to the cap {cap:,} (no densification in this schedule)"
        return cap, f"the cap (max_gaussians {cap:,}): densification fills it"
    if not densifies:
        return num_points, "the initial points (no densification in this schedule, no cap)"
    events = len(range(dc.start, min(dc.stop, config.iters_2dgs), dc.interval))
    reach = num_points * 2.0 ** events  # each event at most doubles the count
    n = int(min(reach, UNCAPPED_GAUSSIANS))
    return n, (f"no cap: densification may reach {n:,} ({events} events from {num_points:,} points, "
               f"at most doubling each, bounded by the {UNCAPPED_GAUSSIANS:,} 2DGS reaches on the Mip-NeRF 360 "
               "scenes); --max-gaussians makes it a cap")


def mean_stage1_gaussians(config, num_points: int, gaussians: int) -> int:
    """The mean active Gaussian count over the first stage's steps: the initial points (at most
    ``gaussians``) until densification starts, rising linearly to ``gaussians`` by its last event
    (or the stage's end), then ``gaussians`` (a study's untextured runs continue at that count)."""
    dc, steps = config.densify, config.iters_2dgs
    p, n = min(int(num_points), int(gaussians)), int(gaussians)
    start, stop = min(dc.start, steps), min(dc.stop, steps)
    if stop <= start:
        return p
    extra = config.continue_2dgs if config.spec.textures is None else 0
    total = p * start + 0.5 * (p + n) * (stop - start) + n * (steps - stop) + n * extra
    return int(round(total / (steps + extra)))


def eq7_texels(view_pixels, gaussians: int, config) -> tuple[int, int, float | None, str]:
    """Eq. 7's RGBA texels at ``gaussians`` Gaussians, with the real functions of
    :mod:`patexgs_jax.adaptive`.

    Without a trained model the contribution counts are modelled: every Gaussian gets the same
    share of every view's pixels, ``S_ij = P_j / N`` (the counts of a view sum to its pixels). The
    runs in docs/memory.md allocate 6.5 (beer) to 14 (embedded scene) RGBA texels a Gaussian
    where this model gives 9: the sides are skewed (most 1, a few 32), the total is near.

    Args:
      view_pixels: (V,) pixels of each training view (unpadded).
      gaussians: N.
      config: the TrainConfig (method, sigma, texture_budget_mb, budget_eq7_share, max_texture_size).
    Returns:
      (RGBA texels after Eq. 7, RGBA texels the texture stage may reach with growth, sigma or None,
      how sigma was chosen).
    """
    spec = config.spec
    n = max(int(gaussians), 1)
    if spec.textures is None:
        return 0, 0, None, "no textures"
    if spec.size is not None:
        t = n * spec.size ** 2
        return t, t, None, f"{spec.size}x{spec.size} for every Gaussian"
    P = np.asarray(view_pixels, np.float64).reshape(-1, 1)
    S = P / n  # (V, 1): the one column every Gaussian shares
    if config.texture_budget_mb is not None:
        budget = mb_to_texels(config.texture_budget_mb)
        target = max(int(round(config.budget_eq7_share * budget)), n)
        return target, max(budget, target), None, (f"solved for {config.budget_eq7_share:.0%} of the "
                                                   f"{config.texture_budget_mb:g} MiB budget")
    sigma, how = adaptive.eq7_sigma(config.sigma_setting, P, n)  # (the paper's H x W / 1e4, the pixel share, given)
    side = int(adaptive.initial_texture_sizes(S, sigma, max_size=config.max_texture_size)[0])
    t = n * side ** 2
    return t, int(t * (1 + GROWTH_SHARE)), float(sigma), f"sigma {sigma:.4g} from {how}; side {side} a Gaussian"


#: Texels growth (Eqs. 8-10) adds to Eq. 7's without a budget: measured 2-4% on the cpu and tiny
#: presets (beer, the embedded scene); kept at 10% for longer schedules.
GROWTH_SHARE = 0.10


# -- memory --------------------------------------------------------------------------------------

#: GPU bytes besides the per-pixel, per-Gaussian and texture arrays: the images of a step on the
#: device, the compiled programs' constants and small buffers (counted, not calibrated).
GPU_BASE_BYTES = 256 * 2**20
#: Per-pixel bytes on a GPU besides the compositor's working memory: the CPU figure less the host
#: copies of the image (counted).
GPU_BYTES_PER_PIXEL = memory.BYTES_PER_PIXEL - 24.0
#: An evaluation render keeps no cotangents: its per-pixel arrays are about half a training step's.
EVAL_PIXEL_SHARE = 0.5
#: CPU resident memory of a run besides its per-pixel, per-Gaussian, texture and image terms, per stage
#: (calibrated on ``experiments.plan_check``'s runs, docs/memory.md): the runtime and the step's compile
#: (``stage1``; a textured run's also compiles the texture stage's first programs); the texture stage's
#: is mostly the compiled code it keeps (1.85 GB on beer at 1/8, 2.87 GB on the embedded scene, whose
#: short stage grows often: the base lies between them). Evaluation's peak is the training peak.
CPU_BASE_BYTES = dict(stage1=560 * 2**20, stage1_textured=1240 * 2**20, texture=2200 * 2**20)


def pixel_bytes(pixels: int, kind: str, device_bytes: int | None = None, *, training: bool = True,
                tile_size: int = 16, chunk: int = 32, compositor: str = "pallas") -> float:
    """Bytes that grow with the padded pixels of one view.

    Args:
      pixels: padded pixels (whole tiles) of the largest view.
      kind: ``"cpu"`` or ``"gpu"``.
      device_bytes: a GPU's memory for JAX (sizes the compositor's tile batch).
      training: a training step (forward and backward) or an evaluation render (forward).
      compositor: on a GPU, ``"pallas"`` (the default there) or ``"xla"``, whose chunked compositor
        holds a working memory that grows with the tiles it advances at once.
    Returns:
      bytes (float).
    """
    share = 1.0 if training else EVAL_PIXEL_SHARE
    if kind == "cpu":
        return share * memory.BYTES_PER_PIXEL * pixels
    if compositor != "xla":
        # The Pallas kernel (a GPU's default compositor) keeps its per-pair state on the chip: the
        # H100's 2DGS step at 1.04 MP left 0.31 GB besides the Gaussians for everything else.
        return share * GPU_BYTES_PER_PIXEL * pixels
    tiles = max(1, -(-int(pixels) // (tile_size * tile_size)))
    env = os.environ.get(tiling.ENV_TILE_BATCH, "").strip()
    batch = min(int(env), tiles) if env.isdigit() and int(env) > 0 else tiling.choose_tile_batch(
        tiles, backend="gpu", tile_size=tile_size, chunk=chunk, memory_bytes=device_bytes)
    working = batch * tile_size * tile_size * chunk * tiling.PAIR_BYTES
    return share * (GPU_BYTES_PER_PIXEL * pixels + working)


#: GPU bytes a Gaussian slot of a training step, measured: the slope of the 2DGS step's device peak
#: between 1.1M and 3.3M slots on one H100 (1.76 and 4.70 GiB, ``experiments.bench_scale``,
#: benchmarks/bench_scale_h100_{1m,3m}_43b446a.json). The CPU keeps the counted 2,000 B (XLA's CPU
#: buffers are not the GPU allocator's).
GPU_BYTES_PER_GAUSSIAN = 1435.0
#: GPU bytes an allocated RGBA texel adds to the texture stage's step, measured the same way (the
#: textured step less the 2DGS one: 3.48 GiB for 13.5M texels at 1M Gaussians, 11.09 GiB for 40.7M
#: at 3M: 277 and 292 B): the parameter, gradient, Adam moments and ages in power-of-two bucket
#: slots with the buckets' headroom (1.3x the texels' own size, then up to 2x in capacity), the atlas
#: and mip levels the renderer builds, and their cotangents.
GPU_BYTES_PER_TEXEL = 285.0


def gaussian_bytes(gaussians: int, *, training: bool = True, kind: str = "cpu") -> float:
    """Bytes per Gaussian slot times ``gaussians``: training holds parameters, gradients, Adam
    moments, the updated copy and the projection's rows (:data:`patexgs_jax.memory.BYTES_PER_GAUSSIAN`
    counted; on a GPU :data:`GPU_BYTES_PER_GAUSSIAN` measured); evaluation the parameters and the
    projection's rows (a fifth of it)."""
    per = GPU_BYTES_PER_GAUSSIAN if kind == "gpu" else memory.BYTES_PER_GAUSSIAN
    return (1.0 if training else 0.2) * per * int(gaussians)


#: Texture buckets keep this share of spare texels (:data:`patexgs_jax.schedule.TEXTURE_HEADROOM`).
TEXTURE_HEADROOM = 0.25


def texture_bytes(rgba_texels: int, *, mip: bool = True, training: bool = True) -> float:
    """Bytes of ``rgba_texels`` RGBA float32 texels (16 B each) with the buckets' headroom: when
    training, parameter, gradient and two Adam moments (4 copies) plus the mip levels (a third more)
    for the forward and its cotangent; when evaluating, the parameter and its mip levels."""
    copies = (4.0 + (2.0 / 3.0 if mip else 0.0)) if training else (1.0 + (1.0 / 3.0 if mip else 0.0))
    return 16.0 * copies * (1.0 + TEXTURE_HEADROOM) * int(rgba_texels)


def stage_peaks(kind: str, *, train_pixels: int, eval_pixels: int, gaussians: int, rgba_texels: int,
                textured: bool, mip: bool = True, device_bytes: int | None = None,
                image_bytes: int = 0) -> dict[str, int]:
    """Peak memory (bytes) of the 2DGS stage, the texture stage and evaluation.

    Args:
      kind: ``"cpu"`` (the process's peak resident memory) or ``"gpu"`` (the device's peak in use).
      train_pixels, eval_pixels: padded pixels of the largest training view and evaluated view.
      gaussians: Gaussian slots.
      rgba_texels: RGBA texels the texture stage reaches (0 for an untextured method).
      textured: whether the run has a texture stage.
      mip: textures with mipmaps.
      device_bytes: a GPU's memory for JAX (its compositor's tile batch).
      image_bytes: CPU only: the images the dataset caches.
    Returns:
      ``{"stage1", "texture", "eval"}`` in bytes (``texture`` 0 without a texture stage).
    """
    g = gaussian_bytes(gaussians)
    tex = texture_bytes(rgba_texels, mip=mip)
    if kind == "cpu":
        px = pixel_bytes(train_pixels, "cpu")
        s1 = CPU_BASE_BYTES["stage1_textured" if textured else "stage1"] + px + g + image_bytes
        s2 = CPU_BASE_BYTES["texture"] + px + g + tex + image_bytes if textured else 0.0
        ev = max(s1, s2, CPU_BASE_BYTES["stage1"] + pixel_bytes(eval_pixels, "cpu", training=False) + image_bytes)
    else:
        px = pixel_bytes(train_pixels, "gpu", device_bytes)
        g = gaussian_bytes(gaussians, kind="gpu")
        tex = GPU_BYTES_PER_TEXEL * int(rgba_texels)
        s1 = GPU_BASE_BYTES + px + g
        s2 = GPU_BASE_BYTES + px + g + tex if textured else 0.0
        ev = (GPU_BASE_BYTES + pixel_bytes(eval_pixels, "gpu", device_bytes, training=False)
              + gaussian_bytes(gaussians, training=False, kind="gpu")
              + texture_bytes(rgba_texels, mip=mip, training=False))
    return dict(stage1=int(s1), texture=int(s2), eval=int(ev))


def fixes(device: Device, peaks: dict[str, int], *, sizes, factor: float, gaussians: int, rgba_texels: int,
          textured: bool, mip: bool, image_bytes: int, eval_pixels: int) -> list[str]:
    """What makes a plan that does not fit on ``device`` fit: the flags, each with the figure it
    needs (an empty list when the plan fits).

    Args:
      sizes: (width, height) of the training views as loaded; ``factor`` their downsampling.
      the rest: as :func:`stage_peaks`.
    """
    if max(peaks.values()) <= device.memory_bytes:
        return []

    def peaks_at(sizes_, n, texels, eval_px, images):
        px = max(padded_pixels(w, h) for w, h in sizes_)
        return stage_peaks(device.kind, train_pixels=px, eval_pixels=eval_px, gaussians=n, rgba_texels=texels,
                           textured=textured, mip=mip, device_bytes=device.memory_bytes, image_bytes=images)

    out = []
    for f in range(int(math.floor(factor)) + 1, 65):
        shrink = factor / f
        smaller = [(max(round(w * shrink), 1), max(round(h * shrink), 1)) for w, h in sizes]
        p = peaks_at(smaller, gaussians, rgba_texels, int(eval_pixels * shrink ** 2), int(image_bytes * shrink ** 2))
        if max(p.values()) <= device.memory_bytes:
            w, h = max(smaller, key=lambda s: s[0] * s[1])
            out.append(f"--factor {f} ({w}x{h} images: peak {max(p.values()) / GB:.1f} GB)")
            break
    lo, hi = 0, gaussians  # the largest cap that fits (textures scale with the count)
    while hi - lo > max(1, gaussians // 1000):
        mid = (lo + hi) // 2
        p = peaks_at(sizes, mid, rgba_texels * mid // max(gaussians, 1), eval_pixels, image_bytes)
        lo, hi = (mid, hi) if max(p.values()) <= device.memory_bytes else (lo, mid)
    if lo > 0:
        p = peaks_at(sizes, lo, rgba_texels * lo // max(gaussians, 1), eval_pixels, image_bytes)
        out.append(f"--max-gaussians {lo} (peak {max(p.values()) / GB:.1f} GB)")
    if textured and rgba_texels > 0:
        room = device.memory_bytes - max(peaks_at(sizes, gaussians, 0, eval_pixels, image_bytes).values())
        per_texel = GPU_BYTES_PER_TEXEL if device.kind == "gpu" else texture_bytes(1, mip=mip)
        mb = math.floor(max(room, 0) / per_texel * 16 / 2**20 * 10) / 10
        if mb > 0:
            out.append(f"--texture-budget-mb {mb:g} (the planned textures are {rgba_texels * 16 / 2**20:.0f} MiB "
                       "of texels)")
    if device.kind == "gpu":
        px = max(padded_pixels(w, h) for w, h in sizes)
        tiles = max(1, px // 256)
        batch = tiling.choose_tile_batch(tiles, backend="gpu", tile_size=16, chunk=32,
                                         memory_bytes=device.memory_bytes)
        if batch > 64:
            out.append(f"{tiling.ENV_TILE_BATCH}={max(batch // 4, 1)} (the renderer's tile_batch: {batch} tiles at "
                       f"once now, {batch * 256 * 32 * tiling.PAIR_BYTES / GB:.1f} GB of working memory)")
    return out


def padded_pixels(width: int, height: int, tile_size: int = 16) -> int:
    """Pixels of a ``width`` x ``height`` view padded to whole tiles (as the training step renders it)."""
    h, w = padded_shape(height, width, tile_size)
    return h * w


# -- the plan ------------------------------------------------------------------------------------


@dataclasses.dataclass
class Plan:
    """A run's plan: what :func:`make_plan` found (see :meth:`to_json` for the units)."""

    method: str
    views: list  # [{"name", "split", "width", "height", "padded_width", "padded_height"}]
    steps: dict  # {"stage1", "texture"}
    gaussians: int
    gaussians_from: str
    texels_eq7: int
    texels_max: int
    sigma: float | None
    sigma_from: str
    devices: list  # [{"device", "kind", "memory_bytes", "peak_bytes", "fits", "fixes"}]
    step_seconds: dict
    measured: dict
    total_seconds: float | None
    time_terms: dict
    advice: list = dataclasses.field(default_factory=list)  # lines: where the run belongs, what fits here

    @property
    def fits(self) -> bool:
        """Whether the run fits on this device (the first of :attr:`devices`)."""
        return bool(self.devices[0]["fits"])

    def to_json(self) -> dict:
        """The plan as JSON: every figure's unit in its name or beside it."""
        here = self.devices[0]
        return dict(
            method=self.method, units=dict(bytes="B", seconds="s", texels="RGBA texels (float32 x 4 each)"),
            views=self.views, steps=self.steps, gaussians=self.gaussians, gaussians_from=self.gaussians_from,
            texels_eq7=self.texels_eq7, texels_max=self.texels_max, sigma=self.sigma, sigma_from=self.sigma_from,
            device=here["device"], memory_bytes=here["memory_bytes"], peak_bytes=here["peak_bytes"],
            fits=self.fits, fixes=here["fixes"], devices=self.devices, step_seconds=self.step_seconds,
            measured=self.measured, total_seconds=self.total_seconds, time_terms_seconds=self.time_terms,
            advice=self.advice)

    def text(self) -> str:
        """The plan as lines for a terminal."""
        sizes: dict[tuple, int] = {}
        for v in self.views:
            k = (v["split"], v["width"], v["height"], v["padded_width"], v["padded_height"])
            sizes[k] = sizes.get(k, 0) + 1
        lines = [f"plan for {self.method} (nothing is trained or written):"]
        for (split, w, h, pw, ph), n in sorted(sizes.items()):
            lines.append(f"  {n:4d} {split} views {w}x{h}, padded {pw}x{ph}")
        lines.append(f"  steps: {self.steps['stage1']} (2DGS stage) + {self.steps['texture']} (texture stage)")
        lines.append(f"  Gaussians: {self.gaussians:,} ({self.gaussians_from})")
        if self.texels_max:
            lines.append(f"  texels (RGBA): {self.texels_eq7:,} after Eq. 7 ({self.sigma_from}), up to "
                         f"{self.texels_max:,} with growth ({self.texels_max * 16 / 2**20:.1f} MiB)")
        if self.total_seconds is None:
            lines.append("  step time: not measured (--plan-steps 0)")
        else:
            lines.extend(self._time_lines())
            lines.extend(f"  {a}" for a in self.advice)
        for d in self.devices:
            p = d["peak_bytes"]
            lines.append(f"  peak memory on {d['device']}: 2DGS {p['stage1'] / GB:.2f} GB, texture "
                         f"{p['texture'] / GB:.2f} GB, evaluation {p['eval'] / GB:.2f} GB of "
                         f"{d['memory_bytes'] / GB:.1f} GB: {'fits' if d['fits'] else 'does NOT fit'}")
            if d["fixes"]:
                lines.append("    to fit, pass " + "; or ".join(d["fixes"]))
            elif not d["fits"]:
                lines.append("    no flag alone makes it fit: fewer or smaller images, or a larger device")
        return "\n".join(lines)

    def _time_lines(self) -> list[str]:
        m, lines = self.measured, []
        at = f" at {m['padded_size'][1]}x{m['padded_size'][0]} px, 1 of {m['padded_sizes']} sizes" if m.get(
            "padded_size") else ""
        lines.append(f"  step time (this device, {m['steps']} timed steps a stage{at}, {m['seconds']:.0f} s): 2DGS "
                     f"{_s(self.step_seconds['stage1'])} (at {m.get('stage1_gaussians', m['gaussians']):,} Gaussians, "
                     f"the stage's mean), texture {_s(self.step_seconds['texture'])} (at {m['gaussians']:,})"
                     f"{'; ' + m['note'] if m.get('note') else ''}")
        tt = self.time_terms
        lines.append(f"  whole run: {_hms(self.total_seconds or 0.0)} ({_hms(tt['stage1'])} 2DGS + "
                     f"{_hms(tt['texture'])} textures + {_hms(tt['compile'])} compiling + "
                     f"{_hms(tt['eval'])} evaluation)")
        return lines


def _s(x):
    return "-" if x is None else (f"{x * 1e3:.0f} ms" if x < 10 else f"{x:.1f} s")


def _hms(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def memory_plan(dataset, config, gaussians: int, rgba_texels: int, device: Device) -> dict:
    """This run's peaks on ``device`` and whether they fit: ``{"device", "kind", "memory_bytes",
    "peak_bytes", "fits", "fixes"}`` (bytes)."""
    spec = config.spec
    tests = list(getattr(dataset, "test_views", ()))
    sizes = [(v.camera.width, v.camera.height) for v in dataset.train_views]
    evals = [(v.camera.width, v.camera.height) for v in tests + list(dataset.train_views)[:32]]
    train_px = max(padded_pixels(w, h) for w, h in sizes)
    eval_px = max(padded_pixels(w, h) for w, h in evals)
    images = 0
    if device.kind == "cpu":
        w, h = max(sizes, key=lambda s: s[0] * s[1])
        images = memory._cache_bytes(getattr(dataset, "image_cache", None), w * h * 12, len(sizes) + len(tests))
    textured = spec.textures is not None
    mip = spec.mip != "none"
    peaks = stage_peaks(device.kind, train_pixels=train_px, eval_pixels=eval_px, gaussians=gaussians,
                        rgba_texels=rgba_texels, textured=textured, mip=mip, device_bytes=device.memory_bytes,
                        image_bytes=images)
    fits = max(peaks.values()) <= device.memory_bytes
    advice = fixes(device, peaks, sizes=sizes, factor=float(getattr(dataset, "factor", 1) or 1), gaussians=gaussians,
                   rgba_texels=rgba_texels, textured=textured, mip=mip, image_bytes=images, eval_pixels=eval_px)
    return dict(device=device.name, kind=device.kind, memory_bytes=int(device.memory_bytes), peak_bytes=peaks,
                fits=bool(fits), fixes=advice)


#: On a CPU the plan times steps at no more than this many Gaussians and padded pixels, and scales.
MEASURE_MAX_GAUSSIANS = 10_000
MEASURE_MAX_PIXELS = 1 << 20
#: Steps timed a stage where the plan extrapolates anyway (the count scaled linearly); its Eq. 7
#: allocation then runs at the texture stage's start (no warm-up step: one compile less).
EXTRAPOLATED_STEPS = 3


def make_plan(dataset, config, *, devices=(), measure: bool = True, steps: int = 5,
              measured: dict | None = None, progress: bool | Progress = True) -> Plan:
    """The plan of training ``config`` on ``dataset`` (see the module docstring).

    Args:
      dataset: a loaded :class:`patexgs_jax.data.Dataset`.
      config: the run's TrainConfig.
      devices: other :class:`Device` s to plan for (this process's device comes first).
      measure: time real steps (:func:`measure_steps`); False leaves the step times None.
      steps: timed steps a stage.
      measured: step times already measured for this dataset and config (skips measuring).
      progress: say what is measured while measuring (:class:`patexgs_jax.plan_steps.Progress`: a line
        at least every 10 s), or a Progress to say it with; False: silent.
    """
    spec = config.spec
    n, n_from = planned_gaussians(config, len(dataset.points))
    train_px = [v.camera.width * v.camera.height for v in dataset.train_views]
    texels, texels_max, sigma, sigma_from = eq7_texels(train_px, n, config)
    views = []
    for split, vs in (("train", dataset.train_views), ("test", dataset.test_views)):
        for v in vs:
            w, h = v.camera.width, v.camera.height
            ph, pw = padded_shape(h, w)
            views.append(dict(name=v.name, split=split, width=w, height=h, padded_width=pw, padded_height=ph))
    here = this_device()
    plans = [memory_plan(dataset, config, n, texels_max, d) for d in (here, *devices)]
    steps1 = config.iters_2dgs + (config.continue_2dgs if spec.textures is None else 0)
    steps2 = config.iters_tex if spec.textures is not None else 0
    if measured is None and measure:
        m_n, scale, note = n, 1.0, ""
        px = max(padded_pixels(v.camera.width, v.camera.height) for v in dataset.train_views)
        timed, quick = steps, False
        if here.kind == "cpu" and (n > MEASURE_MAX_GAUSSIANS or px > MEASURE_MAX_PIXELS or not plans[0]["fits"]):
            m_n = min(n, MEASURE_MAX_GAUSSIANS)
            scale = max(n / m_n, 1.0)
            timed, quick = min(steps, EXTRAPOLATED_STEPS), True  # (scaled anyway: fewer steps, one compile less)
            note = (f"measured at {m_n:,} Gaussians and scaled by {scale:.3g} (linear in the count: an "
                    "extrapolation)")
        mean = mean_stage1_gaussians(config, len(dataset.points), n) * m_n // max(n, 1)
        pr = progress if isinstance(progress, Progress) else Progress() if progress else None
        with pr if pr is not None else contextlib.nullcontext():
            got = measure_steps(dataset, config, m_n, steps=timed, stage1_gaussians=mean, quick=quick,
                                progress=pr)
        measured = dict(got, gaussians=m_n, scale=scale, note=note)
    elif measured is None:
        measured = dict(stage1=None, texture=None, compile_stage1=0.0, compile_texture=0.0, eval_view=0.0,
                        eval_compile=0.0, steps=0,
                        seconds=0.0, gaussians=n, scale=1.0, note="not measured")
    sc = measured.get("scale", 1.0)
    t1 = None if measured["stage1"] is None else measured["stage1"] * sc
    t2 = None if measured.get("texture") is None else measured["texture"] * sc
    n_eval = len(dataset.test_views) + min(len(dataset.train_views), 32)  # as train() evaluates
    dens = config.densify
    doublings = max(0, math.ceil(math.log2(max(n, 1) / max(len(dataset.points), 1)))) if dens.stop > dens.start else 0
    sizes = measured.get("padded_sizes", 1)  # (each padded size of the training views compiles its steps)
    terms = dict(stage1=steps1 * (t1 or 0.0), texture=steps2 * (t2 or 0.0),
                 compile=sizes * (measured["compile_stage1"] * (1 + doublings) + measured["compile_texture"] * 2),
                 eval=n_eval * measured["eval_view"] * sc + 2 * measured.get("eval_compile", 0.0))
    total = None if t1 is None else float(sum(terms.values()))
    advice = []
    if total is not None and here.kind == "cpu" and total > plan_advice.ABSURD_SECONDS:
        advice = plan_advice.advice_lines(dataset, config, measured, total, n=n, steps1=steps1, steps2=steps2,
                                          n_eval=n_eval, compile_seconds=terms["compile"], sizes=sizes,
                                          texels=texels_max)
    return Plan(method=config.method, views=views, steps=dict(stage1=steps1, texture=steps2), gaussians=n,
                gaussians_from=n_from, texels_eq7=texels, texels_max=texels_max, sigma=sigma, sigma_from=sigma_from,
                devices=plans, step_seconds=dict(stage1=t1, texture=t2), measured=measured,
                total_seconds=total, time_terms=terms, advice=advice)


def check_fits(dataset, config, gaussians: int, device: Device | None = None) -> dict:
    """Raises :class:`patexgs_jax.memory.NotEnoughMemory` when a stage of the run (2DGS, texture,
    evaluation) would not fit on ``device`` (default :func:`this_device`), with the flags of
    :func:`fixes`; ``PATEXGS_SKIP_MEMORY_CHECK=1`` skips it.

    Args:
      dataset, config: the run's.
      gaussians: the Gaussian slots the run holds (its cap, else its scene's capacity).
    Returns:
      :func:`memory_plan`'s dict.
    """
    device = device or this_device()
    spec = config.spec
    texels = 0
    if spec.textures is not None:
        texels = eq7_texels([v.camera.width * v.camera.height for v in dataset.train_views], gaussians, config)[1]
    mp = memory_plan(dataset, config, gaussians, texels, device)
    if mp["fits"] or os.environ.get(memory._ENV_SKIP, "") not in ("", "0"):
        return mp
    stage, peak = max(mp["peak_bytes"].items(), key=lambda kv: kv[1])
    name = dict(stage1="the 2DGS stage", texture="the texture stage", eval="evaluation")[stage]
    hint = "; or ".join(mp["fixes"]) or "fewer or smaller images (no flag alone fits)"
    raise memory.NotEnoughMemory(
        f"Not enough memory to train {config.method}: {name} needs about {peak / GB:.1f} GB at its peak "
        f"({gaussians:,} Gaussians, {texels:,} RGBA texels) and {device.name} has {device.memory_bytes / GB:.1f} GB. "
        f"To fit, pass {hint}; or set {memory._ENV_SKIP}=1 to train anyway. "
        "(python -m patexgs_jax.train ... --plan shows the whole plan.)")
