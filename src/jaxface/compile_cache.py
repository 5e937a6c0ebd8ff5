"""The persistent XLA compilation cache of the command line.

Every ``jaxface`` process compiles the rig's synthesis, the inner least-squares solve and
the reverse pass of the gradient correction before it fits anything: about 28 s of a
single-scan ``jaxface fit`` on the 2-core CPU. JAX can keep compiled programs on disk
(``jax_compilation_cache_dir``); a later process that compiles the same program (the same
subject's rig, the same solver shapes) loads it instead. Programs with a host callback are
never written (JAX's rule), so the fit traces the rig without its run-time input check
(:func:`jaxface.validate.traced_checks`). Measurements: ``docs/benchmarks.md``, "Fit speed".

The command line turns the cache on by default, in :func:`default_cache_dir`;
``--compile-cache DIR`` or ``JAXFACE_COMPILE_CACHE=DIR`` moves it and ``off`` turns it off.
The library itself never turns it on: call :func:`enable_compile_cache` for that.
Only programs that took at least JAX's ``jax_persistent_cache_min_compile_time_secs``
(1 s by default) to compile are written. Delete the folder to clear it.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

#: values of ``--compile-cache`` / ``JAXFACE_COMPILE_CACHE`` that turn the cache off
OFF = ("off", "none", "no", "false", "0", "")


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/jaxface/xla``, or ``~/.cache/jaxface/xla``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxface" / "xla"


def enable_compile_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn JAX's persistent compilation cache on in ``path`` (default
    :func:`default_cache_dir`); ``"off"`` (or ``none``/``no``/``false``/``0``/empty) leaves it
    off. Returns the folder, or None when the cache stays off.

    A folder that cannot be created or written only gives a warning: the cache is an
    optimisation, and the command goes on without it.
    """
    if path is not None and str(path).strip().lower() in OFF:
        return None
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK):
            raise PermissionError(f"{folder} is not writable")
    except OSError as e:
        warnings.warn(
            f"the compilation cache stays off: {e}. Give a writable folder with "
            f"--compile-cache DIR (or JAXFACE_COMPILE_CACHE=DIR), or 'off'.",
            stacklevel=2,
        )
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(folder))
    return folder
