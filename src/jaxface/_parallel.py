"""Running independent NumPy blocks on all CPU cores.

NumPy, SciPy's k-d trees and BLAS release the GIL inside their kernels, so independent
blocks of build-time work (RBF evaluation, closest-point queries) run in parallel on threads
without copying data. Two pools per process, each sized to the machine's cores: the *inner*
pool runs the blocks of one kernel (:func:`thread_map`); the *outer* pool runs whole
independent jobs, such as the per-scan alignment and evaluation of a batch fit and the
per-scan exact syntheses and inner solves of its outer iterations
(``thread_map(..., outer=True)``). An outer job may call :func:`thread_map` (the inner pool
never waits on the outer one, so nesting cannot deadlock; outer jobs it submits run on its
own thread, one after the other); an inner block must not submit outer jobs.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Iterable
from typing import TypeVar

__all__ = ["thread_map", "n_workers"]

T = TypeVar("T")
R = TypeVar("R")


def n_workers() -> int:
    """Number of worker threads: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


#: thread-name prefix of the outer pool's workers (:func:`_on_outer_worker`)
_OUTER_PREFIX = "jaxface-outer"


@functools.lru_cache(maxsize=2)
def _pool(outer: bool = False):
    import concurrent.futures

    name = _OUTER_PREFIX if outer else "jaxface"
    return concurrent.futures.ThreadPoolExecutor(max_workers=n_workers(), thread_name_prefix=name)


def _on_outer_worker() -> bool:
    """Whether this thread is a worker of the outer pool."""
    return threading.current_thread().name.startswith(_OUTER_PREFIX)


def thread_map(fn: Callable[[T], R], items: Iterable[T], *, outer: bool = False) -> list[R]:
    """``[fn(x) for x in items]``, on a thread pool when there are several items and cores
    (results in input order; the first exception is raised).

    Args:
        fn: the work of one item.
        items: the items.
        outer: run on the outer pool (whole jobs that may themselves call ``thread_map``).
    """
    items = list(items)
    if len(items) < 2 or n_workers() < 2 or (outer and _on_outer_worker()):
        # an outer job that submits outer jobs runs them itself: waiting on its own pool
        # could leave every worker waiting
        return [fn(x) for x in items]
    return list(_pool(bool(outer)).map(fn, items))
