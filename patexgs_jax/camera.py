"""Pinhole cameras in the OpenCV / COLMAP convention.

Conventions, fixed for the whole package:

* camera frame: x right, y down, z forward (OpenCV / COLMAP);
* ``world_to_camera`` is a 4x4 rigid transform mapping homogeneous world points to camera points;
* pixel (row i, column j) has its centre at continuous image coordinates (x, y) = (j + 0.5, i + 0.5),
  so that ``K @ p_cam`` gives continuous coordinates directly (as COLMAP's intrinsics do).

A :class:`Camera` is a pytree: ``K`` and ``world_to_camera`` are array leaves (a new pose or focal
length does not recompile a jitted renderer), ``width`` and ``height`` are static.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

#: The zoom-out factors of the paper's protocol (Table 2; 1 = full resolution): the studies evaluate
#: and the viewer renders at ``Camera.scaled(s)`` for each.
ZOOM_SCALES = (1, 2, 4, 8)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
      K: (3, 3) float intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in continuous pixel
        coordinates (pixel centres at j + 0.5, i + 0.5).
      world_to_camera: (4, 4) float rigid transform, OpenCV axes.
      width: image width in pixels (static).
      height: image height in pixels (static).
    """

    K: jax.Array
    world_to_camera: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True))
    height: int = dataclasses.field(metadata=dict(static=True))

    @classmethod
    def from_intrinsics(cls, K, world_to_camera, width: int, height: int) -> Camera:
        """Builds a camera, checking shapes and values.

        Args:
          K: (3, 3) intrinsics, or a 4-sequence ``(fx, fy, cx, cy)``.
          world_to_camera: (4, 4) or (3, 4) world-to-camera transform.
          width, height: positive image size in pixels.
        """
        K = np.asarray(K, dtype=np.float64)
        if K.shape == (4,):
            fx, fy, cx, cy = K
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        if K.shape != (3, 3):
            raise ValueError(f"Camera intrinsics K must have shape (3, 3) or (4,), got {K.shape}.")
        # (finite as float32 too: values beyond 3.4e38 would be stored as inf)
        if not np.all(np.abs(K) < np.finfo(np.float32).max) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"Camera intrinsics must be finite with positive focal lengths, got K={K.tolist()}.")
        w2c = np.asarray(world_to_camera, dtype=np.float64)
        if w2c.shape == (3, 4):
            w2c = np.concatenate([w2c, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
        if w2c.shape != (4, 4):
            raise ValueError(
                f"world_to_camera must have shape (4, 4) or (3, 4), got {w2c.shape}."
            )
        if not np.all(np.abs(w2c) < np.finfo(np.float32).max):
            raise ValueError("world_to_camera has non-finite entries; check the pose source.")
        R = w2c[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise ValueError(
                "world_to_camera's rotation block is not a rotation (R R^T != I or det < 0); "
                "pass a rigid OpenCV-convention world-to-camera matrix (invert camera-to-world poses)."
            )
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise ValueError(f"Image size must be positive, got width={width}, height={height}.")
        return cls(K=jax.numpy.asarray(K, jax.numpy.float32),
                   world_to_camera=jax.numpy.asarray(w2c, jax.numpy.float32),
                   width=width, height=height)

    def scaled(self, factor: int) -> Camera:
        """The camera of the image box-downsampled by an integer ``factor`` (zoom-out view).

        A block of ``factor x factor`` pixels becomes one pixel, so continuous coordinates are divided
        by ``factor``: fx, fy, cx, cy are all divided by it, which keeps pixel centres consistent
        (new centre j + 0.5 is the centre of old pixels [factor*j, factor*(j+1))). The size is
        ``width // factor`` by ``height // factor`` (a partial last block is cropped).
        """
        factor = int(factor)
        if factor < 1:
            raise ValueError(f"scale factor must be a positive integer, got {factor}.")
        if self.width // factor < 1 or self.height // factor < 1:
            raise ValueError(f"factor {factor} leaves no pixel of a {self.width}x{self.height} image.")
        scale = np.diag([1.0 / factor, 1.0 / factor, 1.0]).astype(np.float32)
        return Camera(K=jax.numpy.asarray(scale @ np.asarray(self.K)), world_to_camera=self.world_to_camera,
                      width=self.width // factor, height=self.height // factor)

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4, 4) float64 inverse of ``world_to_camera`` (host-side)."""
        return np.linalg.inv(np.asarray(self.world_to_camera, np.float64))

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 camera centre in world coordinates (host-side)."""
        return self.camera_to_world[:3, 3]


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """(4, 4) world-to-camera matrix (OpenCV axes) of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear up in the image (the camera's -y axis).
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the viewing direction is parallel to `up`; choose another up vector.")
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=0)
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c
