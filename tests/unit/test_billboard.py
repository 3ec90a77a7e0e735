"""Billboard coverage (``RenderConfig(coverage="billboard")``, :mod:`patexgs_jax.rendering.billboard`):
the render against the float64 reference, its exact square support and screen bounds, the tile cull,
the kernel's hand-written backward, finite differences and the hard cases' gradients."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hard_scenes as hs
from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, render_jit
from patexgs_jax.rendering import billboard, binning, chunks, kernel, projection
from patexgs_jax.rendering.projection import COLS
from render_cases import (
    CONFIGS,
    camera,
    check_matches_reference,
    cull_pairs,
    directional_fd_check,
    hard_scene,
    ref_render,
    scene,
    tile_render,
)

BB = RenderConfig(mip="none", coverage="billboard")
BB_MIP = RenderConfig(mip="nearest", coverage="billboard")


@pytest.mark.parametrize("name", ["billboard", "billboard-mip"])
def test_matches_reference(name):
    check_matches_reference(name)


def test_gradients_match_finite_differences():
    """The square's edge passes no gradient; where no pixel centre crosses an edge within the step
    the gradient is the finite difference's. The step is 1e-8 (float64): with 1e-6, a few of this
    scene's 1,760 pixels cross an edge along the direction, a jump of about 0.03 in the loss that
    swamps its derivative (the FD of the means was 13,810 for a gradient of 77.05; at 1e-7 they
    agree to 6e-6)."""
    textured, degree, cfg = CONFIGS["billboard"]
    sc = scene(21, textured, degree)
    for seed in range(3):
        directional_fd_check(sc, camera(), cfg, seed, h=1e-8, rtol=2e-4)


def _facing(alpha, scale=0.1, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), mean=(0.0, 0.0, 0.0), n_pad=4):
    """One billboard at ``mean`` (normal along z for the identity quaternion), padded to n_pad slots."""
    return Scene.from_arrays([list(mean)], [[scale, scale]], [list(quat)], [opacity], np.zeros((1, 1, 3)),
                             rgb_textures=[None], alpha_textures=[alpha], capacity=n_pad)


def _camera(eye=(0.0, 0.0, -2.0), target=(0.0, 0.0, 0.0), f=100.0, w=64, h=48):
    return Camera.from_intrinsics([f, f, w / 2, h / 2], look_at(eye, target), w, h)


def test_alpha_is_the_texture_on_the_square_and_zero_outside():
    """A billboard facing the camera, its alpha texture constant: alpha is exactly opacity * A on
    the pixels whose centres fall in the projected square (half side 3 s f / z = 15 px) and 0
    elsewhere: no falloff, no low-pass."""
    cam = _camera()
    sc = _facing(np.full((4, 4), 0.9))
    out = tile_render(sc, cam, BB, capacity=Capacity(pairs=1024))
    x = np.arange(64) + 0.5 - 32.0
    y = np.arange(48) + 0.5 - 24.0
    half = 3 * 0.1 * 100.0 / 2.0
    inside = (np.abs(y)[:, None] <= half) & (np.abs(x)[None, :] <= half)
    np.testing.assert_allclose(out.alpha, np.where(inside, 0.8 * 0.9, 0.0), atol=1e-6, rtol=0)
    np.testing.assert_allclose(out.depth, np.where(inside, 2.0, 0.0), atol=1e-5, rtol=0)
    assert inside.sum() == 30 * 30


@jax.jit
def _project(sc, cam):
    """The billboards' projection (one program, not one per operation)."""
    return projection.project(sc, cam, BB, None, None, projection.alpha_peak(sc))


def test_bounds_are_the_projected_square_and_clip_at_the_near_plane():
    """The screen box is the box of the square's projected corners; for a square that crosses the
    near plane, the box of its part beyond it, and every pixel the float64 reference covers lies
    inside the box (the renderer draws no pixel outside it)."""
    cam = _camera()
    sc = _facing(np.full((2, 2), 1.0), quat=(np.cos(0.3), 0.3, 0.5, 0.2))
    proj = _project(sc, cam)
    M, _, _ = jax.jit(projection.image_map)(sc, cam)
    h = billboard.HALF
    q = np.einsum("ij,kj->ki", np.asarray(M[0], np.float64), [[-h, -h, 1], [h, -h, 1], [h, h, 1], [-h, h, 1]])
    xy = q[:, :2] / q[:, 2:]
    got = np.asarray([b[0] for b in proj.bounds])
    want = np.array([xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()])
    np.testing.assert_allclose(got, want, atol=2e-3, rtol=0)
    assert np.all(got[[0, 2]] <= want[[0, 2]]) and np.all(got[[1, 3]] >= want[[1, 3]])

    # A large billboard tilted through the camera's plane: part of it behind the camera.
    for quat in [(np.cos(0.6), 0.0, np.sin(0.6), 0.0), (np.cos(0.7), np.sin(0.7), 0.0, 0.0)]:
        sc = _facing(np.full((2, 2), 1.0), scale=1.2, quat=quat, mean=(0.1, 0.0, -1.0))
        proj = _project(sc, cam)
        assert bool(proj.visible[0])
        xmin, xmax, ymin, ymax = (float(b[0]) for b in proj.bounds)
        ref = ref_render(sc, cam, BB)
        ii, jj = np.nonzero(ref["alpha"] > 0)
        assert ii.size > 0
        assert xmin <= jj.min() + 0.5 and jj.max() + 0.5 <= xmax
        assert ymin <= ii.min() + 0.5 and ii.max() + 0.5 <= ymax
        out = tile_render(sc, cam, BB, capacity=Capacity(pairs=1024))
        np.testing.assert_allclose(out.alpha, ref["alpha"], atol=1e-5, rtol=0)


@functools.partial(jax.jit, static_argnames=("config",))
def _cull_check(sc, cam, config, g, px, py, real):
    """For (splat g, tile (px, py)) pairs: whether the billboard tile test keeps each, and whether
    the compositor's kernel covers a pixel of the tile beyond the near plane with alpha >= 1/255."""
    ts = config.tile_size
    peak = projection.alpha_peak(sc)
    proj = projection.project(sc, cam, config, None, None, peak)
    F = projection.FOOTPRINT
    fp = [proj.footprint[:, i][g] for i in range(F.width)]
    keep = billboard.square_touches(fp[F.a], fp[F.b], fp[F.c], fp[F.side], px, py, ts, binning.TOUCH_GROW)
    pk = proj.packed[g][:, None, :]
    iy, ix = jnp.divmod(jnp.arange(ts * ts), ts)
    x = (px[:, None] * ts + ix).astype(jnp.float32) + 0.5
    y = (py[:, None] * ts + iy).astype(jnp.float32) + 0.5
    G, z = kernel.chunk_geometry(pk, x, y, billboard=True)
    bound = chunks.cols(pk)[COLS.opacity] * peak[g][None, :, None] * G
    reach = jnp.any((bound >= 1.0 / 255.0) & (z > config.near), axis=(0, 2)) & real
    return keep & real, reach


@pytest.mark.parametrize("case", ["edge_on", "needle", "tiny_huge", "near_plane", "focal"])
def test_tile_cull_keeps_every_pair_that_can_contribute(case):
    """No (billboard, tile) pair of a screen box that the square test leaves out is covered by the
    compositor's own float32 kernel, on the hard cases; and the test does leave pairs out."""
    cfg = RenderConfig(mip="none", coverage="billboard", near=hs.NEAR)
    dropped = 0
    for seed, knob in [(0, 0.0), (1, 0.5), (2, 1.0)]:
        sc, cam, _ = hs.build(case, seed, knob)
        keep, reach, _ = cull_pairs(sc, cam, cfg, check=_cull_check)
        assert not np.any(reach & ~keep), (case, seed, knob)
        dropped += int(np.sum(~keep))
    if case in ("edge_on", "needle"):
        assert dropped > 0, "thin or edge-on squares leave most of their boxes' tiles"


def test_geometry_backward_matches_autodiff():
    """:func:`kernel.chunk_geometry_bwd` with ``billboard`` gives autodiff's cotangent through
    :func:`kernel.chunk_geometry`: the depth's, inside the square; nothing through G or the centre."""
    rng = np.random.default_rng(7)
    B, P, c = 3, 20, 6
    with jax.enable_x64(True):
        pk = rng.normal(size=(B, c, COLS.width))
        c0 = COLS.c.start
        pk[:, :, :COLS.plane] *= 0.3
        pk[:, :, c0:c0 + 2] += rng.normal(size=(B, c, 2))
        pk[:, :, c0 + 2] = rng.uniform(0.5, 1.0, (B, c))
        pk[:, 0, [COLS.a.stop - 1, COLS.b.stop - 1, c0 + 2]] = 0.0  # no ray meets this plane
        x = jnp.asarray(np.array([[0.0], [2.0], [1.0]]) + rng.uniform(0.0, 2.0, (1, P)))
        y = jnp.asarray(np.array([[0.0], [0.0], [3.0]]) + rng.uniform(0.0, 2.0, (1, P)))
        pk = jnp.asarray(pk)
        g_G = jnp.asarray(rng.normal(size=(c, B, P)))
        g_z = jnp.asarray(rng.normal(size=(c, B, P)))
        @jax.jit  # one program, not one per operation
        def both(pk):
            (G, z), vjp = jax.vjp(lambda p: kernel.chunk_geometry(p, x, y, billboard=True), pk)
            want = vjp((g_G, g_z))[0]
            geo = kernel.geometry_terms(pk, x, y, False, True)
            return kernel.chunk_geometry_bwd(pk, x, y, geo, g_G, g_z, billboard=True), want, G

        got, want, G = jax.tree.map(np.asarray, both(pk))
    assert 0 < G.mean() < 1 and set(np.unique(G)) <= {0.0, 1.0}
    assert np.all(G[0] == 0), "no coverage where the ray misses the plane"
    assert np.abs(got[..., :COLS.plane]).max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("case", ["edge_on", "tiny_and_huge", "needles", "near_plane", "saturated"])
def test_hard_case_gradients_finite(case):
    """Every gradient finite on the hard scenes, with the billboard's mipmaps."""
    sc = hard_scene(case)
    cam = Camera.from_intrinsics([40.0, 42.0, 22.3, 17.8], look_at((0.0, 0.0, -3.0), (0.0, 0.0, 1.0)), 44, 36)

    def loss(s):
        out = render_jit(s, cam, config=BB_MIP, capacity=Capacity(pairs=1024))
        return jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.normal) + jnp.sum(out.alpha)

    val, g = jax.value_and_grad(loss)(sc)
    assert np.isfinite(float(val))
    for path, leaf in jax.tree_util.tree_leaves_with_path(g):
        assert np.all(np.isfinite(np.asarray(leaf))), jax.tree_util.keystr(path)
