"""Shared test settings: tests import helpers from this folder; hypothesis keeps examples few
(each new shape costs a JAX compile on CPU) and has no deadline (compiles are slow)."""

import os
import sys

import pytest
from hypothesis import settings

from patexgs_jax import compiled

sys.path.insert(0, os.path.dirname(__file__))

settings.register_profile("default", deadline=None, max_examples=10, derandomize=False)
settings.register_profile("ci", deadline=None, max_examples=10, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """After each module, free JAX's compiled code once the process holds a quarter of its
    memory-map cap (see patexgs_jax.compiled): a whole suite in one process compiles far more than
    the cap allows, and reaching it ended in a crash (or, with pycolmap's signal handler, a hang)."""
    yield
    compiled.release_compiled_code(threshold=0.25)
