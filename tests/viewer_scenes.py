"""The viewer's test scene, a run folder holding it, and cameras orbiting it (tests/unit/test_view.py,
tests/integration/test_viewer_server.py; the fixtures are in tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from patexgs_jax import checkpoint as ckpt
from patexgs_jax.camera import Camera, look_at
from patexgs_jax.scene import Scene, random_scene


def textured_scene(seed: int = 0, n: int = 300) -> Scene:
    """A random scene of n splats around the origin with 2 x 2 or 8 x 8 RGB textures and 4 x 4 alpha
    textures (few texture buckets: cheap to compile)."""
    sides = np.random.default_rng(seed).choice([2, 8], size=n)
    return random_scene(seed, n, sh_degree=1, extent=1.0, scale_range=(0.03, 0.25), rgb_sizes=sides,
                        alpha_sizes=[4] * n)


def write_run(folder: Path, scene: Scene, method: str = "patexgs") -> Path:
    """A run folder as training leaves it: checkpoints/ with the scene and its configuration."""
    ckpt.save_checkpoint(ckpt.checkpoint_path(folder / "checkpoints", 10), {"scene": scene},
                         {"step": 10, "config": {"method": method, "background": [0.0, 0.0, 0.0]}})
    return folder


def study_of_two_runs(folder: Path, scene: Scene) -> Path:
    """A study's folder with two runs of one scene: ``runs/toy/patexgs`` (returned) and
    ``runs/toy/2dgs`` (a smaller scene, without textures)."""
    write_run(folder / "runs" / "toy" / "2dgs", random_scene(1, 50), method="2dgs")
    return write_run(folder / "runs" / "toy" / "patexgs", scene)


#: The canvas of the in-process tests: one padded size (and its 1/4 preview), shared through
#: ``frames``, so the renderer compiles for it once.
W, H = 48, 32


def orbit_camera(angle: float, width: int = W, height: int = H, radius: float = 3.5) -> Camera:
    eye = (radius * np.sin(angle), -0.6, -radius * np.cos(angle))
    f = 0.8 * width
    return Camera.from_intrinsics((f, f, width / 2, height / 2), look_at(eye, (0.0, 0.0, 0.0)), width, height)
