"""The loaded scene: :class:`Dataset`, its posed :class:`View` s and its :class:`SceneNormalization`.

Everything here is host-side numpy (jax is only touched to build :class:`~patexgs_jax.camera.Camera`).

* :class:`View` -- one posed image: a :class:`Camera`, a name and a lazily loaded ``(H, W, 3)`` float32
  image in [0, 1] (read on first access of ``view.image`` and kept in a bounded LRU
  :class:`~.images.ImageCache`: at most a set number of images and of bytes).
* :class:`Dataset` -- train/test views, an initial point cloud and the :class:`SceneNormalization`.
* the 3DGS train/test split (:func:`split_indices`), the 3DGS scene normalisation
  (:func:`compute_normalization`) and zoom-out views (:func:`zoom_out_views`).

The format loaders' shared steps are in :mod:`.records`, image files in :mod:`.images`, cache
folders in :mod:`.cache`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from ..camera import Camera
from .errors import DatasetError
from .images import ImageCache, box_downsample

__all__ = [
    "Dataset",
    "SceneNormalization",
    "View",
    "compute_normalization",
    "split_indices",
    "zoom_out_views",
]


class View:
    """One posed image of a dataset.

    Attributes:
      camera: the :class:`Camera` (OpenCV axes, K in continuous pixel coordinates).
      name: image name as in the source (e.g. the COLMAP image name ``"0001.jpg"``); scaled views
        keep the name of the view they come from.
      scale: integer zoom-out factor relative to the loaded view (1 for views of a :class:`Dataset`).
      image_path: the file the pixels come from (after undistortion / ``images_N`` selection), or None.
      near, far: optional depth bounds (LLFF ``poses_bounds.npy``), else None.
      image: (H, W, 3) float32 in [0, 1] with (H, W) = (camera.height, camera.width); loaded on access
        and held in the dataset's bounded LRU cache. Read-only.
    """

    __slots__ = ("camera", "name", "scale", "image_path", "near", "far", "_load", "_cache", "_key")

    def __init__(self, camera: Camera, name: str, load: Callable[[], np.ndarray], *, cache: ImageCache,
                 key=None, scale: int = 1, image_path=None, near=None, far=None):
        self.camera = camera
        self.name = str(name)
        self.scale = int(scale)
        self.image_path = None if image_path is None else Path(image_path)
        self.near = None if near is None else float(near)
        self.far = None if far is None else float(far)
        self._load = load
        self._cache = cache
        self._key = key if key is not None else (id(self), self.scale)

    @property
    def image(self) -> np.ndarray:
        """(H, W, 3) float32 image in [0, 1], loaded lazily (LRU-cached, read-only)."""
        return self._cache.get(self._key, self._checked_load)

    def _checked_load(self) -> np.ndarray:
        img = np.asarray(self._load(), dtype=np.float32)
        want = (self.camera.height, self.camera.width, 3)
        if img.shape != want:
            src = self.image_path if self.image_path is not None else self.name
            raise DatasetError(f"Image {src} decoded to shape {img.shape} but its camera expects {want}; "
                               "the file changed after loading the dataset: reload it.")
        return img

    def scaled(self, factor: int) -> View:
        """The zoom-out view: image box-downsampled by ``factor`` and ``camera.scaled(factor)``.

        The image is cropped to a multiple of ``factor`` and averaged over ``factor x factor`` blocks,
        which is exactly consistent with :meth:`Camera.scaled` (continuous coordinates divided by
        ``factor``). The result shares this view's image cache.

        Args:
          factor: positive integer.

        Returns:
          a :class:`View` of size (height // factor, width // factor) with ``scale = self.scale * factor``.
        """
        factor = int(factor)
        if factor == 1:
            return self
        camera = self.camera.scaled(factor)
        parent = self
        return View(camera, self.name, lambda: box_downsample(parent.image, factor), cache=self._cache,
                    key=(self._key, factor), scale=self.scale * factor, image_path=self.image_path,
                    near=self.near, far=self.far)

    def __repr__(self) -> str:
        return (f"View(name={self.name!r}, {self.camera.width}x{self.camera.height}, scale={self.scale}, "
                f"image_path={str(self.image_path) if self.image_path else None!r})")


def zoom_out_views(views: Sequence[View], factors: Iterable[int] = (2, 4, 8)) -> dict[int, list[View]]:
    """For each factor, the zoom-out (box-downsampled) version of every view.

    Args:
      views: sequence of N views (typically ``dataset.test_views``).
      factors: positive integer zoom-out factors.

    Returns:
      ``{factor: [views[0].scaled(factor), ..., views[N-1].scaled(factor)]}`` (lists aligned with
      ``views``; images load lazily).
    """
    return {int(f): [v.scaled(int(f)) for v in views] for f in factors}


# ----------------------------------------------------------------------------------------------------
# Scene normalisation
# ----------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SceneNormalization:
    """The 3DGS scene normalisation and the similarity (if any) applied to the loaded scene.

    Attributes:
      center: (3,) float64 mean centre of the training cameras (all cameras if there is no training
        view), in the *dataset's* (returned) coordinates.
      radius: 1.1 x the largest distance of those camera centres from ``center`` (dataset
        coordinates); 3DGS's ``cameras_extent``.
      transform: (4, 4) float64 similarity mapping original (file) world coordinates to dataset
        coordinates, ``x_dataset = s * R x_original + t`` (identity unless ``normalize=True``).
      original_center, original_radius: the same statistics in the original coordinates.
    """

    center: np.ndarray
    radius: float
    transform: np.ndarray
    original_center: np.ndarray
    original_radius: float

    @property
    def applied(self) -> bool:
        """Whether the cameras and points were transformed (``normalize=True``)."""
        return not np.allclose(self.transform, np.eye(4))

    @property
    def scale(self) -> float:
        """Scale ``s`` of :attr:`transform` (dataset length = s * original length)."""
        return float(np.cbrt(np.linalg.det(self.transform[:3, :3])))

    def to_original_points(self, points) -> np.ndarray:
        """Maps (..., 3) dataset-coordinate points to original coordinates; returns float64."""
        inv = np.linalg.inv(self.transform)
        p = np.asarray(points, np.float64)
        return p @ inv[:3, :3].T + inv[:3, 3]

    def from_original_points(self, points) -> np.ndarray:
        """Maps (..., 3) original-coordinate points to dataset coordinates; returns float64."""
        p = np.asarray(points, np.float64)
        return p @ self.transform[:3, :3].T + self.transform[:3, 3]

    def to_original_length(self, length):
        """Converts lengths (e.g. Gaussian scales, depths) from dataset to original units (``/ s``)."""
        return np.asarray(length, np.float64) / self.scale

    def to_original_world_to_camera(self, world_to_camera) -> np.ndarray:
        """(4, 4) world-to-camera of the original scene for a dataset-coordinate (4, 4) world-to-camera.

        Camera-space lengths are in original units (the similarity's scale is undone).
        """
        w2c = np.asarray(world_to_camera, np.float64) @ self.transform
        out = np.eye(4)
        out[:3, :] = w2c[:3, :] / self.scale
        return out

    def from_original_world_to_camera(self, world_to_camera) -> np.ndarray:
        """(4, 4) dataset-coordinate world-to-camera for an original-coordinate (4, 4) world-to-camera."""
        w2c = np.asarray(world_to_camera, np.float64) @ np.linalg.inv(self.transform)
        out = np.eye(4)
        out[:3, :] = w2c[:3, :] * self.scale
        return out


def compute_normalization(camera_centers, normalize: bool = False) -> SceneNormalization:
    """The 3DGS normalisation of a set of camera centres.

    ``center`` = mean camera centre, ``radius`` = 1.1 * max distance of a centre from it (the loaders
    pass the training cameras, as 3DGS does, or all cameras when there is no training view; a single
    camera gives radius 1.1 * 1, so the radius is never 0, as in 3DGS when all centres coincide).

    Args:
      camera_centers: (N, 3) camera centres in original world coordinates (N >= 1).
      normalize: if True the recorded transform maps ``x -> (x - center) / radius`` (so the normalised
        scene has centre 0 and radius 1); otherwise it is the identity.

    Returns:
      a :class:`SceneNormalization`.
    """
    c = np.asarray(camera_centers, np.float64).reshape(-1, 3)
    center = c.mean(axis=0)
    dist = np.linalg.norm(c - center, axis=1).max()
    radius = float(1.1 * dist) if dist > 0 else 1.1
    transform = np.eye(4)
    if normalize:
        transform[:3, :3] /= radius
        transform[:3, 3] = -center / radius
        return SceneNormalization(center=np.zeros(3), radius=1.0, transform=transform,
                                  original_center=center, original_radius=radius)
    return SceneNormalization(center=center, radius=radius, transform=transform,
                              original_center=center, original_radius=radius)


# ----------------------------------------------------------------------------------------------------
# Dataset
# ----------------------------------------------------------------------------------------------------


@dataclasses.dataclass(eq=False)
class Dataset:
    """A loaded scene.

    Attributes:
      train_views, test_views: tuples of :class:`View` (sorted by name within each split).
      points: (M, 3) float32 initial point cloud (dataset coordinates).
      colors: (M, 3) float32 in [0, 1], or None when the points carry no colour.
      points_source: ``"sfm"`` (COLMAP points3D), ``"ply"`` (a PLY named by transforms.json) or
        ``"random"`` (seeded random points; see the format loaders for the region).
      normalization: the :class:`SceneNormalization` (centre, radius, and the applied similarity).
      format: ``"colmap"``, ``"llff"`` or ``"nerf"``.
      path: the scene folder (or transforms file) that was loaded.
      factor: the image downsampling factor that was applied (1 = full resolution; with the default
        resolution rule, images wider than 1600 px resized to 1600 wide, the largest ratio, e.g. 2.52).
      image_cache: the shared :class:`ImageCache` of decoded images.
      info: free-form details (e.g. ``{"undistorted_from": ..., "skipped": [...]}``).
    """

    train_views: tuple
    test_views: tuple
    points: np.ndarray
    colors: np.ndarray | None
    points_source: str
    normalization: SceneNormalization
    format: str
    path: Path
    factor: float
    image_cache: ImageCache
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def views(self) -> tuple:
        """All views (train then test)."""
        return tuple(self.train_views) + tuple(self.test_views)

    def zoom_out_views(self, factors: Iterable[int] = (2, 4, 8)) -> dict[int, list[View]]:
        """``{factor: [test_view.scaled(factor) for each test view]}``; see :func:`zoom_out_views`."""
        return zoom_out_views(self.test_views, factors)

    def __repr__(self) -> str:
        n = self.normalization
        return (f"Dataset(format={self.format!r}, path={str(self.path)!r}, factor={self.factor}, "
                f"train={len(self.train_views)}, test={len(self.test_views)}, points={len(self.points)} "
                f"({self.points_source}), center={np.round(n.center, 4).tolist()}, radius={n.radius:.4g})")


def split_indices(n: int, test_every: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The 3DGS / Mip-NeRF 360 hold-out split of ``n`` name-sorted images.

    Image ``i`` is a test image iff ``i % test_every == 0`` (so images 0, 8, 16, ... with the default
    8). ``test_every`` of 0 or None means no test split.

    Returns:
      (train_indices, test_indices), int64 arrays.
    """
    idx = np.arange(int(n))
    if not test_every:
        return idx, idx[:0]
    test_every = int(test_every)
    if test_every < 0:
        raise ValueError(f"test_every must be >= 0 or None, got {test_every}.")
    is_test = idx % test_every == 0
    return idx[~is_test], idx[is_test]
