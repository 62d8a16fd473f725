"""What a device and the host can hold: the checks every backend makes before its first
allocation (:func:`check_grid`), the device memory of the transport by regions
(:func:`region_bytes`) and the host's free memory. The estimates of a whole run, which plan
its launches, are :mod:`nebula_rt.transport.resources` (above the transport; this module is below it).
"""

from __future__ import annotations

import math
import os

from ..errors import ResourceError
from .regions import region_shift_for, region_state_bytes


def _gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**28 else f"{n / 2**20:.1f} MiB"


def region_bytes(backend, nvox: int, biased: bool) -> int:
    """Device bytes of the transport by regions on ``backend`` for a grid of ``nvox`` voxels
    (0 where the backend traces it without regions)."""
    tuning = getattr(backend, "transport_tuning", {}) or {}
    if not hasattr(backend, "transport_tuning") or not region_shift_for(backend, nvox, biased, tuning):
        return 0
    return region_state_bytes(nvox, tuning)


def host_available_bytes() -> int:
    """Memory the host can give a new allocation now: MemAvailable (Linux), else the physical
    memory."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 1 << 62


def check_grid(shape, backend, n_bands: int = 0) -> None:
    """Refuse a grid the device cannot hold: the density alone (``n_bands`` 0: 4 B per voxel,
    one buffer), or a transport of ``n_bands`` bands (one batch slot and the two running sums,
    8 B per cell each, and the density), and a density the host cannot hold (twice, while it is
    generated and copied)."""
    shape = [int(n) for n in shape]
    nvox = math.prod(shape)
    ncell = int(n_bands) * nvox
    biggest, need = (8 * ncell, 24 * ncell + 4 * nvox) if n_bands else (4 * nvox, 4 * nvox)
    total, max_alloc = backend.memory_limits()
    what = f"a transport of {n_bands} band(s)" if n_bands else "the density"
    if biggest > max_alloc or need > total:
        raise ResourceError("grid.shape", shape,
                            f"needs {_gib(need)} of device memory for {what} (largest buffer "
                            f"{_gib(biggest)}); the device ({backend.device_name}) has {_gib(total)}, "
                            f"at most {_gib(max_alloc)} per buffer")
    avail = host_available_bytes()
    if 8 * nvox > avail:
        raise ResourceError("grid.shape", shape, f"the density needs about {_gib(8 * nvox)} of host "
                                                 f"memory; {_gib(avail)} is available")
