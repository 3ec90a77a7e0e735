"""The project's embedded default scene: a procedurally textured, ray-traced synthetic COLMAP dataset.

:func:`generate` writes, deterministically from a seed, a real on-disk scene in the Mip-NeRF 360
layout::

    out_dir/
      images/img_0000.png ...      anti-aliased renders (supersampled), uint8 RGB
      images_2/img_0000.png ...    the same, box-downsampled by 2
      sparse/0/{cameras,images,points3D}.bin   one PINHOLE camera, poses, SfM-like 3D points with
                                               colours and tracks (written by .colmap_binary)
      synthetic.json               generation parameters and format version (written last)

The scene is :mod:`.synthetic_scene`'s analytic one (a tiled ground with a text-covered cube, a
striped box, a zone-plate panel and a sphere; Lambertian, view-independent), whose
:func:`make_scene` and :func:`render_ground_truth` render ground truth from any
:class:`patexgs_jax.camera.Camera`. Cameras sit on two rings (low and high) around the scene centre
at distances varying by 1.5x, so the same surfaces are seen at different scales: fine detail when
near, aliasing-prone when far.

Command line: ``python -m patexgs_jax.data.synthetic OUT_DIR [--seed N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
import uuid
from pathlib import Path

import numpy as np

from ..camera import Camera, look_at
from .colmap_binary import write_binary_model
from .colmap_records import (
    CAMERA_MODELS_BY_NAME,
    ColmapCamera,
    ColmapImage,
    ColmapPoints,
    quaternion_from_rotation,
    rotation_from_quaternion,
)
from .images import box_downsample, save_image
from .synthetic_scene import Scene, camera_rays, make_scene, render_ground_truth, row_matmul

__all__ = [
    "FORMAT_VERSION",
    "SCENE_CENTER",
    "default_scene_dir",
    "ensure_default_scene",
    "generate",
    "main",
    "make_cameras",
    "make_scene",
    "render_ground_truth",
]

FORMAT_VERSION = 1
"""Bumped whenever the generated content changes; part of ``synthetic.json`` and the cache name."""

SCENE_CENTER = np.array([0.0, 0.0, 0.35])
"""(3,) world point the cameras look at (near the middle of the objects)."""


def make_cameras(seed: int = 0, num_views: int = 24, width: int = 128, height: int = 96,
                 fov_x_degrees: float = 60.0, radius: float = 3.0, radius_ratio: float = 1.5,
                 elevations=(18.0, 38.0), arc_degrees: float = 360.0) -> list[Camera]:
    """The generator's cameras, looking at (about) :data:`SCENE_CENTER` with world z up.

    Views alternate between rings at the given ``elevations`` (degrees, +-4 jitter), spread over
    ``arc_degrees`` of azimuth (a full ring by default), at distances in
    ``[radius, radius * radius_ratio]`` (near and far views interleaved by a golden-ratio sequence,
    so the same surfaces are seen at different scales). One shared PINHOLE intrinsics with
    horizontal field of view ``fov_x_degrees``, principal point at the image centre.
    """
    rng = np.random.default_rng([int(seed), 0xCA3E7A])
    f = 0.5 * width / np.tan(np.radians(fov_x_degrees) / 2)
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    offset = rng.uniform(0, 2 * np.pi)
    cams = []
    golden = (np.sqrt(5) - 1) / 2
    full = arc_degrees >= 360.0
    step = np.radians(arc_degrees) / (num_views if full else max(num_views - 1, 1))
    for k in range(num_views):
        azimuth = offset + step * (k + rng.uniform(-0.15, 0.15))
        elevation = np.radians(elevations[k % len(elevations)] + rng.uniform(-4, 4))
        frac = np.mod(0.5 + k * golden, 1.0) if num_views > 2 else float(k)
        r = radius * (1.0 + (radius_ratio - 1.0) * frac)
        eye = SCENE_CENTER + r * np.array([np.cos(elevation) * np.cos(azimuth),
                                           np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        target = SCENE_CENTER + np.r_[rng.uniform(-0.15, 0.15, 2), rng.uniform(-0.1, 0.1)]
        cams.append(Camera.from_intrinsics(K, look_at(eye, target, up=(0.0, 0.0, 1.0)), width, height))
    return cams


# --------------------------------------------------------------------------------------------------
# SfM-like points.
# --------------------------------------------------------------------------------------------------

def _project(K, w2c, p):
    """Continuous pixel coordinates (N, 2) and depths (N,) of world points ``p`` (N, 3)."""
    pc = row_matmul(p, w2c[:3, :3].T) + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = row_matmul(pc, K.T)[:, :2] / z[:, None]
    return xy, z


def _sample_points(scene: Scene, cams: list, num_points: int, rng: np.random.Generator):
    """Points on surfaces visible in the views with tracks (>= 2 views, occlusion-checked).

    Returns ``(xyz (P, 3) float64, colour (P, 3) float64 in [0, 1], tracks)`` where ``tracks[p]`` is a
    list of ``(view index, x, y)`` with the exact continuous projection of the (noise-free) point.
    Colours are the anti-aliased colour at the point in its source view (a pixel-sized box filter),
    like SfM colours taken from images.
    """
    Ks = [np.asarray(c.K, np.float64) for c in cams]
    w2cs = [np.asarray(c.world_to_camera, np.float64) for c in cams]
    per_view = int(np.ceil(2.0 * num_points / len(cams)))
    xyz, col, prim = [], [], []
    for v, cam in enumerate(cams):
        x = rng.uniform(0.5, cam.width - 0.5, per_view)
        y = rng.uniform(0.5, cam.height - 0.5, per_view)
        o, d = camera_rays(Ks[v], w2cs[v], x, y)
        t, index = scene.trace(o, d)
        hit = index >= 0
        # Box-filtered colour over the pixel-sized square centred on the point's projection.
        offs = (np.arange(4) + 0.5) / 4 - 0.5
        shape = (int(hit.sum()), 4, 4)
        gx = np.broadcast_to(x[hit, None, None] + offs[None, None, :], shape)
        gy = np.broadcast_to(y[hit, None, None] + offs[None, :, None], shape)
        oo, dd = camera_rays(Ks[v], w2cs[v], gx, gy)
        c = scene.radiance(oo, dd).reshape(-1, 16, 3).mean(1)
        xyz.append(o[hit] + t[hit, None] * d[hit])
        col.append(c)
        prim.append(index[hit])
    xyz, col, prim = (np.concatenate(a) for a in (xyz, col, prim))
    tracks = [[] for _ in range(len(xyz))]
    for v, cam in enumerate(cams):
        xy, z = _project(Ks[v], w2cs[v], xyz)
        inside = (z > 0) & (xy[:, 0] >= 0.5) & (xy[:, 0] <= cam.width - 0.5) \
            & (xy[:, 1] >= 0.5) & (xy[:, 1] <= cam.height - 0.5)
        centre = np.linalg.inv(w2cs[v])[:3, 3]
        idx = np.nonzero(inside)[0]
        dvec = xyz[idx] - centre
        dist = np.linalg.norm(dvec, axis=1)
        t, index = scene.trace(np.broadcast_to(centre, dvec.shape).copy(), dvec / dist[:, None])
        visible = (index == prim[idx]) & (np.abs(t - dist) < 1e-6 * (1 + dist))
        for p in idx[visible]:
            tracks[p].append((v, xy[p, 0], xy[p, 1]))
    keep = np.array([len(tr) >= 2 for tr in tracks], bool)
    order = np.nonzero(keep)[0]
    if len(order) > num_points:
        order = np.sort(rng.choice(order, num_points, replace=False))
    return xyz[order], col[order], [tracks[p] for p in order]


def _write_model(folder: Path, cams, names, xyz, colors_u8, tracks) -> None:
    """Writes the COLMAP model (binary) of the scene into ``folder``: one PINHOLE camera, image ``v + 1``
    named ``names[v]`` with the pose of ``cams[v]`` and the keypoints of the tracks, 3D point ``p + 1``
    with ``xyz[p]``, ``colors_u8[p]``, its track ``tracks[p]`` of (view, x, y) and its mean
    reprojection error in pixels."""
    K = np.asarray(cams[0].K, np.float64)
    camera = ColmapCamera(1, CAMERA_MODELS_BY_NAME["PINHOLE"], cams[0].width, cams[0].height,
                          np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    keypoints: list[list[tuple[float, float]]] = [[] for _ in cams]
    observers: list[list[int]] = [[] for _ in cams]
    rows, error = [], []
    # The poses as the file stores them (rotations through unit quaternions; the cameras' float32
    # matrices are orthonormal to about 1e-7 only), so that the errors are those of the stored model.
    w2cs = []
    for cam in cams:
        w2c = np.asarray(cam.world_to_camera, np.float64)
        R = rotation_from_quaternion(quaternion_from_rotation(w2c[:3, :3]))
        w2cs.append(np.concatenate([R, w2c[:3, 3:4]], axis=1))
    for p, tr in enumerate(tracks):
        residuals = []
        for v, x, y in tr:
            rows.append((v + 1, len(keypoints[v])))
            keypoints[v].append((x, y))
            observers[v].append(p + 1)
            q = K @ (w2cs[v][:3, :3] @ xyz[p] + w2cs[v][:3, 3])
            residuals.append(np.hypot(q[0] / q[2] - x, q[1] / q[2] - y))
        error.append(np.mean(residuals))
    images = [ColmapImage(v + 1, name, 1, w2cs[v], np.asarray(keypoints[v], np.float64).reshape(-1, 2),
                          np.asarray(observers[v], np.int64))
              for v, name in enumerate(names)]
    points = ColmapPoints(ids=np.arange(1, len(xyz) + 1), xyz=np.asarray(xyz, np.float64),
                          rgb=np.asarray(colors_u8, np.uint8), error=np.asarray(error, np.float64),
                          track_length=np.array([len(tr) for tr in tracks], np.int64),
                          tracks=np.asarray(rows, np.int64).reshape(-1, 2))
    write_binary_model(folder, [camera], images, points)


# --------------------------------------------------------------------------------------------------
# On-disk generation.
# --------------------------------------------------------------------------------------------------

def _params(seed, num_views, width, height, supersample, num_points, fov_x_degrees=60.0, radius_ratio=1.5,
            elevations=(18.0, 38.0), arc_degrees=360.0):
    return dict(version=FORMAT_VERSION, seed=int(seed), num_views=int(num_views), width=int(width),
                height=int(height), supersample=int(supersample), num_points=int(num_points),
                fov_x_degrees=float(fov_x_degrees), radius_ratio=float(radius_ratio),
                elevations=[float(e) for e in elevations], arc_degrees=float(arc_degrees))


def _is_complete(out_dir: Path, params: dict) -> bool:
    try:
        stored = json.loads((out_dir / "synthetic.json").read_text())
    except (OSError, ValueError):
        return False
    if {k: stored.get(k) for k in params} != params:
        return False
    names = stored.get("images", [])
    return (len(names) == params["num_views"]
            and all((out_dir / "sparse/0" / f).is_file() for f in ("cameras.bin", "images.bin", "points3D.bin"))
            and all((out_dir / "images" / n).is_file() and (out_dir / "images_2" / n).is_file() for n in names))


def _remove_stale_temps(out_dir: Path) -> None:
    """Removes temp dirs of earlier generations into ``out_dir`` whose process is gone."""
    for tmp in out_dir.parent.glob(f".{out_dir.name}.tmp-*"):
        try:
            pid = int(tmp.name.split(".tmp-")[1].split("-")[0])
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(tmp, ignore_errors=True)
        except (ValueError, IndexError, PermissionError, OSError):
            pass


def _write_scene(tmp: Path, params: dict, verbose: bool) -> None:
    t0 = time.perf_counter()
    seed = params["seed"]
    scene = make_scene(seed)
    cams = make_cameras(seed, params["num_views"], params["width"], params["height"],
                        fov_x_degrees=params["fov_x_degrees"], radius_ratio=params["radius_ratio"],
                        elevations=params["elevations"], arc_degrees=params["arc_degrees"])
    names = [f"img_{k:04d}.png" for k in range(len(cams))]
    (tmp / "images").mkdir(parents=True)
    (tmp / "images_2").mkdir()
    for cam, name in zip(cams, names):
        img = np.round(255.0 * scene.render(cam, params["supersample"])).astype(np.uint8)
        save_image(img, tmp / "images" / name)
        save_image(box_downsample(img, 2, dtype=np.uint8), tmp / "images_2" / name)
    t1 = time.perf_counter()
    rng = np.random.default_rng([seed, 0x901275])
    xyz, col, tracks = _sample_points(scene, cams, params["num_points"], rng)
    xyz = xyz + rng.normal(0.0, 0.003, xyz.shape)  # SfM-like triangulation noise (metres)
    col_u8 = np.clip(np.round(255.0 * col + rng.normal(0.0, 1.5, col.shape)), 0, 255).astype(np.uint8)
    (tmp / "sparse/0").mkdir(parents=True)
    _write_model(tmp / "sparse/0", cams, names, xyz, col_u8, tracks)
    meta = dict(params, images=names, num_points3D=len(xyz),
                note="patexgs_jax synthetic scene (world z up, metres); see patexgs_jax/data/synthetic.py")
    (tmp / "synthetic.json").write_text(json.dumps(meta, indent=1) + "\n")
    if verbose:
        print(f"synthetic: rendered {len(cams)} views {params['width']}x{params['height']} "
              f"({params['supersample']}x{params['supersample']} supersampling) in {t1 - t0:.1f}s, "
              f"{len(xyz)} points in {time.perf_counter() - t1:.1f}s", file=sys.stderr)


def generate(out_dir, seed: int = 0, num_views: int = 24, width: int = 128, height: int = 96,
             supersample: int = 4, num_points: int = 3000, fov_x_degrees: float = 60.0,
             radius_ratio: float = 1.5, elevations=(18.0, 38.0), arc_degrees: float = 360.0,
             overwrite: bool = False, verbose: bool = False) -> Path:
    """Generates (or reuses) the synthetic COLMAP scene of ``seed`` in ``out_dir``.

    Args:
      out_dir: target directory. It is written atomically: everything goes into a hidden temp dir
        next to it which is renamed at the end, so an interrupted generation leaves no partial
        ``out_dir``. If ``out_dir`` already holds a complete scene with the same parameters and
        :data:`FORMAT_VERSION`, it is reused as is.
      seed: everything (textures, layout, cameras, points) is a deterministic function of it.
      num_views: number of images (ring cameras, see :func:`make_cameras`).
      width, height: image size in pixels (``images_2`` is ``width // 2`` by ``height // 2``).
      supersample: samples per pixel along each axis for anti-aliasing.
      num_points: maximum number of 3D points (points seen by >= 2 views are kept).
      fov_x_degrees, radius_ratio, elevations, arc_degrees: camera layout, see :func:`make_cameras`.
      overwrite: replace an existing different synthetic scene in ``out_dir`` (a directory that is
        not a synthetic scene is never removed).
      verbose: print timings to stderr.
    Returns:
      ``out_dir`` as a :class:`pathlib.Path`.
    Raises:
      FileExistsError: ``out_dir`` exists, is not empty, and is not this scene (and not
        ``overwrite`` of a synthetic scene).
    """
    out_dir = Path(out_dir).expanduser().absolute()
    if num_views < 2 or width < 2 or height < 2 or supersample < 1 or num_points < 1:
        raise ValueError("generate: need num_views >= 2, width, height >= 2, supersample >= 1, num_points >= 1.")
    params = _params(seed, num_views, width, height, supersample, num_points, fov_x_degrees, radius_ratio,
                     elevations, arc_degrees)
    if _is_complete(out_dir, params):
        return out_dir
    replace = False
    if out_dir.exists():
        if not out_dir.is_dir():
            raise FileExistsError(f"{out_dir} exists and is not a directory.")
        if any(out_dir.iterdir()):
            if not (overwrite and (out_dir / "synthetic.json").is_file()):
                raise FileExistsError(
                    f"{out_dir} is not empty and does not hold the synthetic scene with these parameters; "
                    "choose another directory (or pass overwrite=True / --overwrite to replace a synthetic scene).")
            replace = True
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(out_dir)
    if verbose:
        print(f"synthetic: generating scene (seed {seed}) in {out_dir} ...", file=sys.stderr)
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        _write_scene(tmp, params, verbose)
        if out_dir.exists():
            if replace:
                old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
                out_dir.rename(old)
                shutil.rmtree(old, ignore_errors=True)
            else:
                out_dir.rmdir()  # empty (checked above); fails if someone filled it meanwhile
        try:
            tmp.rename(out_dir)
        except OSError:
            if _is_complete(out_dir, params):  # another process generated it concurrently
                return out_dir
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def default_scene_dir(seed: int = 0) -> Path:
    """Cache location of the default scene: ``$PATEXGS_CACHE/synthetic-v1-seed0`` if the environment
    variable ``PATEXGS_CACHE`` is set, else ``~/.cache/patexgs_jax/synthetic-v1-seed0``."""
    root = os.environ.get("PATEXGS_CACHE")
    root = Path(root).expanduser() if root else Path.home() / ".cache" / "patexgs_jax"
    return root / f"synthetic-v{FORMAT_VERSION}-seed{int(seed)}"


def ensure_default_scene(seed: int = 0, verbose: bool = True) -> Path:
    """The default scene's directory (:func:`default_scene_dir`), generated there first if missing."""
    return generate(default_scene_dir(seed), seed=seed, verbose=verbose)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.data.synthetic",
                                 description="Generate the synthetic COLMAP scene (Mip-NeRF 360 layout).")
    ap.add_argument("out_dir", type=Path, help="folder to write the COLMAP scene into (images/, sparse/0/)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the scene's content and cameras (default 0)")
    ap.add_argument("--num-views", type=int, default=24, help="cameras around the scene (default 24)")
    ap.add_argument("--width", type=int, default=128, help="image width in pixels (default 128)")
    ap.add_argument("--height", type=int, default=96, help="image height in pixels (default 96)")
    ap.add_argument("--supersample", type=int, default=4,
                    help="samples per pixel side of the anti-aliased renders (default 4)")
    ap.add_argument("--num-points", type=int, default=3000,
                    help="points of the sparse model (the SfM stand-in; default 3000)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing synthetic scene")
    a = ap.parse_args(argv)
    try:
        path = generate(a.out_dir, seed=a.seed, num_views=a.num_views, width=a.width, height=a.height,
                        supersample=a.supersample, num_points=a.num_points, overwrite=a.overwrite, verbose=True)
    except (OSError, ValueError) as e:
        if isinstance(e, OSError) and e.errno is not None:  # the system's: a path through a file, a full disk
            e = f"cannot write {a.out_dir} ({e.strerror}: {e.filename}): pass OUT_DIR a folder you can write to."
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
