"""The renderer tests' shared scenes, camera and configurations (tests/unit/test_render.py,
test_render_gradients.py, test_texture_lookup.py, test_coverage.py).

Compiles are the expensive part on CPU: every scene here has one capacity (C=48), every camera one
image size (44x36, a partial tile on each edge), every render one Capacity, so compiled renderers are
shared across tests (one per configuration and dtype).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import hard_scenes as hs
from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, random_scene, render_jit
from patexgs_jax.rendering import binning, chunks, kernel, projection
from patexgs_jax.rendering.projection import COLS
from render_reference import reference_render, scene_to_reference

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
    "billboard": (True, 1, RenderConfig(mip="none", coverage="billboard")),
    "billboard-mip": (True, 1, RenderConfig(mip="nearest", coverage="billboard")),
}


def single_splat_scene(tex_rgb, tex_alpha=None, scale=1.0, n_pad=C):
    """One splat facing the camera (normal along z) at the origin, padded to capacity C."""
    q = [1.0, 0.0, 0.0, 0.0]
    sh = np.zeros((1, 1, 3))
    return Scene.from_arrays([[0.0, 0.0, 0.0]], [[scale, scale]], [q], [1.0], sh,
                             rgb_textures=[tex_rgb], alpha_textures=[tex_alpha], capacity=n_pad)


# ---------------------------------------------------------------------------------------------
# Checks run over configurations: a few in tests/unit, the rest in tests/integration/test_render_sweeps.py
# ---------------------------------------------------------------------------------------------
def check_matches_reference(name):
    """The render of configuration ``name`` (``CONFIGS``) against the float64 brute-force reference."""
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


def _fd_loss(s, cam, wts, cfg):
    """The finite-difference checks' loss: every output of the render, weighted."""
    out = render_jit(s, cam, config=cfg, capacity=CAP)
    return jnp.sum(out.rgb * wts) + jnp.sum(out.alpha) + 0.1 * jnp.sum(out.depth) + jnp.sum(out.distortion)


_fd_grad = jax.jit(jax.grad(_fd_loss), static_argnames=("cfg",))


def _fd_value(s, cam, wts, cfg) -> float:
    """:func:`_fd_loss`'s value, summed in numpy from ``render_jit``'s outputs: the render is the
    program the other checks of the configuration run (float64, ``CAP``), not one of its own."""
    out = jax.tree_util.tree_map(np.asarray, render_jit(s, cam, config=cfg, capacity=CAP))
    return float(np.sum(out.rgb * wts) + np.sum(out.alpha) + 0.1 * np.sum(out.depth) + np.sum(out.distortion))


def directional_fd_check(sc, cam, cfg, seed, h=1e-6, rtol=2e-4):
    """The gradient of :func:`_fd_loss` (float64) along a random direction against the central
    difference with step h (the gradient one program, whatever the seed)."""
    with jax.enable_x64(True):
        sc64 = sc.astype(jnp.float64)
        rng = np.random.default_rng(seed)
        wts = jnp.asarray(rng.uniform(0.5, 1.5, (H, W, 3)))
        g = _fd_grad(sc64, cam, wts, cfg=cfg)
        leaves, treedef = jax.tree_util.tree_flatten(sc64)
        leaves = [np.asarray(x) for x in leaves]
        gleaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(g)]
        frozen = {id(x) for x in (sc64.active,) + (() if sc64.filter3d is None else (sc64.filter3d,)) + tuple(
            getattr(b, f) for b in (sc64.rgb, sc64.alpha) if b is not None for f in ("bucket", "slot", "size"))}
        dirs = [np.zeros_like(x) if id(y) in frozen else rng.normal(size=x.shape)
                for x, y in zip(leaves, jax.tree_util.tree_leaves(sc64))]
        analytic = sum(float(np.sum(a * d)) for a, d in zip(gleaves, dirs))

        def shift(eps):
            return jax.tree_util.tree_unflatten(treedef, [x + eps * d for x, d in zip(leaves, dirs)])

        w64 = np.asarray(wts)
        fd = (_fd_value(shift(h), cam, w64, cfg) - _fd_value(shift(-h), cam, w64, cfg)) / (2 * h)
        assert np.isfinite(analytic)
        assert abs(analytic - fd) <= rtol * abs(fd) + 1e-6, (analytic, fd)


def check_gradients_match_finite_differences(name):
    """Directional float64 finite differences of configuration ``name`` against its gradient."""
    textured, degree, cfg = CONFIGS[name]
    sc = scene(21, textured, degree)
    # The prefilter composites more faint pairs (a skipped pair's alpha jumps from 0 to 1/255 times
    # its coverage): a smaller step keeps the difference off those jumps.
    h = 1e-7 if cfg.coverage == "prefilter" else 1e-6
    for seed in range(3):
        directional_fd_check(sc, camera(), cfg, seed, h=h)


HARD_CASES = ["edge_on", "tiny_and_huge", "needles", "near_plane", "saturated"]


def hard_scene(case):
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


def check_hard_case_gradients_finite(case, mip):
    """Every gradient of a loss of every output finite on the hard scene ``case`` (``hard_scene``)."""
    sc = hard_scene(case)
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


# ---------------------------------------------------------------------------------------------
# Pairs left out of a splat's screen box (binning.tile_touches), against the compositor's kernel
# ---------------------------------------------------------------------------------------------
CULL_PAIRS = 8192  # pairs checked per scene (padded): one compile for every scene of a shape


@functools.partial(jax.jit, static_argnames=("config",))
def cull_check(sc, cam, config, g, px, py, real):
    """For the (splat g, tile (px, py)) pairs (real ones marked): whether tile_touches keeps each,
    and whether the compositor's own kernel reaches alpha 1/255 (bounded by each splat's largest
    alpha texel) at a pixel of the tile in front of the near plane."""
    ts = config.tile_size
    prefilter = config.coverage == "prefilter"
    peak = projection.alpha_peak(sc)
    proj = projection.project(sc, cam, config, None, None, peak)
    keep = binning.tile_touches([proj.footprint[:, i][g] for i in range(projection.FOOTPRINT.width)],
                                px, py, ts, not prefilter)
    pk = proj.packed[g][:, None, :]                                        # (N, 1, F): one slot a "tile"
    iy, ix = jnp.divmod(jnp.arange(ts * ts), ts)
    x = (px[:, None] * ts + ix).astype(jnp.float32) + 0.5
    y = (py[:, None] * ts + iy).astype(jnp.float32) + 0.5
    G, z = kernel.chunk_geometry(pk, x, y, prefilter)                      # (1, N, P)
    col = chunks.cols(pk)
    bound = col[COLS.opacity] * peak[g][None, :, None] * G
    floor = kernel.alpha_min(chunks.Static(config, 1, 1, False, False), pk)
    reach = jnp.any((bound >= floor) & (z > config.near), axis=(0, 2)) & real
    return keep & real, reach


@functools.partial(jax.jit, static_argnames=("config",))
def _screen_boxes(sc, cam, config):
    """The splats' tile ranges (tx0, tx1, ty0, ty1, ok), each (C,), as the renderer bins them (one
    program, not one per operation)."""
    proj = projection.project(sc, cam, config, None, None, projection.alpha_peak(sc))
    ts = config.tile_size
    return binning.tile_ranges(proj.bounds, proj.visible, ts, -(-cam.width // ts), -(-cam.height // ts))


def cull_pairs(sc, cam, config, check=None):
    """(kept, reached, boxed): tile_touches' verdicts and the kernel's over every pair of the screen
    boxes of a view (kept, reached (N,) bool; N = boxed); ``check``: the pair test, :func:`cull_check`
    unless given (same arguments)."""
    tx0, tx1, ty0, ty1, ok = (np.asarray(a) for a in _screen_boxes(sc, cam, config))
    pairs = [(i, x, y) for i in np.flatnonzero(ok) for y in range(ty0[i], ty1[i]) for x in range(tx0[i], tx1[i])]
    n = len(pairs)
    assert 0 < n <= CULL_PAIRS
    g, px, py = (np.pad(np.asarray(v, np.int32), (0, CULL_PAIRS - n)) for v in zip(*pairs))
    keep, reach = (check or cull_check)(sc, cam, config, g, px, py, np.arange(CULL_PAIRS) < n)
    return np.asarray(keep)[:n], np.asarray(reach)[:n], n


CULL_CONFIGS = [RenderConfig(coverage="prefilter"), RenderConfig(coverage="lowpass")]


def check_tile_cull_keeps_every_pair(case):
    """No (splat, tile) pair that tile_touches leaves out reaches alpha 1/255 at a pixel of its tile in
    front of the near plane, by the compositor's own float32 kernel, on the hard cases (splats
    edge-on, needles, tiny and huge, across the near plane, far, at extreme focal lengths), in both
    coverage modes."""
    for seed, knob in [(0, 0.0), (1, 0.5), (2, 1.0)]:
        sc, cam, _ = hs.build(case, seed, knob)
        for cfg in CULL_CONFIGS:
            keep, reach, _ = cull_pairs(sc, cam, cfg)
            assert not np.any(reach & ~keep), (case, seed, knob, cfg.coverage)
