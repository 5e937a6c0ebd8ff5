"""Running independent NumPy blocks on all CPU cores.

NumPy, SciPy's k-d trees and BLAS release the GIL inside their kernels, so independent
blocks of build-time work (RBF evaluation, closest-point queries) run in parallel on threads
without copying data. One pool per process, sized to the machine's cores.
"""

from __future__ import annotations

import functools
import os
from typing import Callable, Iterable, TypeVar

__all__ = ["thread_map", "n_workers"]

T = TypeVar("T")
R = TypeVar("R")


def n_workers() -> int:
    """Number of worker threads: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@functools.lru_cache(maxsize=1)
def _pool():
    import concurrent.futures

    return concurrent.futures.ThreadPoolExecutor(max_workers=n_workers(), thread_name_prefix="jaxface")


def thread_map(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, on the thread pool when there are several items and cores
    (results in input order; the first exception is raised)."""
    items = list(items)
    if len(items) < 2 or n_workers() < 2:
        return [fn(x) for x in items]
    return list(_pool().map(fn, items))
