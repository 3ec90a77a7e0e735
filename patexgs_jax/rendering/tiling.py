"""How many tiles the compositor advances at once (``RenderConfig.tile_batch``), chosen per device.

The compositor walks tiles in batches of B (:mod:`.chunks`): a loop over batches, and within a
batch a loop over chunks of splats until the batch's slowest tile is done. The best B depends on
the device:

  * On a CPU, small batches: the per-pair blocks of a batch stay in cache, and a loop iteration
    costs little. :data:`CPU_TILE_BATCH` (8) is the measured best on a 2-core machine
    (docs/performance.md).
  * On a GPU (or TPU), every loop iteration is a kernel launch and a synchronisation: small
    batches leave most of the device idle (docs/performance.md has the A/B on an H100). There B is
    as large as memory allows: every tile of the image when the batch's working memory fits
    :data:`MEMORY_SHARE` of the device's memory, else the largest batch that fits.

Memory bound: a batch's forward and backward keep about :data:`PAIR_BYTES` bytes per (tile, pixel,
chunk slot) of working memory, so a batch needs ``B * tile_size**2 * chunk * PAIR_BYTES`` bytes.
:data:`PAIR_BYTES` is above the largest slope measured (XLA's memory analysis of the compiled
forward and backward of trilinear mipmaps with the prefilter, the heaviest configuration, in
docs/performance.md; tests/integration/test_device_tiling.py measures it again).

``RenderConfig(tile_batch=N)`` fixes B; the environment variable ``PATEXGS_TILE_BATCH`` sets it
for every render whose config leaves it to the device (None, the default).
"""

from __future__ import annotations

import os

import jax

__all__ = ["CPU_TILE_BATCH", "DEFAULT_DEVICE_MEMORY", "ENV_TILE_BATCH", "MEMORY_SHARE", "PAIR_BYTES",
           "choose_tile_batch", "device_memory", "resolve_tile_batch"]

#: Tiles a batch on a CPU.
CPU_TILE_BATCH = 8
#: Working memory of the forward and backward per (tile, pixel, chunk slot), bytes (an upper bound).
PAIR_BYTES = 128
#: The share of the device's memory one render's tile batch may use: the rest holds the scene, its
#: gradients and optimizer state, the images, and the other programs of a training step.
MEMORY_SHARE = 0.25
#: The memory assumed for an accelerator that does not report it (bytes).
DEFAULT_DEVICE_MEMORY = 8 << 30
#: The environment variable that fixes the tile batch of renders that leave it to the device.
ENV_TILE_BATCH = "PATEXGS_TILE_BATCH"


def device_memory(device=None) -> int | None:
    """The memory (bytes) the allocator of ``device`` (default: the first device of the default
    backend) may use, or None where the device does not say (a CPU)."""
    device = device or jax.devices()[0]
    try:
        stats = device.memory_stats()
    except Exception:  # backends without allocator statistics raise (or return None)
        return None
    if not stats:
        return None
    limit = stats.get("bytes_limit") or stats.get("bytes_reservable_limit")
    return int(limit) if limit else None


def choose_tile_batch(num_tiles: int, *, backend: str, tile_size: int, chunk: int,
                      memory_bytes: int | None = None) -> int:
    """The tiles a batch for an image of ``num_tiles`` tiles on ``backend`` ("cpu", "gpu", "cuda",
    "rocm", "tpu", ...), the rule of the module docstring.

    Args:
      memory_bytes: the device's memory (:func:`device_memory`); None: :data:`DEFAULT_DEVICE_MEMORY`.
    Returns:
      B in [1, num_tiles] (at most :data:`CPU_TILE_BATCH` on a CPU).
    """
    num_tiles = max(1, int(num_tiles))
    if backend == "cpu":
        return min(CPU_TILE_BATCH, num_tiles)
    memory = DEFAULT_DEVICE_MEMORY if memory_bytes is None else int(memory_bytes)
    per_tile = tile_size * tile_size * chunk * PAIR_BYTES
    return max(1, min(num_tiles, int(MEMORY_SHARE * memory) // per_tile))


def resolve_tile_batch(tile_batch: int | None, num_tiles: int, *, tile_size: int, chunk: int,
                       backend: str | None = None) -> int:
    """``tile_batch`` if it is set, else ``$PATEXGS_TILE_BATCH`` if that is set, else
    :func:`choose_tile_batch` for the default backend (called at trace time: the result is static)."""
    if tile_batch is not None:
        return int(tile_batch)
    env = os.environ.get(ENV_TILE_BATCH, "").strip()
    if env:
        try:
            value = int(env)
        except ValueError:
            value = 0
        if value < 1:
            raise ValueError(f"{ENV_TILE_BATCH}={env!r}: a positive number of tiles is expected "
                             f"(unset it to let the device choose).")
        return value
    backend = backend or jax.default_backend()
    memory = None if backend == "cpu" else device_memory()
    return choose_tile_batch(num_tiles, backend=backend, tile_size=tile_size, chunk=chunk, memory_bytes=memory)
