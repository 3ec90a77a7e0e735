"""The dataset loaders' error and warning types."""

from __future__ import annotations

import warnings

__all__ = ["DatasetError", "DatasetWarning", "pycolmap_module", "warn"]


class DatasetError(ValueError):
    """A dataset cannot be loaded; the message names the offending file and how to fix it."""


class DatasetWarning(UserWarning):
    """Something in a dataset is unusual but was worked around (e.g. an empty point cloud)."""


def warn(msg: str) -> None:
    """Emits a :class:`DatasetWarning`."""
    warnings.warn(msg, DatasetWarning, stacklevel=3)


def pycolmap_module(purpose: str):
    """The pycolmap module, imported on first use (through :mod:`patexgs_jax._pycolmap`), so that
    the loaders that do not need it (the embedded scene's images, LLFF, ``transforms.json`` without
    distortion) work without it. ``purpose`` names what needs it, for the error where it is missing.

    Raises:
      DatasetError: pycolmap is not installed.
    """
    try:
        from .._pycolmap import pycolmap
    except ImportError as e:
        raise DatasetError(f"{purpose} needs pycolmap, which is not installed ({e}); install it with "
                           f"`pip install 'pycolmap>=4.0'`.") from None
    return pycolmap
