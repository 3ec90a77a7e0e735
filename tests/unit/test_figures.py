"""The study's figures a person reads: ``compare.png`` (its tiles enlarged to a readable size, the
labels on white bands of their own, never over an image) and ``accuracy_vs_time.png`` (each point's
label inside the frame)."""

from __future__ import annotations

import numpy as np
from PIL import Image

from experiments import study_figures as figs

H, W = 48, 64


def _sky(seed: int) -> np.ndarray:
    """A light sky over dark ground, a red disc: (H, W, 3) uint8."""
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.empty((H, W, 3), np.uint8)
    img[:] = (216, 235, 255)
    img[yy > H // 2] = (90, 128, 64)
    img[(xx - 20 - seed) ** 2 + (yy - 24) ** 2 < 60] = (204, 51, 51)
    return img


def test_compare_sheet_readable_with_labels_off_the_images(tmp_path):
    keys = ["2dgs", "patexgs"]
    (tmp_path / "first").mkdir()
    small = {}
    for j, k in enumerate(["ground-truth", *keys]):
        full = _sky(j)
        small[k] = full.reshape(H // 8, 8, W // 8, 8, 3).mean((1, 3)).astype(np.uint8)
        Image.fromarray(full).save(tmp_path / "first" / f"{k}_x1.png")
        Image.fromarray(small[k]).save(tmp_path / "first" / f"{k}_x8.png")
    px = np.asarray(Image.open(figs.write_comparison(tmp_path, keys)).convert("RGB"))
    cols, rows = ["ground-truth", *keys], [figs.row_label(1), figs.row_label(8)]
    lay = figs.sheet_layout((H, W), cols, rows)
    e = lay["enlarge"]
    assert min(lay["tile"]) >= figs.MIN_TILE and lay["tile"] == (H * e, W * e)
    assert px.shape[:2] == lay["size"] and px.shape[0] > 2 * figs.MIN_TILE and px.shape[1] > 3 * figs.MIN_TILE
    for j, k in enumerate(cols):
        y, x = lay["origin"](0, j)  # full size: every pixel an e x e block
        np.testing.assert_array_equal(px[y:y + H * e:e, x:x + W * e:e], _sky(j))
        y, x = lay["origin"](1, j)  # 1/8: 8 e x 8 e blocks of the saved render
        b = 8 * e
        np.testing.assert_array_equal(px[y + b // 2:y + H * e:b, x + b // 2:x + W * e:b], small[k])
    # The labels: dark text on the white bands (header above, row labels to the left of the images).
    head, left = px[:lay["head"]], px[lay["head"]:, :lay["left"]]
    for band in (head, left):
        assert band.min() < 80 and np.median(band) == 255
    for i in range(2):
        y, _ = lay["origin"](i, 0)
        assert left[y - lay["head"]:y - lay["head"] + 40].min() < 80  # each row's label beside it


def test_plot_labels_stay_inside_the_frame():
    plt = figs._pyplot()
    fig, ax = plt.subplots(figsize=(5, 4))
    points = [("3dgs", 106.0, 22.1), ("2dgs", 160.0, 23.9), ("patexgs", 373.0, 24.23)]
    for _, x, y in points:
        ax.scatter([x], [y])
    ax.margins(x=0.15, y=0.2)
    figs._annotate_inside(ax, points)
    fig.canvas.draw()
    frame = ax.get_window_extent()
    for text in ax.texts:
        box = text.get_window_extent()
        assert frame.x0 < box.x0 and box.x1 < frame.x1 and frame.y0 < box.y0 and box.y1 < frame.y1, text.get_text()
    plt.close(fig)
