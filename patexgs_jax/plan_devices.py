"""The devices a run plan is made for (:mod:`patexgs_jax.plan`): this process's, the ones
``--plan-device`` names, and a memory size in bytes."""

from __future__ import annotations

import dataclasses
import re

from . import memory
from .rendering import tiling

__all__ = ["DEVICES", "GB", "GPU_MEMORY_SHARE", "H100_STEPS", "Device", "StepTimes", "h100_run_seconds",
           "parse_device", "this_device"]

GB = 1e9
#: The share of a GPU's memory JAX's allocator takes by default (``XLA_PYTHON_CLIENT_MEM_FRACTION``).
GPU_MEMORY_SHARE = 0.75


@dataclasses.dataclass(frozen=True)
class Device:
    """A device a run may train on.

    Attributes:
      name: what the plan calls it.
      kind: ``"cpu"`` (the model of the process's resident memory) or ``"gpu"`` (device memory).
      memory_bytes: the memory the run may use (bytes): on a GPU what JAX's allocator gets, on a CPU
        the memory available to the process (its resident memory included).
    """

    name: str
    kind: str
    memory_bytes: int


#: The devices ``--plan-device`` names: two GPUs (JAX's default 75% of their memory) and a CPU.
DEVICES = {
    "h100-80gb": Device("h100-80gb (NVIDIA H100, 80 GB; JAX's default 75%)", "gpu", int(GPU_MEMORY_SHARE * 80 * GB)),
    "rtx4090-24gb": Device("rtx4090-24gb (NVIDIA RTX 4090, 24 GB; JAX's default 75%)", "gpu",
                           int(GPU_MEMORY_SHARE * 24 * GB)),
    "cpu-24gb": Device("cpu-24gb (a CPU with 24 GB available)", "cpu", int(24 * GB)),
}

_UNITS = {"": 1, "b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "tb": 1e12, "kib": 2**10, "mib": 2**20, "gib": 2**30,
          "tib": 2**40}


def parse_device(text: str) -> Device:
    """A :data:`DEVICES` name, or a byte figure (``24e9``, ``24GB``, ``80GiB``, ``25769803776``; a GPU's
    memory as JAX's allocator gets it). Raises ValueError naming the accepted forms."""
    key = text.strip().lower()
    if key in DEVICES:
        return DEVICES[key]
    m = re.fullmatch(r"(gpu:|cpu:)?\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([kmgt]i?b|b)?", key)
    if not m or float(m.group(2)) <= 0:
        raise ValueError(f"--plan-device {text!r}: give one of {', '.join(DEVICES)} or a memory size in bytes "
                         f"(e.g. 24e9, 24GB, 80GiB; prefix cpu: for a CPU's memory, default a GPU's).")
    size = int(float(m.group(2)) * _UNITS[m.group(3) or ""])
    kind = "cpu" if m.group(1) == "cpu:" else "gpu"
    return Device(f"{kind} with {size / GB:.3g} GB", kind, size)


def this_device() -> Device:
    """This process's device: the default backend's first device and the memory it may use
    (a GPU's allocator limit; on a CPU the memory available plus this process's resident memory)."""
    import jax

    if jax.default_backend() == "cpu":
        avail = memory.available_bytes()
        total = (avail if avail is not None else 1 << 62) + memory._resident_bytes()
        return Device(f"this CPU ({total / GB:.1f} GB available)", "cpu", int(total))
    dev = jax.devices()[0]
    limit = tiling.device_memory(dev) or tiling.DEFAULT_DEVICE_MEMORY
    return Device(f"this {dev.device_kind} ({limit / GB:.1f} GB for JAX)", "gpu", int(limit))


@dataclasses.dataclass(frozen=True)
class StepTimes:
    """Training steps measured on one device: seconds of a steady step of each stage at two Gaussian
    counts, and of the first step (compiling it).

    Attributes:
      size: the views' (width, height).
      gaussians: the two counts.
      stage1, texture: seconds of a 2DGS and of a textured step (at Eq. 7's allocation) at each count.
      first_stage1, first_texture: seconds of the first step of each.
      source: the measurements' file.
    """

    size: tuple[int, int]
    gaussians: tuple[int, int]
    stage1: tuple[float, float]
    texture: tuple[float, float]
    first_stage1: float
    first_texture: float
    source: str


#: One NVIDIA H100 80GB (``experiments.bench_scale``, 1237 x 822 views, jax 0.11.2).
H100_STEPS = StepTimes(size=(1237, 822), gaussians=(1_000_000, 3_000_000), stage1=(0.0438, 0.0922),
                       texture=(0.0889, 0.2100), first_stage1=7.5, first_texture=21.2,
                       source="benchmarks/bench_scale_h100_{1m,3m}_43b446a.json")


def _h100_step(stage: str, gaussians: float, pixels: int) -> float:
    """Seconds of one steady step of ``stage`` on the H100: the line through the two measured
    counts (its value at 0 Gaussians kept as the least), scaled by the pixels where the views are
    larger than the measured ones (smaller views are not scaled down: the figure is then a bound)."""
    (n0, n1), (t0, t1) = H100_STEPS.gaussians, getattr(H100_STEPS, stage)
    slope = (t1 - t0) / (n1 - n0)
    t = max(t0 + slope * (float(gaussians) - n0), t0 - slope * n0)
    w, h = H100_STEPS.size
    return t * max(1.0, pixels / float(w * h))


def h100_run_seconds(*, steps1: int, stage1_gaussians: int, steps2: int, gaussians: int, pixels: int,
                     sizes: int = 1) -> dict:
    """The run's time on one H100 from :data:`H100_STEPS`: ``{"stage1", "texture", "compile",
    "total"}`` in seconds.

    Args:
      steps1, steps2: steps of the 2DGS and the texture stage.
      stage1_gaussians: the 2DGS stage's mean active Gaussians; ``gaussians``: the texture stage's.
      pixels: the largest training view's pixels.
      sizes: the training views' padded sizes (each compiles its steps).
    """
    t1 = steps1 * _h100_step("stage1", stage1_gaussians, pixels)
    t2 = steps2 * _h100_step("texture", gaussians, pixels) if steps2 else 0.0
    comp = sizes * (H100_STEPS.first_stage1 + (2 * H100_STEPS.first_texture if steps2 else 0.0))
    return dict(stage1=t1, texture=t2, compile=comp, total=t1 + t2 + comp)
