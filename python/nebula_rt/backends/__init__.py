"""Compute backends and their selection.

``get_backend("auto")`` prefers CUDA where a CUDA backend is available, then an
OpenCL GPU, then OpenCL on the CPU (PoCL). Backends are cached per (name, device),
so repeated runs reuse compiled programs.
"""

from __future__ import annotations

import functools

from ..errors import BackendUnavailableError, SceneError
from .base import Backend, TransportSession, TransportSetup

BACKENDS = ("auto", "opencl", "cuda")


@functools.lru_cache(maxsize=8)
def get_backend(name: str = "auto", device: str = "") -> Backend:
    """Return a (cached) backend.

    Parameters
    ----------
    name : {"auto", "opencl", "cuda"}
        Backend kind (``transport.backend``).
    device : str
        Device selector (``transport.device``); see :func:`nebula_rt.backends.opencl.select_device`.
    """
    if name not in BACKENDS:
        raise SceneError("transport.backend", name, "one of: " + ", ".join(repr(b) for b in BACKENDS))
    if name == "cuda":
        raise BackendUnavailableError(
            "transport.backend = 'cuda': the CUDA backend is not available in this build; "
            "use 'opencl' (NVIDIA GPUs are reached through their OpenCL driver) or 'auto'"
        )
    from .opencl import OpenCLBackend

    return OpenCLBackend(device)


__all__ = ["BACKENDS", "Backend", "TransportSession", "TransportSetup", "get_backend"]
