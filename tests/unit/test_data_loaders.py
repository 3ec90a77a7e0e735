"""Tests of patexgs_jax.data: COLMAP / LLFF / transforms.json loaders, views, caches, bad input."""

from __future__ import annotations

import math
import os
import stat
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import patexgs_jax.data as data
from data_builders import (  # noqa: E402
    camera_params,
    make_colmap_scene,
    opengl_c2w,
    random_image,
    ring_poses,
    save_png,
    write_json,
    write_llff,
)
from locations import BEER, REPO
from patexgs_jax._pycolmap import pycolmap  # noqa: E402  (keeps the fatal-signal handlers, see there)
from patexgs_jax.camera import Camera
from patexgs_jax.data import DatasetError, DatasetWarning
from patexgs_jax.data.colmap_binary import validate_binary_model
from patexgs_jax.data.nerf import distort_normalized, read_ply_points


def f32(x):
    return np.asarray(x, np.float32)


def project(camera: Camera, X) -> np.ndarray:
    """(N, 2) continuous pixel coordinates of (N, 3) world points (float64 on the host)."""
    X = np.atleast_2d(np.asarray(X, np.float64))
    w2c = np.asarray(camera.world_to_camera, np.float64)
    p = X @ w2c[:3, :3].T + w2c[:3, 3]
    q = p @ np.asarray(camera.K, np.float64).T
    return q[:, :2] / q[:, 2:3]


# ----------------------------------------------------------------------------------------------------
# COLMAP round trips
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_colmap_roundtrip_exact(tmp_path, text):
    sc = make_colmap_scene(tmp_path, models=("PINHOLE", "SIMPLE_PINHOLE"), n_images=10, text=text)
    ds = data.load(tmp_path, test_every=3, cache_dir=tmp_path / "cache")
    assert ds.format == "colmap" and ds.factor == 1 and ds.points_source == "sfm"
    names = sorted(sc["names"])
    assert [v.name for v in ds.test_views] == names[0::3]
    assert [v.name for v in ds.train_views] == [n for i, n in enumerate(names) if i % 3]
    for v in ds.views:
        np.testing.assert_array_equal(np.asarray(v.camera.K), f32(sc["K"][v.name]))
        np.testing.assert_allclose(np.asarray(v.camera.world_to_camera), sc["w2c"][v.name], atol=1e-6)
        assert (v.camera.width, v.camera.height) == (40, 30)
        np.testing.assert_array_equal(v.image, sc["image"][v.name].astype(np.float32) / 255.0)
        assert v.image.dtype == np.float32 and v.image.shape == (30, 40, 3)
    np.testing.assert_array_equal(ds.points, f32(sc["points"]))
    np.testing.assert_array_equal(ds.colors, sc["colors"].astype(np.float32) / 255.0)
    assert ds.points.dtype == np.float32 and ds.colors.dtype == np.float32
    assert not (tmp_path / "cache").exists()  # pinhole: nothing to cache


def test_colmap_sparse_without_0_and_no_split(tmp_path):
    make_colmap_scene(tmp_path, n_images=4, sparse_sub="sparse")
    ds = data.load(tmp_path, test_every=0)
    assert len(ds.train_views) == 4 and len(ds.test_views) == 0
    ds = data.load(tmp_path, test_every=None)
    assert len(ds.test_views) == 0


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"])
def test_colmap_distorted_models_are_undistorted_and_cached(tmp_path, capfd, model):
    W, H = 48, 36

    def smooth(k, W_, H_):  # a smooth image of the *distorted* camera: colour = f(normalised ray)
        cam = pycolmap.Camera.create_from_model_name(1, model, 50.0, W_, H_)
        cam.params = camera_params(model, W_, H_)
        jj, ii = np.meshgrid(np.arange(W_) + 0.5, np.arange(H_) + 0.5)
        xy = cam.cam_from_img(np.stack([jj.ravel(), ii.ravel()], -1))
        return _pattern(xy[:, 0], xy[:, 1]).reshape(H_, W_, 3)

    sc = make_colmap_scene(tmp_path / "scene", models=(model,), n_images=3, W=W, H=H, image_fn=smooth)
    cache = tmp_path / "cache"
    ds = data.load(tmp_path / "scene", cache_dir=cache, test_every=0)
    err = capfd.readouterr().err
    assert "undistorting" in err and model in err
    und_dir = Path(ds.info["undistorted_dir"])
    assert und_dir.is_relative_to(cache) and (und_dir / "COMPLETE").is_file()
    assert not list(und_dir.parent.glob(".tmp-*"))
    expect = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), sc["rec"].cameras[1])
    fx, fy, cx, cy = expect.params
    for v in ds.views:
        np.testing.assert_allclose(np.asarray(v.camera.K), [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rtol=1e-6)
        assert (v.camera.width, v.camera.height) == (expect.width, expect.height)
        np.testing.assert_allclose(np.asarray(v.camera.world_to_camera), sc["w2c"][v.name], atol=1e-6)
        # The undistorted image is the same smooth function of the pinhole ray (bilinear error only).
        jj, ii = np.meshgrid(np.arange(v.camera.width) + 0.5, np.arange(v.camera.height) + 0.5)
        want = _pattern((jj - cx) / fx, (ii - cy) / fy) / 255.0
        inner = (slice(2, -2), slice(2, -2))
        assert np.abs(v.image[inner] - want[inner]).mean() < 0.02
    mtime = und_dir.stat().st_mtime_ns
    ds2 = data.load(tmp_path / "scene", cache_dir=cache, test_every=0)
    assert "undistorting" not in capfd.readouterr().err
    assert ds2.info["undistorted_dir"] == str(und_dir) and und_dir.stat().st_mtime_ns == mtime
    assert len(list((cache).rglob("COMPLETE"))) == 1


def test_distorted_model_with_images_n_folder(tmp_path):
    sc = make_colmap_scene(tmp_path, models=("OPENCV",), n_images=3, W=48, H=36)
    for k, _ in enumerate(sc["names"]):
        save_png(tmp_path / "images_2" / f"x{k}.png", random_image(24, 18, k))  # other names: by order
    full = data.load(tmp_path, factor=1, test_every=0, cache_dir=tmp_path / "c", verbose=False)
    half = data.load(tmp_path, factor=2, test_every=0, cache_dir=tmp_path / "c", verbose=False)
    for a, b in zip(full.views, half.views):
        assert b.image_path.parent.parent.name.startswith("images_2-")  # undistorted from images_2/
        np.testing.assert_allclose(np.asarray(b.camera.K)[:2, :2], np.asarray(a.camera.K)[:2, :2] / 2, rtol=1e-6)
        assert abs(b.camera.width - a.camera.width / 2) <= 1 and b.image.shape == (b.camera.height, b.camera.width, 3)


def _pattern(x, y):
    """uint8-ish RGB smooth pattern of normalised coordinates."""
    r = 127.5 + 100 * np.sin(3.0 * x)
    g = 127.5 + 100 * np.cos(2.5 * y)
    b = 127.5 + 80 * np.sin(2.0 * (x + y))
    return np.round(np.stack([r, g, b], -1)).astype(np.uint8)


def test_colmap_unsupported_model_names_it(tmp_path):
    make_colmap_scene(tmp_path, models=("EQUIRECTANGULAR",), n_images=2)
    with pytest.raises(DatasetError, match="EQUIRECTANGULAR"):
        data.load(tmp_path, cache_dir=tmp_path / "cache")


def test_undistortion_is_atomic_when_interrupted(tmp_path, monkeypatch):
    make_colmap_scene(tmp_path / "scene", models=("OPENCV",), n_images=2)
    real = pycolmap.undistort_images

    def interrupted(out, *a, **k):
        real(out, *a, **k)  # writes a partial output ...
        raise KeyboardInterrupt  # ... then the user presses Ctrl-C

    monkeypatch.setattr(pycolmap, "undistort_images", interrupted)
    with pytest.raises(KeyboardInterrupt):
        data.load(tmp_path / "scene", cache_dir=tmp_path / "cache", verbose=False)
    und = next((tmp_path / "cache").iterdir()) / "undistorted"
    assert list(und.iterdir()) == []  # neither a final folder nor a temporary one
    monkeypatch.setattr(pycolmap, "undistort_images", real)
    ds = data.load(tmp_path / "scene", cache_dir=tmp_path / "cache", verbose=False)
    assert len(ds.views) == 2 and ds.views[0].image.shape[2] == 3


# ----------------------------------------------------------------------------------------------------
# images_N selection and downsampling
# ----------------------------------------------------------------------------------------------------


def test_images_n_folder_is_used_with_actual_size_ratio(tmp_path):
    W, H = 41, 31
    sc = make_colmap_scene(tmp_path, models=("PINHOLE",), n_images=4, W=W, H=H)
    w2, h2 = 21, 16  # rounded up like the Mip-NeRF 360 folders (41 / 2 = 20.5, 31 / 2 = 15.5)
    small = {}
    for k, n in enumerate(sc["names"]):
        small[n] = random_image(w2, h2, seed=50 + k)
        save_png(tmp_path / "images_2" / n, small[n])
    ds = data.load(tmp_path, factor=2, test_every=0)
    for v in ds.views:
        K = sc["K"][v.name]
        np.testing.assert_allclose(np.asarray(v.camera.K), np.diag([w2 / W, h2 / H, 1]) @ K, rtol=1e-6)
        assert (v.camera.width, v.camera.height) == (w2, h2)
        np.testing.assert_array_equal(v.image, small[v.name] / np.float32(255))
        assert v.image_path.parent.name == "images_2"


def test_images_n_with_other_names_matched_by_order(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=3, W=40, H=30)
    for k, _ in enumerate(sc["names"]):
        save_png(tmp_path / "images_2" / f"frame{k:05d}.jpg.png", random_image(20, 15, seed=k))
    ds = data.load(tmp_path, factor=2, test_every=0)
    assert [v.image_path.name for v in ds.views] == [f"frame{k:05d}.jpg.png" for k in range(3)]


def test_downsampling_from_images_is_box_and_pixel_centre_exact(tmp_path):
    W, H = 43, 30
    sc = make_colmap_scene(tmp_path, n_images=3, W=W, H=H)
    ds = data.load(tmp_path, factor=4, test_every=0)
    assert ds.factor == 4
    for v in ds.views:
        assert (v.camera.width, v.camera.height) == (W // 4, H // 4)
        np.testing.assert_allclose(np.asarray(v.camera.K), np.diag([0.25, 0.25, 1]) @ sc["K"][v.name], rtol=1e-6)
        full = sc["image"][v.name].astype(np.float64) / 255.0
        want = full[: H // 4 * 4, : W // 4 * 4].reshape(H // 4, 4, W // 4, 4, 3).mean((1, 3))
        np.testing.assert_allclose(v.image, want, atol=1e-6)


def test_default_factors_for_mipnerf360_names(tmp_path):
    assert data.default_factor(tmp_path / "garden") == 4 and data.default_factor(tmp_path / "bicycle") == 4
    assert data.default_factor(tmp_path / "room") == 2 and data.default_factor(tmp_path / "bonsai") == 2
    assert data.default_factor(tmp_path / "beer") == 1
    make_colmap_scene(tmp_path / "counter", n_images=2, W=40, H=30)
    assert data.load(tmp_path / "counter").views[0].camera.width == 20


def _area_matrix(n_out: int, n_in: int) -> np.ndarray:
    """(n_out, n_in) weights of an area filter: output pixel j averages input [j s, (j + 1) s), s = n_in / n_out."""
    s = n_in / n_out
    A = np.zeros((n_out, n_in))
    for j in range(n_out):
        lo, hi = j * s, (j + 1) * s
        for i in range(int(np.floor(lo)), min(int(np.ceil(hi)), n_in)):
            A[j, i] = (min(hi, i + 1) - max(lo, i)) / s
    return A


def test_images_wider_than_1600_are_resized_to_1600_by_area_and_said(tmp_path, capfd):
    W, H = 1700, 40
    sc = make_colmap_scene(tmp_path / "wide", n_images=2, W=W, H=H)
    ds = data.load(tmp_path / "wide", test_every=0)
    w, h = 1600, H * 1600 // W  # 37: the 3DGS rule (width 1600, height truncated)
    said = capfd.readouterr().err
    assert f"training at {w}x{h}" in said and f"{W}x{H}" in said and "--factor 1" in said
    assert said.count("wider than 1600") == 1  # one line for the dataset
    assert ds.factor == pytest.approx(W / 1600)
    Ay, Ax = _area_matrix(h, H), _area_matrix(w, W)
    for v in ds.views:
        assert (v.camera.width, v.camera.height) == (w, h)
        np.testing.assert_allclose(np.asarray(v.camera.K), np.diag([w / W, h / H, 1]) @ sc["K"][v.name], rtol=1e-6)
        full = sc["image"][v.name].astype(np.float64) / 255.0
        want = np.einsum("ai,ijc,bj->abc", Ay, full, Ax, optimize=True)
        np.testing.assert_allclose(v.image, want, atol=2e-6)
    # --factor 1 keeps the full size, silently; 1600 px or less is never resized.
    full = data.load(tmp_path / "wide", factor=1, test_every=0)
    assert full.views[0].image.shape == (H, W, 3) and full.factor == 1
    make_colmap_scene(tmp_path / "narrow", n_images=2, W=1600, H=30)
    assert data.load(tmp_path / "narrow", test_every=0).views[0].camera.width == 1600
    assert "wider than" not in capfd.readouterr().err


def test_resolution_rule_keeps_mipnerf360_factors_and_covers_llff(tmp_path, capfd):
    make_colmap_scene(tmp_path / "garden", n_images=2, W=1700, H=40)
    assert data.load(tmp_path / "garden", test_every=0).views[0].camera.width == 1700 // 4
    assert "wider than" not in capfd.readouterr().err
    assert data.default_resolution(tmp_path / "garden", None) == (4, None)
    assert data.default_resolution(tmp_path / "phone", None) == (1, data.DEFAULT_MAX_WIDTH)
    assert data.default_resolution(tmp_path / "phone", 2) == (2, None)
    W, H = 1800, 30
    root = tmp_path / "llff"
    poses = ring_poses(3)
    for k in range(3):
        save_png(root / "images" / f"IMG_{k}.png", random_image(W, H, seed=k))
    write_llff(root, [np.linalg.inv(p) for p in poses], (H, W, 900.0), [(0.5, 9.0)] * 3)
    ds = data.load(root, test_every=0)
    v = ds.views[0]
    assert (v.camera.width, v.camera.height) == (1600, H * 1600 // W) and v.image.shape == (26, 1600, 3)
    np.testing.assert_allclose(np.asarray(v.camera.K)[0, 0], 900.0 * 1600 / W, rtol=1e-6)
    assert "training at 1600x26" in capfd.readouterr().err


# ----------------------------------------------------------------------------------------------------
# view.scaled, zoom-out helper, lazy loading, normalisation
# ----------------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(s=st.sampled_from([2, 3, 4, 8]), fx=st.floats(20, 500), fy=st.floats(20, 500), cx=st.floats(0, 64),
       cy=st.floats(0, 48), X=st.tuples(*[st.floats(-1, 1)] * 2), z=st.floats(0.5, 10), k=st.integers(0, 5))
def test_scaled_camera_projects_consistently(s, fx, fy, cx, cy, X, z, k):
    w2c = ring_poses(6)[k]
    cam = Camera.from_intrinsics((fx, fy, cx, cy), w2c, 64, 48)
    p_cam = np.array([X[0] * z, X[1] * z, z])
    Xw = np.linalg.inv(w2c)[:3, :3] @ p_cam + np.linalg.inv(w2c)[:3, 3]
    np.testing.assert_allclose(project(cam.scaled(s), Xw), project(cam, Xw) / s, rtol=1e-5, atol=1e-3)


def test_view_scaled_image_and_zoom_out_helper(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=4, W=37, H=29)
    ds = data.load(tmp_path, test_every=2)
    v = ds.test_views[0]
    for s in (2, 3, 4):
        vs = v.scaled(s)
        assert (vs.camera.width, vs.camera.height) == (37 // s, 29 // s) and vs.scale == s and vs.name == v.name
        full = sc["image"][v.name].astype(np.float64) / 255.0
        want = full[: 29 // s * s, : 37 // s * s].reshape(29 // s, s, 37 // s, s, 3).mean((1, 3))
        np.testing.assert_allclose(vs.image, want, atol=1e-6)
        # A pixel centre of the scaled view is the centre of its s x s block in the original view.
        np.testing.assert_allclose(np.asarray(vs.camera.K)[:2, 2] * s, np.asarray(v.camera.K)[:2, 2], rtol=1e-6)
    z = ds.zoom_out_views()
    assert sorted(z) == [2, 4, 8] and all(len(z[f]) == len(ds.test_views) for f in z)
    assert z[4][1].camera.width == 37 // 4 and z[8][0].image.shape == (29 // 8, 37 // 8, 3)
    assert data.zoom_out_views(ds.train_views, (2,))[2][0].scale == 2


def test_lazy_loading_respects_the_cache_bound(tmp_path):
    make_colmap_scene(tmp_path, n_images=9, W=16, H=12)
    ds = data.load(tmp_path, test_every=0, image_cache_size=3)
    cache = ds.image_cache
    assert len(cache) == 0 and cache.misses == 0  # nothing is read at load time
    for v in ds.views:
        _ = v.image
        assert len(cache) <= 3
    assert cache.misses == 9
    _ = ds.views[-1].image
    assert cache.hits == 1
    _ = ds.views[0].image  # evicted -> reloaded
    assert cache.misses == 10
    with pytest.raises(ValueError):
        ds.views[0].image[0, 0, 0] = 1.0  # cached arrays are read-only
    uncached = data.load(tmp_path, test_every=0, image_cache_size=0)
    _ = uncached.views[0].image
    assert len(uncached.image_cache) == 0


def test_image_cache_never_holds_more_than_its_limits():
    import threading

    def img(k):  # a loader of a 1200-byte image
        return lambda: np.full((10, 10, 3), k, np.float32)

    by_count = data.ImageCache(maxsize=3, max_bytes=None)
    by_bytes = data.ImageCache(maxsize=100, max_bytes=2 * 1200 + 100)
    rng = np.random.default_rng(0)

    def hammer(cache, seed):
        r = np.random.default_rng(seed)
        for _ in range(300):
            k = int(r.integers(0, 12))
            assert float(cache.get(k, img(k))[0, 0, 0]) == k
            assert len(cache) <= cache.maxsize
            assert cache.max_bytes is None or cache.nbytes <= cache.max_bytes

    for cache, limit in ((by_count, 3), (by_bytes, 2)):
        threads = [threading.Thread(target=hammer, args=(cache, int(rng.integers(1 << 30)))) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert 1 <= len(cache) <= limit and cache.nbytes == sum(cache._items[k].nbytes for k in cache._items)
    assert by_bytes.misses > 12  # evictions happened and were reloaded
    # An image larger than the byte bound is returned but not kept.
    tiny = data.ImageCache(maxsize=5, max_bytes=100)
    assert tiny.get("big", img(1)).shape == (10, 10, 3) and len(tiny) == 0 and tiny.nbytes == 0
    with pytest.raises(ValueError, match="bytes"):
        data.ImageCache(maxsize=2, max_bytes=-1)


def test_dataset_image_cache_bound_in_bytes(tmp_path):
    make_colmap_scene(tmp_path, n_images=6, W=40, H=30)
    one = 40 * 30 * 3 * 4
    ds = data.load(tmp_path, test_every=0, image_cache_bytes=2 * one)
    for v in ds.views:
        _ = v.image
        assert len(ds.image_cache) <= 2 and ds.image_cache.nbytes <= 2 * one
    assert ds.image_cache.misses == 6 and len(ds.image_cache) == 2


def test_normalization_recorded_and_optional(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=6)
    ds = data.load(tmp_path, test_every=0)
    centers = np.stack([-w[:3, :3].T @ w[:3, 3] for w in sc["w2c"].values()])
    c = centers.mean(0)
    r = 1.1 * np.linalg.norm(centers - c, axis=1).max()
    n = ds.normalization
    np.testing.assert_allclose(n.center, c, atol=1e-9)
    assert n.radius == pytest.approx(r) and not n.applied
    np.testing.assert_array_equal(n.transform, np.eye(4))

    dn = data.load(tmp_path, test_every=0, normalize=True)
    m = dn.normalization
    assert m.applied and m.radius == 1.0 and m.original_radius == pytest.approx(r)
    np.testing.assert_allclose(m.center, 0, atol=1e-12)
    np.testing.assert_allclose([np.linalg.norm(v.camera.center) for v in dn.views],
                               np.linalg.norm(centers - c, axis=1) / r, atol=1e-5)
    np.testing.assert_allclose(m.to_original_points(dn.points), sc["points"], atol=1e-5)
    for v, v0 in zip(dn.views, ds.views):
        np.testing.assert_allclose(m.to_original_world_to_camera(v.camera.world_to_camera),
                                   np.asarray(v0.camera.world_to_camera), atol=1e-5)
        # Pixels are invariant: the same point projects to the same place.
        np.testing.assert_allclose(project(v.camera, dn.points), project(v0.camera, ds.points), atol=2e-3)
    assert m.to_original_length(1.0) == pytest.approx(r)
    # With a split, 3DGS normalises with the training cameras only.
    split = data.load(tmp_path, test_every=2).normalization
    train_centers = np.stack([v.camera.center for v in data.load(tmp_path, test_every=2).train_views])
    np.testing.assert_allclose(split.center, train_centers.mean(0), atol=1e-5)


def test_read_image_modes(tmp_path):
    import PIL.Image as Image

    g = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    Image.fromarray(g, "L").save(tmp_path / "l.png")
    np.testing.assert_allclose(data.read_image(tmp_path / "l.png"), np.repeat(g[..., None], 3, -1) / 255.0)
    la = np.stack([g, np.full_like(g, 0)], -1)
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    np.testing.assert_allclose(data.read_image(tmp_path / "la.png", background=(0.2, 0.4, 0.6)),
                               np.broadcast_to([0.2, 0.4, 0.6], (3, 4, 3)), atol=1e-6)
    g16 = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000)
    Image.fromarray(g16).save(tmp_path / "g16.png")
    np.testing.assert_allclose(data.read_image(tmp_path / "g16.png")[..., 0], g16 / 65535.0, atol=1e-6)
    p = Image.fromarray(g, "L").convert("P")
    p.info["transparency"] = int(np.asarray(p)[0, 0])
    p.save(tmp_path / "p.png", transparency=int(np.asarray(p)[0, 0]))
    img = data.read_image(tmp_path / "p.png", background=(1, 0, 0))
    np.testing.assert_allclose(img[0, 0], [1, 0, 0])
    with pytest.raises(DatasetError, match="nothere.png"):
        data.read_image(tmp_path / "nothere.png")


def test_split_indices_protocol():
    tr, te = data.split_indices(71, 8)
    assert len(tr) == 62 and len(te) == 9 and list(te[:3]) == [0, 8, 16]
    assert len(data.split_indices(5, 0)[1]) == 0


# ----------------------------------------------------------------------------------------------------
# transforms.json
# ----------------------------------------------------------------------------------------------------


def _blender_scene(root: Path, n_train=4, n_test=2, W=32, H=24, angle=0.69):
    poses = ring_poses(n_train + n_test, seed=3)
    imgs = {}
    for split, idx in (("train", range(n_train)), ("test", range(n_train, n_train + n_test))):
        frames = []
        for k in idx:
            rgba = random_image(W, H, seed=200 + k, channels=4)
            save_png(root / split / f"r_{k}.png", rgba)
            imgs[f"{split}/r_{k}.png"] = (rgba, poses[k])
            frames.append({"file_path": f"./{split}/r_{k}", "rotation": 0.1, "transform_matrix": opengl_c2w(poses[k])})
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": angle, "frames": frames})
    return imgs


def test_transforms_blender_splits_angle_and_rgba(tmp_path):
    W, H, angle = 32, 24, 0.69
    imgs = _blender_scene(tmp_path, W=W, H=H, angle=angle)
    ds = data.load(tmp_path, num_random_points=500)
    assert ds.format == "nerf"
    assert [v.name for v in ds.train_views] == [f"train/r_{k}.png" for k in range(4)]
    assert [v.name for v in ds.test_views] == ["test/r_4.png", "test/r_5.png"]
    f = 0.5 * W / math.tan(0.5 * angle)
    for v in ds.views:
        rgba, w2c = imgs[v.name]
        np.testing.assert_allclose(np.asarray(v.camera.K), [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(v.camera.world_to_camera), w2c, atol=1e-5)
        a = rgba[..., 3:] / 255.0
        np.testing.assert_allclose(v.image, rgba[..., :3] / 255.0 * a + (1 - a), atol=1e-6)
        # The ring cameras look at ~ the origin: it projects near the image centre, in front (z > 0).
        assert np.linalg.norm(project(v.camera, [0, 0, 0])[0] - [W / 2, H / 2]) < 0.1 * f
    black = data.load(tmp_path, background=(0, 0, 0), num_random_points=10)
    rgba, _ = imgs[black.views[0].name]
    np.testing.assert_allclose(black.views[0].image, rgba[..., :3] / 255.0 * (rgba[..., 3:] / 255.0), atol=1e-6)
    # random initial points: documented count, seeded, inside the box around the cameras
    assert ds.points.shape == (500, 3) and ds.points_source == "random" and ds.colors.shape == (500, 3)
    np.testing.assert_array_equal(ds.points, data.load(tmp_path, num_random_points=500).points)
    half = 0.5 * ds.normalization.radius / 1.1
    assert np.all(np.abs(ds.points - ds.normalization.center) <= half + 1e-5)
    assert data.DEFAULT_NUM_RANDOM_POINTS == 100_000


def test_transforms_ngp_shared_and_per_frame_intrinsics(tmp_path):
    W, H = 30, 20
    poses = ring_poses(5, seed=4)
    frames = []
    for k, w2c in enumerate(poses):
        save_png(tmp_path / "images" / f"{k:04d}.jpg.png", random_image(W, H, seed=k))
        fr = {"file_path": f"images/{k:04d}.jpg.png", "transform_matrix": opengl_c2w(w2c)}
        if k == 3:
            fr.update(fl_x=70.0, fl_y=71.0, cx=14.0, cy=9.5)  # per-frame intrinsics override
        frames.append(fr)
    write_json(tmp_path / "transforms.json", {"fl_x": 40.0, "fl_y": 42.0, "cx": 15.5, "cy": 10.25, "w": W, "h": H,
                                              "aabb_scale": 4, "frames": frames})
    ds = data.load(tmp_path, test_every=2, num_random_points=10)
    assert [v.name for v in ds.test_views] == ["images/0000.jpg.png", "images/0002.jpg.png", "images/0004.jpg.png"]
    for v in ds.views:
        k = int(v.name[7:11])
        want = [[70, 0, 14], [0, 71, 9.5], [0, 0, 1]] if k == 3 else [[40, 0, 15.5], [0, 42, 10.25], [0, 0, 1]]
        np.testing.assert_allclose(np.asarray(v.camera.K), want, rtol=1e-6)
        np.testing.assert_allclose(np.asarray(v.camera.world_to_camera), poses[k], atol=1e-5)
    # the json file itself can be passed, and camera_angle_y sets fy
    write_json(tmp_path / "t2.json", {"camera_angle_x": 1.0, "camera_angle_y": 0.8, "frames": frames[:1]})
    v = data.load(tmp_path / "t2.json", test_every=0, num_random_points=10).views[0]
    np.testing.assert_allclose(np.asarray(v.camera.K)[[0, 1], [0, 1]],
                               [0.5 * W / math.tan(0.5), 0.5 * H / math.tan(0.4)], rtol=1e-6)


@settings(max_examples=30, deadline=None)
@given(x=st.floats(-0.6, 0.6), y=st.floats(-0.6, 0.6),
       which=st.sampled_from(["OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"]))
def test_distortion_equations_match_pycolmap(x, y, which):
    p = {"OPENCV": dict(k1=0.05, k2=-0.02, p1=0.003, p2=-0.002),
         "FULL_OPENCV": dict(k1=0.05, k2=-0.02, p1=0.003, p2=-0.002, k3=0.01),
         "OPENCV_FISHEYE": dict(k1=0.03, k2=-0.01, k3=0.002, k4=-0.001)}[which]
    fx, fy, cx, cy = 100.0, 110.0, 40.0, 30.0
    cam = pycolmap.Camera.create_from_model_name(1, which, fx, 80, 60)
    if which == "OPENCV":
        cam.params = [fx, fy, cx, cy, p["k1"], p["k2"], p["p1"], p["p2"]]
    elif which == "FULL_OPENCV":
        cam.params = [fx, fy, cx, cy, p["k1"], p["k2"], p["p1"], p["p2"], p["k3"], 0, 0, 0]
    else:
        cam.params = [fx, fy, cx, cy, p["k1"], p["k2"], p["k3"], p["k4"]]
    xd, yd = distort_normalized(x, y, p, fisheye=which == "OPENCV_FISHEYE")
    want = cam.img_from_cam(np.array([[x, y, 1.0]]))[0]
    np.testing.assert_allclose([fx * xd + cx, fy * yd + cy], want, atol=1e-7)


def test_transforms_distortion_undistorted_and_cached(tmp_path, capfd):
    W, H = 48, 36
    K = dict(fl_x=40.0, fl_y=41.0, cx=24.3, cy=17.8)
    dist = dict(k1=0.08, k2=-0.02, p1=0.004, p2=-0.003)
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", 40.0, W, H)
    cam.params = [40.0, 41.0, 24.3, 17.8, 0.08, -0.02, 0.004, -0.003]
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xy = cam.cam_from_img(np.stack([jj.ravel(), ii.ravel()], -1))
    img = _pattern(xy[:, 0], xy[:, 1]).reshape(H, W, 3)
    poses = ring_poses(3, seed=5)
    frames = []
    for k, w2c in enumerate(poses):
        save_png(tmp_path / "scene" / f"f{k}.png", img)
        frames.append({"file_path": f"f{k}.png", "transform_matrix": opengl_c2w(w2c)})
    write_json(tmp_path / "scene" / "transforms.json", {**K, **dist, "w": W, "h": H, "frames": frames})
    ds = data.load(tmp_path / "scene", test_every=0, cache_dir=tmp_path / "cache", num_random_points=10)
    assert "undistorting" in capfd.readouterr().err
    und = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    fx, fy, cx, cy = und.params
    for v in ds.views:
        np.testing.assert_allclose(np.asarray(v.camera.K), [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rtol=1e-6)
        assert (v.camera.width, v.camera.height) == (und.width, und.height)
        assert v.image_path.is_relative_to(tmp_path / "cache") and v.name.startswith("f")
        j2, i2 = np.meshgrid(np.arange(und.width) + 0.5, np.arange(und.height) + 0.5)
        want = _pattern((j2 - cx) / fx, (i2 - cy) / fy) / 255.0
        assert np.abs(v.image[2:-2, 2:-2] - want[2:-2, 2:-2]).mean() < 0.02
    data.load(tmp_path / "scene", test_every=0, cache_dir=tmp_path / "cache", num_random_points=10)
    assert "undistorting" not in capfd.readouterr().err


def test_transforms_ply_point_cloud(tmp_path):
    poses = ring_poses(2)
    for k in range(2):
        save_png(tmp_path / f"{k}.png", random_image(8, 6, k))
    rec = pycolmap.Reconstruction()
    pts = np.random.default_rng(0).normal(size=(7, 3))
    for k, x in enumerate(pts):
        rec.add_point3D(x, pycolmap.Track(), np.array([k, 2 * k, 255 - k], np.uint8))
    rec.export_PLY(str(tmp_path / "sparse_pc.ply"))
    write_json(tmp_path / "transforms.json", {"fl_x": 10.0, "ply_file_path": "sparse_pc.ply", "frames": [
        {"file_path": f"{k}.png", "transform_matrix": opengl_c2w(poses[k])} for k in range(2)]})
    ds = data.load(tmp_path)
    assert ds.points_source == "ply"
    order = np.argsort(ds.points[:, 0])  # pycolmap writes the PLY in hash-map order
    np.testing.assert_allclose(ds.points[order], pts[np.argsort(pts[:, 0])], atol=1e-6)
    k = np.argsort(pts[:, 0])
    want = np.array([[i, 2 * i, 255 - i] for i in range(7)], np.float32)[k] / 255
    np.testing.assert_allclose(ds.colors[order], want, atol=1e-7)
    p, c = read_ply_points(tmp_path / "sparse_pc.ply")
    assert p.shape == (7, 3) and c.shape == (7, 3)
    (tmp_path / "bad.ply").write_bytes((tmp_path / "sparse_pc.ply").read_bytes()[:-5])
    with pytest.raises(DatasetError, match="bad.ply"):
        read_ply_points(tmp_path / "bad.ply")
    ascii_ply = ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                 "end_header\n")
    (tmp_path / "nan.ply").write_text(ascii_ply + "0 0 0\n1 nan 2\n")
    with pytest.raises(DatasetError, match="nan.ply: 1 of 2 vertices have non-finite coordinates"):
        read_ply_points(tmp_path / "nan.ply")


# ----------------------------------------------------------------------------------------------------
# LLFF
# ----------------------------------------------------------------------------------------------------


def test_llff_poses_factor_folder_with_other_names(tmp_path):
    W, H, focal = 40, 30, 33.0
    w2cs = ring_poses(5, seed=6)
    c2ws = [np.linalg.inv(w) for w in w2cs]
    bounds = [(0.5 + 0.1 * k, 9.0 + k) for k in range(5)]
    full, small = {}, {}
    for k in range(5):
        full[k] = random_image(W, H, seed=k)
        save_png(tmp_path / "images" / f"IMG_{k + 100}.png", full[k])
        small[k] = random_image(W // 2, H // 2, seed=10 + k)
        save_png(tmp_path / "images_2" / f"image{k:03d}.png", small[k])
    write_llff(tmp_path, c2ws, (H, W, focal), bounds)
    ds = data.load(tmp_path, factor=2, test_every=0, num_random_points=300)
    assert ds.format == "llff" and [v.name for v in ds.views] == [f"IMG_{k + 100}.png" for k in range(5)]
    for k, v in enumerate(ds.views):
        np.testing.assert_allclose(np.asarray(v.camera.K), [[focal / 2, 0, W / 4], [0, focal / 2, H / 4], [0, 0, 1]],
                                   rtol=1e-6)
        np.testing.assert_allclose(np.asarray(v.camera.world_to_camera), w2cs[k], atol=1e-5)
        np.testing.assert_array_equal(v.image, small[k] / np.float32(255))
        assert (v.near, v.far) == pytest.approx(bounds[k])
    # no sparse model: seeded random points inside the frustums between near and far
    assert ds.points_source == "random" and ds.points.shape == (300, 3)
    depth_ok = []
    for p in ds.points:
        d = [(v.camera.world_to_camera @ np.append(p, 1))[2] for v in ds.views]
        depth_ok.append(any(0.45 < z < 14.1 for z in d))
    assert all(depth_ok)
    # factor without a folder: box-downsampling of images/
    d4 = data.load(tmp_path, factor=4, test_every=0, num_random_points=10)
    want = full[0][:28].reshape(7, 4, 10, 4, 3).mean((1, 3)) / 255  # 30 rows: the last 2 are cropped
    np.testing.assert_allclose(d4.views[0].image, want, atol=1e-6)


def test_llff_uses_sparse_points_when_present(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=3, W=40, H=30)
    write_llff(tmp_path, [np.linalg.inv(sc["w2c"][n]) for n in sc["names"]], (30, 40, 50.0), [(1, 10)] * 3)
    assert data.detect_format(tmp_path) == "colmap"
    ds = data.load(tmp_path, format="llff", test_every=0)
    assert ds.format == "llff" and ds.points_source == "sfm"
    np.testing.assert_array_equal(ds.points, f32(sc["points"]))


# ----------------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------------


def test_not_a_dataset_says_what_was_looked_for(tmp_path):
    with pytest.raises(DatasetError) as e:
        data.load(tmp_path)
    msg = str(e.value)
    assert "sparse/0" in msg and "poses_bounds.npy" in msg and "transforms.json" in msg
    assert issubclass(DatasetError, ValueError)
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    with pytest.raises(DatasetError, match="no complete model"):
        data.load(tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        data.load(tmp_path / "nope")
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.png").write_bytes(b"")
    with pytest.raises(DatasetError, match=r"no camera poses.*python -m patexgs_jax\.sfm"):
        data.load(tmp_path / "photos")


def test_missing_and_unreadable_images(tmp_path, capfd):
    sc = make_colmap_scene(tmp_path, n_images=6)
    (tmp_path / "images" / sc["names"][2]).unlink()
    with pytest.raises(DatasetError, match=sc["names"][2]) as e:
        data.load(tmp_path)
    assert "skip_missing" in str(e.value)
    (tmp_path / "images" / sc["names"][4]).write_bytes(b"not an image at all")
    ds = data.load(tmp_path, skip_missing=True, test_every=0)
    assert len(ds.views) == 4 and "skipped 2 of 6" in capfd.readouterr().err
    (tmp_path / "images" / sc["names"][2]).write_bytes(b"")
    with pytest.raises(DatasetError, match=sc["names"][4]):
        data.load(tmp_path)


def test_truncated_image_data_fails_on_access_naming_the_file(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=2, W=64, H=64)
    f = tmp_path / "images" / sc["names"][0]
    f.write_bytes(f.read_bytes()[:200])  # header intact, pixel data cut
    ds = data.load(tmp_path, test_every=0)
    with pytest.raises(DatasetError, match=sc["names"][0]):
        _ = ds.views[0].image


def test_image_size_disagreeing_with_camera(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=3)
    save_png(tmp_path / "images" / sc["names"][1], random_image(30, 40, 0))  # rotated
    with pytest.raises(DatasetError, match=rf"{sc['names'][1]} is 30x40 but .* expects 40x30"):
        data.load(tmp_path)
    save_png(tmp_path / "images" / sc["names"][1], random_image(40, 30, 0))
    for n in sc["names"]:
        save_png(tmp_path / "images_2" / n, random_image(12, 15, 0))
    with pytest.raises(DatasetError, match="images_2"):
        data.load(tmp_path, factor=2)


def test_model_without_registered_images(tmp_path):
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 50.0, 40, 30)
    rec.add_camera_with_trivial_rig(cam)
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(tmp_path / "sparse" / "0"))
    (tmp_path / "images").mkdir()
    with pytest.raises(DatasetError, match="no registered images"):
        data.load(tmp_path)


def test_empty_point_cloud_warns_and_uses_random_points(tmp_path):
    make_colmap_scene(tmp_path, n_images=4, n_points=0)
    with pytest.warns(DatasetWarning, match="no 3D points"):
        ds = data.load(tmp_path, num_random_points=123, seed=5)
    assert ds.points_source == "random" and ds.points.shape == (123, 3) and ds.colors.shape == (123, 3)


@pytest.mark.parametrize("fname", ["cameras.bin", "images.bin", "points3D.bin", "frames.bin", "rigs.bin"])
def test_truncated_or_padded_binary_model_is_a_clear_error(tmp_path, fname):
    sc = make_colmap_scene(tmp_path, n_images=3)
    f = sc["sparse"] / fname
    good = f.read_bytes()
    assert validate_binary_model(sc["sparse"])["images"] == 3
    # pycolmap 4.2.1 hangs on some of these (e.g. images.bin cut to 4 bytes) and silently accepts others
    # (cut by one byte); the loader must fail fast with the file's name.
    for cut in sorted({0, 4, 8, 13, len(good) // 2, len(good) - 1}):
        f.write_bytes(good[:cut])
        t0 = time.time()
        with pytest.raises(DatasetError, match=fname):
            data.load(tmp_path)
        assert time.time() - t0 < 5
    f.write_bytes(good + b"\0\0\0")
    with pytest.raises(DatasetError, match="trailing"):
        data.load(tmp_path)


@pytest.mark.parametrize("what,value", [("k1", float("nan")), ("fx", float("inf")), ("point", float("nan")),
                                        ("pose", float("nan"))])
def test_non_finite_binary_model_values_are_a_clear_error(tmp_path, what, value):
    """pycolmap reads NaN / inf from binary models without complaint: a NaN k1 had been undistorted
    into a camera twice the image's size, a NaN point would have become a NaN Gaussian."""
    sc = make_colmap_scene(tmp_path, models=("OPENCV",) if what == "k1" else ("PINHOLE",), n_images=3, n_points=5)
    sp = sc["sparse"]
    # Byte offsets of the first record's fields: cameras.bin (count u64, id i32, model i32, width u64,
    # height u64, params f64...), points3D.bin (count u64, id u64, xyz f64), images.bin (count u64,
    # id i32, qvec f64 x 4, tvec f64 x 3; read for poses only without frames.bin, as in Mip-NeRF 360).
    fname, offset = {"k1": ("cameras.bin", 32 + 8 * 4), "fx": ("cameras.bin", 32), "point": ("points3D.bin", 16),
                     "pose": ("images.bin", 12 + 32)}[what]
    if what == "pose":
        (sp / "rigs.bin").unlink()
        (sp / "frames.bin").unlink()
    b = bytearray((sp / fname).read_bytes())
    b[offset:offset + 8] = struct.pack("<d", value)
    (sp / fname).write_bytes(bytes(b))
    with pytest.raises(DatasetError, match=f"{fname}.*non-finite") as e:
        data.load(tmp_path)
    assert {"k1": "camera 1 (OPENCV)", "fx": "camera 1 (PINHOLE)", "point": "1 of 5 points",
            "pose": "image 1 (img_000.png)"}[what] in str(e.value)


def test_truncated_text_model_is_a_clear_error(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=3, text=True)
    f = sc["sparse"] / "points3D.txt"
    lines = f.read_text().splitlines(keepends=True)
    f.write_text("".join(lines[:-3]))  # cut at a line boundary: pycolmap reads fewer points silently
    with pytest.raises(DatasetError, match="points3D.txt"):
        data.load(tmp_path)
    f.write_text("".join(lines)[:-40])  # cut inside a line
    with pytest.raises(DatasetError, match="points3D"):
        data.load(tmp_path)


def test_bad_transforms_and_poses_bounds(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "transforms.json").write_text("{not json")
    with pytest.raises(DatasetError, match="transforms.json"):
        data.load(tmp_path / "a")
    write_json(tmp_path / "b" / "transforms.json",
               {"frames": [{"file_path": "x", "transform_matrix": np.eye(4).tolist()}]})
    with pytest.raises(DatasetError, match="x"):
        data.load(tmp_path / "b")
    save_png(tmp_path / "b" / "x.png", random_image(8, 6, 0))
    with pytest.raises(DatasetError, match="focal"):
        data.load(tmp_path / "b")
    write_json(tmp_path / "b" / "transforms.json", {"fl_x": 5, "w": 9, "h": 6, "frames": [
        {"file_path": "x", "transform_matrix": np.eye(4).tolist()}]})
    with pytest.raises(DatasetError, match=r"x.png is 8x6 but w/h"):
        data.load(tmp_path / "b")
    (tmp_path / "c").mkdir()
    np.save(tmp_path / "c" / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(DatasetError, match=r"poses_bounds.npy has shape \(3, 15\)"):
        data.load(tmp_path / "c")
    np.save(tmp_path / "c" / "poses_bounds.npy", np.zeros((3, 17)))
    save_png(tmp_path / "c" / "images" / "a.png", random_image(4, 4, 0))
    with pytest.raises(DatasetError, match="3 poses but .* has 1 images"):
        data.load(tmp_path / "c")


def test_missing_image_folder(tmp_path):
    make_colmap_scene(tmp_path, n_images=2, write_images=False)
    with pytest.raises(DatasetError, match="images"):
        data.load(tmp_path)


# ----------------------------------------------------------------------------------------------------
# Cache location and import-order hazard
# ----------------------------------------------------------------------------------------------------


def test_cache_dir_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv("PATEXGS_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    scene = tmp_path / "scene"
    scene.mkdir()
    assert data.resolve_cache_dir(scene) == scene.resolve() / ".patexgs_cache"
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)  # read-only dataset (the check uses permission bits, so it also holds for root)
    try:
        got = data.resolve_cache_dir(ro)
        assert got.parent == tmp_path / "xdg" / "patexgs_jax" and got.name.startswith("ro-")
    finally:
        ro.chmod(0o755)
    monkeypatch.setenv("PATEXGS_CACHE", str(tmp_path / "env"))
    assert data.resolve_cache_dir(scene).parent == tmp_path / "env"
    assert data.resolve_cache_dir(scene, tmp_path / "arg").parent == tmp_path / "arg"
    assert data.resolve_cache_dir(scene, tmp_path / "arg") != data.resolve_cache_dir(ro, tmp_path / "arg")


def _run(code: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=env,
                          timeout=120, cwd=REPO)


def test_pycolmap_pil_import_order_is_safe(tmp_path):
    # Our modules import pycolmap (through patexgs_jax._pycolmap, where they need it); user code
    # imports PIL afterwards and saves a PNG (the order that used to abort with 'free(): invalid
    # pointer'), then uses zlib directly.
    r = _run(f"""
        import patexgs_jax._pycolmap
        import pycolmap
        from PIL import Image
        import numpy as np, zlib
        Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save({str(tmp_path / 'a.png')!r})
        assert len(zlib.compress(b'x' * 10000)) < 100
        print('ok')
        """)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
    if not sys.platform.startswith("linux"):
        return  # the load-order check below uses glibc's dl_iterate_phdr
    # Importing pycolmap before anything else cannot be repaired afterwards: the package warns.
    r = _run("""
        import pycolmap, warnings
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter('always')
            import patexgs_jax._pycolmap
        print(any('imported before zlib' in str(x.message) for x in w))
        """)
    assert r.returncode == 0 and r.stdout.strip() == "True", r.stderr[-2000:]


# ----------------------------------------------------------------------------------------------------
# Real capture: $PATEXGS_REAL_DATA/beer, else ../shared/data/beer (tests/locations.py)
# ----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def beer(tmp_path_factory):
    if not (BEER / "sparse" / "0").is_dir():
        pytest.skip(f"real capture not found at {BEER} (set PATEXGS_REAL_DATA to the folder holding beer/)")
    cache = tmp_path_factory.mktemp("beer_cache")
    before = sorted(str(p.relative_to(BEER)) for p in BEER.rglob("*"))
    ds = data.load(BEER, factor=8, cache_dir=cache, verbose=False)
    assert sorted(str(p.relative_to(BEER)) for p in BEER.rglob("*")) == before  # nothing written to shared/
    return ds, cache


def test_beer_real_capture(beer):
    ds, cache = beer
    assert len(ds.train_views) == 62 and len(ds.test_views) == 9 and len(ds.views) == 71
    assert ds.info["undistorted_from"] == ["SIMPLE_RADIAL"]
    assert len(ds.points) == 4414 and ds.points_source == "sfm" and ds.colors.min() >= 0 and ds.colors.max() <= 1
    und = pycolmap.Reconstruction(str(Path(ds.info["undistorted_dir"]) / "sparse"))
    assert {c.model.name for c in und.cameras.values()} == {"PINHOLE"}
    by_name = {im.name: im for im in und.images.values()}
    errors, inside = [], []
    for v in ds.views:
        assert v.camera.height > v.camera.width  # portrait
        assert v.camera.width == by_name[v.name].camera.width // 8
        im = by_name[v.name]
        obs = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs]) / 8.0  # continuous coordinates scale with the factor
        X = np.array([und.points3D[o[1]].xyz for o in obs])
        uv = project(v.camera, X)
        errors.append(np.linalg.norm(uv - xy, axis=1))
        inside.append((uv[:, 0] >= 0) & (uv[:, 0] < v.camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < v.camera.height))
    errors, inside = np.concatenate(errors), np.concatenate(inside)
    assert np.median(errors) < 0.15 and inside.mean() > 0.98  # ~0.75 px SfM error at full res / 8
    img = ds.test_views[0].image
    assert img.shape == (ds.test_views[0].camera.height, ds.test_views[0].camera.width, 3)
    assert 0.05 < img.mean() < 0.95 and img.std() > 0.02


def test_beer_second_load_reuses_cache_and_default_cache_is_outside_shared(beer, monkeypatch, capfd):
    ds, cache = beer
    t0 = time.time()
    again = data.load(BEER, factor=8, cache_dir=cache)
    assert time.time() - t0 < 5 and "undistorting" not in capfd.readouterr().err
    assert again.info["undistorted_dir"] == ds.info["undistorted_dir"]
    monkeypatch.delenv("PATEXGS_CACHE", raising=False)
    if not os.access(BEER, os.W_OK) or not BEER.stat().st_mode & stat.S_IWUSR:
        assert not data.resolve_cache_dir(BEER).is_relative_to(BEER)
