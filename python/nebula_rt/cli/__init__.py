"""The ``nebula-rt`` command: :mod:`~nebula_rt.cli.commands` (render, sky, compare, devices; the
options every command shares), :mod:`~nebula_rt.cli.fit`, :mod:`~nebula_rt.cli.image`,
:mod:`~nebula_rt.cli.arguments` (the argument types the parsers share) and
:mod:`~nebula_rt.cli.failures` (exit statuses and messages, agreed by the ranks under mpiexec)."""

import os as _os
import sys as _sys

from .. import interrupts as _interrupts

# run as the command (the nebula-rt script, or python -m nebula_rt.cli, whose argv[0] is "-m"
# while its package loads): a signal while the modules below load cancels the run when it
# starts. An import from Python (a notebook, the tests) keeps its own Ctrl-C.
if _os.path.basename(_sys.argv[0] if _sys.argv else "") in ("nebula-rt", "-m"):
    _interrupts.install_early()

from .commands import build_parser, main  # noqa: E402

__all__ = ["build_parser", "main"]
