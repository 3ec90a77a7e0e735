"""Tests of our COLMAP model reader and writer (patexgs_jax.data.colmap_model) against pycolmap's, and of
loading COLMAP and embedded scenes with pycolmap made unimportable."""

from __future__ import annotations

import os
import re
import shutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import patexgs_jax.data as data
from data_builders import make_colmap_scene
from locations import BEER, REPO
from patexgs_jax._pycolmap import pycolmap  # (keeps the fatal-signal handlers, see there)
from patexgs_jax.data import DatasetError, synthetic
from patexgs_jax.data.colmap_binary import write_binary_model
from patexgs_jax.data.colmap_model import (
    CAMERA_MODELS,
    quaternion_from_rotation,
    read_model,
    rotation_from_quaternion,
)

SMALL = dict(num_views=4, width=64, height=48, supersample=1, num_points=200)


def test_camera_model_table_matches_pycolmap():
    theirs = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if int(mid.value) >= 0:
            cam = pycolmap.Camera.create_from_model_id(1, mid, 1.0, 1, 1)
            theirs[int(mid.value)] = (name, len(cam.params), cam.is_perspective())
    ours = {i: (m.name, m.num_params, m.perspective) for i, m in CAMERA_MODELS.items()}
    assert ours == theirs


def _rig_model(folder: Path, text: bool) -> Path:
    """A model of two frames of a two-camera rig (the second camera 0.5 m to the side, turned by 0.3
    rad), as COLMAP 3.12+ writes one: image poses come from frames and rigs."""
    rec = pycolmap.Reconstruction()
    rec.add_camera(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 50.0, 40, 30))
    rec.add_camera(pycolmap.Camera.create_from_model_name(2, "OPENCV", 60.0, 40, 30))
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 1))
    rig.add_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 2),
                   pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0.3, 0.0])), np.array([0.5, 0.0, 0.0])))
    rec.add_rig(rig)
    for f in range(2):
        frame = pycolmap.Frame()
        frame.frame_id, frame.rig_id = f + 1, 1
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.1 * f, 0.2, 0.0])),
                                                np.array([0.0, 0.1, 3.0 + f]))
        for s in (1, 2):
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, s), 2 * f + s))
        rec.add_frame(frame)
        for s in (1, 2):
            rec.add_image(pycolmap.Image(name=f"f{f}_c{s}.png", camera_id=s, image_id=2 * f + s, frame_id=f + 1))
    for k, x in enumerate(np.random.default_rng(0).normal(size=(5, 3))):
        rec.add_point3D(x, pycolmap.Track(), np.array([k, 2 * k, 3 * k], np.uint8))
    folder.mkdir(parents=True)
    (rec.write_text if text else rec.write_binary)(str(folder))
    return folder


def assert_same_as_pycolmap(folder: Path) -> None:
    """Our reader and pycolmap read the same cameras, image poses, keypoints and 3D points."""
    ours, theirs = read_model(folder), pycolmap.Reconstruction(str(folder))
    assert sorted(ours.cameras) == sorted(theirs.cameras)
    for cid, cam in ours.cameras.items():
        other = theirs.cameras[cid]
        assert (cam.model.name, cam.width, cam.height) == (other.model.name, other.width, other.height)
        np.testing.assert_array_equal(cam.params, other.params)
    assert sorted(ours.images) == sorted(theirs.images)
    for iid, im in ours.images.items():
        other = theirs.images[iid]
        assert (im.name, im.camera_id) == (other.name, other.camera_id) and other.has_pose
        np.testing.assert_allclose(im.cam_from_world, other.cam_from_world().matrix(), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(im.points2D, np.array([p.xy for p in other.points2D]).reshape(-1, 2))
        np.testing.assert_array_equal(im.point3D_ids, [p.point3D_id if p.has_point3D() else -1
                                                       for p in other.points2D])
    pts, ids = ours.points, sorted(theirs.points3D)
    np.testing.assert_array_equal(pts.ids, ids)
    np.testing.assert_array_equal(pts.xyz, np.reshape([theirs.points3D[i].xyz for i in ids], (-1, 3)))
    np.testing.assert_array_equal(pts.rgb, np.reshape([theirs.points3D[i].color for i in ids], (-1, 3)))
    np.testing.assert_array_equal(pts.error, [theirs.points3D[i].error for i in ids])
    np.testing.assert_array_equal(pts.track_length, [theirs.points3D[i].track.length() for i in ids])
    rows = [(e.image_id, e.point2D_idx) for i in ids for e in theirs.points3D[i].track.elements]
    np.testing.assert_array_equal(pts.tracks, np.reshape(rows, (-1, 2)))


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_reader_matches_pycolmap(tmp_path, text):
    sc = make_colmap_scene(tmp_path / "a", models=("PINHOLE", "SIMPLE_RADIAL", "FULL_OPENCV"), n_images=5, text=text)
    assert_same_as_pycolmap(sc["sparse"])
    assert_same_as_pycolmap(_rig_model(tmp_path / "rig", text))
    # Without rigs and frames (the layout before COLMAP 3.12) the poses are the images' own.
    if not text:
        for f in ("rigs.bin", "frames.bin"):
            (sc["sparse"] / f).unlink()
        assert_same_as_pycolmap(sc["sparse"])


def test_reader_matches_pycolmap_on_the_embedded_scene_and_the_real_capture(tmp_path):
    scene = synthetic.generate(tmp_path / "synthetic", **SMALL)
    assert_same_as_pycolmap(scene / "sparse" / "0")
    if not (BEER / "sparse" / "0").is_dir():
        pytest.skip(f"real capture not found at {BEER}")
    assert_same_as_pycolmap(BEER / "sparse" / "0")


def test_embedded_scene_model_is_what_pycolmap_builds(tmp_path):
    """The scene's points, tracks and keypoints as pycolmap reads them, and their reprojection
    errors as pycolmap computes them, are the ones we wrote."""
    scene = synthetic.generate(tmp_path / "s", **SMALL)
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    stored = {i: p.error for i, p in rec.points3D.items()}
    rec.update_point_3d_errors()
    for i, p in rec.points3D.items():
        assert p.track.length() >= 2
        assert stored[i] == pytest.approx(p.error, rel=1e-9, abs=1e-12)
        for el in p.track.elements:
            assert rec.images[el.image_id].points2D[el.point2D_idx].point3D_id == i
    truth = synthetic.make_cameras(0, SMALL["num_views"], SMALL["width"], SMALL["height"])
    for iid, im in rec.images.items():
        np.testing.assert_allclose(im.cam_from_world().matrix(), np.asarray(truth[iid - 1].world_to_camera)[:3],
                                   rtol=0, atol=1e-6)


def test_embedded_scene_loads_as_when_pycolmap_wrote_it(tmp_path):
    """The embedded scene's model, rebuilt and written by pycolmap as the generator did before it had
    its own writer, loads into the same dataset (poses to float32 rounding) and the same model."""
    scene = synthetic.generate(tmp_path / "ours", **SMALL)
    ours = read_model(scene / "sparse" / "0")
    cams = synthetic.make_cameras(0, SMALL["num_views"], SMALL["width"], SMALL["height"])
    rec = pycolmap.Reconstruction()
    K = np.asarray(cams[0].K, np.float64)
    camera = pycolmap.Camera.create_from_model_name(1, "PINHOLE", float(K[0, 0]), cams[0].width, cams[0].height)
    camera.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    rec.add_camera_with_trivial_rig(camera)
    for v, cam in enumerate(cams):
        image = pycolmap.Image(name=f"img_{v:04d}.png", keypoints=ours.images[v + 1].points2D, camera_id=1,
                               image_id=v + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.asarray(cam.world_to_camera, np.float64)[:3, :4]))
    starts = np.cumsum(ours.points.track_length) - ours.points.track_length
    for k in range(len(ours.points)):
        rows = ours.points.tracks[starts[k]:starts[k] + ours.points.track_length[k]]
        track = pycolmap.Track([pycolmap.TrackElement(int(i), int(j)) for i, j in rows])
        assert rec.add_point3D(ours.points.xyz[k], track, ours.points.rgb[k]) == ours.points.ids[k]
    rec.update_point_3d_errors()
    theirs = tmp_path / "theirs"
    shutil.copytree(scene, theirs)
    shutil.rmtree(theirs / "sparse" / "0")
    (theirs / "sparse" / "0").mkdir()
    rec.write(str(theirs / "sparse" / "0"))
    assert_same_as_pycolmap(theirs / "sparse" / "0")
    again = read_model(theirs / "sparse" / "0")
    np.testing.assert_allclose(again.points.error, ours.points.error, rtol=1e-9, atol=1e-12)
    a, b = (data.load(p, test_every=0, verbose=False) for p in (scene, theirs))
    assert [v.name for v in a.views] == [v.name for v in b.views]
    for u, v in zip(a.views, b.views):
        np.testing.assert_array_equal(np.asarray(u.camera.K), np.asarray(v.camera.K))
        np.testing.assert_allclose(np.asarray(u.camera.world_to_camera), np.asarray(v.camera.world_to_camera),
                                   rtol=0, atol=1e-7)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.colors, b.colors)


@pytest.mark.parametrize("source", ["built", "beer"])
def test_writer_round_trip(tmp_path, source):
    if source == "beer":
        if not (BEER / "sparse" / "0").is_dir():
            pytest.skip(f"real capture not found at {BEER}")
        folder = BEER / "sparse" / "0"
    else:
        folder = make_colmap_scene(tmp_path / "a", models=("PINHOLE", "OPENCV"), n_images=4)["sparse"]
    model = read_model(folder)
    out = tmp_path / "out"
    out.mkdir()
    write_binary_model(out, list(model.cameras.values()), list(model.images.values()), model.points)
    assert_same_as_pycolmap(out)
    back = read_model(out)
    for iid, im in model.images.items():
        np.testing.assert_allclose(back.images[iid].cam_from_world, im.cam_from_world, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(back.points.xyz, model.points.xyz)
    np.testing.assert_array_equal(back.points.tracks, model.points.tracks)


def test_quaternions():
    rng = np.random.default_rng(0)
    for q in [*rng.normal(size=(20, 4)), [0, 1, 0, 0], [0, 0, 1e-9, 1], [1e-12, 0.6, 0.8, 0]]:
        R = rotation_from_quaternion(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-14)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
        back = quaternion_from_rotation(R)
        np.testing.assert_allclose(back, np.sign(q[0] or 1.0) * np.asarray(q) / np.linalg.norm(q), rtol=0, atol=1e-12)
        np.testing.assert_allclose(rotation_from_quaternion(back), R, rtol=0, atol=1e-15)
    with pytest.raises(ValueError):
        rotation_from_quaternion([0, 0, 0, 0])


# ----------------------------------------------------------------------------------------------------
# Damaged rig models
# ----------------------------------------------------------------------------------------------------


def test_rig_model_damage_is_a_clear_error(tmp_path):
    good = _rig_model(tmp_path / "good", text=True)

    def damaged(name, edit, fname="frames.txt"):
        folder = tmp_path / name
        shutil.copytree(good, folder)
        f = folder / fname
        f.write_text(edit(f.read_text()))
        return folder

    lines = (good / "frames.txt").read_text().splitlines(keepends=True)
    data_lines = [k for k, line in enumerate(lines) if not line.startswith("#")]
    # Image 4 in no frame (the frame's data count fixed too, so that only the frames are inconsistent).
    no_frame = damaged("no_frame", lambda s: s.replace(" CAMERA 2 4", "").replace(
        lines[data_lines[1]].split()[9] + " CAMERA 1 3", "1 CAMERA 1 3"))
    with pytest.raises(DatasetError, match=r"frames.txt: image 4 \(f1_c2.png\) is in no frame"):
        read_model(no_frame)
    unknown_rig = damaged("unknown_rig", lambda s: s.replace(lines[data_lines[0]], "1 7 " + lines[data_lines[0]][4:]))
    with pytest.raises(DatasetError, match="frames.txt: frame 1 belongs to rig 7"):
        read_model(unknown_rig)
    nan_pose = damaged("nan_pose", lambda s: s.replace(lines[data_lines[1]], "2 1 nan " + lines[data_lines[1]].split(
        " ", 3)[3]))
    with pytest.raises(DatasetError, match=r"frames.txt: image 3 \(f1_c1.png\) has a non-finite pose"):
        read_model(nan_pose)
    # Camera 2's pose in the rig unknown (COLMAP cannot write this: its images would have no pose).
    unposed = damaged("unposed", lambda s: re.sub(r"CAMERA 2 1 .*", "CAMERA 2 0", s), "rigs.txt")
    with pytest.raises(DatasetError, match="frames.txt: frame 1 holds camera 2, whose pose in rig 1 is unknown"):
        read_model(unposed)
    (tmp_path / "no_rigs").mkdir()
    for f in good.iterdir():
        if f.name != "rigs.txt":
            shutil.copy(f, tmp_path / "no_rigs" / f.name)
    with pytest.raises(DatasetError, match="has frames.txt but no rigs.txt"):
        read_model(tmp_path / "no_rigs")


def test_binary_frame_with_non_finite_pose(tmp_path):
    sc = make_colmap_scene(tmp_path, n_images=3)
    f = sc["sparse"] / "frames.bin"
    b = bytearray(f.read_bytes())
    b[16:24] = struct.pack("<d", float("nan"))  # count u64, frame id u32, rig id u32, then qw
    f.write_bytes(bytes(b))
    with pytest.raises(DatasetError, match=r"frames.bin: image \d+ \(img_\d+.png\) has a non-finite pose"):
        data.load(tmp_path)


# ----------------------------------------------------------------------------------------------------
# Without pycolmap
# ----------------------------------------------------------------------------------------------------

WITHOUT_PYCOLMAP = """
    import sys
    sys.modules["pycolmap"] = None  # `import pycolmap` raises ImportError, as where it is not installed
    import numpy as np
    import patexgs_jax.data as data
    from patexgs_jax.data import synthetic
    assert sys.modules["pycolmap"] is None
    scene = synthetic.generate(sys.argv[1], num_views=4, width=32, height=24, supersample=1, num_points=100)
    ds = data.load(scene, test_every=0, verbose=False)
    print("synthetic", len(ds.views), ds.points.shape[0])
    for path in sys.argv[2:4]:
        ds = data.load(path, test_every=0, verbose=False)
        print("pinhole", len(ds.views), ds.points.shape[0])
    try:
        data.load(sys.argv[4], test_every=0, verbose=False)
    except data.DatasetError as e:
        print("distorted:", e)
    import importlib, pkgutil, patexgs_jax
    needs = []  # the modules that cannot be imported without pycolmap
    for m in pkgutil.walk_packages(patexgs_jax.__path__, "patexgs_jax."):
        try:
            importlib.import_module(m.name)
        except ImportError:
            needs.append(m.name)
    print("needs pycolmap:", " ".join(sorted(needs)))
    assert sys.modules["pycolmap"] is None
"""


def test_loading_without_pycolmap(tmp_path):
    """The embedded scene and undistorted (PINHOLE / SIMPLE_PINHOLE) COLMAP scenes load with pycolmap
    unimportable; a distorted model fails with the install command; of the package's modules, only
    the SfM (prepare) and the one place that imports pycolmap need it."""
    pinhole_bin = make_colmap_scene(tmp_path / "bin", models=("PINHOLE", "SIMPLE_PINHOLE"), n_images=3)
    pinhole_txt = make_colmap_scene(tmp_path / "txt", models=("PINHOLE",), n_images=2, text=True)
    make_colmap_scene(tmp_path / "distorted", models=("OPENCV",), n_images=2)
    env = dict(os.environ, JAX_PLATFORMS="cpu", PATEXGS_CACHE=str(tmp_path / "cache"),
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(WITHOUT_PYCOLMAP), str(tmp_path / "synthetic"),
                        str(tmp_path / "bin"), str(tmp_path / "txt"), str(tmp_path / "distorted")],
                       capture_output=True, text=True, env=env, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    out = r.stdout.splitlines()
    n_points = len(read_model(tmp_path / "synthetic" / "sparse" / "0").points)
    assert out[0] == f"synthetic 4 {n_points}"
    assert out[1:3] == [f"pinhole 3 {len(pinhole_bin['points'])}", f"pinhole 2 {len(pinhole_txt['points'])}"]
    assert out[3].startswith("distorted: Undistorting a COLMAP scene's images needs pycolmap")
    assert "pip install 'pycolmap" in out[3]
    assert out[4] == "needs pycolmap: patexgs_jax._pycolmap patexgs_jax.sfm"


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_damaged_files_are_a_dataset_error_or_read(tmp_path, text):
    """Random byte damage in any model file (rigs and frames included) is a DatasetError naming the
    file, or reads: never another exception (the reader runs in-process: it cannot hang or crash)."""
    good = _rig_model(tmp_path / "good", text)
    make_colmap_scene(tmp_path / "scene", models=("PINHOLE", "OPENCV"), n_images=3, n_points=6, text=text)
    rng = np.random.default_rng(1 + text)
    for source in (good, tmp_path / "scene" / "sparse" / "0"):
        files = sorted(p.name for p in source.iterdir())
        for k in range(150):
            folder = tmp_path / "damaged"
            shutil.rmtree(folder, ignore_errors=True)
            shutil.copytree(source, folder)
            f = folder / files[k % len(files)]
            b = bytearray(f.read_bytes())
            for _ in range(int(rng.integers(1, 4))):
                pos = int(rng.integers(0, len(b)))
                b[pos] = (b[pos] + int(rng.integers(1, 256))) % 256
            if k % 5 == 4:
                b = b[:int(rng.integers(0, len(b)))]
            f.write_bytes(bytes(b))
            try:
                read_model(folder)
            except DatasetError as e:
                assert str(folder) in str(e), str(e)
