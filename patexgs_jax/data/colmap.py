"""COLMAP scenes: ``sparse/0`` (or ``sparse/``) + ``images/`` (+ Mip-NeRF 360 ``images_2/4/8``).

Models are found, checked and read by :mod:`.colmap_model` (``.bin`` or ``.txt``, our own reader:
PINHOLE and SIMPLE_PINHOLE scenes load without pycolmap). Distorted camera models are undistorted once
with ``pycolmap.undistort_images`` into the cache folder (see
:func:`~patexgs_jax.data.cache.resolve_cache_dir`), written atomically and reused afterwards; only that
step needs pycolmap.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import numpy as np

from .cache import atomic_build_dir, fingerprint, is_complete_dir, resolve_cache_dir
from .colmap_model import find_sparse_dir, model_points, read_model
from .dataset import Dataset
from .errors import DatasetError, pycolmap_module, warn
from .images import (
    DEFAULT_IMAGE_CACHE_BYTES,
    DEFAULT_IMAGE_CACHE_SIZE,
    IMAGE_EXTENSIONS,
    ImageCache,
    image_loader,
    image_size,
    list_images,
    probe_image,
)
from .records import (
    DEFAULT_NUM_RANDOM_POINTS,
    check_size_against_camera,
    finish_dataset,
    fit_records_to_width,
    handle_unreadable,
    random_points_in_box,
)

__all__ = [
    "load_colmap",
    "default_factor",
    "default_resolution",
    "DEFAULT_MAX_WIDTH",
    "MIPNERF360_FACTORS",
    "PINHOLE_MODELS",
]

#: Default downsampling factors of the Mip-NeRF 360 scenes (3DGS / Mip-NeRF 360 evaluation protocol).
MIPNERF360_FACTORS = {
    **{s: 4 for s in ("bicycle", "flowers", "garden", "stump", "treehill")},
    **{s: 2 for s in ("room", "counter", "kitchen", "bonsai")},
}
#: Camera models used as they are (no distortion).
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
#: Without a factor, images wider than this many pixels are resized to this width (the 3DGS rule).
DEFAULT_MAX_WIDTH = 1600


def default_resolution(scene: Path, factor: int | None) -> tuple[int, int | None]:
    """``(factor, max_width)`` of a scene loaded with ``factor``: an explicit factor as it is (no
    width limit); None -> the Mip-NeRF 360 factor for those scene names (:func:`default_factor`),
    else factor 1 with images wider than :data:`DEFAULT_MAX_WIDTH` resized to that width."""
    if factor is not None:
        return int(factor), None
    named = default_factor(scene)
    return (named, None) if named != 1 else (1, DEFAULT_MAX_WIDTH)


def default_factor(scene: Path) -> int:
    """Default image downsampling factor for a scene folder: 4 for the Mip-NeRF 360 outdoor scenes
    (bicycle, flowers, garden, stump, treehill), 2 for the indoor ones (room, counter, kitchen, bonsai),
    1 otherwise (decided by the folder name)."""
    return MIPNERF360_FACTORS.get(Path(scene).resolve().name, 1)


# ----------------------------------------------------------------------------------------------------
# Loader
# ----------------------------------------------------------------------------------------------------


def _intrinsics(cam) -> np.ndarray:
    p = np.asarray(cam.params, np.float64)
    name = cam.model.name
    if name == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif name == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    else:  # pragma: no cover - guarded by the callers
        raise DatasetError(f"internal: camera model {name} is not a pinhole model.")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _resolve_image_files(names: list[str], folder: Path, base_folder: Path) -> dict[str, Path | None]:
    """Maps image names to files in ``folder``: exact name, else same stem with another image
    extension, else (when ``folder`` has exactly as many images as ``base_folder``) by sorted order."""
    out: dict[str, Path | None] = {}
    missing = []
    for n in names:
        p = folder / n
        if p.is_file():
            out[n] = p
            continue
        alt = [q for q in (p.with_suffix(e) for e in IMAGE_EXTENSIONS + tuple(x.upper() for x in IMAGE_EXTENSIONS))
               if q.is_file()]
        out[n] = alt[0] if alt else None
        if not alt:
            missing.append(n)
    if missing and folder != base_folder and base_folder.is_dir():
        base = [p.name for p in list_images(base_folder)]
        files = list_images(folder)
        if len(base) == len(files) and len(files) > 0:
            by_order = dict(zip(base, files))
            for n in missing:
                out[n] = by_order.get(n)
    return out


def load_colmap(path, factor: int | None = None, test_every: int | None = 8, skip_missing: bool = False, *,
                normalize: bool = False, cache_dir=None, image_cache_size: int = DEFAULT_IMAGE_CACHE_SIZE,
              image_cache_bytes: int | None = DEFAULT_IMAGE_CACHE_BYTES,
                background=(1.0, 1.0, 1.0), num_random_points: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0,
                images: str = "images", verbose: bool = True) -> Dataset:
    """Loads a COLMAP scene folder.

    Layout: ``<scene>/sparse/0/`` (or ``<scene>/sparse/``) with cameras/images/points3D ``.bin`` or
    ``.txt``; images in ``<scene>/images/`` named as in the model; optional ``images_N/`` (Mip-NeRF 360
    downsampled copies, same names, or the same count of files matched by sorted order).

    Args:
      path: scene folder.
      factor: image downsampling factor; None -> :func:`default_resolution` (the Mip-NeRF 360 factors
        for those scene names, else full size with images wider than 1600 px resized to 1600 wide
        with an area filter and K scaled per axis, as 3DGS).
        If ``images_<factor>`` exists it is used and K is scaled per axis by the actual size ratio
        (``w_N / W``, ``h_N / H``); otherwise ``images/`` is box-downsampled to ``W // f x H // f`` and K
        divided by ``f`` (pixel-centre consistent, like :meth:`Camera.scaled`).
      test_every: every ``test_every``-th name-sorted image is a test view (0 / None: no test views).
      skip_missing: drop views whose image is missing or unreadable (printing how many) instead of
        raising.
      normalize: apply the 3DGS similarity (centre -> 0, radius -> 1) to cameras and points; the
        mapping back is recorded in ``dataset.normalization``.
      cache_dir: root folder for derived data (undistorted images); see ``resolve_cache_dir``.
      image_cache_size, image_cache_bytes: at most this many decoded images, and bytes of them, are
        kept in memory (LRU; defaults 64 and 2 GiB; None: no byte bound).
      background: (3,) RGB in [0, 1] for compositing images with alpha.
      num_random_points, seed: used only if the model has no 3D points (a :class:`DatasetWarning` is
        emitted and random points fill the cube of half-side 0.5 x the largest camera distance around
        the mean camera centre).
      images: name of the full-resolution image folder.
      verbose: print a message when undistorting / skipping.

    Returns:
      a :class:`Dataset` (``format="colmap"``); cameras are PINHOLE (distorted models are undistorted
      with pycolmap and cached).

    Raises:
      DatasetError: no model, unreadable / corrupt model, no registered images, missing image folder,
        missing / unreadable images (unless ``skip_missing``), image size that disagrees with its camera,
        camera model that cannot be undistorted.
    """
    scene = Path(path)
    sparse = find_sparse_dir(scene)
    if sparse is None:
        raise DatasetError(f"No COLMAP model in {scene}: expected sparse/0/ or sparse/ with cameras, images "
                           "and points3D (.bin or .txt).")
    rec = read_model(sparse)
    point_ids, pts, cols = model_points(rec)  # before undistorting, which keeps the points as they are
    reg = sorted(rec.images.values(), key=lambda im: im.name)  # COLMAP writes registered images only
    if not reg:
        raise DatasetError(f"The COLMAP model in {sparse} has no registered images: the reconstruction failed; "
                           "re-run COLMAP mapping.")
    factor, max_width = default_resolution(scene, factor)
    if factor < 1:
        raise DatasetError(f"factor must be a positive integer, got {factor}.")

    base_folder = scene / images
    folder, folder_factor = base_folder, 1
    if factor > 1 and (scene / f"{images}_{factor}").is_dir():
        folder, folder_factor = scene / f"{images}_{factor}", factor
    post = factor // folder_factor
    if not folder.is_dir():
        raise DatasetError(f"Image folder {folder} not found: a COLMAP scene needs its images in "
                           f"{scene}/{images}/ with the names used in {sparse}.")

    # Resolve files, check headers and sizes.
    files = _resolve_image_files([im.name for im in reg], folder, base_folder)
    kept, problems, ratios = [], [], {}
    for im in reg:
        f = files[im.name]
        size, why = probe_image(f)
        if size is None or f is None:
            problems.append((f if f is not None else folder / im.name, why))
            continue
        cam = rec.cameras[im.camera_id]
        ratios[im.name] = check_size_against_camera(
            f, size, (cam.width, cam.height), folder_factor,
            f"its camera {im.camera_id} ({cam.model.name} {cam.width}x{cam.height}) in {sparse}")
        kept.append(im)
    skipped = handle_unreadable(problems, len(reg), f"the COLMAP model {sparse} (images in {folder})", skip_missing)
    if not kept:
        raise DatasetError(f"None of the {len(reg)} registered images of {sparse} could be read from {folder}.")

    info = {"sparse": str(sparse), "image_folder": str(folder), "skipped": skipped}
    models = sorted({rec.cameras[im.camera_id].model.name for im in kept})
    distorted = [m for m in models if m not in PINHOLE_MODELS]
    undistorted_dir = None
    if distorted:
        for m in distorted:
            cam = next(rec.cameras[im.camera_id] for im in kept if rec.cameras[im.camera_id].model.name == m)
            if not cam.model.perspective:
                raise DatasetError(f"Camera model {m} (in {sparse}) is not a perspective model and cannot be "
                                   "undistorted to a pinhole camera; convert the capture to perspective images "
                                   "(e.g. cube maps) and re-run COLMAP.")
        undistorted_dir = _undistort(scene, sparse, rec, kept, files, ratios, folder, cache_dir, distorted, verbose)
        info["undistorted_from"] = models
        info["undistorted_dir"] = str(undistorted_dir)
        rec = read_model(undistorted_dir / "sparse")
        by_name = {im.name: im for im in rec.images.values()}
        und_images = undistorted_dir / "images"
        new_kept = []
        for im in kept:
            uim = by_name.get(im.name)
            f = und_images / im.name
            if uim is None or not f.is_file():
                if not skip_missing:
                    raise DatasetError(f"pycolmap could not undistort {files[im.name]} (no output in {und_images}); "
                                       "the image is probably corrupt: replace it or use skip_missing=True.")
                skipped.append(im.name)
                continue
            files[im.name] = f
            cam = rec.cameras[uim.camera_id]
            ratios[im.name] = check_size_against_camera(
                f, image_size(f), (cam.width, cam.height), 1, f"its undistorted camera in {undistorted_dir}")
            new_kept.append(uim)
        kept = new_kept

    records = []
    for im in kept:
        cam = rec.cameras[im.camera_id]
        rx, ry = ratios[im.name]
        K = _intrinsics(cam)
        K = np.diag([rx, ry, 1.0]) @ K  # images_N: per-axis ratio of actual size (exact 1 otherwise)
        w_file = int(round(cam.width * rx))
        h_file = int(round(cam.height * ry))
        if post > 1:
            K = np.diag([1.0 / post, 1.0 / post, 1.0]) @ K
        w, h = w_file // post, h_file // post
        if w < 1 or h < 1:
            raise DatasetError(f"factor {factor} leaves no pixel of the {w_file}x{h_file} image {files[im.name]}.")
        w2c = np.eye(4)
        w2c[:3, :] = im.cam_from_world
        records.append(dict(name=im.name, K=K, w2c=w2c, width=w, height=h, image_path=files[im.name],
                            load=image_loader(files[im.name], post, background)))
    records, ratio = fit_records_to_width(records, max_width, background, verbose)
    applied: float = ratio if ratio > 1 else factor

    if point_ids.size:
        source = "sfm"
    else:
        warn(f"The COLMAP model in {sparse} has no 3D points; using {num_random_points} random points "
             "(seeded) around the cameras instead. Re-run COLMAP triangulation for a better initialisation.")
        pts = cols = None
        source = "random"

    def rand(norm):
        half = 0.5 * norm.original_radius / 1.1
        return random_points_in_box(norm.original_center, half, num_random_points, seed)

    return finish_dataset(records, fmt="colmap", path=scene, factor=applied, test_every=test_every,
                          normalize=normalize, points=pts, colors=cols, points_source=source,
                          cache=ImageCache(image_cache_size, image_cache_bytes), info=info, random_points=rand)


def _undistort(scene, sparse, rec, kept, files, ratios, folder, cache_dir, distorted, verbose) -> Path:
    """Undistorts the kept images once into the cache (atomically); returns the folder holding
    ``images/`` and ``sparse/`` of the undistorted (PINHOLE) model."""
    names = [im.name for im in kept]
    rescale = {}
    for im in kept:
        cam = rec.cameras[im.camera_id]
        rx, ry = ratios[im.name]
        if abs(rx - 1) > 1e-12 or abs(ry - 1) > 1e-12:
            rescale[im.camera_id] = (int(round(cam.width * rx)), int(round(cam.height * ry)))
    # Files whose names differ from the model's (images_N matched by order) need renaming: link them.
    renamed = {n: files[n] for n in names
               if files[n].name != Path(n).name or files[n].parent != folder / Path(n).parent}
    sparse_files = sorted(p for p in sparse.iterdir() if p.is_file())
    key = fingerprint("undistort-v1", *sparse_files, folder.resolve(), names, sorted(rescale.items()),
                      *[files[n] for n in names])
    root = resolve_cache_dir(scene, cache_dir) / "undistorted"
    final = root / f"{folder.name}-{key}"
    if is_complete_dir(final):
        return final

    pycolmap = pycolmap_module("Undistorting a COLMAP scene's images")

    def build(tmp: Path):
        src_model = sparse
        src_images = folder
        if rescale or renamed:
            r2 = pycolmap.Reconstruction(str(sparse))
            for cid, (w, h) in rescale.items():
                cam = r2.cameras[cid]
                cam.rescale(w, h)
                r2.cameras[cid] = cam
            src_model = tmp / "input_model"
            src_model.mkdir()
            r2.write_binary(str(src_model))
        if renamed:
            src_images = tmp / "input_images"
            for n in names:
                dst = src_images / n
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.symlink_to(files[n].resolve())
        out = tmp / "out"
        if verbose:
            print(f"[patexgs_jax] {scene}: {len(names)} images use distorted camera models "
                  f"({', '.join(distorted)}); undistorting them once with pycolmap into {final} "
                  "(reused on later loads) ...", file=sys.stderr, flush=True)
        t0 = time.time()
        old = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = max(old, 2)
        try:
            pycolmap.undistort_images(str(out), str(src_model), str(src_images), image_names=names,
                                      jpeg_quality=100)
        except Exception as e:
            raise DatasetError(
                f"pycolmap failed to undistort the images of {scene} ({type(e).__name__}: {e}).") from None
        finally:
            pycolmap.logging.minloglevel = old
        (out / "images").rename(tmp / "images")
        (out / "sparse").rename(tmp / "sparse")
        for extra in ("out", "input_model", "input_images"):
            _rmtree(tmp / extra)
        if verbose:
            print(f"[patexgs_jax] undistortion done in {time.time() - t0:.1f} s.", file=sys.stderr, flush=True)

    try:
        return atomic_build_dir(final, build)
    except OSError as e:
        raise DatasetError(f"Cannot write the undistortion cache {final} ({e}); pass cache_dir= or set "
                           "PATEXGS_CACHE to a writable folder.") from None


def _rmtree(p: Path):
    if p.is_symlink() or p.is_file():
        p.unlink()
    elif p.exists():
        shutil.rmtree(p)
