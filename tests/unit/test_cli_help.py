"""Every flag of every command line has a help line (``-h`` explains each one)."""

import argparse
import importlib

import pytest

#: The command lines a user runs (``python -m MODULE``), and the function that builds each parser.
COMMANDS = [
    "patexgs_jax.training.cli", "patexgs_jax.viewer.server", "patexgs_jax.data.synthetic",
    "patexgs_jax.data.download", "patexgs_jax.sfm", "experiments.mipnerf360", "experiments.tradeoffs",
    "experiments.zoom_ab", "experiments.headline", "experiments.plan_check", "experiments.plan_time",
    "experiments.bench_render",
    "experiments.bench_train", "experiments.bench_scale", "experiments.bench_viewer", "experiments.bench_mappings",
    "experiments.device_check", "patexgs_jax.render_cli", "patexgs_jax.evaluate",
]


class _Parsed(Exception):
    """Raised in place of parsing: the parser is built, nothing runs."""


@pytest.mark.parametrize("module", COMMANDS)
def test_every_flag_has_a_help_line(module, monkeypatch):
    seen = []

    def capture(self, *args, **kwargs):
        seen.append(self)
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", capture)
    with pytest.raises(_Parsed):
        importlib.import_module(module).main([])
    parser = seen[0]
    bare = [a.option_strings[0] if a.option_strings else a.dest for a in parser._actions
            if not (a.help and a.help.strip()) and a.help is not argparse.SUPPRESS]
    assert not bare, f"python -m {module}: no help line for {', '.join(bare)}"
