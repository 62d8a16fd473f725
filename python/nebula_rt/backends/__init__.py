"""Compute backends and their selection.

``get_backend("auto")`` prefers CUDA where CuPy sees a GPU, then an OpenCL GPU, then
OpenCL on the CPU (PoCL). Backends are cached per (name, device),
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
        from .cuda import CUDABackend

        return CUDABackend(device)
    if name == "auto":
        from .cuda import CUDABackend, cuda_available

        if cuda_available():
            try:  # a device selector naming an OpenCL device falls through to OpenCL
                return CUDABackend(device)
            except BackendUnavailableError:
                pass
    from .opencl import OpenCLBackend

    return OpenCLBackend(device)


__all__ = ["BACKENDS", "Backend", "TransportSession", "TransportSetup", "get_backend"]
