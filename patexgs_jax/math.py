"""Safe numerical primitives and small geometry helpers shared by the renderer and training.

Every function here keeps both its value and its gradient finite for all finite inputs (the "double
where" pattern: the unsafe branch is evaluated on a harmless input, so its derivative never produces
inf * 0 = nan).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# Real spherical-harmonics constants (orthonormal basis, the 3DGS sign convention).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

SH_COEFFS_PER_DEGREE = (1, 4, 9, 16)


def sh_degree_of(num_coeffs: int) -> int:
    """SH degree (0..3) for K coefficients per colour channel; K must be 1, 4, 9 or 16."""
    if num_coeffs not in SH_COEFFS_PER_DEGREE:
        raise ValueError(
            f"SH coefficients per channel must be one of {SH_COEFFS_PER_DEGREE} (degree 0-3), got {num_coeffs}."
        )
    return SH_COEFFS_PER_DEGREE.index(num_coeffs)


def safe_div(num, den, eps: float = 1e-20):
    """num / den with den pushed away from zero (keeping its sign; +eps for den == 0)."""
    small = jnp.abs(den) < eps
    den_safe = jnp.where(small, jnp.where(den < 0, -eps, eps), den)
    return num / den_safe


def safe_sqrt(x, eps: float = 1e-20):
    """sqrt(max(x, 0)) whose gradient is finite at 0 (it is taken as 0 there)."""
    pos = x > eps
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def safe_norm(x, axis=-1, keepdims=False, eps: float = 1e-20):
    """Euclidean norm with a finite gradient at the zero vector."""
    return safe_sqrt(jnp.sum(x * x, axis=axis, keepdims=keepdims), eps)


def safe_normalize(x, axis=-1, eps: float = 1e-12):
    """x / |x|; the zero vector maps to zero with a finite gradient."""
    n = safe_norm(x, axis=axis, keepdims=True)
    return x / jnp.maximum(n, eps)


def safe_log2(x, eps: float = 1e-30):
    """log2(max(x, eps)), finite value and gradient for x <= 0."""
    return jnp.log2(jnp.maximum(x, eps))


def quat_to_rotmat(q):
    """Rotation matrices from quaternions (w, x, y, z), normalised first.

    Args:
      q: (..., 4) quaternions, any non-zero norm (a zero quaternion maps to the identity).
    Returns:
      (..., 3, 3) rotation matrices; column k is the rotated k-th axis.
    """
    n2 = jnp.sum(q * q, axis=-1, keepdims=True)
    tiny = n2 < 1e-24
    q = jnp.where(tiny, jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype), q)
    q = q * jax.lax.rsqrt(jnp.where(tiny, 1.0, n2))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def sh_basis(dirs, degree: int, active_degree=None):
    """Real SH basis values for unit directions.

    Args:
      dirs: (..., 3) unit directions.
      degree: static maximum degree 0..3 (sets the number of coefficients, (degree+1)^2).
      active_degree: optional traced int; bands above it are multiplied by zero (lets training add
        bands without recompiling).
    Returns:
      (..., (degree+1)^2) basis values.
    """
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [jnp.full_like(x, SH_C0)]
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z  # unused below degree 2: traced away
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    basis = jnp.stack(out, axis=-1)
    if active_degree is not None and degree > 0:
        band = jnp.asarray([0] + [1] * 3 + [2] * 5 + [3] * 7)[: basis.shape[-1]]
        basis = basis * (band <= active_degree).astype(basis.dtype)
    return basis
