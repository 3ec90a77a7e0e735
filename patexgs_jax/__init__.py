"""patexgs_jax: PATexGS (textured 2D Gaussian splatting with adaptive textures and RGBA mipmaps) in JAX.

Conventions (cameras, kernel, textures, mip levels) are fixed in :mod:`patexgs_jax.render`.
"""

from typing import TYPE_CHECKING

# First, before JAX is imported: a Ctrl-C in `python -m patexgs_jax...`'s first second (see _startup).
from . import _startup  # noqa: F401  (installs on import)
from .camera import Camera, look_at
from .render import Capacity, RenderConfig, RenderOutput, render, render_jit
from .scene import Scene, random_scene
from .textures import TextureBank

if TYPE_CHECKING:  # imported on first use (see __getattr__)
    from .training import TrainConfig, TrainResult, train

__all__ = [
    "Camera",
    "TrainConfig",
    "TrainResult",
    "Capacity",
    "RenderConfig",
    "RenderOutput",
    "Scene",
    "TextureBank",
    "look_at",
    "random_scene",
    "render",
    "render_jit",
    "train",
]

_LAZY = ("train", "TrainConfig", "TrainResult")


def __getattr__(name):
    # Training pulls in optax, scipy and the data loaders: imported on first use, from the training
    # package. The module patexgs_jax.train (the command line) is not imported, so this attribute is
    # the function and `python -m patexgs_jax.train` stays free of runpy's double-import warning.
    if name in _LAZY:
        from . import training

        for n in _LAZY:
            globals()[n] = getattr(training, n)
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
