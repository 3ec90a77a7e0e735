"""The browser viewer end to end (patexgs_jax.viewer): the command line's bad input, the server answering
a client (a protocol-level client here, headless Chromium below) and stopping on SIGINT, training
views snapped to and compared, and the viewer benchmark's report.

The servers serve a small random textured scene's run folder (tests/viewer_scenes.py) and render at
most 96 pixels a side (``--max-side``): the tests measure behaviour, not speed.
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
from patexgs_jax.render import RenderConfig
from patexgs_jax.viewer import frames as vw
from viewer_scenes import H, W, orbit_camera

viser = pytest.importorskip("viser", reason='the viewer needs viser: pip install -e ".[viewer]"')

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


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
    return subprocess.run([sys.executable, "-m", "patexgs_jax.viewer", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO)


def test_cli_bad_input(viewer_run_dir, tmp_path, capsys):
    """Each gets one line naming the fix and exit status 2 (in-process; the command line's own exit
    status and the absence of a traceback in a subprocess, for a port in use)."""
    from patexgs_jax.viewer.server import main

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        busy = held.getsockname()[1]
        cases = [((tmp_path / "missing",), "does not exist"),
                 ((tmp_path,), "no trained run"),
                 ((viewer_run_dir, "--port", busy), f"port {busy} on 127.0.0.1 is already in use: pass another one"),
                 ((viewer_run_dir, "--port", 70000), "is not a TCP port"),
                 ((viewer_run_dir, "--host", "no.such.host.invalid"), "is not an address of this machine"),
                 ((viewer_run_dir, "--max-side", 4), "--max-side must be at least 16")]
        for args, message in cases:
            assert main([str(a) for a in args]) == 2, args
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], (args, err)
        r = run_cli(viewer_run_dir, "--port", busy)
    assert r.returncode == 2 and r.stderr.startswith("error: port") and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr + r.stdout


# ------------------------------------------------------------------------------------------------
# The server
# ------------------------------------------------------------------------------------------------
def start_viewer(path, port, *extra, before=None):
    """The viewer's process and its log file, once it printed its URL; ``before``: Python statements
    run in the process first, which then becomes the viewer (exec keeps signal dispositions and
    masks, as a viewer started by another program inherits them)."""
    env = subprocess_env(PYTHONUNBUFFERED="1")
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)
    cmd = [sys.executable, "-m", "patexgs_jax.viewer", str(path), "--port", str(port), *extra]
    if before is not None:
        cmd = [sys.executable, "-c", f"import os, signal, sys; {before}; os.execv(sys.executable, "
               "[sys.executable] + sys.argv[1:])"] + cmd[1:]
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
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
def server(viewer_run_dir):
    """(process, log file, port) of one viewer serving ``viewer_run_dir`` (frames at most 96 pixels a side),
    shared by the server tests; ``test_server_stops_on_sigint`` ends it."""
    port = free_port()
    proc, log = start_viewer(viewer_run_dir, port, "--max-side", "96")
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
    # The server logs a tab's first frame after sending it: the line may trail the image a little.
    deadline = time.monotonic() + 30
    while log.read_text().count("first frame") < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert log.read_text().count("first frame") >= 2, log.read_text()


def test_non_loopback_host_warns(viewer_run_dir):
    port = free_port()
    proc, log = start_viewer(viewer_run_dir, port, "--host", "0.0.0.0")
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


@pytest.mark.parametrize("inherit", ["signal.signal(signal.SIGINT, signal.SIG_IGN)",
                                     "signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})"],
                         ids=["ignored", "blocked"])
def test_server_stops_on_sigint_inherited_ignored_or_blocked(viewer_run_dir, inherit):
    """A viewer started with SIGINT ignored or blocked (both are inherited, e.g. from a test runner's
    worker) still ends on Ctrl-C."""
    proc, log = start_viewer(viewer_run_dir, free_port(), before=inherit)
    try:
        took = stop_viewer(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert proc.returncode == 0 and text.rstrip().endswith("viewer: stopped"), text
    assert took < 10, took


def test_bench_viewer_reports_frames(tmp_path, capsys):
    from experiments import bench_viewer

    out = tmp_path / "viewer.json"
    # --preview 1: the preview is the frame's own padded size, one program to compile
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


def test_training_views_snap_and_compare(viewer_run_dir, viewer_scene):
    """With a dataset, the training cameras are frustums; snapping a tab to one moves its camera to
    the view's pose and shows the render beside the ground truth with the PSNR."""
    import contextlib
    import types

    from patexgs_jax.viewer.server import Viewer

    cams = [orbit_camera(a) for a in (0.2, 1.0, 2.0)]
    gt = vw.FrameRenderer(viewer_scene, RenderConfig(coverage="prefilter"))
    views = [types.SimpleNamespace(camera=c, name=f"view{i}", image=gt.render(c).image / np.float32(255))
             for i, c in enumerate(cams)]
    lines = []
    viewer = Viewer(vw.find_runs(viewer_run_dir.parents[2]), types.SimpleNamespace(train_views=views), log=lines.append)
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
