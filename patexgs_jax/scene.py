"""The scene pytree: 2D (or 3D) Gaussians with fixed capacity, an active mask, and optional textures.

Parameters are stored unconstrained, as training optimises them:

* ``means`` (C, 3) world positions;
* ``log_scales`` (C, 2) log of the two tangent-axis scales (standard deviations); (C, 3) for a
  scene of 3D Gaussians (3DGS, Mip-Splatting): the scales along the rotation's three columns. The
  static shape decides the primitive (:attr:`Scene.is_3d`), so a 2D scene compiles as it always did;
* ``quats`` (C, 4) rotation quaternions (w, x, y, z), normalised when used; the splat's tangent
  axes are the rotation's first two columns and its normal the third;
* ``opacity_logits`` (C,) logit of the opacity;
* ``sh`` (C, K, 3) spherical-harmonics coefficients, K in {1, 4, 9, 16}; colour is
  ``max(SH(d) + 0.5, 0)`` with d the unit direction from the camera centre to the mean;
* ``active`` (C,) float 1.0 / 0.0: inactive slots are never rendered, so that adding or removing
  Gaussians keeps every array shape (and hence the compiled renderer);
* ``rgb`` / ``alpha``: optional :class:`~patexgs_jax.textures.TextureBank` of RGB offsets
  (added to the SH colour) and alpha multipliers (``alpha = min(0.99, opacity * G * A)``).
  A Gaussian without an RGB texture adds 0; without an alpha texture it multiplies by 1.
  3D scenes have no textures.
* ``filter3d``: optional (C,) Mip-Splatting's 3D smoothing filter, the variance f (world units^2)
  added to each Gaussian's covariance in all three axes (3D scenes), or in its plane for 2D splats
  (each scale s becomes sqrt(s^2 + f) in the Gaussian; textures keep their extent; textured splats
  need coverage "prefilter"), its opacity scaled so the integral is kept (:mod:`patexgs_jax.filter3d`);
  not trained (its gradient is zero).

Every leaf is a float array, so ``jax.grad`` of a loss of ``render(scene, ...)`` with respect to the
whole scene works directly; the mask and texture indices get zero gradient.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .math import sh_degree_of
from .textures import TextureBank

_OPACITY_EPS = 1e-7


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """N active Gaussians in a fixed capacity C (see the module docstring for the fields)."""

    means: jax.Array
    log_scales: jax.Array
    quats: jax.Array
    opacity_logits: jax.Array
    sh: jax.Array
    active: jax.Array
    rgb: TextureBank | None = None
    alpha: TextureBank | None = None
    filter3d: jax.Array | None = None

    # ----------------------------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, means, scales, quats, opacities, sh, rgb_textures=None, alpha_textures=None,
                    capacity: int | None = None, filter3d=None) -> Scene:
        """Builds a scene from activated values.

        Args:
          means: (N, 3) world positions.
          scales: (N, 2) positive scales of the two tangent axes, or (N, 3) for 3D Gaussians.
          quats: (N, 4) quaternions (w, x, y, z), non-zero.
          opacities: (N,) in [0, 1] (clipped to [1e-7, 1 - 1e-7] for the logit).
          sh: (N, K, 3) SH coefficients with K in {1, 4, 9, 16}, or (N, 3) for degree 0.
          rgb_textures: optional length-N list; entry i is None or an (n, n, 3) RGB offset texture,
            first index along the first tangent axis.
          alpha_textures: optional length-N list; entry i is None or an (m, m) alpha texture.
          capacity: fixed capacity C >= N (default N); slots beyond N are inactive.
          filter3d: optional (N,) 3D filter variances (see the module docstring).
        """
        means = np.asarray(means, np.float32)
        if means.ndim != 2 or means.shape[1] != 3:
            raise ValueError(f"means must have shape (N, 3), got {means.shape}.")
        n = means.shape[0]
        scales = np.asarray(scales, np.float32)
        quats = np.asarray(quats, np.float32)
        opacities = np.asarray(opacities, np.float32)
        sh = np.asarray(sh, np.float32)
        if sh.ndim == 2:
            sh = sh[:, None, :]
        dims = scales.shape[1] if scales.ndim == 2 and scales.shape[1] in (2, 3) else 2
        if dims == 3 and (rgb_textures is not None or alpha_textures is not None):
            raise ValueError("3D Gaussians (scales (N, 3)) take no textures; pass rgb_textures=None and "
                             "alpha_textures=None, or two scales per Gaussian for textured 2D splats.")
        for name, arr, shape in [("scales", scales, (n, dims)), ("quats", quats, (n, 4)),
                                 ("opacities", opacities, (n,))]:
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {arr.shape}.")
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"sh must have shape (N, K, 3) with N={n}, got {sh.shape}.")
        sh_degree_of(sh.shape[1])
        for name, arr in [("means", means), ("scales", scales), ("quats", quats),
                          ("opacities", opacities), ("sh", sh)]:
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} has non-finite values.")
        if np.any(scales <= 0):
            raise ValueError("scales must be positive (they are the activated, not log, values).")
        if np.any((opacities < 0) | (opacities > 1)):
            raise ValueError("opacities must lie in [0, 1] (activated values, not logits).")
        if np.any(np.linalg.norm(quats, axis=1) == 0):
            raise ValueError("quaternions must be non-zero (w, x, y, z).")
        cap = n if capacity is None else int(capacity)
        if cap < n:
            raise ValueError(f"capacity {cap} is smaller than the number of Gaussians {n}.")

        def pad(a, fill=0.0):
            out = np.full((cap,) + a.shape[1:], fill, np.float32)
            out[:n] = a
            return jnp.asarray(out)

        op = np.clip(opacities, _OPACITY_EPS, 1 - _OPACITY_EPS).astype(np.float64)
        logits = np.log(op) - np.log1p(-op)
        quats_p = np.zeros((cap, 4), np.float32)
        quats_p[:, 0] = 1.0
        quats_p[:n] = quats
        active = np.zeros(cap, np.float32)
        active[:n] = 1.0

        def bank(textures, channels, default):
            if textures is None:
                return None
            textures = list(textures)
            if len(textures) != n:
                raise ValueError(f"got {len(textures)} textures for {n} Gaussians; pass one entry "
                                 "(an array or None) per Gaussian.")
            return TextureBank.from_list(textures, cap, channels, default)

        return cls(means=pad(means), log_scales=pad(np.log(scales)), quats=jnp.asarray(quats_p),
                   opacity_logits=pad(logits.astype(np.float32), -20.0), sh=pad(sh),
                   active=jnp.asarray(active), rgb=bank(rgb_textures, 3, 0.0),
                   alpha=bank(alpha_textures, 1, 1.0),
                   filter3d=None if filter3d is None else pad(np.asarray(filter3d, np.float32).reshape(n)))

    # ----------------------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(int(self.sh.shape[1]))

    @property
    def is_3d(self) -> bool:
        """Whether the Gaussians are 3D (``log_scales`` (C, 3)): static, from the shape."""
        return int(self.log_scales.shape[-1]) == 3

    @property
    def scales(self) -> jax.Array:
        """(C, 2) activated scales ((C, 3) for 3D Gaussians)."""
        return jnp.exp(self.log_scales)

    @property
    def opacities(self) -> jax.Array:
        """(C,) activated opacities."""
        return jax.nn.sigmoid(self.opacity_logits)

    def num_active(self) -> int:
        """Number of active Gaussians (host-side)."""
        return int(np.sum(np.asarray(self.active) > 0))

    def texel_count(self) -> dict:
        """Texels stored for active Gaussians: ``{"rgb": ..., "alpha": ...}`` (host-side)."""
        out = {}
        for name in ("rgb", "alpha"):
            bank = getattr(self, name)
            out[name] = 0 if bank is None else bank.texel_count(self.active)
        return out

    def replace(self, **kw) -> Scene:
        return dataclasses.replace(self, **kw)

    def astype(self, dtype) -> Scene:
        """The same scene with every leaf cast to ``dtype`` (e.g. float64 for reference renders)."""
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), self)


def random_scene(seed: int, n: int, sh_degree: int = 0, extent: float = 1.0, scale_range=(0.02, 0.2),
                 center=(0.0, 0.0, 0.0), rgb_sizes: Sequence[int] | None = None,
                 alpha_sizes: Sequence[int] | None = None, opacity_range=(0.2, 0.95),
                 capacity: int | None = None, scale_dims: int = 2) -> Scene:
    """A random scene for tests, demos and benchmarks (deterministic in ``seed``).

    Means uniform in a cube of half-side ``extent`` around ``center``; log-uniform scales; uniform
    random rotations; SH DC such that colours are in (0.1, 0.9), higher bands small. ``rgb_sizes``
    and ``alpha_sizes`` give per-Gaussian texture sides (0 for none), filled with random values
    (RGB offsets in [-0.3, 0.3], alpha in [0.3, 1.2]). ``scale_dims=3``: 3D Gaussians (no textures).
    """
    rng = np.random.default_rng(seed)
    means = rng.uniform(-extent, extent, (n, 3)) + np.asarray(center)
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    scales = np.exp(rng.uniform(lo, hi, (n, scale_dims)))
    quats = rng.normal(size=(n, 4))
    opac = rng.uniform(opacity_range[0], opacity_range[1], n)
    K = (sh_degree + 1) ** 2
    sh = np.zeros((n, K, 3))
    sh[:, 0] = (rng.uniform(0.1, 0.9, (n, 3)) - 0.5) / 0.28209479177387814
    sh[:, 1:] = rng.normal(0.0, 0.1, (n, K - 1, 3))

    def textures(sizes, ch, lo_, hi_):
        if sizes is None:
            return None
        out = []
        for s in sizes:
            s = int(s)
            out.append(None if s == 0 else rng.uniform(lo_, hi_, (s, s, ch) if ch == 3 else (s, s)))
        return out

    return Scene.from_arrays(means, scales, quats, opac, sh, textures(rgb_sizes, 3, -0.3, 0.3),
                             textures(alpha_sizes, 1, 0.3, 1.2), capacity=capacity)
