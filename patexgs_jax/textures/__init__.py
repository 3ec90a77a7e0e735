"""The texture bank family: per-Gaussian RGB and alpha textures in power-of-two buckets.

  :mod:`.bank`: :class:`TextureBank` (the storage: buckets, slots, sizes) and the mip pyramid's
  sizes and filter.
  :mod:`.atlas`: the flat texel atlas with the mip pyramids that the renderer builds inside jit, and
  its addressing and lookups.
  :mod:`.billboard_alpha`: the alpha textures billboards start from (the 2DGS Gaussian, sampled).
  :mod:`.rebucket`: banks resized or created with their Adam moments, between jitted steps (texture
  growth, the schedule of :mod:`patexgs_jax.schedule`).
"""

from .atlas import (
    Atlas,
    bilinear,
    build_atlas,
    corners,
    gather_corners,
    level_address,
    mip_level,
    mip_level_log2,
)
from .bank import TextureBank, bucket_of, downsample_matrix, mip_level_sizes

__all__ = [
    "Atlas",
    "TextureBank",
    "bilinear",
    "bucket_of",
    "build_atlas",
    "corners",
    "downsample_matrix",
    "gather_corners",
    "level_address",
    "mip_level",
    "mip_level_log2",
    "mip_level_sizes",
]
