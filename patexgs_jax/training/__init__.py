"""Training: configuration, the jitted step, the host-side strategies, the run and its command line.

One module a concern:

- :mod:`.config`: :class:`TrainConfig`, the methods (:class:`Method`), the presets;
- :mod:`.step`: the jitted single-view and batched steps;
- :mod:`.strategies`: the strategy protocol, densification and the 3D filter, called between steps
  (the texture schedule, also a strategy, is :mod:`patexgs_jax.schedule`);
- :mod:`.steps`: the step provider, which runs the step: the tile capacity, which compiled step runs;
- :mod:`.compile_ahead`: the texture stage's first programs compiled in the background (a strategy);
- :mod:`.trainer`: the host loop (:class:`~.trainer.Trainer`);
- :mod:`.estimate`: the start line, the time estimate, the note on long runs;
- :mod:`.run`: :func:`train` (resume, stage-1 sharing, outputs);
- :mod:`.cli`: ``python -m patexgs_jax.train``.

The PSNR / SSIM a run reports come from :func:`patexgs_jax.evaluation.evaluate` (re-exported).
"""

from ..evaluation import evaluate
from .config import FIXED_SIZES, METHODS, PRESETS, Method, TrainConfig, preset_config
from .run import TrainResult, stage1_checkpoint, train

__all__ = [
    "FIXED_SIZES",
    "METHODS",
    "Method",
    "PRESETS",
    "TrainConfig",
    "TrainResult",
    "evaluate",
    "preset_config",
    "stage1_checkpoint",
    "train",
]
