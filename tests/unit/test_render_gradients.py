"""The renderer's gradients: float64 finite differences, every gradient finite in hard cases, and the
compositor's and the kernel's hand-derived backward passes against autodiff."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from patexgs_jax import Camera, Capacity, RenderConfig, Scene, look_at, render_jit
from patexgs_jax.render import ALPHA_MAX
from patexgs_jax.rendering import chunks, composite, kernel
from patexgs_jax.rendering.projection import COLS
from render_cases import HARD_CASES, check_gradients_match_finite_differences, check_hard_case_gradients_finite


# ---------------------------------------------------------------------------------------------
# Gradients: float64 finite differences
# ---------------------------------------------------------------------------------------------
def test_gradients_match_finite_differences():
    """PATexGS's own configuration; the baseline and trilinear mipmaps are in
    tests/integration/test_render_sweeps.py."""
    check_gradients_match_finite_differences("prefilter")


# ---------------------------------------------------------------------------------------------
# Hard cases: every gradient finite
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_case_gradients_finite(case):
    """Nearest mipmaps; trilinear ones are in tests/integration/test_render_sweeps.py."""
    check_hard_case_gradients_finite(case, "nearest")


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
    # The chunk reads only the banks' texture flags; the binning fields are a one-tile placeholder.
    ctx = chunks.CompositeInputs(
        ids_sorted=jnp.asarray(gid), tile_start=jnp.zeros(1, jnp.int32), binned=jnp.full(1, c, jnp.int32),
        peak=jnp.ones(c, jnp.float32), flag=jnp.asarray(True),
        rgb_has=jnp.asarray(np.arange(c) % 3 != 1), alpha_has=jnp.asarray(np.arange(c) % 4 != 2))
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

        @jax.jit  # one program, not one per operation
        def both(pk, G, z, offs, a_tex):
            (dacc, log_t_out), vjp, (done_out, w) = jax.vjp(f, pk, G, z, offs, a_tex, has_aux=True)
            dot_out = dot_in + jnp.sum(ct * dacc, axis=-1)
            want = vjp((ct, base - dot_out))
            (lt, dn, dot), (g_pk, g_G, g_z, (g_offs, g_atex)) = composite._chunk_contrib_bwd(
                st_, ctx, pk, G, z, offs, a_tex, gid, valid, log_t, done, ct, dot_in, base)
            terms = composite._contrib_terms(st_, ctx, pk, G, z, a_tex, gid, valid, log_t, done)
            return ((lt, dn, dot), (g_pk, g_G, g_z, g_offs, g_atex)), ((log_t_out, done_out, dot_out), want), terms, w

        got, want, terms, w = jax.tree.map(np.asarray, both(pk, G, z, offs, a_tex))
        done_out = want[0][1]
        done = np.asarray(done)
    # The cases the inputs are meant to reach.
    assert done_out[0, 2] and not done[0, 2], "pixel 2 stops inside the chunk"
    assert np.all(w[:, 0, 1] == 0), "pixel 1 had stopped before the chunk"
    assert np.any(terms.keep & (terms.a_raw > ALPHA_MAX)), "saturated pairs"
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
        @jax.jit  # one program, not one per operation
        def both(pk):
            _, vjp = jax.vjp(lambda p: kernel.chunk_geometry(p, x, y, prefilter), pk)
            geo = kernel.geometry_terms(pk, x, y, prefilter)
            got = kernel.chunk_geometry_bwd(pk, x, y, geo, g_G, g_z, prefilter)
            return got, vjp((g_G, g_z))[0], geo.ok, geo.use3, geo.G

        got, want, ok, use3, G = jax.tree.map(np.asarray, both(pk))
    assert not ok[0].any() and ok[1:].all()
    if prefilter:
        assert np.all(G[0] == 0) and G[1:].max() > 0.1, "no coverage where the ray misses the plane"
        assert 0 < use3[1:].mean() < 1 and np.all(G[~use3] == 0), "cut outside the screen support"
        assert np.abs(got[..., COLS.conic]).max() > 0
    else:
        assert 0 < use3.mean() < 1, "both terms of the kernel should win somewhere"
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
