"""Every host-side stage of a paper-length run at the paper's scale, timed one by one.

    python -m experiments.bench_scale --gaussians 1000000 [--width 1237 --height 822] [--views 4]
                                      [--eq7-views 200] [--steps 2] [--skip step,eval] [--json FILE]

Builds a paper-scale state without training it and times each stage of a run on it, one row each:

* the state: ``--gaussians`` N 2D splats (SH degree 3) spread uniformly through the embedded
  synthetic scene's box, with scales shrinking as N^-1/2 so that a pixel sees about the same depth
  of overlapping splats at any N (:data:`DEPTH`), opacities as after an opacity reset's recovery;
  RGBA textures whose sides follow the distribution Eq. 7 and Eqs. 8-10 gave a real run
  (:data:`SIDE_HISTOGRAM`: ``patexgs`` on the capture ``beer``, ``benchmarks/tables_beer.json``),
  with Adam moments; ``--views`` V cameras of W x H around the scene (the synthetic scene's rig)
  with smooth synthetic images (only their size matters).
* ``eq6_counts``: the Eq. 6 contribution counts of V views (renders: ``host`` false).
* ``eq7_allocation``: Eq. 7 from the counts of ``--eq7-views`` views (the V rendered ones repeated
  with their columns permuted, so that the host work is that of a capture of that many views), kept
  sparse as a run keeps them, sigma from the pixel share; ``eq7_budget_solve``: sigma solved for a
  texel budget (the real run's texels a Gaussian).
* ``textures_start``: stage 2's first textures (:func:`~patexgs_jax.textures.rebucket.add_textures`).
* ``eq8_10_growth``: one growth event's selection (Eqs. 8-10) from a gradient statistic, and
  ``rebucket``: re-bucketing the grown textures with their Adam moments, in place, as the schedule
  does (its programs compiled in the background since the allocation's re-bucketing made the
  layout); ``rebucket_again``: a second event; ``rebucket_overflow``: an event that overflows a
  bucket (one more texture grows into it than it has free slots), so that every bucket is sized
  afresh and the step would recompile. ``--rebucket-path host`` makes these re-bucketings' (and the
  allocation's) buckets on the host instead (``resize_textures(on_device=False)``: the reference, the same result).
* ``densify``: one densification step's bookkeeping (clone, split, prune; moments moved), on a
  copy of the state that it donates, as the trainer does (the first call compiles its row writes);
  ``densify_again``: a second event on its result (nothing to compile).
* ``checkpoint_save`` / ``checkpoint_load``: the trainer's checkpoint of this state.
* ``checkpoint_save_async_first``: the same checkpoint through
  :class:`~patexgs_jax.checkpoint_writer.CheckpointWriter`, until its first ``save`` returns (the
  arrays copied to the host, into fresh memory: what the training thread waits for);
  ``checkpoint_save_async``: the writer's second save, into the first's buffers (a run's 2nd-30th);
  ``checkpoint_save_async_total``: that save until ``wait`` returns (the whole write; its CPU time
  counts the writer's thread).
* ``ply_export`` / ``ply_load``: the PLY and its texture sidecar.
* ``eval_render_1/2/4/8``: one view rendered at full size and zoomed out by 2, 4, 8 (renders).
* ``train_step_2dgs`` / ``train_step_textured``: one training step (forward + backward + Adam
  update) through the real trainer, its steady-state time (median of ``--steps`` after a first
  that compiles) and peak memory, each in a fresh process (so that the peaks are the step's own:
  the state, the step's buffers and compilation; ``process_seconds``: that process's whole time).

Each row: ``event``, ``gaussians``, ``seconds``, ``cpu_seconds`` (the process's CPU time over the row,
every thread's: what a loaded machine stretches less), ``host`` (true for host-side work), ``peak_rss_bytes``
(the process's resident-memory high-water mark during that row, Linux's VmHWM reset before it) and,
on a GPU, ``device_peak_bytes`` (JAX's peak bytes in use so far: a running maximum). Host rows are
timed once (they are seconds, not milliseconds; the first call of a jitted helper counts its
compile, as in a run). Results go to ``--json``: the provenance header (:mod:`experiments.provenance`),
``config`` and ``rows``, rewritten after every row.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

from experiments.bench_train import _high_water_bytes
from experiments.provenance import header, write_json

SCHEMA = 1

#: Final texture sides of ``patexgs`` on the capture ``beer`` (``--factor 4 --preset cpu``,
#: benchmarks/tables_beer.json, ``sides_final``): side -> Gaussians. 85% keep 1 x 1, 0.7% reach 32.
SIDE_HISTOGRAM = {1: 5020, 2: 542, 3: 77, 4: 46, 5: 20, 6: 21, 7: 15, 8: 15, 9: 9, 10: 10, 11: 7, 12: 10,
                  13: 6, 14: 5, 15: 4, 16: 5, 17: 2, 18: 4, 19: 6, 20: 2, 21: 2, 22: 2, 23: 4, 24: 3, 26: 1,
                  27: 1, 28: 1, 30: 2, 32: 44}
#: Mean depth of overlapping splats (within their 3-sigma extent) along a ray through the box.
DEPTH = 24.0
#: Half-side of the box the splats fill, around the synthetic scene's centre.
EXTENT = 1.2
#: Slots beyond N: densification's clones and splits fit without doubling the capacity.
CAPACITY_HEADROOM = 1.1
#: Share of the active Gaussians above the densification threshold (cloned or split).
DENSIFY_SHARE = 0.02


# ---------------------------------------------------------------------------------------------
# Memory readings (Linux)
# ---------------------------------------------------------------------------------------------
def _device_peak() -> int | None:
    import jax

    stats = jax.devices()[0].memory_stats()
    return None if not stats else int(stats.get("peak_bytes_in_use", 0))


class Rows:
    """Collects rows; :meth:`time` runs a block as one row."""

    def __init__(self, gaussians: int, say, on_row=lambda rows: None):
        self.rows: list[dict] = []
        self.gaussians = gaussians
        self.say, self.on_row = say, on_row

    @contextlib.contextmanager
    def time(self, event: str, host: bool, **extra):
        gc.collect()
        _high_water_bytes(reset=True)
        t0, c0 = time.perf_counter(), time.process_time()
        note: dict = {}
        yield note
        seconds = time.perf_counter() - t0
        cpu = time.process_time() - c0
        row = dict(event=event, gaussians=self.gaussians, seconds=seconds, cpu_seconds=cpu, host=host,
                   peak_rss_bytes=_high_water_bytes(), device_peak_bytes=_device_peak(), **extra, **note)
        self.rows.append(row)
        self.say(f"{event:<22} {seconds:9.3f} s (CPU {cpu:7.3f} s)  peak RSS {row['peak_rss_bytes'] / 2**30:6.2f} GiB"
                 + ("" if row["device_peak_bytes"] is None else f"  device {row['device_peak_bytes'] / 2**30:6.2f} GiB")
                 + "".join(f"  {k} {v}" for k, v in note.items()))
        self.on_row(self.rows)


# ---------------------------------------------------------------------------------------------
# The state
# ---------------------------------------------------------------------------------------------
def sample_sides(n: int, rng) -> np.ndarray:
    """(n,) texture sides drawn from :data:`SIDE_HISTOGRAM`."""
    sides = np.asarray(list(SIDE_HISTOGRAM), np.int64)
    p = np.asarray(list(SIDE_HISTOGRAM.values()), np.float64)
    return rng.choice(sides, size=n, p=p / p.sum())


def splat_scale(n: int) -> float:
    """The median scale (sigma) at which ``n`` splats in the box overlap :data:`DEPTH` deep on average.

    A ray through the box of side L meets a disc of radius r = 3 sigma (seen at a random angle,
    half its area on average) ``n * (pi r^2 / 2) / L^2`` times."""
    L = 2 * EXTENT
    return float(L * np.sqrt(2 * DEPTH / (n * np.pi)) / 3.0)


def make_state(n: int, seed: int = 0):
    """(scene with capacity ``ceil(n * CAPACITY_HEADROOM)``, no textures) at the paper's scale."""
    from patexgs_jax import Scene
    from patexgs_jax.data.synthetic import SCENE_CENTER

    rng = np.random.default_rng(seed)
    means = rng.uniform(-EXTENT, EXTENT, (n, 3)) + np.asarray(SCENE_CENTER)
    s = splat_scale(n)
    scales = np.exp(rng.uniform(np.log(s / 2), np.log(2 * s), (n, 2)))
    quats = rng.normal(size=(n, 4))
    opac = rng.uniform(0.05, 0.95, n)
    sh = np.zeros((n, 16, 3))
    sh[:, 0] = (rng.uniform(0.1, 0.9, (n, 3)) - 0.5) / 0.28209479177387814
    sh[:, 1:] = rng.normal(0.0, 0.05, (n, 15, 3))
    return Scene.from_arrays(means, scales, quats, opac, sh, capacity=int(np.ceil(n * CAPACITY_HEADROOM)))


def make_views(width: int, height: int, num_views: int, seed: int = 0):
    """The synthetic rig's cameras at ``width x height`` and smooth images (only their size matters)."""
    from patexgs_jax.data.synthetic import make_cameras

    cams = make_cameras(seed, num_views=num_views, width=width, height=height)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    views = []
    for i, c in enumerate(cams):
        img = np.stack([0.5 + 0.3 * np.sin(xx / 97.0 + i), 0.5 + 0.3 * np.cos(yy / 61.0 - i),
                        np.full_like(xx, 0.4 + 0.02 * i)], axis=-1).astype(np.float32)
        views.append(types.SimpleNamespace(camera=c, image=img, name=f"view{i}"))
    return views


def _used_texels(scene) -> dict:
    """{(bank, bucket): bool mask like the bucket}: the texels of each slot's texture (its top-left
    n x n block), false in the padding and the free slots."""
    masks = {}
    for name in ("rgb", "alpha"):
        bank = getattr(scene, name)
        bucket, slot, size = (np.asarray(x).astype(np.int64) for x in (bank.bucket, bank.slot, bank.size))
        for b, x in enumerate(bank.buckets):
            m = np.zeros(x.shape, bool)
            for n in np.unique(size[bucket == b]):
                m[slot[(bucket == b) & (size == n)], :n, :n] = True
            masks[name, b] = m
    return masks


def _as_trained(scene, opt_state, rng):
    """The scene's textures and Adam's state as after training, so that the copies and the
    checkpoint below move what a run's would: texels that vary within each texture, moments that
    vary from element to element, each texture's age one whole number of steps for its whole slot;
    zeros where a run has them (a texture's padding and the free slots, which get no gradient and are
    zeroed when left; the frozen index leaves' moments). Returns (scene, opt_state)."""
    import jax

    adam, group = opt_state
    frozen = {"active", "bucket", "slot", "size"}
    used = _used_texels(scene)

    def name(path):
        return str(getattr(path[-1], "name", ""))

    def texel(path):
        return any(str(getattr(k, "name", "")) == "buckets" for k in path)

    def where_used(path, v):  # (+0.0 elsewhere, as a run writes it: v * 0 would leave -0.0 where v < 0)
        return np.where(used[str(path[0].name), int(path[-1].idx)], v, np.float32(0)) if texel(path) else v

    def params(path, x):
        if not texel(path) or np.size(x) == 0:
            return x
        v = (rng.normal(0.0, 0.05, np.shape(x)) if str(path[0].name) == "rgb"
             else rng.uniform(0.2, 1.5, np.shape(x))).astype(np.float32)
        return jax.device_put(where_used(path, v))

    def moment(path, x, scale):
        if name(path) in frozen or np.size(x) == 0:
            return x
        return jax.device_put(where_used(path, (scale * np.abs(rng.standard_normal(np.shape(x), np.float32)))
                                         .astype(np.float32)))

    def age(path, x):
        if not texel(path) or np.size(x) == 0:
            return x
        per_slot = rng.integers(1, 10_000, (np.shape(x)[0], 1, 1, 1)).astype(np.float32)
        slots = used[str(path[0].name), int(path[-1].idx)].reshape(np.shape(x)[0], -1).any(axis=1)
        return jax.device_put(np.array(np.broadcast_to(per_slot * slots[:, None, None, None], np.shape(x))))

    scene = jax.tree_util.tree_map_with_path(params, scene)
    return scene, (adam._replace(mu=jax.tree_util.tree_map_with_path(lambda p, x: moment(p, x, 1e-3), adam.mu),
                                 nu=jax.tree_util.tree_map_with_path(lambda p, x: moment(p, x, 1e-6), adam.nu),
                                 age=jax.tree_util.tree_map_with_path(age, adam.age)), group)


def _block(tree):
    import jax

    return jax.block_until_ready(tree)


# ---------------------------------------------------------------------------------------------
# The rows
# ---------------------------------------------------------------------------------------------
def overflowing_sides(bank, sides: np.ndarray, rng) -> tuple[np.ndarray, int]:
    """``sides`` with one more texture grown (by one texel a side) into a bucket than the bucket has
    free slots: of the buckets the largest side of the bucket below can overflow, the one that needs
    the fewest. Returns (new sides, the bucket that overflows)."""
    caps = bank.capacities
    b_of = np.where(sides > 0, np.frexp(np.maximum(sides - 1, 0).astype(np.float64))[1], -1)
    counts = np.bincount(b_of[b_of >= 0], minlength=len(caps))
    best = None
    for b in range(1, len(caps)):
        cand = np.flatnonzero(sides == (1 << (b - 1)))  # one texel more takes them into bucket b
        need = int(caps[b] - counts[b]) + 1
        if cand.size >= need and (best is None or need < best[1]):
            best = (b, need, cand)
    if best is None:
        raise ValueError("no bucket can be overflowed by growing the textures below it by one texel")
    b, need, cand = best
    out = sides.copy()
    out[rng.choice(cand, need, replace=False)] += 1
    return out, b


def run(n: int, width: int, height: int, num_views: int, eq7_views: int, steps: int, skip: set, say,
        on_row=lambda rows: None, rebucket_path: str = "device") -> list[dict]:
    """The rows of one N (see the module docstring); ``on_row(rows so far)`` after each."""
    import jax

    from patexgs_jax import RenderConfig
    from patexgs_jax import checkpoint as ckpt
    from patexgs_jax.adaptive import (
        ContributionCounts,
        GrowthSchedule,
        TextureScheduleState,
        initial_texture_sizes,
        pixel_share_sigma,
        solve_sigma_for_budget,
        total_texels,
    )
    from patexgs_jax.checkpoint_writer import CheckpointWriter
    from patexgs_jax.densify import DensifyConfig, DensifyStats, densify_and_prune
    from patexgs_jax.export import export_ply, load_ply
    from patexgs_jax.optim import ages_per_slot, make_optimizer, upgrade_state
    from patexgs_jax.padding import ViewRenderer
    from patexgs_jax.schedule import TEXTURE_HEADROOM, TEXTURE_MIN_SPARE
    from patexgs_jax.textures.rebucket import add_textures, prepare_growth, resize_textures

    rows = Rows(n, say, on_row)
    rng = np.random.default_rng(1)
    with rows.time("build_state", host=True):
        scene = make_state(n)
        views = make_views(width, height, num_views)
    C = scene.capacity
    active = np.asarray(scene.active) > 0
    optimizer = make_optimizer(scene_radius=2.0)
    opt_state = optimizer.init(scene)
    tex_cfg = RenderConfig(mip="nearest", coverage="prefilter")

    # Eq. 6: rendered on the untextured scene, as at the allocation (textures then are 1 x 1 / 5 x 5).
    counts = None
    if "counts" not in skip:
        with rows.time("eq6_counts", host=False, views=num_views) as note:
            rows_ = []
            with ViewRenderer(scene, RenderConfig()) as renderer:
                t0 = time.perf_counter()
                renderer.prepare([v.camera for v in views])
                _block(renderer(views[0].camera).max_contrib_count)
                note["compile_s"] = time.perf_counter() - t0  # counted in the row (a run compiles too)
                for v in views:
                    rows_.append(np.asarray(renderer(v.camera).max_contrib_count, np.float32))
            counts = np.stack(rows_)
            note["contributing"] = int((counts.sum(axis=0) > 0).sum())
    if counts is None:  # stand-ins: a fifth of a view's pixels' top contributors, 5 pixels each on average
        counts = np.zeros((num_views, C), np.float32)
        k = min(int(active.sum()), width * height // 5)
        for j in range(num_views):
            counts[j, rng.choice(np.flatnonzero(active), k, replace=False)] = rng.geometric(0.2, k)
    # A capture of eq7_views views: the rendered rows repeated, each repeat's columns permuted.
    perms = [np.arange(C)] + [rng.permutation(C) for _ in range(min(eq7_views, 8) - 1)]

    def capture():
        for i in range(eq7_views):
            yield counts[i % num_views][perms[(i // num_views) % len(perms)]]

    pixels = eq7_views * width * height
    with rows.time("eq7_allocation", host=True, views=eq7_views) as note:
        # The run keeps each view's counts sparse as it renders them (schedule.TextureSchedule.allocate).
        S = ContributionCounts.from_views(capture(), C)
        sigma = pixel_share_sigma(pixels, int(active.sum()))
        sides0 = initial_texture_sizes(S, sigma, max_size=32, active=active)
        note.update(texels=total_texels(sides0, active), nonzero_counts=int(S.values.size))
    target = int(n * np.dot(np.asarray(list(SIDE_HISTOGRAM)) ** 2, list(SIDE_HISTOGRAM.values()))
                 / sum(SIDE_HISTOGRAM.values()))
    with rows.time("eq7_budget_solve", host=True, views=eq7_views) as note:
        sigma_b = solve_sigma_for_budget(S, target, max_size=32, active=active)
        note["sigma"] = float(sigma_b)
    del S

    if "densify" not in skip:
        g = np.zeros(C, np.float32)
        hot = rng.random(C) < DENSIFY_SHARE
        g[active & hot] = 1e-3
        stats = DensifyStats(grad_sum=jax.device_put(g), count=jax.device_put(active.astype(np.float32)),
                             max_radius=jax.device_put(np.where(active, 3.0, 0.0).astype(np.float32)))
        # The trainer's call donates the state (written in place); the rows below still need this one.
        d_scene, d_state = _block(jax.tree_util.tree_map(lambda x: jax.device_put(np.array(x)), (scene, opt_state)))
        with rows.time("densify", host=True) as note:  # the 2DGS stage's: untextured
            d_scene, d_state, _, dinfo = densify_and_prune(d_scene, d_state, stats, DensifyConfig(), 2.0, 0,
                                                           donate=True)
            _block((d_scene, d_state))
            note.update({k: v for k, v in vars(dinfo).items() if isinstance(v, (int, float, bool))})
        with rows.time("densify_again", host=True) as note:  # a second event: nothing to compile
            d_scene, d_state, _, dinfo = densify_and_prune(d_scene, d_state, stats, DensifyConfig(), 2.0, 1,
                                                           donate=True)
            _block((d_scene, d_state))
            note.update(cloned=dinfo.cloned, split=dinfo.split, pruned=dinfo.pruned)
        del d_scene, d_state, stats

    # Stage 2's textures: the real run's side distribution (1 x 1 RGB / 5 x 5 alpha first, as at its start).
    with rows.time("textures_start", host=True):
        scene, opt_state, _ = add_textures(scene, opt_state, optimizer, np.where(active, 1, 0), np.where(active, 5, 0),
                                           headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
        _block(scene)
    sides = np.where(active, sample_sides(C, rng), 0)
    with rows.time("allocation_rebucket", host=True) as note:
        scene, opt_state, info = resize_textures(scene, opt_state, sides, sides, headroom=TEXTURE_HEADROOM,
                                                 min_spare=TEXTURE_MIN_SPARE, on_device=rebucket_path == "device")
        _block((scene, opt_state))
        note["texels"] = int(total_texels(sides, active))
        # As the schedule does: the growth events' programs, in the background.
        prepare_growth(scene, headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
    scene, opt_state = _as_trained(scene, opt_state, rng)

    schedule = GrowthSchedule(t0=1000, t_final=20_000)
    state = TextureScheduleState.create(sides)
    # A statistic whose top few percent pass Eq. 9's threshold midway through the schedule.
    grad = np.where(active, rng.exponential(schedule.tau_preset, C), 0.0)
    step = 10_000
    with rows.time("eq8_10_growth", host=True) as note:
        state, new_sides, sel = state.step(grad, step, schedule, active=active)
        note["grown"] = int(sel.sum())
    # Two events (the programs of the layout were compiled in the background since the allocation).
    on_device = rebucket_path == "device"
    for event in ("rebucket", "rebucket_again", "rebucket_overflow"):
        if event == "rebucket_again":
            grad = np.where(active, rng.exponential(schedule.tau_preset, C), 0.0)
            state, new_sides, sel = state.step(grad, step + schedule.interval, schedule, active=active)
        overflows = None
        if event == "rebucket_overflow":
            before = new_sides
            new_sides, overflows = overflowing_sides(scene.rgb, new_sides, rng)
            sel = new_sides != before
            state = TextureScheduleState.create(new_sides)
        with rows.time(event, host=True) as note:
            scene, opt_state, info = resize_textures(scene, opt_state, new_sides, new_sides, donate=True,
                                                     headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE,
                                                     on_device=on_device)
            _block((scene, opt_state))
            note.update(grown=int(sel.sum()), layout_changed=bool(info.shapes_changed), path=rebucket_path)
            if overflows is not None:
                note["bucket"] = overflows
                if not info.shapes_changed:
                    raise AssertionError("the overflowing event kept the layout")

    tmp = Path(tempfile.mkdtemp(prefix="bench_scale_"))
    try:
        if "checkpoint" not in skip:
            tree = dict(scene=scene, opt_state=ages_per_slot(opt_state), tex_sizes=state.sizes)  # (as a run's)
            path = ckpt.checkpoint_path(tmp / "checkpoints", 1)
            with rows.time("checkpoint_save", host=True) as note:
                ckpt.save_checkpoint(path, tree, dict(step=1), keep=2)
                note["bytes"] = sum(f.stat().st_size for f in path.parent.rglob("*") if f.is_file())
            with rows.time("checkpoint_load", host=True):
                loaded, _ = ckpt.load_checkpoint(path)
                _block((loaded, upgrade_state(loaded["opt_state"])))
            del loaded
            async_path = ckpt.checkpoint_path(tmp / "checkpoints_async", 2)
            with CheckpointWriter() as writer:
                with rows.time("checkpoint_save_async_first", host=True):
                    writer.save(ckpt.checkpoint_path(tmp / "checkpoints_async", 1), tree, dict(step=1), keep=2)
                writer.wait()
                with rows.time("checkpoint_save_async_total", host=True) as total:
                    with rows.time("checkpoint_save_async", host=True):
                        writer.save(async_path, tree, dict(step=2), keep=2)
                    writer.wait()
                    total["bytes"] = async_path.stat().st_size
            del tree
        if "ply" not in skip:
            with rows.time("ply_export", host=True) as note:
                ply = export_ply(scene, tmp / "scene.ply")
                note["bytes"] = sum(f.stat().st_size for f in tmp.glob("scene*") if f.is_file())
            with rows.time("ply_load", host=True):
                _block(load_ply(ply))
    finally:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)

    if "eval" not in skip:
        cam = views[0].camera
        with ViewRenderer(scene, tex_cfg) as renderer:
            for k in (1, 2, 4, 8):
                c = cam.scaled(k)
                renderer.prepare([c])
                _block(renderer(c).rgb)  # compiles
                with rows.time(f"eval_render_{k}", host=False, width=c.width, height=c.height):
                    _block(renderer(c).rgb)

    if "step" not in skip:
        for kind in ("2dgs", "textured"):
            label = f"train_step_{kind}"
            say(f"{label}: in a fresh process (its own peak memory)")
            r = step_in_process(kind, n, width, height, num_views, steps)
            row = dict(event=label, gaussians=n, seconds=r["ms_per_step"] / 1e3, host=False,
                       peak_rss_bytes=r["peak_rss_bytes"], device_peak_bytes=r["device_peak_bytes"],
                       first_step_s=r["first_step_s"], recompiles_steady=r["recompiles_steady"],
                       pairs_capacity=r["capacity"], compositor=r["compositor"], process_seconds=r["process_seconds"])
            rows.rows.append(row)
            on_row(rows.rows)
            dev = r["device_peak_bytes"]
            say(f"{label:<22} {r['ms_per_step']:9.1f} ms a step (first {r['first_step_s']:.1f} s)  peak RSS "
                f"{r['peak_rss_bytes'] / 2**30:6.2f} GiB" + ("" if dev is None else f"  device {dev / 2**30:6.2f} GiB"))
    return rows.rows


def textured_state(n: int, seed: int = 0):
    """:func:`make_state` with textures of :data:`SIDE_HISTOGRAM`'s sides and its optimiser."""
    from patexgs_jax.optim import make_optimizer
    from patexgs_jax.schedule import TEXTURE_HEADROOM, TEXTURE_MIN_SPARE
    from patexgs_jax.textures.rebucket import add_textures, resize_textures

    scene = make_state(n, seed)
    active = np.asarray(scene.active) > 0
    optimizer = make_optimizer(scene_radius=2.0)
    scene, state, _ = add_textures(scene, optimizer.init(scene), optimizer, np.where(active, 1, 0),
                                   np.where(active, 5, 0), headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
    sides = np.where(active, sample_sides(scene.capacity, np.random.default_rng(1)), 0)
    scene, _, _ = resize_textures(scene, state, sides, sides, headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
    return scene


def step_in_process(kind: str, n: int, width: int, height: int, num_views: int, steps: int) -> dict:
    """Runs :func:`step_main` in a fresh process: the step's peak memory (resident and, on a GPU, the
    device's) is then its own, not this process's running maximum."""
    import json
    import subprocess

    cmd = [sys.executable, "-m", "experiments.bench_scale", "--step-only", kind, "--gaussians", str(n),
           "--width", str(width), "--height", str(height), "--views", str(num_views), "--steps", str(steps)]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"the {kind} step at {n} Gaussians failed (exit {out.returncode}):\n{out.stderr[-3000:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["process_seconds"] = time.perf_counter() - t0
    return result


def step_main(kind: str, n: int, width: int, height: int, num_views: int, steps: int) -> dict:
    """One training configuration's steps (forward + backward + Adam update, the real trainer) on the
    paper-scale state: ``2dgs`` untextured, ``textured`` with the real run's side distribution and the
    ``patexgs`` renderer. Returns bench_train's row plus the process's peak memory."""
    from experiments.bench_train import bench

    views = make_views(width, height, num_views)
    scene = make_state(n) if kind == "2dgs" else textured_state(n)
    r = bench("2dgs" if kind == "2dgs" else "tex8-mip-prefilter", n, views, steps, scene=scene, compositor=None)
    # VmHWM, not ru_maxrss: a child started by fork + exec keeps its parent's ru_maxrss, while the
    # high-water mark belongs to the new address space.
    r["peak_rss_bytes"] = _high_water_bytes()
    r["device_peak_bytes"] = _device_peak()
    return r


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gaussians", type=int, nargs="+", default=[100_000], help="N (several: one set of rows each)")
    p.add_argument("--width", type=int, default=1237,
                   help="view width in pixels (default 1237: Mip-NeRF 360 bicycle at factor 4)")
    p.add_argument("--height", type=int, default=822, help="view height in pixels (default 822)")
    p.add_argument("--views", type=int, default=4, help="views rendered for the Eq. 6 counts (and the step's views)")
    p.add_argument("--eq7-views", type=int, default=200, help="views Eq. 7 sums over (a Mip-NeRF 360 capture: 150-300)")
    p.add_argument("--steps", type=int, default=2, help="steady training steps timed after the first")
    p.add_argument("--skip", default="", help="comma-separated: counts, densify, checkpoint, ply, eval, step")
    p.add_argument("--json", type=Path, default=None, help="also write the rows here (with the commit and machine)")
    p.add_argument("--rebucket-path", choices=["device", "host"], default="device",
                   help="where the growth events' re-bucketings make the buckets: device (the default: only "
                        "the changing slots cross to the host) or host (every bucket; the reference)")
    p.add_argument("--step-only", choices=["2dgs", "textured"], default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.step_only is not None:  # the child of step_in_process: one JSON line on stdout
        import json

        r = step_main(args.step_only, args.gaussians[0], args.width, args.height, args.views, args.steps)
        print(json.dumps(r, default=str), flush=True)
        return 0
    skip = {s for s in args.skip.split(",") if s}
    unknown = skip - {"counts", "densify", "checkpoint", "ply", "eval", "step"}
    if unknown:
        p.error(f"--skip: unknown stage(s) {sorted(unknown)}")

    def say(msg):
        print(msg, flush=True)

    done: list[dict] = []
    config = dict(width=args.width, height=args.height, views=args.views, eq7_views=args.eq7_views,
                  steps=args.steps, rebucket_path=args.rebucket_path, depth=DEPTH, side_histogram=SIDE_HISTOGRAM)

    head = header(SCHEMA)  # the code and machine at the start (the checkout may move while it runs)

    def write(rows):  # after every row: a run cut short (a device's time limit) keeps what it measured
        if args.json is not None:
            write_json(args.json, dict(head, config=config, rows=done + rows))

    for n in args.gaussians:
        say(f"== {n} Gaussians, {args.views} views of {args.width}x{args.height}, Eq. 7 over {args.eq7_views} views")
        done += run(n, args.width, args.height, args.views, args.eq7_views, args.steps, skip, say, write,
                    rebucket_path=args.rebucket_path)
    write([])
    return 0


if __name__ == "__main__":
    sys.exit(main())
