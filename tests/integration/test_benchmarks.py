"""The benchmark scripts run and report what they promise (tiny sizes: behaviour, not speed)."""

import json
import math

import pytest

from experiments import bench_render
from locations import REPO


def test_bench_render_reports_each_configuration(tmp_path, capsys):
    out = tmp_path / "render.json"
    bench_render.main(["--gaussians", "300", "--sizes", "48x32", "--repeats", "1", "--no-peak",
                       "--configs", "2dgs,tex8-mip,mip-splatting", "--json", str(out)])
    data = json.loads(out.read_text())
    for key in ("schema", "git", "date", "machine", "cpu", "cpus", "jax", "backend", "devices"):
        assert key in data, key  # where and on what the figures were measured
    assert data["schema"] == bench_render.SCHEMA and data["timing"] == "interleaved"
    rows = data["results"]
    assert [r["config"] for r in rows] == ["2dgs", "tex8-mip", "mip-splatting"]  # (the last: 3D Gaussians)
    for r in rows:
        assert (r["gaussians"], r["width"], r["height"]) == (300, 48, 32)
        assert r["recompiles"] == 0
        assert r["binned_pairs"] > 0 and r["max_tile"] > 0
        for key in ("forward_ms", "forward_backward_ms", "bin_ms", "listed_pixel_pairs_per_s",
                    "temp_backward_mib"):
            assert math.isfinite(r[key]) and r[key] > 0, (r["config"], key)
        assert r["fraction_of_peak"] is None  # --no-peak
        # Interleaved timing: each configuration's ratio to 2DGS is a median of per-round ratios.
        for key in ("forward_over_2dgs", "forward_backward_over_2dgs"):
            assert math.isfinite(r[key]) and r[key] > 0, (r["config"], key)
    assert rows[0]["forward_over_2dgs"] == 1.0 and rows[0]["forward_backward_over_2dgs"] == 1.0
    printed = capsys.readouterr().out
    assert all(name in printed for name in ("2dgs", "tex8-mip", "mip-splatting"))


def test_bench_render_compositors_side_by_side(tmp_path, capsys):
    """--compositor xla,pallas: a row per configuration and compositor, timed in one process."""
    out = tmp_path / "render.json"
    bench_render.main(["--gaussians", "200", "--sizes", "32x32", "--repeats", "1", "--no-peak",
                       "--configs", "2dgs", "--compositor", "xla,pallas", "--json", str(out)])
    rows = json.loads(out.read_text())["results"]
    assert [(r["config"], r["compositor"]) for r in rows] == [("2dgs", "xla"), ("2dgs", "pallas")]
    assert rows[1]["forward_over_2dgs"] == 1.0  # against the 2dgs row of its own compositor
    assert rows[1]["binned_pairs"] == rows[0]["binned_pairs"] and rows[1]["recompiles"] == 0
    assert "2dgs@pallas" in capsys.readouterr().out


def test_bench_render_rejects_unknown_config(capsys):
    with pytest.raises(SystemExit):
        bench_render.main(["--configs", "2dgs,tex9", "--no-peak"])
    assert "tex9" in capsys.readouterr().err


def test_provenance_header_names_commit_date_and_machine(tmp_path, monkeypatch):
    import datetime
    import subprocess

    from experiments import provenance

    path = provenance.write_benchmark_json(tmp_path / "sub" / "b.json", [{"x": 1}], 3, steps=5)
    data = json.loads(path.read_text())
    assert data["schema"] == 3 and data["steps"] == 5 and data["results"] == [{"x": 1}]
    datetime.datetime.strptime(data["date"], "%Y-%m-%dT%H:%M:%SZ")
    assert data["cpus"] >= 1 and data["devices"] >= 1 and data["machine"] and data["cpu"]
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=provenance._REPO,
                          capture_output=True, text=True).stdout.strip()
    if head:  # a checkout: the commit, marked when tracked files differ from it
        assert data["git"].split("-")[0] == head
    # Outside a checkout (an installed copy), or without git, the commit is null, not an error.
    monkeypatch.setattr(provenance, "_git", lambda *a: None)
    assert provenance.git_commit() is None
    assert not list(tmp_path.glob("sub/*.tmp"))


def test_every_benchmark_file_names_its_provenance():
    """Each file in benchmarks/ says what code, when, on what machine and JAX it was measured; a
    header reconstructed after the fact says so, and a null commit says which code instead."""
    import datetime

    files = sorted((REPO / "benchmarks").glob("*.json"))
    assert files
    for path in files:
        data = json.loads(path.read_text())
        assert isinstance(data["schema"], int) and data["schema"] >= 1, path.name
        datetime.datetime.strptime(data["date"], "%Y-%m-%dT%H:%M:%SZ")
        assert isinstance(data["machine"], str) and data["machine"], path.name
        assert isinstance(data["jax"], str) and data["jax"][0].isdigit(), path.name
        git = data["git"]
        if git is None:
            assert data.get("code") or data.get("provenance"), path.name
        else:
            assert len(git.split("-")[0]) >= 7 and all(c in "0123456789abcdef" for c in git.split("-")[0]), path.name
        provenance_note = data.get("provenance")
        assert provenance_note is None or provenance_note.startswith("reconstructed from git history"), path.name



def test_bench_scale_times_every_host_stage(tmp_path, capsys):
    """bench_scale's rows: every stage of a run on one state, with the fields scripts read; the host
    events flagged as host work; the re-bucketing of a growth event keeps its layout (the in-place
    path), the overflowing one makes a new layout; the JSON rewritten after every row. (Renders and
    steps skipped: behaviour, not speed.)"""
    from experiments import bench_scale

    out = tmp_path / "scale.json"
    bench_scale.main(["--gaussians", "3000", "--width", "64", "--height", "48", "--views", "2",
                      "--eq7-views", "6", "--skip", "counts,eval,step", "--json", str(out)])
    data = json.loads(out.read_text())
    assert data["schema"] == bench_scale.SCHEMA and data["config"]["eq7_views"] == 6
    rows = {r["event"]: r for r in data["rows"]}
    host = ["build_state", "eq7_allocation", "eq7_budget_solve", "densify", "densify_again", "textures_start",
            "allocation_rebucket", "eq8_10_growth", "rebucket", "rebucket_again", "rebucket_overflow",
            "checkpoint_save", "checkpoint_load", "checkpoint_save_async_first", "checkpoint_save_async",
            "checkpoint_save_async_total", "ply_export", "ply_load"]
    assert list(rows) == host
    for r in rows.values():
        assert r["gaussians"] == 3000 and r["host"] is True
        assert math.isfinite(r["seconds"]) and r["seconds"] >= 0
        assert r["peak_rss_bytes"] > 0
    assert rows["rebucket"]["grown"] > 0 and rows["rebucket"]["layout_changed"] is False
    assert rows["rebucket_overflow"]["layout_changed"] is True and rows["rebucket_overflow"]["path"] == "device"
    assert rows["checkpoint_save"]["bytes"] > 0 and rows["ply_export"]["bytes"] > 0
    assert rows["checkpoint_save_async_total"]["bytes"] == rows["checkpoint_save"]["bytes"]
    assert rows["densify"]["cloned"] + rows["densify"]["split"] > 0
    assert rows["densify_again"]["cloned"] + rows["densify_again"]["split"] > 0
    assert rows["eq7_allocation"]["texels"] >= 3000  # at least one texel a Gaussian
    printed = capsys.readouterr().out
    assert "rebucket_again" in printed
