"""Builders of small on-disk scenes (COLMAP, LLFF, transforms.json) for tests/unit/test_data_loaders.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import PIL.Image

from patexgs_jax._pycolmap import pycolmap  # (keeps the fatal-signal handlers, see there)
from patexgs_jax.camera import look_at

# Parameters per model: (fx or f, [fy], cx, cy, distortion...) for a W x H camera, built in camera_params.
DISTORTION = {
    "SIMPLE_RADIAL": [0.04],
    "RADIAL": [0.04, -0.01],
    "OPENCV": [0.03, -0.01, 0.002, -0.001],
    "FULL_OPENCV": [0.03, -0.01, 0.002, -0.001, 0.001, 0.0, 0.0, 0.0],
    "OPENCV_FISHEYE": [0.02, -0.005, 0.001, 0.0],
}


def camera_params(model: str, W: int, H: int, f: float = 50.0) -> list[float]:
    """Plausible parameters of a ``model`` camera (principal point slightly off-centre)."""
    cx, cy = 0.5 * W + 0.7, 0.5 * H - 0.4
    if model == "SIMPLE_PINHOLE":
        return [f, cx, cy]
    if model == "PINHOLE":
        return [f, 1.05 * f, cx, cy]
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        return [f, cx, cy] + DISTORTION[model]
    if model in ("OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"):
        return [f, 1.02 * f, cx, cy] + DISTORTION[model]
    if model == "EQUIRECTANGULAR":
        return [float(W), float(H)]
    raise ValueError(model)


def ring_poses(n: int, radius: float = 4.0, height: float = 0.7, seed: int = 0) -> list[np.ndarray]:
    """(4, 4) world-to-camera matrices of ``n`` cameras on a ring looking at (about) the origin."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n + 0.1
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height + 0.1 * k])
        target = rng.normal(scale=0.05, size=3)
        out.append(look_at(eye, target, up=(0.0, 0.0, 1.0)))
    return out


def random_image(W: int, H: int, seed: int, channels: int = 3) -> np.ndarray:
    """(H, W, channels) uint8 random image."""
    return np.random.default_rng(seed).integers(0, 256, size=(H, W, channels), dtype=np.uint8)


def save_png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    PIL.Image.fromarray(arr).save(path)


def make_colmap_scene(root: Path, models=("PINHOLE",), n_images: int = 6, W: int = 40, H: int = 30,
                      text: bool = False, n_points: int = 25, write_images: bool = True, sparse_sub: str = "sparse/0",
                      image_fn=None, seed: int = 0) -> dict:
    """Writes ``root/sparse/0`` (bin or txt) and ``root/images/*.png``.

    Image k uses camera ``k % len(models) + 1`` (one camera per model). Returns a dict with the
    reconstruction (``rec``), ``names`` (sorted), per-name ``K`` (3, 3) (pinhole part), ``w2c`` (4, 4),
    ``image`` uint8, ``camera_id``, and ``points`` (M, 3), ``colors`` uint8 (M, 3) in point-id order.
    """
    root = Path(root)
    rec = pycolmap.Reconstruction()
    for cid, model in enumerate(models, start=1):
        cam = pycolmap.Camera.create_from_model_name(cid, model, 50.0, W, H)
        cam.params = camera_params(model, W, H)
        rec.add_camera_with_trivial_rig(cam)
    out = {"rec": rec, "names": [], "K": {}, "w2c": {}, "image": {}, "camera_id": {}}
    for k, w2c in enumerate(ring_poses(n_images, seed=seed)):
        name = f"img_{k:03d}.png"
        cid = k % len(models) + 1
        im = pycolmap.Image(name=name, camera_id=cid, image_id=k + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
        p = rec.cameras[cid].params
        if models[cid - 1] == "EQUIRECTANGULAR":
            K = None
        elif models[cid - 1] in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            K = np.array([[p[0], 0, p[1]], [0, p[0], p[2]], [0, 0, 1.0]])
        else:
            K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        img = image_fn(k, W, H) if image_fn else random_image(W, H, seed=1000 + k)
        if write_images:
            save_png(root / "images" / name, img)
        out["names"].append(name)
        out["K"][name], out["w2c"][name], out["image"][name], out["camera_id"][name] = K, w2c, img, cid
    rng = np.random.default_rng(seed + 7)
    pts = rng.uniform(-1, 1, size=(n_points, 3))
    cols = rng.integers(0, 256, size=(n_points, 3), dtype=np.uint8)
    for x, c in zip(pts, cols):
        rec.add_point3D(x, pycolmap.Track(), c)
    ids = sorted(rec.points3D.keys())
    out["points"] = np.array([rec.points3D[i].xyz for i in ids])
    out["colors"] = np.array([rec.points3D[i].color for i in ids], np.uint8).reshape(-1, 3)
    sparse = root / sparse_sub
    sparse.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(sparse))
    out["sparse"] = sparse
    return out


def write_llff(root: Path, c2ws, hwf, bounds) -> None:
    """Writes ``root/poses_bounds.npy`` from OpenCV camera-to-world matrices."""
    from patexgs_jax.data.llff import opencv_c2w_to_llff

    rows = [np.concatenate([opencv_c2w_to_llff(c, *hwf).ravel(), b]) for c, b in zip(c2ws, bounds)]
    np.save(root / "poses_bounds.npy", np.array(rows))


def write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))


def opengl_c2w(w2c_cv: np.ndarray) -> list:
    """The transforms.json ``transform_matrix`` (OpenGL camera-to-world) of an OpenCV world-to-camera."""
    return (np.linalg.inv(w2c_cv) @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()


def make_3dgs_layout(scene: Path, root: Path, scenes: dict) -> dict:
    """Copies a COLMAP scene (its ``images/`` and ``sparse/0``) into ``root`` as 3DGS distributes
    Tanks and Temples and Deep Blending: ``scenes`` maps a dataset folder to its scene names, e.g.
    ``{"tandt": ["truck"], "db": ["drjohnson"]}``. Returns ``{name: folder}``."""
    import shutil

    out = {}
    for folder, names in scenes.items():
        for name in names:
            target = Path(root) / folder / name
            shutil.copytree(Path(scene) / "images", target / "images")
            shutil.copytree(Path(scene) / "sparse" / "0", target / "sparse" / "0")
            out[name] = target
    return out
