import subprocess
import sys
import textwrap

import pytest

from jaxface.errors import DataNotFoundError
from jaxface.testing import shared_path


def test_missing_data_raises_outside_pytest(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXFACE_SHARED", str(tmp_path))
    with pytest.raises(DataNotFoundError, match="JAXFACE_SHARED"):
        shared_path("data", "nope.npz", pytest_skip=False)


@pytest.mark.parametrize("require,expect", [("0", "skipped"), ("1", "failed")])
def test_missing_data_skips_or_fails(tmp_path, require, expect):
    test = tmp_path / "test_inner.py"
    test.write_text(
        textwrap.dedent("""
        from jaxface.testing import shared_path
        def test_needs_data():
            shared_path("data", "does_not_exist.npz")
    """)
    )
    env = {"JAXFACE_SHARED": str(tmp_path), "JAXFACE_REQUIRE_DATA": require, "PATH": ""}
    import os

    env = {**os.environ, **env}
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    assert f"1 {expect}" in r.stdout, r.stdout + r.stderr


def test_shared_data_present_in_ci(shared):
    # In CI (JAXFACE_REQUIRE_DATA=1) this fails if ../shared is not beside the clone.
    assert (shared("data") / "ict" / "ict_face.npz").is_file()
