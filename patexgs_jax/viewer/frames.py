"""What the interactive viewer shows, without the web server: trained runs found on disk, the
camera of a browser's view, and frames of each view mode (:mod:`patexgs_jax.viewer.server` serves them).

Cameras
  A browser's camera (viser's) is a camera-to-world rotation ``wxyz`` and position in OpenCV axes
  (x right, y down, z forward), a vertical field of view ``fov`` in radians, and the canvas size in
  pixels. Its :class:`Camera` has square pixels, ``fy = (H / 2) / tan(fov / 2)``, and the principal
  point at the canvas centre (W / 2, H / 2) in the package's continuous pixel coordinates.

Frames
  A frame is rendered at the canvas size divided by the render scale s (1, 2, 4, 8: the zoom-out
  protocol's ``Camera.scaled``) and enlarged s times by nearest neighbour, so aliasing stays
  visible. Views are rendered at the padded sizes of :class:`patexgs_jax.padding.ViewRenderer`, with
  a tile capacity fitted with headroom when a padded size is first met: a moving camera reuses the
  compiled programs of its canvas size.

View modes (per pixel)
  * ``rgb``: the render;
  * ``depth``: the expected ray-splat depth, colour-mapped between its 2nd and 98th percentiles
    (black: nothing hit);
  * ``normal``: the unit camera-frame normal drawn as (x, -y, -z) / 2 + 1/2 (surfaces facing the
    camera are blue; OpenGL's axes);
  * ``alpha``: accumulated opacity, white = opaque;
  * ``mip level``: the Eq. 11 level of the pixel's dominant splat (the largest blending weight,
    ``RenderOutput.dominant``) in its RGB texture (its alpha texture when it has no RGB one),
    computed with the renderer's formula (:func:`dominant_mip_level`); black: no splat or no texture;
  * ``texture side``: that splat's texture side n, colour-mapped by log2 n from 1 to 32.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import textures as tex
from ..camera import ZOOM_SCALES, Camera
from ..padding import ViewRenderer, crop, release_scene_programs
from ..render import RenderConfig
from ..rendering.kernel import UV_LIMIT
from ..rendering.kernel import uv as ray_plane_uv
from ..rendering.projection import image_map, ray_planes
from ..sources import SourceError, is_run, load_source
from ..sources import render_config_of as render_config_of  # (the viewer's name for it)

#: Render scales (zoom-out factors) the viewer offers.
SCALES = ZOOM_SCALES
#: View modes, in the order the viewer lists them.
VIEWS = ("rgb", "depth", "normal", "alpha", "mip level", "texture side")
#: Coverage modes: key -> label.
MODES = {"patexgs": "PATexGS (prefilter)", "literal": "literal Eqs. 11-13 (2DGS low-pass)",
         "mip-off": "mip off (prefilter, level 0 only)"}
#: The compositor schedule of the viewer's frames (:class:`RenderConfig` fields that change the work's
#: order, not the image: within 1e-6). A trained model's view lists far more splats per tile than a
#: training batch's random views, so a frame is almost all compositing, which smaller chunks over
#: more tiles at once (the same 64k-pair block as the default 8 x 32) run faster
#: (docs/performance.md has the A/B). A CPU's: on a GPU the device's own (:mod:`patexgs_jax.rendering.tiling`)
#: advances every tile at once.
FRAME_SCHEDULE = dict(tile_batch=16, chunk=16)


def frame_schedule(backend: str | None = None) -> dict:
    """The :class:`RenderConfig` fields of the viewer's frames on ``backend`` (default: JAX's):
    :data:`FRAME_SCHEDULE` on a CPU, the renderer's device-chosen schedule elsewhere."""
    return dict(FRAME_SCHEDULE) if (backend or jax.default_backend()) == "cpu" else {}
#: Colours of mip levels 0, 1, 2, ... (the last one repeats for higher levels).
LEVEL_COLOURS = np.array([[0.15, 0.35, 0.95], [0.1, 0.8, 0.9], [0.2, 0.85, 0.25], [0.95, 0.9, 0.15],
                          [0.98, 0.55, 0.1], [0.9, 0.15, 0.15]], np.float32)
# A dark-to-light ramp (dark blue, purple, orange, light yellow) for depth and texture sides.
_RAMP = np.array([[0.05, 0.03, 0.25], [0.35, 0.1, 0.55], [0.8, 0.25, 0.4], [0.98, 0.6, 0.2],
                  [0.99, 0.97, 0.65]], np.float32)


class ViewerError(ValueError):
    """A problem with what the viewer was asked to show; the message says how to fix it."""


# ------------------------------------------------------------------------------------------------
# Runs
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class RunEntry:
    """One trained model the viewer can show: ``name`` (what the browser lists, e.g.
    ``synthetic-v1-seed0/patexgs``) and ``path`` (a run folder or a checkpoint file)."""

    name: str
    path: Path


def find_runs(path) -> list[RunEntry]:
    """The runs under ``path``: a run folder (``checkpoints/`` or ``scene.ply``, what
    ``python -m patexgs_jax.train --out`` writes), a study's output folder (its
    ``runs/<scene>/<label>/``, or any folder holding run folders up to three levels down) or a
    ``.ckpt`` file. Raises :class:`ViewerError` when there is none."""
    path = Path(path)
    what = ("a run folder (checkpoints/ or scene.ply, as python -m patexgs_jax.train --out writes), a "
            "study's output folder (python -m experiments.mipnerf360 --out) or a .ckpt file")
    if not path.exists():
        raise ViewerError(f"{path} does not exist: pass {what}.")
    if path.is_file():
        if path.suffix != ".ckpt":
            raise ViewerError(f"{path} is not a checkpoint (.ckpt): pass {what}.")
        return [RunEntry(path.name, path)]
    if is_run(path):
        return [RunEntry(path.resolve().name, path)]
    found = []
    for depth in (1, 2, 3):
        for d in sorted(path.glob("/".join(["*"] * depth))):
            if d.is_dir() and not d.name.startswith(".") and d.name != "checkpoints" and is_run(d):
                if not any(p in d.parents for p in (e.path for e in found)):
                    found.append(RunEntry(str(d.relative_to(path)), d))
    # A study keeps its runs under runs/: list them by <scene>/<label>.
    found = [RunEntry(e.name[len("runs/"):] if e.name.startswith("runs/") else e.name, e.path) for e in found]
    if not found:
        raise ViewerError(f"no trained run in {path}: pass {what}.")
    return found


@dataclasses.dataclass
class LoadedRun:
    """A run's scene and its method's render configuration."""

    name: str
    scene: object
    config: RenderConfig
    method: str


def load_run(entry: RunEntry) -> LoadedRun:
    """Loads a run: its newest checkpoint's scene (or ``scene.ply`` without checkpoints) with its
    method's render configuration (:func:`patexgs_jax.sources.load_source`). Raises
    :class:`ViewerError` when it cannot be read."""
    try:
        src = load_source(entry.path, name=entry.name)
    except SourceError as e:
        raise ViewerError(str(e)) from None
    return LoadedRun(entry.name, src.scene, src.render_config, src.method)


def mode_config(base: RenderConfig, mode: str) -> RenderConfig:
    """The render configuration of coverage mode ``mode`` (a key of :data:`MODES`) for a run
    rendered with ``base``: the run's mip flags and background, with the mode's coverage, lambda_mip
    and mip setting (``patexgs``: prefilter, lambda 1/6; ``literal``: the 2DGS low-pass, lambda 0.4;
    ``mip-off``: prefilter, level 0 only). The run's own lambda_mip is kept under its own coverage.
    Billboards (the ``bbsplat`` runs) have one coverage, their square: the modes switch their mip
    levels only (``mip-off``: level 0)."""
    if mode not in MODES:
        raise ViewerError(f"unknown coverage mode {mode!r}; choose one of {', '.join(MODES)}.")
    mip = base.mip if base.mip != "none" else "nearest"
    kw: dict[str, Any] = dict(rgb_mip=base.rgb_mip, alpha_mip=base.alpha_mip, background=base.background)
    if base.coverage == "billboard":
        return RenderConfig(coverage="billboard", mip="none" if mode == "mip-off" else mip, lambda_mip=base.lambda_mip,
                            **kw)
    if mode == "patexgs":
        lam = base.lambda_mip if base.coverage == "prefilter" else None
        return RenderConfig(coverage="prefilter", mip=mip, lambda_mip=lam, **kw)
    if mode == "literal":
        lam = base.lambda_mip if base.coverage == "lowpass" else 0.4
        return RenderConfig(coverage="lowpass", mip=mip, lambda_mip=lam, **kw)
    return RenderConfig(coverage="prefilter", mip="none", **kw)


def own_mode(base: RenderConfig) -> str:
    """The coverage mode a run's own configuration corresponds to."""
    if base.coverage == "lowpass":
        return "literal"
    return "mip-off" if base.mip == "none" else "patexgs"


# ------------------------------------------------------------------------------------------------
# Cameras
# ------------------------------------------------------------------------------------------------
def quat_to_matrix(wxyz) -> np.ndarray:
    """(3, 3) float64 rotation of a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R) -> np.ndarray:
    """(4,) float64 (w, x, y, z) unit quaternion, w >= 0, of a (3, 3) rotation."""
    R = np.asarray(R, np.float64)
    t = np.trace(R)
    # Largest of 4 w^2, 4 x^2, 4 y^2, 4 z^2 first: the division by it is well conditioned.
    if t > max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def camera_from_viewer(wxyz, position, fov: float, width: int, height: int) -> Camera:
    """The :class:`Camera` of a browser's view (see the module docstring).

    Args:
      wxyz: (4,) camera-to-world rotation, OpenCV axes.
      position: (3,) camera centre in world coordinates.
      fov: vertical field of view in radians, in (0, pi).
      width, height: canvas size in pixels.
    """
    if not 0.0 < fov < math.pi:
        raise ViewerError(f"field of view must be in (0, pi) radians, got {fov}.")
    R = quat_to_matrix(wxyz)
    t = np.asarray(position, np.float64)
    w2c = np.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ t
    f = 0.5 * height / math.tan(0.5 * fov)
    K = np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])
    return Camera.from_intrinsics(K, w2c, width, height)


def viewer_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz (4,), position (3,), vertical fov in radians) of a camera, as a browser's view takes
    them; the inverse of :func:`camera_from_viewer` for square pixels and a centred principal point."""
    c2w = camera.camera_to_world
    fy = float(np.asarray(camera.K)[1, 1])
    return matrix_to_quat(c2w[:3, :3]), c2w[:3, 3].copy(), 2.0 * math.atan(0.5 * camera.height / fy)


def fit_canvas(width: int, height: int, max_side: int) -> tuple[int, int]:
    """The canvas size, shrunk (aspect kept) so that its longer side is at most ``max_side``."""
    width, height = max(int(width), 1), max(int(height), 1)
    longest = max(width, height)
    if longest <= max_side:
        return width, height
    f = max_side / longest
    return max(int(round(width * f)), 1), max(int(round(height * f)), 1)


# ------------------------------------------------------------------------------------------------
# Per-pixel mip level of the dominant splat
# ------------------------------------------------------------------------------------------------
def _dominant_mip_level(scene, camera: Camera, dominant, *, bank: str, lambda_mip: float, use_mip: bool):
    M = image_map(scene, camera)[0]
    A, B, Cc = ray_planes(M[:, 0], M[:, 1], M[:, 2])  # the renderer's ray-plane map of every splat
    b = scene.rgb if bank == "rgb" else scene.alpha
    g = jnp.maximum(dominant, 0)
    a, bb, c = A[g], B[g], Cc[g]  # (H, W, 3)
    H, W = dominant.shape
    y, x = jnp.meshgrid(jnp.arange(H, dtype=a.dtype) + 0.5, jnp.arange(W, dtype=a.dtype) + 0.5, indexing="ij")
    s = x[..., None] * a + y[..., None] * bb + c

    def uv(t):  # the renderer's intersection; a ray that misses the plane gives the coarsest level
        return ray_plane_uv(t[..., 0], t[..., 1], t[..., 2])[:3]

    u0, v0, ok0 = uv(s)
    ux, vx, okx = uv(s + a)
    uy, vy, oky = uv(s + bb)
    d = jnp.sqrt(jnp.maximum((ux - u0) ** 2 + (vx - v0) ** 2, (uy - u0) ** 2 + (vy - v0) ** 2))
    d = jnp.where(ok0 & okx & oky, d, UV_LIMIT)
    n = b.size[g]
    top = jnp.maximum(b.bucket[g], 0.0).astype(jnp.int32)  # ceil(log2 n), the coarsest level
    level = tex.mip_level(d, n, top, lambda_mip, trilinear=False) if use_mip else jnp.zeros_like(top)
    return jnp.where((dominant >= 0) & (n > 0), level, -1)


#: ``dominant_mip_level(scene, camera, dominant, *, bank, lambda_mip, use_mip)`` -> (H, W) int32:
#: the Eq. 11 level (``floor(log2(lambda_mip n D))`` clipped to [0, ceil(log2 n)], D the larger
#: splat-plane distance from a pixel's ray-splat intersection to its +x and +y neighbours') of
#: each pixel's dominant splat (``dominant`` (H, W) int32 from a render of ``camera``) in texture
#: bank ``bank`` ("rgb" or "alpha"); 0 everywhere without mipmaps (``use_mip`` False), -1 where
#: there is no splat or it has no texture in that bank.
dominant_mip_level = jax.jit(_dominant_mip_level, static_argnames=("bank", "lambda_mip", "use_mip"))


# ------------------------------------------------------------------------------------------------
# Colours
# ------------------------------------------------------------------------------------------------
def colour_ramp(t: np.ndarray) -> np.ndarray:
    """(..., 3) float32 colours of values t in [0, 1] on the viewer's dark-to-light ramp."""
    t = np.clip(np.asarray(t, np.float32), 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(t.astype(np.int32), len(_RAMP) - 2)
    f = (t - i)[..., None]
    return _RAMP[i] * (1.0 - f) + _RAMP[i + 1] * f


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclasses.dataclass
class Frame:
    """One rendered frame: ``image`` (H, W, 3) uint8 (enlarged to the canvas when asked),
    ``rendered`` (width, height) of the render, ``ms`` the time from the camera to the image
    (render, the view's per-pixel quantities, colouring), ``grew`` whether a tile capacity had to
    grow (a new program), ``compiled`` whether any program was compiled for it (then ``ms``
    includes the compile)."""

    image: np.ndarray
    rendered: tuple[int, int]
    ms: float
    grew: bool
    compiled: bool = False


class FrameRenderer:
    """Frames of one scene in every coverage mode and view (one :class:`ViewRenderer` per mode).

    Args:
      scene: the trained :class:`patexgs_jax.Scene`.
      base: the run's own :class:`RenderConfig` (its mip flags and background).
      headroom: tile capacity headroom of a padded size (see :class:`ViewRenderer`).
    """

    def __init__(self, scene, base: RenderConfig, *, headroom: float = 2.0):
        self.scene, self.base, self.headroom = scene, base, headroom
        self._renderers: dict[str | None, ViewRenderer] = {}

    def renderer(self, mode: str | None) -> ViewRenderer:
        """The renderer of coverage mode ``mode`` (a key of :data:`MODES`; None: the run's own
        configuration, ``base``)."""
        r = self._renderers.get(mode)
        if r is None:
            config = dataclasses.replace(self.base if mode is None else mode_config(self.base, mode),
                                         **frame_schedule())
            scene = self.scene
            if (scene.filter3d is not None and config.coverage != "prefilter"
                    and (scene.rgb is not None or scene.alpha is not None)):
                scene = scene.replace(filter3d=None)  # (textured splats take the 3D filter in the prefilter only)
            r = self._renderers[mode] = ViewRenderer(scene, config, headroom=self.headroom, reuse_textures=True)
        return r

    def render(self, camera: Camera, *, mode: str | None = "patexgs", view: str = "rgb", scale: int = 1,
               enlarge: bool = True) -> Frame:
        """The frame of ``camera`` (the canvas) in coverage mode ``mode`` (None: the run's own
        configuration) at render scale ``scale`` in view ``view``; with
        ``enlarge``, enlarged back to the canvas size by nearest neighbour (the last partial
        block of pixels repeats the edge), else at the render's size."""
        if view not in VIEWS:
            raise ViewerError(f"unknown view {view!r}; choose one of {', '.join(VIEWS)}.")
        scale = int(scale)
        t0 = time.perf_counter()
        programs = _programs()
        cam = camera if scale == 1 else camera.scaled(scale)
        r = self.renderer(mode)
        before = dict(r.capacities)
        out = r.padded(cam)
        grew = any(before.get(k) not in (None, v) for k, v in r.capacities.items())
        img = self._colour(out, r, cam, view)
        ms = 1e3 * (time.perf_counter() - t0)
        fresh = _programs() != programs
        if enlarge and scale > 1:
            img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
            img = np.pad(img, ((0, camera.height - img.shape[0]), (0, camera.width - img.shape[1]), (0, 0)),
                         mode="edge")
        return Frame(image=img, rendered=(cam.width, cam.height), ms=ms, grew=grew, compiled=fresh)

    def _colour(self, out, r: ViewRenderer, cam: Camera, view: str) -> np.ndarray:
        H, W = cam.height, cam.width

        def crop_hw(x):
            return crop(x, H, W)

        if view == "rgb":
            return _to_uint8(crop_hw(out.rgb))
        alpha = crop_hw(out.alpha)
        if view == "alpha":
            return np.repeat(_to_uint8(alpha)[..., None], 3, axis=-1)
        if view == "depth":
            depth = crop_hw(out.depth)
            hit = alpha > 0.05
            if not hit.any():
                return np.zeros((H, W, 3), np.uint8)
            lo, hi = np.percentile(depth[hit], [2.0, 98.0])
            img = colour_ramp(1.0 - (depth - lo) / max(hi - lo, 1e-9))  # near: light
            return _to_uint8(np.where(hit[..., None], img, 0.0))
        if view == "normal":
            n = crop_hw(out.normal) / np.maximum(alpha, 1e-6)[..., None]
            n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9)
            img = 0.5 + 0.5 * n * np.array([1.0, -1.0, -1.0], np.float32)
            return _to_uint8(np.where((alpha > 0.05)[..., None], img, 0.0))
        bank = "rgb" if self.scene.rgb is not None else ("alpha" if self.scene.alpha is not None else None)
        if bank is None:
            return np.zeros((H, W, 3), np.uint8)  # no textures: nothing to show
        cfg = r.config
        if view == "mip level":
            use = cfg.mip != "none" and (cfg.rgb_mip if bank == "rgb" else cfg.alpha_mip)
            lev = crop_hw(dominant_mip_level(self.scene, r.camera(cam), out.dominant, bank=bank,
                                          lambda_mip=float(cfg.lambda_mip), use_mip=bool(use)))
            img = LEVEL_COLOURS[np.clip(lev, 0, len(LEVEL_COLOURS) - 1)]
            return _to_uint8(np.where((lev >= 0)[..., None], img, 0.0))
        dom = crop_hw(out.dominant)
        sizes = np.asarray(getattr(self.scene, bank).size)
        n = sizes[np.maximum(dom, 0)]
        img = colour_ramp(np.log2(np.maximum(n, 1.0)) / 5.0)
        return _to_uint8(np.where(((dom >= 0) & (n > 0))[..., None], img, 0.0))

    def release(self) -> None:
        """Releases the compiled renderers (another scene has other shapes)."""
        for r in self._renderers.values():
            r.capacities.clear()
        self._renderers.clear()
        release_scene_programs()
        from ..memory_maps import release_programs

        release_programs(dominant_mip_level)


def _programs() -> int:
    """XLA programs this process has compiled (or loaded from the persistent cache) so far, from JAX's
    compile events: a frame that changes the count compiled something (the renderer, the pair
    counter, the texture preparer, the mip-level function or an eager op)."""
    from .. import memory_maps

    return memory_maps.xla_compiles()[0]


def scene_stats(scene) -> dict:
    """``{"gaussians", "texels", "storage_mb"}`` of a scene (see :func:`metrics.scene_storage`)."""
    from ..metrics import scene_storage

    size = scene_storage(scene)
    return {k: size[k] for k in ("gaussians", "texels", "storage_mb")}
