"""A brute-force float64 reference renderer, written independently of the tile renderer.

It follows the conventions of ``patexgs_jax.rendering`` literally, with different maths where it can:
explicit ray-plane intersection (instead of the homogeneous adjugate form), a per-splat sequential
loop over all splats in depth order (no tiles, no capacities), and its own mip pyramid and bilinear
sampling code. Small scenes and images only.
"""

from __future__ import annotations

import numpy as np

#: The prefilter's screen support (the renderer's SUPPORT_Q, by its definition): twice the radius at
#: which a fully opaque splat's kernel falls to 1/255.
SUPPORT_Q = 4.0 * 2.0 * np.log(255.0)
#: Half the side of a billboard's square in units of the scales (coverage "billboard"): the textures' span.
BILLBOARD_HALF = 3.0

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def quat_rot(q):
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def sh_color(coeffs, d):
    """coeffs (K, 3), d unit (3,) -> (3,)"""
    x, y, z = d
    b = [C0]
    if len(coeffs) > 1:
        b += [-C1 * y, C1 * z, -C1 * x]
    if len(coeffs) > 4:
        b += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y), C2[3] * x * z,
              C2[4] * (x * x - y * y)]
    if len(coeffs) > 9:
        b += [C3[0] * y * (3 * x * x - y * y), C3[1] * x * y * z, C3[2] * y * (4 * z * z - x * x - y * y),
              C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), C3[4] * x * (4 * z * z - x * x - y * y),
              C3[5] * z * (x * x - y * y), C3[6] * x * (x * x - 3 * y * y)]
    return np.maximum(np.asarray(b) @ coeffs + 0.5, 0.0)


def tent_down(level, s_out):
    """Tent-filter downsampling of a (s, s, ch) align-corners level to (s_out, s_out, ch)."""
    s_in = level.shape[0]
    if s_out == 1:
        return level.mean(axis=(0, 1), keepdims=True)
    xs = [-3 + 6 * i / (s_in - 1) for i in range(s_in)]
    ys = [-3 + 6 * j / (s_out - 1) for j in range(s_out)]
    h = 6 / (s_out - 1)
    D = np.array([[max(0.0, 1 - abs(xi - yj) / h) for xi in xs] for yj in ys])
    D /= D.sum(axis=1, keepdims=True)
    out = np.zeros((s_out, s_out, level.shape[2]))
    for c in range(level.shape[2]):
        out[:, :, c] = D @ level[:, :, c] @ D.T
    return out


def pyramid(t):
    n = t.shape[0]
    L = int(np.ceil(np.log2(n))) if n > 1 else 0
    levels = [t]
    for k in range(1, L + 1):
        levels.append(tent_down(levels[-1], 2 ** (L - k)))
    return levels


def bilinear(level, u, v):
    """level (s, s, ch); u, v arrays -> (..., ch); align-corners over [-3, 3], clamped."""
    s = level.shape[0]
    if s == 1:
        return np.broadcast_to(level[0, 0], np.shape(u) + (level.shape[2],)).copy()
    ta = np.clip((u + 3) / 6 * (s - 1), 0, s - 1)
    tb = np.clip((v + 3) / 6 * (s - 1), 0, s - 1)
    a0 = np.minimum(np.floor(ta), s - 2).astype(int)
    b0 = np.minimum(np.floor(tb), s - 2).astype(int)
    fa, fb = (ta - a0)[..., None], (tb - b0)[..., None]
    return ((1 - fa) * (1 - fb) * level[a0, b0] + (1 - fa) * fb * level[a0, b0 + 1]
            + fa * (1 - fb) * level[a0 + 1, b0] + fa * fb * level[a0 + 1, b0 + 1])


def sample_mip(levels, u, v, footprint, mip, lam):
    n = levels[0].shape[0]
    L = len(levels) - 1
    if mip == "none" or L == 0:
        return bilinear(levels[0], u, v)
    with np.errstate(divide="ignore"):
        lf = np.log2(np.maximum(lam * n * footprint, 1e-300))
    if mip == "nearest":
        lev = np.clip(np.floor(lf), 0, L).astype(int)
        out = np.zeros(np.shape(u) + (levels[0].shape[2],))
        for k in range(L + 1):
            m = lev == k
            if np.any(m):
                out[m] = bilinear(levels[k], u[m], v[m])
        return out
    lf = np.clip(lf, 0, L)
    l0 = np.floor(lf).astype(int)
    frac = (lf - l0)[..., None]
    l1 = np.minimum(l0 + 1, L)
    out0 = np.zeros(np.shape(u) + (levels[0].shape[2],))
    out1 = np.zeros_like(out0)
    for k in range(L + 1):
        m0, m1 = l0 == k, l1 == k
        if np.any(m0):
            out0[m0] = bilinear(levels[k], u[m0], v[m0])
        if np.any(m1):
            out1[m1] = bilinear(levels[k], u[m1], v[m1])
    return (1 - frac) * out0 + frac * out1


def screen_jacobian(K, Rc, tc, mean, axes):
    """(2, 2) d(pixel)/d(u, v) at a splat's centre: column j is the derivative of the projection of
    ``mean + h axes[j]`` at h = 0 (axes: the scaled tangent axes, world frame)."""
    pc = Rc @ mean + tc
    q = K @ pc
    out = np.zeros((2, 2))
    for j in range(2):
        dq = K @ (Rc @ axes[j])
        out[:, j] = (dq[:2] * q[2] - q[:2] * dq[2]) / q[2] ** 2
    return out


def reference_render(g, K, w2c, width, height, mip="nearest", lam=0.4, rgb_mip=True, alpha_mip=True,
                     background=(0.0, 0.0, 0.0), near=0.01, coverage="lowpass", pixel_var=0.1, min_var=0.0):
    """Renders a dict of activated float64 parameters.

    coverage "lowpass" is the 2DGS kernel; "prefilter" the splat's Gaussian convolved with a
    Gaussian pixel filter of variance ``pixel_var`` through the centre's screen Jacobian J: the
    kernel exp(-0.5 h^T (I + pixel_var J^-1 J^-T)^-1 h) scaled by det(I + pixel_var J^-1 J^-T)^-1/2,
    here from J directly (J^T (J J^T + v I)^-1 J and |det J| / sqrt(det(J J^T + v I))); a pair is
    skipped below 1/255 times that scale. The filter's variance is raised to min_var minus the
    splat's smallest screen variance where that is more than pixel_var. The kernel is zero outside
    the screen ellipse d^T (J J^T + v I)^-1 d <= SUPPORT_Q, d the pixel's offset from the centre.
    "billboard": the kernel is 1 where the ray meets the plane in the closed square |u|, |v| <= 3
    (BILLBOARD_HALF) and 0 elsewhere, with the intersection's depth.

    With ``g["filter3d"]``, each splat is first convolved in its plane with an isotropic Gaussian of
    variance f (world units^2; Mip-Splatting's 3D filter on a surfel): with "lowpass" (untextured
    splats) the splat with scales sqrt(s^2 + f) and its opacity times prod s / sqrt(s^2 + f).

    g: dict with means (N,3), scales (N,2), quats (N,4), opacities (N,) (0 for inactive), sh (N,K,3),
       rgb (list of None or (n,n,3)), alpha (list of None or (m,m,1)), optionally filter3d (N,).
    Returns dict rgb (H,W,3), alpha (H,W), depth (H,W), normal (H,W,3), best (H,W) int (-1 none).
    """
    K = np.asarray(K, np.float64)
    w2c = np.asarray(w2c, np.float64)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    Rinv = np.linalg.inv(Rc)  # not Rc.T: a float32-stored rotation is only nearly orthonormal
    origin = -Rinv @ tc
    jj, ii = np.meshgrid(np.arange(width), np.arange(height))
    x, y = jj.ravel() + 0.5, ii.ravel() + 0.5
    Kinv = np.linalg.inv(K)

    def rays(xx, yy):
        dc = Kinv @ np.stack([xx, yy, np.ones_like(xx)])
        return (Rinv @ dc).T  # world directions whose camera z is 1

    d0, dx, dy = rays(x, y), rays(x + 1, y), rays(x, y + 1)
    N = len(g["means"])
    depths = np.array([(Rc @ g["means"][i] + tc)[2] for i in range(N)])
    order = np.argsort(depths, kind="stable")
    P = x.size
    T = np.ones(P)
    done = np.zeros(P, bool)
    rgb = np.zeros((P, 3))
    dep = np.zeros(P)
    nrm = np.zeros((P, 3))
    best_w = np.zeros(P)
    dA, dD1, dD2, dist = np.zeros(P), np.zeros(P), np.zeros(P), np.zeros(P)
    best = -np.ones(P, int)
    for i in order:
        if depths[i] <= near or g["opacities"][i] <= 0:
            continue
        R = quat_rot(g["quats"][i])
        mean, s = g["means"][i], g["scales"][i]
        opacity = g["opacities"][i]
        f_i = 0.0 if g.get("filter3d") is None else g["filter3d"][i]
        if f_i > 0 and coverage == "lowpass":  # (an untextured splat: the convolved Gaussian itself)
            s_f = np.sqrt(s * s + f_i)
            opacity, s = opacity * np.prod(s / s_f), s_f
        tu, tv, n = R[:, 0], R[:, 1], R[:, 2]
        pc = Rc @ mean + tc
        mu = (K @ pc)[:2] / pc[2]

        def hit(d, mean=mean, n=n, tu=tu, tv=tv, s=s):
            den = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((mean - origin) @ n) / den
            X = origin[None] + t[:, None] * d
            u = (X - mean) @ tu / s[0]
            v = (X - mean) @ tv / s[1]
            bad = ~np.isfinite(u) | ~np.isfinite(v) | (np.abs(den) == 0)
            return np.where(bad, 1e30, u), np.where(bad, 1e30, v), t, bad

        u, v, t, bad = hit(d0)
        a_min = 1 / 255
        if coverage == "billboard":
            inside = ~bad & (np.abs(u) <= BILLBOARD_HALF) & (np.abs(v) <= BILLBOARD_HALF)
            G = inside.astype(np.float64)
            z = np.where(inside, t, pc[2])
        elif coverage == "prefilter":
            J = screen_jacobian(K, Rc, tc, mean, (tu * s[0], tv * s[1]))
            if f_i > 0:
                # The 3D filter in the plane: the splat's plane covariance (units of the scales)
                # D = diag(1 + f / s^2), the pixel filter's e (J^T J)^-1 added, inverted directly;
                # the peak sqrt(det I / det(sum)) keeps the integral of the unit Gaussian.
                D = np.diag(1.0 + f_i / np.square(s))
                S = J @ D @ J.T
                e = max(pixel_var, min_var - np.linalg.eigvalsh(S)[0])
                Sf = S + e * np.eye(2)
                Sig = D + e * np.linalg.inv(J.T @ J)
                Pm = np.linalg.inv(Sig)
                cov = 1.0 / np.sqrt(np.linalg.det(Sig))
            else:
                S = J @ J.T
                Sf = S + max(pixel_var, min_var - np.linalg.eigvalsh(S)[0]) * np.eye(2)
                Pm = J.T @ np.linalg.inv(Sf) @ J
                cov = abs(np.linalg.det(J)) / np.sqrt(np.linalg.det(Sf))
            opacity, a_min = opacity * cov, a_min * cov
            uc, vc = np.where(bad, 0.0, u), np.where(bad, 0.0, v)
            q = Pm[0, 0] * uc * uc + 2 * Pm[0, 1] * uc * vc + Pm[1, 1] * vc * vc
            dxy = np.stack([x - mu[0], y - mu[1]])
            inside = np.sum(dxy * (np.linalg.inv(Sf) @ dxy), axis=0) <= SUPPORT_Q
            G = np.where(bad | ~inside, 0.0, np.exp(-0.5 * q))
            z = np.where(bad | ~inside, pc[2], t)
        else:
            rho3 = np.where(bad, np.inf, u * u + v * v)
            rho2 = 2 * ((x - mu[0]) ** 2 + (y - mu[1]) ** 2)
            use3 = rho3 <= rho2
            G = np.exp(-0.5 * np.minimum(rho3, rho2))
            z = np.where(use3, t, pc[2])
        ux, vx, _, _ = hit(dx)
        uy, vy, _, _ = hit(dy)
        foot = np.maximum(np.hypot(ux - u, vx - v), np.hypot(uy - u, vy - v))
        foot = np.where(np.isfinite(foot), foot, 1e30)
        uc, vc = np.clip(u, -1e6, 1e6), np.clip(v, -1e6, 1e6)
        A = np.ones(P)
        if g["alpha"][i] is not None:
            A = sample_mip(pyramid(np.asarray(g["alpha"][i], np.float64)), uc, vc, foot,
                           mip if alpha_mip else "none", lam)[:, 0]
        off = np.zeros((P, 3))
        if g["rgb"][i] is not None:
            off = sample_mip(pyramid(np.asarray(g["rgb"][i], np.float64)), uc, vc, foot,
                             mip if rgb_mip else "none", lam)
        col = sh_color(g["sh"][i], (mean - origin) / np.linalg.norm(mean - origin)) + off
        nc = Rc @ n
        if nc @ pc > 0:
            nc = -nc
        a = np.clip(opacity * G * A, 0.0, 0.99)
        take = ~done & (a >= a_min) & (z > near)
        test_T = T * (1 - a)
        stop = take & (test_T < 1e-4)
        done |= stop
        take &= ~stop
        w = np.where(take, a * T, 0.0)
        rgb += w[:, None] * col
        mz = 1000.0 / (1000.0 - 0.2) * (1 - 0.2 / np.where(take, z, 1.0))
        dist += w * (mz * mz * dA + dD2 - 2 * mz * dD1)  # sum over earlier j of w_i w_j (m_i - m_j)^2
        dA, dD1, dD2 = dA + w, dD1 + w * mz, dD2 + w * mz * mz
        dep += w * z
        nrm += w[:, None] * nc[None]
        better = w > best_w
        best_w = np.where(better, w, best_w)
        best = np.where(better, i, best)
        T = np.where(take, test_T, T)
    alpha = 1 - T
    rgb += T[:, None] * np.asarray(background)[None]
    depth = np.where(alpha > 1e-6, dep / np.maximum(alpha, 1e-6), 0.0)
    return dict(rgb=rgb.reshape(height, width, 3), alpha=alpha.reshape(height, width),
                depth=depth.reshape(height, width), normal=nrm.reshape(height, width, 3),
                distortion=dist.reshape(height, width),
                best=best.reshape(height, width))


def scene_to_reference(scene):
    """Activated float64 parameters of a patexgs_jax Scene (inactive splats get opacity 0)."""
    n = scene.capacity
    act = np.asarray(scene.active) > 0

    def textures(bank, ch):
        if bank is None:
            return [None] * n
        out = []
        for i in range(n):
            t = bank.texture(i)
            out.append(None if t is None else np.asarray(t, np.float64).reshape(t.shape[0], t.shape[1], ch))
        return out

    return dict(means=np.asarray(scene.means, np.float64), scales=np.exp(np.asarray(scene.log_scales, np.float64)),
                quats=np.asarray(scene.quats, np.float64),
                opacities=np.where(act, 1 / (1 + np.exp(-np.asarray(scene.opacity_logits, np.float64))), 0.0),
                sh=np.asarray(scene.sh, np.float64), rgb=textures(scene.rgb, 3), alpha=textures(scene.alpha, 1),
                filter3d=None if scene.filter3d is None else np.asarray(scene.filter3d, np.float64))


def reference_render_3d(g, K, w2c, width, height, background=(0.0, 0.0, 0.0), near=0.01, coverage="lowpass",
                        pixel_var=0.1):
    """Renders a dict of activated float64 3D Gaussians (3DGS / Mip-Splatting), written from the
    papers' formulas, not the renderer's: the covariance R S^2 R^T (plus the 3D filter's variance
    f I, opacity times sqrt(det / det filtered)), its EWA projection J W Sigma W^T J^T with the
    centre clamped to 1.3 half fields of view in J, plus 0.3 I ("lowpass", 3DGS) or pixel_var I with
    the opacity times sqrt(det Sigma' / det(Sigma' + pixel_var I)) ("prefilter", Mip-Splatting's 2D
    filter), inverted with numpy; alpha = min(0.99, opacity G), skipped below 1/255; every pair's
    depth the centre's camera z; normal the axis of the smallest scale, facing the camera.

    g: dict with means (N,3), scales (N,3), quats (N,4), opacities (N,), sh (N,K,3), filter3d (N,)
       or None. Returns as :func:`reference_render`.
    """
    K = np.asarray(K, np.float64)
    w2c = np.asarray(w2c, np.float64)
    Rc, tc = w2c[:3, :3], w2c[:3, 3]
    origin = -np.linalg.inv(Rc) @ tc
    jj, ii = np.meshgrid(np.arange(width), np.arange(height))
    x, y = jj.ravel() + 0.5, ii.ravel() + 0.5
    N = len(g["means"])
    depths = np.array([(Rc @ g["means"][i] + tc)[2] for i in range(N)])
    order = np.argsort(depths, kind="stable")
    P = x.size
    T = np.ones(P)
    done = np.zeros(P, bool)
    rgb, dep, nrm = np.zeros((P, 3)), np.zeros(P), np.zeros((P, 3))
    best_w, best = np.zeros(P), -np.ones(P, int)
    dA, dD1, dD2, dist = np.zeros(P), np.zeros(P), np.zeros(P), np.zeros(P)
    for i in order:
        if depths[i] <= near or g["opacities"][i] <= 0:
            continue
        R = quat_rot(g["quats"][i])
        mean, s = g["means"][i], g["scales"][i]
        opacity = g["opacities"][i]
        Sigma = R @ np.diag(s * s) @ R.T
        if g.get("filter3d") is not None:
            f = g["filter3d"][i]
            opacity = opacity * np.sqrt(np.prod(s * s) / np.prod(s * s + f))
            Sigma = Sigma + f * np.eye(3)
        pc = Rc @ mean + tc
        z = pc[2]
        # J at the centre, whose pixel is clamped to the principal point +- 0.65 of the image (3DGS's
        # x/z within 1.3 tan(fov / 2)); K is upper triangular.
        mx = K[0, 0] * pc[0] / z + K[0, 1] * pc[1] / z + K[0, 2]
        my = K[1, 1] * pc[1] / z + K[1, 2]
        mxc = np.clip(mx, K[0, 2] - 0.65 * width, K[0, 2] + 0.65 * width)
        myc = np.clip(my, K[1, 2] - 0.65 * height, K[1, 2] + 0.65 * height)
        J = np.array([[K[0, 0] / z, K[0, 1] / z, (K[0, 2] - mxc) / z],
                      [0.0, K[1, 1] / z, (K[1, 2] - myc) / z]])
        S = J @ Rc @ Sigma @ Rc.T @ J.T
        if coverage == "prefilter":
            Sf = S + pixel_var * np.eye(2)
            opacity = opacity * np.sqrt(max(np.linalg.det(S), 0.0) / np.linalg.det(Sf))
        else:
            Sf = S + 0.3 * np.eye(2)
        d = np.stack([x - mx, y - my])
        q = np.sum(d * (np.linalg.inv(Sf) @ d), axis=0)
        G = np.exp(-0.5 * q)
        col = sh_color(g["sh"][i], (mean - origin) / np.linalg.norm(mean - origin))
        nc = Rc @ R[:, int(np.argmin(s))]
        if nc @ pc > 0:
            nc = -nc
        a = np.clip(opacity * G, 0.0, 0.99)
        take = ~done & (a >= 1 / 255)
        test_T = T * (1 - a)
        stop = take & (test_T < 1e-4)
        done |= stop
        take &= ~stop
        w = np.where(take, a * T, 0.0)
        rgb += w[:, None] * col
        mz = 1000.0 / (1000.0 - 0.2) * (1 - 0.2 / z)
        dist += w * (mz * mz * dA + dD2 - 2 * mz * dD1)
        dA, dD1, dD2 = dA + w, dD1 + w * mz, dD2 + w * mz * mz
        dep += w * z
        nrm += w[:, None] * nc[None]
        better = w > best_w
        best_w = np.where(better, w, best_w)
        best = np.where(better, i, best)
        T = np.where(take, test_T, T)
    alpha = 1 - T
    rgb += T[:, None] * np.asarray(background)[None]
    depth = np.where(alpha > 1e-6, dep / np.maximum(alpha, 1e-6), 0.0)
    return dict(rgb=rgb.reshape(height, width, 3), alpha=alpha.reshape(height, width),
                depth=depth.reshape(height, width), normal=nrm.reshape(height, width, 3),
                distortion=dist.reshape(height, width), best=best.reshape(height, width))
