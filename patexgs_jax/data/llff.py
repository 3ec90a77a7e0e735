"""LLFF scenes: ``poses_bounds.npy`` + ``images/`` (+ ``images_N/``).

``poses_bounds.npy`` holds an (N, 17) array, one row per image in name-sorted order of ``images/``:
a 3x5 matrix ``[R | t | hwf]`` flattened row-major, then ``near, far``. The rotation columns are the
camera's *down, right, backwards* axes in world coordinates (LLFF convention), ``t`` the camera centre
and ``hwf = (height, width, focal)`` of the full-resolution images (principal point at the centre).
They are converted to OpenCV axes (x right = column 1, y down = column 0, z forward = -column 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .colmap import default_resolution
from .colmap_model import find_sparse_dir, model_points, read_model
from .dataset import Dataset
from .errors import DatasetError
from .images import (
    DEFAULT_IMAGE_CACHE_BYTES,
    DEFAULT_IMAGE_CACHE_SIZE,
    ImageCache,
    image_loader,
    list_images,
    probe_image,
)
from .records import (
    DEFAULT_NUM_RANDOM_POINTS,
    check_size_against_camera,
    finish_dataset,
    fit_records_to_width,
    handle_unreadable,
    orthonormalize_pose,
    random_points_in_frustums,
)

__all__ = ["load_llff", "llff_to_opencv_c2w", "opencv_c2w_to_llff"]


def llff_to_opencv_c2w(pose_3x5) -> np.ndarray:
    """(4, 4) OpenCV camera-to-world from an LLFF (3, 5) ``[down, right, back | centre | hwf]`` pose."""
    p = np.asarray(pose_3x5, np.float64)
    c2w = np.eye(4)
    c2w[:3, 0] = p[:, 1]
    c2w[:3, 1] = p[:, 0]
    c2w[:3, 2] = -p[:, 2]
    c2w[:3, 3] = p[:, 3]
    return c2w


def opencv_c2w_to_llff(c2w, height: float, width: float, focal: float) -> np.ndarray:
    """(3, 5) LLFF pose (inverse of :func:`llff_to_opencv_c2w`) for a (4, 4) OpenCV camera-to-world."""
    c2w = np.asarray(c2w, np.float64)
    out = np.empty((3, 5))
    out[:, 0] = c2w[:3, 1]
    out[:, 1] = c2w[:3, 0]
    out[:, 2] = -c2w[:3, 2]
    out[:, 3] = c2w[:3, 3]
    out[:, 4] = [height, width, focal]
    return out


def load_llff(path, factor: int | None = None, test_every: int | None = 8, skip_missing: bool = False, *,
              normalize: bool = False, cache_dir=None, image_cache_size: int = DEFAULT_IMAGE_CACHE_SIZE,
              image_cache_bytes: int | None = DEFAULT_IMAGE_CACHE_BYTES,
              background=(1.0, 1.0, 1.0), num_random_points: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0,
              images: str = "images", verbose: bool = True) -> Dataset:
    """Loads an LLFF scene folder.

    Args:
      path: folder with ``poses_bounds.npy`` and ``images/``.
      factor: downsampling factor (None -> Mip-NeRF 360 default by folder name, else full size with
        images wider than 1600 px resized to 1600 wide, as 3DGS; see :func:`default_resolution`). If
        ``images_<factor>/`` exists it is used, its files matched to the poses by *sorted order* (names
        may differ, e.g. ``IMG_001.JPG`` vs ``image000.png``) and K scaled by the actual size ratio per
        axis; otherwise ``images/`` is box-downsampled (``W // f x H // f``, K / f).
      test_every: every ``test_every``-th name-sorted image is a test view (0 / None: none).
      skip_missing: drop images that cannot be read (their pose rows are dropped too). Missing files
        cannot be skipped: the pose rows are matched by order, so a count mismatch is always an error.
      normalize, cache_dir, image_cache_size, image_cache_bytes, background, verbose: as for :func:`load_colmap`
        (``cache_dir`` is unused: LLFF images are pinhole).
      num_random_points, seed: without a COLMAP model in ``sparse/``, the initial points are
        ``num_random_points`` seeded random points, uniform in the image and depth between each
        camera's near and far bound. With a model, its points3D are used.
      images: name of the full-resolution image folder.

    Returns:
      a :class:`Dataset` (``format="llff"``; views carry ``near`` / ``far``). View names are the file
      names in ``images/``.

    Raises:
      DatasetError: malformed ``poses_bounds.npy``, image count mismatch, unreadable images, sizes that
        disagree with ``hwf``.
    """
    scene = Path(path)
    pb_path = scene / "poses_bounds.npy"
    try:
        pb = np.load(pb_path, allow_pickle=False)
    except FileNotFoundError:
        raise DatasetError(f"{pb_path} not found: an LLFF scene needs poses_bounds.npy.") from None
    except Exception as e:
        raise DatasetError(f"Cannot read {pb_path} ({type(e).__name__}: {e}); regenerate it with LLFF's "
                           "imgs2poses.py.") from None
    if pb.ndim != 2 or pb.shape[1] != 17 or pb.shape[0] == 0:
        raise DatasetError(f"{pb_path} has shape {pb.shape}; expected (N, 17) with N >= 1 (3x5 pose + near, far "
                           "per image). Regenerate it with LLFF's imgs2poses.py.")
    pb = pb.astype(np.float64)
    if not np.all(np.isfinite(pb)):
        raise DatasetError(f"{pb_path} contains non-finite values; regenerate it.")
    n = pb.shape[0]
    poses = pb[:, :15].reshape(n, 3, 5)
    bounds = pb[:, 15:17]

    factor, max_width = default_resolution(scene, factor)
    if factor < 1:
        raise DatasetError(f"factor must be a positive integer, got {factor}.")
    base = scene / images
    if not base.is_dir():
        raise DatasetError(f"Image folder {base} not found: an LLFF scene needs its images in {base}.")
    base_files = list_images(base)
    if len(base_files) != n:
        raise DatasetError(f"{pb_path} has {n} poses but {base} has {len(base_files)} images; the rows are matched "
                           "to the name-sorted images, so the counts must agree (restore the missing images or "
                           "regenerate poses_bounds.npy).")
    folder, folder_factor, files = base, 1, base_files
    if factor > 1 and (scene / f"{images}_{factor}").is_dir():
        folder, folder_factor = scene / f"{images}_{factor}", factor
        files = list_images(folder)
        if len(files) != n:
            raise DatasetError(f"{folder} has {len(files)} images but {pb_path} has {n} poses; regenerate "
                               f"{folder.name}/ or pass another factor.")
    post = factor // folder_factor

    records, problems = [], []
    for i in range(n):
        h_full, w_full, focal = poses[i, :, 4]
        size, why = probe_image(files[i])
        if size is None:
            problems.append((files[i], why))
            continue
        rx, ry = check_size_against_camera(files[i], size, (w_full, h_full), folder_factor,
                                           f"row {i} of {pb_path} (hwf)")
        K = np.array([[focal * rx, 0.0, 0.5 * size[0]], [0.0, focal * ry, 0.5 * size[1]], [0.0, 0.0, 1.0]])
        if post > 1:
            K = np.diag([1.0 / post, 1.0 / post, 1.0]) @ K
        w, h = size[0] // post, size[1] // post
        if w < 1 or h < 1:
            raise DatasetError(f"factor {factor} leaves no pixel of the {size[0]}x{size[1]} image {files[i]}.")
        c2w = orthonormalize_pose(llff_to_opencv_c2w(poses[i]), f"{pb_path} row {i}")
        records.append(dict(name=base_files[i].name, K=K, w2c=np.linalg.inv(c2w), width=w, height=h,
                            image_path=files[i], near=bounds[i, 0], far=bounds[i, 1],
                            load=image_loader(files[i], post, background)))
    skipped = handle_unreadable(problems, n, f"{pb_path} (images in {folder})", skip_missing)
    records, ratio = fit_records_to_width(records, max_width, background, verbose)
    applied: float = ratio if ratio > 1 else factor
    if not records:
        raise DatasetError(f"No readable image in {folder}.")

    sparse = find_sparse_dir(scene)
    info = {"image_folder": str(folder), "skipped": skipped, "bounds": bounds}
    if sparse is not None:
        ids, pts, cols = model_points(read_model(sparse))
        source = "sfm"
        info["sparse"] = str(sparse)
        if not ids.size:
            pts = cols = None
            source = "random"
    else:
        pts = cols = None
        source = "random"

    def rand(norm):
        cams = [(r["K"], r["w2c"], r["width"], r["height"], r["near"], r["far"]) for r in records]
        return random_points_in_frustums(cams, num_random_points, seed)

    return finish_dataset(records, fmt="llff", path=scene, factor=applied, test_every=test_every,
                          normalize=normalize, points=pts, colors=cols, points_source=source,
                          cache=ImageCache(image_cache_size, image_cache_bytes), info=info, random_points=rand)

