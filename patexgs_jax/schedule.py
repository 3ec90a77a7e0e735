"""The texture schedule of PATexGS, host-side between jitted steps: :class:`TextureSchedule`.

What happens to the textures of a textured method over its texture stage (paper Sec. 3.2-3.3):

  1. Stage start (step ``iters_2dgs``): ``patexgs*`` give every Gaussian a 5x5 alpha texture (ones)
     and a 1x1 RGB offset (zeros), so the first render equals the 2DGS one; ``fixed`` methods give
     every Gaussian its N x N RGBA texture (:meth:`TextureSchedule.start`).
  2. Warm-up end (step ``iters_2dgs + warmup_tex``): Eq. 6's max-contribution counts over every
     training view, then Eq. 7's sizes (:meth:`TextureSchedule.allocate`; sigma from the pixel
     share, the paper's H x W / 1e4 or a number, ``TrainConfig.sigma``, or solved for a texel budget).
  3. Growth events (every ``growth_interval`` steps from one interval after the allocation up to
     ``growth_stop`` of the stage, or its end for ``patexgs-literal``): Eqs. 8-10 select the Gaussians
     whose screen-space position gradient, averaged over the steps since the last event (the
     densification statistic; the paper takes it "at each iteration"), lies in Eq. 8's band
     ``(0.9 tau_high, tau_high)`` under Eq. 9's threshold, which rises from ``tau_preset`` to the
     largest gradient as ``r^3`` over the growth window, and grow their sides by Eq. 10
     (:meth:`TextureSchedule.after_step`). These departures are named in docs/paper.md.

The equations are the named functions of :mod:`patexgs_jax.adaptive` (``initial_texture_sizes``,
``solve_sigma_for_budget``, ``GrowthSchedule``, ``TextureScheduleState.step``); every size change
re-buckets the textures with their Adam moments (:mod:`patexgs_jax.textures.rebucket`), between
jitted steps, and a new bucket layout is the only reason the step recompiles.

A schedule is a strategy as gsplat's densification strategies are: ``before_step(state, step)``
before the step that starts at ``step`` and ``after_step(state, step)`` once ``step`` steps are
complete; each takes the :class:`TrainState` and returns the new one (the input is never mutated).
It keeps its own small state (the growth state, the texel budget, the events it logged), which the
trainer checkpoints. The training loop (:mod:`patexgs_jax.training`) calls it after densification.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from . import adaptive, padding
from . import densify as dens
from .metrics import mb_to_texels
from .render import RenderConfig
from .scene import Scene
from .textures.billboard_alpha import with_gaussian_alpha
from .textures.rebucket import add_textures, prepare_growth, resize_textures

if TYPE_CHECKING:  # the training package imports this module: no import at run time
    from .training.config import TrainConfig

__all__ = ["TEXTURE_HEADROOM", "TEXTURE_MIN_SPARE", "TextureSchedule", "TrainState", "growth_schedule",
           "growth_steps", "side_histogram"]

#: Free slots (a share of the count, a least number) a texture bucket gets when the layout is made
#: (the texture stage's start, the Eq. 7 allocation, a growth event that overflows a bucket):
#: ``max(headroom * count, min_spare)``, then rounded up to a power of two
#: (:func:`patexgs_jax.textures.rebucket.resize_textures`). An Eqs. 8-10 event grows a few dozen textures by
#: one texel a side, so most events fit and recompile nothing; spare slots cost their texels in the
#: atlas and the optimiser's update (docs/performance.md).
TEXTURE_HEADROOM, TEXTURE_MIN_SPARE = 0.25, 16


class TrainState(NamedTuple):
    """What the jitted step updates and the strategies rewrite between steps."""

    scene: Scene
    opt_state: Any
    stats: dens.DensifyStats


def growth_schedule(cfg: TrainConfig) -> adaptive.GrowthSchedule:
    """The Eqs. 8-10 schedule of a run: growth every ``growth_interval`` steps from one interval after
    the Eq. 7 allocation (step ``iters_2dgs + warmup_tex``) up to ``growth_stop`` of the texture stage
    (up to its last step for a method that grows to the end, ``patexgs-literal``)."""
    t0 = cfg.iters_2dgs + cfg.warmup_tex + cfg.growth_interval
    stop = 1.0 if cfg.spec.growth_to_end else cfg.growth_stop
    t_final = max(t0 + 1, cfg.iters_2dgs + int(stop * cfg.iters_tex))
    return adaptive.GrowthSchedule(t0=t0, t_final=t_final, interval=cfg.growth_interval, tau_preset=cfg.tau_preset,
                                max_size=cfg.max_texture_size)


def growth_steps(cfg: TrainConfig) -> list[int]:
    """The steps (completed steps, as ``after_step`` counts them) at which growth events run."""
    if not cfg.spec.grows:
        return []
    g = growth_schedule(cfg)
    return [t for t in range(g.t0, min(g.t_final, cfg.total_steps) + 1) if g.is_growth_step(t)]


def _texels(sides, active) -> int:
    """Texels of RGB and alpha textures that share their ``sides`` (C,): ``2 sum n^2`` over the active
    Gaussians. "Texels" counts an RGB texel and an alpha texel as one each, everywhere the project
    reports them (logs, ``summary.json``, ``results.json``, tables); a budget's RGBA texel (the unit of
    :func:`patexgs_jax.adaptive.total_texels` and ``texel_budget``) is two of them."""
    return 2 * adaptive.total_texels(sides, active)


def side_histogram(sides, active) -> dict:
    """``{side: number of active Gaussians with that texture side}`` (str keys, as JSON writes them)."""
    values, counts = np.unique(np.asarray(sides)[np.asarray(active)].astype(int), return_counts=True)
    return {str(int(v)): int(c) for v, c in zip(values, counts)}


class TextureSchedule:
    """The texture stage of a textured method: textures at its start, the Eq. 6-7 allocation after
    the warm-up and the Eqs. 8-10 growth events (the equations: :mod:`patexgs_jax.adaptive`; the textures are
    re-bucketed by :mod:`patexgs_jax.textures.rebucket`). Does nothing for ``2dgs``.

    Its own state: ``state`` (the :class:`patexgs_jax.adaptive.TextureScheduleState`, None before the
    allocation), ``texel_budget`` (RGBA texels, or None), ``allocation`` and ``growth_events`` (what
    ``summary.json`` reports). ``log`` receives event records (``log.jsonl``), ``say`` progress lines.
    """

    def __init__(self, config: TrainConfig, optimizer, train_views, render_config: RenderConfig, *,
                 log: Callable[[dict], None] = lambda record: None, say: Callable[[str], None] = lambda msg: None,
                 programs: Callable[[Scene, int], dict | None] = lambda scene, step: None):
        self.cfg, self.spec, self.optimizer = config, config.spec, optimizer
        self.train_views, self.render_config = train_views, render_config
        self.log, self.say = log, say
        # Eq. 7's pair counter and renderer compiled ahead for a scene's layout (padding.ViewRenderer's
        # ``programs``), asked for at the allocation: the trainer passes its compile-ahead's claim.
        self.programs = programs
        self.schedule = growth_schedule(config)
        self.state: adaptive.TextureScheduleState | None = None
        self.texel_budget: int | None = None
        self.allocation: dict | None = None
        self.growth_events: list[dict] = []  # one dict per Eq. 8-10 event that grew textures

    def load(self, state: adaptive.TextureScheduleState | None, allocation: dict | None, growth_events) -> None:
        """Restores the strategy's state from a checkpoint."""
        self.state = state
        self.allocation = allocation
        self.growth_events = list(growth_events or [])
        if state is not None and self.cfg.texture_budget_mb is not None:
            self.texel_budget = mb_to_texels(self.cfg.texture_budget_mb)

    def before_step(self, state: TrainState, step: int) -> TrainState:
        cfg = self.cfg
        if self.spec.textures is not None and step == cfg.iters_2dgs and state.scene.rgb is None:
            state = self.start(state)
        if self.allocates_at(state, step):
            state = self.allocate(state, step)
        return state

    def allocates_at(self, state: TrainState, step: int) -> bool:
        """Whether :meth:`before_step` runs the Eq. 7 allocation at ``step``."""
        cfg = self.cfg
        return self.spec.textures == "adaptive" and self.state is None and step == cfg.iters_2dgs + cfg.warmup_tex

    def start(self, state: TrainState) -> TrainState:
        """Stage 2 starts: ``fixed`` methods get their N x N textures, the adaptive ones a 5x5 alpha
        texture (ones) and a 1x1 RGB offset (zeros), so the first render equals the 2DGS one.
        Billboards' alpha textures start as the 2DGS Gaussian instead
        (:mod:`patexgs_jax.textures.billboard_alpha`)."""
        scene, opt_state = state.scene, state.opt_state
        act = np.asarray(scene.active) > 0
        if self.spec.textures == "fixed":
            n = self.spec.size
            assert n is not None  # every "fixed" method has a size (Method.from_name)
            sizes = np.where(act, n, 0)
            scene, opt_state, _ = add_textures(scene, opt_state, self.optimizer, sizes, sizes,
                                               headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
            self.say(f"[stage 2] every Gaussian gets a {n}x{n} RGBA texture")
        else:
            scene, opt_state, _ = add_textures(scene, opt_state, self.optimizer, np.where(act, 1, 0),
                                               np.where(act, 5, 0), headroom=TEXTURE_HEADROOM,
                                               min_spare=TEXTURE_MIN_SPARE)
            self.say(f"[stage 2] 5x5 alpha + 1x1 RGB textures; warm-up {self.cfg.warmup_tex} steps")
        if self.spec.coverage == "billboard":
            scene = with_gaussian_alpha(scene, act)
        return TrainState(scene, opt_state, dens.DensifyStats.zeros(state.scene.capacity))

    def allocate(self, state: TrainState, step: int) -> TrainState:
        """Eqs. 6-7 at ``step``: contribution counts over all training views -> initial sizes (or
        N x N for every Gaussian, ``patexgs-fixed-N``)."""
        scene = state.scene
        with padding.ViewRenderer(scene, self.render_config, programs=self.programs(scene, step)) as renderer:
            renderer.prepare([v.camera for v in self.train_views])
            # Kept sparse, one view at a time: a dense (views, C) stack is GBs at the paper's scale.
            counts = adaptive.ContributionCounts.from_views(
                (np.asarray(renderer(v.camera).max_contrib_count) for v in self.train_views), scene.capacity)
        act = np.asarray(scene.active) > 0
        sides, sigma, budget = self.allocation_sides(counts, act)
        sigma_from = self.sigma_from(act) if sigma is not None else None
        self.state = adaptive.TextureScheduleState.create(sides)
        scene, opt_state, _ = resize_textures(scene, state.opt_state, sides, sides, headroom=TEXTURE_HEADROOM,
                                              min_spare=TEXTURE_MIN_SPARE)
        if self.spec.grows and self.spec.size is None:  # the growth events' programs, compiled meanwhile
            prepare_growth(scene, headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
        self.texel_budget = budget
        self.allocation = dict(step=step, sigma=None if sigma is None else float(sigma), sigma_from=sigma_from,
                               texels=_texels(sides, act), budget_texels=None if budget is None else 2 * budget,
                               sides=side_histogram(sides, act))
        self.log(dict(event="allocation", **self.allocation))
        n = self.spec.size
        how = f"{n}x{n} for every Gaussian" if sigma is None else f"Eq. 7, sigma {sigma:.4g} from {sigma_from}"
        self.say(f"[stage 2] allocation ({how}): sides {np.bincount(sides[act]).nonzero()[0].tolist()}, "
                 f"{_texels(sides, act)} texels")
        return TrainState(scene, opt_state, dens.DensifyStats.zeros(scene.capacity))

    def allocation_sides(self, S, act: np.ndarray) -> tuple[np.ndarray, float | None, int | None]:
        """Eq. 7's texture sides from the contribution counts ``S`` ((V, C), or their
        :class:`patexgs_jax.adaptive.ContributionCounts`) of the active Gaussians
        ``act`` (C,): (sides (C,) int64, sigma (None for ``patexgs-fixed-N``), the texel budget or
        None). Pure: also what a speculative allocation compiles ahead for
        (:meth:`patexgs_jax.training.compile_ahead.CompileAhead.prepare`)."""
        cfg = self.cfg
        if self.spec.size is not None:  # patexgs-fixed-N: the same schedule with one size for all
            return np.where(act, self.spec.size, 0).astype(np.int64), None, None
        budget = None
        if cfg.texture_budget_mb is not None:
            budget = mb_to_texels(cfg.texture_budget_mb)
            # Eq. 7 spends its share (at least one texel a Gaussian), growth the rest.
            target = max(int(round(cfg.budget_eq7_share * budget)), int(act.sum()))
            sigma = adaptive.solve_sigma_for_budget(S, target, max_size=cfg.max_texture_size, active=act)
        else:
            sigma = self._sigma(act)[0]
        return adaptive.initial_texture_sizes(S, sigma, max_size=cfg.max_texture_size, active=act), sigma, budget

    def _sigma(self, act: np.ndarray) -> tuple[float, str]:
        """Eq. 7's sigma without a budget (``TrainConfig.sigma_setting``) and where it came from."""
        pixels = [v.camera.height * v.camera.width for v in self.train_views]
        return adaptive.eq7_sigma(self.cfg.sigma_setting, pixels, int(act.sum()))

    def sigma_from(self, act: np.ndarray) -> str:
        """Where the allocation's sigma came from, as the allocation line and ``summary.json`` say it:
        ``"the paper's H x W / 1e4 (H x W = 96 x 128)"``, ``"the pixel share"``, ``"given"`` or the budget."""
        if self.cfg.texture_budget_mb is not None:
            return f"the {self.cfg.texture_budget_mb:g} MiB texel budget"
        how = self._sigma(act)[1]
        if self.cfg.sigma_setting == "paper":
            sizes = sorted({f"{v.camera.height} x {v.camera.width}" for v in self.train_views})
            how += f" (H x W = {', '.join(sizes)})"
        return how

    def after_step(self, state: TrainState, step: int) -> TrainState:
        """An Eqs. 8-10 growth event at the schedule's growth steps (``patexgs`` sizes only); the
        gradient statistics restart after each."""
        if step <= self.cfg.iters_2dgs or self.state is None or self.spec.size is not None:
            return state
        if not self.schedule.is_growth_step(step):
            return state
        scene, opt_state = state.scene, state.opt_state
        grad = state.stats.mean_grad()
        act = np.asarray(scene.active) > 0
        before = self.state.sides(self.cfg.max_texture_size)
        self.state, sides, sel = self.state.step(grad, step, self.schedule, active=act,
                                                 texel_budget=self.texel_budget)
        if sel.any():
            # (the trainer drops the old state: the kept layout is written in place)
            scene, opt_state, info = resize_textures(scene, opt_state, sides, sides, headroom=TEXTURE_HEADROOM,
                                                     min_spare=TEXTURE_MIN_SPARE, donate=True)
            # (layout_changed: a bucket overflowed and was sized afresh; the step recompiles)
            if info.shapes_changed and step + self.schedule.interval <= self.schedule.t_final:
                prepare_growth(scene, headroom=TEXTURE_HEADROOM, min_spare=TEXTURE_MIN_SPARE)
            event = dict(step=step, grown=int(np.sum(sides[act] > before[act])),
                         texels_added=_texels(sides, act) - _texels(before, act), texels=_texels(sides, act),
                         layout_changed=bool(info.shapes_changed))
            self.growth_events.append(event)
            self.log(dict(event="growth", **event))
            grew = f"{event['grown']} Gaussian{'' if event['grown'] == 1 else 's'} grew"
            self.say(f"[stage 2] Eq. 8-10 growth at step {step}: {grew}, "
                     f"+{event['texels_added']} texels ({event['texels']} in all)")
        return TrainState(scene, opt_state, dens.DensifyStats.zeros(scene.capacity))
