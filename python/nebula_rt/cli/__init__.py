"""The ``nebula-rt`` command: :mod:`~nebula_rt.cli.commands` (render, sky, compare, devices; the
options every command shares), :mod:`~nebula_rt.cli.fit`, :mod:`~nebula_rt.cli.image`,
:mod:`~nebula_rt.cli.arguments` (the argument types the parsers share) and
:mod:`~nebula_rt.cli.failures` (exit statuses and messages, agreed by the ranks under mpiexec)."""

from .commands import build_parser, main

__all__ = ["build_parser", "main"]
