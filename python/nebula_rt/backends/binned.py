"""Binned deposits: a run's launches traced by kernels/binned.cl instead of the walk.

A backend whose transport tuning holds ``binned_deposits: 1`` traces the analog track-length
estimator on a grid this way (``benchmarks/bench_mcx.py --tuning binned_deposits=1``): flights
by delta tracking against each block's largest density, their track lengths cut into pieces at
the faces of blocks of :data:`BLOCK`^3 voxels, the pieces binned by block and drawn block by
block in local memory (the kernel file's comment says how, docs/physics.md why). Each launch's
packets go cell by cell (batch slot and band), in sub-launches of at most
:data:`MAX_PACKETS`: a counting walk, the buckets laid out on the host from its counts, the
same walk writing the records, then the drawing.

The batch slots, tallies, headroom flags, folds and everything after them are the walk's: only
how the deposits reach the slots differs. The random numbers are spent differently, so a seed
gives other bits than the walk's (the same bits for any launch split, device or number of
ranks).
"""

from __future__ import annotations

import numpy as np

#: voxels along a block's edge (the drawing's local sums: BLOCK^3 64-bit cells, 32 KiB)
BLOCK = 16
#: records one work group of the drawing takes at a time
CHUNK = 4096
#: blocks whose counts per work group fit local memory (32 KiB); beyond, each group's counts
#: go to a row of its own in global memory
LOCAL_BLOCKS = 8192
#: packets of one sub-launch (its records: about 1.5 per block a packet crosses, 32 bytes each)
MAX_PACKETS = 1 << 21
RECORD_WORDS = 8  # float32 words of a record (start, length, direction, padding)
PROGRAM = "binned.cl"
MODES = {"count": 0, "write": 1, "direct": 2}


def enabled(backend) -> bool:
    """Whether ``backend`` traces with binned deposits (its transport tuning ``binned_deposits``:
    1, or 2 for every piece added at once with global atomics, a check of the drawing)."""
    return bool(int((getattr(backend, "transport_tuning", None) or {}).get("binned_deposits", 0)))


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


def block_maxima(density: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """Each block's largest density (float32, blocks x fastest), the grid padded with zeros
    to whole blocks: delta tracking's majorant."""
    d = np.asarray(density, np.float32)
    nb = [-(-n // block) for n in d.shape]
    padded = np.zeros([b * block for b in nb], np.float32)
    padded[: d.shape[0], : d.shape[1], : d.shape[2]] = d
    m = padded.reshape(nb[0], block, nb[1], block, nb[2], block).max(axis=(1, 3, 5))
    return np.ascontiguousarray(m.transpose(2, 1, 0)).reshape(-1)  # x fastest


def batch_start(k: int, base: int, extra: int) -> int:
    """First packet of batch k (the first ``extra`` batches hold base + 1, kernels/transport.cl,
    nrt_batch_of)."""
    return k * (base + 1) if k < extra else extra * (base + 1) + (k - extra) * base


def batch_of(photon: int, base: int, extra: int) -> int:
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
        self.n_blocks = int(np.prod([-(-n // BLOCK) for n in s.shape]))
        self.global_counts = self.n_blocks > LOCAL_BLOCKS
        self.defines = {k: v for k, v in s.defines.items() if k not in ("NRT_SORTED", "NRT_REGIONS")}
        self.defines.update(NRT_NX=nx, NRT_NY=ny, NRT_NZ=nz, NRT_BLOCK=BLOCK, NRT_BIN_GLOBAL=int(self.global_counts))
        self.d_rho_max = be.to_device(block_maxima(s.setup.density))
        self.local = {m: be.trace_local_size(PROGRAM, "binned_walk", self._defines(m)) for m in MODES}
        be.kernel(PROGRAM, "binned_draw", self._defines("count"))
        self.d_block_count = be.device_zeros(self.n_blocks, np.uint32)
        self.d_group_off = be.device_zeros(1, np.uint32)
        self.d_hist = be.device_zeros(1, np.uint32)
        self.d_records = be.device_zeros(RECORD_WORDS, np.float32)
        #: records per packet of the last sub-launch (a diagnostic for benchmarks)
        self.records_per_packet = 0.0

    def _defines(self, mode: str) -> dict:
        return dict(self.defines, NRT_BIN_MODE=MODES[mode])

    def _grow(self, name: str, n: int, dtype):
        buf = getattr(self, name)
        if buf.size < n:
            setattr(self, name, None)
            setattr(self, name, self.backend.device_zeros(int(n * 1.25) + 1, dtype))
        return getattr(self, name)

    def run(self, photon_start: int, count: int, first_batch: int, band0: int, n_lb: int):
        """Trace packets photon_start .. + count of bands band0 .. + n_lb (the launch's cells:
        slot = batch - first_batch, cell = slot n_lb + band offset)."""
        s = self.session
        base, extra = int(s.params["batch_base"][0]), int(s.params["batch_extra"][0])
        for lband in range(n_lb):
            p, end = int(photon_start), int(photon_start) + int(count)
            while p < end:
                k = batch_of(p, base, extra)
                stop = min(end, batch_start(k + 1, base, extra), p + MAX_PACKETS)
                slot = k - int(first_batch)
                self._cell(p, stop - p, band0 + lband, slot * n_lb + lband, slot)
                p = stop

    def _walk(self, mode: str, photon_start, n, band, cell, slot, bucket=None):
        s, be = self.session, self.backend
        groups = -(-n // self.local[mode])
        if mode == "count":
            self._grow("d_group_off", groups * self.n_blocks, np.uint32)
        if self.global_counts and mode != "direct":
            be.fill_zero(self._grow("d_hist", groups * self.n_blocks, np.uint32))
        be.launch_trace(PROGRAM, "binned_walk", n, s.d_params, np.uint64(photon_start), np.uint64(n), np.int32(band),
                        np.uint64(cell), np.uint64(slot), s.d_density, self.d_rho_max, s.d_optics, s.d_stars, s.d_cdf,
                        s.d_acc, s.d_tallies, s.d_overflow, self.d_block_count, self.d_group_off,
                        self.d_block_count if bucket is None else bucket, self.d_records, self.d_hist,
                        defines=self._defines(mode))

    def _cell(self, photon_start, n, band, cell, slot):
        be = self.backend
        if self.direct:
            self._walk("direct", photon_start, n, band, cell, slot)
            return
        be.fill_zero(self.d_block_count)
        self._walk("count", photon_start, n, band, cell, slot)
        counts = be.to_host(self.d_block_count).astype(np.int64)  # (waits for the counting walk)
        total = int(counts.sum())
        self.records_per_packet = total / max(1, n)
        if total == 0:
            return
        if total >= 2**32:
            raise ValueError(f"{total} records of one sub-launch pass 32-bit offsets")
        starts = np.zeros(self.n_blocks, np.int64)
        np.cumsum(counts[:-1], out=starts[1:])
        self._grow("d_records", total * RECORD_WORDS, np.float32)
        n_chunks = -(-counts // CHUNK)
        blocks = np.repeat(np.arange(self.n_blocks, dtype=np.uint32), n_chunks)
        index = np.arange(blocks.size) - np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
        chunk_start = (starts[blocks] + index * CHUNK).astype(np.uint32)
        chunk_len = np.minimum(CHUNK, counts[blocks] - index * CHUNK).astype(np.uint32)
        bucket = be.to_device(starts.astype(np.uint32))
        self._walk("write", photon_start, n, band, cell, slot, bucket)
        s = self.session
        d_blocks, d_start, d_len = be.to_device(blocks), be.to_device(chunk_start), be.to_device(chunk_len)
        local = be.trace_local_size(PROGRAM, "binned_draw", self._defines("count"))
        be.launch_trace(PROGRAM, "binned_draw", blocks.size * local, s.d_params, np.uint64(cell), np.uint64(slot),
                        d_blocks, d_start, d_len, np.uint64(blocks.size), self.d_records, s.d_acc, s.d_overflow,
                        defines=self._defines("count"))
