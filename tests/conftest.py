"""Shared pytest configuration.

* float64 is enabled for the whole test session so that finite-difference gradient checks
  are meaningful; library code is dtype-agnostic and is also exercised with float32 inputs.
* ``shared`` fixture: a callable giving paths into ../shared (skip, or fail in CI).
"""

import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")

# One session cache folder, shared by this process and every process it starts (CLI
# subprocesses, notebook kernels, Dask workers inherit the environment): JAX's persistent
# compilation cache for those processes, so a program one of them compiled (the rig's
# synthesis, the fit's inner solve) is loaded by every later one; and
# ``$XDG_CACHE_HOME``, so the library's on-disk caches (ARKit inverse maps) are shared too and
# nothing is written to the home folder. ``JAXFACE_TEST_CACHE=DIR`` keeps the folder between
# runs (a warm re-run); otherwise it is a fresh temporary folder removed at the end. Tests of
# the cache itself use their own folders (tests/commands/test_cli.py).
# (pytest-xdist workers and nested pytest runs inherit the folder of the process that made it,
# which alone removes it.)
_INHERITED = os.environ.get("JAXFACE_TEST_CACHE") or os.environ.get("_JAXFACE_SESSION_CACHE")
SESSION_CACHE = Path(_INHERITED or tempfile.mkdtemp(prefix="jaxface-test-cache-")).resolve()
SESSION_CACHE.mkdir(parents=True, exist_ok=True)
_OWN_CACHE = not _INHERITED
os.environ["_JAXFACE_SESSION_CACHE"] = str(SESSION_CACHE)
os.environ["XDG_CACHE_HOME"] = str(SESSION_CACHE / "xdg")
# prepared subjects (jaxface.fit.subject_cache): the suite builds the same Bosphorus neutral
# with the same options in several modules, CLI runs, Dask workers and a notebook; the first
# build is kept and the others load it (a test of the cache itself uses its own folder)
os.environ["JAXFACE_SUBJECT_CACHE"] = str(SESSION_CACHE / "subjects")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
# the processes the tests start read the folder from the environment (JAX reads it at
# import); this process uses it too, so a program a CLI subprocess, a Dask worker or an earlier
# module compiled (the bs900 rig's synthesis and reverse pass, the default head's) is loaded,
# not compiled again after ``jax.clear_caches`` below (measured: 549 -> 504 s on five
# rig-heavy modules; a 0.2 s minimum compile time instead of JAX's 1 s wrote more than it
# saved, 543 s). ``JAXFACE_TEST_INPROCESS_CACHE=0`` compiles this process without it. The
# CLI run in-process leaves JAX's configuration alone ("off").
os.environ["JAX_COMPILATION_CACHE_DIR"] = str(SESSION_CACHE / "xla")
os.environ.setdefault("JAXFACE_COMPILE_CACHE", "off")
if os.environ.get("JAXFACE_TEST_INPROCESS_CACHE", "1") == "1":
    jax.config.update("jax_compilation_cache_dir", str(SESSION_CACHE / "xla"))

from jaxface.testing import shared_path  # noqa: E402


def pytest_unconfigure(config):
    if _OWN_CACHE:
        shutil.rmtree(SESSION_CACHE, ignore_errors=True)


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
