"""patexgs_jax: PATexGS (textured 2D Gaussian splatting with adaptive textures and RGBA mipmaps) in JAX.

Conventions (cameras, kernel, textures, mip levels) are fixed in :mod:`patexgs_jax.render`.
"""

# pycolmap's extension bundles and exports its own zlib; if it is loaded before the system zlib,
# later zlib users (PNG writing) corrupt the heap. Loading zlib first makes import order safe.
import zlib  # noqa: F401  (see patexgs_jax/data/__init__.py)

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
