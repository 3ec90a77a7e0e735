"""Tests of ``patexgs_jax.sfm`` (pycolmap SfM to the Mip-NeRF 360 layout)."""


import numpy as np
import PIL.Image
import pytest

from patexgs_jax import sfm
from patexgs_jax._pycolmap import pycolmap  # (keeps the fatal-signal handlers, see there)
from patexgs_jax.data import synthetic

# 16 views over a half ring, 12 degrees apart: enough overlap for SIFT on the textured scene.
SCENE = dict(seed=1, num_views=16, width=320, height=240, supersample=2, num_points=200,
             arc_degrees=180.0, elevations=(30.0, 40.0), radius_ratio=1.25)


def _cam_from_world(image) -> np.ndarray:
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(pose.matrix())


def _umeyama(src: np.ndarray, dst: np.ndarray):
    """Similarity (s, R, t) minimising sum |s R src_i + t - dst_i|^2; src, dst (N, 3)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (a ** 2).sum(1).mean()
    return s, R, mu_d - s * R @ mu_s


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def test_sfm_recovers_synthetic_poses(tmp_path, capsys):
    scene = synthetic.generate(tmp_path / "scene", **SCENE)
    out = sfm.reconstruct(scene / "images", tmp_path / "out", verbose=True)
    log = capsys.readouterr().out
    for stage in ("feature extraction", "matching", "incremental mapping", "undistortion", "downsampling"):
        assert stage in log
    assert out == tmp_path / "out"
    assert not (out / ".work").exists()
    rec = pycolmap.Reconstruction(out / "sparse/0")
    assert rec.num_reg_images() >= 14
    assert all(c.model_name == "PINHOLE" for c in rec.cameras.values())

    names = sorted(p.name for p in (out / "images").iterdir())
    assert len(names) == rec.num_reg_images() and all(n.endswith(".png") for n in names)
    with PIL.Image.open(out / "images" / names[0]) as im:
        W, H = im.size
    assert abs(W - 320) <= 8 and abs(H - 240) <= 8  # undistortion of a near-pinhole camera
    for f in (2, 4, 8):
        assert sorted(p.name for p in (out / f"images_{f}").iterdir()) == names
        with PIL.Image.open(out / f"images_{f}" / names[-1]) as im:
            assert im.size == (W // f, H // f)
    with PIL.Image.open(out / "images" / names[3]) as full, PIL.Image.open(out / "images_2" / names[3]) as half:
        np.testing.assert_array_equal(np.asarray(half), sfm.box_downsample(np.asarray(full.convert("RGB")), 2))

    # Recovered poses agree with the ground truth up to a similarity transform.
    truth = {f"img_{k:04d}.png": c for k, c in enumerate(synthetic.make_cameras(
        SCENE["seed"], SCENE["num_views"], SCENE["width"], SCENE["height"], radius_ratio=SCENE["radius_ratio"],
        elevations=SCENE["elevations"], arc_degrees=SCENE["arc_degrees"]))}
    images = sorted(rec.images.values(), key=lambda im: im.name)
    c_rec = np.array([im.projection_center() for im in images])
    c_gt = np.array([truth[im.name].center for im in images])
    s, R, t = _umeyama(c_rec, c_gt)
    centre_err = np.linalg.norm(s * c_rec @ R.T + t - c_gt, axis=1)
    assert centre_err.max() < 0.02 * np.linalg.norm(c_gt - c_gt.mean(0), axis=1).mean()
    rot_err = []
    for im in images:
        R_rec = _cam_from_world(im)[:, :3] @ R.T  # camera-from-ground-truth-world
        R_gt = np.asarray(truth[im.name].world_to_camera, np.float64)[:3, :3]
        rot_err.append(_angle_deg(R_gt.T @ R_rec))
    assert max(rot_err) < 2.0, rot_err
    fx_true = float(np.asarray(truth[images[0].name].K)[0, 0])
    for cam in rec.cameras.values():
        assert cam.params[0] == pytest.approx(fx_true, rel=0.03)


def test_errors(tmp_path, capsys):
    with pytest.raises(sfm.SfmError, match="does not exist"):
        sfm.reconstruct(tmp_path / "missing", tmp_path / "out", verbose=False)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("not an image")
    with pytest.raises(sfm.SfmError, match="No images"):
        sfm.reconstruct(empty, tmp_path / "out", verbose=False)
    few = tmp_path / "few"
    few.mkdir()
    for k in range(2):
        PIL.Image.fromarray(np.full((48, 64, 3), 40 * k, np.uint8)).save(few / f"{k}.png")
    with pytest.raises(sfm.SfmError, match="at least 3"):
        sfm.reconstruct(few, tmp_path / "out", verbose=False)
    with pytest.raises(ValueError, match="matcher"):
        sfm.reconstruct(few, tmp_path / "out", matcher="vocab")
    # Blank images: a clear error instead of a failed mapping deep inside COLMAP.
    PIL.Image.fromarray(np.full((48, 64, 3), 200, np.uint8)).save(few / "2.png")
    with pytest.raises(sfm.SfmError, match="No features"):
        sfm.reconstruct(few, tmp_path / "out", verbose=False)
    assert not (tmp_path / "out" / ".work").exists()
    # The command line reports errors without a traceback.
    assert sfm.main([str(tmp_path / "missing"), str(tmp_path / "out2"), "--quiet"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_box_downsample():
    img = np.arange(5 * 7 * 3, dtype=np.uint8).reshape(5, 7, 3)
    out = sfm.box_downsample(img, 2)
    assert out.shape == (2, 3, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[0, 0], np.round(img[:2, :2].reshape(4, 3).mean(0)))
    f = sfm.box_downsample(img.astype(np.float32), 2)
    assert f.dtype == np.float32 and f[1, 2, 1] == pytest.approx(img[2:4, 4:6, 1].mean())
    with pytest.raises(ValueError):
        sfm.box_downsample(img, 8)
