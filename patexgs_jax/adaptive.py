"""Adaptive texture sizes, the paper's Eqs. 6-10: Eq. 7 allocation, texel budgets, Eqs. 8-10 growth.

Everything here is host-side numpy, run between jitted training steps; every function is pure
(it returns new objects and never mutates its inputs). The textures themselves are re-bucketed to
new sizes by :mod:`patexgs_jax.textures.rebucket`.

Units and conventions
  * A Gaussian's texture *side* is an int n >= 1 (an n x n texture), 0 meaning "no texture".
  * The schedule keeps a real-valued size T_i (Eqs. 7 and 10) and uses
    ``side = clip(floor(T + 1/2), 1, max_size)`` (round half up) for the texture it allocates;
    a Gaussian with T = 0 has no texture. Because every Eq. 10 increment ``sqrt(g / tau_low)`` is
    > 1 (the Gaussian was selected with g > tau_low), every growth event adds at least one texel
    to the side, unless the side is already ``max_size``.
  * Budgets count *RGBA texels*: a Gaussian of side n holds n*n RGBA texels = an n x n RGB texture
    (3 floats a texel) plus an n x n alpha texture (1 float), i.e. ``FLOATS_PER_RGBA_TEXEL = 4``
    floats = 16 bytes a texel. :func:`patexgs_jax.metrics.mb_to_texels` converts MiB (``2**20``
    bytes, as :func:`patexgs_jax.metrics.storage_mb`) to such texels.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .metrics import texel_count

__all__ = [
    "ContributionCounts", "DEFAULT_MAX_SIZE", "GrowthSchedule", "SIGMA_PIXEL_SHARE", "SIGMA_SETTINGS",
    "TextureScheduleState", "contribution_sizes", "default_sigma", "eq7_sigma", "grow_sizes",
    "initial_texture_sizes", "pixel_share_sigma", "side_of", "sigma_setting", "solve_sigma_for_budget",
    "total_texels",
]

#: Default cap of Eq. 7 / Eq. 10 sizes.
DEFAULT_MAX_SIZE = 32


# =============================================================================================
# Eq. 7: initial sizes from contribution counts
# =============================================================================================
def default_sigma(height: int, width: int) -> float:
    """The paper's Eq. 7 sigma, ``H * W / 1e4`` for training images of H x W pixels (``--sigma paper``).

    It was set for Mip-NeRF 360 captures (about 200 views of about 1 MP) trained to about a million
    Gaussians; :func:`pixel_share_sigma` (``--sigma scene``, the default) keeps its meaning at other scales.
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height} x {width}.")
    return float(height) * float(width) / 1e4


#: Pixel-views per Gaussian at which Eq. 7 counts one unit of side, as a share of the fair share
#: ``total_pixels / num_gaussians`` (see :func:`pixel_share_sigma`).
SIGMA_PIXEL_SHARE = 0.5


def pixel_share_sigma(total_pixels: float, num_gaussians: int, share: float = SIGMA_PIXEL_SHARE) -> float:
    """Eq. 7 sigma from the scene's size: ``share * total_pixels / num_gaussians``.

    ``total_pixels`` is the sum of H * W over the training views, ``num_gaussians`` the active
    Gaussians: ``total_pixels / num_gaussians`` is a Gaussian's fair share of the pixel-views. Where
    ``S_ij << sigma``, ``T_i ~ sum_j S_ij / (sigma ln 2) = 2 f / ln 2`` for a Gaussian that dominates f
    times its fair share in all: the same T at any scale. With ``share = 0.5`` it equals the paper's
    ``H * W / 1e4`` at 200 views and 10^6 Gaussians (``0.5 * 200 H W / 10^6``); on a 128 x 96 scene of
    21 views and 3,900 Gaussians the paper's value (1.2) would give 43% of the Gaussians side >= 8 and
    99% of the texels to them (docs/tradeoffs.md, docs/paper.md).
    """
    if not total_pixels > 0 or num_gaussians < 1 or not share > 0:
        raise ValueError(f"need total_pixels > 0, num_gaussians >= 1 and share > 0, got {total_pixels}, "
                         f"{num_gaussians} and {share}.")
    return float(share) * float(total_pixels) / float(num_gaussians)


#: The named Eq. 7 sigma settings (``TrainConfig.sigma``, ``--sigma``; a positive number is the third).
SIGMA_SETTINGS = ("paper", "scene")


def sigma_setting(value) -> str | float:
    """An Eq. 7 sigma setting as ``TrainConfig.sigma`` keeps it: ``"paper"`` (:func:`default_sigma`),
    ``"scene"`` (:func:`pixel_share_sigma`) or a positive number (or its text, as ``--sigma`` gives it)."""
    if isinstance(value, str) and value.strip().lower() in SIGMA_SETTINGS:
        return value.strip().lower()
    try:
        x = float(value) if not isinstance(value, bool) else float("nan")
    except (TypeError, ValueError):
        x = float("nan")
    if not (np.isfinite(x) and x > 0):
        raise ValueError(f"sigma must be 'paper' (H x W / 1e4 of the training views, the paper's Eq. 7), 'scene' "
                         f"(half the training pixels a Gaussian) or a positive number, got {value!r}.")
    return x


def eq7_sigma(setting, view_pixels, num_gaussians: int) -> tuple[float, str]:
    """Eq. 7's sigma of a :func:`sigma_setting` and where it came from, for (V,) ``view_pixels`` (H * W
    of each training view) and ``num_gaussians`` active at the allocation: ``"paper"``, the views' (mean)
    ``H * W / 1e4``; ``"scene"``, :func:`pixel_share_sigma`; a number, itself. Returns (sigma, words)."""
    setting, P = sigma_setting(setting), np.asarray(view_pixels, np.float64).ravel()
    if setting == "paper":
        if P.size == 0 or not np.all(P > 0):
            raise ValueError("the paper's sigma needs the training views' sizes (H * W > 0 each).")
        return float(P.mean()) / 1e4, "the paper's H x W / 1e4"
    if setting == "scene":
        return pixel_share_sigma(float(P.sum()), int(num_gaussians)), "the pixel share"
    return float(setting), "given"


@dataclasses.dataclass(frozen=True, eq=False)
class ContributionCounts:
    """Eq. 6's counts S_ij of V views, kept sparse: only the non-zero ones.

    A Gaussian contributes the largest weight at pixels of a few of the views (a capture of 200
    views and a million Gaussians has a dense (V, C) matrix of 200M entries, 1.6 GB as float64, most
    of them zeros), and a zero adds nothing to Eq. 7's ``sum_j log2(1 + S_ij / sigma)``. Build it one
    view at a time with :meth:`from_views` (memory: 8 bytes a non-zero count) or from a dense matrix
    with :meth:`from_dense`; every Eq. 7 function takes either form.

    Attributes:
      values: (nnz,) float32, the non-zero S_ij, view by view (pixel counts: exact in float32 up to 2**24).
      index: (nnz,) int32 (int64 from 2**31 Gaussians), the Gaussian i of each (increasing within a view).
      offsets: (V + 1,) int64: view j's counts are ``values[offsets[j]:offsets[j + 1]]``.
      capacity: C.
    """

    values: np.ndarray
    index: np.ndarray
    offsets: np.ndarray
    capacity: int

    @property
    def num_views(self) -> int:
        return int(self.offsets.shape[0]) - 1

    @classmethod
    def from_views(cls, rows, capacity: int | None = None) -> ContributionCounts:
        """From an iterable of (C,) per-view counts (e.g. each view's ``max_contrib_count``)."""
        values, index, C = [], [], capacity
        for row in rows:
            r = np.asarray(row)
            if r.ndim != 1 or (C is not None and r.shape[0] != C):
                raise ValueError(f"each view's counts must have shape (C,) = ({C},), got {r.shape}.")
            C = r.shape[0]
            bad = r.dtype.kind not in "iuf" or (r.dtype.kind == "f" and not np.all(np.isfinite(r)))
            if bad or r.min(initial=0) < 0:
                raise ValueError("contrib_counts must be finite and non-negative (pixel counts S_ij).")
            nz = np.flatnonzero(r != 0)  # (on a boolean mask: a cheaper scan than the float counts)
            values.append(r[nz].astype(np.float32))
            index.append(nz.astype(np.int32 if C < 2**31 else np.int64))
        if C is None:
            raise ValueError("contrib_counts holds no view.")
        offsets = np.concatenate([[0], np.cumsum([v.size for v in values], dtype=np.int64)]).astype(np.int64)
        return cls(np.concatenate(values) if values else np.zeros(0, np.float32),
                   np.concatenate(index) if index else np.zeros(0, np.int32), offsets, int(C))

    @classmethod
    def from_dense(cls, S) -> ContributionCounts:
        """From a (V, C) matrix of counts."""
        S = np.asarray(S)
        if S.ndim != 2:
            raise ValueError(f"contrib_counts must have shape (num_images, C), got {S.shape}.")
        return cls.from_views(S, S.shape[1])

    def _views(self):
        for j in range(self.num_views):
            a, b = int(self.offsets[j]), int(self.offsets[j + 1])
            yield self.index[a:b], self.values[a:b]

    def columns(self, keep: np.ndarray) -> ContributionCounts:
        """The counts of the Gaussians ``keep`` (a sorted (M,) index array), renumbered 0..M-1."""
        pos = np.full(self.capacity, -1, np.int64)
        pos[keep] = np.arange(keep.size)
        new = pos[self.index]
        sel = new >= 0
        view_of = np.repeat(np.arange(self.num_views), np.diff(self.offsets))
        per_view = np.bincount(view_of[sel], minlength=self.num_views)
        offsets = np.concatenate([[0], np.cumsum(per_view)]).astype(np.int64)
        return ContributionCounts(self.values[sel], new[sel].astype(np.int32), offsets, int(keep.size))

    def column_sum(self) -> np.ndarray:
        """(C,) float64: ``sum_j S_ij``."""
        return np.bincount(self.index, weights=self.values, minlength=self.capacity)

    def column_max(self) -> np.ndarray:
        """(C,) float64: ``max_j S_ij`` (0 where never counted)."""
        out = np.zeros(self.capacity, np.float64)
        for idx, val in self._views():  # a Gaussian appears once a view: plain fancy indexing is exact
            out[idx] = np.maximum(out[idx], val)
        return out

    @functools.cached_property
    def _whole_counts(self) -> tuple[np.ndarray, int] | None:
        """(the counts as int32, their largest) where every count is a whole number (pixel counts are)
        and the largest is below their number (a table of logarithms no longer than the counts), else
        None."""
        top = float(self.values.max()) if self.values.size else 0.0
        if self.values.size == 0 or not top < min(self.values.size, 2**31 - 1):
            return None
        whole = self.values.astype(np.int32)
        return (whole, int(top)) if np.array_equal(whole, self.values) else None

    def sizes(self, sigma: float) -> np.ndarray:
        """(C,) float64 Eq. 7 real sizes ``T_i = sum_j log2(1 + S_ij / sigma)``.

        Pixel counts take few distinct values: the logarithm is taken once a value (0..the largest)
        and looked up, the same float64 operations on the same numbers as one a count, and far fewer
        of them at a million Gaussians (docs/performance.md)."""
        whole = self._whole_counts
        if whole is None:
            w = np.log2(1.0 + self.values.astype(np.float64) / float(sigma))
        else:
            w = np.log2(1.0 + np.arange(whole[1] + 1, dtype=np.float64) / float(sigma))[whole[0]]
        return np.bincount(self.index, weights=w, minlength=self.capacity)


def _as_counts(contrib_counts) -> ContributionCounts:
    if isinstance(contrib_counts, ContributionCounts):
        return contrib_counts
    return ContributionCounts.from_dense(contrib_counts)


def _check_counts(contrib_counts, active=None):
    S = _as_counts(contrib_counts)
    if active is None:
        act = np.ones(S.capacity, bool)
    else:
        act = np.asarray(active)
        if act.shape != (S.capacity,):
            raise ValueError(f"active must have shape (C,) = ({S.capacity},), got {act.shape}.")
        act = act > 0
    return S, act


def contribution_sizes(contrib_counts, sigma: float) -> np.ndarray:
    """Real-valued Eq. 7 sizes ``T_i = sum_j log2(1 + S_ij / sigma)``.

    Args:
      contrib_counts: (num_images, C) per-image max-contribution pixel counts S_ij (Eq. 6; the
        renderer's ``max_contrib_count`` of each training view stacked), or their
        :class:`ContributionCounts`.
      sigma: positive scale (see :func:`default_sigma`).
    Returns:
      (C,) float64.
    """
    S, _ = _check_counts(contrib_counts)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be positive and finite, got {sigma}.")
    return S.sizes(sigma)


def side_of(T, max_size: int = DEFAULT_MAX_SIZE, min_size: int = 1) -> np.ndarray:
    """Texture sides of real sizes: ``clip(floor(T + 1/2), min_size, max_size)``, 0 where T <= 0.

    Args:
      T: (C,) real sizes (0 or negative: no texture).
    Returns:
      (C,) int64.
    """
    T = np.asarray(T, np.float64)
    side = np.clip(np.floor(T + 0.5), min_size, max_size).astype(np.int64)
    return np.where(T > 0, side, 0)


def initial_texture_sizes(contrib_counts, sigma: float, *, max_size: int = DEFAULT_MAX_SIZE,
                          min_size: int = 1, active=None) -> np.ndarray:
    """Eq. 7 texture sides: ``clip(round_half_up(sum_j log2(1 + S_ij / sigma)), min_size, max_size)``.

    Every (active) Gaussian gets at least ``min_size`` (default 1), even with no contribution.

    Args:
      contrib_counts: (num_images, C) S_ij counts, or their :class:`ContributionCounts`.
      sigma: positive scale.
      max_size, min_size: bounds of the side (1 <= min_size <= max_size).
      active: optional (C,) mask; inactive Gaussians get side 0.
    Returns:
      (C,) int64 sides.
    """
    if not 1 <= min_size <= max_size:
        raise ValueError(f"need 1 <= min_size <= max_size, got {min_size}, {max_size}.")
    S, act = _check_counts(contrib_counts, active)
    side = np.clip(np.floor(contribution_sizes(S, sigma) + 0.5), min_size, max_size)
    return np.where(act, side, 0).astype(np.int64)


# =============================================================================================
# Budgets
# =============================================================================================
def total_texels(sides, active=None) -> int:
    """RGBA texels of an allocation: ``sum_i side_i^2`` over (active) Gaussians; sides (C,) ints."""
    s = np.asarray(sides, np.int64)
    if active is not None:
        s = s * (np.asarray(active) > 0)
    return texel_count(s)


def _log_budget_residual(log_sigma, args):
    """log(total texels at sigma) - log(target) on a column sample, the function bisected
    (module-level: compiled once a sample size)."""
    values, index, columns, fixed, log_target, min_size, max_size = args
    T = jax.ops.segment_sum(jnp.log2(1.0 + values / jnp.exp(log_sigma)), index, num_segments=columns.shape[0])
    side = jnp.clip(jnp.floor(T + 0.5), min_size, max_size)
    return jnp.log(jnp.sum(side * side) + fixed) - log_target


#: Gaussians the sigma search bisects over before it checks the result on all of them (a larger
#: scene is sampled: a random 65,536 of its contributing Gaussians give its total within ~1%).
SOLVE_SAMPLE = 1 << 16


def solve_sigma_for_budget(contrib_counts, target_texels: int, *, max_size: int = DEFAULT_MAX_SIZE,
                           min_size: int = 1, active=None, rtol: float = 0.01, max_steps: int = 200) -> float:
    """The Eq. 7 sigma whose rounded allocation holds ``target_texels`` RGBA texels (within rtol).

    ``total(sigma) = sum_i initial_texture_sizes(S, sigma)_i^2`` is a non-increasing step function
    of sigma; its root in ``log(total / target)`` over log sigma is found with
    ``optimistix.root_find`` and ``optimistix.Bisection`` on at most :data:`SOLVE_SAMPLE` of the
    contributing Gaussians (all of them in a smaller scene; a sample's target is the target's share
    of the sample), then checked on every Gaussian and, where the sample missed by more than
    ``rtol``, bisected further on all of them from there. Each step costs O(non-zero counts), never
    O(V C): at a million Gaussians and 200 views a few evaluations on all of them.

    Args:
      contrib_counts: (num_images, C) S_ij counts, or their :class:`ContributionCounts`.
      target_texels: wanted ``sum_i side_i^2`` (e.g. from :func:`patexgs_jax.metrics.mb_to_texels`).
      max_size, min_size, active: as in :func:`initial_texture_sizes`.
      rtol: relative tolerance on the total (default 1%).
    Returns:
      sigma (float).
    Raises:
      ValueError: the target is outside ``[min_total, max_total]`` (all Gaussians at ``min_size``;
        every contributing Gaussian at ``max_size``), or no sigma lands within ``rtol`` (the total
        jumps over the target, e.g. with very few Gaussians).
    """
    import optimistix as optx

    S, act = _check_counts(contrib_counts, active)
    target = float(target_texels)
    if not target > 0:
        raise ValueError(f"target_texels must be positive, got {target_texels}.")

    def total(sigma):
        return total_texels(initial_texture_sizes(S, sigma, max_size=max_size, min_size=min_size, active=act))

    col_sum = S.column_sum()
    contributing = act & (col_sum > 0)
    n_contrib, n_rest = int(contributing.sum()), int(np.sum(act & ~contributing))
    lo_total = int(np.sum(act)) * min_size**2
    hi_total = n_contrib * max_size**2 + n_rest * min_size**2
    if not lo_total * (1 - rtol) <= target <= hi_total * (1 + rtol):
        raise ValueError(f"target of {target_texels} texels is unreachable: the Eq. 7 allocation holds "
                         f"between {lo_total} (every Gaussian at side {min_size}) and {hi_total} texels "
                         f"(every contributing Gaussian at side {max_size}).")
    if not n_contrib:
        return 1.0
    # Bracket: at sigma_lo every contributing Gaussian has T >= max_size + 1/2; at sigma_hi all T < 1/2.
    s_min = S.column_max()[contributing].min()
    sigma_lo = s_min / (2.0 ** (max_size + 0.5) - 1.0) / 2.0
    sigma_hi = 4.0 * col_sum.max() / np.log(2.0) + 1.0
    # total(sigma_lo) = hi_total and total(sigma_hi) = lo_total: targets near the ends need no search.
    if abs(hi_total - target) <= rtol * target:
        return float(sigma_lo)
    if abs(lo_total - target) <= rtol * target:
        return float(sigma_hi)

    # The bisection on a sample of the contributing Gaussians (the others hold min_size^2 each).
    cols = np.flatnonzero(contributing)
    share = 1.0
    if cols.size > SOLVE_SAMPLE:
        share = SOLVE_SAMPLE / cols.size
        cols = np.sort(np.random.default_rng(0).choice(cols, SOLVE_SAMPLE, replace=False))
    sample = S.columns(cols)
    # Shapes padded to powers of two, so that scenes of similar sizes share one compiled bisection:
    # a padded count (0 at Gaussian 0) adds log2(1) = 0; a padded column holds min_size^2, taken off.
    nnz, m = _next_pow2(sample.values.size), _next_pow2(cols.size)
    values = np.zeros(nnz, np.float32)
    values[: sample.values.size] = sample.values
    index = np.zeros(nnz, np.int32)
    index[: sample.index.size] = sample.index
    fixed = share * n_rest * min_size**2 - (m - cols.size) * min_size**2
    args = (jnp.asarray(values), jnp.asarray(index), jnp.zeros(m, jnp.float32), jnp.float32(fixed),
            jnp.float32(np.log(share * target)), jnp.float32(min_size), jnp.float32(max_size))
    solver = optx.Bisection(rtol=0.0, atol=float(np.log1p(rtol)) / 4)
    y0 = jnp.float32(0.5 * (np.log(sigma_lo) + np.log(sigma_hi)))
    sol = optx.root_find(_log_budget_residual, solver, y0, args,
                         options=dict(lower=np.log(sigma_lo), upper=np.log(sigma_hi)),
                         max_steps=max_steps, throw=False)
    candidates = [float(np.exp(sol.value)), float(np.exp(sol.state.lower)), float(np.exp(sol.state.upper))]
    if share == 1.0:  # the whole scene: the bracket's ends are the closest sigmas found
        totals = [total(c) for c in candidates]
    else:  # a sample: its root, checked (and refined) on every Gaussian
        candidates, totals = candidates[:1], [total(candidates[0])]
        _refine(total, target, rtol, candidates, totals, np.log(sigma_lo), np.log(sigma_hi))
    best = int(np.argmin([abs(t - target) for t in totals]))
    if abs(totals[best] - target) > rtol * target:
        raise ValueError(f"no sigma gives {target_texels} texels within {rtol:.1%}: the allocation jumps "
                         f"from {max(totals)} to {min(totals)} texels near sigma = {candidates[best]:.6g} "
                         "(too few Gaussians for this tolerance?).")
    return candidates[best]


def _next_pow2(x: int) -> int:
    return 1 if x <= 1 else 1 << (int(x) - 1).bit_length()


def _refine(total, target: float, rtol: float, candidates: list, totals: list, log_lo: float, log_hi: float,
            max_evals: int = 40) -> None:
    """Bisects ``log sigma`` on the whole scene from the sample's root ``candidates[0]`` until a total
    is within ``rtol`` of ``target``, appending every sigma tried and its total. The bracket grows
    from the root by doubling steps (the sample's root is usually within 1% already: one evaluation)."""
    x = float(np.log(candidates[0]))
    if abs(totals[0] - target) <= rtol * target:
        return
    up = totals[0] > target  # too many texels: sigma must grow
    lo_, hi_ = (x, None) if up else (None, x)
    step = 0.01
    for _ in range(max_evals):
        if lo_ is not None and hi_ is not None:
            mid = 0.5 * (lo_ + hi_)
        else:
            mid = min(x + step, log_hi) if up else max(x - step, log_lo)
            step *= 2.0
        t = total(float(np.exp(mid)))
        candidates.append(float(np.exp(mid)))
        totals.append(t)
        if abs(t - target) <= rtol * target:
            return
        if t > target:
            lo_ = mid
        else:
            hi_ = mid
        if lo_ is not None and hi_ is not None and hi_ - lo_ < 1e-7:
            return


# =============================================================================================
# Eqs. 8-10: progressive growth
# =============================================================================================
@dataclasses.dataclass(frozen=True, kw_only=True)
class GrowthSchedule:
    """Eqs. 8-10 hyper-parameters.

    Attributes:
      t0, t_final: first and last growth iterations (t_final > t0).
      interval: grow every ``interval`` steps from t0 (:meth:`is_growth_step`).
      tau_preset: Eq. 9's initial threshold, in the units of the gradient statistic passed to
        :func:`grow_sizes` (2DGS measures it in NDC units; the renderer's ``screen_offset``
        gradient is in pixels, i.e. smaller by a factor of about W/2).
      max_size: largest texture side growth can reach.
    """

    t0: int
    t_final: int
    interval: int = 100
    tau_preset: float = 1e-5
    max_size: int = DEFAULT_MAX_SIZE

    def __post_init__(self):
        if not self.t_final > self.t0:
            raise ValueError(f"t_final ({self.t_final}) must be larger than t0 ({self.t0}).")
        if self.interval < 1 or self.max_size < 1:
            raise ValueError("interval and max_size must be >= 1.")
        if not self.tau_preset >= 0:
            raise ValueError(f"tau_preset must be >= 0, got {self.tau_preset}.")

    def is_growth_step(self, step: int) -> bool:
        """Whether ``step`` is in [t0, t_final] and a multiple of ``interval`` after t0."""
        return self.t0 <= step <= self.t_final and (step - self.t0) % self.interval == 0

    def tau_high(self, step: int, tau_max: float) -> float:
        """Eq. 9: ``tau_preset + r^3 (tau_max - tau_preset)``, ``r = clip((t - t0)/(t_final - t0), 0, 1)``."""
        r = min(max((step - self.t0) / (self.t_final - self.t0), 0.0), 1.0)
        return float(self.tau_preset + r**3 * (tau_max - self.tau_preset))


def grow_sizes(sizes_float, grad, step: int, schedule: GrowthSchedule, *, active=None,
               texel_budget: int | None = None):
    """One Eq. 8-10 growth event.

    Eligible Gaussians are active ones with a texture (T > 0). ``tau_max`` is the largest gradient
    among them; a Gaussian is selected when ``tau_low < g < tau_high`` (Eq. 8) and its side is below
    ``schedule.max_size``; its real size grows by ``sqrt(g / tau_low)`` (Eq. 10), capped at
    ``max_size``. With ``texel_budget`` (RGBA texels, ``sum side^2`` over active Gaussians), the
    selected Gaussians are taken in order of decreasing gradient and growth stops at the first
    one that would take the total above the budget.

    Args:
      sizes_float: (C,) real sizes T (0 = no texture).
      grad: (C,) non-negative position-gradient statistic (or (C, 2) per-axis values, whose norm
        is used).
      step: the iteration t.
      schedule: the :class:`GrowthSchedule`.
      active: optional (C,) mask.
      texel_budget: optional cap on the total texels after growth.
    Returns:
      ``(new_sizes_float (C,) float64, selected (C,) bool, tau_low, tau_high)``.
    """
    T = np.asarray(sizes_float, np.float64)
    if T.ndim != 1 or not np.all(np.isfinite(T)) or np.any(T < 0):
        raise ValueError("sizes_float must be a (C,) array of finite, non-negative sizes.")
    C = T.shape[0]
    g = np.asarray(grad, np.float64)
    if g.shape == (C, 2):
        g = np.linalg.norm(g, axis=1)
    if g.shape != (C,):
        raise ValueError(f"grad must have shape (C,) or (C, 2) with C = {C}, got {g.shape}.")
    if not np.all(np.isfinite(g)) or np.any(g < 0):
        raise ValueError("grad must be finite and non-negative.")
    act = np.ones(C, bool) if active is None else np.asarray(active) > 0
    if act.shape != (C,):
        raise ValueError(f"active must have shape ({C},), got {act.shape}.")
    eligible = act & (T > 0)
    tau_max = float(g[eligible].max()) if eligible.any() else 0.0
    tau_high = schedule.tau_high(step, tau_max)
    tau_low = 0.9 * tau_high
    side = side_of(T, schedule.max_size)
    sel = eligible & (g > tau_low) & (g < tau_high) & (side < schedule.max_size)
    new_T = T.copy()
    if sel.any():
        new_T[sel] = np.minimum(T[sel] + np.sqrt(g[sel] / tau_low), schedule.max_size)
    if texel_budget is not None and sel.any():
        new_side = side_of(new_T, schedule.max_size)
        order = np.flatnonzero(sel)[np.argsort(-g[sel], kind="stable")]
        extra = np.cumsum(new_side[order] ** 2 - side[order] ** 2)
        room = int(texel_budget) - total_texels(side, act)
        # extra is increasing (each selected side grows), so this is the longest fitting prefix.
        take = order[: int(np.searchsorted(extra, room, side="right"))]
        drop = np.setdiff1d(np.flatnonzero(sel), take)
        new_T[drop] = T[drop]
        sel = np.zeros(C, bool)
        sel[take] = True
    return new_T, sel, float(tau_low), float(tau_high)


@dataclasses.dataclass(frozen=True)
class TextureScheduleState:
    """Checkpointable state of the texture schedule.

    Attributes:
      sizes: (C,) float64 real sizes T (Eqs. 7 and 10); texture sides are :func:`side_of` them.
      last_growth_step: iteration of the last growth event (-1: none yet).
      num_growth_events: growth events run so far.
      num_grown: total selections over all events.
    """

    sizes: np.ndarray
    last_growth_step: int = -1
    num_growth_events: int = 0
    num_grown: int = 0

    @classmethod
    def create(cls, initial_sides) -> TextureScheduleState:
        """State starting from integer sides (C,), e.g. :func:`initial_texture_sizes`."""
        s = np.asarray(initial_sides)
        if s.ndim != 1 or np.any(s < 0):
            raise ValueError("initial_sides must be a (C,) array of non-negative sides.")
        return cls(sizes=s.astype(np.float64))

    def sides(self, max_size: int = DEFAULT_MAX_SIZE) -> np.ndarray:
        """(C,) int64 texture sides (round half up, clipped to [1, max_size], 0 for no texture)."""
        return side_of(self.sizes, max_size)

    def step(self, grad, step: int, schedule: GrowthSchedule, *, active=None,
             texel_budget: int | None = None):
        """Grows if ``schedule.is_growth_step(step)`` (else no change).

        Returns:
          ``(new_state, sides (C,) int64, selected (C,) bool)``; pass the sides to
          :func:`patexgs_jax.textures.rebucket.resize_textures` (for both banks) when ``selected.any()``.
        """
        if not schedule.is_growth_step(step):
            return self, self.sides(schedule.max_size), np.zeros(self.sizes.shape, bool)
        new_T, sel, _, _ = grow_sizes(self.sizes, grad, step, schedule, active=active,
                                      texel_budget=texel_budget)
        new = dataclasses.replace(self, sizes=new_T, last_growth_step=int(step),
                                  num_growth_events=self.num_growth_events + 1,
                                  num_grown=self.num_grown + int(sel.sum()))
        return new, new.sides(schedule.max_size), sel

    def to_dict(self) -> dict[str, Any]:
        """Plain numpy arrays and ints (for ``np.savez`` or a checkpoint's metadata)."""
        return {"sizes": np.asarray(self.sizes, np.float64), "last_growth_step": int(self.last_growth_step),
                "num_growth_events": int(self.num_growth_events), "num_grown": int(self.num_grown)}

    @classmethod
    def from_dict(cls, d) -> TextureScheduleState:
        """Inverse of :meth:`to_dict` (accepts 0-d arrays for the ints, as ``np.load`` returns)."""
        return cls(sizes=np.asarray(d["sizes"], np.float64), last_growth_step=int(d["last_growth_step"]),
                   num_growth_events=int(d["num_growth_events"]), num_grown=int(d["num_grown"]))

    def __eq__(self, other):
        if not isinstance(other, TextureScheduleState):
            return NotImplemented
        return (np.array_equal(self.sizes, other.sizes) and self.last_growth_step == other.last_growth_step
                and self.num_growth_events == other.num_growth_events and self.num_grown == other.num_grown)

    __hash__ = None  # pyright: ignore[reportAssignmentType]  (unhashable: it holds an array, compared by value)
