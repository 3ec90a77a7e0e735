"""PLY export in the 2DGS attribute layout (3DGS's for 3D Gaussians), with a texture sidecar, and the
matching loader.

PLY (binary little-endian, one ``vertex`` element, all properties ``float``), in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}
    opacity  scale_0 scale_1  rot_0 rot_1 rot_2 rot_3

as written by 2DGS (3DGS's layout with two scales): normals are zeros; ``f_dc_c`` is the DC SH
coefficient of channel c; ``f_rest`` is channel-major (all K-1 higher coefficients of R, then of
G, then of B: ``f_rest_{c (K-1) + k - 1} = sh[:, k, c]``); ``opacity`` is the logit;
``scale_*`` are log scales; ``rot_*`` the quaternion (w, x, y, z), unnormalised, as stored. Only
active Gaussians are written, in slot order.

A scene of 3D Gaussians (``3dgs``, ``mip-splatting``) is written in 3DGS's own layout, which the
common 3DGS viewers read: the same properties with ``scale_0 scale_1 scale_2``. Mip-Splatting's 3D
filter is baked in as its reference code's fused PLY does (:func:`patexgs_jax.filter3d.bake`:
scales sqrt(s^2 + f), opacity times sqrt(det Sigma / det(Sigma + f I))), so a viewer without the
filter shows the trained model (the 2D Mip filter, a renderer setting, is not in the file).
2D splats with the filter (``patexgs+filter3d``) cannot have it baked (widened scales would stretch
their textures, which span +-3 scales): their PLY has one more property after ``rot_3``,
``filter_3D``, the filter's standard deviation sqrt(f) (world units) as Mip-Splatting's unfused PLY
stores it, which :func:`load_ply` reads back (from Mip-Splatting's own unfused 3D files too: their
scales are then filtered as its renderer does) and other 2DGS readers skip.

Texture sidecar ``path.with_suffix(".textures.npz")`` (e.g. ``scene.ply`` ->
``scene.textures.npz``), written by :func:`export_ply` for a scene with textures (a scene without
any, e.g. ``2dgs`` or ``3dgs``, is the PLY alone, and a sidecar left at that path by an earlier
export is removed), a numpy ``.npz`` with
  * ``format``: the string ``"patexgs-textures"``; ``version``: int, currently 1;
  * ``num_gaussians``: N, the PLY's vertex count; ``ply_crc32``: CRC-32 of the PLY's vertex data
    (a sidecar left over from another export is rejected);
  * for each bank ``b`` in ``rgb`` (3 channels, RGB offsets) and ``alpha`` (1 channel, alpha
    multipliers): ``{b}_present`` (bool: the scene has this bank at all), ``{b}_num_buckets``
    (int, bucket count to rebuild), ``{b}_sizes`` (N,) int32 texture side per exported Gaussian
    (0: none), ``{b}_texels`` (sum of sizes**2, channels) float32: the textures concatenated in
    Gaussian order, each row-major (index [a, c] at row ``offset + a * n + c``, a along the first
    tangent axis).
:func:`load_ply` reads the sidecar if it exists (a plain 2DGS PLY loads without textures).
"""

from __future__ import annotations

import os
import tempfile
import zlib
from pathlib import Path

import jax
import numpy as np

from . import filter3d
from .checkpoint import make_public
from .math import SH_COEFFS_PER_DEGREE
from .scene import Scene
from .textures import TextureBank

SIDECAR_FORMAT = "patexgs-textures"
SIDECAR_VERSION = 1
_MAX_HEADER = 1 << 16
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4",
              "uint32": "<u4", "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


class PlyFormatError(ValueError):
    """A PLY file or its texture sidecar is truncated, corrupt or not in the expected layout."""


def sidecar_path(path) -> Path:
    return Path(path).with_suffix(".textures.npz")


def ply_property_names(sh_coeffs: int, scales: int = 2) -> list[str]:
    """The 2DGS vertex properties for K SH coefficients per channel (3DGS's with ``scales=3``)."""
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(3 * (sh_coeffs - 1))] + ["opacity"]
            + [f"scale_{i}" for i in range(scales)] + [f"rot_{i}" for i in range(4)])


def _atomic_write(path: Path, write) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            make_public(f.fileno())
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _bank_export(bank: TextureBank | None, rows: np.ndarray, channels: int):
    """(sizes (N,), texels (sum n^2, ch), num_buckets) of the exported rows."""
    n_rows = rows.shape[0]
    if bank is None:
        return np.zeros(n_rows, np.int32), np.zeros((0, channels), np.float32), 0
    bucket = np.asarray(bank.bucket).astype(np.int64)[rows]
    slot = np.asarray(bank.slot).astype(np.int64)[rows]
    sizes = np.where(bucket >= 0, np.asarray(bank.size).astype(np.int64)[rows], 0)
    offsets = np.concatenate([[0], np.cumsum(sizes * sizes)])
    texels = np.zeros((int(offsets[-1]), channels), np.float32)
    data = [np.asarray(b) for b in bank.buckets]
    for b in np.unique(bucket[bucket >= 0]):
        for n in np.unique(sizes[bucket == b]):
            sel = np.flatnonzero((bucket == b) & (sizes == n))
            vals = data[b][slot[sel], :n, :n].reshape(sel.size, n * n, channels)
            pos = offsets[sel][:, None] + np.arange(n * n)[None, :]
            texels[pos.ravel()] = vals.reshape(-1, channels)
    return sizes.astype(np.int32), texels, bank.num_buckets


def export_ply(scene: Scene, path) -> Path:
    """Writes the active Gaussians of ``scene`` to ``path`` (PLY) and, when the scene has textures,
    its texture sidecar (a scene without textures leaves none: an older sidecar at that path is
    removed, so that :func:`load_ply` does not find a stale one).

    Both files are written atomically (temp file + rename) with the mode ``open()`` gives a new
    file (0666 less the umask: 0644 under the usual 022). Returns the PLY path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = np.flatnonzero(np.asarray(scene.active) > 0)
    n = rows.size
    sh = np.asarray(scene.sh, np.float32)[rows]                  # (N, K, 3)
    K = sh.shape[1]
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(n, 3 * (K - 1))
    plane_filter = scene.filter3d is not None and not scene.is_3d  # (stored, not baked: module docstring)
    if plane_filter:
        log_scales, logits = np.asarray(scene.log_scales, np.float32), np.asarray(scene.opacity_logits, np.float32)
    else:
        log_scales, logits = filter3d.bake(scene)  # the scene's own without a 3D filter
    cols = [np.asarray(scene.means, np.float32)[rows], np.zeros((n, 3), np.float32), sh[:, 0, :], rest,
            logits[rows][:, None], log_scales[rows], np.asarray(scene.quats, np.float32)[rows]]
    names = ply_property_names(K, log_scales.shape[1])
    if plane_filter:
        cols.append(np.sqrt(np.maximum(np.asarray(scene.filter3d, np.float32)[rows], 0.0))[:, None])
        names.append("filter_3D")
    data = np.ascontiguousarray(np.concatenate(cols, axis=1).astype("<f4"))
    assert data.shape[1] == len(names)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment patexgs-jax {'3DGS' if scene.is_3d else '2DGS'} export\n"
              f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in names)
              + "end_header\n").encode("ascii")
    body = data.tobytes()
    if scene.rgb is None and scene.alpha is None:
        sidecar_path(path).unlink(missing_ok=True)  # (before the PLY: never a new PLY beside a stale sidecar)
    _atomic_write(path, lambda f: (f.write(header), f.write(body)))
    if scene.rgb is None and scene.alpha is None:
        return path

    side = {"format": np.asarray(SIDECAR_FORMAT), "version": np.asarray(SIDECAR_VERSION),
            "num_gaussians": np.asarray(n), "ply_crc32": np.asarray(zlib.crc32(body), np.int64)}
    for name, ch in (("rgb", 3), ("alpha", 1)):
        bank = getattr(scene, name)
        sizes, texels, nb = _bank_export(bank, rows, ch)
        side.update({f"{name}_present": np.asarray(bank is not None), f"{name}_num_buckets": np.asarray(nb),
                     f"{name}_sizes": sizes, f"{name}_texels": texels})
    _atomic_write(sidecar_path(path), lambda f: np.savez(f, **side))
    return path


# ------------------------------------------------------------------------------------------------
def _parse_header(path: Path, raw: bytes):
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise PlyFormatError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in the "
                             f"first {_MAX_HEADER} bytes).")
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise PlyFormatError(f"{path}: truncated PLY header.")
    try:
        lines = raw[:end].decode("ascii").replace("\r", "").split("\n")
    except UnicodeDecodeError:
        raise PlyFormatError(f"{path}: PLY header is not ASCII text.") from None
    fmt, elements = None, []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1:]
        elif tok[0] == "element" and len(tok) == 3:
            try:
                count = int(tok[2])
            except ValueError:
                raise PlyFormatError(f"{path}: bad element count {tok[2]!r}.") from None
            if count < 0:
                raise PlyFormatError(f"{path}: negative element count {count}.")
            elements.append((tok[1], count, []))
        elif tok[0] == "property" and elements:
            if len(tok) != 3:
                raise PlyFormatError(f"{path}: unsupported property line {line!r} (list properties "
                                     "are not supported).")
            if tok[1] not in _PLY_TYPES:
                raise PlyFormatError(f"{path}: unknown property type {tok[1]!r}.")
            elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        else:
            raise PlyFormatError(f"{path}: malformed PLY header line {line!r}.")
    if fmt != ["binary_little_endian", "1.0"]:
        raise PlyFormatError(f"{path}: PLY format {' '.join(fmt or ['missing'])!r}; only "
                             "'binary_little_endian 1.0' is supported.")
    if not elements or elements[0][0] != "vertex":
        raise PlyFormatError(f"{path}: the first PLY element must be 'vertex'.")
    return elements, nl + 1


def _read_vertices(path: Path):
    """(structured vertex array, property names, raw vertex bytes)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        raw = f.read(_MAX_HEADER)
        elements, start = _parse_header(path, raw)
        _, n, props = elements[0]
        names = [p for p, _ in props]
        if len(set(names)) != len(names):
            raise PlyFormatError(f"{path}: duplicate vertex properties.")
        try:
            dtype = np.dtype([(p, t) for p, t in props])
        except (TypeError, ValueError) as e:
            raise PlyFormatError(f"{path}: bad vertex properties: {e}") from None
        need = n * dtype.itemsize
        have = size - start
        if have < need:
            raise PlyFormatError(f"{path}: truncated: {n} vertices need {need} bytes of data, the file "
                                 f"has {have}.")
        if have > need and len(elements) == 1:
            raise PlyFormatError(f"{path}: {have - need} unexpected bytes after the vertex data.")
        f.seek(start)
        body = f.read(need)
    if len(body) != need:
        raise PlyFormatError(f"{path}: truncated vertex data.")
    return np.frombuffer(body, dtype=dtype, count=n), names, body


def load_ply(path, capacity: int | None = None) -> Scene:
    """Reads a PLY written by :func:`export_ply` (or any 2DGS or 3DGS PLY) and its sidecar into a Scene
    (of 3D Gaussians for a 3DGS file: ``scale_2`` present).

    Args:
      path: the PLY file.
      capacity: scene capacity (default: the number of Gaussians N); slots beyond N are inactive.
    Raises:
      PlyFormatError for truncated or corrupt files, missing properties, non-finite values, or a
      sidecar of the wrong format, version or PLY.
    """
    path = Path(path)
    verts, names, body = _read_vertices(path)
    n = verts.shape[0]
    dims = 3 if "scale_2" in names else 2
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    if n_rest % 3 or (n_rest // 3 + 1) not in SH_COEFFS_PER_DEGREE:
        raise PlyFormatError(f"{path}: {n_rest} f_rest properties; expected 3 (K - 1) with K in "
                             f"{SH_COEFFS_PER_DEGREE}.")
    K = n_rest // 3 + 1
    missing = [p for p in ply_property_names(K, dims) if p not in names and p not in ("nx", "ny", "nz")]
    if missing:
        raise PlyFormatError(f"{path}: missing vertex properties {missing}.")

    def col(*ps):
        if not ps:
            return np.zeros((n, 0), np.float32)
        return np.stack([np.asarray(verts[p], np.float32) for p in ps], axis=1)

    means = col("x", "y", "z")
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")
    rest = col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, K - 1)
    sh = np.concatenate([dc[:, None, :], np.transpose(rest, (0, 2, 1))], axis=1)
    logits = col("opacity")[:, 0]
    log_scales = col(*[f"scale_{i}" for i in range(dims)])
    quats = col("rot_0", "rot_1", "rot_2", "rot_3")
    f3d = col("filter_3D")[:, 0] if "filter_3D" in names else None  # (ours, or Mip-Splatting's unfused PLY)
    for name, a in (("positions", means), ("SH", sh), ("opacity", logits), ("scales", log_scales),
                    ("rotations", quats), ("filter_3D", np.zeros(0) if f3d is None else f3d)):
        if not np.all(np.isfinite(a)):
            raise PlyFormatError(f"{path}: non-finite {name} (corrupt file?).")

    C = n if capacity is None else int(capacity)
    if C < n:
        raise ValueError(f"capacity {C} is smaller than the {n} Gaussians in {path}.")

    def pad(a, fill: float | np.ndarray = 0.0):
        out = np.empty((C,) + a.shape[1:], np.float32)
        out[:] = fill
        out[:n] = a
        return jax.device_put(out)

    active = np.zeros(C, np.float32)
    active[:n] = 1.0
    rgb, alpha = _load_sidecar(path, n, zlib.crc32(body), C)
    return Scene(means=pad(means), log_scales=pad(log_scales),
                 quats=pad(quats, np.asarray([1.0, 0.0, 0.0, 0.0], np.float32)),
                 opacity_logits=pad(logits, -20.0), sh=pad(sh), active=jax.device_put(active),
                 rgb=rgb, alpha=alpha, filter3d=None if f3d is None else pad(np.square(f3d)))


def _load_sidecar(path: Path, n: int, crc: int, capacity: int):
    sc = sidecar_path(path)
    if not sc.exists():
        return None, None
    try:
        with np.load(sc, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except Exception as e:  # zip / npy parsing errors of a damaged file
        raise PlyFormatError(f"{sc}: texture sidecar is truncated or corrupt "
                             f"({type(e).__name__}: {e}).") from e
    try:
        if str(d["format"]) != SIDECAR_FORMAT:
            raise PlyFormatError(f"{sc}: not a patexgs texture sidecar (format {str(d['format'])!r}).")
        if int(d["version"]) != SIDECAR_VERSION:
            raise PlyFormatError(f"{sc}: texture sidecar version {int(d['version'])}; this code reads "
                                 f"version {SIDECAR_VERSION}.")
        if int(d["num_gaussians"]) != n or int(d["ply_crc32"]) != crc:
            raise PlyFormatError(f"{sc}: texture sidecar does not belong to {path.name} (Gaussian count "
                                 "or vertex-data checksum differs; stale file from another export?).")
        banks = []
        for name, ch in (("rgb", 3), ("alpha", 1)):
            if not bool(d[f"{name}_present"]):
                banks.append(None)
                continue
            sizes = np.asarray(d[f"{name}_sizes"]).astype(np.int64)
            texels = np.asarray(d[f"{name}_texels"], np.float32)
            if sizes.shape != (n,) or np.any(sizes < 0):
                raise PlyFormatError(f"{sc}: {name}_sizes has shape {sizes.shape} or negative sides.")
            total = int(np.sum(sizes * sizes))
            if texels.shape != (total, ch):
                raise PlyFormatError(f"{sc}: {name}_texels has shape {texels.shape}, the sizes need "
                                     f"({total}, {ch}).")
            if not np.all(np.isfinite(texels)):
                raise PlyFormatError(f"{sc}: non-finite {name} texels.")
            banks.append(TextureBank.from_packed(sizes, texels, capacity, ch,
                                                 min_buckets=int(d[f"{name}_num_buckets"])))
    except KeyError as e:
        raise PlyFormatError(f"{sc}: texture sidecar lacks the entry {e}.") from None
    except (TypeError, ValueError) as e:
        if isinstance(e, PlyFormatError):
            raise
        raise PlyFormatError(f"{sc}: invalid texture sidecar ({e}).") from e
    return banks[0], banks[1]
