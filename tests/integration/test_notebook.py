"""notebooks/explore.ipynb runs top to bottom on the embedded scene.

The code cells are executed in order in one namespace with matplotlib's Agg backend (no Jupyter
needed) by :func:`execute_notebook`. To keep the suite short the execution test lives in
``test_tradeoffs.py``: it runs the notebook on the PATexGS run that module's study trained on the
embedded scene (``PATEXGS_NOTEBOOK_RUN``; ``PATEXGS_NOTEBOOK_TINY=1`` for the third-resolution data
and fewer zooms), instead of training another one with the same settings.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib
import numpy as np

from locations import REPO

NOTEBOOK = REPO / "notebooks" / "explore.ipynb"


def code_cells(path: Path) -> list[str]:
    nb = json.loads(path.read_text())
    return ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]


def test_notebook_is_plain_python():
    """No IPython magics or shell escapes: the cells run with exec (and in any kernel)."""
    cells = code_cells(NOTEBOOK)
    assert len(cells) >= 6
    for src in cells:
        assert not any(line.lstrip().startswith(("%", "!")) for line in src.splitlines()), src[:80]
        compile(src, "<cell>", "exec")


def execute_notebook(tmp_path, monkeypatch, run_dir) -> dict:
    """Runs every code cell of the notebook on the trained run ``run_dir``; returns its namespace
    after checking the pictures it describes."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    monkeypatch.setenv("PATEXGS_NOTEBOOK_TINY", "1")
    monkeypatch.setenv("PATEXGS_NOTEBOOK_RUN", str(run_dir))
    monkeypatch.chdir(tmp_path)
    ns: dict = {"__name__": "__notebook__"}
    for i, src in enumerate(code_cells(NOTEBOOK)):
        try:
            exec(compile(src, f"<explore.ipynb cell {i}>", "exec"), ns)
        finally:
            plt.close("all")
    h, w = ns["view"].camera.height, ns["view"].camera.width
    assert ns["heat"].shape == (h, w, 3) and np.all(np.isfinite(ns["heat"]))
    assert len(ns["orbit"]) == 6 and all(img.shape == (h, w, 3) for img in ns["orbit"])
    # The orbit views differ from each other (the cameras move) and are not empty.
    assert np.abs(ns["orbit"][0] - ns["orbit"][3]).mean() > 1e-3
    assert all(img.mean() > 0.01 for img in ns["orbit"])
    # Every mip mode was rendered at every zoom and scored.
    assert set(ns["mip_psnr"]) == {(m, s) for m in ("none", "nearest", "trilinear") for s in ns["ZOOMS"]}
    assert all(np.isfinite(v) for v in ns["mip_psnr"].values())
    # The per-pixel mip levels: the dominant splat's level, within its texture's pyramid (-1: none).
    cam = ns["view"].camera.scaled(4)
    lev = ns["pixel_levels"](ns["scene"], cam, ns["scene"].rgb)
    assert lev.shape == (cam.height, cam.width) and np.any(lev >= 0)
    dom = np.asarray(ns["render_scene"](ns["scene"], cam, ns["config"]).dominant)
    n = np.asarray(ns["scene"].rgb.size)
    top = np.array([int(k - 1).bit_length() if k > 0 else 0 for k in n])
    drawn = dom >= 0
    assert np.all(lev[~drawn] == -1)
    assert np.all((lev[drawn] >= -1) & (lev[drawn] <= top[dom[drawn]]))
    return ns
