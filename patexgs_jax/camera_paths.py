"""Camera paths for rendering videos: orbits and spirals around a scene, the zoom-out, and
nerfstudio's camera-path JSON (read and written), so that paths move between the two programs.

Generated cameras have square pixels and the principal point at the image centre (the cameras
nerfstudio's JSON can hold): ``fx = fy = (H / 2) / tan(fov / 2)``, ``(cx, cy) = (W / 2, H / 2)``,
with the vertical field of view ``fov`` of the reference camera (a training or test camera).

The scene's frame (:func:`scene_frame`) comes from the training cameras: its centre is the point
closest to every camera's optical axis (least squares; where the axes are near parallel, a
forward-facing capture, the median of the Gaussians' centres instead), its up direction the mean of
the cameras' up (-y) axes, its radius the median distance of the cameras from the centre across
up and its height their median offset along up. Without training cameras the Gaussians set it:
the median centre, world -y up (the OpenCV convention), and 2.5 times the distance within which 90%
of them lie.

nerfstudio's camera-path JSON (what ``ns-render camera-path`` reads)
  ``{"camera_type": "perspective", "render_width": W, "render_height": H, "fps": F, "seconds": S,
  "camera_path": [{"camera_to_world": [16 floats], "fov": degrees, "aspect": W / H}, ...]}``:
  ``camera_to_world`` a 4x4 row-major matrix in OpenGL-style camera axes (x right, y up, z back),
  ``fov`` the vertical field of view. The matrices are in this scene's world coordinates: a path
  exported from nerfstudio's viewer is in its dataparser's normalised coordinates
  (``dataparser_transforms.json``), which are not applied here.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .camera import Camera, look_at

__all__ = ["GL_FROM_CV", "PATHS", "PathError", "ScenePlace", "camera_from_entry", "camera_like", "entry_of",
           "orbit", "read_path", "scene_frame", "spiral", "write_path", "zoom_out"]

#: The generated paths (``--path``), besides a JSON file.
PATHS = ("orbit", "spiral", "zoom-out", "test")

#: Flips camera y and z: OpenCV camera axes (x right, y down, z forward) <-> OpenGL's (y up, z back).
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])

#: How far :func:`zoom_out` goes: the focal length falls to 1 / 8 of the start's, where what filled the
#: view's width covers 1 / 8 of it (the zoom-out protocol's 1/8).
ZOOM_OUT = 8.0


class PathError(ValueError):
    """A camera path that cannot be made or read; the message says what to fix."""


def camera_like(camera: Camera, width: int | None = None) -> Camera:
    """A camera at ``camera``'s pose and vertical field of view, with square pixels and a centred
    principal point, ``width`` wide (default its own width; the height keeps its aspect)."""
    fy = float(np.asarray(camera.K)[1, 1])
    fov = 2.0 * math.atan(0.5 * camera.height / fy)
    w = int(width or camera.width)
    h = max(1, int(round(camera.height * w / camera.width)))
    return _camera(np.asarray(camera.world_to_camera, np.float64), fov, w, h)


def _camera(w2c, fov: float, width: int, height: int) -> Camera:
    f = 0.5 * height / math.tan(0.5 * fov)
    return Camera.from_intrinsics((f, f, 0.5 * width, 0.5 * height), w2c, width, height)


# ------------------------------------------------------------------------------------------------
# The scene's frame and the generated paths
# ------------------------------------------------------------------------------------------------
class ScenePlace:
    """Where a scene lies: ``centre`` (3,), unit ``up`` (3,), ``radius`` and ``height`` of the
    cameras' circle about the centre (see the module docstring)."""

    def __init__(self, centre, up, radius: float, height: float):
        self.centre = np.asarray(centre, np.float64)
        self.up = np.asarray(up, np.float64) / np.linalg.norm(up)
        self.radius, self.height = float(radius), float(height)


def _gaussian_centres(scene) -> np.ndarray:
    means = np.asarray(scene.means, np.float64)
    active = np.asarray(scene.active) > 0
    return means[active] if active.any() else means


def scene_frame(cameras: Sequence[Camera], scene) -> ScenePlace:
    """The :class:`ScenePlace` of a scene from its training ``cameras`` (may be empty) and its
    Gaussians (see the module docstring)."""
    pts = _gaussian_centres(scene)
    if len(cameras) == 0:
        centre = np.median(pts, axis=0)
        r = float(np.percentile(np.linalg.norm(pts - centre, axis=1), 90)) if len(pts) else 1.0
        return ScenePlace(centre, (0.0, -1.0, 0.0), 2.5 * max(r, 1e-6), 0.0)
    c2w = np.stack([c.camera_to_world for c in cameras])
    origins, axes = c2w[:, :3, 3], c2w[:, :3, 2]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(origins, axes, strict=True):
        P = np.eye(3) - np.outer(d, d)  # the distance of a point from this optical axis, squared: |P (x - o)|^2
        A += P
        b += P @ o
    eig = np.linalg.eigvalsh(A)
    centre = np.linalg.solve(A, b) if eig[0] > 1e-3 * eig[-1] else np.median(pts, axis=0)
    up = -c2w[:, :3, 1].mean(axis=0)
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, -1.0, 0.0])
    up = up / np.linalg.norm(up)
    off = origins - centre
    along = off @ up
    across = np.linalg.norm(off - along[:, None] * up, axis=1)
    return ScenePlace(centre, up, max(float(np.median(across)), 1e-6), float(np.median(along)))


def _basis(place: ScenePlace, start: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across ``up``; the first towards ``start`` (a camera centre) if given."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(place.up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    if start is not None:
        d = start - place.centre
        d = d - (d @ place.up) * place.up
        if np.linalg.norm(d) > 1e-9:
            ref = d
    e1 = ref - (ref @ place.up) * place.up
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(place.up, e1)


def _circle(place: ScenePlace, reference: Camera, frames: int, turns: float, radius_wave: float,
            height_wave: float, width: int | None) -> list[Camera]:
    if frames < 1:
        raise PathError(f"--frames {frames}: a path needs at least 1 frame.")
    like = camera_like(reference, width)
    fov = 2.0 * math.atan(0.5 * like.height / float(np.asarray(like.K)[1, 1]))
    e1, e2 = _basis(place, reference.center)
    out = []
    for i in range(frames):
        t = i / frames  # (the last frame stops one step short of the first: the video loops)
        a = 2.0 * math.pi * turns * t
        r = place.radius * (1.0 + radius_wave * math.sin(2.0 * math.pi * t))
        h = place.height + height_wave * place.radius * math.sin(2.0 * math.pi * t)
        eye = place.centre + r * (math.cos(a) * e1 + math.sin(a) * e2) + h * place.up
        out.append(_camera(look_at(eye, place.centre, up=place.up), fov, like.width, like.height))
    return out


def orbit(place: ScenePlace, reference: Camera, frames: int, width: int | None = None) -> list[Camera]:
    """``frames`` cameras on one turn about the scene at its cameras' radius and height, looking at
    its centre, starting beside ``reference`` (its field of view; ``width``: see :func:`camera_like`)."""
    return _circle(place, reference, frames, 1.0, 0.0, 0.0, width)


def spiral(place: ScenePlace, reference: Camera, frames: int, width: int | None = None) -> list[Camera]:
    """Two turns about the scene, the radius swelling and shrinking by 20% and the height rising and
    falling by a quarter of the radius once over the path (otherwise as :func:`orbit`)."""
    return _circle(place, reference, frames, 2.0, 0.2, 0.25, width)


def zoom_out(start: Camera, frames: int, width: int | None = None, factor: float = ZOOM_OUT) -> list[Camera]:
    """``frames`` cameras at ``start``'s pose whose focal length falls from its own to 1 / ``factor``
    of it at a geometric pace (the scene shrinks at an even rate), at the output size: at the end,
    what filled the view's width covers 1 / ``factor`` of it, the view the zoom-out protocol renders
    at 1 / ``factor`` (its image, ``factor`` times smaller, is the last frame's centre).

    A zoom of the lens rather than a dolly: a camera pulled back out of a captured scene meets the
    background's Gaussians (a sky, far walls), which then hide it.
    """
    if frames < 1:
        raise PathError(f"--frames {frames}: a path needs at least 1 frame.")
    like = camera_like(start, width)
    w2c = np.asarray(like.world_to_camera, np.float64)
    fov = 2.0 * math.atan(0.5 * like.height / float(np.asarray(like.K)[1, 1]))
    out = []
    for i in range(frames):
        t = i / max(frames - 1, 1)
        out.append(_camera(w2c, 2.0 * math.atan(math.tan(0.5 * fov) * factor ** t), like.width, like.height))
    return out


# ------------------------------------------------------------------------------------------------
# nerfstudio's camera-path JSON
# ------------------------------------------------------------------------------------------------
def entry_of(camera: Camera) -> dict:
    """The ``camera_path`` entry of a camera (its vertical fov; see the module docstring)."""
    c2w = camera.camera_to_world @ GL_FROM_CV
    fy = float(np.asarray(camera.K)[1, 1])
    return {"camera_to_world": [float(x) for x in c2w.reshape(-1)],
            "fov": math.degrees(2.0 * math.atan(0.5 * camera.height / fy)), "aspect": camera.width / camera.height}


def camera_from_entry(entry: dict, width: int, height: int) -> Camera:
    """The camera of a ``camera_path`` entry at the path's ``render_width`` x ``render_height``."""
    c2w = np.asarray(entry["camera_to_world"], np.float64)
    if c2w.size == 12:
        c2w = np.concatenate([c2w.reshape(-1), [0.0, 0.0, 0.0, 1.0]])
    c2w = c2w.reshape(4, 4) @ GL_FROM_CV
    fov = float(entry["fov"])
    if not 0.0 < fov < 180.0:
        raise ValueError(f"fov {fov} is not a vertical field of view in degrees (0 to 180)")
    return _camera(np.linalg.inv(c2w), math.radians(fov), width, height)


def write_path(path, cameras: Sequence[Camera], fps: float) -> Path:
    """Writes ``cameras`` (one size) as a nerfstudio camera-path JSON file; returns its path."""
    if not cameras:
        raise PathError("no camera to write: the path is empty.")
    w, h = cameras[0].width, cameras[0].height
    doc = {"camera_type": "perspective", "render_width": w, "render_height": h, "fps": float(fps),
           "seconds": len(cameras) / float(fps), "camera_path": [entry_of(c) for c in cameras]}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def read_path(path) -> tuple[list[Camera], float | None]:
    """The cameras of a nerfstudio camera-path JSON file and its frame rate (``fps``, else the
    frames over ``seconds``; None when neither is there). Raises :class:`PathError` naming what is
    wrong with the file."""
    path = Path(path)
    fix = ("expected nerfstudio's camera-path JSON: render_width, render_height and camera_path, a list of "
           "{camera_to_world: 16 numbers, fov: degrees} (docs/rendering.md)")
    try:
        doc = json.loads(path.read_text())
    except OSError as e:
        raise PathError(f"cannot read the camera path {path} ({e.strerror or e}): pass an existing JSON file or "
                        f"one of {', '.join(PATHS)}.") from None
    except ValueError as e:
        raise PathError(f"camera path {path} is not JSON ({e}); {fix}.") from None
    if not isinstance(doc, dict):
        raise PathError(f"camera path {path} holds a {type(doc).__name__}, not an object; {fix}.")
    missing = [k for k in ("render_width", "render_height", "camera_path") if k not in doc]
    if missing:
        raise PathError(f"camera path {path} lacks {', '.join(missing)}; {fix}.")
    kind = str(doc.get("camera_type", "perspective")).lower()
    if kind != "perspective":
        raise PathError(f"camera path {path} has camera_type {kind!r}: only perspective cameras are rendered here.")
    try:
        w, h = int(doc["render_width"]), int(doc["render_height"])
        if w <= 0 or h <= 0:
            raise ValueError(f"render size {w} x {h} is not positive")
        entries = doc["camera_path"]
        if not isinstance(entries, list) or not entries:
            raise ValueError("camera_path is not a non-empty list")
        cams = []
        for i, e in enumerate(entries):
            try:
                cams.append(camera_from_entry(e, w, h))
            except (KeyError, TypeError, ValueError) as err:
                raise ValueError(f"camera_path[{i}]: {type(err).__name__} {err}") from None
    except (KeyError, TypeError, ValueError) as e:
        raise PathError(f"camera path {path}: {e}; {fix}.") from None
    fps = doc.get("fps")
    if fps is None and doc.get("seconds"):
        fps = len(cams) / float(doc["seconds"])
    return cams, None if fps is None else float(fps)
