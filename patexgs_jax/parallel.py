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
  * Several processes (hosts, or one process per GPU): every process runs the same command with
    ``--coordinator HOST:PORT --num-processes N --process-id I`` (or none of them under SLURM's
    ``srun`` or Open MPI's ``mpirun``, whose environment JAX reads); :func:`initialize` joins the
    run before anything else uses JAX. ``jax.devices()`` then lists every process's devices,
    :func:`data_mesh` spans all of them, each process loads only its share of the step's views
    (:func:`process_slice`: the rows of the batch its devices hold) and :func:`shard_batch`
    assembles the global batch from those shares (``jax.make_array_from_process_local_data``).
    Between steps each process keeps its own copy of the state on its own devices
    (:func:`to_local`), so host-side work (densification, texture growth, capacity counts) never
    waits for another process; it gives the same result on every process because every process
    runs the same deterministic code on the same all-reduced gradients, which :func:`check_same`
    verifies at start and at every checkpoint. Only process 0 writes.
    Failures end the run instead of hanging it: :func:`initialize` gives up after its time-out
    (with the reason), a failed cross-process exchange becomes a :class:`DistributedError`
    (:func:`lost_process`), and :func:`end_process` exits without ``jax.distributed``'s shutdown
    barrier, which would wait for the processes that are gone. docs/parallel.md has the table.

Costs to know
  Between steps the state stays replicated, so host-side jitted work on it (capacity counts, the
  Eq. 7 contribution renders, evaluation) runs on every device of the mesh at once: free on GPUs
  (each does the same work in parallel), but forced CPU devices share the cores, so there it costs
  D times the CPU. Every device holds a full copy of the scene and the Adam moments.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import zlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

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
        None: the largest count up to ``jax.device_count()`` that divides B. With several processes
        D is always every device of every process (B must be a multiple of it).
    """
    batch_size = int(batch_size)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}.")
    available = jax.device_count()
    if jax.process_count() > 1:
        # Every process must hold an equal share of the batch: the mesh is all devices of all processes.
        if devices is not None and int(devices) != available:
            raise ValueError(f"devices={devices}, but a run of {jax.process_count()} processes splits the batch "
                             f"over all {available} devices of its processes; leave --devices out.")
        if batch_size % available:
            raise ValueError(f"batch_size {batch_size} is not a multiple of the {available} devices of the "
                             f"{jax.process_count()} processes; every device renders the same number of views.")
        return available
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
    process passes only the rows :func:`process_slice` gives it, and the global arrays are
    assembled from those shares.
    """
    sharding = batch_sharding(mesh)
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)
    return jax.tree_util.tree_map(
        lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), tree)


def process_slice(batch_size: int, mesh: Mesh | None = None) -> slice:
    """The rows of a batch of ``batch_size`` views that this process loads: all of them with one
    process, else the rows that :func:`batch_sharding` puts on this process's devices of ``mesh``
    (default :func:`data_mesh`); one contiguous block of B / P rows for P processes with the same
    number of devices each."""
    if jax.process_count() == 1:
        return slice(0, batch_size)
    mesh = data_mesh() if mesh is None else mesh
    if batch_size % mesh.size:
        raise ValueError(f"batch_size {batch_size} is not divisible by the {mesh.size} devices of the mesh.")
    index = batch_sharding(mesh).addressable_devices_indices_map((batch_size,))
    rows = sorted({r for idx in index.values() if idx is not None for r in range(*idx[0].indices(batch_size))})
    if not rows or rows != list(range(rows[0], rows[-1] + 1)):
        raise ValueError(f"process {jax.process_index()} would hold rows {rows} of the batch; its devices must be "
                         "consecutive in the mesh (build it with data_mesh()).")
    return slice(rows[0], rows[-1] + 1)


def local_mesh(mesh: Mesh) -> Mesh:
    """The devices of ``mesh`` that belong to this process, in mesh order (``mesh`` itself when it
    has no other process's devices)."""
    mine = [d for d in mesh.devices.flat if d.process_index == jax.process_index()]
    if len(mine) == mesh.size:
        return mesh
    if not mine:
        raise ValueError(f"the mesh has no device of process {jax.process_index()}.")
    return Mesh(np.asarray(mine), mesh.axis_names)


def to_global(tree, mesh: Mesh):
    """Replicated arrays on this process's devices -> the same arrays as replicated global arrays over
    ``mesh`` (every process passes its own, identical copy); no data moves. The identity with one
    process. Leaves are placed on :func:`local_mesh` first (a copy only if they are elsewhere)."""
    if jax.process_count() == 1:
        return tree
    local, glob = replicated(local_mesh(mesh)), replicated(mesh)

    def one(x):
        x = jax.device_put(x, local)
        return jax.make_array_from_single_device_arrays(x.shape, glob, [s.data for s in x.addressable_shards])

    return jax.tree_util.tree_map(one, tree)


def to_local(tree, mesh: Mesh):
    """Replicated global arrays over ``mesh`` -> this process's copy, replicated on its devices
    (:func:`local_mesh`); no data moves. The identity with one process."""
    if jax.process_count() == 1:
        return tree
    local = replicated(local_mesh(mesh))

    def one(x):
        if not x.is_fully_replicated:
            raise ValueError(f"to_local takes replicated arrays, got one sharded as {x.sharding}.")
        return jax.make_array_from_single_device_arrays(x.shape, local, [s.data for s in x.addressable_shards])

    return jax.tree_util.tree_map(one, tree)


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


# ------------------------------------------------------------------------------------------------
# Several processes (jax.distributed)
# ------------------------------------------------------------------------------------------------
#: Exit status of a process whose run of several processes could not start or lost a process (2 is
#: kept for bad arguments and data).
EXIT_DISTRIBUTED = 3

#: Seconds to wait for every process to join (and for the others at ``jax.distributed``'s shutdown)
#: before giving up.
DEFAULT_TIMEOUT = 300.0


class DistributedError(RuntimeError):
    """A run of several processes cannot start or continue; the message says why and what to do."""


def is_main_process() -> bool:
    """Whether this process writes the run's outputs (process 0; always with one process)."""
    return jax.process_index() == 0


def launcher_processes() -> int | None:
    """The process count a cluster launcher announces in this process's environment, as JAX reads
    it (SLURM ``srun``: ``SLURM_NTASKS`` within a job step; Open MPI ``mpirun``:
    ``OMPI_COMM_WORLD_SIZE``), or None outside such a launcher."""
    env = os.environ
    for present, count in ((("SLURM_JOB_ID", "SLURM_STEP_NODELIST"), "SLURM_NTASKS"),
                           (("OMPI_COMM_WORLD_RANK",), "OMPI_COMM_WORLD_SIZE")):
        if all(k in env for k in present) and env.get(count, "").isdigit():
            return int(env[count])
    return None


def _parse_address(coordinator: str) -> tuple[str, int]:
    host, sep, port = str(coordinator).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise DistributedError(f"--coordinator must be HOST:PORT (e.g. 10.0.0.1:5432, a free port on process 0's "
                               f"host), got {coordinator!r}.")
    return host.strip("[]"), int(port)


def _reachable(coordinator: str, seconds: float = 3.0) -> bool:
    """Whether something accepts TCP connections at HOST:PORT."""
    try:
        host, port = _parse_address(coordinator)
        with socket.create_connection((host, port), timeout=seconds):
            return True
    except (OSError, DistributedError):
        return False


def _join_failure(coordinator, num_processes, process_id, timeout) -> str:
    n = "all" if num_processes is None else f"all {num_processes}"
    ids = "" if num_processes is None else f" in 0..{num_processes - 1}"
    where = f"at {coordinator}" if coordinator else "at the coordinator the cluster environment names"
    who = "this process" if process_id is None else f"process {process_id}"
    if coordinator and process_id not in (None, 0) and not _reachable(coordinator):
        return (f"{who} could not reach the coordinator at {coordinator} within {timeout:g} s: start process 0 "
                f"with --coordinator {coordinator} (it serves that address), or check that this host reaches it.")
    return (f"{who} waited {timeout:g} s for {n} processes to join the run {where}: start every process with "
            f"the same --coordinator and --num-processes, each with its own --process-id{ids}.")


def _exit_now(message: str | None, code: int = EXIT_DISTRIBUTED) -> None:
    """Prints ``error: message`` (if given) and ends the process at once: no ``jax.distributed``
    shutdown, whose barrier would wait for processes that are gone."""
    try:
        sys.stdout.flush()
        if message is not None:
            sys.stderr.write(f"error: {message}\n")
        sys.stderr.flush()
    finally:
        os._exit(code)


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, timeout: float = DEFAULT_TIMEOUT) -> bool:
    """Joins a run of several processes; call it before anything else uses JAX.

    With none of the three arguments it joins only when a cluster launcher (SLURM ``srun``, Open
    MPI ``mpirun``) started several processes, whose environment then supplies them; arguments
    given override the environment. On CPU the processes' collectives use gloo over TCP.

    Returns:
      True in a run of several processes (``jax.distributed`` initialised, every process's
      devices visible, every process started with the same ``num_processes``); False otherwise
      (nothing done).
    Raises:
      DistributedError: malformed arguments, or processes started with different process counts.
    If not every process has joined after ``timeout`` seconds, the process prints why and exits
    with :data:`EXIT_DISTRIBUTED` (JAX's own time-out would abort the process).
    """
    explicit = any(v is not None for v in (coordinator, num_processes, process_id))
    if not explicit and (launcher_processes() or 1) <= 1:
        return False
    if coordinator is not None:
        _parse_address(coordinator)
    if num_processes is not None and num_processes < 1:
        raise DistributedError(f"--num-processes must be >= 1, got {num_processes}.")
    if process_id is not None and (process_id < 0 or (num_processes is not None and process_id >= num_processes)):
        raise DistributedError(f"--process-id must be in 0..{'N-1' if num_processes is None else num_processes - 1}"
                               f" (one per process), got {process_id}.")
    if timeout <= 0:
        raise DistributedError(f"the distributed time-out must be > 0 seconds, got {timeout}.")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    watchdog = threading.Timer(timeout, lambda: _exit_now(_join_failure(coordinator, num_processes, process_id,
                                                                        timeout)))
    watchdog.daemon = True
    watchdog.start()
    try:
        try:
            # JAX's own connection time-out is longer than the watchdog's: its expiry aborts the process.
            jax.distributed.initialize(coordinator, num_processes, process_id,
                                       initialization_timeout=int(timeout) + 60,
                                       shutdown_timeout_seconds=int(max(timeout, DEFAULT_TIMEOUT)))
        except (ValueError, TypeError, RuntimeError) as e:
            raise DistributedError(f"could not start the run of several processes ({e}); outside SLURM and Open MPI "
                                   "pass --coordinator HOST:PORT --num-processes N --process-id I.") from None
        jax.devices()  # starts the backends: the processes exchange their devices
        wanted = -1 if num_processes is None else int(num_processes)
        counts = process_allgather_ints([wanted])[:, 0]
        if any(c not in (-1, jax.process_count()) for c in counts):
            raise DistributedError(
                "the processes were started with different --num-processes ("
                + ", ".join(f"process {i}: {'from the environment' if c < 0 else int(c)}" for i, c in enumerate(counts))
                + f"; {jax.process_count()} joined); start every process with the same count.")
    finally:
        watchdog.cancel()
    return jax.process_count() > 1


def process_allgather_ints(values) -> np.ndarray:
    """Every process's ``values`` (the same number of int32 on each): (P, K) int32, row p from
    process p. A collective: every process must call it."""
    from jax.experimental import multihost_utils

    local = np.asarray(values, np.int32).reshape(-1)
    if jax.process_count() == 1:
        return local[None]
    try:
        return np.asarray(multihost_utils.process_allgather(local)).reshape(jax.process_count(), -1)
    except Exception as e:  # a failed collective surfaces as XLA's runtime error
        raise lost_process("exchanging values with the other processes", e) from e


def lost_process(during: str, error: BaseException) -> DistributedError:
    """The error for a collective that failed ``during`` something: in a run of several processes
    that almost always means another process stopped (XLA's message, ``error``, says which peer)."""
    text = str(error).strip()
    first = text.splitlines()[0] if text else type(error).__name__
    return DistributedError(f"{during} failed in this run of {jax.process_count()} processes ({first}); another "
                            "process has probably stopped: its output says why. Checkpoints are kept: start all "
                            "processes again with --resume.")


def tree_checksum(tree) -> int:
    """A CRC-32 of the bytes, shapes and dtypes of every array leaf of ``tree`` (this process's copy),
    as a signed 32-bit int (for :func:`check_same`)."""
    crc = 0
    for x in jax.tree_util.tree_leaves(tree):
        a = np.ascontiguousarray(np.asarray(x))
        crc = zlib.crc32(f"{a.dtype}{a.shape}".encode(), crc)
        crc = zlib.crc32(a.tobytes(), crc)
    return crc - (1 << 32) if crc >= 1 << 31 else crc


def check_same(what: str, values) -> None:
    """Raises :class:`DistributedError` unless every process passes the same ``values`` (small ints;
    a collective, every process calls it; nothing with one process)."""
    if jax.process_count() == 1:
        return
    rows = process_allgather_ints(values)
    if np.any(rows != rows[:1]):
        differ = "; ".join(f"process {i}: {r.tolist()}" for i, r in enumerate(rows))
        raise DistributedError(f"the processes disagree on {what} ({differ}).")


def add_cli_arguments(ap) -> None:
    """The command-line flags of a run of several processes (see :func:`initialize_from_args`)."""
    g = ap.add_argument_group("several processes (jax.distributed; omit all under SLURM srun or Open MPI mpirun)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="process 0's address and a free port there; every process passes the same")
    g.add_argument("--num-processes", type=int, default=None, metavar="N", help="processes in the run")
    g.add_argument("--process-id", type=int, default=None, metavar="I", help="this process, 0..N-1")
    g.add_argument("--distributed-timeout", type=float, default=DEFAULT_TIMEOUT, metavar="SECONDS",
                   help=f"give up when not every process has joined after this long (default {DEFAULT_TIMEOUT:g})")


def initialize_from_args(args) -> bool:
    """:func:`initialize` from :func:`add_cli_arguments`' flags."""
    return initialize(args.coordinator, args.num_processes, args.process_id, timeout=args.distributed_timeout)


#: What a command line reports as one ``error:`` line and exit status 2 instead of a traceback: bad
#: arguments or data, an output that cannot be written, not enough memory.
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileExistsError, OSError, MemoryError)


def run_cli(args, body: Callable[..., int | None], user_errors: tuple[type[BaseException], ...] = ()) -> int:
    """A command line's run with :func:`add_cli_arguments`' flags parsed into ``args``: joins the
    processes, creates ``args.devices`` CPU devices in a single process, runs ``body(args)`` and
    returns its exit code (None counts as 0).

    Errors become exit codes: a :class:`DistributedError` one ``error:`` line and
    :data:`EXIT_DISTRIBUTED`; :data:`USER_ERRORS` and ``user_errors`` one ``error:`` line and 2;
    anything else is raised in a single process, and in a process of several printed with its
    traceback and 1. A process of several that fails ends at once (:func:`end_process`)."""
    try:
        several = initialize_from_args(args)
    except DistributedError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_DISTRIBUTED
    if args.devices is not None and not several:
        request_cpu_devices(args.devices)
    try:
        code = body(args) or 0
    except DistributedError as e:
        print(f"error: {e}", file=sys.stderr)
        code = EXIT_DISTRIBUTED
    except USER_ERRORS + tuple(user_errors) as e:
        print(f"error: {e}", file=sys.stderr)
        code = 2
    except BaseException:
        if not several:
            raise
        import traceback

        traceback.print_exc()  # an unexpected error: its traceback, then this process ends (no hang)
        code = 1
    if several and code != 0:
        end_process(code)  # the message is out; skip the shutdown barrier (see end_process)
    return code


def end_process(code: int, message: str | None = None) -> None:
    """Ends a process of a run of several processes after an error: prints ``error: message`` (if
    given) and exits at once with ``code``, without the ``jax.distributed`` shutdown barrier (which
    would wait for processes that may be gone). Does nothing outside ``jax.distributed``."""
    if jax.distributed.is_initialized():
        _exit_now(message, code)
