"""The format loaders' shared steps, from per-view records to a :class:`~.dataset.Dataset`.

A loader turns its files into records (one dict per view: name, intrinsics, pose, size, a lazy image
loader), checks the images against their cameras, drops or reports unreadable ones, applies the
default resolution rule, and hands the records to :func:`finish_dataset` (the train/test split,
the 3DGS normalisation, the views, the point cloud or random initial points).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..camera import Camera
from .dataset import Dataset, View, compute_normalization, split_indices
from .errors import DatasetError
from .images import ImageCache, image_loader

__all__ = [
    "DEFAULT_NUM_RANDOM_POINTS",
    "check_size_against_camera",
    "finish_dataset",
    "fit_records_to_width",
    "handle_unreadable",
    "orthonormalize_pose",
    "random_points_in_box",
    "random_points_in_frustums",
]

#: Default number of random initial points when a scene has no point cloud (3DGS uses 100k for Blender).
DEFAULT_NUM_RANDOM_POINTS = 100_000


def finish_dataset(records: list[dict], *, fmt: str, path: Path, factor: float, test_every, normalize: bool,
                   points, colors, points_source: str, cache: ImageCache, info: dict | None = None,
                   splits: tuple[list[int], list[int]] | None = None, random_points=None) -> Dataset:
    """Builds a :class:`Dataset` from per-view records (internal helper shared by the loaders).

    Each record is a dict with ``name``, ``K`` (3, 3) float64, ``w2c`` (4, 4) float64 (original
    coordinates), ``width``, ``height``, ``load`` (callable returning the (H, W, 3) image), optionally
    ``image_path``, ``near``, ``far``. Records are sorted by name; ``splits`` (indices into the *given*
    order) overrides ``test_every``. ``random_points`` is a callable ``(normalization) -> (points,
    colors)`` used when ``points`` is None.
    """
    if not records:
        raise DatasetError(f"No usable views in {path}.")
    order = sorted(range(len(records)), key=lambda i: records[i]["name"])
    if splits is not None:
        train_idx = sorted(splits[0], key=lambda i: records[i]["name"])
        test_idx = sorted(splits[1], key=lambda i: records[i]["name"])
    else:
        tr, te = split_indices(len(order), test_every)
        train_idx = [order[k] for k in tr]
        test_idx = [order[k] for k in te]
    # 3DGS normalises with the training cameras (all cameras if there is no training view).
    centers = np.stack([-r["w2c"][:3, :3].T @ r["w2c"][:3, 3] for r in (
        [records[i] for i in train_idx] if train_idx else records)])
    norm = compute_normalization(centers, normalize=normalize)
    if points is None:
        if random_points is None:
            raise ValueError("finish_dataset needs points or random_points.")
        points, colors = random_points(norm)
    T = norm.transform
    s = norm.scale
    views = {}
    for i in order:
        r = records[i]
        w2c = r["w2c"]
        if normalize:
            w2c = norm.from_original_world_to_camera(w2c)
        try:
            cam = Camera.from_intrinsics(r["K"], w2c, r["width"], r["height"])
        except ValueError as e:
            raise DatasetError(f"{path}: invalid camera for view {r['name']!r}: {e}") from None
        near, far = r.get("near"), r.get("far")
        if normalize and near is not None:
            near, far = near * s, None if far is None else far * s
        views[i] = View(cam, r["name"], r["load"], cache=cache, key=(i, 1), image_path=r.get("image_path"),
                        near=near, far=far)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if normalize:
        points = points @ T[:3, :3].T + T[:3, 3]
    return Dataset(train_views=tuple(views[i] for i in train_idx), test_views=tuple(views[i] for i in test_idx),
                   points=points.astype(np.float32),
                   colors=None if colors is None else np.asarray(colors, np.float32).reshape(-1, 3),
                   points_source=points_source, normalization=norm, format=fmt, path=Path(path),
                   factor=factor if isinstance(factor, float) else int(factor), image_cache=cache,
                   info=dict(info or {}))


def handle_unreadable(problems: list[tuple[str, str]], total: int, source: str, skip_missing: bool) -> list[str]:
    """Raises (or, with ``skip_missing``, prints and returns the skipped names) for missing/unreadable images.

    Args:
      problems: ``(path or name, reason)`` for each bad image.
      total: number of images the source lists.
      source: what lists them (e.g. the COLMAP model folder), for the message.
    """
    if not problems:
        return []
    listed = "; ".join(f"{p} {why}" for p, why in problems[:5]) + ("; ..." if len(problems) > 5 else "")
    if not skip_missing:
        raise DatasetError(f"{len(problems)} of {total} images listed by {source} are missing or unreadable: {listed}. "
                           "Restore them, or load with skip_missing=True to drop those views.")
    print(f"[patexgs_jax] skip_missing: skipped {len(problems)} of {total} images listed by {source} "
          f"(missing or unreadable): {listed}", file=sys.stderr, flush=True)
    return [str(p) for p, _ in problems]


def fit_records_to_width(records: list[dict], max_width: int | None, background,
                         verbose: bool) -> tuple[list[dict], float]:
    """Applies the default resolution rule to loader records (see :func:`finish_dataset`): the
    images wider than ``max_width`` are resized to ``max_width`` pixels wide (height
    ``H * max_width // W``) with an area filter, their intrinsics scaled per axis, and one line says
    so. Returns the records and the largest downscaling ratio applied (1.0 when none).
    """
    if max_width is None:
        return records, 1.0
    wide = [r for r in records if r["width"] > max_width]
    if not wide:
        return records, 1.0
    out = []
    for r in records:
        if r["width"] <= max_width:
            out.append(r)
            continue
        w, h = int(max_width), max(1, r["height"] * int(max_width) // r["width"])
        K = np.diag([w / r["width"], h / r["height"], 1.0]) @ np.asarray(r["K"], np.float64)
        out.append(dict(r, K=K, width=w, height=h, load=image_loader(r["image_path"], 1, background, size=(w, h)),
                        full_size=(r["width"], r["height"])))
    big = max(wide, key=lambda r: r["width"])
    ratio = big["width"] / max_width
    if verbose:
        small = next(r for r in out if r["name"] == big["name"])
        print(f"[patexgs_jax] {len(wide)} of {len(records)} images are wider than {max_width} px (up to "
              f"{big['width']}x{big['height']}): training at {small['width']}x{small['height']}, downscaled "
              f"{ratio:.3g}x with an area filter, as 3DGS does; --factor 1 (factor=1) keeps the full size.",
              file=sys.stderr, flush=True)
    return out, ratio


def check_size_against_camera(path: Path, file_size: tuple[int, int], cam_size: tuple[float, float],
                              folder_factor: int, what: str) -> tuple[float, float]:
    """Checks an image's (w, h) against its full-resolution camera size divided by ``folder_factor``.

    Mip-NeRF 360's ``images_N`` folders round the size (not floor), so any size within one pixel of
    ``camera_size / N`` is accepted; the returned per-axis ratios ``(w / W, h / H)`` are what the
    intrinsics must be scaled by. With ``folder_factor == 1`` the sizes must match exactly.

    Raises:
      DatasetError naming the file, both sizes and the fix.
    """
    w, h = file_size
    W, H = cam_size
    f = int(folder_factor)
    if f == 1:
        ok = abs(w - W) < 0.5 and abs(h - H) < 0.5
    else:
        ok = abs(w * f - W) < f and abs(h * f - H) < f
    if not ok:
        expect = f"{W:g}x{H:g}" if f == 1 else f"about {W / f:g}x{H / f:g} (= {W:g}x{H:g} / {f})"
        raise DatasetError(
            f"Image {path} is {w}x{h} but {what} expects {expect}. The image does not belong to this "
            f"camera model (wrong folder, rotated/resized image?): replace it with the original, or fix "
            f"the camera model.")
    return w / W, h / H


def orthonormalize_pose(c2w: np.ndarray, source: str) -> np.ndarray:
    """Projects the rotation block of a (4, 4) camera-to-world onto SO(3) (float32 rounding in files).

    Raises:
      DatasetError if the block is far from a rotation (scaled / sheared / reflected pose).
    """
    c2w = np.array(c2w, np.float64)
    R = c2w[:3, :3]
    U, S, Vt = np.linalg.svd(R)
    if not np.all(np.isfinite(c2w)) or np.abs(S - 1).max() > 1e-2 or np.linalg.det(R) < 0:
        raise DatasetError(f"{source}: the camera rotation is not a rotation matrix (singular values "
                           f"{np.round(S, 4).tolist()}, det {np.linalg.det(R):.3g}); poses must be rigid "
                           "camera-to-world transforms.")
    c2w[:3, :3] = U @ Vt
    c2w[3] = [0.0, 0.0, 0.0, 1.0]
    return c2w


# ----------------------------------------------------------------------------------------------------
# Random initial points
# ----------------------------------------------------------------------------------------------------


def random_points_in_box(center, half_extent: float, count: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0):
    """Uniform random points in an axis-aligned cube, with uniform random colours (as 3DGS's Blender init).

    Args:
      center: (3,) cube centre.
      half_extent: half the cube's side.
      count: number of points.
      seed: numpy Generator seed (deterministic).

    Returns:
      (points (count, 3) float64, colors (count, 3) float32 in [0, 1]).
    """
    rng = np.random.default_rng(seed)
    pts = np.asarray(center, np.float64) + rng.uniform(-half_extent, half_extent, size=(int(count), 3))
    cols = rng.uniform(0.0, 1.0, size=(int(count), 3)).astype(np.float32)
    return pts, cols


def random_points_in_frustums(cameras: Sequence[tuple[np.ndarray, np.ndarray, int, int, float, float]],
                              count: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0):
    """Uniform-in-image random points between near and far depth bounds of random cameras.

    Args:
      cameras: sequence of ``(K (3, 3), w2c (4, 4), width, height, near, far)``.
      count: number of points.
      seed: numpy Generator seed.

    Returns:
      (points (count, 3) float64 world coordinates, colors (count, 3) float32 uniform in [0, 1]).
    """
    rng = np.random.default_rng(seed)
    count = int(count)
    which = rng.integers(0, len(cameras), size=count)
    pts = np.empty((count, 3))
    u, v, t = rng.uniform(size=(3, count))
    for c, (K, w2c, w, h, near, far) in enumerate(cameras):
        m = which == c
        if not m.any():
            continue
        pix = np.stack([u[m] * w, v[m] * h, np.ones(m.sum())], axis=-1)
        rays = pix @ np.linalg.inv(K).T
        depth = near + t[m] * (far - near)
        p_cam = rays * depth[:, None]
        c2w = np.linalg.inv(w2c)
        pts[m] = p_cam @ c2w[:3, :3].T + c2w[:3, 3]
    cols = rng.uniform(0.0, 1.0, size=(count, 3)).astype(np.float32)
    return pts, cols
