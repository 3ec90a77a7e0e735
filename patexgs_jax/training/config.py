"""What a training run depends on: :class:`TrainConfig`, the methods (:class:`Method`), the presets.

Field metadata sorts :class:`TrainConfig`'s fields, so the sets that stage-1 sharing, resuming and
:func:`preset_config` use are derived from the fields themselves, never listed by name elsewhere:
``stage2`` (only matters after the 2DGS stage), ``runtime`` (changes how a run executes, not what it
computes) and ``texture_schedule`` (scaled with an ``iters_tex`` override).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from .. import densify as dens
from ..adaptive import DEFAULT_MAX_SIZE, sigma_setting
from ..optim import LearningRates
from ..padding import PADDING_POLICIES
from ..render import RenderConfig

__all__ = [
    "CPU_PRESET",
    "FIXED_SIZES",
    "METHODS",
    "Method",
    "PRESETS",
    "RUNTIME_FIELDS",
    "STAGE2_FIELDS",
    "STAGE2_LR_FIELDS",
    "TEXTURE_SCHEDULE_FIELDS",
    "TrainConfig",
    "comparable_config",
    "default_preset",
    "config_dict",
    "effective_config",
    "equal_steps",
    "preset_config",
    "stage1_key",
    "stage1_part",
]

#: Texture sides of the ``textured-fixed-N`` baselines (Textured Gaussians' fixed sizes).
FIXED_SIZES = (1, 2, 4, 8, 16, 32)


@dataclasses.dataclass(frozen=True)
class Method:
    """What a ``--method`` name means.

    Attributes:
      textures: None (2DGS); "fixed" (every Gaussian gets ``size`` x ``size`` textures when stage 2
        starts); "adaptive" (the warm-up textures, then at the allocation step the Eq. 7 sizes and
        Eqs. 8-10 growth, or, when ``size`` is set, ``size`` x ``size`` for every Gaussian and no
        growth: ``patexgs-fixed-N``, which differs from ``patexgs`` in the sizes only).
      size: the fixed texture side, or None.
      mip, rgb_mip, alpha_mip, coverage: the stage-2 :class:`RenderConfig` fields (the ``patexgs``
        family prefilters, the ``bbsplat`` family renders billboards, the other baselines and
        ``patexgs-literal`` keep the 2DGS low-pass).
      primitive: "2d" (2DGS splats) or "3d": 3D Gaussians from the first step (``3dgs``,
        ``mip-splatting``; untextured, their own render config in both stages, no normal loss).
      filter3d: Mip-Splatting's 3D smoothing filter (:mod:`patexgs_jax.filter3d`).
      prune_opacity: the method's own densification prune threshold (3DGS's 0.005), or None for
        ``TrainConfig.densify``'s.
      sigma: the method's Eq. 7 sigma setting where ``TrainConfig.sigma`` is None (``"scene"``;
        ``"paper"`` for ``patexgs-literal`` and ``patexgs-paper-sigma``).
      growth_to_end: Eqs. 8-10 grow up to the texture stage's last step (Eq. 9's t_final, "the ending
        iteration", read literally: ``patexgs-literal``) instead of ``TrainConfig.growth_stop`` of it.
    """

    textures: str | None = "adaptive"
    size: int | None = None
    mip: str = "nearest"
    rgb_mip: bool = True
    alpha_mip: bool = True
    coverage: str = "prefilter"
    primitive: str = "2d"
    filter3d: bool = False
    prune_opacity: float | None = None
    sigma: str = "scene"
    growth_to_end: bool = False

    @property
    def stage1_name(self) -> str:
        """The first stage's name after what it trains: ``"3DGS"`` (3D Gaussians) or ``"2DGS"``."""
        return "3DGS" if self.primitive == "3d" else "2DGS"

    @property
    def grows(self) -> bool:
        """Whether the method runs the Eq. 7 allocation with its sizes and Eqs. 8-10 growth."""
        return self.textures == "adaptive" and self.size is None

    @classmethod
    def from_name(cls, name: str) -> Method:
        """The method of a name: one of :data:`METHODS`, ``textured-fixed-N`` (N in
        :data:`FIXED_SIZES`) or ``patexgs-fixed-N`` (N in 1..32). Raises ValueError otherwise."""
        if name.startswith("patexgs-fixed-"):
            n = name.rsplit("-", 1)[1]
            if not n.isdigit() or not 1 <= int(n) <= DEFAULT_MAX_SIZE:
                raise ValueError(f"patexgs-fixed-N takes N in 1..{DEFAULT_MAX_SIZE}, got {name!r}.")
            return cls(size=int(n))
        if name.startswith("textured-fixed-"):
            n = name.rsplit("-", 1)[1]
            if not n.isdigit() or int(n) not in FIXED_SIZES:
                raise ValueError(f"textured-fixed-N takes N in {FIXED_SIZES}, got {name!r}.")
            return cls(textures="fixed", size=int(n), mip="none", coverage="lowpass")
        if name not in METHODS:
            raise ValueError(f"unknown method {name!r}; choose one of 2dgs, textured-fixed-N (N in "
                             f"{FIXED_SIZES}), patexgs-fixed-N (N in 1..{DEFAULT_MAX_SIZE}), "
                             f"{', '.join(n for n in METHODS if n != '2dgs')}.")
        return METHODS[name]

    def render_config(self, lambda_mip: float | None = None, background=(0.0, 0.0, 0.0)) -> RenderConfig:
        """The renderer's settings of the method's texture stage (also used to evaluate it)."""
        return RenderConfig(mip=self.mip, rgb_mip=self.rgb_mip, alpha_mip=self.alpha_mip, coverage=self.coverage,
                            lambda_mip=lambda_mip, background=tuple(background))


#: The methods with a plain name (the ``-fixed-N`` families are parsed by :meth:`Method.from_name`).
METHODS: dict[str, Method] = {
    "2dgs": Method(textures=None, mip="none", coverage="lowpass"),
    "patexgs": Method(),
    "patexgs-no-mip": Method(mip="none"),
    "patexgs-no-alpha-mip": Method(alpha_mip=False),
    "patexgs-no-rgb-mip": Method(rgb_mip=False),
    "patexgs-no-adaptive": Method(textures="fixed", size=8),
    "patexgs-trilinear": Method(mip="trilinear"),
    # The paper read literally end to end (docs/paper.md): the 2DGS low-pass under Eq. 13, lambda_mip
    # 0.4 (the low-pass's default), sigma = H x W / 1e4 and growth through the stage's end.
    "patexgs-literal": Method(coverage="lowpass", sigma="paper", growth_to_end=True),
    "patexgs-paper-sigma": Method(sigma="paper"),
    # Baselines of the paper's Tables 1-2 (docs/baselines.md): BBSplat's billboards with its 16 x 16
    # RGBA textures, with our mipmaps, with our adaptive sizes; Textured Gaussians as textured-fixed-8.
    "bbsplat": Method(textures="fixed", size=16, mip="none", coverage="billboard"),
    "bbsplat+mip": Method(textures="fixed", size=16, mip="nearest", coverage="billboard"),
    "bbsplat+adaptive": Method(mip="none", coverage="billboard"),
    "textured-gaussians": Method(textures="fixed", size=8, mip="none", coverage="lowpass"),
    # 3D Gaussians (docs/baselines.md): 3DGS's 0.3 px^2 dilation; Mip-Splatting's 2D Mip and 3D filters.
    "3dgs": Method(textures=None, mip="none", coverage="lowpass", primitive="3d", prune_opacity=0.005),
    "mip-splatting": Method(textures=None, mip="none", coverage="prefilter", primitive="3d", filter3d=True,
                            prune_opacity=0.005),
    # PATexGS with Mip-Splatting's 3D filter in each splat's plane, throughout (its own stage 1; zoom-in).
    "patexgs+filter3d": Method(filter3d=True),
}


def _field(default, *, stage2: bool = False, runtime: bool = False, texture_schedule: bool = False):
    return dataclasses.field(default=default, metadata=dict(stage2=stage2, runtime=runtime,
                                                            texture_schedule=texture_schedule))


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a run depends on (saved in checkpoints and the summary).

    Attributes:
      method: a method name (:meth:`Method.from_name`; see :mod:`patexgs_jax.training.cli`).
      iters_2dgs, iters_tex: steps of the two stages (``iters_tex`` unused by ``2dgs``).
      continue_2dgs: untextured methods only (``2dgs``, ``3dgs``, ``mip-splatting``): steps that
        continue the first stage after ``iters_2dgs`` (its
        schedules as at the end of the stage: no densification, the final position learning rate).
        Set to ``iters_tex`` for a 2DGS baseline that trains as many steps as the textured methods
        (the studies do).
      warmup_tex: stage-2 warm-up steps before the Eq. 7 allocation (patexgs methods).
      growth_interval: steps between Eq. 8-10 growth events.
      growth_stop: fraction of stage 2 after which textures stop growing (t_final).
      tau_preset: Eq. 9's initial threshold (NDC gradient units, as densification).
      sigma: Eq. 7's sigma (``--sigma``): ``"scene"``, :func:`patexgs_jax.adaptive.pixel_share_sigma` of
        the training views and the Gaussians at the allocation (the paper's H * W / 1e4 at the paper's
        scale, the same meaning at other scales); ``"paper"``, the paper's H * W / 1e4 of the training
        views (:func:`patexgs_jax.adaptive.default_sigma`); or a positive number. None: the method's
        own (:attr:`Method.sigma`: ``"scene"``, but ``"paper"`` for ``patexgs-literal``).
      texture_budget_mb: optional texel budget (MiB of RGBA texels): sigma is solved so that the Eq. 7
        allocation spends ``budget_eq7_share`` of it, and growth (Eqs. 8-10) may spend the rest; the
        total never exceeds it.
      budget_eq7_share: the share of ``texture_budget_mb`` the Eq. 7 allocation spends (at least one
        texel per Gaussian); growth is left the rest.
      max_texture_size: largest texture side.
      lambda_dssim, lambda_normal, lambda_dist: loss weights; ``normal_from`` the first step of
        the normal-consistency term.
      sh_degree, sh_interval: final SH degree and steps per added band.
      densify: adaptive density control (stage 1).
      max_gaussians: cap on the number of Gaussians (budget runs); None for no cap.
      lr: learning rates.
      background: RGB behind the scene.
      lambda_mip: the paper's lambda_mip (Eq. 11); None: the coverage mode's calibrated value
        (:data:`patexgs_jax.render.LAMBDA_MIP_DEFAULT`).
      seed: seeds data order, initialisation and every random choice.
      checkpoint_every: steps between checkpoints (and one at the end of each stage and the run).
      log_every: steps between progress lines.
      checkpoint_on_stop: on SIGINT / SIGTERM (:mod:`patexgs_jax.interrupt`) a checkpoint is written
        when the newest is more than this many steps old (0: whenever a step was done since).
      max_bad_steps: consecutive non-finite steps that stop the run.
      init_opacity: opacity of initial Gaussians.
      batch_size: views per step (one Adam update from the mean of their gradients); 1 is the
        single-view step. B > 1 takes B consecutive views of the per-epoch permutations and splits
        them over ``devices`` (:mod:`patexgs_jax.parallel`); every training view must have the
        same image size.
      devices: devices the batch is split over (must divide ``batch_size``); None: as many as
        JAX sees that divide it. Unused when ``batch_size`` is 1.
      padding: the padded sizes the single-view step trains at (:mod:`patexgs_jax.padding`):
        "per-size" (each view at its own tile grid: a program per distinct grid and tile capacity),
        "one" (every view at the largest grid: a program per tile capacity; the tile capacity then
        grows with 2x headroom, so that one densification's doubling does not overflow it) or
        "auto" (default): "one" on a GPU or TPU, "per-size" on a CPU. The same result either way
        (to float rounding: tiles are batched differently); batches (``batch_size`` > 1) have one
        size already.
    """

    method: str = _field("patexgs", stage2=True)
    iters_2dgs: int = 30_000
    iters_tex: int = _field(30_000, stage2=True)
    continue_2dgs: int = _field(0, stage2=True)
    warmup_tex: int = _field(1_000, stage2=True, texture_schedule=True)
    growth_interval: int = _field(100, stage2=True, texture_schedule=True)
    growth_stop: float = _field(0.5, stage2=True)
    tau_preset: float = _field(1e-5, stage2=True)
    sigma: float | str | None = _field(None, stage2=True)
    texture_budget_mb: float | None = _field(None, stage2=True)
    budget_eq7_share: float = _field(0.8, stage2=True)
    max_texture_size: int = _field(32, stage2=True)
    lambda_dssim: float = 0.2
    lambda_normal: float = 0.05
    normal_from: int = 7_000
    lambda_dist: float = 0.0
    sh_degree: int = 3
    sh_interval: int = 1_000
    densify: dens.DensifyConfig = dens.DensifyConfig()
    max_gaussians: int | None = None
    lr: LearningRates = LearningRates()
    background: tuple = (0.0, 0.0, 0.0)
    lambda_mip: float | None = _field(None, stage2=True)
    seed: int = 0
    checkpoint_every: int = _field(2_000, stage2=True, runtime=True)
    log_every: int = _field(100, stage2=True, runtime=True)
    checkpoint_on_stop: int = _field(10, stage2=True, runtime=True)
    max_bad_steps: int = _field(20, stage2=True)
    init_opacity: float = 0.1
    batch_size: int = 1
    devices: int | None = _field(None, runtime=True)
    padding: str = _field("auto", runtime=True)

    def __post_init__(self):
        spec = Method.from_name(self.method)
        if self.batch_size < 1 or (self.devices is not None and self.devices < 1):
            raise ValueError(f"batch_size and devices must be >= 1, got {self.batch_size} and {self.devices}.")
        if self.padding not in PADDING_POLICIES:
            raise ValueError(f"padding must be one of {', '.join(PADDING_POLICIES)}, got {self.padding!r}.")
        if self.checkpoint_on_stop < 0:
            raise ValueError(f"checkpoint_on_stop must be >= 0, got {self.checkpoint_on_stop}.")
        if self.checkpoint_every < 1 or self.log_every < 1:
            raise ValueError(f"checkpoint_every and log_every must be >= 1, got {self.checkpoint_every} and "
                             f"{self.log_every}.")
        if self.iters_2dgs < 1 or self.iters_tex < 0:
            raise ValueError("iters_2dgs must be >= 1 and iters_tex >= 0.")
        if self.continue_2dgs < 0 or (self.continue_2dgs and spec.textures is not None):
            raise ValueError(f"continue_2dgs (steps that continue the first stage) must be >= 0 and is for the "
                             f"untextured methods only, got {self.continue_2dgs} with method {self.method!r}.")
        if not 0 < self.budget_eq7_share <= 1:
            raise ValueError(f"budget_eq7_share (the share of the texture budget Eq. 7 spends) must be in (0, 1], got "
                             f"{self.budget_eq7_share}.")
        if self.sigma is not None:
            object.__setattr__(self, "sigma", sigma_setting(self.sigma))
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}.")
        if self.growth_interval < 1 or self.warmup_tex < 0:
            raise ValueError(f"growth_interval must be >= 1 and warmup_tex >= 0, got {self.growth_interval} and "
                             f"{self.warmup_tex}.")
        if spec.textures == "adaptive" and self.warmup_tex >= self.iters_tex:
            raise ValueError(
                f"method {self.method!r} allocates its texture sizes (Eq. 7) after the {self.warmup_tex}-step "
                f"texture warm-up, but the texture stage has only {self.iters_tex} steps: the allocation would never "
                "happen. Give more texture steps (iters_tex, --iters-tex) or a shorter warm-up (warmup_tex); "
                "preset_config scales the warm-up with an iters_tex override.")

    @property
    def spec(self) -> Method:
        """The :class:`Method` of ``method``."""
        return Method.from_name(self.method)

    @property
    def sigma_setting(self) -> str | float:
        """Eq. 7's sigma setting of the run: ``sigma``, or the method's own where it is None."""
        return self.spec.sigma if self.sigma is None else self.sigma

    @property
    def total_steps(self) -> int:
        return self.iters_2dgs + (self.continue_2dgs if self.spec.textures is None else self.iters_tex)

    def in_stage1(self, step: int) -> bool:
        """Whether step ``step`` trains as the first stage (every step of an untextured method)."""
        return step < self.iters_2dgs or self.spec.textures is None

    def stage_name(self, step: int) -> str:
        """``"2DGS"`` (``"3DGS"`` for 3D Gaussians) or ``"textured"``: which step ``step`` runs."""
        return self.spec.stage1_name if self.in_stage1(step) else "textured"

    def view_index(self, step: int, num_views: int, seed: int | None = None) -> int:
        """The training view of ``step``, of ``num_views``: a per-epoch permutation seeded by (seed,
        epoch); ``seed`` defaults to the run's."""
        epoch, i = divmod(step, num_views)
        return int(np.random.default_rng([self.seed if seed is None else seed, epoch]).permutation(num_views)[i])

    def render_config(self, stage: int = 2) -> RenderConfig:
        """The renderer's settings in ``stage`` (1: the 2DGS stage, the same for every method so that
        it can be shared, but 3D methods' own; 2: the method's own, also used to evaluate the trained
        scene)."""
        if stage == 1 and self.spec.primitive == "2d":
            return RenderConfig(mip="none", background=tuple(self.background))
        return self.spec.render_config(lambda_mip=self.lambda_mip, background=self.background)


def _fields_with(key: str) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(TrainConfig) if f.metadata.get(key))


#: Fields that only matter after the 2DGS stage: runs that agree on every other field have the same
#: stage 1, which :func:`patexgs_jax.training.train` can take from another run's end-of-stage-1 checkpoint.
STAGE2_FIELDS = frozenset(_fields_with("stage2"))

#: Fields that change how a run executes, not what it computes: a run may resume (or take its stage 1
#: from a run) with other values of these.
RUNTIME_FIELDS = frozenset(_fields_with("runtime"))

#: Texture-stage fields that :func:`preset_config` scales with an ``iters_tex`` override.
TEXTURE_SCHEDULE_FIELDS = _fields_with("texture_schedule")


#: The ``cpu`` preset (see :data:`PRESETS`).
CPU_PRESET = dict(iters_2dgs=1_000, iters_tex=400, warmup_tex=40, growth_interval=25, growth_stop=0.8,
                  normal_from=500, sh_interval=250, log_every=50, checkpoint_every=250, max_gaussians=6_000,
                  densify=dens.DensifyConfig(start=100, stop=700, interval=50, opacity_reset_interval=10_000))

#: Named schedules. ``tiny``: minutes on a 2-core CPU (the embedded-scene default); ``small``: a
#: quick real-scene run; ``paper``: the 2DGS/PATexGS iteration counts (the TrainConfig defaults).
PRESETS = {
    # tiny: no opacity reset (it costs more steps to recover than the run has). Its texture stage is
    # long enough for every stage to act: warm-up, Eq. 7, then growth every 15 steps up to 80% of the
    # stage (8 events, each followed by training) and 40 steps after the last.
    "tiny": dict(iters_2dgs=600, iters_tex=200, warmup_tex=40, growth_interval=15, growth_stop=0.8,
                 normal_from=300, sh_interval=150, log_every=50, checkpoint_every=200, max_gaussians=4_000,
                 densify=dens.DensifyConfig(start=100, stop=450, interval=50, opacity_reset_interval=10_000)),
    # cpu: real captures downsampled to about 200-400 px (beer at --factor 4: 175 x 312) on a 2-core
    # CPU in at most about 30 minutes a method, sized from measured step times (docs/tradeoffs.md):
    # 6,000 Gaussians, 1,000 + 400 steps, 11 growth events.
    "cpu": CPU_PRESET,
    # small: no opacity reset either. A reset at 3,000 leaves densification (until 3,500) five events
    # to regrow what the next prune removes: beer at full size went from 54k to 11.6k Gaussians and
    # did not recover by step 7,000 (the log's PSNR 26.4 -> 24.7).
    "small": dict(iters_2dgs=7_000, iters_tex=5_000, warmup_tex=500, growth_interval=100, normal_from=3_500,
                  sh_interval=1_000, densify=dens.DensifyConfig(start=500, stop=3_500, interval=100,
                                                                opacity_reset_interval=10_000)),
    "paper": {},
}


def default_preset(data, backend: str | None = None) -> str:
    """The preset a run gets when none is named: ``tiny`` on the embedded scene (``data`` None:
    minutes on a 2-core CPU); for a capture, ``paper`` (30k + 30k steps) on a GPU or TPU and ``cpu``
    (1,000 + 400 steps) on a CPU, where the paper's steps take hours to days (the start line's
    estimate says how long). ``backend``: ``jax.default_backend()`` unless given."""
    if data is None:
        return "tiny"
    if backend is None:
        import jax

        backend = jax.default_backend()
    return "cpu" if backend == "cpu" else "paper"


def preset_config(preset: str = "paper", **overrides) -> TrainConfig:
    """A :class:`TrainConfig` from a named preset, with keyword overrides (None values ignored).

    An ``iters_tex`` override scales the preset's texture schedule (:data:`TEXTURE_SCHEDULE_FIELDS`:
    ``warmup_tex`` and ``growth_interval``, unless given too) with it, so that they keep their share
    of the stage and the warm-up, the Eq. 7 allocation and the growth events all still happen (the
    paper preset's 1,000-step warm-up would otherwise outlast a 600-step texture stage).
    :class:`TrainConfig` refuses a schedule whose warm-up leaves no room for Eq. 7.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}.")
    kw = dict(PRESETS[preset])
    given = {k: v for k, v in overrides.items() if v is not None}
    if "iters_tex" in given:
        base = kw.get("iters_tex", TrainConfig.iters_tex)
        f = given["iters_tex"] / base
        for name in TEXTURE_SCHEDULE_FIELDS:
            if name not in given:
                given[name] = max(1, round(f * kw.get(name, getattr(TrainConfig, name))))
    kw.update(given)
    return TrainConfig(**kw)


def equal_steps(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with every method training ``iters_2dgs + iters_tex`` steps, as the studies compare
    them: an untextured method (``2dgs``, ``3dgs``, ``mip-splatting``) continues its first stage for
    the texture stage's ``iters_tex`` steps (``continue_2dgs``); a textured one is unchanged."""
    if cfg.spec.textures is not None:
        return cfg
    return dataclasses.replace(cfg, continue_2dgs=cfg.iters_tex)


def effective_config(cfg: TrainConfig) -> TrainConfig:
    """The configuration a run of ``cfg`` trains with: ``cfg`` with its method's own settings in
    place of the general ones (the 3D methods' densification prune threshold, 3DGS's 0.005, and no
    normal-consistency loss: a 3D Gaussian has no surface normal). ``summary.json`` records it;
    checkpoints keep ``cfg`` as given (resuming compares what was asked for)."""
    spec, changes = cfg.spec, {}
    if spec.prune_opacity is not None:
        changes["densify"] = dataclasses.replace(cfg.densify, prune_opacity=spec.prune_opacity)
    if spec.primitive == "3d":
        changes["lambda_normal"] = 0.0
    return dataclasses.replace(cfg, **changes) if changes else cfg


def config_dict(cfg: TrainConfig) -> dict:
    """``cfg`` as checkpoints and ``summary.json`` save it (JSON types)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))


def comparable_config(saved: dict) -> dict:
    """A saved config as compared on resume: fields added since it was written take their defaults
    (which reproduce the older behaviour), and :data:`RUNTIME_FIELDS` are left out."""
    full = {**config_dict(TrainConfig()), **saved}
    return {k: v for k, v in full.items() if k not in RUNTIME_FIELDS}


#: Learning rates (fields of :class:`~patexgs_jax.optim.LearningRates`) that only act on textures,
#: which appear after the 2DGS stage: runs that differ in them share stage 1.
STAGE2_LR_FIELDS = ("texture_rgb", "texture_alpha")


def stage1_part(saved: dict) -> dict:
    """The part of a saved config that determines stage 1 (3D methods' and those with the 3D filter
    own: their method is part)."""
    part = {k: v for k, v in comparable_config(saved).items() if k not in STAGE2_FIELDS}
    if saved.get("method") in METHODS and (METHODS[saved["method"]].primitive == "3d"
                                           or METHODS[saved["method"]].filter3d):
        part["method"] = saved["method"]
    if isinstance(part.get("lr"), dict):
        part["lr"] = {k: v for k, v in part["lr"].items() if k not in STAGE2_LR_FIELDS}
    return part


def stage1_key(cfg: TrainConfig) -> dict:
    """The part of a config that determines stage 1 (JSON-able; equal keys, equal 2DGS stages)."""
    return stage1_part(config_dict(cfg))
