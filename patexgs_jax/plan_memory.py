"""The run plan's memory model (:mod:`patexgs_jax.plan`; docs/memory.md has its terms and its
measured error): the peak of the 2DGS stage, the texture stage and evaluation on a device, and the
flags that make a run fit where it does not.

  peak = base + per-pixel bytes x padded pixels of the largest view + per-Gaussian bytes x
         Gaussians + texture bytes x RGBA texels (+ on a CPU, the images the dataset caches)
"""

from __future__ import annotations

import math
import os

from . import memory
from .padding import padded_shape
from .plan_devices import GB, Device
from .rendering import tiling

__all__ = ["CPU_BASE_BYTES", "CPU_SIZE_BYTES", "EVAL_PIXEL_SHARE", "GPU_BASE_BYTES", "GPU_BYTES_PER_GAUSSIAN",
           "GPU_BYTES_PER_PIXEL", "GPU_BYTES_PER_TEXEL", "TEXTURE_HEADROOM", "fixes", "gaussian_bytes", "memory_plan",
           "padded_pixels", "padded_sizes", "pixel_bytes", "stage_peaks", "texture_bytes"]

#: GPU bytes besides the per-pixel, per-Gaussian and texture arrays: the images of a step on the
#: device, the compiled programs' constants and small buffers (counted, not calibrated).
GPU_BASE_BYTES = 256 * 2**20
#: Per-pixel bytes on a GPU besides the compositor's working memory: the CPU figure less the host
#: copies of the image (counted).
GPU_BYTES_PER_PIXEL = memory.BYTES_PER_PIXEL - 24.0
#: An evaluation render keeps no cotangents: its per-pixel arrays are about half a training step's.
EVAL_PIXEL_SHARE = 0.5
#: CPU resident memory of a run besides its per-pixel, per-Gaussian, texture and image terms, per stage,
#: for a run that compiles its programs itself (the first run of a command line: XLA's compiler
#: works in the process, so a run whose programs all come from the compilation cache peaks lower,
#: 620 against 980 MiB for the embedded scene's 2DGS stage). Calibrated on the embedded scene's
#: runs of ``experiments.plan_check`` in empty caches (docs/memory.md, "Measured error (CPU)"):
#: the runtime and the 2DGS step's compiles (``stage1``); a textured run's 2DGS stage also compiles
#: the texture stage's first step ahead, in the background (``stage1_textured``); the texture
#: stage's is mostly the compiled code it keeps (its start, Eq. 7's counter and renderer, the step
#: of each layout growth makes). Evaluation's peak is the training peak.
CPU_BASE_BYTES = dict(stage1=960 * 2**20, stage1_textured=1360 * 2**20, texture=2000 * 2**20)
#: CPU bytes each padded size of the training views past the first adds to a textured run's stages
#: (the bases above are one size's): the programs compiled for each size stay resident, Eq. 7's pair
#: counter and renderer compiled ahead in the 2DGS stage (``stage1_textured``), the textured step
#: and Eq. 7's programs of each size in the texture stage (``texture``). Calibrated on beer at 1/4
#: (three padded sizes; benchmarks/plan_check_cpu_idle_cold_2f15410.json, the calibration row,
#: docs/memory.md): its peaks above the one-size bases' 2,111 - 1,422 MiB (2DGS stage) and 2,717 -
#: 2,066 MiB (texture stage), over its two more sizes. An untextured run keeps its bases (beer at 1/4
#: in ``2dgs``, the same three sizes: its 2DGS peak 7% above the base's, within the noise).
CPU_SIZE_BYTES = dict(stage1=0, stage1_textured=340 * 2**20, texture=320 * 2**20)


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
                image_bytes: int = 0, sizes: int = 1) -> dict[str, int]:
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
      sizes: CPU only: the training views' padded sizes (:data:`CPU_SIZE_BYTES` for each past the first).
    Returns:
      ``{"stage1", "texture", "eval"}`` in bytes (``texture`` 0 without a texture stage).
    """
    g = gaussian_bytes(gaussians)
    tex = texture_bytes(rgba_texels, mip=mip)
    if kind == "cpu":
        px = pixel_bytes(train_pixels, "cpu")
        more = max(int(sizes) - 1, 0)
        key = "stage1_textured" if textured else "stage1"
        s1 = CPU_BASE_BYTES[key] + more * CPU_SIZE_BYTES[key] + px + g + image_bytes
        s2 = (CPU_BASE_BYTES["texture"] + more * CPU_SIZE_BYTES["texture"] + px + g + tex + image_bytes
              if textured else 0.0)
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
                           textured=textured, mip=mip, device_bytes=device.memory_bytes, image_bytes=images,
                           sizes=padded_sizes(sizes_))

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


def padded_sizes(sizes) -> int:
    """How many padded sizes views of these (width, height) ``sizes`` have (each compiles its
    programs: :mod:`patexgs_jax.padding`)."""
    return len({padded_shape(h, w) for w, h in sizes})


def memory_plan(dataset, config, gaussians: int, rgba_texels: int, device: Device, image_bytes: int) -> dict:
    """This run's peaks on ``device`` and whether they fit: ``{"device", "kind", "memory_bytes",
    "peak_bytes", "fits", "fixes"}`` (bytes). ``image_bytes``: the decoded images the dataset may
    hold (:func:`patexgs_jax.memory.cached_image_bytes`), counted on a CPU, whose memory they share."""
    spec = config.spec
    tests = list(getattr(dataset, "test_views", ()))
    sizes = [(v.camera.width, v.camera.height) for v in dataset.train_views]
    evals = [(v.camera.width, v.camera.height) for v in tests + list(dataset.train_views)[:32]]
    train_px = max(padded_pixels(w, h) for w, h in sizes)
    eval_px = max(padded_pixels(w, h) for w, h in evals)
    images = image_bytes if device.kind == "cpu" else 0
    textured = spec.textures is not None
    mip = spec.mip != "none"
    peaks = stage_peaks(device.kind, train_pixels=train_px, eval_pixels=eval_px, gaussians=gaussians,
                        rgba_texels=rgba_texels, textured=textured, mip=mip, device_bytes=device.memory_bytes,
                        image_bytes=images, sizes=padded_sizes(sizes))
    fits = max(peaks.values()) <= device.memory_bytes
    advice = fixes(device, peaks, sizes=sizes, factor=float(getattr(dataset, "factor", 1) or 1), gaussians=gaussians,
                   rgba_texels=rgba_texels, textured=textured, mip=mip, image_bytes=images, eval_pixels=eval_px)
    return dict(device=device.name, kind=device.kind, memory_bytes=int(device.memory_bytes), peak_bytes=peaks,
                fits=bool(fits), fixes=advice)
