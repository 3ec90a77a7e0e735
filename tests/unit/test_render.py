"""The tile renderer against the brute-force float64 reference (tests/render_reference.py), its
outputs' invariants, its compiles and tile capacity, and its input checks."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hard_scenes as hs
from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, render, render_jit
from patexgs_jax.data.colmap_model import quaternion_from_rotation
from patexgs_jax.render import TRACE_COUNTS, check_inputs
from patexgs_jax.rendering import chunks, projection
from render_cases import (
    CAP,
    CONFIGS,
    C,
    H,
    W,
    camera,
    check_matches_reference,
    check_tile_cull_keeps_every_pair,
    cull_pairs,
    ref_render,
    scene,
    tile_render,
)
from render_reference import scene_to_reference, sh_color


@pytest.mark.parametrize("name", ["2dgs", "nearest", "prefilter"])
def test_matches_reference(name):
    """The baseline, the textured default and PATexGS's own coverage; the other configurations are in
    tests/integration/test_render_sweeps.py."""
    check_matches_reference(name)


def test_inactive_slots_render_nothing():
    sc = scene(1)
    cam = camera()
    cfg = CONFIGS["nearest"][2]
    keep = np.arange(C) % 3 != 0
    masked = sc.replace(active=jnp.asarray(keep, jnp.float32))
    ref = ref_render(masked, cam, cfg)
    out = tile_render(masked, cam, cfg, jnp.float64)
    np.testing.assert_allclose(out.rgb, ref["rgb"], atol=1e-7)
    assert np.all(out.max_contrib_count[~keep] == 0)
    assert not np.any(out.visible[~keep])


def test_output_invariants():
    sc = scene(5)
    out = tile_render(sc, camera(), CONFIGS["nearest"][2])
    assert np.all((out.alpha >= 0) & (out.alpha <= 1))
    # Colour lies in the convex hull of the splat colours and the black background: bounded by
    # the extreme SH colours plus the extreme texture offsets.
    g = scene_to_reference(sc)
    cam = camera()
    origin = np.asarray(cam.center)
    cols = np.array([sh_color(g["sh"][i], (g["means"][i] - origin) / np.linalg.norm(g["means"][i] - origin))
                     for i in range(C)])
    offs = np.concatenate([t.reshape(-1, 3) for t in g["rgb"] if t is not None])
    assert np.all(out.rgb >= min(0.0, cols.min() + offs.min()) - 1e-6)
    assert np.all(out.rgb <= max(0.0, cols.max() + offs.max()) + 1e-6)
    assert out.max_contrib_count.sum() <= W * H
    assert np.all(out.radius_px[out.visible] > 0)
    # The per-pixel dominant splat: -1 where nothing was drawn, else a visible splat; its counts are
    # max_contrib_count.
    dom = np.asarray(out.dominant)
    assert dom.shape == (H, W) and dom.min() >= -1
    assert np.all(np.asarray(out.visible)[dom[dom >= 0]])
    np.testing.assert_array_equal(np.bincount(dom[dom >= 0], minlength=C), out.max_contrib_count)
    assert np.all(np.asarray(out.alpha)[dom < 0] < 1e-6)


def test_scaled_camera_is_pixel_consistent():
    cam = camera(w=48, h=32)
    small = cam.scaled(4)
    assert (small.width, small.height) == (12, 8)
    X = np.array([0.2, -0.1, 0.3, 1.0])
    pc = np.asarray(cam.world_to_camera) @ X
    big = (np.asarray(cam.K) @ pc[:3])[:2] / pc[2]
    sm = (np.asarray(small.K) @ pc[:3])[:2] / pc[2]
    np.testing.assert_allclose(sm, big / 4, rtol=1e-6)


# ---------------------------------------------------------------------------------------------
# Compiles and capacity
# ---------------------------------------------------------------------------------------------
def test_one_compile_per_configuration():
    cfg = RenderConfig(mip="nearest", lambda_mip=0.7)  # a config no other test uses
    before = TRACE_COUNTS[(cfg, CAP)]
    for seed, eye in [(11, (0.3, -0.4, -3.2)), (12, (-0.5, 0.2, -3.0)), (13, (0.0, 0.1, -2.5))]:
        render_jit(scene(seed), camera(eye=eye), config=cfg, capacity=CAP).rgb.block_until_ready()
    assert TRACE_COUNTS[(cfg, CAP)] - before == 1


def test_overflow_is_counted_and_render_grows():
    sc, cam, cfg = scene(7), camera(), CONFIGS["nearest"][2]
    full = tile_render(sc, cam, cfg)
    tiny = Capacity(pairs=64)
    out = render_jit(sc, cam, config=cfg, capacity=tiny)
    assert bool(out.overflow)
    assert float(out.pairs_needed) == float(full.pairs_needed)
    assert int(out.max_tile_count) == int(full.max_tile_count)
    assert int(full.max_tile_count) > 4 and float(full.pairs_needed) > 64
    with pytest.warns(UserWarning, match="growing"):
        grown = render(sc, cam, cfg, capacity=tiny)
    assert not bool(grown.overflow)
    np.testing.assert_allclose(np.asarray(grown.rgb), full.rgb, atol=1e-6)


def test_render_public_api_and_grad():
    sc, cam = scene(8), camera()
    out = render(sc, cam)  # default config: mip nearest
    assert out.rgb.shape == (H, W, 3) and out.depth.shape == (H, W) and out.normal.shape == (H, W, 3)

    def loss(s):
        return jnp.mean(render(s, cam, RenderConfig()).rgb)

    g = jax.grad(loss)(sc)
    assert isinstance(g, Scene)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        leaf = getattr(g, name)
        assert np.all(np.isfinite(leaf)), name
        assert np.abs(leaf).sum() > 0, name
    assert sum(float(jnp.abs(b).sum()) for b in g.rgb.buckets) > 0
    assert sum(float(jnp.abs(b).sum()) for b in g.alpha.buckets) > 0


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), eye_x=st.floats(-1.0, 1.0), eye_y=st.floats(-1.0, 1.0))
def test_random_views_match_reference(seed, eye_x, eye_y):
    cfg = CONFIGS["nearest"][2]
    sc = scene(seed % 100000)
    cam = camera(eye=(eye_x, eye_y, -3.0))
    ref = ref_render(sc, cam, cfg)
    out = tile_render(sc, cam, cfg, jnp.float64)
    np.testing.assert_allclose(out.rgb, ref["rgb"], atol=1e-7)


@pytest.mark.parametrize("num_tiles, tile_batch, batch", [(1, 8, 1), (6, 8, 6), (12, 8, 6), (17, 8, 6),
                                                          (300, 8, 8), (301, 8, 8), (5, 1, 1)])
def test_tile_batches_do_not_repeat_tiles_needlessly(num_tiles, tile_batch, batch):
    """Every lane of a tile batch is computed, padding included: the batch is the smallest size that
    keeps the fewest batches, so a one-tile image (a zoom-out by 8) is not rendered 8 times over."""
    st_ = chunks.Static(config=RenderConfig(tile_batch=tile_batch), tiles_x=1, num_tiles=num_tiles,
                             rgb=False, alpha=False)
    assert st_.batch == batch
    num_batches = -(-num_tiles // tile_batch)
    assert num_batches * st_.batch - num_tiles < num_batches  # less than one padding lane per batch
    binned = jnp.arange(num_tiles, dtype=jnp.int32)  # (the batches read the tile lists' lengths only)
    ctx = chunks.CompositeInputs(ids_sorted=binned, tile_start=binned, binned=binned, peak=jnp.ones(1),
                                 flag=jnp.array(True))
    tiles = np.asarray(chunks.tile_batches(st_, ctx))
    assert tiles.shape == (num_batches, batch)
    assert set(tiles.reshape(-1).tolist()) == set(range(num_tiles))


def test_inputs_off_the_layout_fail_at_trace_time_naming_the_field():
    """A Scene or Camera edited by hand against the layout fails before any rendering work, with the
    field, the expected shape or dtype and how to build one; float64 scenes (the references) pass."""
    sc, cam = scene(3), camera()
    check_inputs(sc, cam)
    with jax.enable_x64(True):
        check_inputs(sc.astype(jnp.float64), cam)
    cases = [
        (sc.replace(means=sc.means[:, :2]), cam, r"Scene\.means must be \(\d+, 3\)"),
        (sc.replace(quats=sc.quats[:-1]), cam, r"Scene\.quats must be \(\d+, 4\)"),
        (sc.replace(active=sc.active.astype(jnp.int32)), cam, r"Scene\.active .* floating-point"),
        (sc.replace(sh=jnp.zeros((sc.capacity, 2, 3))), cam, r"Scene\.sh has 2 coefficients"),
        (sc, dataclasses.replace(cam, K=cam.K[:2]), r"Camera\.K must be \(3, 3\)"),
    ]
    for bad_scene, bad_cam, match in cases:
        with pytest.raises(AssertionError, match=match) as err:
            render_jit(bad_scene, bad_cam, config=RenderConfig(), capacity=CAP)
        assert "Scene.from_arrays" in str(err.value)


def test_texture_pairs_is_validated():
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="texture_pairs"):
            RenderConfig(texture_pairs=bad)


# ---------------------------------------------------------------------------------------------
# Pairs left out of a splat's screen box (binning.tile_touches)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["edge_on", "near_plane"])
def test_tile_cull_keeps_every_pair_that_can_contribute(case):
    """Edge-on splats and splats across the near plane; the other hard cases are in
    tests/integration/test_render_sweeps.py."""
    check_tile_cull_keeps_every_pair(case)


def _far_walls_scene():
    """Walls of half-unit splats on both sides of the camera and above it, reaching behind it (their
    footprints on screen are unbounded, only their screen support bounds their boxes), and small
    splats ahead."""
    rng = np.random.default_rng(5)
    means, scales, normals = [], [], []
    for z in np.linspace(-1.5, 1.5, 7):
        for centre, normal in [((1.0, 0.0, z), (1, 0, 0)), ((-1.0, 0.3, z), (1, 0.2, 0)), ((0.2, 1.0, z), (0, 1, 0.1))]:
            means.append(centre)
            normals.append(normal)
            scales.append((0.5, 0.5))
    for _ in range(24):
        means.append((rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.6), rng.uniform(3.0, 8.0)))
        normals.append(hs._unit(rng.normal(size=3)))
        scales.append(rng.uniform(0.05, 0.3, 2))
    n = len(means)
    quats = [quaternion_from_rotation(hs.frame_with_normal(np.asarray(v, float), rng)) for v in normals]
    sh = np.zeros((n, 1, 3))
    sh[:, 0] = (rng.uniform(0.2, 0.8, (n, 3)) - 0.5) / hs.SH_C0
    alpha = [rng.uniform(0.2, 1.0, (4, 4)) if i % 2 else None for i in range(n)]
    rgb = [rng.uniform(-0.2, 0.2, (s, s, 3)) for s in rng.integers(1, 5, n)]
    sc = Scene.from_arrays(np.asarray(means), np.asarray(scales), np.asarray(quats), rng.uniform(0.3, 0.9, n),
                           sh, rgb_textures=rgb, alpha_textures=alpha, capacity=64)
    cam = Camera.from_intrinsics([60.0, 60.0, 48.0, 32.0], look_at((0.0, 0.0, -0.2), (0.0, 0.0, 5.0)), 96, 64)
    return sc, cam


@pytest.mark.parametrize("coverage", ["prefilter", "lowpass"])
def test_tile_cull_drops_pairs_of_unbounded_footprints_and_keeps_the_image(coverage):
    """On walls of splats reaching behind the camera (footprints unbounded on screen), tile_touches
    leaves out about half of the boxes' pairs; none of them reaches alpha 1/255, and the render
    is the one without the cull (rgb, alpha, depth, normal, the dominant splat)."""
    sc, cam = _far_walls_scene()
    cfg = RenderConfig(coverage=coverage)
    keep, reach, n = cull_pairs(sc, cam, cfg)
    assert not np.any(reach & ~keep)
    assert keep.sum() < 0.6 * n, (int(keep.sum()), n)
    cap = Capacity(pairs=8192)
    on = tile_render(sc, cam, cfg, capacity=cap)
    off = tile_render(sc, cam, dataclasses.replace(cfg, tile_cull=False), capacity=cap)
    assert on.alpha.mean() > 0.2
    for a, b in [(on.rgb, off.rgb), (on.alpha, off.alpha), (on.normal, off.normal)]:
        np.testing.assert_allclose(a, b, atol=2e-5, rtol=1e-5)
    # Depth sums values of 1-3 over hundreds of pairs: two programs' float32 roundings of it differ
    # by up to 4e-5 of it (the suite's codegen, tests/conftest.py).
    np.testing.assert_allclose(on.depth, off.depth, atol=2e-5, rtol=1e-4)
    np.testing.assert_array_equal(on.dominant, off.dominant)


def _binning_case(rng, n, box, tiles_x, tiles_y):
    """n splats with random boxes of up to ``box`` tiles a side and distinct depths; every other one
    can reach every tile of its box (footprint side 0), the rest none (in front of the camera
    nowhere, centre far off: tile_touches is False for any tile, with a wide margin)."""
    depth = rng.permutation(n).astype(np.float32)
    tx0 = rng.integers(0, tiles_x, n)
    ty0 = rng.integers(0, tiles_y, n)
    tx1 = np.minimum(tx0 + rng.integers(1, box + 1, n), tiles_x)
    ty1 = np.minimum(ty0 + rng.integers(1, box + 1, n), tiles_y)
    ok = rng.random(n) < 0.9
    every = np.arange(n) % 2 == 0
    fp = np.zeros((n, projection.FOOTPRINT.width), np.float32)
    F = projection.FOOTPRINT
    fp[:, F.c] = (1.0, 1.0, 1.0)                 # s = (1, 1, 1) at every pixel: front = side * 1
    fp[:, F.conic] = (1.0, 0.0, 1.0)
    fp[:, F.r2] = 0.0                            # Phi = -|s01|^2 < 0 (and the front is negative)
    fp[:, F.side] = np.where(every, 0.0, -1.0)
    fp[:, F.mu] = -1e6
    return depth, tx0, tx1, ty0, ty1, ok, every, fp


@pytest.mark.parametrize("box", [2, 6, 12])
def test_bin_pairs_lists_with_culled_blocks_and_sorted_prefixes(box):
    """bin_pairs at a capacity of 16 cull blocks (65,536 slots) where the box pairs fill 4%, 18% and
    54% of the slots (the sort runs over an eighth, a quarter and all of them): every tile's list
    is the splats that reach it, front to back."""
    from patexgs_jax.rendering import binning

    tiles_x, tiles_y, n, N = 40, 30, 1200, 65536
    depth, tx0, tx1, ty0, ty1, ok, every, fp = _binning_case(np.random.default_rng(box), n, box, tiles_x, tiles_y)
    total = int(np.sum(np.where(ok, (tx1 - tx0) * (ty1 - ty0), 0)))
    assert total <= N
    run = jax.jit(binning.bin_pairs, static_argnums=(6, 7, 8), static_argnames=("tile_size", "lowpass"))
    ids, start, binned = (np.asarray(a) for a in run(
        jnp.asarray(depth), *(jnp.asarray(a, jnp.int32) for a in (tx0, tx1, ty0, ty1)), jnp.asarray(ok),
        tiles_x, tiles_x * tiles_y, N, footprint=jnp.asarray(fp), tile_size=16, lowpass=False))
    front_to_back = np.argsort(depth, kind="stable")
    for t in range(tiles_x * tiles_y):
        x, y = t % tiles_x, t // tiles_x
        want = [g for g in front_to_back
                if ok[g] and every[g] and tx0[g] <= x < tx1[g] and ty0[g] <= y < ty1[g]]
        assert binned[t] == len(want)
        np.testing.assert_array_equal(ids[start[t]:start[t] + binned[t]], want)
