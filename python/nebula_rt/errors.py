"""Exceptions raised by NebulaRT."""

from __future__ import annotations

import os
import sys


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
        super().__init__(f"{_shorten(str(parameter))} = {_shorten(repr(value))}: {allowed}")


#: Characters of a parameter's name or value a message shows at most (a 300 kB value in a
#: scene file made a message of 300 kB): the first ones, then how many there are
MESSAGE_VALUE_CHARS = 200


def _shorten(text: str) -> str:
    if len(text) <= MESSAGE_VALUE_CHARS:
        return text
    return f"{text[:MESSAGE_VALUE_CHARS - 40]}... ({len(text)} characters)"


class OutputError(NebulaError, ValueError):
    """An output file cannot be written as asked (checked before any work starts).

    Parameters
    ----------
    option : str
        The option naming the file (``--output``, ``--png``).
    path : object
        The path given.
    reason : str
        Why it cannot be written.
    """

    def __init__(self, option: str, path: object, reason: str):
        self.option, self.path, self.reason = option, str(path), reason
        super().__init__(f"{option} {str(path)!r}: {reason}")


class ResourceError(SceneError, MemoryError):
    """A run would need more memory than the host or the device has (estimated before any
    allocation). A :class:`SceneError` of the parameter that drives the need.

    Parameters
    ----------
    parameter : str
        The scene parameter (or option) that drives the need, e.g. ``grid.shape``.
    value : object
        Its value.
    detail : str
        The estimate, its parts and the limit.
    """

    def __init__(self, parameter: str, value: object, detail: str):
        super().__init__(parameter, value, detail)
        self.detail = detail


class BackendUnavailableError(NebulaError, RuntimeError):
    """The requested compute backend or device cannot be used here."""


class KernelCacheError(BackendUnavailableError):
    """An OpenCL compiler cannot use its kernel cache folder (the device itself may be fine).

    Parameters
    ----------
    compiler : str
        Whose cache: ``"PoCL"`` or ``"pyopencl"``.
    folder : str
        The cache folder.
    reason : str
        Why it cannot be used (the operating system's words).
    remedy : str
        What to set instead, e.g. ``"set POCL_CACHE_DIR to a writable folder"``.
    """

    def __init__(self, compiler: str, folder: object, reason: str, remedy: str):
        self.compiler, self.folder, self.reason = compiler, str(folder), reason
        super().__init__(f"transport.backend = 'opencl': {compiler} cannot use its kernel cache folder "
                         f"{str(folder)!r} ({reason}); {remedy}")


class CancelledError(NebulaError):
    """A run was cancelled between batches by its progress callback."""


class TimeLimitError(NebulaError):
    """A run's time limit passed before any batch of packets finished."""


class AccumulatorOverflowError(NebulaError, OverflowError):
    """A 64-bit fixed-point tally would have overflowed and could not be recovered."""


def user_stacklevel() -> int:
    """The ``stacklevel`` for :func:`warnings.warn` called by the caller of this function that
    names the first frame outside the ``nebula_rt`` package: a warning then points at the
    user's line whichever of the library's paths (``trace``, a request, an observable) led to
    it, as a fixed stacklevel cannot."""
    here = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(here):
        frame, level = frame.f_back, level + 1
    return level


class NebulaWarning(UserWarning):
    """A run finished, but a result is less trustworthy than its error estimate alone says
    (e.g. packets stopped at ``transport.max_scatterings``). The VTK filters show it on the
    output window as a VTK warning."""
