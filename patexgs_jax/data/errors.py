"""The dataset loaders' error and warning types."""

from __future__ import annotations

import warnings

__all__ = ["DatasetError", "DatasetWarning", "warn"]


class DatasetError(ValueError):
    """A dataset cannot be loaded; the message names the offending file and how to fix it."""


class DatasetWarning(UserWarning):
    """Something in a dataset is unusual but was worked around (e.g. an empty point cloud)."""


def warn(msg: str) -> None:
    """Emits a :class:`DatasetWarning`."""
    warnings.warn(msg, DatasetWarning, stacklevel=3)
