"""Training settings shared by the tests that train (test_train, test_ahead, the studies' tests)."""

from patexgs_jax.densify import DensifyConfig
from patexgs_jax.training.config import TrainConfig

#: The training tests' synthetic capture (tests/integration/conftest.py's ``synthetic_scene_dir``):
#: image width and height. 48 x 32 is 3 x 2 tiles of 16 pixels, one tile batch on a CPU: every
#: property the tests check (learning, densification, Eq. 7 allocation and growth, resumes) shows
#: there, and a tiny run takes a fifth less than at 64 x 48 (docs/performance.md).
SCENE_W, SCENE_H = 48, 32


def tiny_config(**kw) -> TrainConfig:
    """test_train's main run on its synthetic scene (:data:`SCENE_W` x :data:`SCENE_H`): 30 2DGS
    steps (densify at 3, 6, 9; the first doubles the capacity 512 -> 1024, capped at 700 Gaussians),
    then 24 texture steps (warm-up 3, allocation at 33, growth at 36, 39, ..., 48, textures up to
    6 x 6). ``kw`` overrides fields."""
    base = dict(method="patexgs", iters_2dgs=30, iters_tex=24, warmup_tex=3, growth_interval=3, growth_stop=0.75,
                max_texture_size=6, sh_interval=6, normal_from=8, checkpoint_every=3, log_every=3,
                max_gaussians=700,
                densify=DensifyConfig(start=2, stop=12, interval=3, prune_opacity=0.095,
                                      opacity_reset_interval=10_000))
    base.update(kw)
    return TrainConfig(**base)


#: The studies' tests (test_mipnerf360, test_mipnerf360_datasets): ``experiments.mipnerf360.run``'s
#: smallest protocol, 12 + 8 steps, at most 300 Gaussians, 2 test views; Eq. 7 allocation after 2
#: texture steps; no growth event (each re-bucketing compiles a step).
TINY_STUDY = dict(preset="tiny", iters_2dgs=12, iters_tex=8, max_gaussians=300, test_views=2,
                  train_overrides=dict(warmup_tex=2, growth_interval=100, max_texture_size=8, log_every=4,
                                       checkpoint_every=4))
