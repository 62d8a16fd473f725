"""NumPy or CuPy: the array module an array belongs to.

The post-processing stages (normalisation, error estimate, filtering, colour) are written
once against this namespace: on the CUDA backend they run on the GPU with CuPy and only the
final arrays are copied back; elsewhere they run with NumPy.
"""

from __future__ import annotations

import numpy as np


def array_module(*arrays):
    """``cupy`` if any argument is a CuPy array, else ``numpy``."""
    for a in arrays:
        if type(a).__module__.startswith("cupy"):
            import cupy

            return cupy
    return np


def to_numpy(a):
    """A NumPy array (copies a CuPy array to the host; NumPy arrays pass through)."""
    if type(a).__module__.startswith("cupy"):
        return a.get()
    return np.asarray(a)


def fftconvolve_same(xp, a, kernel):
    """``scipy.signal.fftconvolve(a, kernel, mode="same")`` on the array's own device."""
    if xp is np:
        from scipy import signal

        return signal.fftconvolve(a, kernel, mode="same")
    from cupyx.scipy import signal

    return signal.fftconvolve(a, xp.asarray(kernel), mode="same")
