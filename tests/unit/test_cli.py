"""Every command line meets bad input with one ``error:`` line that names the problem and the fix,
a non-zero exit and no traceback, before any scene is made or any code compiled: a missing scene
folder, an unknown method (or knob), an output folder that cannot be written, and a folder of photos
without camera poses (pointed to ``python -m patexgs_jax.sfm``)."""

from __future__ import annotations

import pytest

from experiments import mipnerf360, tradeoffs
from patexgs_jax import sfm
from patexgs_jax.training import cli as train_cli
from patexgs_jax.viewer import server as view


@pytest.fixture
def bad(tmp_path):
    """Paths for each kind of bad input: a missing folder, a file where a folder is needed, and
    photos without poses (as a scene folder's images/ and as a bare folder)."""
    photos = tmp_path / "capture" / "images"
    photos.mkdir(parents=True)
    for i in range(sfm.MIN_IMAGES):
        (photos / f"{i:04d}.jpg").write_bytes(b"")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    return dict(missing=str(tmp_path / "nope"), unwritable=str(blocker / "out"), scene=str(photos.parent),
                photos=str(photos), out=str(tmp_path / "out"))


def _one_error_line(capsys, code, *needles):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code != 0 and "Traceback" not in err, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _cases(bad):
    return [
        (["--data", bad["missing"], "--out", bad["out"]], ("does not exist", "pass a scene folder")),
        (["--data", bad["missing"], "--out", bad["unwritable"]], ("cannot write to --out", "Not a directory",
                                                                   "pass --out a folder you can write to")),
        (["--data", bad["scene"], "--out", bad["out"]], ("no camera poses", "python -m patexgs_jax.sfm")),
        (["--data", bad["photos"], "--out", bad["out"]], ("no camera poses", "python -m patexgs_jax.sfm")),
    ]


def test_train_cli_bad_input(bad, capsys):
    for argv, needles in _cases(bad):
        _one_error_line(capsys, train_cli.main(argv), *needles)
    code = train_cli.main(["--data", bad["missing"], "--out", bad["out"], "--method", "nerf"])
    _one_error_line(capsys, code, "unknown method 'nerf'", "choose one of", "patexgs")


def test_mipnerf360_cli_bad_input(bad, capsys):
    for argv, needles in _cases(bad):
        _one_error_line(capsys, mipnerf360.main(argv + ["--no-compile-cache"]), *needles)
    code = mipnerf360.main(["--methods", "patexgs,nerf", "--out", bad["out"], "--no-compile-cache"])
    _one_error_line(capsys, code, "unknown method 'nerf'", "choose one of")


def test_tradeoffs_cli_bad_input(bad, capsys):
    for argv, needles in _cases(bad):
        _one_error_line(capsys, tradeoffs.main(argv), *needles)
    code = tradeoffs.main(["--data", bad["missing"], "--knobs", "mip,colour"])
    _one_error_line(capsys, code, "unknown knob(s) colour", "choose from mip")
    code = tradeoffs.main(["--data", bad["missing"], "--effects", "--run", bad["missing"]])
    _one_error_line(capsys, code, "--run", "python -m patexgs_jax.train --out")


def test_sfm_cli_bad_input(bad, capsys):
    code = sfm.main([bad["missing"], bad["out"], "--quiet"])
    _one_error_line(capsys, code, "does not exist", "pass the folder that holds your photos")
    code = sfm.main([bad["photos"], bad["unwritable"], "--quiet"])
    _one_error_line(capsys, code, "cannot write to OUT_DIR", "pass OUT_DIR a folder you can write to")


def test_view_cli_bad_input(bad, capsys):
    _one_error_line(capsys, view.main([bad["missing"]]), "does not exist", "pass a run folder")
    _one_error_line(capsys, view.main([bad["scene"]]), "no trained run", "pass a run folder")


def test_synthetic_and_zoom_ab_cli_bad_input(bad, capsys):
    from experiments import zoom_ab
    from patexgs_jax.data import synthetic

    code = synthetic.main([bad["unwritable"]])
    _one_error_line(capsys, code, "cannot write", "pass OUT_DIR a folder you can write to")
    code = zoom_ab.main(["--study", bad["missing"]])
    _one_error_line(capsys, code, "no results.json in --study", "python -m experiments.mipnerf360 --out")


def test_train_help_documents_method_and_out(capsys):
    with pytest.raises(SystemExit):
        train_cli.main(["-h"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--method METHOD what to train (default: patexgs)" in text
    assert "--out OUT the run's folder" in text and "(no default: required)" in text
    assert "--skip-unreadable" in text and "--checkpoint-on-stop STEPS" in text


def test_corrupt_image_named_before_any_work_and_skippable(tmp_path, capsys):
    """A truncated image (its header intact, so loading accepts it) is named, with the flag that
    skips it, before anything compiles; the run leaves no folder behind; the flag drops its view."""
    from data_builders import make_colmap_scene
    from patexgs_jax.data import check_images, load

    scene = make_colmap_scene(tmp_path / "scene", n_images=6)
    bad = tmp_path / "scene" / "images" / scene["names"][2]
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])
    out = tmp_path / "out"
    line = _one_error_line(capsys, train_cli.main(["--data", str(tmp_path / "scene"), "--out", str(out)]),
                           "1 of 6 images cannot be used", str(bad), "pass --skip-unreadable")
    assert "skip_missing" not in line
    assert not out.exists()  # no empty checkpoints/ (nor --out) left by a run that never started
    ds = check_images(load(tmp_path / "scene", factor=1, verbose=False), skip=True)
    assert len(ds.views) == 5 and scene["names"][2] not in [v.name for v in ds.views]
    assert ds.info["skipped"] == [scene["names"][2]]
    assert "skipped 1 of 6 views" in capsys.readouterr().err


def test_resume_command_and_flag_hint():
    assert train_cli.resume_command("patexgs_jax.train", ["--data", "my scene", "--out", "r"]) == (
        "python -m patexgs_jax.train --data 'my scene' --out r --resume")
    assert train_cli.resume_command("patexgs_jax.train", ["--out", "r", "--resume"]).count("--resume") == 1
    err = train_cli.skip_flag_hint(ValueError("x.png is missing; restore it, or load with skip_missing=True."))
    assert str(err) == "x.png is missing; restore it, or pass --skip-unreadable."


def test_time_estimate_and_the_long_run_note():
    from patexgs_jax.training import preset_config
    from patexgs_jax.training.estimate import format_seconds, long_run_note, run_estimate

    paper = preset_config("paper")  # 30,000 + 30,000 steps
    left, whole = run_estimate(paper, True, 0, 1, 0.1)  # 0.1 s a 2DGS step, a textured step 3x that
    assert whole == pytest.approx(30_000 * 0.1 + 30_000 * 0.3) and left == pytest.approx(whole)
    left, _ = run_estimate(paper, True, 40_000, 2, 0.5)  # measured in the texture stage
    assert left == pytest.approx(20_000 * 0.5)
    left, whole = run_estimate(preset_config("tiny", method="2dgs"), False, 100, 1, 0.1)
    assert whole == pytest.approx(60.0) and left == pytest.approx(50.0)
    assert [format_seconds(s) for s in (40, 14 * 60, 2 * 3600 + 5 * 60)] == ["40 s", "14 min", "2 h 05 min"]
    note = long_run_note(paper, (0.1, 0.3), 1600, 1200, 1.0)  # 3000 s + 9000 s
    assert note.startswith("note: this run takes about 3 h 20 min on ")
    assert "(30,000 + 30,000 steps on 1600x1200 px images)" in note
    # cpu: 1,000 x 0.1 + 400 x 0.3 s; factor 2: a quarter of 3 h 20 min
    assert "--preset cpu (1,000 + 400 steps, about 4 min)" in note
    assert "--factor 2 (images 2x smaller a side than full size, about 50 min)" in note
    assert note.endswith("brings it down. Going on.")
    assert "--factor 5 " in long_run_note(paper, (0.04, 0.1), 400, 300, 4.0)  # 70 min at 4: the next factor
    assert "--factor 4 " in long_run_note(paper, (0.4, 1.2), 1600, 1200, 1.0)  # 13 h 20 min: 4 x 4 smaller
    small = long_run_note(paper, (0.4, 1.2), 312, 175, 4.0)  # --factor 14 would leave 50 px: not offered
    assert "--factor" not in small and small.endswith("(1,000 + 400 steps, about 15 min) brings it down. Going on.")


def test_mipnerf360_unknown_group_names_the_groups_and_leaves_no_out(tmp_path, capsys):
    out = tmp_path / "study"
    line = _one_error_line(capsys, mipnerf360.main(["--methods", "table9", "--out", str(out), "--no-compile-cache"]),
                           "unknown method 'table9'", "2dgs", "patexgs")
    for group in ("table1", "table2", "tables", "table4", "zoom-in"):
        assert group in line, (group, line)
    assert not out.exists()
    # A failure after --out was checked (no such scene) leaves no empty folder either.
    _one_error_line(capsys, mipnerf360.main(["--data", str(tmp_path / "nope"), "--out", str(out),
                                             "--no-compile-cache"]), "does not exist")
    assert not out.exists()
