"""The counts a run plan makes before anything trains (:mod:`patexgs_jax.plan`): the Gaussians
the run plans for, the mean active count of its 2DGS stage, and the RGBA texels Eq. 7 gives at
that count (modelled contribution counts, the real functions of :mod:`patexgs_jax.adaptive`)."""

from __future__ import annotations

import numpy as np

from . import adaptive
from .metrics import mb_to_texels

__all__ = ["GROWTH_SHARE", "UNCAPPED_GAUSSIANS", "densify_events", "eq7_texels", "mean_stage1_gaussians",
           "planned_gaussians"]

#: Gaussians planned for when the run has no cap (``max_gaussians`` None): densification is then
#: bounded only by its gradient threshold, and 2DGS on the Mip-NeRF 360 scenes reaches 1 to several
#: million; ``--max-gaussians`` makes the count a cap.
UNCAPPED_GAUSSIANS = 3_000_000


def densify_events(config) -> list[int]:
    """The steps after which the 2DGS stage densifies, as the run's densification does
    (:class:`patexgs_jax.training.strategies.Densification`): ``densify.densify_at(t)``, strictly
    after ``start``, and before ``iters_2dgs`` (a study's untextured run does not densify in the
    steps it continues). A 150-step stage with ``start`` 100 and ``interval`` 50 has none."""
    return config.densify.densify_steps(config.iters_2dgs)


def planned_gaussians(config, num_points: int) -> tuple[int, str]:
    """The Gaussian count a run plans for and where it comes from.

    Args:
      config: the :class:`patexgs_jax.training.TrainConfig`.
      num_points: the initial point cloud's size.
    Returns:
      (count, a phrase saying which: the cap, or what densification may reach).
    """
    events = len(densify_events(config))
    densifies = events > 0
    cap = config.max_gaussians
    if cap is not None:
        if not densifies:
            n = min(cap, num_points)
            return n, f"the initial points, {num_points:,}, up to the cap {cap:,} (no densification in this schedule)"
        return cap, f"the cap (max_gaussians {cap:,}): densification fills it"
    if not densifies:
        return num_points, "the initial points (no densification in this schedule, no cap)"
    reach = num_points * 2.0 ** events  # each event at most doubles the count
    n = int(min(reach, UNCAPPED_GAUSSIANS))
    return n, (f"no cap: densification may reach {n:,} ({events} events from {num_points:,} points, "
               f"at most doubling each, bounded by the {UNCAPPED_GAUSSIANS:,} 2DGS reaches on the Mip-NeRF 360 "
               "scenes); --max-gaussians makes it a cap")


def mean_stage1_gaussians(config, num_points: int, gaussians: int) -> int:
    """The mean active Gaussian count over the first stage's steps: the initial points (at most
    ``gaussians``) until densification starts, rising linearly to ``gaussians`` by its last event
    (or the stage's end), then ``gaussians`` (a study's untextured runs continue at that count)."""
    dc, steps = config.densify, config.iters_2dgs
    p, n = min(int(num_points), int(gaussians)), int(gaussians)
    start, stop = min(dc.start, steps), min(dc.stop, steps)
    if stop <= start or not densify_events(config):
        return p
    extra = config.continue_2dgs if config.spec.textures is None else 0
    total = p * start + 0.5 * (p + n) * (stop - start) + n * (steps - stop) + n * extra
    return int(round(total / (steps + extra)))


def eq7_texels(view_pixels, gaussians: int, config) -> tuple[int, int, float | None, str]:
    """Eq. 7's RGBA texels at ``gaussians`` Gaussians, with the real functions of
    :mod:`patexgs_jax.adaptive`.

    Without a trained model the contribution counts are modelled: every Gaussian gets the same
    share of every view's pixels, ``S_ij = P_j / N`` (the counts of a view sum to its pixels). The
    runs in docs/memory.md allocate 6.5 (beer) to 14 (embedded scene) RGBA texels a Gaussian
    where this model gives 9: the sides are skewed (most 1, a few 32), the total is near.

    Args:
      view_pixels: (V,) pixels of each training view (unpadded).
      gaussians: N.
      config: the TrainConfig (method, sigma, texture_budget_mb, budget_eq7_share, max_texture_size).
    Returns:
      (RGBA texels after Eq. 7, RGBA texels the texture stage may reach with growth, sigma or None,
      how sigma was chosen).
    """
    spec = config.spec
    n = max(int(gaussians), 1)
    if spec.textures is None:
        return 0, 0, None, "no textures"
    if spec.size is not None:
        t = n * spec.size ** 2
        return t, t, None, f"{spec.size}x{spec.size} for every Gaussian"
    P = np.asarray(view_pixels, np.float64).reshape(-1, 1)
    S = P / n  # (V, 1): the one column every Gaussian shares
    if config.texture_budget_mb is not None:
        budget = mb_to_texels(config.texture_budget_mb)
        target = max(int(round(config.budget_eq7_share * budget)), n)
        return target, max(budget, target), None, (f"solved for {config.budget_eq7_share:.0%} of the "
                                                   f"{config.texture_budget_mb:g} MiB budget")
    sigma, how = adaptive.eq7_sigma(config.sigma_setting, P, n)  # (the paper's H x W / 1e4, the pixel share, given)
    side = int(adaptive.initial_texture_sizes(S, sigma, max_size=config.max_texture_size)[0])
    t = n * side ** 2
    return t, int(t * (1 + GROWTH_SHARE)), float(sigma), f"sigma {sigma:.4g} from {how}; side {side} a Gaussian"


#: Texels growth (Eqs. 8-10) adds to Eq. 7's without a budget: measured 2-4% on the cpu and tiny
#: presets (beer, the embedded scene); kept at 10% for longer schedules.
GROWTH_SHARE = 0.10
