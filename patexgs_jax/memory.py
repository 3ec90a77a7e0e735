"""The training step's memory: an estimate from the image size, and a check before training.

On the CPU backend every array of the step lives in the process's resident memory, and a step
that does not fit is killed by the kernel's out-of-memory killer without a message. So, before
training, :func:`check_training_memory` compares an estimate of the run's peak resident memory
(:func:`estimate_step_bytes`) and of the images its dataset may cache with the memory the
machine has available (:func:`available_bytes`: ``MemAvailable``, and the cgroup's limit when one
is set), and stops with :class:`NotEnoughMemory` naming the image size and the ``--factor`` that
would fit.

The estimate is linear in the step's padded pixel count and the Gaussian count, calibrated on
``python -m experiments.bench_train --memory`` (peak ``ru_maxrss`` of fresh processes at 1, 4
and 12 MP, with 2DGS and with 8x8 RGBA textures + mipmaps; the figures and the estimate's error
are in docs/performance.md). Set ``PATEXGS_SKIP_MEMORY_CHECK=1`` to train anyway.
"""

from __future__ import annotations

import dataclasses
import os

__all__ = [
    "NotEnoughMemory",
    "MemoryPlan",
    "estimate_step_bytes",
    "available_bytes",
    "plan_training_memory",
    "check_training_memory",
    "cached_image_bytes",
]

GiB = float(1 << 30)

#: Resident memory of a training process besides its per-pixel and per-Gaussian arrays (the
#: Python and JAX runtime, compiling the step, one strip of the loss's filters), without and with
#: textures.
BASE_BYTES = {False: 1.2 * GiB, True: 1.37 * GiB}
#: Bytes per padded pixel of the largest training view: the render's per-tile accumulators and
#: their cotangents, its per-pixel outputs, the loss's per-pixel terms and gradients, the image on
#: the host and on the device.
BYTES_PER_PIXEL = 190.0
#: Bytes per Gaussian slot: parameters, gradients, two Adam moments and the updated copy (about
#: 60 floats each with SH degree 3), the projection's per-splat rows and their cotangents, the
#: densification statistics. Counted, not calibrated: the measurements hold 4,000 Gaussians.
BYTES_PER_GAUSSIAN = 2_000.0
#: The estimate's error on the calibration cases (two runs of six): 0.3% to 11% over the measured
#: peak, never under.
RELATIVE_ERROR = 0.11

_ENV_SKIP = "PATEXGS_SKIP_MEMORY_CHECK"


class NotEnoughMemory(MemoryError):
    """Training would not fit in the memory available; the message names the size and a factor."""


def estimate_step_bytes(width: int, height: int, gaussians: int, textured: bool = False,
                        tile_size: int = 16) -> int:
    """Estimated peak resident memory (bytes) of a training process on the CPU backend.

    Args:
      width, height: the largest training image (padded to whole ``tile_size`` tiles, as the step).
      gaussians: Gaussian slots (the scene's capacity, or the run's cap on the count).
      textured: RGBA textures and mipmaps (stage 2 of the textured methods).
    Returns:
      bytes; the images the dataset caches are not included (see :func:`plan_training_memory`).
    """
    pixels = (-(-int(width) // tile_size) * tile_size) * (-(-int(height) // tile_size) * tile_size)
    return int(BASE_BYTES[bool(textured)] + BYTES_PER_PIXEL * pixels + BYTES_PER_GAUSSIAN * int(gaussians))


def _read_int(path: str) -> int | None:
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_room() -> int | None:
    """Bytes the process's cgroup may still allocate (its limit minus its usage), or None without a
    limit. cgroup v2 (memory.max / memory.current), else v1 (memory.limit_in_bytes / usage)."""
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        limit = _read_int(limit_file)  # "max" (v2, no limit) is not a number
        if limit is None or limit >= 1 << 60:  # v1 writes a huge number for "no limit"
            continue
        usage = _read_int(usage_file) or 0
        return max(limit - usage, 0)
    return None


def available_bytes() -> int | None:
    """Memory a new allocation can take without swapping or an OOM kill: ``MemAvailable`` of
    /proc/meminfo, or less when the process's cgroup limit leaves less. None when unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    room = _cgroup_room()
    if room is not None:
        avail = room if avail is None else min(avail, room)
    return avail


def _resident_bytes() -> int:
    """This process's resident memory now (bytes)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0


@dataclasses.dataclass(frozen=True)
class MemoryPlan:
    """What a run needs against what the machine has (bytes).

    Attributes:
      width, height: the largest training image.
      step: :func:`estimate_step_bytes` of it.
      images: the most the dataset's image cache may hold (its bounds, or all training images).
      resident: the process's resident memory now (already counted in ``available``).
      available: :func:`available_bytes`, None when unknown.
    """

    width: int
    height: int
    step: int
    images: int
    resident: int
    available: int | None

    @property
    def needed(self) -> int:
        """More memory the run needs than it holds now."""
        return max(self.step + self.images - self.resident, 0)

    @property
    def fits(self) -> bool:
        return self.available is None or self.needed <= self.available


def _cache_bytes(cache, image_bytes: int, num_images: int) -> int:
    count = num_images if cache is None else min(num_images, cache.maxsize)
    total = count * image_bytes
    if cache is not None and cache.max_bytes is not None:
        total = min(total, cache.max_bytes)
    return total


def cached_image_bytes(dataset) -> int:
    """Bytes of decoded images ``dataset`` may hold during a run: its training and test views
    (float32 RGB at the largest training view's size), within its image cache's bounds."""
    views = list(dataset.train_views)
    w, h = max(((v.camera.width, v.camera.height) for v in views), key=lambda s: s[0] * s[1])
    count = len(views) + len(getattr(dataset, "test_views", ()))
    return _cache_bytes(getattr(dataset, "image_cache", None), w * h * 12, count)


def plan_training_memory(sizes, gaussians: int, textured: bool, cache=None,
                         available: int | None = None) -> MemoryPlan:
    """The memory plan of training on images of ``sizes`` ((width, height) each).

    Args:
      sizes: the training images' sizes.
      gaussians: Gaussian slots (see :func:`estimate_step_bytes`).
      textured: whether the run renders textures.
      cache: the dataset's :class:`patexgs_jax.data.ImageCache` (its bounds limit the images held).
      available: bytes available (default :func:`available_bytes`).
    """
    sizes = [(int(w), int(h)) for w, h in sizes]
    w, h = max(sizes, key=lambda s: s[0] * s[1])
    step = estimate_step_bytes(w, h, gaussians, textured)
    images = _cache_bytes(cache, w * h * 3 * 4, len(sizes))
    return MemoryPlan(width=w, height=h, step=step, images=images, resident=_resident_bytes(),
                      available=available_bytes() if available is None else available)


def _gb(b: float) -> str:
    return f"{b / 1e9:.1f} GB"


def check_training_memory(dataset, gaussians: int, textured: bool, available: int | None = None) -> MemoryPlan:
    """Raises :class:`NotEnoughMemory` when training on ``dataset`` would not fit in memory.

    Only the CPU backend is checked (on an accelerator the step's arrays live in device memory);
    ``PATEXGS_SKIP_MEMORY_CHECK=1`` skips the check.

    Args:
      dataset: a :class:`patexgs_jax.data.Dataset` (its training views' sizes, its image cache and
        the factor it was loaded with, to suggest one that fits).
      gaussians, textured: see :func:`estimate_step_bytes`.
      available: bytes available (default :func:`available_bytes`).
    Returns:
      the :class:`MemoryPlan` (also when the check is skipped).
    Raises:
      NotEnoughMemory: with the image size, the estimate, the memory available and the smallest
        ``--factor`` whose images would fit.
    """
    import jax

    views = list(dataset.train_views)
    cache = getattr(dataset, "image_cache", None)
    sizes = [(v.camera.width, v.camera.height) for v in views]
    plan = plan_training_memory(sizes, gaussians, textured, cache, available)
    if plan.fits or os.environ.get(_ENV_SKIP, "") not in ("", "0") or jax.default_backend() != "cpu":
        return plan
    loaded = float(getattr(dataset, "factor", 1) or 1)
    full_w, full_h = round(plan.width * loaded), round(plan.height * loaded)
    hint = "no --factor up to 32 would fit either: free memory first"
    for f in range(2, 33):
        if f <= loaded:
            continue
        shrunk = [(max(round(w * loaded) // f, 1), max(round(h * loaded) // f, 1)) for w, h in sizes]
        smaller = plan_training_memory(shrunk, gaussians, textured, cache, plan.available)
        if smaller.fits:
            hint = (f"pass --factor {f} (load(..., factor={f})): {smaller.width}x{smaller.height} images need "
                    f"about {_gb(smaller.step + smaller.images)}")
            break
    cached = f" and up to {_gb(plan.images)} of cached images" if plan.images else ""
    full = f" (the images are {full_w}x{full_h} at full size)" if loaded > 1 else ""
    raise NotEnoughMemory(
        f"Not enough memory to train at {plan.width}x{plan.height}{full}: the training step needs about "
        f"{_gb(plan.step)} (estimate, within about {RELATIVE_ERROR:.0%}){cached}, {_gb(plan.needed)} more than "
        f"this process holds, and {_gb(plan.available or 0)} is available (MemAvailable, or the cgroup's limit). "
        f"To fit, {hint}; or set {_ENV_SKIP}=1 to train anyway.")
