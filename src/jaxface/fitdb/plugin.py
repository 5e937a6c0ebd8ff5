"""The Dask worker set-up of ``jaxface fit-db``: JAX in float64, the XLA compile cache, and
one GPU per worker.

:class:`JaxWorkerSetup` runs on every worker when the client registers it and on every
worker that joins or is restarted later, before the worker runs a task. The module imports
JAX but never starts a JAX backend, so ``CUDA_VISIBLE_DEVICES`` set here still decides which
GPU the worker's JAX sees: worker ``i`` (LocalCluster names its workers ``0, 1, ...``) gets
``gpus[i % len(gpus)]``; with ``gpus`` empty nothing is set (CPU, or the cluster's own
placement).
"""

from __future__ import annotations

import os
import zlib

import jax
from distributed.diagnostics.plugin import WorkerPlugin

from ..compile_cache import enable_compile_cache

__all__ = ["JaxWorkerSetup"]


class JaxWorkerSetup(WorkerPlugin):
    """Worker plugin: ``jax_enable_x64``, the compile cache folder (``"off"`` or None: off;
    see :func:`jaxface.compile_cache.enable_compile_cache`), and the worker's GPU.

    Arguments:
        compile_cache: the folder, ``"off"``, or ``"default"`` for
            :func:`~jaxface.compile_cache.default_cache_dir`.
        gpus: device ids (``CUDA_VISIBLE_DEVICES`` entries) handed out round-robin by worker
            index; empty: leave the device visibility alone.
    """

    name = "jaxface-fitdb-setup"

    def __init__(self, compile_cache: str | None = "off", gpus: tuple[str, ...] = ()):
        self.compile_cache = compile_cache
        self.gpus = tuple(gpus)

    def setup(self, worker) -> None:
        if self.gpus:
            try:
                index = int(worker.name)
            except (TypeError, ValueError):
                index = zlib.crc32(str(worker.name).encode())
            os.environ["CUDA_VISIBLE_DEVICES"] = self.gpus[index % len(self.gpus)]
        jax.config.update("jax_enable_x64", True)
        if self.compile_cache == "default":
            enable_compile_cache(None)
        elif self.compile_cache is not None:
            enable_compile_cache(self.compile_cache)
