"""Exceptions raised by NebulaRT."""

from __future__ import annotations


class NebulaError(Exception):
    """Base class of every NebulaRT error."""


class SceneError(NebulaError, ValueError):
    """A scene parameter has a value outside what is allowed.

    Parameters
    ----------
    parameter : str
        Dotted name of the parameter as it appears in a scene file (``transport.photons``).
    value : object
        The offending value.
    allowed : str
        Human-readable description of the allowed values or range.
    """

    def __init__(self, parameter: str, value: object, allowed: str):
        self.parameter = parameter
        self.value = value
        self.allowed = allowed
        super().__init__(f"{parameter} = {value!r}: {allowed}")


class BackendUnavailableError(NebulaError, RuntimeError):
    """The requested compute backend or device cannot be used here."""


class CancelledError(NebulaError):
    """A run was cancelled between batches by its progress callback."""


class AccumulatorOverflowError(NebulaError, OverflowError):
    """A 64-bit fixed-point tally would have overflowed and could not be recovered."""


class NebulaWarning(UserWarning):
    """A run finished, but a result is less trustworthy than its error estimate alone says
    (e.g. packets stopped at ``transport.max_scatterings``). The VTK filters show it on the
    output window as a VTK warning."""
