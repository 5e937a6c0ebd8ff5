"""Access to the shared reference data for tests, benchmarks and notebooks.

The data folder is found through the ``JAXFACE_SHARED`` environment variable (default
``../shared`` relative to the current directory, i.e. beside the repository). Tests that
need it call :func:`shared_path` (or use the ``shared`` fixture from ``tests/conftest.py``):
when the data is absent they are skipped with a clear reason, unless
``JAXFACE_REQUIRE_DATA=1`` is set (as in CI), in which case they fail.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import DataNotFoundError

__all__ = ["shared_root", "shared_path", "require_data"]


def require_data() -> bool:
    """True when missing shared data must fail rather than skip (``JAXFACE_REQUIRE_DATA=1``)."""
    return os.environ.get("JAXFACE_REQUIRE_DATA", "").strip().lower() in {"1", "true", "yes", "on"}


def shared_root() -> Path:
    """The shared folder: ``$JAXFACE_SHARED`` or ``../shared`` (not checked for existence)."""
    return Path(os.environ.get("JAXFACE_SHARED", "../shared")).expanduser().resolve()


def shared_path(*parts: str, pytest_skip: bool = True) -> Path:
    """Path of a file or folder below the shared folder, e.g. ``shared_path("data", "ict", "ict_face.npz")``.

    If it does not exist: under pytest (``pytest_skip=True``) the calling test is skipped with
    the reason, or failed when ``JAXFACE_REQUIRE_DATA=1``; otherwise :class:`DataNotFoundError`
    is raised telling the user to set ``JAXFACE_SHARED``.
    """
    p = shared_root().joinpath(*parts)
    if p.exists():
        return p
    msg = (
        f"shared data not found: {p}. Set JAXFACE_SHARED to the folder that holds "
        f"data/ (currently {os.environ.get('JAXFACE_SHARED', '<unset, default ../shared>')})."
    )
    if pytest_skip:
        import pytest

        if require_data():
            pytest.fail(msg + " JAXFACE_REQUIRE_DATA=1, so this is a failure, not a skip.")
        pytest.skip(msg)
    raise DataNotFoundError(msg)
