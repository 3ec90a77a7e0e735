"""Data parallelism over training views: a device mesh, shardings, and a sum over sharded views.

A data-parallel training step takes a batch of B views (same image size), renders each one with
the whole scene, and applies one optimiser update with the mean of the B per-view gradients. The
scene, the optimiser state and the densification statistics are replicated on every device; the
views are split along a one-dimensional mesh axis :data:`DATA_AXIS` of D devices (D divides B), so
each device renders B / D views and one all-reduce sums the gradients.

Shapes
  cameras: a :class:`~patexgs_jax.camera.Camera` whose leaves are stacked, ``K`` (B, 3, 3) and
    ``world_to_camera`` (B, 4, 4); ``width`` and ``height`` (static) are shared by the batch
    (:func:`stack_cameras`).
  images: (B, H, W, 3) float32.
  Both are placed with :func:`batch_sharding` (leading axis split over the devices); the state with
  :func:`replicated`.

How a device handles its views
  :func:`sum_over_views` runs the per-view function under :func:`jax.shard_map`: each device walks
  its B / D views with ``lax.scan`` (gradient accumulation, one view's residuals alive at a time),
  adds up their gradients and ``psum``-s the total over the mesh. The renderer is not ``vmap``-ed:
  its tile loops are ``while_loop``-s that stop when a tile's pixels saturate, and a batched loop
  runs every view until the slowest one finishes; a scan keeps each view's early exit, and the
  devices only meet at the one all-reduce.

Running it
  * One host, several GPUs: nothing to set up; ``python -m patexgs_jax.train ... --batch-size 8
    --devices 8`` (``--devices`` defaults to as many local devices as divide the batch). CUDA
    devices are found by JAX; ``CUDA_VISIBLE_DEVICES`` picks which ones.
  * CPU (tests, development): ``--devices 4`` on the command line creates 4 CPU devices (see
    :func:`request_cpu_devices`); in other programs set
    ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` before JAX starts (or
    ``jax.config.update("jax_num_cpu_devices", 4)`` before JAX is first used).
  * Several hosts: every process calls ``jax.distributed.initialize()`` (coordinator address,
    number of processes and process id from the cluster environment - SLURM, Open MPI, TPU pods -
    or passed explicitly) before any other JAX call, then runs the same program, e.g.
    ``python -c "import jax, sys; jax.distributed.initialize(); from patexgs_jax.train import main;
    sys.exit(main(sys.argv[1:]))" --data ... --batch-size 16`` on each host (the training CLI does
    not call it itself). ``jax.devices()`` then lists every host's devices, :func:`data_mesh` spans
    all of them (leave ``--devices`` at its default or the global count), each process loads only
    its share of the step's views (:func:`process_slice`: B / P contiguous views for P processes),
    and :func:`shard_batch` assembles the global batch from those shares
    (``jax.make_array_from_process_local_data``). The replicated state stays identical on every
    host because every host runs the same deterministic host-side code (densification, texture
    growth) on the same all-reduced gradients. (Written to the ``jax.distributed`` contract; only
    single-process runs are tested here.)

Costs to know
  Between steps the state stays replicated, so host-side jitted work on it (capacity counts, the
  Eq. 7 contribution renders, evaluation) runs on every device of the mesh at once: free on GPUs
  (each does the same work in parallel), but forced CPU devices share the cores, so there it costs
  D times the CPU. Every device holds a full copy of the scene and the Adam moments.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from .camera import Camera

#: The mesh axis the batch of views is split along.
DATA_AXIS = "data"


def request_cpu_devices(n: int) -> bool:
    """Asks for ``n`` CPU devices (``jax_num_cpu_devices``), which only works before JAX's backends
    start; returns whether it took effect. Harmless on GPU hosts (the CPU backend is not the
    default there), and a no-op when ``XLA_FLAGS`` already forces a CPU device count."""
    import os

    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return False
    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:  # backends already initialised
        return False
    return True


def num_batch_devices(batch_size: int, devices: int | None = None) -> int:
    """How many devices a batch of ``batch_size`` views is split over.

    Args:
      batch_size: views per step, B >= 1.
      devices: requested device count D (must divide B and be at most ``jax.device_count()``), or
        None: the largest count up to ``jax.device_count()`` that divides B.
    """
    batch_size = int(batch_size)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}.")
    available = jax.device_count()
    if devices is None:
        return max(d for d in range(1, min(batch_size, available) + 1) if batch_size % d == 0)
    devices = int(devices)
    if devices < 1 or devices > available:
        raise ValueError(f"devices={devices} requested but JAX sees {available} device(s); on CPU, set "
                         f"XLA_FLAGS=--xla_force_host_platform_device_count={max(devices, 1)} before JAX starts.")
    if batch_size % devices:
        raise ValueError(f"batch_size {batch_size} is not divisible by devices={devices}; every device "
                         "renders the same number of views.")
    return devices


def data_mesh(num_devices: int | None = None) -> Mesh:
    """A one-dimensional mesh of the first ``num_devices`` devices (all by default), axis
    :data:`DATA_AXIS`."""
    devs = jax.devices()
    n = len(devs) if num_devices is None else int(num_devices)
    if not 1 <= n <= len(devs):
        raise ValueError(f"need 1..{len(devs)} devices, got {n}.")
    return Mesh(np.asarray(devs[:n]), (DATA_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (batch) axis split over :data:`DATA_AXIS`, the rest whole."""
    return NamedSharding(mesh, P(DATA_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    """A full copy on every device of ``mesh``."""
    return NamedSharding(mesh, P())


def replicate(tree, mesh: Mesh):
    """Places every array leaf of ``tree`` on all devices of ``mesh`` (no copy if already there)."""
    return jax.device_put(tree, replicated(mesh))


def shard_batch(tree, mesh: Mesh):
    """Places a batch (leaves with a leading axis B, divisible by the mesh size) split over ``mesh``.

    With one process, ``tree`` holds the whole batch. With several (``jax.distributed``), each
    process passes its own contiguous slice of the batch (B / P views), and the global arrays are
    assembled from those slices.
    """
    sharding = batch_sharding(mesh)
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)
    return jax.tree_util.tree_map(
        lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), tree)


def process_slice(batch_size: int) -> slice:
    """The views of a batch of ``batch_size`` that this process loads: all of them with one
    process, else its contiguous share (B / P views, in process order, the order of
    ``jax.devices()`` and so of :func:`data_mesh`'s devices)."""
    p, i = jax.process_count(), jax.process_index()
    if batch_size % p:
        raise ValueError(f"batch_size {batch_size} is not divisible by the {p} processes.")
    k = batch_size // p
    return slice(i * k, (i + 1) * k)


def stack_cameras(cameras) -> Camera:
    """One :class:`Camera` with ``K`` (B, 3, 3) and ``world_to_camera`` (B, 4, 4) from B cameras
    of the same image size."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("stack_cameras needs at least one camera.")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"a batch of views must share one image size, got {sorted(sizes)}; group the "
                         "views by size or use batch_size 1.")
    return Camera(K=jnp.asarray(np.stack([np.asarray(c.K, np.float32) for c in cameras])),
                  world_to_camera=jnp.asarray(np.stack([np.asarray(c.world_to_camera, np.float32)
                                                        for c in cameras])),
                  width=cameras[0].width, height=cameras[0].height)


def sum_over_views(fn: Callable, mesh: Mesh) -> Callable:
    """Maps ``fn`` over a sharded batch of views, summing one output over all views.

    Args:
      fn: ``fn(shared, view) -> (summand, per_view)`` for ONE view; ``shared`` is replicated
        (e.g. the scene and scalars), ``view`` one element of the batch (e.g. a camera and its
        image); ``summand`` a pytree (e.g. gradients), ``per_view`` a pytree of per-view results.
      mesh: from :func:`data_mesh`.
    Returns:
      ``g(shared, views) -> (total, per_view)`` for use inside ``jax.jit``: ``views`` has leaves
      with a leading axis B (a multiple of the mesh size) sharded by :func:`batch_sharding`;
      ``total`` is the sum of ``summand`` over the B views, replicated; ``per_view`` has leaves
      (B, ...) in batch order, sharded like ``views``. Each device scans its own views in order;
      the per-device totals are combined by one ``psum`` (an all-reduce).
    """

    def local(shared, views):
        first = jax.tree_util.tree_map(lambda x: x[0], views)
        shapes, _ = jax.eval_shape(fn, shared, first)
        zeros = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

        def body(acc, view):
            summand, per_view = fn(shared, view)
            return jax.tree_util.tree_map(jnp.add, acc, summand), per_view

        total, per_view = lax.scan(body, zeros, views)
        return lax.psum(total, DATA_AXIS), per_view

    # check_vma=False: the per-view gradients w.r.t. the replicated inputs are per-device partial
    # sums here, combined by the explicit psum above (not by an implicit transpose of the
    # replication).
    return jax.shard_map(local, mesh=mesh, in_specs=(P(), P(DATA_AXIS)), out_specs=(P(), P(DATA_AXIS)),
                         check_vma=False)
