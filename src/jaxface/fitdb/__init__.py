"""Fit whole databases: ``jaxface fit-db`` on Dask distributed (docs/fit-db.md).

One module per responsibility:

* :mod:`~jaxface.fitdb.discover`: the subjects and scans of a database (Bosphorus folder
  layouts, CSV manifest);
* :mod:`~jaxface.fitdb.task`: one subject's task on a worker (rig once, scans as one batch,
  the files of ``jaxface fit``);
* :mod:`~jaxface.fitdb.outputs`: the per-scan files, atomic writes, when a scan is complete;
* :mod:`~jaxface.fitdb.table`: ``results.parquet`` rebuilt from the per-scan files, and its
  summary per expression code;
* :mod:`~jaxface.fitdb.plugin`: the worker set-up (float64, compile cache, one GPU each);
* :mod:`~jaxface.fitdb.runner`: the cluster, the tasks, resume, retries, Ctrl-C.

The names below are imported lazily (``import jaxface.fitdb`` imports neither JAX nor Dask).
"""

from __future__ import annotations

import importlib

_LAZY = {
    "discover_database": "jaxface.fitdb.discover",
    "read_manifest": "jaxface.fitdb.discover",
    "SubjectJob": "jaxface.fitdb.discover",
    "ScanEntry": "jaxface.fitdb.discover",
    "FitSettings": "jaxface.fitdb.task",
    "fit_subject": "jaxface.fitdb.task",
    "ClusterSpec": "jaxface.fitdb.runner",
    "RunReport": "jaxface.fitdb.runner",
    "run_database": "jaxface.fitdb.runner",
    "read_table": "jaxface.fitdb.table",
    "summarise": "jaxface.fitdb.table",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxface.fitdb' has no attribute {name!r}")


def __dir__():
    return __all__
