"""The render command line (patexgs_jax.render_cli), its camera paths (patexgs_jax.camera_paths) and
the source loader (patexgs_jax.sources), on the viewer's run folder (tests/viewer_scenes.py): no data
set, so the paths go about the Gaussians; the study-run case (recorded data) is in
tests/integration/test_mipnerf360.py."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from locations import REPO
from patexgs_jax import camera_paths as cp
from patexgs_jax import render_cli
from patexgs_jax.camera import Camera, look_at
from patexgs_jax.sources import SourceError, load_source

#: Frames of the command line's tests: small (one padded size) and few.
W, N = 48, 3


def _cameras():
    place = cp.ScenePlace((0.1, -0.2, 0.3), (0.0, -1.0, 0.2), 3.0, 0.8)
    ref = Camera.from_intrinsics((50.0, 50.0, 24.0, 16.0), look_at((0.0, -0.5, -3.0), (0.0, 0.0, 0.0)), W, 32)
    return cp.orbit(place, ref, 4) + cp.spiral(place, ref, 3, width=64) + cp.zoom_out(ref, 3)


def test_camera_path_round_trips_through_nerfstudio_json(tmp_path):
    cams = [c for c in _cameras() if c.width == W]
    path = cp.write_path(tmp_path / "path.json", cams, fps=24)
    doc = json.loads(path.read_text())
    assert doc["camera_type"] == "perspective" and (doc["render_width"], doc["render_height"]) == (W, 32)
    assert doc["fps"] == 24 and doc["seconds"] == pytest.approx(len(cams) / 24)
    assert all(len(e["camera_to_world"]) == 16 and e["aspect"] == pytest.approx(W / 32) for e in doc["camera_path"])
    back, fps = cp.read_path(path)
    assert fps == 24 and len(back) == len(cams)
    for a, b in zip(cams, back, strict=True):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(np.asarray(b.K), np.asarray(a.K), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(np.asarray(b.world_to_camera), np.asarray(a.world_to_camera), atol=1e-6)


def test_nerfstudio_axes_and_paths():
    # An OpenCV camera at the origin looking down +z is nerfstudio's camera looking down its -z: y and z flip.
    cam = Camera.from_intrinsics((10.0, 10.0, 8.0, 6.0), np.eye(4), 16, 12)
    e = cp.entry_of(cam)
    np.testing.assert_allclose(np.reshape(e["camera_to_world"], (4, 4)), np.diag([1.0, -1.0, -1.0, 1.0]))
    assert e["fov"] == pytest.approx(math.degrees(2 * math.atan(6 / 10)))
    place = cp.ScenePlace((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 2.0, 0.5)
    ref = Camera.from_intrinsics((20.0, 20.0, 16.0, 12.0), look_at((2.0, 0.0, 0.5), (0, 0, 0), up=(0, 0, 1)), 32, 24)
    for c in cp.orbit(place, ref, 5):  # on the circle, looking at the centre
        assert np.linalg.norm(c.center[:2]) == pytest.approx(2.0) and c.center[2] == pytest.approx(0.5)
        assert np.asarray(c.world_to_camera)[2, 3] == pytest.approx(np.linalg.norm(c.center), rel=1e-5)
    zoom = cp.zoom_out(ref, 4)
    fx = [float(np.asarray(c.K)[0, 0]) for c in zoom]
    assert fx[0] == pytest.approx(20.0) and fx[-1] == pytest.approx(20.0 / 8) and np.allclose(np.diff(np.log(fx)),
                                                                                              -math.log(2))
    assert all(np.allclose(c.center, ref.center, atol=1e-5) for c in zoom)


@pytest.mark.parametrize("text, match", [
    ("not json", "is not JSON"),
    ('{"render_width": 8}', "lacks render_height, camera_path"),
    ('{"render_width": 8, "render_height": 6, "camera_path": [{"fov": 50}]}', r"camera_path\[0\]: KeyError"),
    ('{"render_width": 8, "render_height": 6, "camera_path": [{"camera_to_world": [1, 0], "fov": 50}]}',
     r"camera_path\[0\]"),
    ('{"render_width": 8, "render_height": 6, "camera_type": "fisheye", "camera_path": []}', "only perspective"),
])
def test_bad_path_file_is_refused_clearly(tmp_path, text, match):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(cp.PathError, match=match):
        cp.read_path(path)
    with pytest.raises(cp.PathError, match="cannot read the camera path"):
        cp.read_path(tmp_path / "missing.json")


def test_bad_sources_name_what_is_expected(viewer_run_dir, tmp_path):
    src = load_source(viewer_run_dir)
    assert src.name == "patexgs" and src.method == "patexgs" and src.data is None  # no results.json there
    for bad, match in ((tmp_path / "nope", "does not exist"), (tmp_path, "is not a run folder"),
                       (tmp_path / "notes.txt", "neither a checkpoint")):
        if bad.suffix:
            bad.write_text("x")
        with pytest.raises(SourceError, match=match) as e:
            load_source(bad)
        assert "a run folder" in str(e.value) and ".ply" in str(e.value)
    (tmp_path / "bad.ckpt").write_bytes(b"not a zip")
    with pytest.raises(SourceError, match="cannot read the run"):
        load_source(tmp_path / "bad.ckpt")


def _frames(folder):
    from PIL import Image

    return [np.asarray(Image.open(p)) for p in sorted(folder.glob("frame_*.png"))]


def test_render_writes_frames_video_and_path(viewer_run_dir, tmp_path, capsys):
    import av

    other = viewer_run_dir.parent / "2dgs"
    args = [str(viewer_run_dir), "--frames", str(N), "--width", str(W), "--compare", str(other)]
    assert render_cli.main([*args, "--out", str(tmp_path / "a"), "--save-path", str(tmp_path / "p.json")]) == 0
    assert f"{N} frames" in capsys.readouterr().out
    frames = _frames(tmp_path / "a")
    h = int(round(480 * W / 640))  # (no data set: a 640 x 480 reference camera, resized)
    assert len(frames) == N and frames[0].shape == (render_cli.BAND + h, 2 * W + render_cli.GAP, 3)
    assert frames[0][render_cli.BAND:].max() > 0  # the scene is in view
    with av.open(str(tmp_path / "a" / "video.mp4")) as c:
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(decoded) == N and decoded[0].shape == frames[0].shape
    # The same frames again, along the saved path: bit-identical.
    again = tmp_path / "b"
    assert render_cli.main([*args, "--path", str(tmp_path / "p.json"), "--out", str(again), "--no-video"]) == 0
    assert not (again / "video.mp4").exists()
    for x, y in zip(frames, _frames(again), strict=True):
        np.testing.assert_array_equal(x, y)


def test_render_refuses_bad_input(viewer_run_dir, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"render_width": 8}')
    assert render_cli.main([str(viewer_run_dir), "--out", str(tmp_path / "o"), "--path", str(bad)]) == 2
    assert "error: camera path" in capsys.readouterr().err
    assert render_cli.main([str(viewer_run_dir), "--out", str(tmp_path / "o"), "--path", "test"]) == 2
    assert "pass --data DIR" in capsys.readouterr().err
    assert render_cli.main([str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_python_m_render_is_the_command_line():
    """``python -m patexgs_jax.render`` hands over to the command line, without runpy's warning."""
    r = subprocess.run([sys.executable, "-m", "patexgs_jax.render", "--help"], cwd=REPO, capture_output=True,
                       text=True, timeout=120, env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"})
    assert r.returncode == 0 and "--compare" in r.stdout and "zoom-out" in r.stdout
    assert "RuntimeWarning" not in r.stderr, r.stderr


def test_dataset_records(viewer_scene, tmp_path):
    """A run's dataset: RUN/data.json (the training command line's), a study's scene folder, or the
    embedded scene by its name (not generated until loaded)."""
    from patexgs_jax.data.synthetic import default_scene_dir
    from patexgs_jax.sources import data_record, write_data_record
    from viewer_scenes import write_run

    run = write_run(tmp_path / "run", viewer_scene)
    assert data_record(run) is None
    write_data_record(run, tmp_path / "scene", 4)
    rec = data_record(run)
    assert rec.path == (tmp_path / "scene").resolve() and rec.factor == 4 and rec.test_every == 8
    study = tmp_path / "study"
    for scene, record in (("synthetic-v1-seed3", {}), ("garden", {"path": "/data/garden", "factor": 4})):
        write_run(study / "runs" / scene / "patexgs", viewer_scene)
        (study / "results.json").write_text(json.dumps({"config": {"test_views": 2}, "scenes": {scene: record}}))
        rec = load_source(study / "runs" / scene / "patexgs").data
        if scene == "garden":
            assert rec.path.as_posix() == "/data/garden" and rec.factor == 4 and rec.embedded_seed is None
        else:
            assert rec.path == default_scene_dir(3) and rec.embedded_seed == 3 and rec.factor is None
        assert rec.test_views == 2
    (run / "data.json").write_text("{")
    with pytest.raises(SourceError, match="unreadable"):
        data_record(run)
