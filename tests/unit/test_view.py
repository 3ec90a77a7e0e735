"""The browser viewer's in-process parts (patexgs_jax.viewer.frames, patexgs_jax.viewer.server): the browser's camera
becomes our Camera, camera moves never compile, the per-pixel mip level follows Eq. 11, the modes, the
runs a path names, and the browser's values only ever picked from lists. The server, the browser and
the command line are in tests/integration/test_viewer_server.py.

The scene is a small random textured scene saved as a run folder (a checkpoint with its training
configuration, as training writes it, tests/viewer_scenes.py); frames are 48 x 32 pixels: the tests
measure behaviour, not speed.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from patexgs_jax import checkpoint as ckpt
from patexgs_jax import memory_maps
from patexgs_jax.camera import Camera, look_at
from patexgs_jax.render import TRACE_COUNTS, RenderConfig, count_pairs, render, render_jit
from patexgs_jax.scene import Scene
from patexgs_jax.textures import TextureBank
from patexgs_jax.viewer import frames as vw
from viewer_scenes import H, W, orbit_camera

viser = pytest.importorskip("viser", reason='the viewer needs viser: pip install -e ".[viewer]"')


@pytest.fixture(scope="module")
def frames(viewer_scene):
    """The viewer's renderer of ``viewer_scene`` in PATexGS's own mode."""
    return vw.FrameRenderer(viewer_scene, RenderConfig(coverage="prefilter"))


# ------------------------------------------------------------------------------------------------
# Cameras, frames, compiles
# ------------------------------------------------------------------------------------------------
def test_quaternion_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R_ = vw.quat_to_matrix(q)
        np.testing.assert_allclose(R_ @ R_.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(vw.matrix_to_quat(R_), q, atol=1e-10)


def test_training_view_through_the_viewer_renders_as_render(viewer_scene, frames):
    """A view's pose and field of view, sent the way the browser sends them, give the same Camera and
    the same image as ``render`` of that view."""
    cam = orbit_camera(0.7)
    wxyz, pos, fov = vw.viewer_pose(cam)
    back = vw.camera_from_viewer(wxyz, pos, fov, cam.width, cam.height)
    np.testing.assert_allclose(np.asarray(back.K), np.asarray(cam.K), rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(np.asarray(back.world_to_camera), np.asarray(cam.world_to_camera), atol=1e-6)
    frame = frames.render(back, mode="patexgs", view="rgb")
    r = frames.renderer("patexgs")
    # render() of the run's own mode with its default compositor schedule: the viewer's
    # frame_schedule() (a CPU's FRAME_SCHEDULE) changes the order of the work, not the image
    assert r.config == dataclasses.replace(vw.mode_config(frames.base, "patexgs"), **vw.frame_schedule())
    ref = np.clip(np.asarray(render(viewer_scene, cam, vw.mode_config(frames.base, "patexgs")).rgb), 0, 1)
    assert frame.image.shape == (H, W, 3)
    assert ref.std() > 0.05  # the view sees the scene
    np.testing.assert_allclose(frame.image / 255.0, ref, atol=1.0 / 255 + 1e-6)


def test_camera_moves_never_compile(frames):
    """After the first frame at a canvas size (full and preview size), frames of other poses at that
    size compile nothing: neither the renderer nor the mip-level function."""
    fns = (render_jit, count_pairs, vw.dominant_mip_level)
    for view in ("rgb", "mip level"):
        frames.render(orbit_camera(0.0), view=view)
        frames.render(orbit_camera(0.0), view=view, scale=4, enlarge=False)
    traces = sum(TRACE_COUNTS.values())
    programs = [memory_maps.program_count(f) for f in fns]
    for k, angle in enumerate(np.linspace(0.2, 2.5, 6)):
        cam = orbit_camera(angle, radius=3.2 + 0.15 * k)
        for view in ("rgb", "mip level"):
            for f in (frames.render(cam, view=view), frames.render(cam, view=view, scale=4, enlarge=False)):
                assert not f.grew and not f.compiled
    assert sum(TRACE_COUNTS.values()) == traces
    assert [memory_maps.program_count(f) for f in fns] == programs


def test_every_view_and_scale(frames):
    cam = orbit_camera(0.3)
    for view in vw.VIEWS:
        img = frames.render(cam, view=view).image
        assert img.shape == (H, W, 3) and img.dtype == np.uint8
        assert img.std() > 5, view  # something is drawn
    small = frames.render(cam, scale=4, enlarge=False).image
    big = frames.render(cam, scale=4).image
    assert small.shape == (H // 4, W // 4, 3) and big.shape == (H, W, 3)
    np.testing.assert_array_equal(big[::4, ::4], small)  # nearest neighbour
    np.testing.assert_array_equal(big[3::4, 3::4], small)


def test_mip_level_follows_eq11():
    """One fronto-parallel splat of scale s with a 32 x 32 texture at depth z under focal f: a pixel
    spans D = z / (f s) scale units, so the level is floor(log2(lambda 32 D)); rendering at 1/2
    doubles D (one level up). (The low-pass mode's dominant splats differ only where a splat is
    sub-pixel; the level's formula is the same with its lambda_mip.)"""
    z, f, s = 4.0, 100.0, 0.05
    D = z / (f * s)  # 0.8 scale units per pixel
    tex = [np.full((32, 32, 3), 0.1, np.float32)]
    scene = Scene.from_arrays(np.zeros((1, 3)), np.full((1, 2), s), np.array([[1.0, 0, 0, 0]]), np.array([0.9]),
                              np.zeros((1, 1, 3)), capacity=1)
    scene = scene.replace(rgb=TextureBank.from_list(tex, 1, 3, 0.0))
    cam = Camera.from_intrinsics((f, f, 32.0, 32.0), look_at((0, 0, -z), (0, 0, 0)), 64, 64)
    bare = scene.replace(rgb=None)  # the same dominant splat, cheaper to compile
    for coverage, lam in (("prefilter", 1 / 6),):
        cfg = RenderConfig(coverage=coverage)
        for factor in (1, 2):
            c = cam if factor == 1 else cam.scaled(factor)
            out = render(bare, c, cfg)
            lev = np.asarray(vw.dominant_mip_level(scene, c, out.dominant, bank="rgb", lambda_mip=lam, use_mip=True))
            want = int(np.clip(np.floor(np.log2(lam * 32 * D * factor)), 0, 5))
            centre = lev[c.height // 2, c.width // 2]
            assert centre == want, (coverage, factor, centre, want)
            assert (lev[np.asarray(out.dominant) < 0] == -1).all()
        lev = vw.dominant_mip_level(scene, cam, out.dominant, bank="rgb", lambda_mip=lam, use_mip=False)
        assert set(np.unique(np.asarray(lev))) <= {-1, 0}


def test_modes():
    base = RenderConfig(coverage="prefilter")
    assert vw.own_mode(base) == "patexgs"
    lit = vw.mode_config(base, "literal")
    assert (lit.coverage, lit.lambda_mip, lit.mip) == ("lowpass", 0.4, "nearest")
    off = vw.mode_config(base, "mip-off")
    assert (off.coverage, off.mip) == ("prefilter", "none")
    assert vw.own_mode(vw.render_config_of({"method": "2dgs"})) == "literal"
    assert vw.own_mode(vw.render_config_of({"method": "patexgs-no-mip"})) == "mip-off"
    with pytest.raises(vw.ViewerError, match="choose one of"):
        vw.mode_config(base, "bogus")


def test_modes_of_a_run_with_the_plane_filter():
    """A ``patexgs+filter3d`` scene (textured 2D splats with a 3D filter, which only the prefilter
    folds in) shows in every mode: the literal (low-pass) mode renders it without the filter; the
    others with it."""
    import jax.numpy as jnp

    from patexgs_jax.scene import random_scene

    sc = random_scene(2, 6, extent=0.5, scale_range=(0.05, 0.2), rgb_sizes=[2] * 6)
    sc = sc.replace(filter3d=jnp.full(sc.capacity, 0.01, jnp.float32))
    fr = vw.FrameRenderer(sc, RenderConfig(coverage="prefilter"))
    cam = Camera.from_intrinsics((40.0, 40.0, 16.0, 16.0), look_at((0, 0, -2.5), (0, 0, 0)), 32, 32)
    imgs = {m: fr.render(cam, mode=m).image for m in vw.MODES}
    assert all(img.max() > 0 for img in imgs.values())
    assert fr.renderer("literal").scene.filter3d is None and fr.renderer("patexgs").scene is sc


# ------------------------------------------------------------------------------------------------
# Runs and bad input
# ------------------------------------------------------------------------------------------------
def test_find_runs(viewer_run_dir, tmp_path):
    study = viewer_run_dir.parents[2]
    names = [r.name for r in vw.find_runs(study)]
    assert names == ["toy/2dgs", "toy/patexgs"]
    assert [r.name for r in vw.find_runs(viewer_run_dir)] == ["patexgs"]
    ck = ckpt.latest_checkpoint(viewer_run_dir / "checkpoints")
    assert vw.find_runs(ck)[0].path == ck
    run = vw.load_run(vw.find_runs(ck)[0])
    assert run.method == "patexgs" and run.config.coverage == "prefilter"
    with pytest.raises(vw.ViewerError, match="does not exist"):
        vw.find_runs(tmp_path / "nope")
    with pytest.raises(vw.ViewerError, match="no trained run"):
        vw.find_runs(tmp_path)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(vw.ViewerError, match="not a checkpoint"):
        vw.find_runs(tmp_path / "notes.txt")
    (tmp_path / "bad.ckpt").write_bytes(b"not a zip")
    with pytest.raises(vw.ViewerError, match="cannot read the run"):
        vw.load_run(vw.find_runs(tmp_path / "bad.ckpt")[0])


def test_browser_input_only_picks_from_lists(viewer_run_dir, tmp_path):
    """Values a browser sends are looked up in the lists made at start-up; anything else (a path, a
    made-up mode) is logged and ignored."""
    from patexgs_jax.viewer.server import Viewer

    lines = []
    viewer = Viewer(vw.find_runs(viewer_run_dir.parents[1]), log=lines.append)

    class Legend:
        content = ""

    viewer.gui_legend = Legend()
    before = dict(viewer.settings)
    viewer._pick_run(str(tmp_path / "elsewhere"))
    viewer._pick("mode", {v: k for k, v in vw.MODES.items()}, "../../etc/passwd")
    viewer._pick("scale", {"1": 1, "1/2": 2}, "1/3")
    assert viewer.settings == before
    assert sum("ignored" in line for line in lines) == 3, lines
    viewer._pick("view", {v: v for v in vw.VIEWS}, "depth")
    assert viewer.settings["view"] == "depth" and "Depth" in viewer.gui_legend.content
