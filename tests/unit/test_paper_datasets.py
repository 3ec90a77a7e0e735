"""The paper's three datasets without training: which dataset and protocol a scene gets (from its
folder, its name, or ``--dataset``), the scenes ``--data`` finds in the downloaded layout, and a
``--methods tables`` study (training and evaluation replaced by stand-ins) over a Tanks and
Temples-shaped and a Deep Blending-shaped scene made from the synthetic one, whose tables set each
dataset's columns beside the paper's figures for it."""

from __future__ import annotations

import json

import pytest

from data_builders import make_3dgs_layout
from experiments import mipnerf360 as mn
from experiments import paper
from experiments.study import Study
from patexgs_jax.data import DatasetError
from patexgs_jax.data.benchmarks import dataset_of, protocol


@pytest.fixture(scope="module")
def paper_layout(tmp_path_factory):
    """DEST as the download lays it out: tandt/truck, db/drjohnson (the synthetic capture, 32 x 24,
    9 views) and 360_v2/garden; and a scene of none of the datasets beside them."""
    from patexgs_jax.data.synthetic import generate

    base = tmp_path_factory.mktemp("paper_layout")
    scene = generate(base / "synthetic", seed=0, num_views=9, width=32, height=24, supersample=1, num_points=100,
                     verbose=False)
    root = base / "data"
    make_3dgs_layout(scene, root, {"tandt": ["truck"], "db": ["drjohnson"], "360_v2": ["garden"], ".": ["mine"]})
    return root


def test_a_scenes_dataset_and_protocol(tmp_path):
    assert dataset_of(tmp_path / "tandt" / "train") == ("tandt", "its parent folder is tandt/")
    assert dataset_of(tmp_path / "db" / "anything")[0] == "db"
    assert dataset_of(tmp_path / "scans" / "playroom") == ("db", "playroom is a Deep Blending scene name")
    assert dataset_of(tmp_path / "scans" / "truck")[0] == "tandt"
    assert dataset_of(tmp_path / "scans" / "train")[0] is None  # too common a name without tandt/
    assert dataset_of(tmp_path / "scans" / "bonsai")[0] == "mipnerf360"
    p = protocol(tmp_path / "tandt" / "truck")
    assert (p.dataset, p.factor, p.test_every) == ("tandt", 1, 8)
    assert p.why == ("Tanks and Temples (its parent folder is tandt/): the images' own size (factor 1, no Mip-NeRF "
                     "360 factor, as 3DGS and the paper), every 8th image held out")
    assert protocol(tmp_path / "360_v2" / "bicycle").factor == 4 and protocol(tmp_path / "x" / "room").factor == 2
    other = protocol(tmp_path / "x" / "mine")
    assert other.dataset is None and other.factor is None and "1600" in other.why
    # --dataset names it instead; --factor sets every scene's
    named = protocol(tmp_path / "x" / "mine", dataset="db")
    assert (named.dataset, named.factor) == ("db", 1) and "--dataset db" in named.why
    assert protocol(tmp_path / "tandt" / "truck", factor=2).factor == 2
    with pytest.raises(DatasetError, match=r"not one of Mip-NeRF 360's nine.*pass --factor"):
        protocol(tmp_path / "x" / "mine", dataset="mipnerf360")
    with pytest.raises(DatasetError, match="unknown dataset 'llff'"):
        protocol(tmp_path / "x" / "mine", dataset="llff")


def test_data_finds_the_scenes_of_the_downloaded_layout(paper_layout, tmp_path):
    found = mn.find_scenes(paper_layout)
    assert list(found) == ["garden", "truck", "drjohnson", "mine"]  # the paper's order, then the others
    assert {n: p.dataset for n, p in mn.scene_protocols(found).items()} == {
        "garden": "mipnerf360", "truck": "tandt", "drjohnson": "db", "mine": None}
    assert list(mn.find_scenes(paper_layout / "tandt")) == ["truck"]
    assert list(mn.find_scenes(paper_layout / "db" / "drjohnson")) == ["drjohnson"]
    with pytest.raises(mn.StudyError, match=r"scene truck .*not one of Mip-NeRF 360.s nine"):
        mn.scene_protocols(found, dataset="mipnerf360")
    # two scenes of one name under one root: refused, naming both
    import shutil

    twice = tmp_path / "twice"
    shutil.copytree(paper_layout / "tandt", twice / "tandt")
    shutil.copytree(paper_layout / "tandt" / "truck", twice / "truck")
    with pytest.raises(mn.StudyError, match="two scenes are named truck"):
        mn.find_scenes(twice)


class _Run:
    def __init__(self, cfg):
        self.scene = None
        self.summary = dict(num_gaussians=10, storage_mb=1.0, texels=0, train_seconds=1.0, steps=20)


def test_a_tables_study_sets_each_datasets_columns_beside_the_papers(paper_layout, tmp_path, monkeypatch, capsys):
    """``--methods tables`` over tandt/truck and db/drjohnson through the command line, with training
    and evaluation replaced by stand-ins (a method's PSNR: 20 + its row's index, + 5 on drjohnson):
    the start lines say each protocol, results.json records it, and tables.md (printed) has one
    Table 1 column group per dataset beside the paper's figures for that dataset."""
    import experiments.study as study_module
    import patexgs_jax.training as training

    monkeypatch.setattr(training, "train", lambda ds, cfg, out, **kw: _Run(cfg))
    monkeypatch.setattr(training, "stage1_checkpoint", lambda run, cfg: run / "checkpoints" / "stage1" / "ck")
    monkeypatch.setattr(study_module, "write_plots", lambda data, folder: None)
    rows = list(paper.TABLES_METHODS)

    def evaluate(self, scene, key, result, ds, cfg):
        assert ds.factor == 1 and len(ds.test_views) == 2  # the images' own size, every 8th held out
        p = 20.0 + rows.index(key) + (5.0 if scene == "drjohnson" else 0.0)
        return {s: dict(psnr=p, ssim=0.5, lpips=0.25, alias_psnr=None) for s in "1248"} | dict(
            method=key, num_gaussians=10, storage_mb=1.0, texels=0, train_seconds=1.0, render_ms=1.0, steps=20)

    monkeypatch.setattr(Study, "evaluate", evaluate)
    out = tmp_path / "study"
    assert mn.main(["--data", str(paper_layout), "--scenes", "truck,drjohnson", "--methods", "tables", "--out",
                    str(out), "--preset", "tiny", "--no-lpips", "--no-compile-cache", "--renders", "0"]) == 0
    printed = capsys.readouterr().out
    assert "[truck] Tanks and Temples (its parent folder is tandt/): the images' own size" in printed
    assert "[drjohnson] Deep Blending (its parent folder is db/)" in printed
    data = json.loads((out / "results.json").read_text())
    assert data["config"]["dataset"] is None
    for name, dataset in (("truck", "tandt"), ("drjohnson", "db")):
        rec = data["scenes"][name]
        assert rec["dataset"] == dataset and rec["factor"] == 1 and rec["training_size"] == [32, 24]
        assert rec["test_views"] == 2 and rec["train_views"] == 7 and "held out" in rec["why"]
    md = (out / "tables.md").read_text()
    t1 = md.split("## Table 1 beside the paper")[1].split("\n## ")[0]
    assert t1 in printed  # the tables are printed too
    assert ("| method | paper row | Tanks and Temples PSNR | paper | SSIM | paper | LPIPS | paper | Deep Blending PSNR "
            "| paper | SSIM | paper | LPIPS | paper | Gaussians |") in t1
    for i, key in enumerate(rows):
        row = next(line for line in t1.splitlines() if line.startswith(f"| {key} |")).split(" | ")
        tandt = paper.PAPER_TABLE1_TANDT.get(key)
        db = paper.PAPER_TABLE1_DB.get(key)
        assert row[2:4] == [f"{20 + i:.2f}", f"{tandt[0]:.2f}" if tandt else ""], key
        assert row[8:10] == [f"{25 + i:.2f}", f"{db[0]:.2f}" if db else ""], key
    assert "Tanks and Temples: truck (1 of its 2); Deep Blending: drjohnson (1 of its 2)" in t1
    # the paper's Table 2 is Mip-NeRF 360's: without such a scene ours is every scene's mean
    assert "ours: every scene of the study" in md
    # Resuming with another --dataset is another protocol: refused
    assert mn.main(["--data", str(paper_layout), "--scenes", "truck,drjohnson", "--methods", "2dgs", "--out",
                    str(out), "--preset", "tiny", "--no-lpips", "--no-compile-cache", "--dataset", "db"]) == 2
    assert "dataset" in capsys.readouterr().err


def test_the_papers_table1_rows_per_dataset():
    """Transcribed from the paper's Table 1 (tests/unit/test_study.py checks the Mip-NeRF 360 column)."""
    assert {m: f[0] for m, f in paper.PAPER_TABLE1_TANDT.items()} == {
        "3dgs": 23.60, "2dgs": 23.42, "mip-splatting": 23.75, "bbsplat": 23.69, "bbsplat+adaptive": 24.10,
        "textured-gaussians": 23.72, "patexgs": 24.15, "2dgs(10%)": 22.56, "patexgs(10%)": 23.43,
        "2dgs(1%)": 19.68, "patexgs(1%)": 20.87}
    assert {m: f[0] for m, f in paper.PAPER_TABLE1_DB.items()} == {
        "3dgs": 29.40, "2dgs": 29.60, "mip-splatting": 29.46, "bbsplat": 29.40, "bbsplat+adaptive": 29.70,
        "textured-gaussians": 29.22, "patexgs": 29.80, "2dgs(10%)": 29.26, "patexgs(10%)": 29.69,
        "2dgs(1%)": 26.80, "patexgs(1%)": 28.05}
    assert paper.PAPER_TABLE1_DB["patexgs"] == (29.80, 0.902, 0.221)
    assert paper.PAPER_TABLE1_TANDT["bbsplat+adaptive"] == (24.10, 0.853, 0.155)
    assert set(paper.PAPER_TABLE1_BY_DATASET) == {"mipnerf360", "tandt", "db"}
