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


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Free XLA's compiled programs after each test module. Every compiled CPU program keeps
    memory mappings for its code, and the whole suite in one process compiles thousands: two
    modules (test_pbd, test_pbd_grad) reached 20,000 mappings, and past the kernel's
    vm.max_map_count (65,530) XLA's next compilation crashed the process with a segmentation
    fault (seen at 87 % of the suite). Modules share few programs, so little is compiled twice."""
    yield
    import gc

    jax.clear_caches()
    gc.collect()


@pytest.fixture
def shared():
    """``shared("data", "ict", "ict_face.npz") -> Path``; skips/fails when absent."""
    return shared_path


@pytest.fixture(scope="session")
def default_rig():
    """The default head's rig (``build_rig(generic_head())``), built once per session: its
    NumPy build is the same for every module (rigs are immutable pytrees)."""
    from jaxface.anatomy.rig import build_rig
    from jaxface.head import generic_head

    return build_rig(generic_head())
