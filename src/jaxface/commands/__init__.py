"""Sub-commands of the ``jaxface`` command line, one module each.

Each module defines ``register(app: typer.Typer) -> None`` and is listed in
:data:`jaxface.cli.COMMAND_MODULES`; :func:`jaxface.cli.main` imports and registers them.
The command functions are thin: they parse options, call library functions, show progress
(rich, on stderr) and let :func:`jaxface.cli.handle_errors` map errors to exit codes
(2 bad input, 3 missing file). Units: millimetres inside; input/output units are options.

* :mod:`~jaxface.commands.convert`: ``.bnt`` <-> PLY/OBJ (range-grid meshing, virtual range
  scanning), OBJ <-> PLY, unit conversion;
* :mod:`~jaxface.commands.clone`: facial motion cloning of morph targets onto a new face;
* :mod:`~jaxface.commands.bench`: run the repository's benchmarks and summarise them.
"""

from __future__ import annotations

from enum import Enum

__all__ = ["Units"]


class Units(str, Enum):
    """Length units accepted on the command line (converted to mm inside)."""

    mm = "mm"
    cm = "cm"
    m = "m"
