"""Exact sums of float32 arrays, the same number on the host and on the compute device.

A float32 value is its significand m (24 bits, the hidden bit included where the exponent field
e is not 0) times 2^(max(e, 1) - 150). Summing the significands of every value of one sign and
exponent field in an integer (a *bin*, 512 of them) loses nothing, in any order; adding the
bins, each shifted by its exponent, in Python's unbounded integers gives the array's sum times
2^150 exactly, and one division the correctly rounded mean. The device kernel
(``kernels/density.cl``: ``significand_sums``, through
:meth:`nebula_rt.backends.base.Backend.density_mean`) forms the same bins, so the density's mean
for the colour's auto opacity has the same bits whether the device summed it while making the
density or the host summed a density read from a file or a ``.vti`` (the Nebula Colour filter).
"""

from __future__ import annotations

import numpy as np

#: bins of the sums: 256 exponent fields for each sign (kernels/density.cl, NRT_SIGNIFICAND_BINS)
SIGNIFICAND_BINS = 512
#: consecutive values one work item of the device kernel sums (NRT_SIGNIFICAND_RUN)
SIGNIFICAND_RUN = 64
#: values per host chunk: a bin's float64 sum of at most 2^22 significands of 24 bits stays
#: below 2^53, so NumPy's weighted bincount is exact
_HOST_CHUNK = 1 << 22


def significand_sums(values) -> list[int]:
    """The 512 bins of a float32 array (any shape and memory layout), summed on the host.

    Returns
    -------
    list of int
        ``bins[256 s + e]``: the sum of the significands of the values with sign bit s and
        exponent field e.
    """
    a = np.asarray(values)
    if a.dtype != np.float32:
        raise TypeError(f"significand_sums: a float32 array, not {a.dtype}")
    bins = [0] * SIGNIFICAND_BINS
    for part in _flat_parts(a):
        u = part.view(np.uint32)
        for s in range(0, u.size, _HOST_CHUNK):
            c = u[s:s + _HOST_CHUNK]
            key = c >> np.uint32(23)
            m = (c & np.uint32(0x7FFFFF)) | ((key & np.uint32(0xFF)) != 0).astype(np.uint32) << np.uint32(23)
            sums = np.bincount(key, weights=m, minlength=SIGNIFICAND_BINS)
            for k in np.flatnonzero(sums).tolist():
                bins[k] += int(sums[k])
    return bins


def _flat_parts(a: np.ndarray):
    """``a``'s values as flat arrays without copying the whole array: itself where its memory
    is one block (C or Fortran order), else one copied slice of the first axis at a time."""
    if a.flags.c_contiguous or a.flags.f_contiguous:
        yield a.ravel(order="K")
    else:
        for sub in a:
            yield np.ravel(sub, order="K")


def exact_total(bins) -> int:
    """The sum of the values whose bins are ``bins`` (:func:`significand_sums`), times 2^150."""
    total = 0
    for k, m in enumerate(int(b) for b in bins):
        if m:
            v = m << max(k & 0xFF, 1)
            total += -v if k >> 8 else v
    return total


def exact_mean(bins, n: int) -> float:
    """The mean of ``n`` values whose bins are ``bins``, correctly rounded to float64 (Python's
    integer division rounds once); 0.0 for no values."""
    n = int(n)
    return exact_total(bins) / (n << 150) if n else 0.0


def mean_float32(values) -> float:
    """The correctly rounded mean of a float32 array, summed on the host."""
    a = np.asarray(values)
    return exact_mean(significand_sums(a), a.size)
