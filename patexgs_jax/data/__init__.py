"""Dataset loaders: COLMAP, LLFF and NeRF ``transforms.json`` scenes -> :class:`Dataset`.

>>> ds = load("/data/360_v2/garden")            # factor 4 by default for Mip-NeRF 360 'garden'
>>> ds.train_views[0].camera, ds.train_views[0].image.shape   # image loads lazily (LRU-cached)
>>> ds.zoom_out_views((2, 4, 8))[4][0].image    # first test view box-downsampled by 4

Modules: :mod:`.dataset` (:class:`Dataset`, :class:`View`, :class:`SceneNormalization`, the split),
:mod:`.images` (reading, resizing, the image cache), :mod:`.records` (the loaders' shared steps),
:mod:`.cache` (cache folders), :mod:`.errors`; the formats :mod:`.colmap` (with :mod:`.colmap_model`
and :mod:`.colmap_records`), :mod:`.llff`, :mod:`.nerf`; the embedded scene :mod:`.synthetic` (with
:mod:`.synthetic_scene`); the paper's datasets: :mod:`.benchmarks` (which one a scene is, its
protocol) and :mod:`.download` (``python -m patexgs_jax.data.download``, the public archives).
"""

from __future__ import annotations

from pathlib import Path

from .cache import resolve_cache_dir
from .colmap import (
    DEFAULT_MAX_WIDTH,
    MIPNERF360_FACTORS,
    default_factor,
    default_resolution,
    load_colmap,
)
from .colmap_model import find_sparse_dir, read_model
from .dataset import Dataset, SceneNormalization, View, compute_normalization, split_indices, zoom_out_views
from .errors import DatasetError, DatasetWarning
from .images import (
    DEFAULT_IMAGE_CACHE_BYTES,
    DEFAULT_IMAGE_CACHE_SIZE,
    ImageCache,
    box_downsample,
    decode_problem,
    read_image,
)
from .llff import load_llff
from .nerf import find_transforms, load_nerf
from .records import DEFAULT_NUM_RANDOM_POINTS

__all__ = [
    "load",
    "check_images",
    "detect_format",
    "photos_without_poses_hint",
    "load_colmap",
    "load_llff",
    "load_nerf",
    "Dataset",
    "View",
    "SceneNormalization",
    "ImageCache",
    "DatasetError",
    "DatasetWarning",
    "box_downsample",
    "read_image",
    "split_indices",
    "compute_normalization",
    "zoom_out_views",
    "resolve_cache_dir",
    "default_factor",
    "default_resolution",
    "DEFAULT_MAX_WIDTH",
    "find_sparse_dir",
    "find_transforms",
    "read_model",
    "MIPNERF360_FACTORS",
    "DEFAULT_IMAGE_CACHE_SIZE",
    "DEFAULT_IMAGE_CACHE_BYTES",
    "DEFAULT_NUM_RANDOM_POINTS",
]

_LOADERS = {"colmap": load_colmap, "llff": load_llff, "nerf": load_nerf}


def photos_without_poses_hint(path) -> str | None:
    """What to do with a folder of photos that has no camera model (the photos directly in ``path``
    or in ``path/images``): run :mod:`patexgs_jax.sfm`; None when it holds no photos."""
    p = Path(path)
    for folder in (p / "images", p):
        n = sum(1 for f in folder.glob("*") if f.suffix.lower() in (".jpg", ".jpeg", ".png")) if folder.is_dir() else 0
        if n:
            out = p.resolve().with_name(p.resolve().name + "_colmap")
            return (f"It holds {n} photo(s) in {folder} but no camera poses: estimate them with "
                    f"`python -m patexgs_jax.sfm {folder} {out}` (COLMAP through pycolmap), "
                    f"then pass {out}.")
    return None


def detect_format(path) -> str:
    """The format of a scene: ``"colmap"``, ``"nerf"`` or ``"llff"``, checked in that order.

    * ``"colmap"``: ``sparse/0/`` or ``sparse/`` with cameras, images, points3D (.bin or .txt). A scene
      that also has ``poses_bounds.npy`` (Mip-NeRF 360, LLFF releases) is read as COLMAP, the more
      complete source (use ``format="llff"`` to force LLFF).
    * ``"nerf"``: ``transforms.json`` or ``transforms_train.json`` (or ``path`` is a .json file).
    * ``"llff"``: ``poses_bounds.npy``.

    Raises:
      DatasetError saying what was looked for when the path is none of these.
    """
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"Dataset path {p} does not exist: pass a scene folder (COLMAP sparse/0, "
                           "transforms.json or poses_bounds.npy).")
    if p.is_file():
        if p.suffix == ".json":
            return "nerf"
        raise DatasetError(f"{p} is a file; pass a scene folder (or a transforms .json file).")
    if find_sparse_dir(p) is not None:
        return "colmap"
    if find_transforms(p) is not None:
        return "nerf"
    if (p / "poses_bounds.npy").is_file():
        return "llff"
    hint = ""
    if (p / "sparse").is_dir():
        hint = (" (sparse/ exists but holds no complete model: it needs cameras, images and points3D, all .bin "
                "or all .txt, in sparse/0/ or sparse/)")
    photos = photos_without_poses_hint(p)
    if photos:
        raise DatasetError(f"{p} is not a recognised dataset{hint}. {photos}")
    raise DatasetError(
        f"{p} is not a recognised dataset{hint}. Looked for: a COLMAP model (sparse/0/ or sparse/ with "
        "cameras, images, points3D as .bin or .txt, images in images/), an LLFF poses_bounds.npy, or a NeRF "
        "transforms.json / transforms_train.json.")


def load(path, factor: int | None = None, test_every: int | None = 8, skip_missing: bool = False, *,
         format: str | None = None, normalize: bool = False, cache_dir=None,
         image_cache_size: int = DEFAULT_IMAGE_CACHE_SIZE,
         image_cache_bytes: int | None = DEFAULT_IMAGE_CACHE_BYTES, background=(1.0, 1.0, 1.0),
         num_random_points: int = DEFAULT_NUM_RANDOM_POINTS, seed: int = 0, verbose: bool = True) -> Dataset:
    """Loads a scene, detecting its format (see :func:`detect_format`).

    Args:
      path: scene folder (or a transforms .json file).
      factor: integer image downsampling factor. None -> 4 for the Mip-NeRF 360 outdoor scenes
        (bicycle, flowers, garden, stump, treehill), 2 for the indoor ones (room, counter, kitchen,
        bonsai), else full size, with images wider than 1600 px resized to 1600 px wide (an area
        filter; the 3DGS rule, announced on stderr); 1 keeps the full size. Uses ``images_<factor>/``
        when present (K scaled by the actual size ratio),
        else box-downsamples to ``W // f x H // f`` with K / f.
      test_every: every ``test_every``-th image (sorted by name, starting with the first) is a test
        view, the 3DGS protocol; 0 or None: no test split. (NeRF split files take precedence.)
      skip_missing: drop views with missing / unreadable images (printing how many) instead of raising.
      format: force ``"colmap"``, ``"llff"`` or ``"nerf"``.
      normalize: transform cameras and points by the 3DGS normalisation (centre -> 0, radius -> 1);
        the mapping back is in ``dataset.normalization``. Default: untouched, only recorded.
      cache_dir: root for derived data (undistorted images); default the ``PATEXGS_CACHE`` env var,
        else ``<scene>/.patexgs_cache`` if the scene folder is writable, else
        ``~/.cache/patexgs_jax/<scene>-<hash>``.
      image_cache_size, image_cache_bytes: at most this many decoded images, and bytes of them, are
        kept in memory (LRU; default 64 images and 2 GiB, None: no byte bound).
      background: (3,) RGB in [0, 1] behind transparent pixels (default white).
      num_random_points, seed: random initial points when the scene has no point cloud (default
        100,000, seed 0).
      verbose: print progress messages (undistortion, skipped images) to stderr.

    Returns:
      a :class:`Dataset`: ``train_views`` / ``test_views`` (:class:`View` with ``.camera``, lazily
      loaded ``.image`` (H, W, 3) float32 in [0, 1], ``.name``), ``points`` (M, 3) float32, ``colors``
      (M, 3) float32 in [0, 1] or None, ``normalization`` (:class:`SceneNormalization`).

    Raises:
      DatasetError (a ValueError) with the offending file and the fix.
    """
    fmt = detect_format(path) if format is None else format
    if fmt not in _LOADERS:
        raise DatasetError(f"Unknown format {fmt!r}; use one of {sorted(_LOADERS)}.")
    kwargs = dict(normalize=normalize, cache_dir=cache_dir, image_cache_size=image_cache_size,
                  image_cache_bytes=image_cache_bytes, background=background,
                  num_random_points=num_random_points, seed=seed, verbose=verbose)
    return _LOADERS[fmt](path, factor, test_every, skip_missing, **kwargs)


def check_images(dataset: Dataset, skip: bool = False, skip_hint: str = "load with skip_missing=True",
                 on_view=None) -> Dataset:
    """Decodes every view's image file (see :func:`.images.decode_problem`) before any work uses them.

    Args:
      dataset: a loaded :class:`Dataset` (its images load lazily, so a corrupt file would otherwise
        surface at its first use, after compiling and possibly hours of training).
      skip: leave the views whose file cannot be decoded out (printing which) instead of raising.
      skip_hint: how the caller turns ``skip`` on, for the error message.
      on_view: called with the number of files checked so far, after each (progress).

    Returns:
      ``dataset``, or with ``skip`` and unreadable files a copy without their views.

    Raises:
      DatasetError: a file cannot be decoded (naming each, and the fix), or no training view is left.
    """
    import dataclasses
    import sys

    problems = {}
    for i, view in enumerate(dataset.views):
        if view.image_path is not None:
            problem = decode_problem(view.image_path)
            if problem is not None:
                problems[id(view)] = f"{view.image_path} {problem}"
        if on_view is not None:
            on_view(i + 1)
    if not problems:
        return dataset
    named = "; ".join(list(problems.values())[:3]) + (f"; and {len(problems) - 3} more" if len(problems) > 3 else "")
    if not skip:
        raise DatasetError(f"{len(problems)} of {len(dataset.views)} images cannot be used: {named}. Replace "
                           f"them (re-export or re-copy), or {skip_hint} to leave those views out.")
    train = tuple(v for v in dataset.train_views if id(v) not in problems)
    test = tuple(v for v in dataset.test_views if id(v) not in problems)
    if not train:
        raise DatasetError(f"no training view is left after leaving out the unreadable images: {named}.")
    print(f"[patexgs_jax] skipped {len(problems)} of {len(dataset.views)} views whose images cannot be used: "
          f"{named}", file=sys.stderr, flush=True)
    info = dict(dataset.info, skipped=list(dataset.info.get("skipped", [])) + [
        v.name for v in dataset.views if id(v) in problems])
    return dataclasses.replace(dataset, train_views=train, test_views=test, info=info)
