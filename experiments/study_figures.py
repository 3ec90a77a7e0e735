"""The study's figures: ground truth | render pairs and the comparison picture (``renders/``), and the
plots (``plots/``: PSNR against scale, accuracy against time, texture sides).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from experiments.study_tables import SCALES, _labels, _mean_over_scenes


def _save_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.png")
    Image.fromarray(image).save(tmp)
    os.replace(tmp, path)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(np.asarray(image, np.float32), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def _labelled_grid(rows, names, gap: int = 4, head: int = 14):
    """A white canvas (PIL image) holding ``rows`` (lists of uint8 (h, w, 3) images, or None for an
    empty cell) in a grid of equal cells, under a header naming each column, and its cell size
    (h, w); None when no cell holds an image."""
    from PIL import Image, ImageDraw

    shapes = [c.shape for r in rows for c in r if c is not None]
    if not shapes:
        return None
    h, w = max(x[0] for x in shapes), max(x[1] for x in shapes)
    canvas = np.full((head + len(rows) * (h + gap), len(names) * (w + gap) - gap, 3), 255, np.uint8)
    for i, r in enumerate(rows):
        for j, c in enumerate(r):
            if c is not None:
                y, x = head + i * (h + gap), j * (w + gap)
                canvas[y:y + c.shape[0], x:x + c.shape[1]] = c
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for j, name in enumerate(names):
        draw.text((j * (w + gap) + 2, 1), name, fill=(0, 0, 0))
    return image, (h, w)


def labelled_pairs(pairs, names, enlarge: int = 1, gap: int = 4, head: int = 14) -> np.ndarray:
    """One uint8 image: a header naming the two columns, then for each (render, ground truth) pair a
    row ``ground truth | render``, each image enlarged ``enlarge`` times with nearest neighbour (so the
    pixels of a zoomed-out render show at a size a person can see)."""
    cells = [[np.repeat(np.repeat(_to_uint8(x), enlarge, axis=0), enlarge, axis=1) for x in (gt, img)]
             for img, gt in pairs]
    image, _ = _labelled_grid(cells, names, gap, head)
    return np.asarray(image)


#: ``compare.png``: the short side a tile is enlarged to at least (nearest neighbour, by a whole
#: factor), so that a small render is seen at a size a person can read.
MIN_TILE = 200
#: ``compare.png``: the labels' font size (px) and the space around them.
LABEL_SIZE, LABEL_PAD = 16, 6


def _font(size: int = LABEL_SIZE):
    """A scalable font of ``size`` px (Pillow's bundled one), or PIL's small bitmap font where
    Pillow has no FreeType."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):  # (Pillow < 10.1, or built without FreeType)
        return ImageFont.load_default()


def _text_size(font, text: str) -> tuple[int, int]:
    """(width, height) in px of ``text`` (several lines allowed) in ``font``."""
    from PIL import Image, ImageDraw

    box = ImageDraw.Draw(Image.new("RGB", (1, 1))).multiline_textbbox((0, 0), text, font=font)
    return int(box[2]), int(box[3])


def row_label(scale: int) -> str:
    """The label of a ``compare.png`` row at 1/``scale``."""
    return "full size" if scale == 1 else f"1/{scale} size\n(enlarged x{scale})"


def sheet_layout(tile: tuple[int, int], cols, rows, gap: int = 6) -> dict:
    """Where ``compare.png`` puts things, for tiles of ``tile`` (h, w) px before enlargement,
    ``cols`` column names and ``rows`` row labels: ``enlarge`` (the whole factor that brings the
    short side to :data:`MIN_TILE`), ``tile`` (the enlarged (h, w)), ``head`` (the header band's
    height), ``left`` (the row-label band's width), ``origin(i, j)`` (the top-left (y, x) of row i,
    column j) and ``size`` (the sheet's (h, w)). The labels are on white bands of their own, never
    over an image."""
    font = _font()
    h, w = tile
    enlarge = max(1, -(-MIN_TILE // max(1, min(h, w))))
    th, tw = h * enlarge, w * enlarge
    head = max(_text_size(font, c)[1] for c in cols) + 2 * LABEL_PAD
    left = max(_text_size(font, r)[0] for r in rows) + 2 * LABEL_PAD

    def origin(i: int, j: int) -> tuple[int, int]:
        return head + i * (th + gap), left + j * (tw + gap)

    size = (head + len(rows) * (th + gap) - gap, left + len(cols) * (tw + gap) - gap)
    return dict(enlarge=enlarge, tile=(th, tw), head=head, left=left, origin=origin, size=size)


def write_comparison(directory, keys, scales=(SCALES[0], SCALES[-1]), gap: int = 6) -> Path | None:
    """``directory/compare.png``: the first test view, ground truth | each of ``keys``, one row per
    scale, from the ``directory/first/<key>_x<s>.png`` images the study saves. Zoomed-out rows are
    enlarged by their factor (nearest neighbour) to the full row's size, so their pixels show, and
    the whole sheet by :func:`sheet_layout`'s factor where the full-size renders are small; the
    column names head the columns and the row labels stand on a band to the left, both black on
    white, never over an image. Returns the path, or None when no image is there yet."""
    from PIL import Image, ImageDraw

    directory = Path(directory)
    cols = ["ground-truth"] + list(dict.fromkeys(k for k in keys if k != "ground-truth"))
    cells = {}
    for i, s in enumerate(scales):
        for j, k in enumerate(cols):
            f = directory / "first" / f"{k}_x{s}.png"
            if f.exists():
                im = np.asarray(Image.open(f).convert("RGB"))
                cells[i, j] = np.repeat(np.repeat(im, s, axis=0), s, axis=1)
    if not cells:
        return None
    tile = (max(c.shape[0] for c in cells.values()), max(c.shape[1] for c in cells.values()))
    labels = [row_label(s) for s in scales]
    lay = sheet_layout(tile, cols, labels, gap)
    canvas = np.full(lay["size"] + (3,), 255, np.uint8)
    for (i, j), c in cells.items():
        y, x = lay["origin"](i, j)
        big = np.repeat(np.repeat(c, lay["enlarge"], axis=0), lay["enlarge"], axis=1)
        canvas[y:y + big.shape[0], x:x + big.shape[1]] = big
    img = Image.fromarray(canvas)
    draw, font = ImageDraw.Draw(img), _font()
    for j, name in enumerate(cols):
        draw.text((lay["origin"](0, j)[1] + LABEL_PAD, LABEL_PAD), name, fill=(0, 0, 0), font=font)
    for i, text in enumerate(labels):
        draw.multiline_text((LABEL_PAD, lay["origin"](i, 0)[0] + LABEL_PAD), text, fill=(0, 0, 0), font=font)
    path = directory / "compare.png"
    _save_png(path, np.asarray(img))
    return path


def _pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig, path, dpi: int = 120) -> Path:
    """Lays out ``fig``, writes it to ``path`` and closes it; returns the path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def write_plots(data: dict, directory) -> list[Path]:
    """``psnr_vs_scale.png`` and ``accuracy_vs_time.png`` (means over scenes); returns the paths."""
    plt = _pyplot()

    results = data.get("results", {})
    labels = _labels(results)
    if not labels:
        return []
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, field, scales, title in (
            (axes[0], "psnr", SCALES, "PSNR against the ground truth"),
            (axes[1], "alias_psnr", SCALES[1:], "alias PSNR: against its own supersampled render")):
        for key in labels:
            ys = [_mean_over_scenes(results, key, lambda e, s=s, f=field: e.get(str(s), {}).get(f)) for s in scales]
            ax.plot(scales, [np.nan if y is None else y for y in ys], marker="o", label=key)
        ax.set_xscale("log", base=2)
        ax.set_xticks(scales, ["full" if s == 1 else f"1/{s}" for s in scales])
        ax.set_xlabel("zoom-out")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("zoom-out (mean over scenes)")
    paths.append(_save_figure(fig, directory / "psnr_vs_scale.png"))

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, field, xlabel in ((axes[0], "train_seconds", "training time (s)"),
                              (axes[1], "render_ms", "render time per image (ms)")):
        points = []
        for key in labels:
            x = _mean_over_scenes(results, key, lambda e, f=field: e.get(f))
            y = _mean_over_scenes(results, key, lambda e: e.get("1", {}).get("psnr"))
            if x is not None and y is not None:
                points.append((key, x, y))
                ax.scatter([x], [y])
        ax.margins(x=0.15, y=0.2)  # (room for the labels inside the frame)
        _annotate_inside(ax, points)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR at full resolution (dB)")
        ax.grid(alpha=0.3)
    fig.suptitle("accuracy vs time (mean over scenes)")
    paths.append(_save_figure(fig, directory / "accuracy_vs_time.png"))
    side_path = plot_sides(data, directory / "texture_sides.png")
    return paths + ([side_path] if side_path else [])


def _annotate_inside(ax, points) -> None:
    """Labels each (name, x, y) point beside it, on the side towards the middle of the axes (left
    of a point in the right half, below one in the top half), so that no label runs into the frame."""
    if not points:
        return
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    for name, x, y in points:
        right = x > (x0 + x1) / 2
        top = y > (y0 + y1) / 2
        ax.annotate(name, (x, y), fontsize=8, xytext=(-4 if right else 4, -4 if top else 4),
                    textcoords="offset points", ha="right" if right else "left", va="top" if top else "bottom")


def plot_sides(data: dict, path) -> Path | None:
    """The texture-side distribution of each adaptive run (one panel per scene and run): Gaussians per
    side after the Eq. 7 allocation and at the end (after Eqs. 8-10), and the share of the texels at
    each side; from the entries' ``sides_allocated`` / ``sides_final`` (summary.json). None if no
    entry has them."""
    plt = _pyplot()

    panels = [(scene, key, e) for scene, per in data.get("results", {}).items() for key, e in per.items()
              if e.get("sides_allocated") and e.get("sides_final") and e.get("sigma") is not None]
    if not panels:
        return None
    fig, axes = plt.subplots(2, len(panels), figsize=(5 * len(panels), 6), squeeze=False)
    for col, (scene, key, e) in enumerate(panels):
        for hist, name, dx in ((e["sides_allocated"], "after Eq. 7", -0.2), (e["sides_final"], "at the end", 0.2)):
            sides = np.array(sorted(int(k) for k in hist))
            counts = np.array([hist[str(k)] for k in sides], float)
            axes[0, col].bar(sides + dx, counts, width=0.4, label=name)
            axes[1, col].bar(sides + dx, counts * sides**2 / np.sum(counts * sides**2), width=0.4, label=name)
        events = e.get("growth_events") or []
        axes[0, col].set_title(f"{scene} {key}: sigma {e['sigma']:.3g}, {len(events)} growth events", fontsize=9)
        axes[0, col].set_yscale("log")
        axes[0, col].set_ylabel("Gaussians")
        axes[1, col].set_ylabel("share of the texels")
        axes[1, col].set_xlabel("texture side")
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    return _save_figure(fig, path)
