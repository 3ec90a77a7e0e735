"""Zoom-in, Mip-Splatting's protocol: a model trained at the study's resolution (``--factor F``) is
evaluated on each test view zoomed IN by 2, 4 and 8, i.e. at z times its pixel density: the finer
images of the same view with the camera intrinsics of that resolution.

Where the finer images come from (:func:`zoom_in_views`):

* the scene loaded again at factor ``F / z`` (an integer >= 1: a COLMAP scene trained at factor 8 is
  zoomed in on with its factor 4, 2 and 1 images), its test views matched by name;
* else, for the embedded synthetic scene (a folder with ``synthetic.json``, see
  :mod:`patexgs_jax.data.synthetic`), its analytic ground truth rendered at z times the camera's
  size (the generator's supersampling and 8-bit rounding, so the images are what the generator
  writes at that size);
* else none: the zoom is recorded as unavailable, with the reason.

:func:`evaluate_zoom_in` measures PSNR / SSIM (and LPIPS where computed) per zoom.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np

#: Zoom-in factors (Mip-Splatting's single-scale training, multi-scale testing: x2, x4, x8).
ZOOM_IN_SCALES = (2, 4, 8)


def upscaled(camera, zoom: int):
    """The camera of the same view at ``zoom`` times its resolution: the inverse of
    :meth:`patexgs_jax.camera.Camera.scaled` (fx, fy, cx, cy and the size multiplied by ``zoom``;
    pixel centres stay consistent)."""
    import jax.numpy as jnp

    from patexgs_jax.camera import Camera

    zoom = int(zoom)
    if zoom < 1:
        raise ValueError(f"zoom-in factor must be a positive integer, got {zoom}.")
    k = np.diag([float(zoom), float(zoom), 1.0]) @ np.asarray(camera.K, np.float64)
    return Camera(K=jnp.asarray(k, jnp.float32), world_to_camera=camera.world_to_camera,
                  width=int(camera.width) * zoom, height=int(camera.height) * zoom)


def _integer_factor(factor) -> int | None:
    f = float(factor)
    return int(f) if f.is_integer() and f >= 1 else None


def _from_images(ds, views, zoom: int):
    """The test views at factor ``F / zoom`` loaded from the scene's images, or a reason why not."""
    from patexgs_jax.data import DatasetError, load

    f = _integer_factor(ds.factor)
    if f is None or f % zoom:
        return None, f"the study's factor {ds.factor:g} is not {zoom} times an integer factor"
    try:
        finer = load(ds.path, factor=f // zoom, verbose=False)
    except DatasetError as e:
        return None, f"the images at factor {f // zoom} cannot be loaded ({e})"
    by_name = {v.name: v for v in finer.views}
    missing = [v.name for v in views if v.name not in by_name]
    if missing:
        return None, f"test view(s) {', '.join(missing[:3])} missing at factor {f // zoom}"
    return [by_name[v.name] for v in views], f"images at factor {f // zoom}"


def _from_synthetic(ds, views, zoom: int):
    """The embedded synthetic scene's analytic ground truth at ``zoom`` times each view's size."""
    from patexgs_jax.data import View
    from patexgs_jax.data.synthetic_scene import make_scene

    meta = ds.path / "synthetic.json"
    if not meta.is_file():
        return None, None
    params = json.loads(meta.read_text())
    seed, supersample = int(params.get("seed", 0)), int(params.get("supersample", 4))
    scene = make_scene(seed)
    norm = ds.normalization
    out = []
    for v in views:
        cam = upscaled(v.camera, zoom)
        # The analytic scene lives in the file's coordinates (the dataset's may be normalised).
        original = type(cam)(K=cam.K, world_to_camera=np.asarray(norm.to_original_world_to_camera(
            cam.world_to_camera), np.float32), width=cam.width, height=cam.height)

        def render(c=original):
            return np.round(255.0 * scene.render(c, supersample)).astype(np.float32) / 255.0

        out.append(View(cam, v.name, render, cache=ds.image_cache, key=("zoom-in", v.name, zoom)))
    return out, f"analytic ground truth (synthetic scene, {supersample}x{supersample} supersampling)"


def zoom_in_views(ds, views: Sequence, zooms: Sequence[int] = ZOOM_IN_SCALES) -> dict[int, tuple]:
    """``{zoom: (views or None, source)}``: the test ``views`` zoomed in by each factor (aligned
    with ``views``; images load lazily) and where they come from, or None and why not."""
    out = {}
    for z in (int(z) for z in zooms):
        got, source = _from_images(ds, views, z)
        if got is None:
            analytic, where = _from_synthetic(ds, views, z)
            if analytic is not None:
                got, source = analytic, where
        out[z] = (got, source)
    return out


def evaluate_zoom_in(renderer, zoomed: dict, *, lpips=None, phase: str | None = None) -> dict:
    """``{str(zoom): {"psnr", "ssim", "lpips", "views", "source"}}`` (means over the views; metric
    fields None for a zoom without images, ``source`` then says why) of the scene ``renderer``
    draws (a :class:`patexgs_jax.padding.ViewRenderer`), renders clipped to [0, 1]. ``phase``: what
    a stop line says is being done (``"... zoomed in"``; the zoom is added)."""
    import jax.numpy as jnp

    from patexgs_jax import interrupt, memory_maps
    from patexgs_jax import lpips as lp
    from patexgs_jax.evaluation import MAX_METRIC_PROGRAMS, usable
    from patexgs_jax.metrics import psnr, ssim

    result = {}
    for z, (views, source) in zoomed.items():
        if not views:
            result[str(z)] = dict(psnr=None, ssim=None, lpips=None, views=0, source=source)
            continue
        views = [v for v in views if usable(v)]
        if phase:
            interrupt.set_phase(f"{phase} x{z}")
        renderer.prepare([v.camera for v in views])
        ps, ss, ls = [], [], []
        for i, v in enumerate(views):
            interrupt.check()
            interrupt.set_step(i, len(views), "view")
            gt = np.asarray(v.image, np.float32)
            img = renderer.image(v.camera)
            ps.append(float(psnr(img, gt)))
            ss.append(float(ssim(jnp.asarray(img), jnp.asarray(gt))))
            ls.append(lpips(img, gt) if lpips is not None else None)
            memory_maps.trim_programs(ssim, lp.lpips, max_programs=MAX_METRIC_PROGRAMS)
        result[str(z)] = dict(psnr=float(np.mean(ps)), ssim=float(np.mean(ss)),
                              lpips=float(np.mean(ls)) if ls and all(x is not None for x in ls) else None,
                              views=len(ps), source=source)
    return result
