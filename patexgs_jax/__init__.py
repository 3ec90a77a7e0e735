"""patexgs_jax: PATexGS (textured 2D Gaussian splatting with adaptive textures and RGBA mipmaps) in JAX.

Conventions (cameras, kernel, textures, mip levels) are fixed in :mod:`patexgs_jax.render`.
"""

from .camera import Camera, look_at
from .render import Capacity, RenderConfig, RenderOutput, render, render_jit
from .scene import Scene, random_scene
from .textures import TextureBank

__all__ = [
    "Camera",
    "Capacity",
    "RenderConfig",
    "RenderOutput",
    "Scene",
    "TextureBank",
    "look_at",
    "random_scene",
    "render",
    "render_jit",
]
