"""Padding views to a few image sizes, so that a run compiles a handful of programs.

A jitted renderer or training step is compiled once per image size (``Camera.width`` and
``height`` are static). Undistorted captures have a slightly different size per image (beer at 1/4:
20 sizes over 62 training views), and evaluation adds every view's zoom-outs, so compiling per size
fills the process's memory mappings (see :mod:`patexgs_jax.memory_maps`). Here a view is rendered at a
padded size instead, with the same intrinsics, and cropped: pixel (i, j) keeps its centre
(j + 0.5, i + 0.5) and the renderer composites each tile independently, so the cropped image is the
unpadded render: bit for bit when the padded size keeps the tile grid, within float rounding (1e-6
relative, tiles are batched differently) when it adds tiles.

Padded sizes: the side is rounded up to whole tiles (the renderer computes whole tiles anyway: the
padding inside the last tile is free), then the number of tiles t to ``steps_per_octave`` sizes per
octave: t itself up to ``steps_per_octave`` tiles, above that the next ``m 2^k`` with
``steps_per_octave <= m < 2 steps_per_octave`` (at most 1/steps_per_octave of extra tiles a side).
``steps_per_octave=None`` keeps the tile grid exactly: then every per-splat output (visibility,
radius, pair count) equals the unpadded render's too, which training needs (densification
statistics); evaluation uses :data:`EVAL_STEPS_PER_OCTAVE`.

Training pads a view in one of two ways (:func:`resolve_padding`, ``TrainConfig.padding``):
"per-size" pads each view to its own tile grid (one step program per distinct tile grid of the
training views); "one" pads every view to the largest tile grid of the training views
(:func:`one_size`; one step program per tile capacity), and the renderer bins only the tiles of the
view's own grid (``render_jit(..., valid_hw=)``), so the splats' visibility, radii and pair counts
are the per-size ones and the extra tiles stay empty (their cost: the pixels the loss and the
compositor pass over, :func:`extra_pixel_share`).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import memory_maps
from .camera import Camera
from .render import Capacity, count_pairs, render_jit, scene_textures

#: Padded sizes per octave of tiles used by evaluation: the exact tile grid up to 16 x 16 = 256
#: pixels a side, at most an eighth of extra tiles above (beer's test views at 1/4 and their
#: zoom-outs by 2, 4, 8: 5 padded sizes).
EVAL_STEPS_PER_OCTAVE = 8


#: ``TrainConfig.padding``'s values: "auto" resolves to "one" on a GPU or TPU (compiles cost the
#: most there: tens of seconds a program at full size) and "per-size" on a CPU (where the step's
#: time grows with its pixels and a compile costs less than the padding would over a run).
PADDING_POLICIES = ("auto", "per-size", "one")


def resolve_padding(policy: str, backend: str | None = None) -> str:
    """"per-size" or "one": ``policy``, or for "auto" the backend's choice (see
    :data:`PADDING_POLICIES`; ``backend`` defaults to ``jax.default_backend()``)."""
    if policy not in PADDING_POLICIES:
        raise ValueError(f"padding must be one of {PADDING_POLICIES}, got {policy!r}.")
    if policy != "auto":
        return policy
    backend = jax.default_backend() if backend is None else backend
    return "per-size" if backend == "cpu" else "one"


def one_size(cameras: Sequence[Camera], tile_size: int = 16) -> tuple[int, int]:
    """(height, width) of the "one" padding of views ``cameras``: the largest padded height and the
    largest padded width among their own tile grids (every view fits it)."""
    if not cameras:
        raise ValueError("one_size needs at least one camera.")
    shapes = [padded_shape(c.height, c.width, tile_size) for c in cameras]
    return max(h for h, _ in shapes), max(w for _, w in shapes)


def train_camera(camera: Camera, tile_size: int = 16, size: tuple[int, int] | None = None) -> Camera:
    """The camera a training step renders ``camera`` with: at its own tile grid (``size`` None,
    "per-size") or at ``size`` = (height, width) ("one", :func:`one_size`); K and pose unchanged."""
    if size is None:
        return padded_camera(camera, tile_size)
    h, w = size
    if camera.height > h or camera.width > w:
        raise ValueError(f"a {camera.width}x{camera.height} view does not fit the padded size {w}x{h}; "
                         "compute the size with one_size over every view trained.")
    if (h, w) == (camera.height, camera.width):
        return camera
    return Camera(K=camera.K, world_to_camera=camera.world_to_camera, width=w, height=h)


def extra_pixel_share(cameras: Sequence[Camera], tile_size: int = 16) -> dict:
    """Pixels a step passes over, as a share over the views' own pixels, per padding: ``per_size``
    (each view's own tile grid), ``one`` (:func:`one_size`), ``one_over_per_size`` (the "one"
    padding's pixels over the per-size padding's, minus 1), and ``sizes`` (distinct per-size
    padded sizes)."""
    own = sum(c.height * c.width for c in cameras)
    per = sum(int(np.prod(padded_shape(c.height, c.width, tile_size))) for c in cameras)
    h, w = one_size(cameras, tile_size)
    one = len(cameras) * h * w
    sizes = {padded_shape(c.height, c.width, tile_size) for c in cameras}
    return dict(per_size=per / own - 1.0, one=one / own - 1.0, one_over_per_size=one / per - 1.0,
                sizes=len(sizes), one_size=[h, w])


class TrainPadding:
    """How a run pads its training views (``TrainConfig.padding``, resolved: :func:`resolve_padding`)
    and how much headroom its step's tile capacity gets over the pairs a view needs.

    Attributes:
      policy: "per-size" or "one".
      headroom: the tile capacity's share over the pairs counted (:data:`HEADROOM`).
    """

    #: Tile-capacity headroom per policy. "one" compiles a program per capacity, so the capacity
    #: gets room for the pairs to double (a densification interval's growth, or a view that needs
    #: twice the one it was fitted to) before it overflows; "per-size" keeps the CPU's 1.25, where a
    #: larger pair list costs its sort on every step.
    HEADROOM = {"per-size": 1.25, "one": 2.0}
    #: A capacity in use is kept while it holds this many times the pairs a refit counts (a new
    #: capacity is a new program): it grows only when the pairs near it, and then by ``headroom``.
    KEEP_WHILE = 1.25

    def __init__(self, policy: str, cameras: Sequence[Camera], backend: str | None = None):
        self.policy = resolve_padding(policy, backend)
        self.headroom = self.HEADROOM[self.policy]
        self._cameras = list(cameras)
        self._sizes: dict[int, tuple[int, int]] = {}  # tile size -> the "one" size

    def size(self, tile_size: int = 16) -> tuple[int, int] | None:
        """(height, width) every view is padded to ("one"), or None ("per-size")."""
        if self.policy != "one":
            return None
        if tile_size not in self._sizes:
            self._sizes[tile_size] = one_size(self._cameras, tile_size)
        return self._sizes[tile_size]

    def camera(self, camera: Camera, tile_size: int = 16) -> Camera:
        """The camera the step renders ``camera`` with (:func:`train_camera`)."""
        return train_camera(camera, tile_size, self.size(tile_size))

    def capacity(self, pairs_needed, minimum: Capacity | None = None, current: Capacity | None = None) -> Capacity:
        """The tile capacity for ``pairs_needed`` pairs: ``headroom`` times them, rounded up to the
        power-of-two bucket (:meth:`Capacity.fit`), never below ``minimum`` or ``current``; the
        capacity in use, ``current`` (a refit, an overflow), is kept while it holds
        :data:`KEEP_WHILE` times the pairs (for "per-size" the same as growing it: its headroom is
        that share)."""
        pairs = float(pairs_needed)
        floor = current if minimum is None or (current is not None and current.pairs >= minimum.pairs) else minimum
        if current is not None and pairs * self.KEEP_WHILE <= current.pairs:
            return current if floor is None else floor
        return Capacity.fit(pairs * self.headroom, minimum=floor)

    def summary(self, tile_size: int = 16) -> dict:
        """summary.json's ``padding``: the policy, the headroom and the pixel shares of
        :func:`extra_pixel_share`."""
        return dict(policy=self.policy, headroom=self.headroom, **extra_pixel_share(self._cameras, tile_size))


def padded_side(side: int, tile_size: int = 16, steps_per_octave: int | None = None) -> int:
    """The padded length of an image side of ``side`` pixels (see the module docstring)."""
    side, tile_size = int(side), int(tile_size)
    if side < 1 or tile_size < 1:
        raise ValueError(f"image side and tile size must be positive, got {side} and {tile_size}.")
    tiles = -(-side // tile_size)
    if steps_per_octave is not None:
        steps = int(steps_per_octave)
        if steps < 1:
            raise ValueError(f"steps_per_octave must be >= 1 or None, got {steps_per_octave}.")
        if tiles > steps:
            k = (tiles - 1).bit_length() - steps.bit_length()  # tiles <= m 2^k with m < 2 steps
            k = max(k, 0)
            while -(-tiles // (1 << k)) >= 2 * steps:
                k += 1
            tiles = -(-tiles // (1 << k)) * (1 << k)
    return tiles * tile_size


def padded_shape(height: int, width: int, tile_size: int = 16,
                 steps_per_octave: int | None = None) -> tuple[int, int]:
    """(padded height, padded width) of an ``height x width`` image."""
    return (padded_side(height, tile_size, steps_per_octave), padded_side(width, tile_size, steps_per_octave))


def padded_camera(camera: Camera, tile_size: int = 16, steps_per_octave: int | None = None) -> Camera:
    """The same camera (K and pose unchanged: pixel centres stay where they are) at its padded size."""
    h, w = padded_shape(camera.height, camera.width, tile_size, steps_per_octave)
    if (h, w) == (camera.height, camera.width):
        return camera
    return Camera(K=camera.K, world_to_camera=camera.world_to_camera, width=w, height=h)


def pad_image(image, height: int, width: int) -> np.ndarray:
    """(height, width, C) float32 copy of an (H, W, C) image, zeros below and to the right."""
    image = np.asarray(image, np.float32)
    H, W = image.shape[:2]
    if H > height or W > width:
        raise ValueError(f"cannot pad a {H}x{W} image to {height}x{width}.")
    out = np.zeros((height, width) + image.shape[2:], np.float32)
    out[:H, :W] = image
    return out


def valid_mask(shape: tuple[int, int], valid_hw) -> jax.Array:
    """(Hb, Wb) bool, True on the top-left ``valid_hw = (H, W)`` block (traced values allowed)."""
    rows = jnp.arange(shape[0])[:, None] < valid_hw[0]
    cols = jnp.arange(shape[1])[None, :] < valid_hw[1]
    return rows & cols


def crop(x, height: int, width: int) -> np.ndarray:
    """``x[:height, :width]`` as a host array, copied from the device first (no slice program per size)."""
    return np.asarray(x)[:height, :width]


def crop_output(out, height: int, width: int):
    """A :class:`patexgs_jax.RenderOutput` of a padded render with its images cropped to
    ``height x width`` (host numpy arrays: cropping on the device would compile a slice per size)
    and ``max_contrib_count`` counted over the kept pixels only, as the unpadded render counts them.
    Per-splat outputs (``visible``, ``radius_px``, ``pairs_needed``) are the padded render's: equal
    to the unpadded ones when the tile grid was kept (``steps_per_octave=None``)."""
    import dataclasses

    if out.rgb.shape[:2] == (height, width):
        return out
    def crop_hw(x):
        return crop(x, height, width)

    dominant = crop_hw(out.dominant)
    best = dominant.reshape(-1)
    counts = np.bincount(best[best >= 0], minlength=out.max_contrib_count.shape[0]).astype(np.int32)
    return dataclasses.replace(out, rgb=crop_hw(out.rgb), alpha=crop_hw(out.alpha), depth=crop_hw(out.depth),
                               normal=crop_hw(out.normal), distortion=crop_hw(out.distortion), dominant=dominant,
                               max_contrib_count=counts)


class ViewRenderer:
    """Renders one scene from views of any size with one program per padded size.

    The tile capacity of a padded size is the largest any of its views needs (:meth:`prepare` counts a
    list of views up front, so that each padded size compiles once; a view met later grows its size's
    capacity, a new program). Images are never truncated. Use as a context manager (or call
    :meth:`release`) so that the scene's compiled renderer and pair counter are released when done:
    another scene has other shapes and never reuses them.

    Args:
      scene: the :class:`patexgs_jax.Scene`.
      config: its :class:`patexgs_jax.RenderConfig`.
      steps_per_octave: the padded sizes (see :func:`padded_side`; None: the exact tile grid).
      active_sh_degree: optional cap on the SH bands.
      headroom: a padded size first met in :meth:`padded` gets the capacity of ``headroom`` times the
        view's need, so that nearby views (an interactive camera) fit it without a new program.
      reuse_textures: build the scene's texture atlases and their pyramids once
        (:func:`patexgs_jax.render.scene_textures`) and reuse them for every view, instead of in every
        render: for many views of one scene (a viewer), at the cost of one more program.
      programs: programs compiled ahead for this scene's layout (:mod:`patexgs_jax.training.compile_ahead`):
        ``("count", h, w)``: ``count_pairs.lower(scene, camera, config=config).compile()``;
        ``("render", h, w, capacity)``: ``render_jit.lower(scene, camera, config=config,
        capacity=capacity, active_sh_degree=None, textures=None).compile()``, for padded cameras of
        h x w; used in place of compiling the same (other keys compile as usual).
    """

    def __init__(self, scene, config, *, steps_per_octave: int | None = EVAL_STEPS_PER_OCTAVE,
                 active_sh_degree=None, headroom: float = 1.0, reuse_textures: bool = False,
                 programs: dict | None = None):
        if not headroom >= 1.0:
            raise ValueError(f"headroom must be >= 1, got {headroom}.")
        self.scene, self.config, self.steps = scene, config, steps_per_octave
        self.active_sh_degree = active_sh_degree
        self.headroom = float(headroom)
        self.reuse_textures = reuse_textures
        self._textures = None  # the scene's scene_textures, once built (reuse_textures)
        self.capacities: dict = {}  # (height, width) of a padded size -> Capacity; one per size
        self.programs = dict(programs or {})
        # (a padded camera's size, intrinsics and pose -> the pairs it needs: one scene, so each view is
        # counted once, however many view lists are prepared with it)
        self._counted: dict = {}

    def camera(self, camera: Camera) -> Camera:
        """``camera`` at its padded size."""
        return padded_camera(camera, self.config.tile_size, self.steps)

    def _needed(self, cam: Camera) -> float:
        key = (cam.height, cam.width, np.asarray(cam.K).tobytes(), np.asarray(cam.world_to_camera).tobytes())
        if key not in self._counted:
            program = self.programs.get(("count", cam.height, cam.width))
            needed, _ = (program(self.scene, cam) if program is not None
                         else count_pairs(self.scene, cam, self.config))
            self._counted[key] = float(needed)
        return self._counted[key]

    def _render(self, cam: Camera, cap: Capacity):
        program = (self.programs.get(("render", cam.height, cam.width, cap))
                   if self.active_sh_degree is None and self._textures is None else None)
        if program is not None:
            return program(self.scene, cam, active_sh_degree=None, textures=None)
        return render_jit(self.scene, cam, config=self.config, capacity=cap,
                          active_sh_degree=self.active_sh_degree, textures=self._textures)

    def prepare(self, cameras: Sequence[Camera]) -> None:
        """Fits every padded size's capacity to the views ``cameras`` (counted, not rendered)."""
        for c in cameras:
            cam = self.camera(c)
            key = (cam.height, cam.width)
            self.capacities[key] = Capacity.fit(self._needed(cam), minimum=self.capacities.get(key))

    def compile(self, cameras: Sequence[Camera]) -> dict:
        """Fits the padded sizes' capacities to ``cameras`` as :meth:`prepare` does, compiling the
        pair counter and renderer of each size as executables of their own (JAX's caches may release
        theirs; these live as long as the dict): what ``programs=`` takes, returned."""
        new = {}
        for c in cameras:
            cam = self.camera(c)
            key = (cam.height, cam.width)
            if ("count", *key) not in self.programs:
                self.programs[("count", *key)] = count_pairs.lower(self.scene, cam, config=self.config).compile()
                new[key] = cam
            self.capacities[key] = Capacity.fit(self._needed(cam), minimum=self.capacities.get(key))
        for key, cam in new.items():
            self.programs[("render", *key, self.capacities[key])] = render_jit.lower(
                self.scene, cam, config=self.config, capacity=self.capacities[key], active_sh_degree=None,
                textures=None).compile()
        return self.programs

    def padded(self, camera: Camera):
        """The :class:`RenderOutput` of ``camera`` rendered at its padded size, uncropped (on the
        device; what render timing measures)."""
        cam = self.camera(camera)
        key = (cam.height, cam.width)
        cap = self.capacities.get(key)
        if cap is None:
            cap = self.capacities[key] = Capacity.fit(self.headroom * self._needed(cam))
        if self.reuse_textures and self._textures is None:
            self._textures = scene_textures(self.scene, config=self.config)
        out = self._render(cam, cap)
        if bool(out.overflow):  # a view not prepared for, needing more than its padded size's capacity holds
            cap = self.capacities[key] = Capacity.fit(float(out.pairs_needed), minimum=cap)
            out = self._render(cam, cap)
        return out

    def __call__(self, camera: Camera):
        """The :class:`RenderOutput` of ``camera`` (images ``camera.height x camera.width``, see
        :func:`crop_output`)."""
        return crop_output(self.padded(camera), camera.height, camera.width)

    def image(self, camera: Camera) -> np.ndarray:
        """(H, W, 3) float32 render clipped to [0, 1]."""
        return np.clip(np.asarray(self(camera).rgb, np.float32), 0.0, 1.0)

    def release(self) -> None:
        """Done with the scene: its capacities and programs are forgotten, and the compiled renderer
        and pair counter released where the process holds more than :data:`memory_maps.KEEP_SHARE` of
        its memory-map cap (below it they are kept for the next scene of these shapes; see
        :func:`release_scene_programs`)."""
        release_scene_programs(retire=True)
        self.capacities.clear()
        self.programs.clear()
        self._counted.clear()
        self._textures = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()
        return False


def release_scene_programs(retire: bool = False) -> bool:
    """Releases the renderer's, the pair counter's and the texture preparer's compiled programs (one
    per scene shape, image size and capacity), and the image metrics' (one per image size); with
    ``retire``, only where the process holds more than :data:`memory_maps.KEEP_SHARE` of its
    memory-map cap (:func:`memory_maps.retire_programs`). Returns whether it released them."""
    from . import metrics

    fns = (render_jit, count_pairs, scene_textures, metrics.ssim)
    if retire:
        return memory_maps.retire_programs(*fns)
    memory_maps.release_programs(*fns)
    return True
