"""``python -m patexgs_jax.render``: a trained model's frames along a camera path, as numbered PNGs
and one H.264 MP4 (:mod:`patexgs_jax.render` stays the renderer; its ``__main__`` hands over here).

    python -m patexgs_jax.render SOURCE --out DIR [--path orbit|spiral|zoom-out|test|FILE.json]
        [--frames N] [--fps F] [--width W] [--enlarge K] [--compare SOURCE2 ...]
        [--mode rgb|depth|normal|alpha|mip|side] [--data DIR [--factor F]] [--save-path FILE.json]
        [--video FILE | --no-video]

SOURCE is a run folder, a checkpoint or a PLY (:func:`patexgs_jax.sources.load_source`). Paths
(:mod:`patexgs_jax.camera_paths`): ``orbit`` and ``spiral`` about the scene (its centre and radius
from the training cameras), ``test`` (the dataset's test cameras), ``zoom-out`` (from the first test
view, or the first training view, the lens zoomed out until what filled its width covers 1/8 of it:
the zoom-out protocol's 1/8 view, at the output size) or a nerfstudio camera-path JSON file. The
training cameras and test views come from the dataset the run recorded
(:func:`patexgs_jax.sources.data_record`) or ``--data``; without either, ``orbit``, ``spiral`` and
``zoom-out`` go about the Gaussians themselves.

Writes ``DIR/frame_00000.png``, ... and ``DIR/video.mp4`` (PyAV's libx264, yuv420p; a frame of odd
width or height has its last column or row repeated in the video only). With ``--compare`` every
frame holds the models side by side, each under a band with its name. ``--mode`` picks the viewer's
views (:mod:`patexgs_jax.viewer.frames`): the render, colour-mapped depth, normals, accumulated
opacity, the dominant splat's mip level or its texture side. Each model renders with its own
method's configuration. Exit status: 0 done, 2 bad arguments or input (one ``error:`` line).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np

from . import camera_paths as cp
from . import progress
from .camera import Camera
from .sources import DataRecord, Source, SourceError, load_source

__all__ = ["MODES", "compose", "label_band", "main", "make_path", "render_frames", "write_video"]

#: ``--mode`` -> the viewer's view (:data:`patexgs_jax.viewer.frames.VIEWS`).
MODES = {"rgb": "rgb", "depth": "depth", "normal": "normal", "alpha": "alpha", "mip": "mip level",
         "side": "texture side"}
#: Height in px of a ``--compare`` label band, and the gap between panels.
BAND, GAP = 14, 2
#: Frames of a generated path without ``--frames``, and the frame rate without ``--fps``.
DEFAULT_FRAMES, DEFAULT_FPS = 60, 30.0


class RenderError(ValueError):
    """Bad arguments for the command line; the message says what to pass."""


def _resized(camera: Camera, width: int | None) -> Camera:
    """``camera`` with its intrinsics scaled to ``width`` px wide (the height keeps its aspect)."""
    if width is None or width == camera.width:
        return camera
    s = width / camera.width
    h = max(1, int(round(camera.height * s)))
    K = np.asarray(camera.K, np.float64) * np.array([[s, 1.0, s], [1.0, s, s], [1.0, 1.0, 1.0]])
    return Camera.from_intrinsics(K, np.asarray(camera.world_to_camera), width, h)


def make_path(kind: str, source: Source, dataset=None, *, frames: int | None = None,
              width: int | None = None) -> tuple[list[Camera], float | None]:
    """The cameras of path ``kind`` (one of :data:`camera_paths.PATHS` or a JSON file's path) for
    ``source``, with ``dataset`` (its training and test cameras; may be None) and the path's own
    frame rate (a JSON file's; else None)."""
    if kind not in cp.PATHS:
        cams, fps = cp.read_path(kind)
        if width is not None:
            cams = [cp.camera_like(c, width) for c in cams]
        return (cams if frames is None else cams[:frames]), fps
    train = [v.camera for v in dataset.train_views] if dataset is not None else []
    if kind == "test":
        if dataset is None:
            raise RenderError("--path test renders the dataset's test cameras: the run records no dataset, pass "
                              "--data DIR (the scene it was trained on).")
        tests = [v.camera for v in dataset.test_views]
        if not tests:
            raise RenderError("the dataset has no test views (every 8th image is held out): use another --path.")
        cams = [_resized(c, width) for c in tests[:frames]]
        if len({(c.width, c.height) for c in cams}) > 1:
            raise RenderError("the test views have several sizes and a video has one: pass --width W.")
        return cams, None
    n = DEFAULT_FRAMES if frames is None else frames
    place = cp.scene_frame(train, source.scene)
    if dataset is not None and (dataset.test_views or dataset.train_views):
        ref = (dataset.test_views or dataset.train_views)[0].camera
    else:  # no cameras: a 50-degree camera beside the scene, looking at it (640 x 480 unless --width)
        from .camera import look_at

        eye = place.centre + place.radius * cp._basis(place, None)[0]
        f = 240.0 / np.tan(np.radians(25.0))
        ref = Camera.from_intrinsics((f, f, 320.0, 240.0), look_at(eye, place.centre, up=place.up), 640, 480)
    if kind == "orbit":
        return cp.orbit(place, ref, n, width), None
    if kind == "spiral":
        return cp.spiral(place, ref, n, width), None
    return cp.zoom_out(ref, n, width), None


def label_band(text: str, width: int) -> np.ndarray:
    """(BAND, width, 3) uint8: ``text`` in white on dark grey (Pillow's default font)."""
    from PIL import Image, ImageDraw, ImageFont

    im = Image.new("RGB", (width, BAND), (40, 40, 40))
    try:
        font = ImageFont.load_default(size=11)
    except (TypeError, OSError, ImportError):  # (Pillow < 10.1, or built without FreeType)
        font = ImageFont.load_default()
    ImageDraw.Draw(im).text((3, 1), text, fill=(255, 255, 255), font=font)
    return np.asarray(im)


def compose(images: Sequence[np.ndarray], names: Sequence[str] | None) -> np.ndarray:
    """One frame: ``images`` (uint8 (H, W, 3), one size) side by side, ``GAP`` white px apart, each
    under a band with its name (no bands when ``names`` is None)."""
    panels = []
    for i, img in enumerate(images):
        if names is not None:
            img = np.concatenate([label_band(names[i], img.shape[1]), img], axis=0)
        if i:
            panels.append(np.full((img.shape[0], GAP, 3), 255, np.uint8))
        panels.append(img)
    return np.concatenate(panels, axis=1)


def render_frames(sources: Sequence[Source], cameras: Sequence[Camera], *, mode: str = "rgb", enlarge: int = 1,
                  labels: bool | None = None, on_frame=None) -> list[np.ndarray]:
    """The frames (uint8 (H, W, 3)) of ``cameras``, each model in ``sources`` side by side (under
    name bands when ``labels``; default: when there are several), enlarged ``enlarge`` times by
    nearest neighbour; ``on_frame(i, frame)`` is called as each is done."""
    from .viewer.frames import FrameRenderer

    if mode not in MODES:
        raise RenderError(f"--mode {mode!r}: choose one of {', '.join(MODES)}.")
    labels = len(sources) > 1 if labels is None else labels
    renderers = [FrameRenderer(s.scene, s.render_config, headroom=1.5) for s in sources]
    names = [s.name for s in sources] if labels else None
    out = []
    try:
        for i, cam in enumerate(cameras):
            imgs = [r.render(cam, mode=None, view=MODES[mode]).image for r in renderers]
            if enlarge > 1:
                imgs = [np.repeat(np.repeat(x, enlarge, axis=0), enlarge, axis=1) for x in imgs]
            frame = compose(imgs, names)
            out.append(frame)
            if on_frame is not None:
                on_frame(i, frame)
    finally:
        for r in renderers:
            r.release()
    return out


def write_video(path, frames: Sequence[np.ndarray], fps: float, crf: int = 20) -> Path:
    """Writes ``frames`` (uint8 (H, W, 3), one size) as an H.264 MP4 (yuv420p) at ``fps``."""
    try:
        import av
    except ImportError:
        raise RenderError("writing the MP4 needs PyAV: pip install av (or pass --no-video for the PNG frames "
                          "only).") from None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    he, we = h + h % 2, w + w % 2  # yuv420p: even sides
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = we, he, "yuv420p"
        stream.options = {"crf": str(crf)}
        for img in frames:
            if (he, we) != (h, w):
                img = np.pad(img, ((0, he - h), (0, we - w), (0, 0)), mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def _dataset(record: DataRecord | None):
    if record is None:
        return None
    from .data import DatasetError

    try:
        return record.load()
    except (DatasetError, OSError) as e:
        raise RenderError(f"cannot load the dataset {record.path} ({e}): pass --data DIR.") from None


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.render", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", help="a run folder, a checkpoint (.ckpt) or a PLY (.ply)")
    ap.add_argument("--out", required=True, help="folder for frame_00000.png, ... and video.mp4")
    ap.add_argument("--path", default="orbit", help=f"{', '.join(cp.PATHS)} or a nerfstudio camera-path JSON file "
                    "(default orbit)")
    ap.add_argument("--frames", type=int, default=None, help=f"frames (default {DEFAULT_FRAMES}; test: every test "
                    "view; a file: all its cameras)")
    ap.add_argument("--fps", type=float, default=None, help=f"frame rate (default a file's, else {DEFAULT_FPS:g})")
    ap.add_argument("--width", type=int, default=None, help="frame width in px (the height keeps the aspect; default "
                    "the reference camera's, or the file's)")
    ap.add_argument("--enlarge", type=int, default=1, help="enlarge frames K times by nearest neighbour (pixels stay "
                    "visible)")
    ap.add_argument("--compare", nargs="+", default=[], metavar="SOURCE2", help="more models, side by side")
    ap.add_argument("--mode", default="rgb", choices=list(MODES), help="what a frame shows (default rgb)")
    ap.add_argument("--data", default=None, help="the scene the run trained on (default: the one it recorded)")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling of --data (as training)")
    ap.add_argument("--save-path", default=None, metavar="FILE.json", help="write the rendered path there "
                    "(nerfstudio's camera-path JSON)")
    ap.add_argument("--video", default=None, metavar="FILE", help="the MP4's path (default DIR/video.mp4)")
    ap.add_argument("--no-video", action="store_true", help="the PNG frames only")
    return ap


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from . import memory_maps
    from .export import PlyFormatError

    try:
        if args.frames is not None and args.frames < 1:
            raise RenderError(f"--frames {args.frames}: pass 1 or more.")
        if args.width is not None and args.width < 2:
            raise RenderError(f"--width {args.width}: pass 2 px or more.")
        if args.enlarge < 1 or (args.fps is not None and not args.fps > 0):
            raise RenderError("--enlarge must be 1 or more and --fps positive.")
        memory_maps.enable_compile_cache()
        sources = [load_source(p) for p in [args.source, *args.compare]]
        if len({s.name for s in sources}) < len(sources):  # the same folder name twice: the paths tell them apart
            for s, p in zip(sources, [args.source, *args.compare], strict=True):
                s.name = str(p)
        record = (DataRecord(Path(args.data), args.factor) if args.data is not None else sources[0].data)
        needs_data = args.path in cp.PATHS
        dataset = _dataset(record) if needs_data else None
        cameras, file_fps = make_path(args.path, sources[0], dataset, frames=args.frames, width=args.width)
        fps = args.fps or file_fps or DEFAULT_FPS
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("frame_*.png"):  # (a shorter path must not leave an earlier one's frames)
            old.unlink()
        if args.save_path:
            cp.write_path(args.save_path, cameras, fps)
        from PIL import Image

        with progress.bar(len(cameras), "render", unit="frame") as bar:
            def save(i, frame):
                Image.fromarray(frame).save(out / f"frame_{i:05d}.png")
                bar.update(1)

            frames = render_frames(sources, cameras, mode=args.mode, enlarge=args.enlarge, on_frame=save)
        video = None
        if not args.no_video:
            video = write_video(args.video or out / "video.mp4", frames, fps)
    except (SourceError, cp.PathError, RenderError, PlyFormatError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    h, w = frames[0].shape[:2]
    progress.say(f"{len(frames)} frames of {w} x {h} px in {out}" + (f", video {video}" if video else "")
                 + (f", path {args.save_path}" if args.save_path else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
