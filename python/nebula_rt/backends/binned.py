"""Binned deposits: a run's launches traced by kernels/binned.cl instead of the walk.

A backend whose transport tuning holds ``binned_deposits: 1`` traces the analog track-length
estimator on a grid this way (``benchmarks/bench_mcx.py --tuning binned_deposits=1``): flights
by delta tracking against the largest density of each cell of :data:`MAJORANT`^3 voxels, their
track lengths cut into pieces at the faces of blocks of :data:`BLOCK`^3 voxels, the pieces
binned by block and drawn block by block in local memory (the kernel file's comment says how,
docs/physics.md why). Each launch's packets go band by band in sub-launches of at most
:data:`MAX_PACKETS` (one or more batch slots): a counting walk, the buckets laid out on the
host from its counts (while the next sub-launch's counting walk runs), the same walk writing
the records, then the drawing.

The batch slots, tallies, headroom flags, folds and everything after them are the walk's: only
how the deposits reach the slots differs. The random numbers are spent differently, so a seed
gives other bits than the walk's (the same bits for any launch split, device or number of
ranks).
"""

from __future__ import annotations

import numpy as np

#: voxels along a block's edge (the drawing's local sums: BLOCK^3 64-bit cells, 32 KiB)
BLOCK = 16
#: voxels along the edge of a majorant cell of delta tracking (a divisor of BLOCK; the tuning
#: ``binned_majorant`` overrides it). On the lognormal medium 4^3 cells make about 3.5x fewer
#: tentative collisions than 16^3 ones for 4x the cell crossings (docs/physics.md): on PoCL
#: the two cost the same; the GPUs are to be measured
MAJORANT = 16
#: records one work group of the drawing takes at a time
CHUNK = 4096
#: blocks whose counts per work group, for the two batch slots its packets may lie in, fit
#: local memory (32 KiB); beyond, each group's counts go to rows of its own in global memory
LOCAL_BLOCKS = 4096
#: bytes the work groups' offsets per block may take (and their counts, for large grids): a
#: walk's work items take several packets each where one each would pass this
GROUP_BYTES = 64 << 20
#: packets of one sub-launch (its records: about 1.5 per block a packet crosses, 32 bytes each)
MAX_PACKETS = 1 << 21
RECORD_WORDS = 8  # float32 words of a record (start, length, direction, padding)
PROGRAM = "binned.cl"
#: the transport tuning keys: 1 binned deposits, 2 every piece added at once with global
#: atomics (a check of the drawing); the majorant cells' edge in voxels
TUNING, MAJORANT_TUNING = "binned_deposits", "binned_majorant"
MODES = {"count": 0, "write": 1, "direct": 2}


def enabled(backend) -> bool:
    """Whether ``backend`` traces with binned deposits (its transport tuning ``binned_deposits``:
    1, or 2 for every piece added at once with global atomics, a check of the drawing)."""
    return bool(int((getattr(backend, "transport_tuning", None) or {}).get(TUNING, 0)))


def majorant_of(backend) -> int:
    """Voxels along a majorant cell's edge on ``backend`` (its tuning ``binned_majorant``, else
    MAJORANT), checked to divide BLOCK."""
    m = int((getattr(backend, "transport_tuning", None) or {}).get(MAJORANT_TUNING, MAJORANT))
    if m < 1 or BLOCK % m:
        raise ValueError(f"transport tuning binned_majorant = {m}: a divisor of {BLOCK}")
    return m


def refusal(setup) -> str | None:
    """Why binned deposits cannot trace ``setup`` (None: they can)."""
    reasons = []
    if setup.estimator != "track-length":
        reasons.append(f"estimator {setup.estimator!r} (binned deposits: track-length)")
    if setup.tree is not None:
        reasons.append("an adaptive tree (binned deposits: a grid)")
    if setup.biased:
        reasons.append("weighted packets (binned deposits: analog)")
    if setup.peel is not None:
        reasons.append("a peel-off image")
    if setup.polar:
        reasons.append("polarization")
    if setup.packet_sq:
        reasons.append("the error estimate by packets (binned deposits: by batches)")
    if setup.tail_classes:
        reasons.append("heavy-tail classes")
    return "; ".join(reasons) or None


def block_maxima(density: np.ndarray, block: int) -> np.ndarray:
    """Each block's largest density (float32, blocks x fastest), the grid padded with zeros
    to whole blocks: delta tracking's majorant per cell of ``block``^3 voxels."""
    d = np.asarray(density, np.float32)
    nb = [-(-n // block) for n in d.shape]
    padded = np.zeros([b * block for b in nb], np.float32)
    padded[: d.shape[0], : d.shape[1], : d.shape[2]] = d
    m = padded.reshape(nb[0], block, nb[1], block, nb[2], block).max(axis=(1, 3, 5))
    return np.ascontiguousarray(m.transpose(2, 1, 0)).reshape(-1)  # x fastest


def estimated_bytes(shape, batch_packets: int, packets: int, majorant: int = MAJORANT) -> int:
    """Device bytes binned deposits are estimated to add to a run (for
    ``nebula_rt.transport.resources``) of ``packets`` per band on a grid of ``shape``, in
    batches of ``batch_packets``, with majorant cells of ``majorant``^3 voxels:
    - the majorant cells' densities;
    - the bins' totals (two sets, a sub-launch's slots each);
    - the work groups' offsets (at most GROUP_BYTES a set, two sets; for large grids their
      counts too, three more sets);
    - the records of a sub-launch (at most MAX_PACKETS packets), taken as 1.5 pieces per block
      along the box's longest axis and 2 more per packet (the neb medium measured 0.8 and 0.5
      of this at 64^3 and 512^3).
    Each buffer is grown by a quarter as it is."""
    axis = max(-(-int(n) // BLOCK) for n in shape)
    n_blocks = int(np.prod([-(-int(n) // BLOCK) for n in shape]))
    n_cells = int(np.prod([-(-int(n) // majorant) for n in shape]))
    sub = max(1, min(MAX_PACKETS, int(packets)))
    slots = sub // max(1, int(batch_packets)) + 2
    offsets = min(GROUP_BYTES, -(-sub // 32) * 2 * n_blocks * 4)  # (groups of at least 32)
    sets = 2 + (3 if n_blocks > LOCAL_BLOCKS else 0)
    records = sub * (1.5 * axis + 2) * RECORD_WORDS * 4
    return int(4 * n_cells + 1.25 * (2 * 4 * slots * n_blocks + sets * offsets + records))


def batch_of(photon: int, base: int, extra: int) -> int:
    """Batch of packet ``photon``: the kernels' nrt_batch_of (kernels/transport.cl) on the host,
    for the layout of ``nebula_rt.transport.plan.BatchPlan`` (the first ``extra`` batches hold
    base + 1 packets)."""
    big = extra * (base + 1)
    return photon // (base + 1) if photon < big else extra + (photon - big) // base


class BinnedDeposits:
    """The binned launches of one :class:`~.session.DeviceTransport` (its buffers and
    parameters)."""

    def __init__(self, session, direct: bool = False):
        self.session = s = session
        self.direct = bool(direct)
        be = self.backend = s.backend
        why = refusal(s.setup)
        if why:
            raise ValueError(f"transport tuning binned_deposits = 1 cannot trace this run: {why}")
        nx, ny, nz = s.shape
        self.majorant = majorant_of(be)
        self.n_blocks = int(np.prod([-(-n // BLOCK) for n in s.shape]))
        self.global_counts = self.n_blocks > LOCAL_BLOCKS
        self.defines = {k: v for k, v in s.defines.items() if k not in ("NRT_SORTED", "NRT_REGIONS")}
        self.defines.update(NRT_NX=nx, NRT_NY=ny, NRT_NZ=nz, NRT_BLOCK=BLOCK, NRT_MAJ=self.majorant,
                            NRT_BIN_GLOBAL=int(self.global_counts))
        self.d_rho_max = be.to_device(block_maxima(s.setup.density, self.majorant))
        self.local = be.trace_local_size(PROGRAM, "binned_walk", self._defines("count"))
        for mode in MODES:
            be.kernel(PROGRAM, "binned_walk", self._defines(mode))
        be.kernel(PROGRAM, "binned_draw", self._defines("count"))
        self.draw_local = be.trace_local_size(PROGRAM, "binned_draw", self._defines("count"))
        # the counting walk of the next sub-launch runs while the host lays out this one's
        # buckets: its bins' totals and the groups' offsets come in two sets
        self.d_bin_count = [be.device_zeros(1, np.uint32) for _ in range(2)]
        self.d_group_off = [be.device_zeros(1, np.uint32) for _ in range(2)]
        self.d_hist = [be.device_zeros(1, np.uint32) for _ in range(3)]  # 2 x counts, slots
        self.d_records = be.device_zeros(RECORD_WORDS, np.float32)
        #: records per packet of the last sub-launch (a diagnostic for benchmarks)
        self.records_per_packet = 0.0

    def device_bytes(self) -> int:
        """Device memory the binned launches hold now."""
        bufs = (self.d_rho_max, *self.d_bin_count, *self.d_group_off, *self.d_hist, self.d_records)
        return int(sum(b.size * b.dtype.itemsize for b in bufs))

    def _defines(self, mode: str) -> dict:
        return dict(self.defines, NRT_BIN_MODE=MODES[mode])

    def _grown(self, buf, n: int, dtype):
        """``buf``, or a larger one where it holds fewer than ``n`` elements."""
        return buf if buf.size >= n else self.backend.device_zeros(int(n * 1.25) + 1, dtype)

    def _sub_launches(self, photon_start, count, first_batch, band0, n_lb):
        """(photon start, count, band offset, first slot, slots) of the sub-launches: each of
        one band, at most MAX_PACKETS packets, whole or part batches."""
        s = self.session
        base, extra = int(s.params["batch_base"][0]), int(s.params["batch_extra"][0])
        out = []
        for lband in range(n_lb):
            p, end = photon_start, photon_start + count
            while p < end:
                stop = min(end, p + MAX_PACKETS)
                k0, k1 = batch_of(p, base, extra), batch_of(stop - 1, base, extra)
                out.append((p, stop - p, lband, k0 - first_batch, k1 - k0 + 1))
                p = stop
        return out

    def run(self, photon_start: int, count: int, first_batch: int, band0: int, n_lb: int):
        """Trace packets photon_start .. + count of bands band0 .. + n_lb into the launch's
        cells (slot = batch - first_batch, cell = slot n_lb + band offset)."""
        subs = self._sub_launches(int(photon_start), int(count), int(first_batch), int(band0), int(n_lb))
        if self.direct:
            for p, n, lband, slot0, _ in subs:
                self._walk("direct", 0, p, n, band0, lband, n_lb, first_batch, slot0, 1)
            return
        pending = self._count(0, subs[0], band0, n_lb, first_batch)
        for j, sub in enumerate(subs):
            totals = self.backend.to_host(self.d_bin_count[j % 2][:pending]).astype(np.int64)  # (waits)
            nxt = self._count((j + 1) % 2, subs[j + 1], band0, n_lb, first_batch) if j + 1 < len(subs) else 0
            self._write_and_draw(j % 2, sub, totals, band0, n_lb, first_batch)
            pending = nxt

    def _per_item(self, n: int) -> int:
        """Packets per work item of a walk: 1, or as many as keep the groups' offsets (and, for
        large grids, their counts) within GROUP_BYTES."""
        groups = -(-n // self.local)
        return max(1, -(-groups * 2 * self.n_blocks * 4 // GROUP_BYTES))

    def _walk(self, mode, j, p, n, band0, lband, n_lb, first_batch, slot0, per_item, bucket=None):
        s, be = self.session, self.backend
        groups = -(-n // (self.local * per_item))
        if mode == "count":
            self.d_group_off[j] = self._grown(self.d_group_off[j], groups * 2 * self.n_blocks, np.uint32)
        h = j if mode == "count" else 2
        if self.global_counts and mode != "direct":
            self.d_hist[h] = self._grown(self.d_hist[h], groups * 2 * self.n_blocks, np.uint32)
            be.fill_zero(self.d_hist[h])
        be.launch_trace(PROGRAM, "binned_walk", groups * self.local, s.d_params, np.uint64(p), np.uint64(n),
                        np.int32(per_item), np.int32(band0 + lband), np.int32(lband), np.int32(n_lb),
                        np.uint64(first_batch), np.uint64(slot0), s.d_density, self.d_rho_max, s.d_optics,
                        s.d_stars, s.d_cdf, s.d_acc, s.d_tallies, s.d_overflow, self.d_bin_count[j],
                        self.d_group_off[j], self.d_bin_count[j] if bucket is None else bucket, self.d_records,
                        self.d_hist[h], defines=self._defines(mode))

    def _count(self, j, sub, band0, n_lb, first_batch) -> int:
        """Queue the counting walk of sub-launch ``sub`` into set ``j``; returns its bins."""
        p, n, lband, slot0, n_slots = sub
        bins = n_slots * self.n_blocks
        self.d_bin_count[j] = self._grown(self.d_bin_count[j], bins, np.uint32)
        self.backend.fill_zero(self.d_bin_count[j])
        self._walk("count", j, p, n, band0, lband, n_lb, first_batch, slot0, self._per_item(n))
        return bins

    def _write_and_draw(self, j, sub, totals, band0, n_lb, first_batch):
        """The buckets laid out from the counting walk's ``totals`` per bin, the records
        written, then drawn."""
        be = self.backend
        p, n, lband, slot0, n_slots = sub
        total = int(totals.sum())
        self.records_per_packet = total / max(1, n)
        if total == 0:
            return
        if total >= 2**32:
            raise ValueError(f"{total} records of one sub-launch pass 32-bit offsets")
        starts = np.zeros(totals.size, np.int64)
        np.cumsum(totals[:-1], out=starts[1:])
        self.d_records = self._grown(self.d_records, total * RECORD_WORDS, np.float32)
        n_chunks = -(-totals // CHUNK)
        bins = np.repeat(np.arange(totals.size, dtype=np.uint32), n_chunks)
        index = np.arange(bins.size) - np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
        chunk_start = (starts[bins] + index * CHUNK).astype(np.uint32)
        chunk_len = np.minimum(CHUNK, totals[bins] - index * CHUNK).astype(np.uint32)
        bucket = be.to_device(starts.astype(np.uint32))
        self._walk("write", j, p, n, band0, lband, n_lb, first_batch, slot0, self._per_item(n), bucket)
        s = self.session
        be.launch_trace(PROGRAM, "binned_draw", bins.size * self.draw_local, s.d_params, np.uint64(slot0),
                        np.int32(lband), np.int32(n_lb), be.to_device(bins), be.to_device(chunk_start),
                        be.to_device(chunk_len), np.uint64(bins.size), self.d_records, s.d_acc, s.d_overflow,
                        defines=self._defines("count"))
