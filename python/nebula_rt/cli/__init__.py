"""The ``nebula-rt`` command: :mod:`~nebula_rt.cli.commands` (render, sky, compare, devices; the
options every command shares), :mod:`~nebula_rt.cli.fit` and :mod:`~nebula_rt.cli.image`."""

from .commands import build_parser, main

__all__ = ["build_parser", "main"]
