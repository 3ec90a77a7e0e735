"""The tile renderer against the brute-force float64 reference, its gradients, and its properties.

Compiles are the expensive part on CPU: every test here renders scenes of one capacity (C=48),
one image size (44x36, a partial tile on each edge) and one Capacity, so compiled renderers are
shared across tests (one per configuration and dtype).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, random_scene, render, render_jit, rendering
from patexgs_jax.rendering import chunks, composite, kernel, texture_lookup
from patexgs_jax.rendering.projection import COLS
from render_reference import reference_render, scene_to_reference, sh_color

C = 48
W, H = 44, 36
CAP = Capacity(pairs=4096)
# Texture sides per Gaussian, fixed so every textured scene has the same bucket layout (shapes).
RGB_SIZES = [0, 1, 2, 3, 4, 5, 7, 8, 9, 16] * 4 + [0] * 8
ALPHA_SIZES = [5, 0, 1, 3, 4, 6, 8, 2, 9, 12] * 4 + [5] * 8


def camera(eye=(0.3, -0.4, -2.6), target=(0.0, 0.0, 0.0), f=40.0, w=W, h=H) -> Camera:
    return Camera.from_intrinsics([f, f * 1.05, w / 2 + 0.3, h / 2 - 0.2], look_at(eye, target), w, h)


def scene(seed, textured=True, sh_degree=1) -> Scene:
    return random_scene(seed, C, sh_degree=sh_degree, extent=0.8, scale_range=(0.08, 0.45),
                        rgb_sizes=RGB_SIZES if textured else None,
                        alpha_sizes=ALPHA_SIZES if textured else None)


def tile_render(sc, cam, cfg, dtype=jnp.float32, capacity=CAP):
    if dtype == jnp.float64:
        with jax.enable_x64(True):
            out = render_jit(sc.astype(jnp.float64), cam, config=cfg, capacity=capacity)
            assert not bool(out.overflow)
            return jax.tree_util.tree_map(np.asarray, out)
    out = render_jit(sc, cam, config=cfg, capacity=capacity)
    assert not bool(out.overflow)
    return jax.tree_util.tree_map(np.asarray, out)


def ref_render(sc, cam, cfg):
    return reference_render(scene_to_reference(sc), np.asarray(cam.K, np.float64),
                            np.asarray(cam.world_to_camera, np.float64), cam.width, cam.height,
                            mip=cfg.mip, lam=cfg.lambda_mip, rgb_mip=cfg.rgb_mip,
                            alpha_mip=cfg.alpha_mip, background=cfg.background, near=cfg.near,
                            coverage=cfg.coverage, pixel_var=cfg.pixel_var, min_var=cfg.min_var)


CONFIGS = {
    "2dgs": (False, 3, RenderConfig(mip="none", background=(0.1, 0.2, 0.3))),
    "none": (True, 1, RenderConfig(mip="none")),
    "nearest": (True, 1, RenderConfig(mip="nearest")),
    "trilinear": (True, 2, RenderConfig(mip="trilinear", lambda_mip=1.5)),
    "no-rgb-mip": (True, 0, RenderConfig(mip="nearest", rgb_mip=False, lambda_mip=2.0)),
    "prefilter": (True, 1, RenderConfig(mip="nearest", coverage="prefilter", min_var=0.25)),
    "prefilter-2dgs": (False, 2, RenderConfig(mip="none", coverage="prefilter", pixel_var=0.3)),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_matches_reference(name):
    textured, degree, cfg = CONFIGS[name]
    sc = scene(3 + len(name), textured, degree)
    cam = camera()
    ref = ref_render(sc, cam, cfg)
    # float64 tile renderer: the same maths, so it agrees to rounding everywhere.
    out64 = tile_render(sc, cam, cfg, jnp.float64)
    np.testing.assert_allclose(out64.rgb, ref["rgb"], atol=1e-7, rtol=0)
    np.testing.assert_allclose(out64.alpha, ref["alpha"], atol=1e-7, rtol=0)
    np.testing.assert_allclose(out64.depth, ref["depth"], atol=1e-6, rtol=0)
    np.testing.assert_allclose(out64.normal, ref["normal"], atol=1e-7, rtol=0)
    np.testing.assert_allclose(out64.distortion, ref["distortion"], atol=1e-9, rtol=1e-6)
    best = ref["best"].ravel()
    counts = np.bincount(best[best >= 0], minlength=C)
    np.testing.assert_array_equal(out64.max_contrib_count, counts)
    assert ref["alpha"].mean() > 0.2, "the test scene should cover much of the image"
    # float32 production renderer: within 2e-4 except where a threshold (alpha >= 1/255, the
    # 1e-4 transmittance stop, a mip level boundary) flips on rounding: at most 0.5% of pixels.
    out32 = tile_render(sc, cam, cfg)
    err = np.abs(out32.rgb - ref["rgb"]).max(axis=-1)
    assert np.mean(err > 2e-4) <= 0.005, (err.max(), np.mean(err > 2e-4))
    assert np.median(err) < 2e-5


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
    before = rendering.TRACE_COUNTS[(cfg, CAP)]
    for seed, eye in [(11, (0.3, -0.4, -3.2)), (12, (-0.5, 0.2, -3.0)), (13, (0.0, 0.1, -2.5))]:
        render_jit(scene(seed), camera(eye=eye), config=cfg, capacity=CAP).rgb.block_until_ready()
    assert rendering.TRACE_COUNTS[(cfg, CAP)] - before == 1


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


# ---------------------------------------------------------------------------------------------
# Gradients: float64 finite differences
# ---------------------------------------------------------------------------------------------
def _directional_fd_check(sc, cam, cfg, seed, h=1e-6, rtol=2e-4):
    with jax.enable_x64(True):
        sc64 = sc.astype(jnp.float64)
        rng = np.random.default_rng(seed)
        wts = jnp.asarray(rng.uniform(0.5, 1.5, (H, W, 3)))

        def loss(s):
            out = render_jit(s, cam, config=cfg, capacity=CAP)
            return (jnp.sum(out.rgb * wts) + jnp.sum(out.alpha) + 0.1 * jnp.sum(out.depth)
                    + jnp.sum(out.distortion))

        g = jax.grad(loss)(sc64)
        leaves, treedef = jax.tree_util.tree_flatten(sc64)
        gleaves = jax.tree_util.tree_leaves(g)
        frozen = {id(x) for x in (sc64.active,) + tuple(
            getattr(b, f) for b in (sc64.rgb, sc64.alpha) if b is not None for f in ("bucket", "slot", "size"))}
        dirs = [jnp.zeros_like(x) if id(x) in frozen else jnp.asarray(rng.normal(size=x.shape))
                for x in leaves]
        analytic = sum(float(jnp.sum(a * d)) for a, d in zip(gleaves, dirs))
        shift = lambda eps: jax.tree_util.tree_unflatten(treedef, [x + eps * d for x, d in zip(leaves, dirs)])  # noqa: E731
        fd = (float(loss(shift(h))) - float(loss(shift(-h)))) / (2 * h)
        assert np.isfinite(analytic)
        assert abs(analytic - fd) <= rtol * abs(fd) + 1e-6, (analytic, fd)


@pytest.mark.parametrize("name", ["2dgs", "trilinear", "prefilter"])
def test_gradients_match_finite_differences(name):
    textured, degree, cfg = CONFIGS[name]
    sc = scene(21, textured, degree)
    # The prefilter composites more faint pairs (a skipped pair's alpha jumps from 0 to 1/255 times
    # its coverage): a smaller step keeps the difference off those jumps.
    h = 1e-7 if cfg.coverage == "prefilter" else 1e-6
    for seed in range(3):
        _directional_fd_check(sc, camera(), cfg, seed, h=h)


# ---------------------------------------------------------------------------------------------
# Mipmap properties
# ---------------------------------------------------------------------------------------------
def _single_splat_scene(tex_rgb, tex_alpha=None, scale=1.0, n_pad=C):
    """One splat facing the camera (normal along z) at the origin, padded to capacity C."""
    q = [1.0, 0.0, 0.0, 0.0]
    sh = np.zeros((1, 1, 3))
    return Scene.from_arrays([[0.0, 0.0, 0.0]], [[scale, scale]], [q], [1.0], sh,
                             rgb_textures=[tex_rgb], alpha_textures=[tex_alpha], capacity=n_pad)


def test_pyramid_levels_and_their_transpose_match_numpy():
    """Each bucket's levels are ``D X D^T`` of the level above (the first with each slot's own
    filter for its size), and the backward is the transpose ``D^T G D``: checked in float64 against
    numpy, for the unrolled filters and the einsum (the first level of a 32-texel slot)."""
    from patexgs_jax import textures as tx

    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        for b in (1, 3, 5):  # slots of 2 and 8 (unrolled), 32 (an einsum to level 1, unrolled below)
            P = 1 << b
            sizes = np.arange(P // 2 + 1, P + 1)
            X = np.zeros((sizes.size, P, P, 2))
            for k, n in enumerate(sizes):
                X[k, :n, :n] = rng.normal(size=(n, n, 2))
            levels, vjp = jax.vjp(lambda x, sizes=sizes, b=b: tx._pyramid(x, jnp.asarray(sizes), b), jnp.asarray(X))
            G = [rng.normal(size=lev.shape) for lev in levels]
            want_levels, want_grad = [X], G[-1]
            Ds = []
            for k in range(1, b + 1):
                if k == 1:  # the level-1 filters are tabulated in float32, zero past each size
                    D = tx._first_level_table(P)[sizes - (P // 2 + 1)].astype(np.float64)
                    np.testing.assert_allclose(D[-1], tx.downsample_matrix(P, P // 2), rtol=1e-6)
                else:
                    D = np.stack([tx.downsample_matrix(P >> (k - 1), P >> k)] * sizes.size)
                Ds.append(D)
                want_levels.append(np.einsum("kip,kpqc,kjq->kijc", Ds[-1], want_levels[-1], Ds[-1]))
            for k in range(b, 0, -1):  # the transpose, coarsest level first
                want_grad = G[k - 1] + np.einsum("kip,kijc,kjq->kpqc", Ds[k - 1], want_grad, Ds[k - 1])
            for got, want in zip(levels, want_levels):
                np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-12)
            np.testing.assert_allclose(np.asarray(vjp([jnp.asarray(g) for g in G])[0]), want_grad,
                                       rtol=0, atol=1e-12)


def test_constant_texture_is_mip_invariant():
    rgb = np.full((9, 9, 3), 0.25)
    alpha = np.full((6, 6), 0.8)
    sc = _single_splat_scene(rgb, alpha)
    cam = camera(eye=(0.0, 0.0, -12.0), f=30.0)  # strong minification: high levels are chosen
    base = tile_render(sc, cam, RenderConfig(mip="none"), capacity=Capacity(1024))
    for cfg in (RenderConfig(mip="nearest"), RenderConfig(mip="trilinear")):
        out = tile_render(sc, cam, cfg, capacity=Capacity(1024))
        np.testing.assert_allclose(out.rgb, base.rgb, atol=2e-6)
        np.testing.assert_allclose(out.alpha, base.alpha, atol=2e-6)


def test_magnification_picks_level_zero():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(-0.5, 0.5, (8, 8, 3))
    alpha = rng.uniform(0.2, 1.0, (8, 8))
    sc = _single_splat_scene(rgb, alpha, scale=0.5)
    cam = camera(eye=(0.0, 0.0, -2.0), f=80.0)  # ~20 px per unit of scale: D ~ 0.05, 0.4*8*D < 1
    base = tile_render(sc, cam, RenderConfig(mip="none"), capacity=Capacity(1024))
    out = tile_render(sc, cam, RenderConfig(mip="nearest"), capacity=Capacity(1024))
    # Same texels, same level: equal up to float32 rounding of a different fusion of the lookups.
    np.testing.assert_allclose(out.rgb, base.rgb, atol=1e-6, rtol=0)
    np.testing.assert_allclose(out.alpha, base.alpha, atol=1e-6, rtol=0)
    assert base.alpha.max() > 0.5


@pytest.mark.parametrize("channel", ["rgb", "alpha"])
def test_minification_is_closer_to_supersampled_truth(channel):
    n = 32
    checker = ((np.add.outer(np.arange(n), np.arange(n)) % 2) * 2 - 1).astype(np.float64)
    if channel == "rgb":
        sc = _single_splat_scene(0.4 * checker[..., None].repeat(3, -1), None, scale=1.0)
    else:
        sc = _single_splat_scene(None, 0.5 + 0.5 * checker, scale=1.0)
    sc = sc.replace(sh=sc.sh.at[0, 0].set(0.5 / 0.28209479177387814 * 0.3))
    # Small view: the 6x6 texture square spans about 16 px, so 32 texels alias badly.
    cam_small = camera(eye=(0.0, 0.0, -10.0), target=(0.0, 0.0, 0.0), f=27.0, w=W, h=H)
    factor = 8
    K_big = np.asarray(cam_small.K, np.float64) * np.array([[factor], [factor], [1]])
    cam_big = Camera.from_intrinsics(K_big, np.asarray(cam_small.world_to_camera), W * factor, H * factor)
    truth = render(sc, cam_big, RenderConfig(mip="none"))
    truth = np.asarray(truth.rgb).reshape(H, factor, W, factor, 3).mean(axis=(1, 3))
    errs = {}
    for mip in ("none", "nearest", "trilinear"):
        out = render(sc, cam_small, RenderConfig(mip=mip))
        errs[mip] = float(np.sqrt(np.mean((np.asarray(out.rgb) - truth) ** 2)))
    assert errs["nearest"] < 0.7 * errs["none"], errs
    assert errs["trilinear"] < 0.7 * errs["none"], errs


# ---------------------------------------------------------------------------------------------
# Hard cases: every gradient finite
# ---------------------------------------------------------------------------------------------
def _hard_scene(case):
    rng = np.random.default_rng(0)
    n = 8
    means = rng.uniform(-0.3, 0.3, (n, 3))
    scales = np.full((n, 2), 0.3)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) + rng.normal(0, 0.1, (n, 4))
    opac = np.full(n, 0.7)
    if case == "edge_on":
        # normal along x: the splat plane contains the viewing rays (camera looks along +z).
        quats = np.tile([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0], (n, 1))
        quats[1:] += rng.normal(0, 1e-7, (n - 1, 4))
    elif case == "tiny_and_huge":
        scales = np.exp(rng.uniform(np.log(1e-6), np.log(1e3), (n, 2)))
    elif case == "needles":
        scales = np.stack([np.full(n, 1e-4), np.full(n, 1e2)], axis=1)
    elif case == "near_plane":
        means[:, 2] = np.linspace(-3.2, -2.9, n)  # camera at z = -3: behind, on, just past near
        scales[:] = 1.0
    elif case == "saturated":
        opac[:] = 1.0
    alpha = [np.full((4, 4), 50.0) if case == "saturated" else rng.uniform(0, 2, (4, 4)) for _ in range(n)]
    rgb = [rng.uniform(-1, 1, (3, 3, 3)) for _ in range(n)]
    return Scene.from_arrays(means, scales, quats, opac, rng.normal(0, 1, (n, 4, 3)),
                             rgb_textures=rgb, alpha_textures=alpha, capacity=n)


@pytest.mark.parametrize("case", ["edge_on", "tiny_and_huge", "needles", "near_plane", "saturated"])
@pytest.mark.parametrize("mip", ["nearest", "trilinear"])
def test_hard_case_gradients_finite(case, mip):
    sc = _hard_scene(case)
    cam = camera(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 1.0))
    cfg = RenderConfig(mip=mip)
    cap = Capacity(pairs=1024)

    def loss(s):
        out = render_jit(s, cam, config=cfg, capacity=cap)
        return jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.normal) + jnp.sum(out.alpha)

    val, g = jax.value_and_grad(loss)(sc)
    assert np.isfinite(float(val))
    for path, leaf in jax.tree_util.tree_leaves_with_path(g):
        assert np.all(np.isfinite(np.asarray(leaf))), jax.tree_util.keystr(path)


def test_thousands_of_splats_on_one_pixel():
    n = 2000
    means = np.zeros((n, 3))
    means[:, 2] = np.linspace(0.0, 2.0, n)
    sc = Scene.from_arrays(means, np.full((n, 2), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)),
                           np.full(n, 0.05), np.zeros((n, 1, 3)) + 0.5)
    cam = Camera.from_intrinsics([50.0, 50.0, 8.0, 8.0], look_at((0, 0, -2.0), (0, 0, 0)), 16, 16)
    cap = Capacity(pairs=4096)

    def loss(s):
        return jnp.sum(render_jit(s, cam, config=RenderConfig(mip="none"), capacity=cap).rgb)

    val, g = jax.value_and_grad(loss)(sc)
    out = render_jit(sc, cam, config=RenderConfig(mip="none"), capacity=cap)
    assert not bool(out.overflow)
    assert float(out.alpha[8, 8]) > 0.99
    assert np.isfinite(float(val))
    for leaf in jax.tree_util.tree_leaves(g):
        assert np.all(np.isfinite(np.asarray(leaf)))


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
    ctx = dict(binned=jnp.arange(num_tiles, dtype=jnp.int32))
    tiles = np.asarray(chunks.tile_batches(st_, ctx))
    assert tiles.shape == (num_batches, batch)
    assert set(tiles.reshape(-1).tolist()) == set(range(num_tiles))


# ---------------------------------------------------------------------------------------------
# Texture lookups only where a pair can contribute, in passes
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("c", [32, 7, 45])
def test_pass_pairs_list_the_marked_pairs_in_order(c):
    """The passes' pairs, read in order, are exactly the marked slots of the block in row-major order,
    then the "none" index: for a chunk of 32 slots (one word per row), fewer (a partial word) and
    more (two words, the second partial), with passes that end inside a row."""
    rng = np.random.default_rng(c)
    B, P = 3, 20
    take = rng.random((B, P, c)) < 0.2
    take[1, 5] = True  # a full row
    take[2] = False    # a tile with no marks
    N = take.size
    K = 13
    passes = texture_lookup._mark_passes(jnp.asarray(take), K)
    want = np.flatnonzero(take.reshape(-1))
    assert int(passes.count) == want.size
    got = []
    j = 0
    while bool(texture_lookup._more_passes(passes, j)):
        got.append(np.asarray(texture_lookup._pass_pairs(passes, j)))
        j += 1
    assert j == -(-want.size // K)
    got = np.concatenate(got)
    np.testing.assert_array_equal(got[:want.size], want)
    assert np.all(got[want.size:] == N)


@pytest.mark.parametrize("shape, share", [((1, 4096, 4095), 1.0), ((1, 4096, 4096), 0.3)])
def test_pass_running_counts_are_exact(shape, share):
    """The rows' running counts of marks are exact integers: by float32 matmuls while the block has
    fewer than 2**24 slots (here every slot marked, the last count 16,773,120, just below), by an
    integer cumsum from 2**24 slots on."""
    rng = np.random.default_rng(shape[-1])
    take = rng.random(shape) < share
    passes = texture_lookup._mark_passes(jnp.asarray(take), 64)
    nw = -(-shape[-1] // 32)
    padded = np.zeros(shape[:-1] + (nw * 32,), bool)
    padded[..., :shape[-1]] = take
    want = np.cumsum(padded.reshape(-1, 32).sum(axis=1))
    np.testing.assert_array_equal(np.asarray(passes.ends), want)
    assert int(passes.count) == int(take.sum())


@pytest.mark.parametrize("K", [1, 5, 64, 1000])
def test_rows_of_ranks_match_searchsorted(K):
    """The rows of a pass's consecutive ranks, from a histogram and running sums, equal
    ``np.searchsorted(ends, rank, side="right")``: for running counts with empty rows (repeated
    ends), passes starting before the first end, inside a row, and past the last end."""
    rng = np.random.default_rng(K)
    counts = rng.integers(0, 4, 300) * (rng.random(300) < 0.6)
    ends = np.cumsum(counts).astype(np.int32)
    for start in [0, 1, int(ends[40]), int(ends[-1]) - K // 2, int(ends[-1]) + 3]:
        got = np.asarray(texture_lookup._rows_of_ranks(jnp.asarray(ends), jnp.int32(start), K))
        want = np.searchsorted(ends, start + np.arange(K), side="right")
        np.testing.assert_array_equal(got, want, err_msg=f"start {start}")


@pytest.mark.parametrize("name", ["nearest", "trilinear"])
def test_texture_passes_do_not_change_the_result(name):
    """Looking textures up only for the pairs that can reach alpha 1/255, in many small passes, gives
    the image and gradients of looking up every pair. (At 1/512 a pass holds 80 of the 40,960 pairs
    of a chunk step here, far fewer than contribute. The default share, about one pass per step, is
    what the float64 reference tests above render with.)"""
    textured, degree, cfg = CONFIGS[name]
    sc = scene(31, textured, degree)
    cam = camera()
    cfgs = [dataclasses.replace(cfg, texture_pairs=t) for t in (1.0, 1 / 512)]

    def loss(s, c):  # the image and the gradient from one compiled function per configuration
        out = rendering._render(s, cam, c, CAP)
        return jnp.mean(jnp.abs(out.rgb - 0.3)) + 0.1 * jnp.mean(out.alpha * out.depth), out

    with jax.enable_x64(True):
        sc64 = sc.astype(jnp.float64)
        res = []
        for c in cfgs:
            (_, out), g = jax.jit(jax.value_and_grad(lambda s, c=c: loss(s, c), has_aux=True))(sc64)
            res.append(jax.tree_util.tree_map(np.asarray, (out, g)))
    (out_d, g_d) = res[0]
    assert out_d.alpha.mean() > 0.2
    for out, g in res[1:]:
        for a, b in [(out.rgb, out_d.rgb), (out.alpha, out_d.alpha), (out.depth, out_d.depth),
                     (out.normal, out_d.normal), (out.distortion, out_d.distortion)]:
            np.testing.assert_allclose(a, b, atol=1e-12, rtol=0)
        np.testing.assert_array_equal(out.max_contrib_count, out_d.max_contrib_count)
        for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(g_d)):
            scale = float(np.abs(b).max()) if b.size else 0.0
            np.testing.assert_allclose(a, b, atol=1e-10 * max(scale, 1.0), rtol=0)


def test_inputs_off_the_layout_fail_at_trace_time_naming_the_field():
    """A Scene or Camera edited by hand against the layout fails before any rendering work, with the
    field, the expected shape or dtype and how to build one; float64 scenes (the references) pass."""
    sc, cam = scene(3), camera()
    rendering.check_inputs(sc, cam)
    with jax.enable_x64(True):
        rendering.check_inputs(sc.astype(jnp.float64), cam)
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
# The compositor's hand-derived backward against autodiff
# ---------------------------------------------------------------------------------------------
def _chunk_inputs(rng, P, c):
    """A tile chunk's inputs with every branch of the compositing taken: saturated alpha (capped at
    0.99), pairs below 1/255, behind the near plane or in padding slots, pixels already stopped and
    pixels whose transmittance crosses 1e-4 inside the chunk, splats with and without textures."""
    OP = COLS.opacity                                    # the opacity column
    pk = rng.normal(size=(c, COLS.width))
    pk[:, OP] = rng.uniform(0.0, 1.0, c)
    pk[:3, OP] = 0.9999                                    # saturating splats at the front
    G = rng.uniform(0.0, 1.0, (P, c))
    G[: P // 2, :3] = 1.0
    G[:, 5] = 1e-4                                         # below 1/255 everywhere
    z = rng.uniform(0.5, 4.0, (P, c))
    z[:, 6] = 0.005                                        # in front of the near plane (0.01)
    a_tex = rng.uniform(0.0, 1.0, (P, c))
    a_tex[: P // 2, :3] = 1.0
    offs = [rng.normal(size=(P, c)) * 0.3 for _ in range(3)]
    valid = np.arange(c) < c - 3                           # the last slots are padding
    done = np.zeros(P, bool)
    done[1] = True
    log_t = np.log(rng.uniform(1e-3, 1.0, P))
    log_t[2] = np.log(2e-4)                                # crosses 1e-4 inside the chunk
    gid = np.arange(c, dtype=np.int32)
    ctx = dict(rgb_has=jnp.asarray(np.arange(c) % 3 != 1), alpha_has=jnp.asarray(np.arange(c) % 4 != 2))
    return pk, G, z, offs, a_tex, valid, done, log_t, gid, ctx


@pytest.mark.parametrize("rgb, alpha", [(False, False), (True, True), (False, True)])
def test_chunk_backward_matches_autodiff(rgb, alpha):
    """:func:`_chunk_contrib_bwd` (the compositing's backward, derived by hand) gives autodiff's
    cotangents of :func:`_chunk_contrib`, and the state after the chunk, to float64 rounding: one
    tile of P pixels, its (P, c) pairs in the chunk's (c, 1, P) layout."""
    rng = np.random.default_rng(11 + 2 * rgb + alpha)
    P, c = 12, 16
    st_ = chunks.Static(config=RenderConfig(), tiles_x=1, num_tiles=1, rgb=rgb, alpha=alpha)
    pk, G, z, offs, a_tex, valid, done, log_t, gid, ctx = _chunk_inputs(rng, P, c)

    def block(a):  # (P, c) -> (c, 1, P)
        return a.T[:, None]

    G, z, a_tex, offs = block(G), block(z), block(a_tex), [block(o) for o in offs]
    pk, valid, gid, done, log_t = pk[None], valid[None], gid[None], done[None], log_t[None]
    with jax.enable_x64(True):
        pk, G, z, offs, a_tex, valid, done, log_t, gid = jax.tree.map(
            jnp.asarray, (pk, G, z, offs, a_tex, valid, done, log_t, gid))
        offs = offs if rgb else None
        a_tex = a_tex if alpha else None
        ct = jnp.asarray(rng.normal(size=(1, P, 9)))
        dot_in = jnp.asarray(rng.normal(size=(1, P)))
        base = jnp.asarray(rng.normal(size=(1, P)))

        def f(pk_, G_, z_, offs_, a_tex_):
            return composite._chunk_contrib(st_, ctx, pk_, G_, z_, offs_, a_tex_, gid, valid, log_t, done)

        (dacc, log_t_out), vjp, (done_out, w) = jax.vjp(f, pk, G, z, offs, a_tex, has_aux=True)
        dot_out = dot_in + jnp.sum(ct * dacc, axis=-1)
        want = vjp((ct, base - dot_out))
        (lt, dn, dot), (g_pk, g_G, g_z, (g_offs, g_atex)) = composite._chunk_contrib_bwd(
            st_, ctx, pk, G, z, offs, a_tex, gid, valid, log_t, done, ct, dot_in, base)
        terms = composite._contrib_terms(st_, ctx, pk, G, z, a_tex, gid, valid, log_t, done)
        got = jax.tree.map(np.asarray, ((lt, dn, dot), (g_pk, g_G, g_z, g_offs, g_atex)))
        want = jax.tree.map(np.asarray, ((log_t_out, done_out, dot_out), want))
        terms, w, done = jax.tree.map(np.asarray, (terms, w, done))
    # The cases the inputs are meant to reach.
    assert done_out[0, 2] and not done[0, 2], "pixel 2 stops inside the chunk"
    assert np.all(w[:, 0, 1] == 0), "pixel 1 had stopped before the chunk"
    assert np.any(terms.keep & (terms.a_raw > rendering.ALPHA_MAX)), "saturated pairs"
    assert np.any(terms.include & ~terms.keep), "skipped pairs"
    (lt, dn, dot), got = got
    (lt_w, dn_w, dot_w), want = want
    np.testing.assert_allclose(lt, lt_w, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(dn, dn_w)
    np.testing.assert_allclose(dot, dot_w, rtol=1e-12, atol=1e-12)
    for name, a, b in zip(("pk", "G", "z", "offs", "a_tex"), got, want):
        assert (a is None) == (b is None), name
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-10, err_msg=name)
    assert np.abs(got[1]).max() > 0 and np.abs(got[0]).max() > 0


@pytest.mark.parametrize("prefilter", [False, True])
def test_geometry_backward_matches_autodiff(prefilter):
    """:func:`kernel.chunk_geometry_bwd` gives autodiff's cotangent of the packed splats through
    :func:`kernel.chunk_geometry`: for rays that meet the splat planes (the 3D term or the screen-space
    low-pass winning; or the prefiltered kernel, inside and outside its screen support) and rays
    (nearly) parallel to them, in tiles at different image positions (the pixels share their
    offsets within the tile, as the renderer's do)."""
    rng = np.random.default_rng(5)
    B, P, c = 3, 20, 6
    F = COLS.width_prefilter if prefilter else COLS.width
    with jax.enable_x64(True):
        pk = rng.normal(size=(B, c, F))
        if prefilter:  # a positive definite quadratic form (p, r, t)
            pk[:, :, COLS.conic] = np.stack([rng.uniform(0.2, 1.0, (B, c)), rng.uniform(-0.1, 0.1, (B, c)),
                                                 rng.uniform(0.2, 1.0, (B, c))], axis=-1)
            # The screen support (radius 2 to 5 px about the centre): some pixels fall outside.
            a = rng.uniform(0.04, 0.25, (B, c))
            pk[:, :, COLS.support] = np.stack([a, 0.1 * a, a], axis=-1)
        c0 = COLS.c.start
        pk[:, :, :COLS.plane] *= 0.05                       # planes: (u, v) of order one
        pk[:, :, c0:c0 + 2] += rng.normal(size=(B, c, 2))
        pk[:, :, c0 + 2] = rng.uniform(0.5, 1.0, (B, c))
        pk[:, 0, [COLS.a.stop - 1, COLS.b.stop - 1, c0 + 2]] = 0.0  # s2 = 0: no ray meets this plane
        pk[:, :, COLS.mu] = rng.uniform(0.0, 5.0, (B, c, 2))
        corner = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 3.0]])    # the tiles' positions
        offset = rng.uniform(0.0, 2.0, (2, P))                      # the pixels' within a tile
        x = jnp.asarray(corner[:, :1] + offset[0])
        y = jnp.asarray(corner[:, 1:] + offset[1])
        pk = jnp.asarray(pk)
        g_G = jnp.asarray(rng.normal(size=(c, B, P)))
        g_z = jnp.asarray(rng.normal(size=(c, B, P)))
        (G, z), vjp = jax.vjp(lambda p: kernel.chunk_geometry(p, x, y, prefilter), pk)
        want = vjp((g_G, g_z))[0]
        geo = kernel.geometry_terms(pk, x, y, prefilter)
        got = kernel.chunk_geometry_bwd(pk, x, y, geo, g_G, g_z, prefilter)
        got, want, ok, use3, G = jax.tree.map(np.asarray, (got, want, geo.ok, geo.use3, geo.G))
    assert not ok[0].any() and ok[1:].all()
    if prefilter:
        assert np.all(G[0] == 0) and G[1:].max() > 0.1, "no coverage where the ray misses the plane"
        assert 0 < use3[1:].mean() < 1 and np.all(G[~use3] == 0), "cut outside the screen support"
        assert np.abs(got[..., COLS.conic]).max() > 0
    else:
        assert 0 < use3.mean() < 1, "both terms of the kernel should win somewhere"
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
