"""jaxface._parallel.thread_map: order, exceptions, and a real parallel NumPy workload."""

from __future__ import annotations

import numpy as np
import pytest

from jaxface._parallel import n_workers, thread_map


def test_results_in_input_order_and_errors_propagate():
    assert thread_map(lambda i: i * i, range(17)) == [i * i for i in range(17)]
    assert thread_map(lambda i: i, []) == []
    assert n_workers() >= 1

    def boom(i):
        if i == 3:
            raise ValueError("block 3")
        return i

    with pytest.raises(ValueError, match="block 3"):
        thread_map(boom, range(6))


def test_closest_point_query_in_blocks_equals_one_block():
    from jaxface.fit.metrics import SurfaceIndex
    from jaxface.head import generic_head

    mesh = generic_head().mesh
    rng = np.random.default_rng(0)
    q = mesh.vertices[rng.integers(0, mesh.n_vertices, 5000)] + rng.normal(
        scale=2.0, size=(5000, 3)
    )
    idx = SurfaceIndex(mesh.vertices, mesh.triangles)
    one = idx.query(q, chunk=10_000)
    blocks = idx.query(q, chunk=700)  # 8 blocks on the thread pool
    np.testing.assert_array_equal(one.triangles, blocks.triangles)
    np.testing.assert_allclose(one.distances, blocks.distances, atol=0)
    np.testing.assert_allclose(one.points, blocks.points, atol=0)


def test_outer_jobs_may_use_the_inner_pool():
    """Whole jobs on the outer pool that run blocked queries on the inner pool (what a batch
    fit does per scan) finish, in order, with the sequential results."""
    from jaxface.fit.metrics import SurfaceIndex
    from jaxface.head import generic_head

    mesh = generic_head().mesh
    idx = SurfaceIndex(mesh.vertices, mesh.triangles)
    rng = np.random.default_rng(1)
    qs = [
        mesh.vertices[rng.integers(0, mesh.n_vertices, 3000)]
        + rng.normal(scale=1.0, size=(3000, 3))
        for _ in range(5)
    ]

    def job(q):
        return idx.query(q, chunk=500).distances  # 6 inner blocks per job

    par = thread_map(job, qs, outer=True)
    for q, d in zip(qs, par):
        np.testing.assert_array_equal(d, idx.query(q, chunk=10_000).distances)


def test_outer_jobs_that_submit_outer_jobs_finish():
    """An outer job that maps outer jobs itself (a batch fit's per-scan work, should a caller
    run fit_points inside an outer job) runs them on its own thread instead of waiting on its
    own pool, whose workers could then all be waiting: every job finishes, in order. Run in a
    child process, so that a deadlock fails the test (timeout) instead of hanging it."""
    import subprocess
    import sys

    code = (
        "import threading\n"
        "from jaxface._parallel import n_workers, thread_map\n"
        "seen = []\n"
        "def inner(j):\n"
        "    seen.append(threading.current_thread().name)\n"
        "    return j + 1\n"
        "out = thread_map(lambda i: thread_map(inner, range(i, i + 3), outer=True), range(6), outer=True)\n"
        "assert out == [[i + 1, i + 2, i + 3] for i in range(6)], out\n"
        "assert n_workers() < 2 or all(n.startswith('jaxface-outer') for n in seen), seen\n"
        "print('ok')\n"
    )
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("outer jobs mapping outer jobs deadlocked")
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
