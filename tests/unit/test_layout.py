"""The house the design names: `render.py` and `schedule.py` at the package's top, the public API
kept, no module over 600 lines, no import cycle between the package's modules, and one default
preset rule for both command lines."""

import subprocess
import sys

from locations import REPO as ROOT

MAX_LINES = 600


def test_design_names_render_and_schedule():
    import patexgs_jax as px
    from patexgs_jax.data import load  # noqa: F401  (the README's public API)
    from patexgs_jax.render import RenderConfig, render, render_jit
    from patexgs_jax.schedule import TextureSchedule
    from patexgs_jax.training import train  # noqa: F401

    assert px.render is render and px.render_jit is render_jit and px.RenderConfig is RenderConfig
    assert callable(px.render) and px.Scene and px.Camera
    assert TextureSchedule.__module__ == "patexgs_jax.schedule"
    readme = (ROOT / "docs" / "development.md").read_text()
    layout = readme[readme.index("## Layout"):]
    first_map = layout[:layout.index("| module |")]
    assert "render.py" in first_map and "schedule.py" in first_map


def test_no_module_over_600_lines():
    long = {str(p.relative_to(ROOT)): n for folder in ("patexgs_jax", "experiments")
            for p in (ROOT / folder).rglob("*.py") if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}; split them by concern"


def test_each_module_imports_on_its_own():
    """Every module of the package imports first in a fresh interpreter (no order it depends on)."""
    names = ["patexgs_jax.schedule", "patexgs_jax.render", "patexgs_jax.textures.rebucket",
             "patexgs_jax.training.compile_ahead", "patexgs_jax.training.estimate", "patexgs_jax.training.steps",
             "patexgs_jax.viewer.frames", "patexgs_jax.data.colmap_text", "patexgs_jax.data.colmap_binary",
             "patexgs_jax.data.colmap_records", "patexgs_jax.padding"]
    code = ("import importlib, sys\n"
            "for n in sys.argv[1:]:\n"
            "    for m in [k for k in sys.modules if k.startswith('patexgs_jax')]:\n"
            "        del sys.modules[m]\n"
            "    importlib.import_module(n)\n")
    r = subprocess.run([sys.executable, "-c", code, *names], capture_output=True, text=True, cwd=ROOT, timeout=300,
                       env={"JAX_PLATFORMS": "cpu", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]


def test_default_preset_fits_the_device_and_the_scene():
    from patexgs_jax.training.config import default_preset

    assert default_preset(None, "cpu") == default_preset(None, "gpu") == "tiny"
    assert default_preset("/data/garden", "cpu") == "cpu"
    assert default_preset("/data/garden", "gpu") == default_preset("/data/garden", "tpu") == "paper"
