"""Shared pytest configuration.

* float64 is enabled for the whole test session so that finite-difference gradient checks
  are meaningful; library code is dtype-agnostic and is also exercised with float32 inputs.
* ``shared`` fixture: a callable giving paths into ../shared (skip, or fail in CI).
"""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
# the CLI's persistent compilation cache stays off in tests run in-process (no writes to the
# home folder); tests/test_cli.py turns it on in a temporary folder in a subprocess
os.environ.setdefault("JAXFACE_COMPILE_CACHE", "off")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

from jaxface.testing import shared_path  # noqa: E402


@pytest.fixture
def shared():
    """``shared("data", "ict", "ict_face.npz") -> Path``; skips/fails when absent."""
    return shared_path
