"""The transport's device state, written once over a backend's device primitives.

A :class:`DeviceTransport` holds one run's arrays on the device: the density, the band and
star tables, the run's constants as one ``nrt_trace_params`` struct
(:mod:`nebula_rt.kernel_params`), the batch slots the kernel accumulates into, and the
per-cell statistics of the batch totals the slots are folded into. It talks to the device
only through the backend's primitives (``to_device``, ``device_zeros``, ``fill_zero``,
``to_host``, ``launch``, ``launch_trace``), so the OpenCL and CUDA paths share every line of
it. A cell is one voxel of one band.

Memory (bytes per voxel, n_b bands): density 4, statistics 12 n_b (float64 sum, float32
centred sum of squares), batch slots 8 per band and slot. :meth:`Backend.launch_plan` picks
how many bands and batches one launch's slots hold, within ``slot_memory_budget`` (or one band
of one batch, whatever the grid), so the transport needs at most 4 + 8 + 12 n_b bytes per
voxel plus the budget: within twice the minimum (density and one 64-bit accumulator per band).
"""

from __future__ import annotations

import numpy as np

from .. import kernel_params
from .base import TransportSession, TransportSetup, transport_defines

#: centred sums of squares are stored as float32 x 2^-64 (kernels/transport.cl)
M2_SCALE = 2.0**64


class DeviceTransport(TransportSession):
    """Device state of one transport run (see the module docstring).

    Parameters
    ----------
    backend : Backend
    setup : TransportSetup
    slots : int
        Batches one launch traces (each into its own slot).
    bands_per_launch : int
        Bands one launch traces (the slots hold this many bands); the bands are traced in
        ``ceil(n_bands / bands_per_launch)`` groups.
    """

    def __init__(self, backend, setup: TransportSetup, slots: int, bands_per_launch: int = 0):
        be = self.backend = backend
        self.setup = setup
        self.shape = tuple(int(n) for n in setup.density.shape)
        nb = setup.n_bands
        self.nvox = int(np.prod(self.shape))
        self.ncell = nb * self.nvox
        self.slots = int(slots)
        self.bands_per_launch = int(bands_per_launch) if bands_per_launch else nb
        self.slot_cells = self.bands_per_launch * self.nvox
        self.words = setup.cell_words  # 64-bit words per cell (2: 128-bit, weighted packets)
        self.tally_words = setup.tally_words
        resident = be.resident_density(setup.density)
        self.d_density = (resident if resident is not None else
                          be.to_device(np.ravel(np.asarray(setup.density, np.float32), order="F")))
        optics = np.zeros((nb, 4), np.float32)
        optics[:, 0], optics[:, 1], optics[:, 2] = setup.sigma_scale, setup.albedo, setup.g
        self.d_optics = be.to_device(optics)
        stars4 = np.zeros((max(1, setup.stars.shape[0]), 4), np.float32)
        stars4[:setup.stars.shape[0], :3] = setup.stars
        self.d_stars = be.to_device(stars4)
        self.d_cdf = be.to_device(np.ascontiguousarray(setup.star_cdf, np.float32))
        nx, ny, nz = self.shape
        self.params = kernel_params.pack(
            seed=setup.seed, batch_base=0, batch_extra=0, nx=nx, ny=ny, nz=nz, n_bands=nb,
            n_stars=setup.stars.shape[0], max_scatterings=setup.max_scatterings,
            track_scale=setup.track_scale, peel_scale=setup.peel_scale, collision_scale=setup.collision_scale,
            peel=np.zeros(15, np.float32) if setup.peel is None else np.asarray(setup.peel, np.float32))
        self.d_params = be.to_device(self.params.view(np.uint8))
        self.d_acc = be.device_zeros(self.slot_cells * self.slots * self.words, np.uint64)
        self.d_sum1 = be.device_zeros(self.ncell, np.float64)
        self.d_m2 = be.device_zeros(self.ncell, np.float32)
        self.d_tallies = be.device_zeros(self.slots * self.bands_per_launch * self.tally_words, np.uint64)
        self.d_overflow = be.device_zeros(self.slots, np.uint32)
        self.d_seen = be.device_zeros(1, np.uint32)
        self.pixels = setup.peel_pixels
        self.d_image = be.device_zeros(max(1, self.slots * self.bands_per_launch * self.pixels * self.words),
                                       np.uint64)
        tuning = dict(be.transport_tuning)
        if "NRT_SORTED" not in tuning and self.nvox >= getattr(be, "sort_min_voxels", 0) > 0:
            tuning["NRT_SORTED"] = 1  # large grids: a warp's first flights side by side
        self.defines = transport_defines(setup, tuning)
        self.sorted = bool(self.defines.get("NRT_SORTED"))
        self.d_keys = be.device_zeros(1, np.uint64)  # NRT_SORTED: the launch's sorted packets
        self._plan = (0, 0)
        self._h_stage = None  # several ranks: the host buffer of reduce_group
        # build the kernels of this option set now (setup time): compiled inside the first
        # launch, they were counted as tracing (up to 1 s per option set on CUDA)
        for name in ("trace_photons", "fold_batches") + (("emission_keys",) if self.sorted else ()):
            be.kernel(be.transport_program, name, self.defines)

    def run_group(self, photon_start, count, batch_base, batch_extra, first_batch, n_slots, fresh=True,
                  bands=None):
        be = self.backend
        band0, n_lb = bands if bands is not None else (0, self.setup.n_bands)
        if n_lb > self.bands_per_launch:
            raise ValueError(f"{n_lb} bands in one launch; the slots hold {self.bands_per_launch}")
        if (batch_base, batch_extra) != self._plan:  # the plan is a run constant but for re-traces
            self.params["batch_base"], self.params["batch_extra"] = batch_base, batch_extra
            self.d_params = be.to_device(self.params.view(np.uint8))
            self._plan = (batch_base, batch_extra)
        if fresh:
            be.fill_zero(self.d_tallies)
            be.fill_zero(self.d_overflow)
        items = int(count) * n_lb
        if self.sorted:
            if self.d_keys.size < items:
                self.d_keys = None
                self.d_keys = be.device_zeros(items, np.uint64)
            be.launch(be.transport_program, "emission_keys", items, self.d_params, self.d_cdf,
                      np.uint64(photon_start), np.uint64(count), np.uint64(first_batch),
                      np.int32(band0), np.int32(n_lb), np.int32(self.slots), self.d_keys,
                      defines=self.defines)
            self.d_keys = be.sort_u64(self.d_keys, items)
        be.launch_trace(
            be.transport_program, "trace_photons", int(count) * n_lb,
            self.d_params, self.d_density, self.d_optics, self.d_stars, self.d_cdf,
            np.uint64(photon_start), np.uint64(count), np.uint64(first_batch),
            np.int32(band0), np.int32(n_lb),
            self.d_acc, self.d_tallies, self.d_overflow, self.d_image, self.d_keys, defines=self.defines)
        tallies = be.to_host(self.d_tallies).reshape(self.slots, self.bands_per_launch,
                                                     self.tally_words)  # synchronises
        overflow = be.to_host(self.d_overflow)
        return tallies[:n_slots, :n_lb].copy(), overflow[:n_slots].astype(bool)

    def empty_group(self, n_slots, bands=None):
        """Clear the group's tallies and flags without tracing (a rank with no packets of a
        group); returns them as :meth:`run_group` would."""
        n_lb = (bands or (0, self.setup.n_bands))[1]
        self.backend.fill_zero(self.d_tallies)
        self.backend.fill_zero(self.d_overflow)
        return np.zeros((n_slots, n_lb, self.tally_words), np.uint64), np.zeros(n_slots, bool)

    def counts_of(self, tallies) -> np.ndarray:
        """The counts of raw tally words (..., tally_words) as exact Python integers (object
        array (..., 4), or (..., 5) 128-bit weight sums with the signed biasing last)."""
        t = np.asarray(tallies, np.uint64)
        if self.tally_words == 4:
            return t.astype(object)
        lo, hi = t[..., 0::2].astype(object), t[..., 1::2].astype(object)
        v = lo + (hi << 64)
        v[..., 4] = np.where(v[..., 4] >= 1 << 127, v[..., 4] - (1 << 128), v[..., 4])
        return v

    def reduce_group(self, comm, n_slots, bands, tallies, overflow):
        """Add the ranks' slots, images, tallies and flags of a group and put the sums back on
        the device, so every rank folds the one-rank run's batch totals.

        The sums are taken in place (:func:`nebula_rt.parallel.sum_checked`): in the slots'
        own memory where the device's memory is the host's (OpenCL on a CPU,
        ``Backend.map_host``: no copy at all), else in one host buffer kept for the run (no
        allocation, and no page faults, per group) that holds everything; the image, tallies
        and flags then travel in it too. Checked cells (the slots with checked adds, the image
        always) are summed so that none can wrap, and a slot with a summed cell at or past the
        headroom limit is flagged, as one rank's checked adds would have flagged it. With
        unchecked adds the batch cannot wrap at all (the bound covers all its packets) and the
        fold checks the limit. Returns (tallies, overflow)."""
        be = self.backend
        n_lb = bands[1]
        cells = n_slots * n_lb * self.nvox * self.words
        mapped = be.map_host(self.d_acc, cells)
        if mapped is None:
            return self._reduce(comm, n_slots, n_lb, tallies, overflow, None)
        with mapped as acc:
            return self._reduce(comm, n_slots, n_lb, tallies, overflow, acc)

    def _reduce(self, comm, n_slots, n_lb, tallies, overflow, acc):
        """:meth:`reduce_group` with the group's slots mapped as ``acc`` (or None: copied)."""
        from ..parallel import sum_checked, sum_wide

        be = self.backend
        cells = 0 if acc is not None else n_slots * n_lb * self.nvox * self.words
        pix, nt = n_slots * n_lb * self.pixels * self.words, tallies.size
        need = cells + pix + nt + n_slots
        if self._h_stage is None or self._h_stage.size < need:
            most = self.slots * self.bands_per_launch
            self._h_stage = be.host_empty((0 if acc is not None else most * self.nvox * self.words)
                                          + most * (self.pixels * self.words + self.tally_words)
                                          + self.slots, np.uint64)
        buf = self._h_stage[:need]
        if acc is None:
            acc = buf[:cells]
            be.to_host(self.d_acc[:cells], out=acc)  # the group's slots only
        if pix:
            be.to_host(self.d_image[:pix], out=buf[cells:cells + pix])
        buf[cells + pix:cells + pix + nt] = tallies.reshape(-1)
        buf[cells + pix + nt:] = overflow
        if self.words == 2:  # 128-bit cells, images and tallies; the flags as 64-bit counts
            past = np.zeros(n_slots, bool)
            for part, checked in ((acc, True), (buf[cells:cells + pix], True),
                                  (buf[cells + pix:cells + pix + nt], False)):
                if part.size:
                    top = sum_wide(comm, part)
                    if checked:
                        past |= (top.reshape(n_slots, -1) >= np.uint64(1 << int(self.setup.acc_limit_bits))).any(1)
            comm.sum_u64(buf[cells + pix + nt:])
        else:
            slots_checked = [] if self.setup.unchecked_adds else [(0, acc.size)]
            if cells:  # one buffer
                parts = [(buf, slots_checked + [(cells, cells + pix)])]
            else:
                parts = [(acc, slots_checked), (buf, [(0, pix)])]
            past = sum_checked(comm, parts, n_slots, int(self.setup.acc_limit_bits))
        flags = (buf[cells + pix + nt:] > 0) | past
        if cells:
            be.upload(self.d_acc, acc)
        if pix:
            be.upload(self.d_image, buf[cells:cells + pix])
        be.upload(self.d_overflow, flags.astype(np.uint32))
        return buf[cells + pix:cells + pix + nt].reshape(tallies.shape).copy(), flags

    def fold(self, n_slots, bands=None, folded_before: int = 0):
        band0, n_lb = bands if bands is not None else (0, self.setup.n_bands)
        n = n_lb * self.nvox
        self.backend.launch(self.backend.transport_program, "fold_batches", n,
                            self.d_acc, self.d_sum1, self.d_m2, self.d_overflow, np.int32(n_slots),
                            np.uint64(n), np.uint64(band0 * self.nvox), np.int32(folded_before),
                            self.d_seen, defines=self.defines)

    def overflow_seen(self):
        return bool(self.backend.to_host(self.d_seen)[0])

    def sums_on_device(self):
        """(sum, centred sum of squares) as (n_bands, nx, ny, nz) float64 arrays of the
        backend's array module (CuPy views and one float64 copy of the squares on CUDA)."""
        be = self.backend
        nb = self.setup.n_bands
        shape = (nb,) + self.shape[::-1]
        if be.array_module is np:
            return self.sums()
        m2 = self.d_m2.astype(np.float64) * M2_SCALE
        return tuple(a.reshape(shape).transpose(0, 3, 2, 1) for a in (self.d_sum1, m2))

    def device_arrays(self):
        """(sum, centred squares, density) as flat device arrays, left in place."""
        return self.d_sum1, self.d_m2, self.d_density

    def sums(self):
        be = self.backend
        shape = (self.setup.n_bands,) + self.shape[::-1]
        s1 = be.to_host(self.d_sum1).reshape(shape).transpose(0, 3, 2, 1)
        m2 = be.to_host(self.d_m2).astype(np.float64).reshape(shape).transpose(0, 3, 2, 1) * M2_SCALE
        return s1, m2

    def take_images(self, n_slots, bands=None):
        s = self.setup
        band0, n_lb = bands if bands is not None else (0, s.n_bands)
        if s.peel is None:
            return np.zeros((n_slots, n_lb, 0, 0), np.uint64)
        w, h = int(s.peel[13]), int(s.peel[14])
        out = self.backend.to_host(self.d_image).reshape(self.slots, self.bands_per_launch, w, h, self.words)
        self.backend.fill_zero(self.d_image)
        out = out[:n_slots, :n_lb]
        if self.words == 1:
            return out[..., 0]
        # 128-bit pixels as float64 (the image statistics are float64 anyway)
        return out[..., 1].astype(np.float64) * 2.0**64 + out[..., 0].astype(np.float64)

    def release_sums(self):
        out = (self.d_sum1, self.d_m2, self.d_density)
        self.d_sum1 = self.d_m2 = self.d_density = None
        self.d_acc = self.d_image = self.d_keys = None  # the slots' memory goes to the finishing
        self._h_stage = None
        return out

    def device_bytes(self) -> int:
        """Device memory this run holds: the batch slots (8 B per slot cell), the statistics
        (12 B per cell), the density (4 B per voxel), the per-slot tallies and the images."""
        return (8 * self.words * self.slot_cells * self.slots + 12 * self.ncell + 4 * self.nvox
                + 8 * self.tally_words * self.bands_per_launch * self.slots + 4 * self.slots
                + 8 * self.words * self.slots * self.bands_per_launch * self.pixels)

    def close(self):
        for name in ("d_acc", "d_sum1", "d_m2", "d_density", "d_image", "d_keys", "_h_stage"):
            setattr(self, name, None)
