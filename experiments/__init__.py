"""Runnable studies and benchmarks (``python -m experiments.<name>``)."""

# A Ctrl-C while `python -m experiments...` imports: one line, no traceback (see patexgs_jax._startup).
from patexgs_jax import _startup  # noqa: F401  (installs on import)
