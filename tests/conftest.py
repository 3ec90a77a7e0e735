"""Shared test settings: tests import helpers from this folder; hypothesis keeps examples few
(each new shape costs a JAX compile on CPU) and has no deadline (compiles are slow)."""

import os
import sys

from hypothesis import settings

sys.path.insert(0, os.path.dirname(__file__))

settings.register_profile("default", deadline=None, max_examples=10, derandomize=False)
settings.register_profile("ci", deadline=None, max_examples=10, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")
