"""The suite's own profile (``PATEXGS_TEST_PROFILE``, tests/conftest.py) and its per-file summary
(tests/profile_summary.py): a real pytest run in a subprocess writes one line per test with JAX's
compile times, and the summary adds them up; and where a run keeps the programs it compiled."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from locations import REPO


def test_profile_lines_and_summary(tmp_path, capsys):
    import profile_summary

    path = tmp_path / "profile.jsonl"
    node = "tests/unit/test_export.py::test_round_trip"
    (tmp_path / "xla").mkdir()  # (a cache of its own: in the session's the programs may load instead)
    env = dict(os.environ, JAX_PLATFORMS="cpu", PATEXGS_TEST_PROFILE=str(path),
               PATEXGS_TEST_XLA_CACHE=str(tmp_path / "xla"),
               XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip())
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", node],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    assert len(recs) >= 2 and all(r["test"].startswith(node) for r in recs)
    assert all(r["wall"] > 0 and r["pid"] > 0 for r in recs)
    # the first case compiles its programs (and counts them); each time is within its test's wall
    first = recs[0]
    assert first["compiles"] > 0 and 0 < first["compile"] <= first["wall"]
    assert first["traces"] > 0 and first["lowers"] > 0
    profile_summary.main([str(path), "tests/unit"])
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:2] == ["wall", "s"] and out[1].endswith("tests/unit/test_export.py")
    total = sum(r["wall"] for r in recs)
    assert out[-1].endswith("all") and abs(float(out[-1].split()[0]) - total) < 0.1 * len(recs)


def test_compiled_programs_are_kept_in_the_project_cache(tmp_path):
    """Without PATEXGS_CACHE the session's compile cache is test-xla/ in the user's project cache
    ($XDG_CACHE_HOME/patexgs_jax), kept after the run (a developer's next run loads from it), never
    the command lines' xla/ there; empty entries found there at the start are removed."""
    node = "tests/unit/test_densify.py::test_capacity_doubling"  # (one small program)
    env = {k: v for k, v in os.environ.items() if k not in ("PATEXGS_CACHE", "PATEXGS_TEST_XLA_CACHE",
                                                          "PATEXGS_COMPILE_CACHE")}
    env.update(JAX_PLATFORMS="cpu", XDG_CACHE_HOME=str(tmp_path / "xdg"))
    root = tmp_path / "xdg" / "patexgs_jax"
    (root / "test-xla").mkdir(parents=True)
    # an entry a killed process left empty (JAX would never replace it) goes; a written one stays
    (root / "test-xla" / "jit_f-0123-cache").write_bytes(b"")
    (root / "test-xla" / "jit_g-4567-cache").write_bytes(b"kept")
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", node],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    names = {p.name for p in (root / "test-xla").iterdir()}
    assert "jit_f-0123-cache" not in names and "jit_g-4567-cache" in names and len(names) > 1
    assert not (root / "xla").exists()
