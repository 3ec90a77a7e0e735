"""Tests of the synthetic COLMAP scene generator (patexgs_jax.data.synthetic)."""

import json
from pathlib import Path

import numpy as np
import PIL.Image
import pytest

from patexgs_jax._pycolmap import pycolmap  # (keeps the fatal-signal handlers, see there)
from patexgs_jax.camera import Camera
from patexgs_jax.data import synthetic
from patexgs_jax.sfm import box_downsample

SMALL = dict(num_views=4, width=64, height=48, supersample=2, num_points=300)


@pytest.fixture(scope="module")
def default_scene(tmp_path_factory):
    """The default scene, generated through ensure_default_scene() into a temporary cache."""
    cache = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PATEXGS_CACHE", str(cache))
        path = synthetic.ensure_default_scene(verbose=False)
        assert path == cache / "synthetic-v1-seed0" == synthetic.default_scene_dir()
    return path


def _read_image(path) -> np.ndarray:
    with PIL.Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def _cam_from_world(image) -> np.ndarray:
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(pose.matrix())


def _cameras(rec):
    """[(name, K (3, 3), w2c (3, 4))] sorted by name."""
    out = []
    for image in rec.images.values():
        K = rec.cameras[image.camera_id].calibration_matrix()
        out.append((image.name, K, _cam_from_world(image)))
    return sorted(out, key=lambda c: c[0])


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Samples (H, W, 3) ``img`` at continuous coordinates with pixel centres at (j + 0.5, i + 0.5)."""
    H, W = img.shape[:2]
    x, y = x - 0.5, y - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]

    def at(i, j):
        return img[np.clip(i, 0, H - 1), np.clip(j, 0, W - 1)]

    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x0 + 1) * fx * (1 - fy)
            + at(y0 + 1, x0) * (1 - fx) * fy + at(y0 + 1, x0 + 1) * fx * fy)


def _tree_bytes(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_layout_and_model_read_back(default_scene):
    meta = json.loads((default_scene / "synthetic.json").read_text())
    assert meta["version"] == synthetic.FORMAT_VERSION and meta["seed"] == 0
    names = sorted(p.name for p in (default_scene / "images").iterdir())
    assert names == meta["images"] and len(names) == 24
    assert sorted(p.name for p in (default_scene / "images_2").iterdir()) == names
    rec = pycolmap.Reconstruction(default_scene / "sparse/0")
    assert rec.num_images() == rec.num_reg_images() == 24
    assert rec.num_cameras() == 1
    assert 2000 <= rec.num_points3D() <= 3000
    cam = next(iter(rec.cameras.values()))
    assert cam.model_name == "PINHOLE" and (cam.width, cam.height) == (128, 96)
    fx, fy, cx, cy = cam.params
    assert fx == pytest.approx(64 / np.tan(np.radians(30))) and fy == fx and (cx, cy) == (64, 48)
    # Stored poses are the generator's cameras, and images are their ground-truth renders.
    truth = synthetic.make_cameras(0, 24, 128, 96)
    for (_, K, w2c), gt in zip(_cameras(rec), truth):
        np.testing.assert_allclose(w2c, np.asarray(gt.world_to_camera)[:3], atol=1e-5)
        np.testing.assert_allclose(K, np.asarray(gt.K), atol=1e-4)
    img = _read_image(default_scene / "images" / names[5])
    assert img.shape == (96, 128, 3) and img.dtype == np.uint8
    gt = synthetic.render_ground_truth(truth[5], supersample=4)
    assert gt.shape == (96, 128, 3) and gt.dtype == np.float32
    # Camera poses are stored in float32 in a Camera, so allow a rare one-level rounding flip.
    assert np.abs(np.round(255 * gt).astype(int) - img).max() <= 1
    # Tracks: every point is observed in >= 2 images, through the right 2D points.
    for pid, point in list(rec.points3D.items())[:50]:
        assert point.track.length() >= 2
        for el in point.track.elements:
            assert rec.images[el.image_id].points2D[el.point2D_idx].point3D_id == pid


def test_point_colours_match_pixels_at_projections(default_scene):
    """End-to-end check of poses, intrinsics and the pixel-centre convention: projecting the 3D points
    with the stored model lands on pixels of the point's colour, and worse so half a pixel off."""
    rec = pycolmap.Reconstruction(default_scene / "sparse/0")
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    color = np.array([rec.points3D[i].color for i in ids], np.float64) / 255
    errors = {0.0: [], 0.5: [], -0.5: []}
    views_ok = 0
    for image in rec.images.values():
        K = rec.cameras[image.camera_id].calibration_matrix()
        w2c = _cam_from_world(image)
        seen = np.zeros(len(ids), bool)
        point_index = {pid: k for k, pid in enumerate(ids)}
        for p2d in image.points2D:
            if p2d.has_point3D():
                seen[point_index[p2d.point3D_id]] = True
        pc = xyz[seen] @ w2c[:, :3].T + w2c[:, 3]
        assert np.all(pc[:, 2] > 0)
        uv = pc @ K.T
        x, y = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        img = _read_image(default_scene / "images" / image.name).astype(np.float64) / 255
        for shift in errors:
            err = np.abs(_bilinear(img, x + shift, y + shift) - color[seen]).max(axis=1)
            errors[shift].append(err)
        views_ok += np.mean(errors[0.0][-1] < 0.1) > 0.6
    assert views_ok >= 0.9 * rec.num_images()
    err = {s: np.concatenate(e) for s, e in errors.items()}
    assert np.mean(err[0.0] < 0.1) > 0.75
    for shift in (0.5, -0.5):
        assert np.median(err[shift]) > 1.25 * np.median(err[0.0])


def test_images_2_is_box_downsampled(default_scene):
    for name in ("img_0000.png", "img_0013.png"):
        full = _read_image(default_scene / "images" / name)
        half = _read_image(default_scene / "images_2" / name)
        assert half.shape == (48, 64, 3)
        np.testing.assert_array_equal(half, box_downsample(full, 2))
        # ...which is (up to rounding) the ground truth of the zoomed-out camera Camera.scaled(2).
        cam = synthetic.make_cameras(0, 24, 128, 96)[int(name[4:8])]
        gt = synthetic.render_ground_truth(cam.scaled(2), supersample=8)
        assert np.abs(255 * gt - half).max() <= 1.5


def test_high_frequency_content_and_scales(default_scene):
    img = _read_image(default_scene / "images" / "img_0001.png").astype(np.float64).mean(axis=2)
    power = np.abs(np.fft.fft2(img - img.mean())) ** 2
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    high = np.maximum(np.abs(fx), np.abs(fy)) > 0.25  # cycles per pixel (Nyquist = 0.5)
    assert power[high].sum() / power.sum() > 0.03
    # Detail beyond the zoomed-out Nyquist rate: point-sampling the zoomed-out view (no filtering)
    # aliases, i.e. differs clearly from the anti-aliased images_2.
    half = _read_image(default_scene / "images_2" / "img_0001.png").astype(np.float64) / 255
    cam = synthetic.make_cameras(0, 24, 128, 96)[1].scaled(2)
    aliased = synthetic.render_ground_truth(cam, supersample=1)
    assert np.abs(aliased - half).mean() > 0.03
    rec = pycolmap.Reconstruction(default_scene / "sparse/0")
    dist = [np.linalg.norm(im.projection_center() - synthetic.SCENE_CENTER) for im in rec.images.values()]
    assert max(dist) / min(dist) > 1.35
    heights = [im.projection_center()[2] for im in rec.images.values()]
    assert max(heights) - min(heights) > 0.8


def test_deterministic(tmp_path):
    a = synthetic.generate(tmp_path / "a", seed=3, **SMALL)
    b = synthetic.generate(tmp_path / "b", seed=3, **SMALL)
    c = synthetic.generate(tmp_path / "c", seed=4, **SMALL)
    ta, tb, tc = _tree_bytes(a), _tree_bytes(b), _tree_bytes(c)
    assert "sparse/0/points3D.bin" in ta and "images/img_0003.png" in ta and "images_2/img_0000.png" in ta
    assert ta == tb
    assert ta.keys() == tc.keys()
    for key in ("sparse/0/images.bin", "sparse/0/points3D.bin", "images/img_0000.png"):
        assert ta[key] != tc[key]


def test_reuse_and_refuse(tmp_path):
    out = synthetic.generate(tmp_path / "s", seed=1, **SMALL)
    stamp = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    assert synthetic.generate(out, seed=1, **SMALL) == out
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == stamp  # reused, not rewritten
    with pytest.raises(FileExistsError):
        synthetic.generate(out, seed=2, **SMALL)  # different parameters: needs overwrite=True
    synthetic.generate(out, seed=2, overwrite=True, **SMALL)
    assert json.loads((out / "synthetic.json").read_text())["seed"] == 2
    other = tmp_path / "user_data"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError):
        synthetic.generate(other, seed=1, overwrite=True, **SMALL)  # never removes non-synthetic dirs
    assert (other / "keep.txt").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s", "user_data"]  # no temp dirs left


def test_atomic_write(tmp_path, monkeypatch):
    calls = []

    def failing_write(folder, *args):
        calls.append(folder)
        raise RuntimeError("simulated crash while writing the model")

    monkeypatch.setattr(synthetic, "write_binary_model", failing_write)
    out = tmp_path / "scene"
    with pytest.raises(RuntimeError, match="simulated crash"):
        synthetic.generate(out, seed=0, **SMALL)
    assert calls, "the failure was not triggered mid-way"
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # the temp dir was cleaned up too
    monkeypatch.undo()
    # An empty target directory is fine; a stale temp dir of a dead process is removed.
    out.mkdir()
    stale = tmp_path / ".scene.tmp-999999999-deadbeef"
    stale.mkdir()
    synthetic.generate(out, seed=0, **SMALL)
    assert (out / "synthetic.json").is_file() and not stale.exists()


def test_render_ground_truth_api():
    K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    from patexgs_jax.camera import look_at
    cam = Camera.from_intrinsics(K, look_at([3.0, 0.5, 1.5], synthetic.SCENE_CENTER, up=(0, 0, 1)), 32, 24)
    img = synthetic.render_ground_truth(cam, supersample=2)
    assert img.shape == (24, 32, 3) and img.dtype == np.float32
    assert 0.0 <= img.min() and img.max() <= 1.0 and img.std() > 0.05
    # Looking straight up only sees the sky; straight down near the centre sees the ground.
    up = Camera.from_intrinsics(K, look_at([0.0, 0.0, 1.0], [0.0, 0.0, 5.0], up=(0, 1, 0)), 32, 24)
    sky = synthetic.render_ground_truth(up, supersample=1)
    assert np.allclose(sky, sky[0, 0], atol=0.1) and sky[..., 2].mean() > sky[..., 0].mean()


def test_cli(tmp_path, capsys):
    assert synthetic.main([str(tmp_path / "cli"), "--seed", "5", "--num-views", "3", "--width", "32",
                           "--height", "24", "--supersample", "1", "--num-points", "50"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "cli")
    assert len(list((tmp_path / "cli" / "images").iterdir())) == 3
