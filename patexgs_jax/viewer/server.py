"""Interactive browser viewer of trained runs (viser).

    python -m patexgs_jax.viewer PATH [--port 8080] [--host 127.0.0.1] [--data DATA [--factor F]]

PATH is a run folder (``runs/<scene>/<label>/``), a study's output folder (its runs are listed and
the browser switches between them) or a checkpoint file. ``--data`` names the scene the run was
trained on, to show its training cameras (frustums with thumbnails; a click snaps to the view and
shows the render beside the ground truth with its PSNR). Open the printed URL in a browser.

The server renders each browser's camera with the jitted renderer and sends the image as the
scene's background: at a reduced size while the camera moves, at full size once it rests for
``--settle`` seconds. Controls: render scale 1, 1/2, 1/4, 1/8 (the zoom-out protocol, enlarged by
nearest neighbour), coverage mode, view (see :mod:`patexgs_jax.viewer.frames`), run.

Safety: it binds to 127.0.0.1 unless ``--host`` says otherwise (with a warning: the viewer has no
authentication). The browser only picks from lists made at start-up (runs, modes, views, scales,
training views): nothing it sends names a file. viser's public share link is switched off. A closed tab
or several tabs never stop the server; Ctrl-C (SIGINT) or SIGTERM ends it.

Needs the ``viewer`` extra: ``pip install -e ".[viewer]"`` (viser).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import io
import math
import os
import socket
import sys
import threading
import time
import warnings
from typing import Any

import numpy as np

from .. import interrupt, memory_maps
from . import frames as vw

_LOOPBACK = ("127.0.0.1", "localhost", "::1")
#: Seconds after a full-size frame at which a resting camera's frame is sent again: viser's browser
#: client drops its background when its 3D view is re-created (seen when it shows a notification).
_RESEND = (1.0, 3.0, 7.0)
_SCALE_LABELS = {"1": 1, "1/2": 2, "1/4": 4, "1/8": 8}


def check_port(host: str, port: int) -> None:
    """Raises :class:`viewing.ViewerError` naming the fix when ``host:port`` cannot be bound (viser
    would silently move to the next free port)."""
    if not 0 < port < 65536:
        raise vw.ViewerError(f"--port {port} is not a TCP port: pass a number from 1 to 65535, e.g. --port 8080.")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise vw.ViewerError(f"--host {host} is not an address of this machine ({e.strerror}): pass e.g. "
                             "--host 127.0.0.1, or 0.0.0.0 for every interface.") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds it
        try:
            s.bind(addr)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise vw.ViewerError(f"port {port} on {host} is already in use: pass another one, e.g. "
                                     f"--port {port + 1 if port < 65535 else 8080}, or stop the program "
                                     "that holds it.") from None
            if e.errno == errno.EACCES:
                raise vw.ViewerError(
                    f"port {port} needs privileges: pass a port above 1023, e.g. --port 8080.") from None
            if e.errno == errno.EADDRNOTAVAIL:
                raise vw.ViewerError(f"--host {host} is not an address of this machine: pass e.g. --host "
                                     "127.0.0.1, or 0.0.0.0 for every interface.") from None
            raise vw.ViewerError(
                f"cannot listen on {host}:{port} ({e.strerror}): pass another --port or --host.") from None


@dataclasses.dataclass
class _Client:
    """What the render loop knows of one browser tab."""

    handle: Any                      # viser's ClientHandle (viser is imported when the viewer starts)
    camera: tuple | None = None      # (wxyz, position, fov, width, height) of the newest message
    version: int = 0                 # counts camera messages
    moved: float = 0.0               # time.monotonic() of the newest message
    sent: tuple | None = None        # (camera version, settings version) of the newest frame sent
    final: bool = False              # the newest frame sent was full size
    frames: int = 0
    image: np.ndarray | None = None  # the newest full-size frame, and when it was sent
    sent_at: float = 0.0
    resent: int = 0                  # how many times it was sent again (see _RESEND)


class Viewer:
    """The viewer's state and its render loop (one thread renders for every tab in turn).

    Args:
      runs: the :class:`viewing.RunEntry` list (found at start-up; the browser picks by index).
      dataset: the training scene (a loaded :class:`patexgs_jax.data.Dataset`) or None.
      max_side: the longest side of a frame (a larger canvas is rendered at this size and stretched).
      preview: while the camera moves, frames are rendered this many times smaller a side.
      settle: seconds without a camera message after which the full-size frame is rendered.
      verbose: log every frame sent (size, time, whether it compiled).
      log: where status lines go.
    """

    run: vw.LoadedRun            # the run on screen and its renderer: set by load(), which __init__ calls
    frames: vw.FrameRenderer

    def __init__(self, runs, dataset=None, *, max_side: int = 1280, preview: int = 4, settle: float = 0.2,
                 max_cameras: int = 300, verbose: bool = False, log=None):
        self.runs = list(runs)
        self.dataset = dataset
        self.max_side, self.preview, self.settle = int(max_side), int(preview), float(settle)
        self.max_cameras = int(max_cameras)
        self.verbose = verbose
        self.log = log or (lambda msg: print(msg, flush=True))
        self.lock = threading.RLock()          # the scene, its renderers and the settings
        self.wake = threading.Condition()
        self.stopping = threading.Event()
        self.clients: dict[int, _Client] = {}
        self.settings: dict[str, Any] = dict(run=0, mode="patexgs", view="rgb", scale=1)
        self.settings_version = 0
        self.last_ms: dict = {}  # "final" / "preview" -> ms of the newest frame that compiled nothing
        self.server = None
        self._thread = None
        self._status_time = 0.0
        # A study opens on a PATexGS run when it has one.
        names = [r.name.rsplit("/", 1)[-1] for r in self.runs]
        self.load(names.index("patexgs") if "patexgs" in names else 0)

    # -- the scene ---------------------------------------------------------------------------------
    def load(self, index: int) -> None:
        """Shows run ``index`` of :attr:`runs` (its own coverage mode)."""
        entry = self.runs[index]
        run = vw.load_run(entry)
        with self.lock:
            if getattr(self, "frames", None) is not None:
                self.frames.release()
            self.run, self.frames = run, vw.FrameRenderer(run.scene, run.config)
            self.stats = vw.scene_stats(run.scene)
            self.settings.update(run=index, mode=vw.own_mode(run.config))
            self.settings_version += 1
        self.log(f"run {entry.name}: {run.method}, {self.stats['gaussians']:,} Gaussians")

    # -- server ------------------------------------------------------------------------------------
    def start(self, host: str, port: int) -> None:
        """Starts the web server on ``host:port`` and the render loop."""
        import viser

        check_port(host, port)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: main() prints the URL
            server = viser.ViserServer(host=host, port=port, label="patexgs-jax", verbose=False)
        if server.get_port() != port:  # taken between the check and the bind
            server.stop()
            raise vw.ViewerError(f"port {port} on {host} is already in use: pass another one, e.g. --port {port + 1}.")
        # A browser may ask viser for a public share link (a tunnel through an outside server): never.
        server.request_share_url = lambda *a, **k: self.log("ignored a browser's request for a public share link")
        server.gui.configure_theme(show_share_button=False)
        # A tab that closes while its frame is sent: that frame is dropped, as it should be.
        warnings.filterwarnings("ignore", message="Queued a BackgroundImageMessage on a closed connection")
        self.server = server
        self._gui(server)
        self._cameras(server)
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)
        self._thread = threading.Thread(target=self._loop, name="patexgs-view-render", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stops the render loop and the server."""
        self.stopping.set()
        with self.wake:
            self.wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
        if self.server is not None:
            with contextlib.redirect_stdout(io.StringIO()):  # viser's "Server stopped": main() says it
                self.server.stop()

    def _gui(self, server) -> None:
        gui = server.gui
        if len(self.runs) > 1:
            self.gui_run = gui.add_dropdown("Run", options=[r.name for r in self.runs],
                                            initial_value=self.runs[self.settings["run"]].name)
            self.gui_run.on_update(lambda _: self._pick_run(self.gui_run.value))
        self.gui_mode = gui.add_dropdown("Coverage", options=list(vw.MODES.values()),
                                         initial_value=vw.MODES[self.settings["mode"]])
        self.gui_mode.on_update(lambda _: self._pick("mode", {v: k for k, v in vw.MODES.items()}, self.gui_mode.value))
        self.gui_view = gui.add_dropdown("View", options=list(vw.VIEWS), initial_value="rgb")
        self.gui_view.on_update(lambda _: self._pick("view", {v: v for v in vw.VIEWS}, self.gui_view.value))
        self.gui_scale = gui.add_dropdown("Render scale", options=list(_SCALE_LABELS), initial_value="1")
        self.gui_scale.on_update(lambda _: self._pick("scale", _SCALE_LABELS, self.gui_scale.value))
        self.gui_status = gui.add_markdown(self._status())
        self.gui_legend = gui.add_markdown(_LEGENDS["rgb"])
        if self.dataset is not None:
            with gui.add_folder("Training view"):
                self.gui_gt_text = gui.add_markdown("Click a camera frustum to snap to its view.")
                self.gui_gt = gui.add_image(np.zeros((8, 16, 3), np.uint8), label="render | ground truth")

    def _pick(self, key: str, allowed: dict, value) -> None:
        """A control changed: ``value`` must be one of ``allowed``'s keys (what the browser sends is
        only ever looked up)."""
        if value not in allowed:
            self.log(f"ignored a {key} of {value!r} from a browser: not one of the choices")
            return
        with self.lock:
            self.settings[key] = allowed[value]
            self.settings_version += 1
        if key == "view":
            self.gui_legend.content = _LEGENDS[value]
        with self.wake:
            self.wake.notify_all()

    def _pick_run(self, name) -> None:
        index = {r.name: i for i, r in enumerate(self.runs)}.get(name)
        if index is None:
            self.log(f"ignored a run {name!r} from a browser: not one of the runs found at start-up")
            return
        if index == self.settings["run"]:
            return
        try:
            self.load(index)
        except vw.ViewerError as e:
            self.log(f"error: {e}")
            return
        self.gui_mode.value = vw.MODES[self.settings["mode"]]
        self.gui_status.content = self._status()
        with self.wake:
            self.wake.notify_all()

    def _status(self) -> str:
        s = self.stats

        def ms(k):
            return f"{self.last_ms[k]:.0f}" if k in self.last_ms else "-"

        return (f"**{self.runs[self.settings['run']].name}** ({self.run.method}): {s['gaussians']:,} Gaussians, "
                f"{s['texels']:,} texels, {s['storage_mb']:.2f} MB; {ms('final')} ms per frame "
                f"({ms('preview')} ms while moving)")

    # -- training cameras --------------------------------------------------------------------------
    def _cameras(self, server) -> None:
        if self.dataset is None:
            return
        views = list(self.dataset.train_views)
        step = max(1, math.ceil(len(views) / self.max_cameras))
        self.train_views = views[::step]
        self.frustums, self.hidden = [], None
        centres = np.array([v.camera.center for v in self.train_views])
        spread = np.median(np.linalg.norm(centres - np.median(centres, axis=0), axis=1)) if len(centres) > 1 else 1.0
        size = 0.08 * float(spread) if spread > 0 else 0.1
        ups = [-v.camera.camera_to_world[:3, 1] for v in self.train_views]
        up = np.mean(ups, axis=0)
        if np.linalg.norm(up) > 1e-6:
            server.scene.set_up_direction(tuple(up / np.linalg.norm(up)))
        for i, v in enumerate(self.train_views):
            wxyz, pos, fov = vw.viewer_pose(v.camera)
            thumb = _thumbnail(v.image, 96)
            h = server.scene.add_camera_frustum(f"/train/{i:04d}", fov=fov, aspect=v.camera.width / v.camera.height,
                                                scale=size, image=thumb, wxyz=wxyz, position=pos,
                                                color=(40, 160, 255))
            h.on_click(lambda event, i=i: self._snap(event.client, i))
            self.frustums.append(h)
        # The browser opens at the first training view, whose frustum (in front of the camera) is hidden.
        wxyz, pos, fov = vw.viewer_pose(self.train_views[0].camera)
        server.initial_camera.position = tuple(pos)
        look = pos + vw.quat_to_matrix(wxyz)[:, 2] * float(spread if spread > 0 else 1.0)
        server.initial_camera.look_at = tuple(look)
        server.initial_camera.fov = fov
        self._hide_frustum(0)

    def _hide_frustum(self, i: int) -> None:
        """Shows every training frustum but ``i`` (the view snapped to: its image plane would cover it)."""
        if self.hidden is not None:
            self.frustums[self.hidden].visible = True
        self.frustums[i].visible = False
        self.hidden = i

    def _snap(self, client, i: int) -> None:
        """Moves ``client``'s camera to training view ``i`` and shows its render beside the ground
        truth, with the PSNR (rendered at the view's own camera, scale 1, current coverage mode)."""
        from ..metrics import psnr

        if not 0 <= i < len(self.train_views):
            return
        v = self.train_views[i]
        wxyz, pos, fov = vw.viewer_pose(v.camera)
        self._hide_frustum(i)
        with client.atomic():
            client.camera.wxyz = wxyz
            client.camera.position = pos
            client.camera.fov = fov
        with self.lock:
            mode = self.settings["mode"]
            img = self.frames.render(v.camera, mode=mode, view="rgb").image
        gt = np.asarray(v.image, np.float32)
        value = float(psnr(img.astype(np.float32) / 255.0, gt))
        self.gui_gt.image = np.concatenate([img, np.full((img.shape[0], 4, 3), 255, np.uint8),
                                            (np.clip(gt, 0, 1) * 255 + 0.5).astype(np.uint8)], axis=1)
        self.gui_gt_text.content = (f"**{v.name}** ({v.camera.width}x{v.camera.height}), {vw.MODES[mode]}: "
                                    f"PSNR {value:.2f} dB")
        self.log(f"client {client.client_id}: snapped to training view {v.name}, PSNR {value:.2f} dB")

    # -- clients -----------------------------------------------------------------------------------
    def _connect(self, client) -> None:
        state = _Client(handle=client)
        self.clients[client.client_id] = state

        def update(camera) -> None:
            state.camera = (np.array(camera.wxyz), np.array(camera.position), float(camera.fov),
                            int(camera.image_width), int(camera.image_height))
            state.version += 1
            state.moved = time.monotonic()
            with self.wake:
                self.wake.notify_all()

        client.camera.on_update(update)
        # viser connects a client on its first camera message, which reached no callback yet.
        update(client.camera)
        self.log(f"client {client.client_id}: connected")

    def _disconnect(self, client) -> None:
        self.clients.pop(client.client_id, None)
        self.log(f"client {client.client_id}: disconnected")

    def _loop(self) -> None:
        while not self.stopping.is_set():
            with self.wake:
                self.wake.wait(timeout=0.05)
            for state in list(self.clients.values()):
                if self.stopping.is_set():
                    return
                job = self._job(state)
                if job is not None:
                    try:
                        self._send(state, job)
                    except Exception as e:  # one tab's failure (a closed socket) never stops the others
                        self.log(f"client {state.handle.client_id}: frame not sent ({type(e).__name__}: {e})")
                        state.sent = (state.version, self.settings_version)

    def _job(self, state: _Client) -> str | None:
        """"preview", "final", "resend" or None: what ``state``'s tab needs next."""
        if state.camera is None:
            return None
        key = (state.version, self.settings_version)
        if state.sent != key:
            moved = state.sent is not None and state.sent[0] != state.version
            return "preview" if moved else "final"
        now = time.monotonic()
        if not state.final and now - state.moved >= self.settle:
            return "final"
        if state.final and state.resent < len(_RESEND) and now - state.sent_at >= _RESEND[state.resent]:
            return "resend"
        return None

    def _send(self, state: _Client, job: str) -> None:
        if job == "resend":
            state.resent += 1
            state.handle.scene.set_background_image(state.image, format="jpeg", jpeg_quality=90)
            state.handle.flush()
            return
        if state.camera is None:
            return
        wxyz, pos, fov, w, h = state.camera
        key = (state.version, self.settings_version)
        w, h = vw.fit_canvas(w, h, self.max_side)
        cam = vw.camera_from_viewer(wxyz, pos, fov, w, h)
        with self.lock:
            s = dict(self.settings)
            scale = s["scale"]
            if job == "preview":  # smaller, and left for the browser to stretch
                p = self.preview
                while p > 1 and min(w, h) // (scale * p) < 8:
                    p //= 2
                frame = self.frames.render(cam, mode=s["mode"], view=s["view"], scale=scale * p, enlarge=False)
            else:
                frame = self.frames.render(cam, mode=s["mode"], view=s["view"], scale=scale)
        client = state.handle
        if state is not self.clients.get(client.client_id):
            return  # the tab closed while its frame rendered
        client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=90 if job == "final" else 70)
        client.flush()
        state.sent, state.final = key, job == "final"
        state.frames += 1
        if job == "final":
            state.image, state.sent_at, state.resent = frame.image, time.monotonic(), 0
        if not frame.compiled:
            self.last_ms[job] = frame.ms
        if self.verbose:
            self.log(f"client {client.client_id}: {job} frame {frame.rendered[0]}x{frame.rendered[1]}, "
                     f"{frame.ms:.0f} ms{' (compiled)' if frame.compiled else ''}")
        if state.frames == 1:
            self.log(f"client {client.client_id}: first frame, {frame.rendered[0]}x{frame.rendered[1]} rendered "
                     f"in {frame.ms:.0f} ms")
        if frame.compiled:  # a long session compiles many programs: keep within the memory-map cap
            memory_maps.release_compiled_code()
        if frame.grew:
            self.log(f"tile capacity grown for a {frame.rendered[0]}x{frame.rendered[1]} view (one new program)")
        now = time.monotonic()
        if now - self._status_time > 0.5:
            self._status_time = now
            self.gui_status.content = self._status()


_LEGENDS = {
    "rgb": "RGB render.",
    "depth": "Depth: light near, dark far (2nd to 98th percentile); black: nothing hit.",
    "normal": "Normals, camera frame as (x, -y, -z) / 2 + 1/2: facing the camera is blue.",
    "alpha": "Accumulated opacity: white opaque, black empty.",
    "mip level": ("Eq. 11 mip level of each pixel's dominant splat: 0 blue, 1 cyan, 2 green, 3 yellow, "
                  "4 orange, 5 red; black: no splat or no texture."),
    "texture side": "Texture side of each pixel's dominant splat: log2 n from 1 (dark) to 32 (light); black: none.",
}


def _thumbnail(image, width: int) -> np.ndarray:
    from PIL import Image

    img = (np.clip(np.asarray(image, np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    h, w = img.shape[:2]
    if w <= width:
        return img
    return np.asarray(Image.fromarray(img).resize((width, max(1, round(h * width / w))), Image.Resampling.BOX))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.viewer", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("path", help="a run folder, a study's output folder or a .ckpt file")
    ap.add_argument("--port", type=int, default=8080, help="port of the web page (default 8080)")
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    ap.add_argument("--data", default=None, help="the scene the run was trained on, to show its training cameras")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling factor of --data (as training)")
    ap.add_argument("--max-side", type=int, default=1280, help="longest side of a rendered frame (default 1280)")
    ap.add_argument("--preview", type=int, default=4, help="frames while moving are this many times smaller a side")
    ap.add_argument("--settle", type=float, default=0.2, help="seconds at rest before the full-size frame")
    ap.add_argument("--verbose", action="store_true", help="log every frame sent")
    args = ap.parse_args(argv)
    memory_maps.enable_compile_cache()
    try:
        if args.max_side < 16 or args.preview < 1 or args.settle < 0:
            raise vw.ViewerError("--max-side must be at least 16, --preview at least 1 and --settle >= 0.")
        try:
            import viser  # noqa: F401
        except ImportError:
            raise vw.ViewerError('the viewer needs viser: pip install -e ".[viewer]"') from None
        runs = vw.find_runs(args.path)
        check_port(args.host, args.port)
        dataset = None
        if args.data is not None:
            from ..data import DatasetError, load

            try:
                dataset = load(args.data, factor=args.factor)
            except (DatasetError, OSError) as e:
                raise vw.ViewerError(f"--data {args.data}: {e}") from None
        viewer = Viewer(runs, dataset, max_side=args.max_side, preview=args.preview, settle=args.settle,
                        verbose=args.verbose)
        viewer.start(args.host, args.port)
    except vw.ViewerError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.host not in _LOOPBACK:
        print(f"warning: listening on {args.host}: anyone who reaches this machine on port {args.port} can "
              "view the scene (the viewer has no authentication)", flush=True)
    shown = "[::1]" if args.host == "::1" else ("127.0.0.1" if args.host in ("0.0.0.0", "::", "") else args.host)
    print(f"viewer: open http://{shown}:{args.port} ({len(runs)} run{'s' if len(runs) > 1 else ''}; "
          "Ctrl-C to stop)", flush=True)
    done = threading.Event()
    # Ctrl-C and SIGTERM end the viewer even when the process that started it ignores or blocks them.
    interrupt.handle_stop_signals(lambda *_: done.set())
    while not done.wait(0.5):
        pass
    viewer.stop(timeout=3.0)  # a frame still compiling is not waited for (see below)
    print("viewer: stopped", flush=True)
    if viewer._thread is not None and viewer._thread.is_alive():
        # A frame still compiling: ending the interpreter under XLA's running thread aborts the process.
        sys.stderr.flush()
        os._exit(0)
    return 0

