"""The browser viewer (patexgs_jax.view, patexgs_jax.viewing): the browser's camera becomes our
Camera, camera moves never compile, the per-pixel mip level follows Eq. 11, the server answers a
client (a protocol-level client here, headless Chromium in the last tests), stops on SIGINT, and bad
input gets one line naming the fix.

The scene is a small random textured scene saved as a run folder (a checkpoint with its training
configuration, as training writes it); in-process frames are 64 x 48 pixels, and the servers
render at most 96 pixels a side (``--max-side``): the tests measure behaviour, not speed.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import jax
import numpy as np
import pytest

from locations import REPO
from patexgs_jax import checkpoint as ckpt
from patexgs_jax import compiled, rendering
from patexgs_jax import viewing as vw
from patexgs_jax.camera import Camera, look_at
from patexgs_jax.scene import Scene, random_scene
from patexgs_jax.textures import TextureBank

viser = pytest.importorskip("viser", reason='the viewer needs viser: pip install -e ".[viewer]"')

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def textured_scene(seed: int = 0, n: int = 300) -> Scene:
    """A random scene of n splats around the origin with 2 x 2 or 8 x 8 RGB textures and 4 x 4 alpha
    textures (few texture buckets: cheap to compile)."""
    sides = np.random.default_rng(seed).choice([2, 8], size=n)
    return random_scene(seed, n, sh_degree=1, extent=1.0, scale_range=(0.03, 0.25), rgb_sizes=sides,
                        alpha_sizes=[4] * n)


def write_run(folder: Path, scene: Scene, method: str = "patexgs") -> Path:
    """A run folder as training leaves it: checkpoints/ with the scene and its configuration."""
    ckpt.save_checkpoint(ckpt.checkpoint_path(folder / "checkpoints", 10), {"scene": scene},
                         {"step": 10, "config": {"method": method, "background": [0.0, 0.0, 0.0]}})
    return folder


#: The canvas of the in-process tests: one size bucket (and its 1/4 preview), shared through
#: ``frames``, so the renderer compiles for it once.
W, H = 64, 48


def orbit_camera(angle: float, width: int = W, height: int = H, radius: float = 3.5) -> Camera:
    eye = (radius * np.sin(angle), -0.6, -radius * np.cos(angle))
    f = 0.8 * width
    return Camera.from_intrinsics((f, f, width / 2, height / 2), look_at(eye, (0.0, 0.0, 0.0)), width, height)


@pytest.fixture(scope="module")
def scene():
    return textured_scene()


@pytest.fixture(scope="module")
def frames(scene):
    """The viewer's renderer of ``scene`` in PATexGS's own mode."""
    return vw.FrameRenderer(scene, rendering.RenderConfig(coverage="prefilter"))


@pytest.fixture(scope="module")
def run_dir(scene, tmp_path_factory):
    """A study's folder with two runs of one scene: ``runs/toy/patexgs`` (returned) and
    ``runs/toy/2dgs`` (a smaller scene, without textures)."""
    study = tmp_path_factory.mktemp("viewer")
    write_run(study / "runs" / "toy" / "2dgs", random_scene(1, 50), method="2dgs")
    return write_run(study / "runs" / "toy" / "patexgs", scene)


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


def test_training_view_through_the_viewer_renders_as_render(scene, frames):
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
    # FRAME_SCHEDULE changes the order of the work, not the image
    assert r.config != vw.mode_config(frames.base, "patexgs")
    ref = np.clip(np.asarray(rendering.render(scene, cam, vw.mode_config(frames.base, "patexgs")).rgb), 0, 1)
    assert frame.image.shape == (H, W, 3)
    assert ref.std() > 0.05  # the view sees the scene
    np.testing.assert_allclose(frame.image / 255.0, ref, atol=1.0 / 255 + 1e-6)


def test_camera_moves_never_compile(frames):
    """After the first frame at a canvas size (full and preview size), frames of other poses at that
    size compile nothing: neither the renderer nor the mip-level function."""
    fns = (rendering.render_jit, rendering.count_pairs, vw.dominant_mip_level)
    for view in ("rgb", "mip level"):
        frames.render(orbit_camera(0.0), view=view)
        frames.render(orbit_camera(0.0), view=view, scale=4, enlarge=False)
    traces = sum(rendering.TRACE_COUNTS.values())
    programs = [compiled.program_count(f) for f in fns]
    for k, angle in enumerate(np.linspace(0.2, 2.5, 6)):
        cam = orbit_camera(angle, radius=3.2 + 0.15 * k)
        for view in ("rgb", "mip level"):
            for f in (frames.render(cam, view=view), frames.render(cam, view=view, scale=4, enlarge=False)):
                assert not f.grew and not f.compiled
    assert sum(rendering.TRACE_COUNTS.values()) == traces
    assert [compiled.program_count(f) for f in fns] == programs


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
        cfg = rendering.RenderConfig(coverage=coverage)
        for factor in (1, 2):
            c = cam if factor == 1 else cam.scaled(factor)
            out = rendering.render(bare, c, cfg)
            lev = np.asarray(vw.dominant_mip_level(scene, c, out.dominant, bank="rgb", lambda_mip=lam, use_mip=True))
            want = int(np.clip(np.floor(np.log2(lam * 32 * D * factor)), 0, 5))
            centre = lev[c.height // 2, c.width // 2]
            assert centre == want, (coverage, factor, centre, want)
            assert (lev[np.asarray(out.dominant) < 0] == -1).all()
        lev = vw.dominant_mip_level(scene, cam, out.dominant, bank="rgb", lambda_mip=lam, use_mip=False)
        assert set(np.unique(np.asarray(lev))) <= {-1, 0}


def test_modes():
    base = rendering.RenderConfig(coverage="prefilter")
    assert vw.own_mode(base) == "patexgs"
    lit = vw.mode_config(base, "literal")
    assert (lit.coverage, lit.lambda_mip, lit.mip) == ("lowpass", 0.4, "nearest")
    off = vw.mode_config(base, "mip-off")
    assert (off.coverage, off.mip) == ("prefilter", "none")
    assert vw.own_mode(vw.render_config_of({"method": "2dgs"})) == "literal"
    assert vw.own_mode(vw.render_config_of({"method": "patexgs-no-mip"})) == "mip-off"
    with pytest.raises(vw.ViewerError, match="choose one of"):
        vw.mode_config(base, "bogus")


# ------------------------------------------------------------------------------------------------
# Runs and bad input
# ------------------------------------------------------------------------------------------------
def test_find_runs(run_dir, tmp_path):
    study = run_dir.parents[2]
    names = [r.name for r in vw.find_runs(study)]
    assert names == ["toy/2dgs", "toy/patexgs"]
    assert [r.name for r in vw.find_runs(run_dir)] == ["patexgs"]
    ck = ckpt.latest_checkpoint(run_dir / "checkpoints")
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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def subprocess_env(**extra) -> dict:
    """The environment of a viewer subprocess: this checkout first, and the session's XLA cache (the
    server's programs, shared by the tests that start one)."""
    env = dict(os.environ, PYTHONPATH=str(REPO), **extra)
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        env.update(JAX_COMPILATION_CACHE_DIR=cache, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="1")
    return env


def run_cli(*args, timeout=120):
    env = subprocess_env()
    return subprocess.run([sys.executable, "-m", "patexgs_jax.view", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO)


def test_cli_bad_input(run_dir, tmp_path, capsys):
    """Each gets one line naming the fix and exit status 2 (in-process; the command line's own exit
    status and the absence of a traceback in a subprocess, for a port in use)."""
    from patexgs_jax.view import main

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        busy = held.getsockname()[1]
        cases = [((tmp_path / "missing",), "does not exist"),
                 ((tmp_path,), "no trained run"),
                 ((run_dir, "--port", busy), f"port {busy} on 127.0.0.1 is already in use: pass another one"),
                 ((run_dir, "--port", 70000), "is not a TCP port"),
                 ((run_dir, "--host", "no.such.host.invalid"), "is not an address of this machine"),
                 ((run_dir, "--max-side", 4), "--max-side must be at least 16")]
        for args, message in cases:
            assert main([str(a) for a in args]) == 2, args
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], (args, err)
        r = run_cli(run_dir, "--port", busy)
    assert r.returncode == 2 and r.stderr.startswith("error: port") and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr + r.stdout


# ------------------------------------------------------------------------------------------------
# The server
# ------------------------------------------------------------------------------------------------
def start_viewer(path, port, *extra):
    env = subprocess_env(PYTHONUNBUFFERED="1")
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)
    proc = subprocess.Popen([sys.executable, "-m", "patexgs_jax.view", str(path), "--port", str(port), *extra],
                            stdout=log, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        text = Path(log.name).read_text()
        if "viewer: open http://" in text:
            return proc, Path(log.name)
        if proc.poll() is not None:
            raise AssertionError(f"viewer exited: {text}")
        time.sleep(0.2)
    proc.kill()
    raise AssertionError(f"viewer did not start: {Path(log.name).read_text()}")


def stop_viewer(proc, timeout=15.0) -> float:
    """SIGINT (Ctrl-C); returns how long it took to exit."""
    t = time.monotonic()
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("the viewer did not stop within 15 s of SIGINT") from None
    return time.monotonic() - t


def _decode_frames(raw: bytes) -> list[dict]:
    """The messages of one server-to-client websocket frame (viser's wire format: sizes, zstd
    msgpack, then binary buffers)."""
    import msgspec
    import zstandard

    n_comp = int.from_bytes(raw[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(raw[16:16 + n_comp], max_output_size=1 << 28)
    return msgspec.msgpack.decode(inner)["messages"]


def client_frames(port: int, width: int, height: int, poses, timeout: float = 120.0) -> list[bytes]:
    """Connects as viser's browser client does, sends one camera message per pose and returns the
    background images (JPEG bytes) the server sent, waiting for one per pose."""
    import msgspec
    from viser import _messages
    from websockets.sync.client import connect

    images = []
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=1 << 26,
                 open_timeout=30) as ws:
        deadline = time.monotonic() + timeout
        for wxyz, pos, fov in poses:
            msg = _messages.ViewerCameraMessage(wxyz=tuple(map(float, wxyz)), position=tuple(map(float, pos)),
                                                fov=float(fov), near=0.01, far=100.0, image_height=height,
                                                image_width=width, look_at=(0.0, 0.0, 0.0),
                                                up_direction=(0.0, -1.0, 0.0))
            ws.send(msgspec.msgpack.encode(msg.as_serializable_dict()))
            want = len(images) + 1
            while len(images) < want:
                raw = ws.recv(timeout=max(deadline - time.monotonic(), 0.1))
                for m in _decode_frames(raw):
                    if m.get("type") == "BackgroundImageMessage" and m.get("rgb_data"):
                        images.append(bytes(m["rgb_data"]))
    return images


@pytest.fixture(scope="module")
def server(run_dir):
    """(process, log file, port) of one viewer serving ``run_dir`` (frames at most 96 pixels a side),
    shared by the server tests; ``test_server_stops_on_sigint`` ends it."""
    port = free_port()
    proc, log = start_viewer(run_dir, port, "--max-side", "96")
    yield proc, log, port
    if proc.poll() is None:
        proc.kill()


def test_server_serves_page_and_answers_cameras(server):
    import io

    from PIL import Image

    proc, log, port = server
    page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30).read().decode()
    assert "<html" in page.lower()
    poses = [vw.viewer_pose(orbit_camera(a, 160, 120)) for a in (0.3, 0.5)]
    images = client_frames(port, 160, 120, poses)
    first = np.asarray(Image.open(io.BytesIO(images[0])))
    assert first.shape == (72, 96, 3) and first.std() > 5  # the canvas at --max-side
    # A second tab while the first one has closed: the server still answers.
    images = client_frames(port, 96, 64, poses[:1])
    assert np.asarray(Image.open(io.BytesIO(images[0]))).shape == (64, 96, 3)
    assert proc.poll() is None
    assert log.read_text().count("first frame") >= 2


def test_non_loopback_host_warns(run_dir):
    port = free_port()
    proc, log = start_viewer(run_dir, port, "--host", "0.0.0.0")
    try:
        text = log.read_text()
        warnings = [l for l in text.splitlines() if l.startswith("warning:")]
        assert len(warnings) == 1 and "0.0.0.0" in warnings[0] and "no authentication" in warnings[0]
    finally:
        stop_viewer(proc)


# ------------------------------------------------------------------------------------------------
# In a real browser
# ------------------------------------------------------------------------------------------------
def chromium_screenshot(url: str, out: Path, size=(800, 600), wait_for=None, timeout: float = 120.0) -> None:
    """Loads ``url`` in headless Chromium and saves a PNG screenshot once ``wait_for()`` is true (then
    one more second for the frame to be drawn), driving it through the DevTools protocol."""
    from websockets.sync.client import connect

    profile = Path(tempfile.mkdtemp(prefix="chromium-profile-"))
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0",
            "about:blank"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + timeout
        port_file = profile / "DevToolsActivePort"
        while not port_file.exists() or not port_file.read_text().strip():
            assert time.monotonic() < deadline and proc.poll() is None, "chromium did not start"
            time.sleep(0.1)
        devtools = int(port_file.read_text().split()[0])
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{devtools}/json/list", timeout=10).read())
        target = next(p for p in pages if p["type"] == "page")
        with connect(target["webSocketDebuggerUrl"], max_size=1 << 26) as ws:
            ids = iter(range(1, 1000))

            def call(method, **params):
                i = next(ids)
                ws.send(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    reply = json.loads(ws.recv(timeout=max(deadline - time.monotonic(), 0.1)))
                    if reply.get("id") == i:
                        return reply.get("result", {})

            call("Page.enable")
            call("Page.navigate", url=url)
            while wait_for is not None and not wait_for():
                assert time.monotonic() < deadline, "the page never showed a frame"
                time.sleep(0.2)
            time.sleep(1.0)
            shot = call("Page.captureScreenshot", format="png")
            out.write_bytes(base64.b64decode(shot["data"]))
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(profile, ignore_errors=True)


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium: apt-get install -y chromium (Debian) to run the "
                                             "browser test")
def test_in_headless_chromium(server, tmp_path):
    from PIL import Image

    proc, log, port = server
    before = log.read_text()
    shot = tmp_path / "viewer.png"
    chromium_screenshot(f"http://127.0.0.1:{port}/", shot,
                        wait_for=lambda: log.read_text().count("first frame") > before.count("first frame"))
    assert proc.poll() is None
    new = log.read_text()[len(before):]
    assert ": connected" in new and ": first frame" in new, new
    img = np.asarray(Image.open(shot).convert("RGB"), np.float32)
    # The scene fills the canvas left of the control panel: not blank, and not one flat colour.
    region = img[100:500, 50:400]
    assert region.std() > 10, region.std()
    assert (np.abs(region - region.mean(axis=(0, 1))).sum(-1) > 30).mean() > 0.05


def test_server_stops_on_sigint(server):
    proc, log, _ = server
    took = stop_viewer(proc)
    text = log.read_text()
    assert proc.returncode == 0 and "Traceback" not in text, text
    assert took < 10, took
    assert text.rstrip().endswith("viewer: stopped"), text


def test_browser_input_only_picks_from_lists(run_dir, tmp_path):
    """Values a browser sends are looked up in the lists made at start-up; anything else (a path, a
    made-up mode) is logged and ignored."""
    from patexgs_jax.view import Viewer

    lines = []
    viewer = Viewer(vw.find_runs(run_dir.parents[1]), log=lines.append)

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


def test_bench_viewer_reports_frames(tmp_path, capsys):
    from experiments import bench_viewer

    out = tmp_path / "viewer.json"
    # --preview 1: the preview is the frame's own size bucket, one program to compile
    bench_viewer.main(["--models", "synthetic", "--gaussians", "400", "--sizes", "32x32", "--repeats", "2",
                       "--preview", "1", "--json", str(out)])
    data = json.loads(out.read_text())
    for key in ("schema", "git", "date", "machine", "cpus", "jax", "load_average_before"):
        assert key in data, key
    (row,) = data["results"]
    assert (row["model"], row["gaussians"], row["width"], row["height"]) == ("synthetic", 400, 32, 32)
    assert row["recompiles"] == 0 and row["preview_size"] == [32, 32]
    for key in ("frame_ms", "frame_cpu_ms", "preview_ms", "jpeg_ms", "fps", "preview_fps"):
        assert np.isfinite(row[key]) and row[key] > 0, key
    assert "32x32" in capsys.readouterr().out


def test_training_views_snap_and_compare(run_dir, scene):
    """With a dataset, the training cameras are frustums; snapping a tab to one moves its camera to
    the view's pose and shows the render beside the ground truth with the PSNR."""
    import contextlib
    import types

    from patexgs_jax.view import Viewer

    cams = [orbit_camera(a) for a in (0.2, 1.0, 2.0)]
    gt = vw.FrameRenderer(scene, rendering.RenderConfig(coverage="prefilter"))
    views = [types.SimpleNamespace(camera=c, name=f"view{i}", image=gt.render(c).image / np.float32(255))
             for i, c in enumerate(cams)]
    lines = []
    viewer = Viewer(vw.find_runs(run_dir.parents[2]), types.SimpleNamespace(train_views=views), log=lines.append)
    assert viewer.run.name == "toy/patexgs"  # a study opens on its patexgs run
    viewer.start("127.0.0.1", free_port())
    try:
        assert len(viewer.frustums) == 3 and not viewer.frustums[0].visible  # the opening view's
        client = types.SimpleNamespace(client_id=7, atomic=contextlib.nullcontext,
                                       camera=types.SimpleNamespace(wxyz=None, position=None, fov=None))
        viewer._snap(client, 1)
        wxyz, pos, fov = vw.viewer_pose(cams[1])
        np.testing.assert_allclose(client.camera.wxyz, wxyz, atol=1e-12)
        np.testing.assert_allclose(client.camera.position, pos, atol=1e-12)
        assert client.camera.fov == pytest.approx(fov)
        assert viewer.frustums[0].visible and not viewer.frustums[1].visible
        assert "view1" in viewer.gui_gt_text.content and "PSNR" in viewer.gui_gt_text.content
        assert viewer.gui_gt.image.shape == (H, 2 * W + 4, 3)
        psnr = float(viewer.gui_gt_text.content.split("PSNR ")[1].split(" dB")[0])
        assert psnr > 40  # the ground truth is this render (uint8-rounded)
        # Switching runs (by the name the browser lists) loads the other one, in its own mode.
        viewer._pick_run("toy/2dgs")
        assert viewer.run.method == "2dgs" and viewer.stats["gaussians"] == 50
        assert viewer.settings["mode"] == "literal" and viewer.gui_mode.value == vw.MODES["literal"]
        assert "toy/2dgs" in viewer.gui_status.content
    finally:
        viewer.stop()
