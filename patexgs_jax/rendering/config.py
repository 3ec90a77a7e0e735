"""The renderer's settings and outputs: constants, :class:`RenderConfig`, :class:`Capacity` and
:class:`RenderOutput`. The conventions they refer to are fixed in :mod:`patexgs_jax.render`."""

from __future__ import annotations

import dataclasses
import math

import jax

#: RenderConfig.mip: level 0 only, the paper's Eq. 11 level, or a blend of the two nearest levels.
MIP_MODES = ("none", "nearest", "trilinear")
#: RenderConfig.coverage: the 2DGS low-pass kernel, the prefiltered (EWA) kernel, the billboard
#: square (:mod:`.billboard`), and two readings of the paper's Eq. 13 (docs/zoom_out.md): Eq. 2's
#: object-space Gaussian alone, and the Gaussian times the alpha texture on the texel grid.
COVERAGE_MODES = ("lowpass", "prefilter", "billboard", "object", "texel-grid")
#: The modes the Pallas kernel does not composite (the XLA compositor renders them).
XLA_ONLY_COVERAGE = ("billboard", "object", "texel-grid")
#: RenderConfig.compositor: the XLA compositor (:mod:`.composite`) or the Pallas GPU kernel
#: (:mod:`.pallas_composite`); None picks per backend (:func:`resolve_compositor`).
COMPOSITORS = ("xla", "pallas")
#: What ``RenderConfig(compositor=None)`` picks on a GPU: the Pallas kernel, which is faster than the
#: XLA compositor on a GPU in every configuration benchmarked (docs/benchmarks.md, the compositor as one
#: Pallas kernel); the CPU always takes "xla" (the kernel runs there only in Pallas's interpreter).
GPU_DEFAULT_COMPOSITOR = "pallas"
#: Eq. 11's lambda_mip per coverage mode when RenderConfig.lambda_mip is None (see RenderConfig).
LAMBDA_MIP_DEFAULT = {"lowpass": 0.4, "prefilter": 1.0 / 6.0, "billboard": 0.4 / 3.0, "object": 0.4,
                      "texel-grid": 0.4}
ALPHA_MAX = 0.99  # a pair's alpha is capped here
ALPHA_MIN = 1.0 / 255.0  # pairs below this alpha are skipped (with the prefilter, times the coverage)
T_MIN = 1e-4  # compositing stops before the first pair that would bring transmittance below this
#: With the prefilter, a splat's kernel is cut outside d^T S^-1 d <= SUPPORT_Q on screen (S its
#: filtered screen covariance, d the offset from its centre): twice the radius where a fully opaque
#: splat's kernel falls to 1/255 (see :func:`projection.project`).
SUPPORT_Q = 4.0 * 2.0 * math.log(255.0)


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Static rendering options (hashable; a new value compiles a new renderer).

    Attributes:
      coverage: how a splat covers a pixel. "lowpass" (default): the 2DGS kernel
        ``exp(-0.5 min(rho3d, 2 |x - mu2d|^2))``, which keeps a sub-pixel splat about a pixel wide
        at its full opacity (the paper's literal Eqs. 11-13 and the 2DGS baselines). "prefilter":
        the splat-plane Gaussian convolved with a Gaussian pixel filter of variance
        ``pixel_var`` (px^2), mapped onto the plane at the splat's centre (EWA resampling), with
        the opacity scaled so that the splat's integrated coverage is kept: a splat smaller than a
        pixel fades instead of growing (the PATexGS methods' mode). "billboard": G = 1 on the
        square ``|u|, |v| <= 3`` of the splat plane (the textures' span) and 0 outside, so the alpha
        texture alone shapes the splat (BBSplat's primitive, :mod:`.billboard`). "object": Eq. 13
        with Eq. 2's ``G = exp(-0.5 rho3d)`` as written, no screen-space low-pass (a sub-pixel splat
        is seen only by the pixel centres its plane ellipse holds). "texel-grid": the alpha
        texture times Eq. 2's G at its texel positions, so that the alpha pyramid holds ``G x A``
        and a coarse level the footprint's mean coverage, under the billboard square (2D splats,
        XLA compositor; docs/zoom_out.md measures both). For 3D Gaussians
        (:mod:`.gaussian3d`): "lowpass" is 3DGS's 0.3 px^2 dilation, "prefilter" Mip-Splatting's
        2D Mip filter of variance ``pixel_var`` (``min_var`` does not apply).
      pixel_var: the prefilter's pixel filter variance in px^2 (a box pixel has 1/12).
      min_var: with the prefilter, the smallest screen variance (px^2) of a filtered splat along
        any axis: where a splat is narrower, its filter is widened to reach it (its coverage still
        kept), so that a sub-pixel splat's summed alpha does not depend on where it falls between
        pixel centres (within 3%; with 0, the filter is ``pixel_var`` everywhere and a 0.1-pixel
        splat's summed alpha varies from 0.6 to 1.1 times its coverage as it moves).
      mip: "none" (level 0 only), "nearest" (paper Eq. 11, default) or "trilinear".
      lambda_mip: the paper's lambda_mip in Eq. 11; None takes the coverage mode's value
        (:data:`LAMBDA_MIP_DEFAULT`). D is in the primitive's own scale units and the paper's 0.4 a
        value in them (docs/zoom_out.md): 0.4 for "lowpass", "object" and "texel-grid"; 0.4 / 3 for
        "billboard", the paper's 0.4 on BBSplat's D, whose scale unit is 3 of ours; 1/6 for
        "prefilter", a calibration that makes ``lambda n D`` the texels per pixel of a texture
        spanning 6 scale units.
      rgb_mip: use mipmaps for the RGB textures (False: level 0 always; paper Table 3 ablation).
      alpha_mip: use mipmaps for the alpha textures (paper Eq. 13).
      background: RGB colour behind everything.
      near: near-plane depth; splats whose centre, or pairs whose intersection, is not beyond it are
        skipped.
      tile_size: tile side in pixels.
      chunk: splats evaluated together per tile step; a tile stops after the chunk in which all its
        pixels saturated (transmittance < 1e-4) or its list ended.
      tile_batch: at most this many tiles advanced together (sorted by list length, so they finish
        at similar steps; fewer when that spreads the tiles more evenly over the batches). None
        (default): chosen for the device when the render is traced (:mod:`.tiling`: 8 on a CPU;
        on a GPU every tile of the image where memory allows).
      texture_pairs: texture lookups per pass, as a share of a chunk step's (tile, pixel, splat)
        pairs. Only the pairs that can reach alpha 1/255 are looked up, gathered into as many
        passes of this size as they need (a few percent to a few tens of percent of the pairs
        contribute). Any value gives the same image; 1.0 looks up every pair without gathering
        them (the dense path, faster only for the forward of cheap lookups: one alpha bank
        without mipmaps).
      tile_cull: leave out the (splat, tile) pairs of a splat's screen box whose tile it cannot
        reach alpha 1/255 in (:func:`binning.tile_touches`): the same image and gradients (to
        float32 rounding), less compositing where footprints are large or unbounded on screen.
      compositor: "xla" (the chunked XLA compositor), "pallas" (one Pallas kernel per image, one
        program per tile: :mod:`.pallas_composite`; interpreted off a GPU; needs a power-of-two
        ``tile_size``) or None (default): per backend, "pallas" on a GPU (:data:`GPU_DEFAULT_COMPOSITOR`)
        and "xla" elsewhere (:func:`resolve_compositor`).
    """

    mip: str = "nearest"
    lambda_mip: float | None = None
    coverage: str = "lowpass"
    pixel_var: float = 0.1
    min_var: float = 0.3
    rgb_mip: bool = True
    alpha_mip: bool = True
    background: tuple = (0.0, 0.0, 0.0)
    near: float = 0.01
    tile_size: int = 16
    chunk: int = 32
    tile_batch: int | None = None
    texture_pairs: float = 1 / 32
    tile_cull: bool = True
    compositor: str | None = None

    def __post_init__(self):
        if self.mip not in MIP_MODES:
            raise ValueError(f"RenderConfig.mip must be one of {MIP_MODES}, got {self.mip!r}.")
        if self.coverage not in COVERAGE_MODES:
            raise ValueError(f"RenderConfig.coverage must be one of {COVERAGE_MODES}, got {self.coverage!r}.")
        lambda_mip = LAMBDA_MIP_DEFAULT[self.coverage] if self.lambda_mip is None else self.lambda_mip
        object.__setattr__(self, "lambda_mip", lambda_mip)
        if not self.pixel_var > 0:
            raise ValueError(f"pixel_var must be positive, got {self.pixel_var}.")
        if not self.min_var >= 0:
            raise ValueError(f"min_var must be >= 0, got {self.min_var}.")
        if not lambda_mip > 0:
            raise ValueError(f"lambda_mip must be positive, got {lambda_mip}.")
        if len(tuple(self.background)) != 3:
            raise ValueError("background must be an RGB triple.")
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))
        if self.tile_size < 1 or self.chunk < 1 or (self.tile_batch is not None and self.tile_batch < 1):
            raise ValueError("tile_size, chunk and tile_batch must be positive (tile_batch None: chosen "
                             "for the device).")
        if not self.near > 0:
            raise ValueError(f"near must be positive, got {self.near}.")
        if not 0 < self.texture_pairs <= 1:
            raise ValueError(f"texture_pairs must be in (0, 1], got {self.texture_pairs}.")
        if self.compositor is not None and self.compositor not in COMPOSITORS:
            raise ValueError(f"RenderConfig.compositor must be one of {COMPOSITORS} or None, got {self.compositor!r}.")
        if self.compositor == "pallas" and self.coverage in XLA_ONLY_COVERAGE:
            raise ValueError(f"compositor='pallas' composites the lowpass and prefilter kernels (2D splats and 3D "
                             f"Gaussians), not coverage {self.coverage!r}; use compositor='xla' (or None) for it.")
        if self.compositor == "pallas" and self.tile_size & (self.tile_size - 1):
            raise ValueError(f"compositor='pallas' needs a power-of-two tile_size (a tile's pixels are one "
                             f"power-of-two vector), got {self.tile_size}.")


def resolve_compositor(config: RenderConfig) -> str:
    """"xla" or "pallas": ``config.compositor``, or for None the default of the backend being traced
    for (:data:`GPU_DEFAULT_COMPOSITOR` on a GPU, "xla" elsewhere, and for what the kernel does not
    composite: billboards, tiles whose side is not a power of two)."""
    if config.compositor is not None:
        return config.compositor
    if config.coverage in XLA_ONLY_COVERAGE or config.tile_size & (config.tile_size - 1):
        return "xla"  # (what the kernel does not composite)
    return GPU_DEFAULT_COMPOSITOR if jax.default_backend() == "gpu" else "xla"


@dataclasses.dataclass(frozen=True)
class Capacity:
    """Static buffer size of the tile lists.

    Attributes:
      pairs: total (splat, tile) pairs that can be binned (the length of the sorted pair list).
    """

    pairs: int = 1 << 14

    @staticmethod
    def fit(pairs_needed, minimum: Capacity | None = None) -> Capacity:
        """The smallest power-of-two capacity (at least 1024, never below ``minimum``) that holds
        ``pairs_needed`` pairs."""
        v = max(int(math.ceil(float(pairs_needed))), minimum.pairs if minimum is not None else 1024, 1)
        return Capacity(pairs=1 << (v - 1).bit_length())


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderOutput:
    """What the renderer returns.

    Attributes:
      rgb: (H, W, 3) colour.
      alpha: (H, W) accumulated opacity, 1 - final transmittance.
      depth: (H, W) alpha-normalised expected intersection depth (0 where alpha is 0); for 3D
        Gaussians, of their centres' camera z (they have no ray intersection).
      normal: (H, W, 3) alpha-weighted camera-frame normals (facing the camera); for 3D Gaussians,
        of the axis of each one's smallest scale.
      distortion: (H, W) the 2DGS depth-distortion term sum_{i<j} w_i w_j (m_i - m_j)^2, m the
        depth mapped to [0, 1) by m = f/(f-n) (1 - n/z) with n = 0.2, f = 1000 (as 2DGS).
      max_contrib_count: (C,) int32, pixels at which each splat has the largest weight
        alpha_i T_i (paper Eq. 6); no gradient.
      dominant: (H, W) int32, the splat with the largest weight at each pixel (-1: none); no
        gradient (e.g. to look up per-pixel texture sizes or mip levels).
      radius_px: (C,) float, screen-space half-extent of each splat's footprint (0: not visible).
      visible: (C,) bool, binned into at least one tile.
      pairs_needed: () float32, (splat, tile) pairs of the splats' screen boxes: what the capacity
        must hold (``tile_cull`` then leaves some out of the lists).
      max_tile_count: () int32, the most screen boxes any tile is in (a statistic).
      overflow: () bool, some pair did not fit the capacity (the image is then truncated).
    """

    rgb: jax.Array
    alpha: jax.Array
    depth: jax.Array
    normal: jax.Array
    distortion: jax.Array
    max_contrib_count: jax.Array
    dominant: jax.Array
    radius_px: jax.Array
    visible: jax.Array
    pairs_needed: jax.Array
    max_tile_count: jax.Array
    overflow: jax.Array
