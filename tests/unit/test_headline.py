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


def test_tables_rows_set_ours_beside_the_papers(tmp_path, capsys):
    """``--tables LABEL``: the README's Table 1, Table 2 and zoom-in rows of a study (means over its
    scenes), the paper's rows first in its order, the paper's Mip-NeRF 360 figures beside ours."""
    def entry(psnr, zoom_in=False):
        e = dict(_entry(psnr), train_seconds=12.0, num_gaussians=1200)
        for s in "1248":
            e[s].update(ssim=0.5, lpips=None)
        if zoom_in:
            e["zoom_in"] = {z: dict(psnr=psnr - int(z), ssim=0.4, lpips=None, views=1, source="x") for z in "248"}
        return e

    results = {"a": {"patexgs": entry(21.0, True), "2dgs": entry(20.0, True), "patexgs-no-mip": entry(19.0)},
               "b": {"patexgs": entry(23.0, True), "2dgs": entry(22.0, True)}}
    data = headline.read(_study(tmp_path, results))
    assert headline.table1_rows(data, "tiny") == [
        "| tiny | 2dgs | 2DGS* | 21.00 | 27.16 | 0.500 | 0.802 | - | 0.237 | 1,200 | 0.50 | 12 |",
        "| tiny | patexgs | Ours | 22.00 | 27.71 | 0.500 | 0.816 | - | 0.197 | 1,200 | 0.50 | 12 |",
        "| tiny | patexgs-no-mip |  | 19.00 |  | 0.500 |  | - |  | 1,200 | 0.50 | 12 |"]
    assert headline.table2_rows(data, "tiny")[1] == (
        "| tiny | patexgs | Ours | 22.00 | 22.20 | 22.40 | 22.80 | 27.71 | 28.63 | 28.49 | 27.12 |")
    assert headline.zoom_in_rows(data, "tiny") == ["| tiny | 2dgs | 21.00 | 19.00 | 17.00 | 13.00 | 0.400 |",
                                                   "| tiny | patexgs | 22.00 | 20.00 | 18.00 | 14.00 | 0.400 |"]
    assert headline.main([str(tmp_path), "--tables", "tiny"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[:3] == ["Table 1:", headline.TABLE1_HEADER, "| --- | --- | --- |" + " ---: |" * 9]
    assert "Zoom-in (Mip-Splatting's protocol, PSNR):" in out and out[-1] == headline.zoom_in_rows(data, "tiny")[1]
    (tmp_path / "x").mkdir()
    no_full = _study(tmp_path / "x", {"a": {"2dgs": {"2": dict(psnr=1.0)}}})
    assert headline.main([no_full, "--tables", "tiny"]) == 2
    assert "no entry evaluated at full size" in capsys.readouterr().err
