"""Every notebook in ``notebooks/`` runs top to bottom (nbclient, a fresh ``python3`` kernel).

The notebooks are executed from their own folder, as Jupyter does, with the small settings
they are committed with. A notebook that reads the shared data says so in its metadata
(``"jaxface": {"requires_data": true}``): it is skipped when the data is absent, or fails when
``JAXFACE_REQUIRE_DATA=1`` (CI), through :func:`jaxface.testing.shared_path`. The committed
outputs are not compared (pictures and timings change); a notebook passes when no cell raises.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
CELL_TIMEOUT_S = 300


def _notebooks():
    return sorted(NOTEBOOKS.glob("*.ipynb"))


@pytest.mark.parametrize("path", _notebooks(), ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    from jaxface.testing import shared_path, shared_root

    nb = nbformat.read(path, as_version=4)
    env_before = os.environ.get("JAXFACE_SHARED")
    if nb.metadata.get("jaxface", {}).get("requires_data"):
        shared_path("data")  # skip (or fail in CI) without the shared data
        # the kernel runs in notebooks/, where the default ../shared does not apply
        os.environ["JAXFACE_SHARED"] = str(shared_root())
    os.environ.setdefault("MPLBACKEND", "Agg")
    try:
        client = nbclient.NotebookClient(
            nb,
            timeout=CELL_TIMEOUT_S,
            kernel_name="python3",
            resources={"metadata": {"path": str(path.parent)}},
        )
        client.execute()
    finally:
        if env_before is None:
            os.environ.pop("JAXFACE_SHARED", None)
        else:
            os.environ["JAXFACE_SHARED"] = env_before
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors, errors
    # the executed copy, for inspection when something looks wrong
    nbformat.write(nb, tmp_path / path.name)
