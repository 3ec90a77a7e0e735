"""What the tests may assume of the backend they run on (the suite runs on a CPU in CI and on a GPU
through scripts/gpu_check.sh)."""

from __future__ import annotations

import os

import jax

#: Why a bit-exact comparison across runs is checked on the CPU only.
NOT_BITWISE = ("bit-exact results across runs hold on the CPU; a GPU's scatter-adds (gradients of "
               "gathers, the densification statistics) use atomics whose order varies between runs "
               "(XLA_FLAGS=--xla_gpu_deterministic_ops=true makes them deterministic)")


def bitwise_reproducible() -> bool:
    """Whether the same program on the same inputs gives the same bits in every run here."""
    return jax.default_backend() == "cpu" or "xla_gpu_deterministic_ops=true" in os.environ.get("XLA_FLAGS", "")
