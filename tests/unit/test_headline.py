"""experiments.headline: the README's rows from a study's record, and clear errors (nothing written)
for a file that is not one."""

import json

from experiments import headline


def _entry(psnr: float) -> dict:
    scales = {"1": dict(psnr=psnr, alias_psnr=None)}
    scales.update({str(s): dict(psnr=psnr + s / 10, alias_psnr=30.0 + s) for s in (2, 4, 8)})
    return dict(scales, num_gaussians=10, storage_mb=0.5)


def _study(tmp_path, results) -> str:
    path = tmp_path / "results.json"
    path.write_text(json.dumps(dict(version=dict(git="abc1234"), results=results)))
    return str(tmp_path)


def test_zoom_rows_follow_the_study_order_and_skip_methods_without_zoom_out(tmp_path):
    results = {"scene": {"patexgs": _entry(21.0), "2dgs": _entry(20.0), "half": {"1": dict(psnr=1.0)}}}
    rows = headline.zoom_rows(headline.read(_study(tmp_path, results)), "embedded")
    assert rows == ["| embedded | patexgs | 21.00 | 21.20 | 21.40 | 21.80 | 32.00 | 34.00 | 38.00 |",
                    "| embedded | 2dgs | 20.00 | 20.20 | 20.40 | 20.80 | 32.00 | 34.00 | 38.00 |"]


def test_save_keeps_the_study_with_provenance(tmp_path, capsys):
    src = _study(tmp_path, {"scene": {"2dgs": _entry(20.0)}})
    out = tmp_path / "zoom.json"
    assert headline.main([src, "--zoom", "beer", "--save", str(out), "--conditions", "idle"]) == 0
    saved = json.loads(out.read_text())
    assert saved["conditions"] == "idle" and saved["date"] and saved["version"]["git"] == "abc1234"
    assert headline.zoom_rows(saved, "beer") == headline.zoom_rows(headline.read(src), "beer")
    assert "| beer | 2dgs |" in capsys.readouterr().out


def test_bad_sources_name_the_problem_and_write_nothing(tmp_path, capsys):
    out = tmp_path / "never.json"
    assert headline.main([str(tmp_path / "missing"), "--zoom", "x", "--save", str(out)]) == 2
    assert "cannot read" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "results.json").write_text("{}")
    assert headline.main([str(tmp_path / "empty"), "--budgets", "x", "--save", str(out)]) == 2
    assert "holds no study results" in capsys.readouterr().err
    no_zoom = _study(tmp_path, {"scene": {"2dgs": {"1": dict(psnr=1.0)}}})
    assert headline.main([no_zoom, "--zoom", "x", "--save", str(out)]) == 2
    assert "no method evaluated at 1, 1/2, 1/4 and 1/8" in capsys.readouterr().err
    assert headline.main([no_zoom, "--budgets", "x", "--save", str(out)]) == 2
    assert "no budget with both 2dgs and patexgs" in capsys.readouterr().err
    assert headline.main([no_zoom]) == 2
    assert "is it the main job's" in capsys.readouterr().err
    assert not out.exists()
