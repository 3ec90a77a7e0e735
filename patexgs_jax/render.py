"""The renderer: the jit-compiled tile renderer of textured 2D Gaussian splats with per-pixel mipmaps.

State pytrees in (:class:`~patexgs_jax.scene.Scene`, :class:`~patexgs_jax.camera.Camera`), a
:class:`RenderOutput` out. The stages it calls live in :mod:`patexgs_jax.rendering`.

Conventions (fixed for the package)
  * Cameras: OpenCV (x right, y down, z forward), world-to-camera 4x4; pixel (i, j) has its centre
    at continuous coordinates (j + 0.5, i + 0.5).
  * Kernel (2DGS): the ray of a pixel meets the splat plane at (u, v), in units of the scales
    (homogeneous ray-splat intersection); ``rho3d = u^2 + v^2``; the screen-space low-pass is
    ``rho2d = 2 |x - mu2d|^2`` in pixels; ``G = exp(-0.5 min(rho3d, rho2d))``. The depth of a
    pair is the intersection's camera z where rho3d <= rho2d, else the splat centre's. A ray so
    nearly parallel to the splat plane that |u| or |v| would exceed 1e4 has no 3D intersection:
    rho3d is taken as 1e8 (G from the low-pass only) and its texture lookups use the splat centre
    (u, v) = (0, 0) (whose mip footprint is the coarsest level).
  * ``RenderConfig(coverage="prefilter")`` (the ``patexgs`` methods) replaces ``G`` and the
    low-pass by the EWA resampling filter: with K the 2x2 Jacobian d(pixel)/d(u, v) at the splat's
    centre, the splat-plane Gaussian convolved with a screen Gaussian of variance ``v``
    (``pixel_var``, widened per axis so the filtered screen variance is at least ``min_var``) is
    ``G = exp(-0.5 h^T P h)``, h the pixel's (u, v) offset from the centre mapped through K, P =
    K^T (K K^T + V)^-1 K, and the opacity is multiplied by the coverage factor
    ``|det K| / sqrt(det(K K^T + V))`` (<= 1), which keeps the splat's integrated coverage. Pairs
    are skipped below 1/255 times that factor, so a faint sub-pixel splat still composites. G is
    zero outside the screen ellipse ``d^T S^-1 d <= SUPPORT_Q`` (S = K K^T + V, d the pixel's
    offset from the centre): the filter is affine about the centre, and where P maps a near
    edge-on splat's pixel to far along its plane, the kernel stops at twice the affine footprint.
  * ``RenderConfig(coverage="billboard")`` (the ``bbsplat`` methods, :mod:`.rendering.billboard`): G = 1
    on the square ``|u|, |v| <= 3`` of the splat plane (the textures' span) and 0 outside, no
    low-pass; the pair's depth is the intersection's. The square's edge passes no gradient.
  * ``alpha = min(0.99, opacity * G * A_tex(u, v))``; a pair with alpha < 1/255, or whose
    intersection lies at depth <= ``near``, is skipped; front-to-back compositing in order of the
    Gaussians' centre depths stops before the first splat that would bring transmittance below 1e-4.
  * Colour of a splat at a pixel: ``max(SH(d) + 0.5, 0) + RGB_tex(u, v)``, d the unit direction
    from the camera centre to the splat's mean (one direction per splat, as in 3DGS).
  * Textures span ``[-3, 3]^2`` of the splat plane, align-corners bilinear, clamped at the edges
    (see :mod:`patexgs_jax.textures`).
  * Mip level per pixel and splat (paper Eq. 11): with (u1, v1), (u2, v2), (u3, v3) the
    intersections of the rays of pixel (X, Y), (X + 1, Y) and (X, Y + 1) with the splat plane,
    ``D = max(|p2 - p1|, |p3 - p1|)`` in splat-plane units and
    ``l = min(L, max(0, floor(log2(lambda_mip * n * D))))`` with n the texture side and
    L = ceil(log2 n). RGB and alpha textures pick their levels independently (their n may differ).
    ``mip="trilinear"`` blends the two nearest levels by the fractional level instead.
  * 3D Gaussians (``Scene.log_scales`` (C, 3); 3DGS, Mip-Splatting) are projected by EWA with
    3DGS's 0.3 px^2 dilation ("lowpass") or Mip-Splatting's 2D Mip filter ("prefilter") and
    composited as above with the screen-space kernel; their pairs' depth is the centre's camera z,
    their normal the axis of the smallest scale facing the camera; no textures (:mod:`.rendering.gaussian3d`).
  * Outputs: ``rgb`` composited over ``background``; ``alpha = 1 - T_final``; ``depth`` is the
    alpha-normalised expected ray-splat intersection depth (camera z), 0 where nothing is hit;
    ``normal`` is the alpha-weighted sum of the splats' camera-frame unit normals, each flipped to
    face the camera (divide by alpha for a unit normal).

Structure: one stage a module of :mod:`patexgs_jax.rendering`
  :mod:`.config`: :class:`RenderConfig`, :class:`Capacity`, :class:`RenderOutput` and the constants
  above (alpha cap and cut, transmittance stop, the prefilter's support).
  :mod:`.projection`: per-splat quantities (C of them) and screen-space bounds, packed into one
  (C, F) array whose columns :data:`projection.COLS` lays out.
  :mod:`.tiling`: how many tiles the compositor advances at once, chosen per device.
  :mod:`.binning`: depth-ordered per-tile lists, with one stable sort of (tile) keys over pairs
  generated in depth order; the tiles of a splat's screen box it cannot reach alpha 1/255 in are
  left out (``RenderConfig.tile_cull``).
  The compositor walks each tile's list front to back in chunks of ``RenderConfig.chunk`` splats
  (pixels x chunk at a time) and stops the tile once every pixel saturated or the list ended, so the
  work follows the splats that actually contribute: :mod:`.chunks` (tile batches, a chunk's slots
  and its (c, B, P) blocks), :mod:`.kernel` (the kernel G and the pair's depth, with their
  hand-derived backward), :mod:`.texture_lookup` (the mip footprint, the atlas lookups of only the
  pairs that can contribute, their backward) and :mod:`.composite` (front-to-back compositing, its
  hand-written backward, ``jax.custom_vjp``, which re-walks the chunks and stores nothing per pair).
  ``RenderConfig(compositor="pallas")`` composites with one Pallas GPU kernel instead
  (:mod:`.rendering.pallas_composite`, :mod:`.rendering.pallas_texture`: one program per tile, the
  same outputs and gradients); None, the default, picks per backend: the Pallas kernel on a GPU,
  the XLA compositor elsewhere (:func:`.rendering.config.resolve_compositor`).
  This module: :func:`render`, :data:`render_jit`, :data:`count_pairs`, :data:`scene_textures`
  and :func:`check_inputs`.

  One-texel textures are constants: they are folded into the splat's colour and opacity
  (:func:`projection.constant_textures`) and not looked up.

  The one static capacity (``Capacity.pairs``, the length of the sorted pair list) is checked
  against the exact need (counted before binning) and the need is returned, so callers grow the
  capacity and render again; :func:`render` does this itself and never returns a truncated image.
"""

from __future__ import annotations

import collections
import dataclasses
import warnings

import chex
import jax
import jax.numpy as jnp
from jax import lax

from . import textures as tex
from .camera import Camera
from .rendering.binning import bin_projection, pair_count, tile_histogram, tile_ranges
from .rendering.chunks import CompositeInputs, Static
from .rendering.composite import composite_tiles
from .rendering.config import (
    ALPHA_MAX,
    ALPHA_MIN,
    COVERAGE_MODES,
    LAMBDA_MIP_DEFAULT,
    MIP_MODES,
    SUPPORT_Q,
    T_MIN,
    Capacity,
    RenderConfig,
    RenderOutput,
    resolve_compositor,
)
from .rendering.gaussian3d import kernel_config, project3d
from .rendering.projection import alpha_peak, constant_textures, project
from .rendering.texture_lookup import meta_table
from .rendering.tiling import resolve_tile_batch
from .scene import Scene
from .textures.billboard_alpha import gaussian_weighted

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "COVERAGE_MODES",
    "LAMBDA_MIP_DEFAULT",
    "MIP_MODES",
    "SUPPORT_Q",
    "T_MIN",
    "TRACE_COUNTS",
    "Capacity",
    "RenderConfig",
    "RenderOutput",
    "SceneTextures",
    "check_inputs",
    "count_pairs",
    "scene_textures",
    "render",
    "render_jit",
]

#: How many times the jitted renderer has been traced, per (config, capacity), in this process. Tests
#: and benchmarks read it to assert that a view of known shapes does not retrace; nothing in the
#: package reads it (whether a viewer frame compiled comes from JAX's compile events,
#: :func:`patexgs_jax.memory_maps.xla_compiles`).
TRACE_COUNTS: collections.Counter = collections.Counter()


def _untile(x, tiles_x, tiles_y, ts, H, W):
    """(T, ts*ts, ...) per-tile values -> (H, W, ...) image."""
    rest = x.shape[2:]
    x = x.reshape((tiles_y, tiles_x, ts, ts) + rest)
    x = jnp.moveaxis(x, 2, 1).reshape((tiles_y * ts, tiles_x * ts) + rest)
    return x[:H, :W]


_LAYOUT_FIX = ("build scenes with Scene.from_arrays or random_scene and cameras with Camera.from_intrinsics "
               "or look_at, which set this layout; see patexgs_jax/scene.py")


def check_inputs(scene: Scene, camera: Camera) -> None:
    """Shapes and dtypes of a scene and camera against the layout the renderer assumes (module
    docstrings of scene.py and camera.py). Static, so it costs nothing under ``jax.jit``: a Scene
    or Camera built or edited by hand fails here, naming the field, not inside the compositor.

    Raises:
      AssertionError (chex's) naming the field, its shape or dtype and the fix.
    """
    c = scene.means.shape[0] if scene.means.ndim else -1
    dims = scene.log_scales.shape[-1] if scene.log_scales.ndim == 2 and scene.log_scales.shape[-1] == 3 else 2
    if dims == 3 and (scene.rgb is not None or scene.alpha is not None):  # (3D Gaussians, gaussian3d.py)
        raise ValueError("render: textures are not supported on 3D Gaussians (log_scales (C, 3)); drop the "
                         "scene's rgb / alpha banks, or use 2D splats (log_scales (C, 2)) for textures.")
    fields = dict(means=(scene.means, (c, 3)), log_scales=(scene.log_scales, (c, dims)),
                  quats=(scene.quats, (c, 4)), opacity_logits=(scene.opacity_logits, (c,)),
                  sh=(scene.sh, (c, None, 3)), active=(scene.active, (c,)))
    for name, (x, shape) in fields.items():
        msg = f"Scene.{name} must be {shape} floating-point for capacity C={c}; {_LAYOUT_FIX}"
        chex.assert_shape(x, shape, custom_message=msg)
        chex.assert_type(x, float, custom_message=msg)
    if scene.sh.shape[1] not in (1, 4, 9, 16):
        raise AssertionError(f"Scene.sh has {scene.sh.shape[1]} coefficients per channel; SH degrees 0-3 "
                             f"have 1, 4, 9 or 16; {_LAYOUT_FIX}")
    for bank in (scene.rgb, scene.alpha):
        if bank is not None:
            for name in ("bucket", "slot", "size"):
                chex.assert_shape(getattr(bank, name), (c,), custom_message=(
                    f"TextureBank.{name} must be ({c},) for capacity C={c}; {_LAYOUT_FIX}"))
    for name, x, shape in (("K", camera.K, (3, 3)), ("world_to_camera", camera.world_to_camera, (4, 4))):
        msg = f"Camera.{name} must be {shape} floating-point; {_LAYOUT_FIX}"
        chex.assert_shape(x, shape, custom_message=msg)
        chex.assert_type(x, float, custom_message=msg)


def _tile_grid(camera: Camera, config: RenderConfig):
    """(tiles_x, tiles_y): the tiles covering the image."""
    ts = config.tile_size
    return -(-camera.width // ts), -(-camera.height // ts)


def _valid_tiles(camera: Camera, config: RenderConfig, valid_hw):
    """(columns, rows) of tiles covering the top-left ``valid_hw = (H, W)`` pixels of a padded
    ``camera`` (traced () int32 each), or None for the whole image (``valid_hw`` None)."""
    if valid_hw is None:
        return None
    tiles_x, tiles_y = _tile_grid(camera, config)
    ts = config.tile_size
    hw = jnp.asarray(valid_hw, jnp.int32)
    return jnp.minimum((hw[1] + ts - 1) // ts, tiles_x), jnp.minimum((hw[0] + ts - 1) // ts, tiles_y)


def _project_and_range(scene: Scene, camera: Camera, config: RenderConfig, screen_offset, active_sh_degree, peak,
                       constant=None, valid_hw=None):
    """The projection of a view, its splats' tile ranges (tx0, tx1, ty0, ty1, ok), the (splat, tile)
    pairs it needs (() float32) and the most splats any tile lists (() int32); with ``valid_hw``
    ((2,) int, the view's own (H, W) within a padded camera), of the tiles covering it only."""
    tiles_x, tiles_y = _tile_grid(camera, config)
    if scene.is_3d:
        proj = project3d(scene, camera, config, screen_offset, active_sh_degree)
    else:
        proj = project(scene, camera, config, screen_offset, active_sh_degree, peak, constant)
    ranges = tile_ranges(proj.bounds, proj.visible, config.tile_size, tiles_x, tiles_y,
                         _valid_tiles(camera, config, valid_hw))
    hist = tile_histogram(*ranges, tiles_x, tiles_y)
    return proj, ranges, pair_count(*ranges), jnp.max(hist)


def _mip_banks(config: RenderConfig) -> tuple[bool, bool]:
    """Whether the RGB and the alpha atlases hold mip pyramids under ``config``."""
    use_mip = config.mip != "none"
    return use_mip and config.rgb_mip, use_mip and config.alpha_mip


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SceneTextures:
    """What a render derives from the scene's textures alone, for any view: reusable across the
    views of a scene that does not change (:func:`scene_textures`).

    Attributes:
      peak: (C,) each splat's largest alpha-texture value (:func:`projection.alpha_peak`).
      rgb_add, alpha_mul, rgb_const, alpha_const: the one-texel textures folded into the colour and
        opacity (:func:`projection.constant_textures`), or None.
      rgb_atlas, alpha_atlas: the banks' :class:`textures.Atlas` (with their mip pyramids), or None.
      mips: (static) whether each atlas holds its pyramid, as :func:`_mip_banks` of the config it
        was prepared for.
    """

    peak: jax.Array
    rgb_add: jax.Array | None
    alpha_mul: jax.Array | None
    rgb_const: jax.Array | None
    alpha_const: jax.Array | None
    rgb_atlas: tex.Atlas | None
    alpha_atlas: tex.Atlas | None
    mips: tuple = dataclasses.field(metadata=dict(static=True))
    texel_grid: bool = dataclasses.field(default=False, metadata=dict(static=True))


def _scene_textures(scene: Scene, config: RenderConfig) -> SceneTextures:
    rgb_mip, alpha_mip = mips = _mip_banks(config)
    texel_grid = config.coverage == "texel-grid"
    if texel_grid:  # Eq. 13's G x A on the texel grid: the pyramid, peaks and folds are of the product
        if scene.alpha is None:
            raise ValueError("render: coverage 'texel-grid' weights the alpha textures by Eq. 2's Gaussian, and the "
                             "scene has none; render an untextured scene with coverage 'lowpass' or 'object'.")
        scene = scene.replace(alpha=gaussian_weighted(scene.alpha))
    return SceneTextures(
        alpha_peak(scene), *constant_textures(scene),
        rgb_atlas=None if scene.rgb is None else tex.build_atlas(scene.rgb, rgb_mip),
        alpha_atlas=None if scene.alpha is None else tex.build_atlas(scene.alpha, alpha_mip), mips=mips,
        texel_grid=texel_grid)


#: ``scene_textures(scene, config=...)`` -> :class:`SceneTextures`: the texture atlases (with
#: their mip pyramids), peaks and one-texel folds of ``scene`` for renders with ``config``'s mip
#: settings, built once. Pass them to :data:`render_jit` (``textures=``) for every view of a scene
#: that does not change (a viewer, an evaluation): each frame then does its view's work only, where
#: it would otherwise rebuild every texture's pyramid. No gradient reaches the textures through
#: prepared ones.
scene_textures = jax.jit(_scene_textures, static_argnames=("config",))


def _render(scene: Scene, camera: Camera, config: RenderConfig, capacity: Capacity,
            screen_offset=None, active_sh_degree=None, textures: SceneTextures | None = None,
            valid_hw=None) -> RenderOutput:
    TRACE_COUNTS[(config, capacity)] += 1
    check_inputs(scene, camera)
    H, W, ts = camera.height, camera.width, config.tile_size
    tiles_x, tiles_y = _tile_grid(camera, config)
    num_tiles = tiles_x * tiles_y
    if textures is None:
        textures = _scene_textures(scene, config)
    elif textures.mips != _mip_banks(config) or (textures.rgb_atlas is None) != (scene.rgb is None) or (
            textures.alpha_atlas is None) != (scene.alpha is None) or textures.texel_grid != (
            config.coverage == "texel-grid"):
        raise ValueError("render: the prepared textures were made for another scene or other mip settings; "
                         "call scene_textures(scene, config=config) with this render's scene and config.")
    peak, rgb_add, alpha_mul = textures.peak, textures.rgb_add, textures.alpha_mul
    rgb_const, alpha_const = textures.rgb_const, textures.alpha_const
    rgb_atlas, alpha_atlas = textures.rgb_atlas, textures.alpha_atlas
    proj, ranges, pairs_needed, max_tile = _project_and_range(
        scene, camera, config, screen_offset, active_sh_degree, peak, (rgb_add, alpha_mul), valid_hw)
    kcfg = kernel_config(config, scene)  # 3D Gaussians: the compositor's screen-space (prefilter) kernel
    ids_sorted, tile_start, binned = bin_projection(proj, ranges, tiles_x, num_tiles, capacity.pairs, kcfg)
    ok = ranges[4]

    batch = resolve_tile_batch(config.tile_batch, num_tiles, tile_size=ts, chunk=config.chunk)
    st = Static(config=dataclasses.replace(kcfg, tile_batch=batch), tiles_x=tiles_x, num_tiles=num_tiles,
                rgb=rgb_atlas is not None, alpha=alpha_atlas is not None)
    # One-texel textures are folded into the colour and opacity (constant_textures): not looked up.
    rgb_has = alpha_has = None
    if rgb_atlas is not None:
        rgb_has = rgb_atlas.has if rgb_const is None else rgb_atlas.has & ~rgb_const
    if alpha_atlas is not None:
        alpha_has = alpha_atlas.has if alpha_const is None else alpha_atlas.has & ~alpha_const
    if alpha_const is not None:
        peak = jnp.where(alpha_const, 1.0, peak)  # the pass bound reads the folded opacity
    tex_has = rgb_has if alpha_has is None else (alpha_has if rgb_has is None else rgb_has | alpha_has)
    ctx = CompositeInputs(
        ids_sorted=ids_sorted, tile_start=tile_start, binned=binned, peak=peak,
        flag=binned[0] >= 0,  # a True XLA cannot prove (see chunks.barrier)
        rgb_has=rgb_has, alpha_has=alpha_has, tex_has=tex_has,
        tex_meta=meta_table(rgb_atlas, alpha_atlas) if st.rgb or st.alpha else None,
        rgb_texels=None if rgb_atlas is None else lax.stop_gradient(rgb_atlas.texels),
        alpha_texels=None if alpha_atlas is None else lax.stop_gradient(alpha_atlas.texels))
    composite = composite_tiles
    if resolve_compositor(config) == "pallas":  # one Pallas kernel, imported when used
        from .rendering import pallas_composite
        composite = pallas_composite.composite_tiles
    # (the Pallas compositor's custom_vjp hides its return type, a tuple of three arrays)
    acc, t_final, best = composite(  # pyright: ignore[reportGeneralTypeIssues]
        st, proj.packed, None if rgb_atlas is None else rgb_atlas.texels,
        None if alpha_atlas is None else alpha_atlas.texels, ctx)
    bg = jnp.asarray(config.background, acc.dtype)
    rgb = acc[..., 0:3] + t_final[..., None] * bg
    depth, normal = acc[..., 3], acc[..., 4:7]
    distortion = (1.0 - t_final) * acc[..., 8] - acc[..., 7] ** 2
    rgb = _untile(rgb, tiles_x, tiles_y, ts, H, W)
    alpha = 1.0 - _untile(t_final, tiles_x, tiles_y, ts, H, W)
    depth = _untile(depth, tiles_x, tiles_y, ts, H, W)
    depth = jnp.where(alpha > 1e-6, depth / jnp.maximum(alpha, 1e-6), 0.0)
    normal = _untile(normal, tiles_x, tiles_y, ts, H, W)
    distortion = _untile(distortion, tiles_x, tiles_y, ts, H, W)
    dominant = _untile(best, tiles_x, tiles_y, ts, H, W)
    best = dominant.reshape(-1)
    C = scene.capacity
    counts = jnp.zeros((C,), jnp.int32).at[jnp.where(best >= 0, best, C)].add(1, mode="drop")
    overflow = pairs_needed > capacity.pairs
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, distortion=distortion,
                        max_contrib_count=counts, dominant=dominant,
                        radius_px=jnp.where(ok, proj.radius, 0.0), visible=ok,
                        pairs_needed=pairs_needed, max_tile_count=max_tile, overflow=overflow)


#: The jitted renderer: ``render_jit(scene, camera, config=..., capacity=..., screen_offset=None,
#: active_sh_degree=None, textures=None)``. It never grows its capacity: check ``output.overflow`` on the host
#: (training does, between steps) and call again with ``Capacity.fit(output.pairs_needed)``.
#: ``screen_offset`` ((C, 2) zeros) is a gradient hook: its gradient is the loss gradient with
#: respect to a screen-space translation of each splat, in pixels (the densification statistic);
#: ``active_sh_degree`` (traced int) masks SH bands above it; ``textures``: the scene's
#: :func:`scene_textures` for this config, or None to build them (differentiably) in the render;
#: ``valid_hw``: None, or the view's own (H, W) ((2,) int, traced) when ``camera`` is a larger padded
#: size of it: only the tiles covering it are binned (the others stay empty and show the background),
#: so visibility, radii and ``pairs_needed`` are those of the view's own tile grid.
render_jit = jax.jit(_render, static_argnames=("config", "capacity"))


def _count(scene: Scene, camera: Camera, config: RenderConfig, valid_hw=None):
    _, _, pairs_needed, max_tile = _project_and_range(scene, camera, config, None, None, alpha_peak(scene),
                                                      valid_hw=valid_hw)
    return pairs_needed, max_tile


#: Exact (pairs_needed, max_tile_count) of a view, without rendering it (``valid_hw`` as
#: :data:`render_jit`'s).
count_pairs = jax.jit(_count, static_argnames=("config",))

_DEFAULT_CONFIG = RenderConfig()


def render(scene: Scene, camera: Camera, config: RenderConfig = _DEFAULT_CONFIG, *,
           capacity: Capacity | None = None, active_sh_degree=None) -> RenderOutput:
    """Renders ``scene`` from ``camera``; never returns a truncated image.

    Args:
      scene: the splats (C slots).
      camera: the view (H = camera.height, W = camera.width).
      config: static options (:class:`RenderConfig`).
      capacity: optional starting capacity; by default the exact need counted for this view (one
        small jitted count, :data:`count_pairs`). A caller rendering many views of one size can pass
        the capacity that fitted the last one instead (:meth:`Capacity.fit` of its ``pairs_needed``).
      active_sh_degree: optional int, SH bands above it are ignored.
    Returns:
      :class:`RenderOutput` with (H, W) images. If the capacity overflows it is grown to fit and the
      view rendered again (a warning says so, once per growth). Differentiable with ``jax.grad``
      (outside ``jax.jit``; under an outer jit use :data:`render_jit` and check ``overflow``).
    """
    cap = capacity
    if cap is None:
        try:
            needed, max_tile = count_pairs(lax.stop_gradient(scene), camera, config)
            cap = Capacity.fit(float(needed))
        except jax.errors.ConcretizationTypeError:
            cap = Capacity()
    for _ in range(4):
        out = render_jit(scene, camera, config=config, capacity=cap,
                         active_sh_degree=active_sh_degree)
        try:
            overflowed = bool(out.overflow)
        except jax.errors.ConcretizationTypeError:
            return out  # traced under an outer jit: the caller checks `overflow`
        if not overflowed:
            return out
        new = Capacity.fit(float(out.pairs_needed), minimum=cap)
        warnings.warn(f"render: capacity {cap} too small for this view (needs {int(out.pairs_needed)} "
                      f"(splat, tile) pairs); growing to {new} and rendering again.", stacklevel=2)
        cap = new
    raise RuntimeError("render: capacity did not converge; this is a bug, please report it.")


if __name__ == "__main__":
    # python -m patexgs_jax.render is the command line (frames and videos of a trained model). It runs
    # by name, not by import: the command line imports the data sources and the trainer's method
    # table, which import this module, so an import here would close a circle through them.
    import runpy

    runpy.run_module("patexgs_jax.render_cli", run_name="__main__", alter_sys=True)
