"""Memory a run will need, estimated from the scene before anything is allocated.

A grid of 2000^3 voxels, a collision filter wider than the box or a sky image of 10^5 pixels
a side must be refused at once, with the estimate and the limit, not after a minute of work
or deep inside the OpenCL driver. The estimate follows the allocations of the stages:

device (the larger of the tracing and the finishing)
    the density (4 B per voxel), the batch slots (8 B per cell each, a cell being one voxel of
    one band; the slot count is the launch plan's), the two running sums (16 B per cell), the
    peel-off images (8 B per pixel, band and slot), the finishing outputs (float32 J, error and
    emissivity, 12 B per cell; the exposure key and rgba, 8 B per voxel) and, for the
    collision filter on the device, its FFT work arrays;
host
    the density, the output arrays and a second copy of them while the ``.vti`` is written
    (VTK's point order), the host sums of error-targeted runs and of the collision filter on
    the host, and its FFT work arrays.

The FFT work of the collision filter is taken as 20 complex128 half-spectra of the padded box
(8 B per point each): the 14 cached spectra of the kernel terms of the face fit
(``nebula_rt.transport.filtering``), the field's and the variance's transforms, their products and the
inverse transforms, per band in turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..backends import binned
from ..backends.capacity import _gib, check_grid, host_available_bytes, region_bytes  # noqa: F401  (public here too)
from ..errors import ResourceError
from .filtering import kernel_half_widths
from .plan import light_while_folding, plan_launches, spare_slot_bytes

#: bytes per FFT point of the collision filter's convolutions (20 complex128 half-spectra)
FFT_BYTES_PER_POINT = 20 * 8


@dataclass
class Estimate:
    """Estimated peak memory of a run, in bytes, with its main parts."""

    device: dict = field(default_factory=dict)
    host: dict = field(default_factory=dict)
    largest_buffer: int = 0

    @property
    def device_bytes(self) -> int:
        return int(sum(self.device.values()))

    @property
    def host_bytes(self) -> int:
        return int(sum(self.host.values()))


def _parts(d: dict) -> str:
    return ", ".join(f"{k} {_gib(v)}" for k, v in sorted(d.items(), key=lambda kv: -kv[1]) if v)


def filter_fft_points(shape, radius: float) -> int:
    """Points of the padded FFT of the collision filter's convolution on ``shape``."""

    half = kernel_half_widths(shape, radius)
    return int(math.prod(n + 2 * h for n, h in zip(shape, half)))


def estimate(scene, backend, peel_pixels: int = 0) -> Estimate:
    """The memory a run of ``scene`` on ``backend`` will need (see the module notes).

    Parameters
    ----------
    peel_pixels : int
        Pixels of a peel-off image traced with it (0: none).
    """

    t = scene.transport
    shape = tuple(int(n) for n in scene.grid.shape)
    nvox = math.prod(shape)
    nb = len(scene.bands.resolve())
    ncell = nb * nvox
    photons, target = t.effective()
    cell = 16 if t.method == "biased" else 8  # 128-bit cells for weighted packets
    launches = plan_launches(photons, t.batch_size, target > 0, shape, nb, backend, cell,
                             error_estimate=t.error_estimate, peel=object() if peel_pixels else None,
                             time_limit=t.time_limit, max_scatterings=t.max_scatterings, estimator=t.estimator)
    packets = launches.packet_scales is not None
    per_launch, slots = launches.bands_per_launch, launches.slots
    slot_cells = per_launch * nvox
    colour = nb > 1
    collision = t.estimator == "collision-filter"
    fft = FFT_BYTES_PER_POINT * filter_fft_points(shape, t.filter_radius) if collision else 0
    on_device_fft = collision and getattr(backend, "name", "") == "cuda"
    if collision and getattr(backend, "name", "") == "opencl":
        from . import filtering_opencl

        on_device_fft = filtering_opencl.available()

    est = Estimate()
    # the device peak: the transport (slots, sums, images), or later the sums it hands over with
    # the finishing's outputs or the filter's work arrays, whichever is larger
    tracing = {
        "density": 4 * nvox,
        "batch slots": cell * slot_cells * slots,
        # (by packets: the squares' slot, which becomes them in place)
        "running sums": 8 * ncell if packets else 12 * ncell,
        "peel-off images": cell * slots * per_launch * int(peel_pixels),
        "tallies and parameters": (84 if cell == 16 else 36) * per_launch * slots + 4096,
        # transport by regions: the stopped packets' states and keys, per-bin counts (binned
        # deposits, a tuning: none, but their records, counts and offsets)
        "region passes": 0 if binned.enabled(backend) else region_bytes(backend, nvox, t.method == "biased"),
        "binned deposits": binned.estimated_bytes(shape, launches.batches.base + 1, photons,
                                                  binned.majorant_of(backend))
        if binned.enabled(backend) else 0,
        # error-targeted runs: a brightness key per voxel and partial sums per 256 voxels
        "error checks": (4 * nvox + 16 * (nvox // 256 + 1)) if target > 0 else 0,
        # J and the emissivity made as the last fold ends (the error goes over
        # the squares)
        "light made while folding": 8 * ncell if light_while_folding(
            t.estimator, ncell, spare_slot_bytes(backend, nvox, launches, cell), packets=packets,
            peel=bool(peel_pixels), targeted=target > 0) else 0,
    }
    # the finishing (postprocess.finish, release=True): first the sums and J, then the sums'
    # float64 half gone and the emissivity, key and rgba made (J and the emissivity made while
    # the transport folded are in its part)
    finishing = {
        "density": 4 * nvox,
        "running sums": 16 * ncell if packets else 12 * ncell,
        "outputs": 4 * ncell,
        "filter FFT": fft if on_device_fft else 0,
        "parameters": 64 * nb + 4096,
    }
    outputs_stage = {
        "density": 4 * nvox,
        "outputs": 12 * ncell + (8 * nvox if colour else 0),
        "parameters": 64 * nb + 4096,
    }
    if collision:  # the filter's float64 J and error in the device layout
        finishing["outputs"] += 16 * ncell
    est.device = max(tracing, finishing, outputs_stage, key=lambda d: sum(d.values()))
    outputs = 4 * nvox + 12 * ncell + (4 * nvox if colour else 0)
    est.host = {
        "density": 4 * nvox,
        "outputs": outputs,
        "filter": (16 * ncell + 16 * nvox + (0 if on_device_fft else fft)) if collision else 0,
    }
    est.largest_buffer = max(8 * slot_cells * slots, 8 * slots * per_launch * int(peel_pixels), 8 * ncell)
    return est


def _driver(est: Estimate, peel_option: str, peel_value, scene):
    """The parameter that drives the largest part of the estimate, and its value."""
    parts = {**{f"d:{k}": v for k, v in est.device.items()}, **{f"h:{k}": v for k, v in est.host.items()}}
    top = max(parts, key=parts.get).split(":", 1)[1]
    if top == "peel-off images":
        return peel_option, peel_value
    if top in ("filter FFT", "filter"):
        return "transport.filter_radius", scene.transport.filter_radius
    return "grid.shape", list(scene.grid.shape)


def check(scene, backend, peel_pixels: int = 0, peel_option: str = "--size", peel_value=None) -> Estimate:
    """Estimate the run's memory and refuse it if the device or the host cannot hold it.

    Raises
    ------
    ResourceError
        Naming the parameter that drives the need (``grid.shape``, ``transport.filter_radius``
        or the sky image size), with the estimate, its parts and the limit.
    """
    est = estimate(scene, backend, peel_pixels)
    total, max_alloc = backend.memory_limits()
    param, value = _driver(est, peel_option, peel_value, scene)
    where = f"the device ({backend.device_name})"
    if est.device_bytes > total:
        raise ResourceError(param, value, f"needs about {_gib(est.device_bytes)} of device memory "
                                          f"({_parts(est.device)}); {where} has {_gib(total)}")
    if est.largest_buffer > max_alloc:
        raise ResourceError(param, value, f"needs a single device buffer of {_gib(est.largest_buffer)}; "
                                          f"{where} allocates at most {_gib(max_alloc)} at once")
    avail = host_available_bytes()
    if est.host_bytes > avail:
        raise ResourceError(param, value, f"needs about {_gib(est.host_bytes)} of host memory "
                                          f"({_parts(est.host)}); {_gib(avail)} is available")
    return est


