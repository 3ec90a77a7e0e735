"""The analytic scene the synthetic dataset (:mod:`.synthetic`) is rendered from.

The scene (world z up, metres) is a tiled ground square with a few objects: a cube covered with
glyph-like "text" at two sizes, a tall box with stripes at several frequencies, a slanted panel with
a zone plate (chirp) and a sphere with smooth gradients and latitude bands. Shading is Lambertian
with a fixed light and no shadows, so it is view-independent (a multi-view consistent scene).

:func:`make_scene` builds it from a seed; :meth:`Scene.render` and :func:`render_ground_truth`
render anti-aliased ground truth from any :class:`patexgs_jax.camera.Camera`. Host-side numpy,
float64 throughout.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "Box",
    "GlyphTexture",
    "Ground",
    "Quad",
    "Scene",
    "Sphere",
    "SphereTexture",
    "StripeTexture",
    "TileTexture",
    "ZonePlateTexture",
    "camera_rays",
    "make_scene",
    "render_ground_truth",
    "row_matmul",
]

_LIGHT = np.array([0.45, 0.3, 0.85]) / np.linalg.norm([0.45, 0.3, 0.85])
_AMBIENT, _DIFFUSE = 0.55, 0.45
_EPS = 1e-9
_CHUNK = 1 << 17  # rays traced at once (keeps temporaries cache/memory friendly)


# --------------------------------------------------------------------------------------------------
# Procedural textures. All take surface coordinates ``uv`` (N, 2) float64 in metres and return
# (N, 3) float64 colours in [0, 1].
# --------------------------------------------------------------------------------------------------

def row_matmul(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(N, 3) @ (3, K) as an einsum, without BLAS: multithreaded BLAS is slow on such tall-thin
    products when the cores are busy (docs/performance.md)."""
    return np.einsum("ij,jk->ik", a, m)


def _dot(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) . (3,) -> (N,), without BLAS."""
    return np.einsum("ij,j->i", a, v)


def _hash2(a: np.ndarray, b: np.ndarray, salt: int) -> np.ndarray:
    """(N,) uint64 deterministic integer hash of integer cell coordinates ``a``, ``b``."""
    with np.errstate(over="ignore"):
        h = (a.astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             ^ b.astype(np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ np.uint64(salt & 0xFFFFFFFFFFFF) * np.uint64(0x165667B19E3779F9))
        h ^= h >> np.uint64(29)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(32)
    return h


def _mix(c0, c1, w: np.ndarray) -> np.ndarray:
    """Blend colours (3,) or (N, 3) with weights ``w`` (N,) in [0, 1]."""
    w = w[:, None]
    return np.asarray(c0) * (1.0 - w) + np.asarray(c1) * w


def _square(x: np.ndarray) -> np.ndarray:
    """Square wave in {0, 1} with period 1."""
    return (np.mod(x, 1.0) < 0.5).astype(np.float64)


@dataclasses.dataclass(frozen=True)
class TileTexture:
    """Ground tiles: a checkerboard of randomly tinted tiles under a smooth gradient, random dots of
    several sizes (distinctive blobs for feature matching), thin grout lines (high frequency when seen
    from afar) and a glyph "mat" in the middle; beyond ``fade_start`` metres from the origin the
    tiles fade to a plain colour.

    Attributes:
      cell: tile size in metres (dots use half-size cells).
      color_a, color_b: (3,) checkerboard colours.
      palette: (8, 3) tint and dot colours.
      salt: hash salt.
    """

    cell: float
    color_a: np.ndarray
    color_b: np.ndarray
    palette: np.ndarray
    salt: int
    text: GlyphTexture
    mat_half: tuple[float, float]
    fade_start: float = 3.0

    def far_color(self) -> np.ndarray:
        return 0.9 * (0.35 * (self.color_a + self.color_b) + 0.3 * self.palette.mean(0))

    def __call__(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        u, v = uv[:, 0], uv[:, 1]
        cu, cv = np.floor(u / self.cell), np.floor(v / self.cell)
        checker = np.mod(cu + cv, 2.0)
        tint = self.palette[(_hash2(cu, cv, self.salt) % np.uint64(8)).astype(np.int64)]
        col = 0.7 * _mix(self.color_a, self.color_b, checker) + 0.3 * tint
        gradient = 0.8 + 0.2 * np.sin(0.9 * u + 0.3) * np.cos(0.7 * v - 0.2)
        col = col * gradient[:, None]
        # Dots: in each half-tile cell, with probability 2/3, a disc of random radius and colour.
        dc = self.cell / 2
        du, dv = np.floor(u / dc), np.floor(v / dc)
        h = _hash2(du, dv, self.salt + 1)

        def frac(shift):  # 10 bits of the hash from bit ``shift``, as a fraction in [0, 1]
            return ((h >> np.uint64(shift)) % np.uint64(1024)).astype(np.float64) / 1023.0

        r = 0.1 + 0.2 * frac(10)
        px, py = r + (1 - 2 * r) * frac(20), r + (1 - 2 * r) * frac(30)
        inside = ((u / dc - du - px) ** 2 + (v / dc - dv - py) ** 2 < r * r) & (h % np.uint64(3) != 0)
        dot_col = self.palette[((h >> np.uint64(40)) % np.uint64(8)).astype(np.int64)]
        dark = ((h >> np.uint64(44)) % np.uint64(2)) == 0
        dot_col = np.where(dark[:, None], 0.35 * dot_col, 0.4 + 0.6 * dot_col)
        col = np.where(inside[:, None], dot_col, col)
        fu, fv = np.mod(u / self.cell, 1.0), np.mod(v / self.cell, 1.0)
        grout_w = 0.025
        grout = (np.minimum(fu, 1 - fu) < grout_w) | (np.minimum(fv, 1 - fv) < grout_w)
        col[grout] = 0.25
        # Far tiles fade to a plain colour (keeps the horizon from being pure aliasing noise).
        fade = np.clip((np.maximum(np.abs(u), np.abs(v)) - self.fade_start) / 2.0, 0.0, 1.0)
        col = _mix(col, self.far_color(), fade)
        mat = (np.abs(u) < self.mat_half[0]) & (np.abs(v - 1.5) < self.mat_half[1])
        if np.any(mat):
            col[mat] = self.text(np.stack([u[mat] + self.mat_half[0], v[mat] - 1.5 + self.mat_half[1]], -1),
                                 face[mat])
        return col


@dataclasses.dataclass(frozen=True)
class GlyphTexture:
    """Text-like pattern: rows of random 5x7 glyphs (from a seeded font of 64 glyphs) on a paper
    colour; two lines in each paragraph are "headlines" with glyphs 2.5x larger.

    Attributes:
      glyphs: (64, 7, 5) bool glyph bitmaps.
      bit: size of one glyph bit in metres (body text).
      paper, ink: (F, 3) per-face colours (face ids index them modulo F).
      salt: hash salt so that different surfaces show different text.
    """

    glyphs: np.ndarray
    bit: float
    paper: np.ndarray
    ink: np.ndarray
    salt: int

    def _layer(self, u, v, bit, face, salt):
        cw, ch = 6 * bit, 9 * bit  # 5x7 glyph + 1 column and 2 rows of spacing
        cu, cv = np.floor(u / cw), np.floor(v / ch)
        bx = np.floor((u / cw - cu) * 6).astype(np.int64)
        by = np.floor((v / ch - cv) * 9).astype(np.int64)
        h = _hash2(cu + 1000 * face, cv, salt)
        gid = (h % np.uint64(64)).astype(np.int64)
        space = ((h >> np.uint64(8)) % np.uint64(6)) == 0  # about one "space" in six
        inside = (bx < 5) & (by < 7) & ~space
        on = np.zeros(u.shape, bool)
        on[inside] = self.glyphs[gid[inside], 6 - by[inside], bx[inside]]  # v grows upwards
        return on

    def __call__(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        u, v = uv[:, 0], uv[:, 1]
        face = face.astype(np.int64)
        para = 9 * self.bit * 8  # 8 body lines per paragraph block...
        head = 9 * self.bit * 2.5 * 1.2  # ...then one headline line
        period = para + head
        local = np.mod(v, period)
        is_head = local >= para
        on = np.where(is_head,
                      self._layer(u, local - para, self.bit * 2.5, face, self.salt + 7),
                      self._layer(u, local + np.floor(v / period) * para, self.bit, face, self.salt))
        k = face % len(self.paper)
        return np.where(on[:, None], self.ink[k], self.paper[k])


@dataclasses.dataclass(frozen=True)
class StripeTexture:
    """Bands of square-wave stripes at doubling frequencies (3 to 96 cycles per metre) stacked along
    v; the top face (face id 5) is a fine checkerboard."""

    colors: np.ndarray  # (4, 3)
    band: float = 0.18
    base_freq: float = 3.0

    def __call__(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        u, v = uv[:, 0], uv[:, 1]
        band = np.clip(np.floor(v / self.band), 0, 5)
        freq = self.base_freq * 2.0 ** band
        diagonal = (face % 2 == 1)  # odd faces get slanted stripes
        coord = np.where(diagonal, u + 0.5 * v, u)
        s = _square(coord * freq)
        c0 = self.colors[(band.astype(np.int64) % 2) * 2]
        c1 = self.colors[(band.astype(np.int64) % 2) * 2 + 1]
        col = c0 * (1 - s[:, None]) + c1 * s[:, None]
        top = face == 5
        if np.any(top):
            chk = np.mod(np.floor(u[top] * 20) + np.floor(v[top] * 20), 2.0)
            col[top] = _mix(self.colors[0], self.colors[3], chk)
        return col


@dataclasses.dataclass(frozen=True)
class ZonePlateTexture:
    """A chirp ``cos(pi k r^2)`` (local frequency ``k r`` cycles per metre, up to ~50) over a smooth
    two-axis colour gradient, inside a dark frame."""

    half: tuple[float, float]
    k: float
    color_u: np.ndarray
    color_v: np.ndarray

    def __call__(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        u, v = uv[:, 0], uv[:, 1]
        hu, hv = self.half
        r2 = u * u + v * v
        chirp = 0.5 + 0.5 * np.cos(np.pi * self.k * r2)
        base = (0.5 + 0.5 * (u / hu))[:, None] * self.color_u + (0.5 + 0.5 * (v / hv))[:, None] * self.color_v
        base = 0.15 + 0.8 * np.clip(base, 0, 1)
        col = base * (0.35 + 0.65 * chirp[:, None])
        frame = (np.abs(u) > hu - 0.04) | (np.abs(v) > hv - 0.04)
        col[frame] = 0.1
        return col


@dataclasses.dataclass(frozen=True)
class SphereTexture:
    """Smooth longitude/latitude colour gradient with latitude bands (coarse) and a checker cap."""

    color_a: np.ndarray
    color_b: np.ndarray
    radius: float

    def __call__(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        lon, lat = uv[:, 0] / self.radius, uv[:, 1] / self.radius  # radians
        w = 0.5 + 0.5 * np.sin(lon)
        col = _mix(self.color_a, self.color_b, w) * (0.75 + 0.25 * np.cos(lat))[:, None]
        bands = _square(lat * 6 / np.pi)
        col = col * (0.7 + 0.3 * bands)[:, None]
        cap = lat > 0.9
        if np.any(cap):
            chk = np.mod(np.floor(lon[cap] * 8 / np.pi) + np.floor(lat[cap] * 20 / np.pi), 2.0)
            col[cap] = _mix(np.array([0.95, 0.95, 0.9]), np.array([0.1, 0.1, 0.15]), chk)
        return col


# --------------------------------------------------------------------------------------------------
# Geometry. ``hit(o, d)`` takes ray origins (N, 3) and unit directions (N, 3) and returns distances
# (N,) (inf on a miss); ``surface(p)`` returns normals (N, 3), uv (N, 2) in metres and face ids (N,).
# --------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Ground:
    """The square ``|x|, |y| <= half`` of the plane z = 0, seen from above."""

    half: float
    texture: TileTexture
    two_sided = False

    def hit(self, o, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 2] / d[:, 2]
        p = o + t[:, None] * d
        ok = (d[:, 2] < 0) & (t > _EPS) & (np.abs(p[:, 0]) <= self.half) & (np.abs(p[:, 1]) <= self.half)
        return np.where(ok, t, np.inf)

    def far_color(self) -> np.ndarray:
        """(3,) shaded colour of the ground far away (also used below the horizon)."""
        return self.texture.far_color() * (_AMBIENT + _DIFFUSE * max(_LIGHT[2], 0.0))

    def surface(self, p):
        n = np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape)
        return n, p[:, :2].copy(), np.zeros(len(p), np.int64)


@dataclasses.dataclass(frozen=True)
class Quad:
    """A rectangle centred at ``center`` spanned by unit axes ``axis_u``, ``axis_v`` (half sizes
    ``half``); two-sided."""

    center: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    half: tuple[float, float]
    texture: ZonePlateTexture
    two_sided = True

    @property
    def normal(self):
        return np.cross(self.axis_u, self.axis_v)

    def hit(self, o, d):
        n = self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _dot(self.center - o, n) / _dot(d, n)
        p = o + t[:, None] * d - self.center
        ok = ((t > _EPS) & (np.abs(_dot(p, self.axis_u)) <= self.half[0])
              & (np.abs(_dot(p, self.axis_v)) <= self.half[1]))
        return np.where(ok, t, np.inf)

    def surface(self, p):
        q = p - self.center
        uv = np.stack([_dot(q, self.axis_u), _dot(q, self.axis_v)], -1)
        return np.broadcast_to(self.normal, p.shape), uv, np.zeros(len(p), np.int64)


@dataclasses.dataclass(frozen=True)
class Box:
    """A box with half sizes ``half`` (3,), rotated by ``yaw`` about z, centred at ``center``.

    Face ids: 2 * axis + (1 if on the positive side), axis 0 = local x, 1 = y, 2 = z (5 = top).
    """

    center: np.ndarray
    half: np.ndarray
    yaw: float
    texture: object
    two_sided = False

    @property
    def rotation(self):
        """(3, 3) local-to-world rotation."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def hit(self, o, d):
        R = self.rotation
        ol, dl = row_matmul(o - self.center, R), row_matmul(d, R)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-self.half - ol) / dl
            t2 = (self.half - ol) / dl
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        tnear = np.maximum(np.maximum(lo[:, 0], lo[:, 1]), lo[:, 2])
        tfar = np.minimum(np.minimum(hi[:, 0], hi[:, 1]), hi[:, 2])
        ok = (tnear <= tfar) & (tnear > _EPS)
        return np.where(ok, tnear, np.inf)

    def surface(self, p):
        R = self.rotation
        pl = row_matmul(p - self.center, R)
        rel = pl / self.half
        axis = np.argmax(np.abs(rel), axis=1)
        positive = np.take_along_axis(rel, axis[:, None], 1)[:, 0] > 0
        nl = np.zeros_like(p)
        nl[np.arange(len(p)), axis] = np.where(positive, 1.0, -1.0)
        q = pl + self.half  # in [0, 2 * half]
        uv = np.where((axis == 0)[:, None], q[:, [1, 2]], np.where((axis == 1)[:, None], q[:, [0, 2]], q[:, [0, 1]]))
        return row_matmul(nl, R.T), uv, 2 * axis + positive


@dataclasses.dataclass(frozen=True)
class Sphere:
    center: np.ndarray
    radius: float
    texture: SphereTexture
    two_sided = False

    def hit(self, o, d):
        oc = o - self.center
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - self.radius ** 2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        ok = (disc >= 0) & (t > _EPS)
        return np.where(ok, t, np.inf)

    def surface(self, p):
        n = (p - self.center) / self.radius
        lon = np.arctan2(n[:, 1], n[:, 0])
        lat = np.arcsin(np.clip(n[:, 2], -1, 1))
        return n, np.stack([lon, lat], -1) * self.radius, np.zeros(len(p), np.int64)


def _sky(d: np.ndarray, below: np.ndarray) -> np.ndarray:
    """(N, 3) background colour for unit directions (N, 3) (at infinity): a vertical sky gradient
    above the horizon, the colour ``below`` (3,) (the far ground's) under it."""
    z = d[:, 2]
    up = np.clip(z, 0, 1)[:, None]
    sky = np.array([0.82, 0.88, 0.95]) * (1 - up) + np.array([0.35, 0.55, 0.85]) * up
    return np.where((z < 0)[:, None], below, sky)


@dataclasses.dataclass(frozen=True)
class Scene:
    """An analytic scene: primitives (each with ``hit``, ``surface``, ``texture``), the first one the
    :class:`Ground` (its far colour also fills the background below the horizon).

    Colours are float64 in [0, 1]; shading is Lambertian with a fixed light, view-independent.
    """

    primitives: tuple
    seed: int

    def trace(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hits of rays ``o`` (N, 3), unit ``d`` (N, 3).

        Returns ``(t, index)``: (N,) float64 distances (inf on a miss) and (N,) int64 primitive
        indices (-1 on a miss).
        """
        ts = np.stack([prim.hit(o, d) for prim in self.primitives], axis=0)
        index = np.argmin(ts, axis=0)
        t = ts[index, np.arange(len(o))]
        return t, np.where(np.isfinite(t), index, -1)

    def shade_points(self, p: np.ndarray, index: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) float64 shaded colour of surface points ``p`` (N, 3) on primitives ``index`` (N,)
        seen along directions ``d`` (only used to orient two-sided surfaces; default: from above)."""
        out = np.zeros_like(p)
        for k, prim in enumerate(self.primitives):
            sel = index == k
            if not np.any(sel):
                continue
            n, uv, face = prim.surface(p[sel])
            if prim.two_sided and d is not None:
                n = np.where((np.einsum("ij,ij->i", n, d[sel]) > 0)[:, None], -n, n)
            albedo = prim.texture(uv, face)
            light = _AMBIENT + _DIFFUSE * np.clip(_dot(n, _LIGHT), 0.0, None)
            out[sel] = albedo * light[:, None]
        return out

    def radiance(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(N, 3) float64 colour seen along rays ``o`` (N, 3), unit ``d`` (N, 3)."""
        out = np.empty_like(o)
        for s in range(0, len(o), _CHUNK):
            oo, dd = o[s:s + _CHUNK], d[s:s + _CHUNK]
            t, index = self.trace(oo, dd)
            col = _sky(dd, self.primitives[0].far_color())
            hit = index >= 0
            p = oo[hit] + t[hit, None] * dd[hit]
            col[hit] = self.shade_points(p, index[hit], dd[hit])
            out[s:s + _CHUNK] = col
        return np.clip(out, 0.0, 1.0)

    def render(self, camera, supersample: int = 4) -> np.ndarray:
        """Anti-aliased render, ``supersample x supersample`` stratified samples per pixel (box filter).

        Args:
          camera: a :class:`patexgs_jax.camera.Camera` (or anything with ``K`` (3, 3),
            ``world_to_camera`` (4, 4), ``width``, ``height``), OpenCV convention, pixel centres at
            (j + 0.5, i + 0.5).
          supersample: samples per pixel along each axis (1 = one ray through each pixel centre).
        Returns:
          (H, W, 3) float32 RGB in [0, 1].
        """
        K = np.asarray(camera.K, np.float64)
        w2c = np.asarray(camera.world_to_camera, np.float64)
        W, H, S = int(camera.width), int(camera.height), int(supersample)
        if S < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}.")
        offsets = (np.arange(S) + 0.5) / S
        xs = (np.arange(W)[:, None] + offsets[None, :]).reshape(-1)
        ys = (np.arange(H)[:, None] + offsets[None, :]).reshape(-1)
        o, d = camera_rays(K, w2c, *np.meshgrid(xs, ys))
        col = self.radiance(o, d).reshape(H, S, W, S, 3).mean(axis=(1, 3))
        return col.astype(np.float32)


def camera_rays(K, w2c, x, y):
    """Rays through continuous pixel coordinates ``x``, ``y`` (any equal shapes): returns origins and
    unit directions, both (N, 3) float64 in world coordinates."""
    pix = np.stack([x.reshape(-1), y.reshape(-1), np.ones(x.size)], -1)
    d_cam = row_matmul(pix, np.linalg.inv(K).T)
    R, t = w2c[:3, :3], w2c[:3, 3]
    d = row_matmul(d_cam, R)  # R^T d_cam, row-wise
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(-R.T @ t, d.shape).copy()
    return o, d


def _font(rng: np.random.Generator) -> np.ndarray:
    """(64, 7, 5) bool random "glyphs": blocky strokes, never empty."""
    g = rng.random((64, 7, 5)) < 0.45
    g[:, :, 2] |= rng.random((64, 7)) < 0.5  # a vertical stroke makes them letter-like
    g[:, 0, :] |= rng.random((64, 1)) < 0.4
    return g


def make_scene(seed: int = 0) -> Scene:
    """The analytic scene of ``seed`` (colours, glyphs and object placement depend on it)."""
    rng = np.random.default_rng([int(seed), 0x5CE7E])
    font = _font(rng)

    def color(lo=0.15, hi=0.95):
        return rng.uniform(lo, hi, 3)

    paper = np.stack([rng.uniform(0.75, 0.98, 3) for _ in range(6)])
    ink = np.stack([rng.uniform(0.0, 0.3, 3) for _ in range(6)])
    text = GlyphTexture(font, bit=0.012, paper=paper, ink=ink, salt=int(rng.integers(1 << 30)))
    mat_text = GlyphTexture(font, bit=0.02, paper=paper[::-1], ink=ink[::-1], salt=int(rng.integers(1 << 30)))
    ground = Ground(half=8.0, texture=TileTexture(cell=0.5, color_a=color(0.5, 0.9), color_b=color(0.1, 0.5),
                                                  palette=rng.uniform(0.05, 1.0, (8, 3)),
                                                  salt=int(rng.integers(1 << 30)),
                                                  text=mat_text, mat_half=(0.6, 0.25)))

    def jitter(s):
        return rng.uniform(-s, s, 2)

    cube = Box(center=np.r_[np.array([-0.75, 0.45]) + jitter(0.1), 0.35], half=np.array([0.35, 0.35, 0.35]),
               yaw=float(rng.uniform(0, np.pi / 2)), texture=text)
    tall = Box(center=np.r_[np.array([0.75, -0.45]) + jitter(0.1), 0.55], half=np.array([0.25, 0.25, 0.55]),
               yaw=float(rng.uniform(0, np.pi / 2)),
               texture=StripeTexture(colors=np.stack([color(0.6, 0.95), color(0.0, 0.3), color(0.5, 0.9),
                                                      color(0.0, 0.35)])))
    # A slanted panel leaning back by 25-35 degrees, facing the scene centre.
    yaw = float(rng.uniform(-0.4, 0.4)) + np.pi / 4
    lean = float(rng.uniform(np.radians(25), np.radians(35)))
    au = np.array([np.cos(yaw), -np.sin(yaw), 0.0])
    facing = np.array([np.sin(yaw), np.cos(yaw), 0.0])
    av = np.cos(lean) * np.array([0.0, 0.0, 1.0]) - np.sin(lean) * facing
    half = (0.6, 0.4)
    panel_center = np.r_[np.array([0.55, 0.85]) + jitter(0.1), 0.0] + av * half[1] + np.array([0, 0, 0.05])
    panel = Quad(center=panel_center, axis_u=au, axis_v=av, half=half,
                 texture=ZonePlateTexture(half=half, k=70.0, color_u=color(), color_v=color()))
    radius = 0.38
    sphere = Sphere(center=np.r_[np.array([-0.35, -0.8]) + jitter(0.1), radius], radius=radius,
                    texture=SphereTexture(color_a=color(), color_b=color(), radius=radius))
    return Scene(primitives=(ground, cube, tall, panel, sphere), seed=int(seed))


def render_ground_truth(camera, supersample: int = 4, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1]: the analytic scene of ``seed`` seen by ``camera``
    (a :class:`patexgs_jax.camera.Camera`), box-filtered with ``supersample**2`` samples per pixel.

    ``generate(..., seed=s)`` images are ``round(255 * render_ground_truth(cam, supersample, s))``
    for its cameras (see :func:`make_cameras`); ``camera.scaled(f)`` gives zoomed-out ground truth.
    """
    return make_scene(seed).render(camera, supersample)
