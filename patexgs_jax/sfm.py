"""Turn a folder of photos into a Mip-NeRF 360 style COLMAP dataset with pycolmap.

``python -m patexgs_jax.sfm IMAGES_DIR OUT_DIR [--matcher auto|exhaustive|sequential]``

Stages: SIFT feature extraction (CPU) -> matching (exhaustive for <= 50 images, sequential
otherwise) -> incremental mapping (largest model kept) -> undistortion to PINHOLE -> layout::

    OUT_DIR/images/        undistorted images (same names and format as the input)
    OUT_DIR/images_{2,4,8}/ box-downsampled copies (size ``floor(size / f)``, as Camera.scaled)
    OUT_DIR/sparse/0/{cameras,images,points3D}.bin   PINHOLE cameras

Working files (feature database, distorted model) live in ``OUT_DIR/.work`` and are removed at the
end (pass ``keep_work=True`` / ``--keep-work`` to keep them for debugging).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import PIL.Image

from ._pycolmap import pycolmap
from .data import images

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".JPG", ".JPEG", ".PNG")
DOWNSAMPLE_FACTORS = (2, 4, 8)
MIN_IMAGES = 3
EXHAUSTIVE_MAX_IMAGES = 50


class SfmError(RuntimeError):
    """A user-facing failure of :func:`reconstruct` (bad input or reconstruction failure)."""


def box_downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """:func:`patexgs_jax.data.images.box_downsample` in the input's dtype (uint8 rounded to nearest),
    as the ``images_N`` files are written."""
    image = np.asarray(image)
    return images.box_downsample(image, factor, dtype=image.dtype)


def write_downsampled(images_dir, out_root, factors=DOWNSAMPLE_FACTORS) -> None:
    """Writes ``out_root/images_{f}/NAME`` for every image of ``images_dir`` and each factor."""
    images_dir, out_root = Path(images_dir), Path(out_root)
    for f in factors:
        (out_root / f"images_{f}").mkdir(parents=True, exist_ok=True)
    for path in sorted(p for p in images_dir.rglob("*") if p.is_file()):
        with PIL.Image.open(path) as im:
            img = np.asarray(im.convert("RGB"))
        rel = path.relative_to(images_dir)
        for f in factors:
            target = out_root / f"images_{f}" / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            images.save_image(box_downsample(img, f), target)


def _list_images(images_dir: Path) -> list[str]:
    return sorted(str(p.relative_to(images_dir)) for p in images_dir.rglob("*")
                  if p.is_file() and p.suffix in IMAGE_EXTENSIONS)


def _log(verbose: bool, msg: str) -> None:
    if verbose:
        print(msg, flush=True)


def reconstruct(images_dir, out_dir, matcher: str = "auto", camera_model: str = "SIMPLE_RADIAL",
            single_camera: bool = True, verbose: bool = True, keep_work: bool = False,
            num_threads: int = -1, colmap_log: bool = False) -> Path:
    """Structure-from-motion on a folder of images, written in the Mip-NeRF 360 layout.

    Args:
      images_dir: folder of JPEG/PNG images (subfolders are included).
      out_dir: output folder (created; existing ``images*``/``sparse`` in it are replaced).
      matcher: ``"auto"`` (exhaustive for <= 50 images, else sequential), ``"exhaustive"`` or
        ``"sequential"`` (for ordered video-like captures).
      camera_model: COLMAP model estimated during mapping (e.g. ``SIMPLE_RADIAL``, ``OPENCV``,
        ``PINHOLE``); the output is always undistorted to PINHOLE.
      single_camera: all images share one camera (same device and zoom).
      verbose: print stages, counts and timings.
      keep_work: keep ``out_dir/.work`` (feature database, distorted model).
      num_threads: CPU threads for pycolmap (-1: all).
      colmap_log: show COLMAP's own (very detailed) log; otherwise only its errors.
    Returns:
      ``out_dir`` as a :class:`pathlib.Path`.
    Raises:
      SfmError: missing/empty folder, too few images, or a failed reconstruction (with hints).
    """
    if matcher not in ("auto", "exhaustive", "sequential"):
        raise ValueError(f"matcher must be 'auto', 'exhaustive' or 'sequential', got {matcher!r}.")
    if camera_model not in pycolmap.CameraModelId.__members__:
        raise ValueError(f"Unknown COLMAP camera model {camera_model!r}; e.g. SIMPLE_RADIAL, OPENCV, PINHOLE.")
    images_dir = Path(images_dir).expanduser().absolute()
    out_dir = Path(out_dir).expanduser().absolute()
    if not images_dir.is_dir():
        raise SfmError(f"Image folder {images_dir} does not exist (or is not a folder): pass the folder "
                           "that holds your photos.")
    names = _list_images(images_dir)
    if not names:
        raise SfmError(f"No images ({', '.join(sorted({e.lower() for e in IMAGE_EXTENSIONS}))}) "
                           f"found in {images_dir}.")
    if len(names) < MIN_IMAGES:
        raise SfmError(f"Only {len(names)} image(s) in {images_dir}; structure-from-motion needs at least "
                           f"{MIN_IMAGES} overlapping views (20-200 is typical).")
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= EXHAUSTIVE_MAX_IMAGES else "sequential"
    if out_dir == images_dir or out_dir / "images" == images_dir:
        raise SfmError("OUT_DIR must differ from IMAGES_DIR and not contain it as OUT_DIR/images.")

    from .checkpoint import CheckpointError, check_output_dir

    try:
        check_output_dir(out_dir, "OUT_DIR")
    except CheckpointError as e:
        raise SfmError(str(e)) from None
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if colmap_log else 2  # 0 INFO, 1 WARNING, 2 ERROR
    work = out_dir / ".work"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    t_start = time.perf_counter()
    try:
        database = work / "database.db"
        _log(verbose, f"[sfm] {len(names)} images in {images_dir}")

        t0 = time.perf_counter()
        _log(verbose, "[sfm] 1/5 feature extraction (SIFT, CPU)")
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.use_gpu = False
        pycolmap.extract_features(database, images_dir, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(database)
        try:
            num_db_images = db.num_images()
            num_keypoints = db.num_keypoints()
        finally:
            db.close()
        _log(verbose, f"[sfm]     {num_db_images} images, {num_keypoints} keypoints "
                      f"({time.perf_counter() - t0:.1f}s)")
        if num_keypoints == 0:
            raise SfmError("No features were found in the images: are they blank, or too small? "
                               "Structure-from-motion needs textured, overlapping photos.")

        t0 = time.perf_counter()
        _log(verbose, f"[sfm] 2/5 {matcher} matching")
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        matching.use_gpu = False
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_sequential(database, matching_options=matching, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(database)
        try:
            _, inliers = db.read_two_view_geometry_num_inliers()
        finally:
            db.close()
        num_pairs = sum(1 for n in inliers if n > 0)
        _log(verbose, f"[sfm]     {num_pairs} geometrically verified pairs, {sum(inliers)} inlier matches "
                      f"({time.perf_counter() - t0:.1f}s)")
        if num_pairs == 0:
            raise SfmError(
                "No image pairs could be matched. The photos need overlapping, textured content; "
                + ("try --matcher exhaustive if the images are not an ordered sequence."
                   if matcher == "sequential" else "check that they show the same scene."))

        t0 = time.perf_counter()
        _log(verbose, "[sfm] 3/5 incremental mapping")
        sparse = work / "sparse"
        sparse.mkdir()
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = num_threads
        reconstructions = pycolmap.incremental_mapping(database, images_dir, sparse, options=options)
        if not reconstructions:
            raise SfmError(
                "Mapping failed: no initial image pair could be reconstructed. Try photos with more overlap "
                "(consecutive views sharing ~60% of their content) and more parallax (move the camera, do not "
                "only rotate it)" + (", or --matcher exhaustive." if matcher == "sequential" else "."))
        best = max(reconstructions.values(), key=lambda r: r.num_reg_images())
        num_reg = best.num_reg_images()
        _log(verbose, f"[sfm]     {len(reconstructions)} model(s); largest registers {num_reg}/{len(names)} "
                      f"images, {best.num_points3D()} points ({time.perf_counter() - t0:.1f}s)")
        if num_reg < max(MIN_IMAGES, int(np.ceil(0.2 * len(names)))):
            raise SfmError(
                f"Mapping registered only {num_reg} of {len(names)} images. Try more overlap between views, "
                "more texture, fewer motion-blurred photos, "
                + ("--matcher exhaustive (sequential matching assumes an ordered capture)."
                   if matcher == "sequential" else "or --matcher sequential for an ordered video-like capture."))
        if num_reg < len(names):
            _log(verbose, f"[sfm]     warning: {len(names) - num_reg} image(s) could not be registered "
                          "and are left out.")
        model = work / "model"
        model.mkdir()
        best.write(model)

        t0 = time.perf_counter()
        _log(verbose, "[sfm] 4/5 undistortion to PINHOLE")
        undistorted = work / "undistorted"
        pycolmap.undistort_images(undistorted, model, images_dir, output_type="COLMAP", num_threads=num_threads)
        for name in ("images", "sparse", *(f"images_{f}" for f in DOWNSAMPLE_FACTORS)):
            target = out_dir / name
            if target.is_dir():
                shutil.rmtree(target)
        shutil.move(undistorted / "images", out_dir / "images")
        (out_dir / "sparse/0").mkdir(parents=True)
        src_sparse = undistorted / "sparse"
        if (src_sparse / "0").is_dir():
            src_sparse = src_sparse / "0"
        for f in sorted(src_sparse.glob("*.bin")):
            shutil.move(f, out_dir / "sparse/0" / f.name)
        rec = pycolmap.Reconstruction(out_dir / "sparse/0")
        models = {c.model_name for c in rec.cameras.values()}
        _log(verbose, f"[sfm]     {rec.num_reg_images()} images, cameras {sorted(models)} "
                      f"({time.perf_counter() - t0:.1f}s)")

        t0 = time.perf_counter()
        _log(verbose, f"[sfm] 5/5 downsampling x{', x'.join(map(str, DOWNSAMPLE_FACTORS))}")
        write_downsampled(out_dir / "images", out_dir)
        _log(verbose, f"[sfm]     done ({time.perf_counter() - t0:.1f}s)")
    finally:
        pycolmap.logging.minloglevel = old_level
        if not keep_work:
            shutil.rmtree(work, ignore_errors=True)
    _log(verbose, f"[sfm] wrote {out_dir} in {time.perf_counter() - t_start:.1f}s")
    return out_dir


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m patexgs_jax.sfm",
                                 description="Structure-from-motion (pycolmap) on a folder of photos, "
                                             "written in the Mip-NeRF 360 layout.")
    ap.add_argument("images_dir", type=Path, help="folder of the photos (JPEG or PNG)")
    ap.add_argument("out_dir", type=Path, help="scene folder to write (images/, sparse/0/: the Mip-NeRF 360 layout)")
    ap.add_argument("--matcher", choices=("auto", "exhaustive", "sequential"), default="auto",
                    help="auto: exhaustive for <= 50 images, sequential otherwise")
    ap.add_argument("--camera-model", default="SIMPLE_RADIAL",
                    help="COLMAP camera model to estimate (default SIMPLE_RADIAL; "
                    "undistorted when the scene is loaded)")
    ap.add_argument("--multiple-cameras", action="store_true",
                    help="estimate one camera per image size/EXIF instead of one shared camera")
    ap.add_argument("--keep-work", action="store_true", help="keep OUT_DIR/.work (database, distorted model)")
    ap.add_argument("--colmap-log", action="store_true", help="show COLMAP's own detailed log")
    ap.add_argument("--quiet", action="store_true", help="print only errors")
    a = ap.parse_args(argv)
    try:
        reconstruct(a.images_dir, a.out_dir, matcher=a.matcher, camera_model=a.camera_model,
                single_camera=not a.multiple_cameras, verbose=not a.quiet, keep_work=a.keep_work,
                colmap_log=a.colmap_log)
    except (SfmError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
