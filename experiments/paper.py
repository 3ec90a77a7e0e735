"""The paper's rows, in one place: which method of this package is which row of the PATexGS paper's
Tables 1 and 2, the paper's own figures for them (Table 1: per dataset), and the method lists of
``python -m experiments.mipnerf360 --methods table1 | table2 | tables | zoom-in | table4``.

The figures are copied from the paper's text: Table 1 gives, for every row, one mean per dataset
(Mip-NeRF 360: nine scenes; Tanks and Temples: truck, train; Deep Blending: drjohnson, playroom; at
the paper's resolutions and 30k + 30k steps), no per-scene figure; Table 2 (zoom-out) is Mip-NeRF
360's alone. Every figure the paper's Table 1 prints is here (it has none missing). Method
names need not exist in this tree: nothing here resolves them; the study checks them
(:meth:`patexgs_jax.training.Method.from_name`) before any work.
"""

from __future__ import annotations

#: ``--methods table1``: the rows of the paper's Table 1 (unbudgeted), in its order.
TABLE1_METHODS = ("3dgs", "2dgs", "mip-splatting", "bbsplat", "bbsplat+adaptive", "textured-gaussians", "patexgs")
#: ``--methods table2``: the rows of the paper's Table 2, in its order.
TABLE2_METHODS = ("2dgs", "bbsplat", "bbsplat+mip", "textured-gaussians", "patexgs")
#: ``--methods tables``: both, Table 1's order with Table 2's BBSplat + mipmap row beside its kin.
TABLES_METHODS = ("3dgs", "2dgs", "mip-splatting", "bbsplat", "bbsplat+adaptive", "bbsplat+mip",
                  "textured-gaussians", "patexgs")
#: ``--methods zoom-in``: the rows the zoom-in table (Mip-Splatting's protocol) is meant for, with
#: PATexGS given Mip-Splatting's 3D filter (not a row of the paper).
ZOOM_IN_METHODS = ("3dgs", "2dgs", "mip-splatting", "patexgs", "patexgs+filter3d")

#: method name -> the paper's row name.
PAPER_NAMES = {
    "3dgs": "3DGS",
    "2dgs": "2DGS*",
    "mip-splatting": "Mip Splatting",
    "bbsplat": "BBSplat*",
    "bbsplat+adaptive": "BBSplat + our_adaptive",
    "bbsplat+mip": "BBSplat + our_mipmap",
    "textured-gaussians": "Tex. Gau.*",
    "patexgs": "Ours",
}

#: The paper's Table 1, Mip-NeRF 360: label -> (PSNR, SSIM, LPIPS); budget rows keyed as the study
#: labels them (``patexgs(10%)``).
PAPER_TABLE1 = {
    "3dgs": (27.21, 0.815, 0.214),
    "2dgs": (27.16, 0.802, 0.237),
    "mip-splatting": (27.79, 0.827, 0.203),
    "bbsplat": (26.92, 0.786, 0.228),
    "bbsplat+adaptive": (27.11, 0.785, 0.234),
    "textured-gaussians": (27.26, 0.791, 0.215),
    "patexgs": (27.71, 0.816, 0.197),
    "2dgs(10%)": (25.62, 0.722, 0.358),
    "patexgs(10%)": (26.54, 0.771, 0.269),
    "2dgs(1%)": (22.64, 0.581, 0.504),
    "patexgs(1%)": (23.84, 0.649, 0.417),
}

#: The paper's Table 1, Tanks and Temples (truck, train): label -> (PSNR, SSIM, LPIPS).
PAPER_TABLE1_TANDT = {
    "3dgs": (23.60, 0.847, 0.181),
    "2dgs": (23.42, 0.837, 0.197),
    "mip-splatting": (23.75, 0.857, 0.157),
    "bbsplat": (23.69, 0.852, 0.150),
    "bbsplat+adaptive": (24.10, 0.853, 0.155),
    "textured-gaussians": (23.72, 0.836, 0.170),
    "patexgs": (24.15, 0.853, 0.151),
    "2dgs(10%)": (22.56, 0.781, 0.298),
    "patexgs(10%)": (23.43, 0.822, 0.216),
    "2dgs(1%)": (19.68, 0.640, 0.450),
    "patexgs(1%)": (20.87, 0.712, 0.360),
}

#: The paper's Table 1, Deep Blending (drjohnson, playroom): label -> (PSNR, SSIM, LPIPS).
PAPER_TABLE1_DB = {
    "3dgs": (29.40, 0.903, 0.243),
    "2dgs": (29.60, 0.902, 0.251),
    "mip-splatting": (29.46, 0.903, 0.243),
    "bbsplat": (29.40, 0.902, 0.248),
    "bbsplat+adaptive": (29.70, 0.902, 0.244),
    "textured-gaussians": (29.22, 0.893, 0.248),
    "patexgs": (29.80, 0.902, 0.221),
    "2dgs(10%)": (29.26, 0.892, 0.284),
    "patexgs(10%)": (29.69, 0.905, 0.244),
    "2dgs(1%)": (26.80, 0.850, 0.369),
    "patexgs(1%)": (28.05, 0.879, 0.307),
}

#: The paper's Table 1 per dataset (:data:`patexgs_jax.data.benchmarks.DATASETS`' keys).
PAPER_TABLE1_BY_DATASET = {"mipnerf360": PAPER_TABLE1, "tandt": PAPER_TABLE1_TANDT, "db": PAPER_TABLE1_DB}

#: The paper's Table 2 (zoom-out, Mip-NeRF 360): method -> {scale: (PSNR, SSIM, LPIPS)}, scale 1 =
#: full resolution, 2, 4, 8 = 1/2, 1/4, 1/8.
PAPER_TABLE2 = {
    "2dgs": {1: (27.16, 0.802, 0.237), 2: (25.82, 0.805, 0.184), 4: (21.31, 0.661, 0.233), 8: (18.20, 0.502, 0.289)},
    "bbsplat": {1: (26.92, 0.786, 0.228), 2: (27.66, 0.828, 0.154), 4: (26.88, 0.815, 0.146),
                8: (25.12, 0.768, 0.182)},
    "bbsplat+mip": {1: (26.92, 0.786, 0.229), 2: (27.82, 0.833, 0.151), 4: (27.91, 0.851, 0.116),
                    8: (27.20, 0.857, 0.111)},
    "textured-gaussians": {1: (27.26, 0.791, 0.215), 2: (26.12, 0.793, 0.171), 4: (21.87, 0.662, 0.227),
                           8: (19.00, 0.529, 0.293)},
    "patexgs": {1: (27.71, 0.816, 0.197), 2: (28.63, 0.862, 0.125), 4: (28.49, 0.880, 0.098),
                8: (27.12, 0.878, 0.099)},
}

#: ``--methods NAME`` groups (a group may be combined with other names: ``table1,patexgs-no-mip``).
METHOD_GROUPS = {"table1": TABLE1_METHODS, "table2": TABLE2_METHODS, "tables": TABLES_METHODS,
                 "zoom-in": ZOOM_IN_METHODS}


def paper_name(label: str) -> str | None:
    """The paper's row name of a study label (``patexgs(10%)`` -> ``Ours(10%)``), or None."""
    base, paren, rest = label.partition("(")
    name = PAPER_NAMES.get(base)
    return None if name is None else name + (f"({rest}" if paren else "")


def ordered(labels, table) -> list[str]:
    """``labels`` with the paper's rows of ``table`` (a method tuple) first, in the paper's order,
    then the others in their own order."""
    labels = list(labels)
    first = [m for m in table if m in labels]
    return first + [k for k in labels if k not in first]
