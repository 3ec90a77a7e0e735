"""The paper's settings: ``--sigma`` (Eq. 7's sigma), ``patexgs-literal`` read end to end, and
docs/paper.md's settings table checked against the code's defaults."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from patexgs_jax import adaptive
from patexgs_jax.plan import eq7_texels
from patexgs_jax.schedule import TextureSchedule, growth_schedule, growth_steps
from patexgs_jax.training.config import TrainConfig, preset_config


def _views(sizes):
    return [SimpleNamespace(camera=SimpleNamespace(height=h, width=w)) for h, w in sizes]


def _schedule(cfg, sizes):
    return TextureSchedule(cfg, None, _views(sizes), cfg.render_config())


@pytest.mark.parametrize("h, w", [(96, 128), (1080, 1920)])
def test_paper_sigma_is_h_times_w_over_1e4_of_the_views(h, w):
    cfg = preset_config("tiny", sigma="paper")
    sched = _schedule(cfg, [(h, w)] * 3)
    act = np.ones(50, bool)
    sides, sigma, budget = sched.allocation_sides(np.ones((3, 50)), act)
    assert sigma == pytest.approx(h * w / 1e4, rel=1e-12) and budget is None
    np.testing.assert_array_equal(sides, adaptive.initial_texture_sizes(np.ones((3, 50)), h * w / 1e4))
    assert sched.sigma_from(act) == f"the paper's H x W / 1e4 (H x W = {h} x {w})"
    # --plan's Eq. 7 line says the same.
    _, _, plan_sigma, how = eq7_texels([h * w] * 3, 50, cfg)
    assert plan_sigma == pytest.approx(h * w / 1e4, rel=1e-12) and "from the paper's H x W / 1e4" in how


def test_views_of_two_sizes_take_their_mean_and_the_other_settings():
    act = np.ones(40, bool)
    sizes = [(96, 128), (48, 64)]
    paper = _schedule(preset_config("tiny", sigma="paper"), sizes)
    assert paper.allocation_sides(np.ones((2, 40)), act)[1] == pytest.approx((96 * 128 + 48 * 64) / 2 / 1e4)
    assert paper.sigma_from(act) == "the paper's H x W / 1e4 (H x W = 48 x 64, 96 x 128)"
    scene = _schedule(preset_config("tiny"), sizes)  # the default: half the pixel-views a Gaussian
    assert scene.allocation_sides(np.ones((2, 40)), act)[1] == pytest.approx(0.5 * (96 * 128 + 48 * 64) / 40)
    assert scene.sigma_from(act) == "the pixel share"
    given = _schedule(preset_config("tiny", sigma="2.5"), sizes)
    assert given.cfg.sigma == 2.5 and given.allocation_sides(np.ones((2, 40)), act)[1] == 2.5
    assert given.sigma_from(act) == "given"


@pytest.mark.parametrize("bad", ["papr", "0", "-1", "nan", True, "inf"])
def test_a_bad_sigma_is_refused_naming_the_choices(bad):
    with pytest.raises(ValueError, match="sigma must be 'paper'.*'scene'.*positive number"):
        TrainConfig(sigma=bad)


def test_the_sigma_flag_refuses_a_bad_value(capsys):
    from experiments import mipnerf360
    from patexgs_jax.training.cli import main

    for cli in (main, mipnerf360.main):
        with pytest.raises(SystemExit) as e:
            cli(["--plan", "--sigma", "papr"])
        assert e.value.code == 2 and "sigma must be 'paper'" in capsys.readouterr().err


def test_literal_is_the_paper_end_to_end():
    lit, ours = preset_config("tiny", method="patexgs-literal"), preset_config("tiny", method="patexgs")
    assert lit.sigma_setting == "paper" and ours.sigma_setting == "scene"
    assert preset_config("tiny", method="patexgs-literal", sigma="scene").sigma_setting == "scene"
    assert lit.render_config().lambda_mip == 0.4 and lit.render_config().coverage == "lowpass"
    assert growth_schedule(lit).t_final == lit.total_steps  # Eq. 9's t_final: the stage's last step
    assert growth_schedule(ours).t_final == ours.iters_2dgs + int(ours.growth_stop * ours.iters_tex)
    assert growth_steps(lit)[-1] > growth_steps(ours)[-1]
    assert preset_config("tiny", method="patexgs-paper-sigma").render_config() == ours.render_config()


def _settings_table() -> dict[str, list[str]]:
    """docs/paper.md's settings table: {setting: its cells}."""
    from locations import REPO

    rows = {}
    for line in (REPO / "docs" / "paper.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 5 and not set(cells[0]) <= {"-", " "} and cells[0] != "setting":
            rows[cells[0]] = cells
    return rows


def _first_code(cell: str) -> str:
    import re

    m = re.search(r"`([^`]*)`", cell)
    assert m, f"no value in backticks in {cell!r}"
    return m.group(1)


def test_the_settings_table_matches_the_code():
    """Each code column's first value in backticks is what the `paper` preset and the method use."""
    from patexgs_jax.adaptive import DEFAULT_MAX_SIZE

    table = _settings_table()
    for col, method in ((2, "patexgs"), (3, "patexgs-literal")):
        cfg = preset_config("paper", method=method)
        rc, spec = cfg.render_config(), cfg.spec
        want = {
            "iterations (2DGS, textures)": f"{cfg.iters_2dgs:,} + {cfg.iters_tex:,}",
            "texture warm-up": f"{cfg.warmup_tex:,}",
            "Eq. 7 sigma": str(cfg.sigma_setting),
            "Eq. 9 tau_preset": repr(cfg.tau_preset),
            "Eqs. 8-10 growth statistic": str(cfg.growth_interval),
            "Eq. 9 t_final": repr(1.0 if spec.growth_to_end else cfg.growth_stop),
            "Eq. 11 lambda_mip": f"{rc.lambda_mip:.4g}",
            "Eq. 11 level": rc.mip,
            "RGBA mipmaps (Eq. 12-13)": "on" if rc.rgb_mip and rc.alpha_mip else "off",
            "Eq. 13 coverage": rc.coverage,
            "largest texture side": str(cfg.max_texture_size),
        }
        assert set(want) <= set(table), sorted(set(want) - set(table))
        for setting, value in want.items():
            assert _first_code(table[setting][col]) == value, (method, setting, table[setting][col], value)
    assert preset_config("paper").max_texture_size == DEFAULT_MAX_SIZE


def test_results_rows_match_their_benchmark_files():
    """docs/results.md's side-by-side of the paper read literally (embedded scene and beer) and its
    readings of Eq. 13 are the rows of ``experiments.headline --paper`` and
    ``experiments.zoom_ab.reading_rows`` of their files, and each study's own rows are its lowpass
    reading."""
    import json

    from experiments import headline, zoom_ab
    from locations import REPO

    text = (REPO / "docs" / "results.md").read_text() + "\n## end"
    section = text[text.index("## Results: the paper read literally"):]
    section = section[:section.index("\n## ", 1)]
    for name, label in (("paper_tiny.json", "embedded"), ("paper_beer.json", "beer")):
        data = json.loads((REPO / "benchmarks" / name).read_text())
        assert data["date"] and data["conditions"] and f"`{data['version']['git']}`" in section, name
        rows = headline.paper_rows(data, label)
        assert [r.split(" | ")[1] for r in rows] == ["2dgs", "patexgs", "patexgs-literal", "patexgs-paper-sigma"]
        for row in rows:
            assert row in section, row
        # The study's own rows of the literal and 2DGS models are their lowpass reading.
        per = next(iter(data["results"].values()))
        for method in ("patexgs-literal",) + (("2dgs",) if label == "beer" else ()):
            e = per[method]
            own = f"| {label} | {method} | lowpass | {e['1']['psnr']:.2f} | {e['2']['psnr']:.2f} | "
            assert own in section, own
    for name, label in (("eq13_tiny.json", "embedded"), ("eq13_beer.json", "beer"), ("eq13_beer_2dgs.json", "beer")):
        readings = json.loads((REPO / "benchmarks" / name).read_text())
        assert readings["date"] and f"`{readings['git'].split('-')[0]}`" in section, name
        rows = zoom_ab.reading_rows(readings, label)
        assert rows and all(r in section for r in rows), rows
