"""patexgs_jax.evaluation: the zoom-out metrics the studies record, the alias PSNR above all (the
render at 1/s against the same model's full-resolution render box-downsampled by s)."""

from __future__ import annotations

import numpy as np
import pytest

from patexgs_jax.data import load
from patexgs_jax.data.images import box_downsample
from patexgs_jax.data.synthetic import generate
from patexgs_jax.evaluation import evaluate_scales, render_image
from patexgs_jax.metrics import psnr
from patexgs_jax.render import RenderConfig
from patexgs_jax.scene import Scene


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    d = generate(tmp_path_factory.mktemp("ev") / "scene", seed=1, num_views=9, width=64, height=48, num_points=200)
    return load(str(d)).test_views[:2]


def _small_splats(n=400, scale=0.01, seed=0):
    """Many splats a few pixels wide at full size, so they are sub-pixel at 1/8."""
    r = np.random.default_rng(seed)
    q = r.normal(size=(n, 4))
    return Scene.from_arrays(r.uniform(-0.8, 0.8, (n, 3)), np.full((n, 2), scale),
                             q / np.linalg.norm(q, axis=1, keepdims=True), np.full(n, 0.7),
                             r.uniform(-0.5, 0.5, (n, 1, 3)), capacity=n)


def test_alias_psnr_is_the_render_against_its_own_downsampled_render(views):
    scene, cfg = _small_splats(), RenderConfig(coverage="prefilter")
    ev = evaluate_scales(scene, views, cfg, scales=(1, 2, 8), keep_images=1)
    assert ev["1"]["alias_psnr"] is None and ev["1"]["supersampled_psnr"] is None
    for s in (2, 8):
        want, bound = [], []
        for v in views:
            full = render_image(scene, v.camera, cfg)
            small = render_image(scene, v.camera.scaled(s), cfg)
            want.append(float(psnr(small, box_downsample(full, s))))
            bound.append(float(psnr(box_downsample(full, s), np.asarray(v.scaled(s).image))))
        assert ev[str(s)]["alias_psnr"] == pytest.approx(np.mean(want), abs=1e-4)
        assert ev[str(s)]["supersampled_psnr"] == pytest.approx(np.mean(bound), abs=1e-4)
        assert ev[str(s)]["views"] == len(views)
        img, gt = ev["images"][str(s)][0]
        assert img.shape == gt.shape == (48 // s, 64 // s, 3)
    # the ground-truth PSNR is unaffected by the alias reference: scale 1 is the full render
    assert ev["1"]["psnr"] == pytest.approx(np.mean([float(psnr(render_image(scene, v.camera, cfg),
                                                                 np.asarray(v.image))) for v in views]), abs=1e-4)


def test_alias_psnr_tells_the_prefilter_from_the_low_pass(views):
    """Zoomed out, sub-pixel splats under the 2DGS low-pass grow to a pixel at full opacity; the
    prefiltered ones keep their coverage. The metric must see the difference."""
    scene = _small_splats()
    low = evaluate_scales(scene, views, RenderConfig(coverage="lowpass"), scales=(1, 8))["8"]["alias_psnr"]
    pre = evaluate_scales(scene, views, RenderConfig(coverage="prefilter"), scales=(1, 8))["8"]["alias_psnr"]
    assert pre > low + 3.0, (pre, low)


def test_one_renderer_for_two_sets_gives_each_its_metrics_with_one_capacity_a_padded_size(views, monkeypatch):
    """A run evaluates its training views, then its test views, with one renderer fitted to both
    (:func:`shared_renderer`): each set scores what a renderer of its own gives it (to float
    rounding: a padded size's capacity may be larger), and the renderer holds one capacity, so one
    program, a padded size of the two sets together (what :func:`eval_programs` counts); it counts
    each view's pairs once, though each set's evaluation fits the capacities to its views again."""
    from patexgs_jax import padding
    from patexgs_jax.evaluation import eval_programs, evaluate, shared_renderer

    scene, cfg = _small_splats(), RenderConfig(coverage="prefilter")
    sets = ([views[0]], [views[1], views[0].scaled(2)])  # (the scaled view: another padded size)
    apart = [evaluate(scene, s, cfg) for s in sets]
    counted = []
    count = padding.count_pairs
    monkeypatch.setattr(padding, "count_pairs", lambda *a, **k: counted.append(1) or count(*a, **k))
    with shared_renderer(scene, cfg, sets) as renderer:
        shared = [evaluate(scene, s, cfg, renderer=renderer) for s in sets]
        sizes = dict(renderer.capacities)
    assert len(counted) == 3
    for a, b in zip(apart, shared, strict=True):
        assert b["psnr"] == pytest.approx(a["psnr"], abs=1e-4) and b["ssim"] == pytest.approx(a["ssim"], abs=1e-6)
    assert len(sizes) == eval_programs(sets, cfg)[0] == 2
