"""The transport's device state, written once over a backend's device primitives.

A :class:`DeviceTransport` holds one run's arrays on the device: the density, the band and
star tables, the run's constants as one ``nrt_trace_params`` struct
(:mod:`nebula_rt.backends.kernel_params`), the batch slots the kernel accumulates into, and the
per-cell statistics of the batch totals the slots are folded into. It talks to the device
only through the backend's primitives (``to_device``, ``device_zeros``, ``fill_zero``,
``to_host``, ``launch``, ``launch_trace``), so the OpenCL and CUDA paths share every line of
it. A cell is one voxel of one band.

Memory (bytes per voxel, n_b bands): density 4, statistics 12 n_b (float64 sum, float32
centred sum of squares), batch slots 8 per band and slot. :meth:`Backend.launch_plan` picks
how many bands and batches one launch's slots hold, within ``slot_memory_budget`` (or one band
of one batch, whatever the grid), so the transport needs at most 4 + 8 + 12 n_b bytes per
voxel plus the budget: within twice the minimum (density and one 64-bit accumulator per band).
The error estimate by packets (``setup.packet_sq``) holds one slot of every band and one of
their squares, 16 n_b, and turns them into the statistics in place (:meth:`_finish_packets`):
4 + 16 n_b bytes per voxel throughout.
"""

from __future__ import annotations

import time

import numpy as np

from . import kernel_params
from ..array_api import to_numpy
from .regions import (NO_REGIONS, MAX_REGION_PASSES, LOCAL_SORT_BINS, EMISSION_MAX_BINS, packet_state_bytes,
                      region_shift_of, region_state_bytes)
from .binned import TUNING as binned_tuning, BinnedDeposits
from .transport_setup import TransportSession, TransportSetup, transport_defines

#: centred sums of squares are stored as float32 x 2^-64 (kernels/transport.cl)
M2_SCALE = 2.0**64

def tail_tables(window_shape, grid_shape, edges) -> np.ndarray:
    """What the kernel reads after the depth map to class J's deposits (kernels/transport.cl,
    nrt_jtail; part of the device's layout, so it lives beside the session): per axis the map cell of each voxel layer, the one holding the layer's centre
    (none for a tree, whose leaves the kernel classes by their centres: ``grid_shape`` (0, 0, 0)),
    premultiplied by the map's strides (x fastest), then each band's class edges (float32; the
    cells are integers below 2^24)."""
    w = [int(n) for n in window_shape]
    strides = (1, w[0], w[0] * w[1])
    parts = []
    for n, m, stride in zip(grid_shape, w, strides):
        i = np.arange(int(n), dtype=np.int64)
        parts.append(((2 * i + 1) * m // (2 * int(n))) * stride)
    parts.append(np.asarray(edges, np.float64).ravel())
    return np.concatenate(parts).astype(np.float32)


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

    # One method though long (about 80 lines): every device buffer of a run is allocated here,
    # in the order the kernel's arguments list them, so one place says what a run holds.
    def __init__(self, backend, setup: TransportSetup, slots: int, bands_per_launch: int = 0):
        be = self.backend = backend
        self.setup = setup
        self.shape = tuple(int(n) for n in setup.density.shape)
        nb = setup.n_bands
        self.nvox = int(np.prod(self.shape))
        self.ncell = nb * self.nvox
        self.slots = int(slots)
        self.bands_per_launch = int(bands_per_launch) if bands_per_launch else nb
        # no light field (a peel-off image alone): the kernel deposits nothing, so no slots
        self.slot_cells = self.bands_per_launch * self.nvox if setup.light_field else 0
        self.words = setup.cell_words  # 64-bit words per cell (2: 128-bit, weighted packets)
        self.tally_words = setup.tally_words
        if setup.tree is not None:  # the leaves' densities, then the nodes (kernels/tree.cl)
            self.d_density = be.to_device(setup.tree_buffer)
        elif setup.peel_columns is not None:  # the densities, then their columns (NRT_PEEL_AXIS)
            self.d_density = be.density_with_columns(setup.density, setup.peel_columns)
        else:
            resident = be.resident_density(setup.density)
            self.d_density = (resident if resident is not None else
                              be.to_device(np.ravel(np.asarray(setup.density, np.float32), order="F")))
        # per band: extinction scale, albedo, g, windows' rate; then per band the polarization's
        # parameters (kernels/transport.cl reads them at optics + 4 n_bands + 4 band), then
        # Mie's tables
        optics = np.zeros((nb, 4), np.float32)
        optics[:, 0], optics[:, 1], optics[:, 2] = setup.sigma_scale, setup.albedo, setup.g
        if setup.window_rate is not None:
            optics[:, 3] = setup.window_rate
        polar = np.zeros(4 * nb, np.float32) if setup.polar_params is None else setup.polar_params
        self.d_optics = be.to_device(np.concatenate([optics.reshape(-1), np.asarray(polar, np.float32)]))
        # weighted packets read the windows' depth map (none given: depth 0, windows at W0)
        # (and, J's heavy-tail classes, the kernel's tables of them after it: nebula_rt.transport.tails)
        self.d_window = be.to_device(np.zeros(1, np.float32) if setup.window is None else np.concatenate(
            [np.ravel(np.asarray(setup.window, np.float32), order="F"),
             np.zeros(0, np.float32) if not setup.tail_classes else
             tail_tables(np.shape(setup.window), (0, 0, 0) if setup.tree is not None else self.shape,
                         setup.tail_edges)]))
        stars4 = np.zeros((max(1, setup.stars.shape[0]), 4), np.float32)
        stars4[:setup.stars.shape[0], :3] = setup.stars
        self.d_stars = be.to_device(stars4)
        self.d_cdf = be.to_device(np.ascontiguousarray(setup.star_cdf, np.float32))
        # (a tree: its root cells; the cells of a slot are its leaves)
        nx, ny, nz = self.shape if setup.tree is None else setup.tree.roots
        self.params = kernel_params.pack(
            seed=setup.seed, batch_base=0, batch_extra=0, cells=self.nvox, nx=nx, ny=ny, nz=nz, n_bands=nb,
            n_stars=setup.stars.shape[0], max_scatterings=setup.max_scatterings, sq_shift=setup.sq_shift,
            window_shape=(1, 1, 1) if setup.window is None else np.shape(setup.window),
            track_scale=setup.track_scale, peel_scale=setup.peel_scale, collision_scale=setup.collision_scale,
            image_stokes=max(1, self.slots * self.bands_per_launch) * setup.peel_pixels * setup.cell_words,
            state_slots=0,
            peel=np.zeros(15, np.float32) if setup.peel is None else np.asarray(setup.peel, np.float32))
        self.d_params = be.to_device(self.params.view(np.uint8))
        self.d_acc = be.device_zeros(max(1, self.slot_cells * self.slots * self.words), np.uint64)
        self.packet_sq = bool(setup.packet_sq)
        if self.packet_sq:
            if self.slots != 1 or self.bands_per_launch != nb:
                raise ValueError("the error estimate by packets traces one slot of every band")
            # the sums and squares of the run's one batch become the statistics in place
            self.d_sq = be.device_zeros(self.slot_cells, np.uint64)
            self.d_sum1 = self.d_m2 = None
        else:
            self.d_sq = be.device_zeros(1, np.uint64)
            stats = self.ncell if setup.light_field else 1
            self.d_sum1 = be.device_zeros(stats, np.float64)
            self.d_m2 = be.device_zeros(stats, np.float32)
        self.d_tallies = be.device_zeros(self.slots * self.bands_per_launch * self.tally_words, np.uint64)
        self.d_overflow = be.device_zeros(self.slots, np.uint32)
        self.d_seen = be.device_zeros(1, np.uint32)
        self.pixels = setup.peel_pixels
        # every cell's intensity image, then (polarized) every cell's Q and U images: the
        # intensities stay one block of checked adds, Q and U a block of signed sums
        self.image_stokes = self.slots * self.bands_per_launch * self.pixels * self.words
        self.stokes_words = self.pixels * (setup.stokes_images - 1) * self.words  # per cell
        self.d_image = be.device_zeros(max(1, self.image_stokes + self.slots * self.bands_per_launch * self.stokes_words),
                                       np.uint64)
        tuning = dict(be.transport_tuning)
        binned = int(tuning.pop(binned_tuning, 0))
        if setup.tree is not None or binned:
            tuning["NRT_SORTED"] = 0  # (the emission order's keys are a grid's; binned: no walk)
        elif "NRT_SORTED" not in tuning and self.nvox >= getattr(be, "sort_min_voxels", 0) > 0:
            tuning["NRT_SORTED"] = 1  # large grids: a warp's first flights side by side
        # (regions keep the deposits of a pass in cache: without deposits, none)
        self.region_shift = region_shift_of(be, setup, tuning) if setup.light_field and not binned else 0
        if self.region_shift and "NRT_REGIONS" not in tuning:
            # larger regions where the bins of every cell and region would pass the sort's
            # local bins (e.g. three bands at 1024^3), whose counts would go key by key
            while (self._region_bins(self.region_shift) > LOCAL_SORT_BINS
                   and (1 << self.region_shift) < max(self.shape)):
                self.region_shift += 1
        tuning["NRT_REGIONS"] = 1 if self.region_shift else 0
        self.defines = transport_defines(setup, tuning)
        self.sorted = bool(self.defines.get("NRT_SORTED"))
        self.d_keys = be.device_zeros(1, np.uint64)  # NRT_SORTED: the launch's sorted packets
        if self.sorted:
            self._setup_emission_sort()
        if self.region_shift:
            self._setup_regions(tuning)
            if setup.polar:  # where the slots' Stokes states start (after their packets)
                self.params["state_slots"] = self.region_capacity
                self.d_params = be.to_device(self.params.view(np.uint8))
        self._plan = (0, 0)
        self._stream = None  # by regions: (group, packets in flight, free slots, slots used) between launches
        self._h_stage = None  # several ranks: the host buffer of reduce_group
        # build the kernels of this option set now (setup time): compiled inside the first
        # launch, they were counted as tracing (up to 1 s per option set on CUDA)
        names = (("trace_photons",) + (("packet_m2", "packet_sum1") if self.packet_sq else
                                       ("fold_batches",) if setup.light_field else ())
                 + (("emission_keys",) if self.sorted else ()))
        for name in names + (("counting_sort_pass", "scan_bins") if self.region_shift or self.sorted else ()):
            be.kernel(be.transport_program, name, self.defines)
        #: binned deposits (backends/binned.py) trace the launches instead of trace_photons
        self.binned = BinnedDeposits(self, direct=binned == 2) if binned else None

    def _region_bins(self, shift: int) -> int:
        """Bins of the region sort: one per cell (slot and band) and region of 2^shift voxels
        a side, and the free slots' bin."""
        regions = int(np.prod([-(-n // (1 << shift)) for n in self.shape]))
        return self.slots * self.bands_per_launch * regions + 1

    def _setup_emission_sort(self):
        """Bins of the emission order's counting sort: the key's cell and star (``groups`` of
        them at most, kernels/transport.cl, emission_keys) and the leading ``2 bits`` of its
        Morton-ordered direction bin, as many as keep the bins within EMISSION_MAX_BINS."""
        sort_bits = int(self.defines.get("NRT_SORT_BITS", 8))
        groups = min(self.slots * self.bands_per_launch * max(1, self.setup.stars.shape[0]),
                     1 << (31 - 2 * sort_bits))
        most = int(self.backend.transport_tuning.get("emission_bins", EMISSION_MAX_BINS))
        bits = sort_bits
        while bits > 0 and groups << (2 * bits) > most:
            bits -= 1
        self.emit_shift = 2 * (sort_bits - bits)
        self.n_emit_bins = (groups << (2 * bits)) + 1  # (and the free slots' bin, empty)
        self.d_emit_bins = self.backend.device_zeros(self.n_emit_bins + 1, np.uint32)
        self._emit_scratch = None

    def _setup_regions(self, tuning):
        """Buffers of the transport by regions: up to ``region_capacity`` packets in flight,
        each with a state slot and two keys (what a pass stopped, and the next pass's packets
        sorted by cell and region, then the free slots), the emission order of a chunk of new
        packets, and the per-bin counts of the counting sort (one bin per cell and region, and
        the free slots' bin last)."""
        be = self.backend
        state_bytes = kernel_params.dtype("nrt_packet").itemsize
        polar = bool(self.setup.polar)
        self.region_capacity = region_state_bytes(self.nvox, tuning, polar) // packet_state_bytes(polar)  # as region_capacity()
        self.region_tail = int(tuning.get("region_tail", getattr(be, "region_tail", 0)))
        self.n_bins = self._region_bins(self.region_shift)
        if self.n_bins >= 0xFFFFFFFE:
            raise ValueError(f"{self.n_bins} region bins do not fit a 32-bit key")
        # the slots' packets, then (polarized) their Stokes states: the kernel finds them after
        # ``state_slots`` packets (kernels/transport.cl)
        stokes = kernel_params.STOKES_STATE_BYTES if polar else 0
        self.d_states = be.device_zeros(self.region_capacity * (state_bytes + stokes) // 8, np.uint64)
        self.d_stopped = be.device_zeros(self.region_capacity, np.uint64)
        self.d_keys = be.device_zeros(self.region_capacity, np.uint64)
        self.d_emit = be.device_zeros(self.region_capacity if self.sorted else 1, np.uint64)
        self.d_bins = be.device_zeros(self.n_bins + 1, np.uint32)
        self.region_passes = 0  # passes traced so far (a diagnostic for benchmarks)
        #: benchmarks set a list here: every pass appends (work items, packets stopped, seconds
        #: from its launch to the stopped count on the host, region shift, new packets); the
        #: tail pass is waited for then, which a run otherwise does not do
        self.region_log = None

    def run_group(self, photon_start, count, batch_base, batch_extra, first_batch, n_slots, fresh=True,
                  bands=None, drain=True):
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
            self._stream = None  # packets of an abandoned group (a cancelled run) are dropped
        if self.binned is not None:
            self.binned.run(int(photon_start), int(count), int(first_batch), int(band0), int(n_lb))
        elif self.region_shift:
            self._trace_by_regions(int(photon_start), int(count), first_batch, band0, n_lb, drain)
        else:
            if self.sorted:
                self.d_keys = self._emission_order(self.d_keys, photon_start, count, first_batch, band0, n_lb)
            self._launch_trace(photon_start, count, first_batch, band0, n_lb)
        work, self.while_tracing = self.while_tracing, None
        if work is not None:  # host work that overlaps the launch
            work()
        tallies = be.to_host(self.d_tallies).reshape(self.slots, self.bands_per_launch,
                                                     self.tally_words)  # synchronises
        overflow = be.to_host(self.d_overflow)
        return tallies[:n_slots, :n_lb].copy(), overflow[:n_slots].astype(bool)

    def _emission_order(self, keys, photon_start, count, first_batch, band0, n_lb, scratch=None):
        """NRT_SORTED: ``count`` packets (all bands) from ``photon_start`` sorted by cell, star
        and first direction, into ``keys`` (grown where too small; returned): the order the
        trace starts them in. The unsorted keys go to ``scratch`` (a buffer of at least as
        many elements; by default one the session keeps), and a counting sort puts them in
        order."""
        be = self.backend
        items = int(count) * n_lb
        if keys.size < items:
            keys = None
            keys = be.device_zeros(items, np.uint64)
        if scratch is None:  # (without regions: one buffer kept for the run's launches)
            if self._emit_scratch is None or self._emit_scratch.size < items:
                self._emit_scratch = None
                self._emit_scratch = be.device_zeros(items, np.uint64)
            scratch = self._emit_scratch
        launch = kernel_params.pack(
            "nrt_launch", photon_start=photon_start, count=count, first_batch=first_batch, n_resume=0, n_fresh=0,
            fresh0=0, n_free=0, hwm=0, band0=band0, n_lbands=n_lb, region_shift=NO_REGIONS, slots=self.slots)[0]
        be.launch(be.transport_program, "emission_keys", items, self.d_params, launch, self.d_cdf, scratch,
                  defines=self.defines)
        self._counting_sort(scratch, items, keys, self.d_emit_bins, self.n_emit_bins, self.emit_shift, read=False)
        return keys

    def _counting_sort(self, keys, n, out, bins, n_bins, shift=0, read=True):
        """Sort keys[0 .. n) into ``out`` by bin ((key >> 32) >> shift; NRT_FREE_BIN last:
        kernels/transport.cl, counting_sort_pass, scan_bins), ``bins`` holding n_bins + 1
        counters. Returns the keys before the last bin (``read``; the stream then waits for
        the sort), else None. The counts become first positions on the device: a pass waited
        for the host's prefix sum and upload in between, about 34 us a pass on an H200 (7 ms
        of 512^3 with 1e8 photons)."""
        be = self.backend
        be.fill_zero(bins)
        args = (keys, np.uint64(n), bins, np.int32(n_bins))
        be.launch_trace(be.transport_program, "counting_sort_pass", n, *args, np.int32(0), out, np.int32(shift),
                        defines=self.defines)
        be.launch_trace(be.transport_program, "scan_bins", 1, bins, np.int32(n_bins), defines=self.defines)
        be.launch_trace(be.transport_program, "counting_sort_pass", n, *args, np.int32(1), out, np.int32(shift),
                        defines=self.defines)
        return int(be.to_host(bins[n_bins:n_bins + 1])[0]) if read else None

    def _launch_trace(self, photon_start, count, first_batch, band0, n_lb, n_resume=0, n_fresh=0, fresh0=0,
                      n_free=0, hwm=0, shift=NO_REGIONS):
        """One launch of trace_photons. Without regions: the launch's ``count`` packets of
        ``n_lb`` bands. By regions, one pass (kernels/transport.cl, nrt_pass_item): the
        ``n_resume`` stopped packets listed in d_keys and ``n_fresh`` new ones of the chunk of
        ``count`` packets from ``photon_start`` (its items ``fresh0`` on), started in the
        ``n_free`` free slots listed after the stopped keys, then in slots ``hwm`` on; packets
        stop at region faces of 2^shift voxels."""
        be = self.backend
        regions = bool(self.region_shift)
        items = n_resume + max(n_fresh, n_free) if regions else int(count) * n_lb
        launch = kernel_params.pack(
            "nrt_launch", photon_start=photon_start, count=count, first_batch=first_batch, n_resume=n_resume,
            n_fresh=n_fresh, fresh0=fresh0, n_free=n_free, hwm=hwm, band0=band0, n_lbands=n_lb,
            region_shift=shift, slots=self.slots)[0]
        be.launch_trace(
            be.transport_program, "trace_photons", items, self.d_params, launch,
            self.d_density, self.d_optics, self.d_stars, self.d_cdf,
            self.d_acc, self.d_sq, self.d_tallies, self.d_overflow, self.d_image, self.d_keys,
            self.d_emit if regions else self.d_keys, self.d_states if regions else self.d_keys, self.d_window,
            self.d_stopped if regions else self.d_keys, defines=self.defines)
        return items

    def _trace_by_regions(self, photon_start, count, first_batch, band0, n_lb, drain=True):
        """Trace a launch's packets in passes. Each pass runs its packets until they end or
        step into another region; the stopped ones, sorted by (cell, region), are the next
        pass's, and new packets take the places of those that ended, so that every pass holds
        as many packets as the state memory has room for (``region_capacity``) while the launch
        has new ones: the packets per region, and with them the share of deposits that stay in
        L2, do not dwindle pass by pass. The new packets come in chunks of at most
        ``region_capacity`` (all bands), each in its emission order. Once no new packets are
        left and fewer than ``region_tail`` are in flight (or after MAX_REGION_PASSES such
        passes), the last pass runs them to the end. With ``drain`` False the launch ends once
        its last new packets have run their first pass, and the next launch of the same group
        goes on with the packets in flight (a group's launches then end in one dwindling tail,
        not one each)."""
        be = self.backend
        cap, shift, log = self.region_capacity, self.region_shift, self.region_log
        chunk = max(1, cap // n_lb)  # photons of one chunk (all bands)
        next_photon, c_start, c_count, c_pos = 0, photon_start, 0, 0
        n_in, n_free, hwm, passes, draining = 0, 0, 0, 0, 0
        group = (first_batch, band0, n_lb, self._plan)
        if self._stream is not None:
            if self._stream[0] != group:
                raise RuntimeError(f"packets of group {self._stream[0]} are in flight, not of {group}")
            _, n_in, n_free, hwm = self._stream
            self._stream = None
        while True:
            if c_pos == c_count * n_lb and next_photon < count and n_in < cap:
                c_start, c_count, c_pos = photon_start + next_photon, min(chunk, count - next_photon), 0
                next_photon += c_count
                if self.sorted:  # (the stopped keys are sorted into d_keys: d_stopped is free)
                    self.d_emit = self._emission_order(self.d_emit, c_start, c_count, first_batch, band0, n_lb,
                                                       self.d_stopped)
            n_new = min(c_count * n_lb - c_pos, cap - n_in)
            more = c_pos + n_new < c_count * n_lb or next_photon < count or not drain
            t0 = time.perf_counter() if log is not None else 0.0
            # the free slots the new packets do not take are passed on while more will need them
            items = self._launch_trace(c_start, c_count, first_batch, band0, n_lb, n_in, n_new, c_pos,
                                       n_free if more else min(n_free, n_new), hwm, shift)
            hwm += max(0, n_new - n_free)
            c_pos += n_new
            passes += 1
            if shift == NO_REGIONS:
                if log is not None:
                    be.to_host(self.d_overflow)  # waits for the pass
                    log.append((items, 0, time.perf_counter() - t0, shift, n_new))
                break
            n_in, n_free = self._sort_stopped(items)
            if log is not None:
                log.append((items, n_in, time.perf_counter() - t0, shift, n_new))
            if not drain and c_pos == c_count * n_lb and next_photon == count:
                self._stream = (group, n_in, n_free, hwm)  # the group's next launch goes on
                break
            if not more:
                draining += 1
                if n_in == 0:
                    break
                if n_in < self.region_tail or draining >= MAX_REGION_PASSES:
                    shift = NO_REGIONS
        self.region_passes += passes

    def _sort_stopped(self, n):
        """Counting sort of the keys the last pass wrote (d_stopped[0..n)) into d_keys by bin,
        the free slots last; returns (stopped packets, free slots). (Keys that also held the
        place and direction in the region, radix-sorted so that a warp's packets enter side by
        side, flying alike, traced no faster on an H200: 71.1k against 70.5k packets/ms at
        512^3.)"""
        stopped = self._counting_sort(self.d_stopped, n, self.d_keys, self.d_bins, self.n_bins)
        return stopped, int(n) - stopped  # (every item of a pass writes a key)

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
        t = np.asarray(tallies, np.uint64)[..., :self.setup.tally_base]
        if not self.setup.biased:
            return t.astype(object)
        lo, hi = t[..., 0::2].astype(object), t[..., 1::2].astype(object)
        v = lo + (hi << 64)
        v[..., 4] = np.where(v[..., 4] >= 1 << 127, v[..., 4] - (1 << 128), v[..., 4])
        return v

    def reduce_group(self, comm, n_slots, bands, tallies, overflow, reducer=None):
        """Add the ranks' slots, images, tallies and flags of a group and put the sums back on
        the device, so every rank folds the one-rank run's batch totals.

        The sums are taken in place (:func:`nebula_rt.backends.parallel.sum_checked`): in the slots'
        own memory where the device's memory is the host's (OpenCL on a CPU,
        ``Backend.map_host``: no copy at all), else in one host buffer kept for the run (no
        allocation, and no page faults, per group) that holds everything; the image, tallies
        and flags then travel in it too. Checked cells (the slots with checked adds, the image
        always) are summed so that none can wrap, and a slot with a summed cell at or past the
        headroom limit is flagged, as one rank's checked adds would have flagged it. With
        unchecked adds the batch cannot wrap at all (the bound covers all its packets) and the
        fold checks the limit. Returns (tallies, overflow).

        ``reducer`` (:func:`nebula_rt.backends.parallel.device_reducer`; CUDA): the slots and squares
        are summed where they are, on the device (NCCL, or through the reducer's host buffer),
        and only the images, tallies and flags travel through the host buffer."""
        from .parallel import DeviceSums

        be = self.backend
        n_lb = bands[1]
        cells = n_slots * (self.slot_cells // self.bands_per_launch) * n_lb * self.words
        if reducer is not None:
            sums = DeviceSums(comm, reducer)
            if self.packet_sq:
                reducer.sum_u64(self.d_sq)
            return self._reduce(sums, n_slots, n_lb, tallies, overflow, self.d_acc[:cells])
        if self.packet_sq:
            self._reduce_squares(comm)
        if cells == 0:  # no light field: images, tallies and flags only
            return self._reduce(comm, n_slots, n_lb, tallies, overflow, np.zeros(0, np.uint64))
        mapped = be.map_host(self.d_acc, cells)
        if mapped is None:
            return self._reduce(comm, n_slots, n_lb, tallies, overflow, None)
        with mapped as acc:
            return self._reduce(comm, n_slots, n_lb, tallies, overflow, acc)

    def _reduce_squares(self, comm):
        """The error estimate by packets: add the ranks' squares (exact: integers, and the
        shift keeps every cell of the sum below 2^63), in place where the device's memory is
        the host's, else through a host copy."""
        from .parallel import StagedReducer

        be, n = self.backend, int(self.d_sq.size)
        mapped = be.map_host(self.d_sq, n)
        if mapped is not None:
            with mapped as sq:
                comm.sum_u64(sq)
            return
        StagedReducer(comm, be).sum_u64(self.d_sq)

    def _reduce(self, comm, n_slots, n_lb, tallies, overflow, acc):
        """:meth:`reduce_group` with the group's slots mapped as ``acc`` (or None: copied; or
        the device's own slots, with ``comm`` a :class:`~nebula_rt.backends.parallel.DeviceSums`)."""
        from .parallel import sum_checked, sum_wide

        be = self.backend
        cells = 0 if acc is not None else n_slots * (self.slot_cells // self.bands_per_launch) * n_lb * self.words
        pix, nt = n_slots * n_lb * self.pixels * self.words, tallies.size
        need = cells + pix + nt + n_slots
        if self._h_stage is None or self._h_stage.size < need:
            most = self.slots * self.bands_per_launch
            self._h_stage = be.host_empty((0 if acc is not None else self.slots * self.slot_cells * self.words)
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
            for part, checked in ((acc, True), (buf[cells:cells + pix], True)):
                if part.size:
                    top = sum_wide(comm, part)
                    if checked:
                        past |= to_numpy((top.reshape(n_slots, -1)
                                          >= np.uint64(1 << int(self.setup.acc_limit_bits))).any(1))
            # the tally blocks: 128-bit weight sums, then the heavy-tail histograms' 64-bit counts
            blocks = buf[cells + pix:cells + pix + nt].reshape(-1, self.tally_words)
            base = self.setup.tally_base
            wide = np.ascontiguousarray(blocks[:, :base])
            sum_wide(comm, wide)
            blocks[:, :base] = wide
            if self.tally_words > base:
                counts = np.ascontiguousarray(blocks[:, base:])
                comm.sum_u64(counts)
                blocks[:, base:] = counts
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
        if self.stokes_words:  # Q and U: signed sums in two's complement, exact modulo 2^64 (2^128; no check)
            from .parallel import sum_wide

            end = self.image_stokes + n_slots * n_lb * self.stokes_words
            whole = np.ascontiguousarray(be.to_host(self.d_image)[:end])  # (the summed intensities first)
            qu = np.ascontiguousarray(whole[self.image_stokes:])
            if self.words == 2:
                sum_wide(comm, qu)
            else:
                comm.sum_u64(qu)
            whole[self.image_stokes:] = qu
            be.upload(self.d_image, whole)
        be.upload(self.d_overflow, flags.astype(np.uint32))
        return buf[cells + pix:cells + pix + nt].reshape(tallies.shape).copy(), flags

    def fold(self, n_slots, bands=None, folded_before: int = 0, packets: int = 0, clear: bool = True):
        if self.packet_sq:
            if n_slots != 1 or folded_before:
                raise RuntimeError("the error estimate by packets folds its one batch once")
            self._finish_packets(int(packets))
            return
        if not self.setup.light_field:
            return  # no J: the images and tallies are folded on the host
        band0, n_lb = bands if bands is not None else (0, self.setup.n_bands)
        n = n_lb * self.nvox
        self.backend.launch(self.backend.transport_program, "fold_batches", n,
                            self.d_acc, self.d_sum1, self.d_m2, self.d_overflow, np.int32(n_slots),
                            np.uint64(n), np.uint64(band0 * self.nvox), np.int32(folded_before),
                            self.d_seen, np.int32(bool(clear)), defines=self.defines)

    def _finish_packets(self, packets: int):
        """The run's one batch (the error estimate by packets) as the statistics the fold
        would have made: the centred sum of squares of the packets' totals, q = S 2^sq_shift
        - T^2 / N, as float32 x 2^-64 in the first half of the squares' slot (launched over
        [0, 1), [1, 2), [2, 4), ... so that no launch overwrites a square it has yet to read:
        kernels/transport.cl, packet_m2), then the sums as float64 in the sums' slot. The
        batch count of the estimate is then N (batches of one packet)."""
        be, n = self.backend, self.ncell
        inv_n, unit = 1.0 / max(packets, 1), float(2.0**self.setup.sq_shift)
        lo, hi = 0, 1
        while lo < n:
            be.launch(be.transport_program, "packet_m2", hi - lo, self.d_acc, self.d_sq, np.uint64(lo),
                      np.uint64(min(hi, n)), np.float64(inv_n), np.float64(unit), self.d_seen,
                      defines=self.defines)
            lo, hi = hi, 2 * hi
        be.launch(be.transport_program, "packet_sum1", n, self.d_acc, np.uint64(n), defines=self.defines)
        self.d_sum1 = self.d_acc.view(np.float64)
        self.d_m2 = self.d_sq.view(np.float32)[:n]
        self.d_acc = self.d_sq = None

    def read_overflow_seen(self):
        be = self.backend
        # one page-locked word per backend, reused by its runs (which follow each other)
        host = be.__dict__.get("_seen_host")
        if host is None:
            host = be.__dict__["_seen_host"] = be.host_empty((1,), np.uint32)
        self._seen_read = (host, be.to_host_async(self.d_seen, host))

    def overflow_seen(self):
        read, self._seen_read = getattr(self, "_seen_read", None), None
        if read is None:
            return bool(self.backend.to_host(self.d_seen)[0])
        self.backend.wait_copy(read[1])
        return bool(read[0][0])

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
        whole = self.backend.to_host(self.d_image)
        self.backend.fill_zero(self.d_image)
        out = whole[:self.image_stokes].reshape(self.slots, self.bands_per_launch, w, h, self.words)[:n_slots, :n_lb]
        if self.stokes_words:  # (n, bands, [I, Q, U], W, H): Q and U as the signed sums they are
            qu = whole[self.image_stokes:].reshape(self.slots, self.bands_per_launch, s.stokes_images - 1, w, h,
                                                   self.words)[:n_slots, :n_lb]
            if self.words == 1:
                return np.concatenate([out[..., 0][:, :, None], qu[..., 0]], axis=2)
            # 128-bit: I as float64, Q and U as signed 128-bit integers (high word signed) in float64
            i64 = out[..., 1].astype(np.float64) * 2.0**64 + out[..., 0].astype(np.float64)
            q64 = qu[..., 1].view(np.int64).astype(np.float64) * 2.0**64 + qu[..., 0].astype(np.float64)
            return np.concatenate([i64[:, :, None], q64], axis=2)
        if self.words == 1:
            return out[..., 0]
        # 128-bit pixels as float64 (the image statistics are float64 anyway)
        return out[..., 1].astype(np.float64) * 2.0**64 + out[..., 0].astype(np.float64)

    def release_sums(self):
        out = (self.d_sum1, self.d_m2, self.d_density)
        self.d_sum1 = self.d_m2 = self.d_density = None
        self.d_acc = self.d_sq = self.d_image = self.d_keys = None  # the slots' memory goes to the finishing
        self.d_states = self.d_stopped = self.d_bins = self.d_emit = self.d_emit_bins = self._emit_scratch = None
        self._h_stage = None
        return out

    def device_bytes(self) -> int:
        """Device memory this run holds: the batch slots (8 B per slot cell), the statistics
        (12 B per cell), the density (4 B per voxel), the per-slot tallies and the images."""
        regions = (self.region_capacity * packet_state_bytes(bool(self.setup.polar))
                   + 4 * self.n_bins
                   if self.region_shift else 0)
        stats = 8 * self.ncell if self.packet_sq else 12 * self.ncell  # (packets: the squares' slot)
        stats = stats if self.setup.light_field else 12
        return (8 * self.words * self.slot_cells * self.slots + stats
                + 4 * self.nvox * (1 if self.setup.peel_columns is None else 2)
                + 8 * self.tally_words * self.bands_per_launch * self.slots + 4 * self.slots
                + 8 * self.words * self.slots * self.bands_per_launch * self.pixels
                + 8 * self.slots * self.bands_per_launch * self.stokes_words + regions
                + (self.binned.device_bytes() if self.binned is not None else 0))

    def close(self):
        for name in ("d_acc", "d_sq", "d_sum1", "d_m2", "d_density", "d_image", "d_keys", "_h_stage", "d_states",
                     "d_stopped", "d_bins", "d_emit", "d_emit_bins", "_emit_scratch"):
            setattr(self, name, None)
