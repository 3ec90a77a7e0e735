"""``python -m patexgs_jax.train``: the training command line (:mod:`patexgs_jax.training.cli`).

The training code lives in :mod:`patexgs_jax.training`. This module exists because ``python -m``
needs a module of this name; it re-exports the public training API, so ``from patexgs_jax.train
import TrainConfig, train`` keeps working. The package attribute ``patexgs_jax.train`` is the
:func:`~patexgs_jax.training.train` function (see ``patexgs_jax/__init__.py``), not this module.
"""

import sys

_STARTING = "stopped by SIGINT while starting; nothing was saved yet"

try:
    from .training import PRESETS, TrainConfig, TrainResult, preset_config, train
    from .training.cli import main
except KeyboardInterrupt:  # Ctrl-C while the training modules load (seconds): one line, no traceback
    if __name__ != "__main__":
        raise
    print(_STARTING, file=sys.stderr)
    sys.exit(130)

__all__ = ["PRESETS", "TrainConfig", "TrainResult", "main", "preset_config", "train"]

if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # Ctrl-C before the command line's own handler is installed (argument parsing)
        print(_STARTING, file=sys.stderr)
        sys.exit(130)
