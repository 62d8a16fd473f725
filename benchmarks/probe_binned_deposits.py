#!/usr/bin/env python
"""Probe: track lengths binned by block and added in on-chip memory, beside global atomics.

    python benchmarks/probe_binned_deposits.py [--backend cuda|opencl] [--device SEL]
        [--grids 64 128 256] [--blocks 8 16] [--photons 2.1e7] [--launch 2097152]
        [--repeats 3] [--out FILE]

Not the library's transport. The neb medium of ``bench_mcx.py`` (uniform, optical depth 1
from the centre to a face, albedo 0.6, g 0.6, an isotropic source at the centre, analog
packets) traced by ``probe_binned_deposits.cl``: flights sampled in closed form (no walk
through the voxels), cut at the faces of blocks of B^3 voxels. Two ways to add the track
lengths to the grid's 64-bit fixed-point cells, timed in the same process:

* ``direct``: each flight's pieces drawn at once with a global atomic add per voxel visit
  (as the library's walk adds them);
* ``binned``: a counting walk (records per block, per work group), the bucket starts on the
  host, the same walk again writing each piece as a 32-byte record into its block's bucket,
  then one work group per chunk of a bucket draws its records into the block's cells in local
  memory and adds them to the grid's once.

Both draw every piece with the same arithmetic, so their sums must agree bit for bit; the
track-length estimate of the absorbed fraction (sum x kappa (1 - albedo) / N) is checked
against the count of absorbed packets. Reported: packets per ms of the whole pipeline
(wall time, device synchronised, median of ``--repeats``), the phases of one binned run,
records per packet and voxel visits per packet.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TAU = 2.0  # extinction per box edge (bench_mcx.py)
ALBEDO = 0.6
G = 0.6
SCALE = 2.0 ** 24  # fixed-point units per voxel length
GROUP = 256
CHUNK = 4096  # records per work group of the drawing kernel
LOCAL_HIST_BYTES = 40 * 1024  # a walk's counts per block in local memory up to this size
MODES = {"MODE_COUNT": 0, "MODE_WRITE": 1, "MODE_DIRECT": 2}


def source_text() -> str:
    from nebula_rt.backends import kernel_params
    from nebula_rt.backends.kernel_source import read_kernel_file

    text = (HERE / "probe_binned_deposits.cl").read_text()
    header = read_kernel_file("nebula_common.h").replace("/* NRT_PARAM_STRUCTS */", kernel_params.all_structs())
    return re.sub(r'^\s*#include\s+"nebula_common.h"\s*$', lambda m: header, text, flags=re.MULTILINE)


class Device:
    """The few calls the probe needs, on CuPy or pyopencl."""

    def __init__(self, backend: str, selector: str):
        self.kind = backend
        if backend == "cuda":
            import cupy as cp

            self.cp = cp
            self.name = cp.cuda.runtime.getDeviceProperties(0)["name"].decode()
        else:
            import pyopencl as cl

            from nebula_rt.backends.opencl import select_device

            self.cl = cl
            dev, self.name = select_device(selector)
            self.ctx = cl.Context([dev])
            self.queue = cl.CommandQueue(self.ctx)

    def build(self, defines: dict):
        opts = [f"-D{k}={v}" for k, v in defines.items()]
        if self.kind == "cuda":
            mod = self.cp.RawModule(code=source_text(), options=("--std=c++14", "--fmad=false", *opts))
            return {n: mod.get_function(n) for n in ("probe_walk", "probe_draw_chunks")}
        prg = self.cl.Program(self.ctx, source_text()).build(options=opts)
        return {n: getattr(prg, n) for n in ("probe_walk", "probe_draw_chunks")}

    def zeros(self, n: int, dtype):
        if self.kind == "cuda":
            return self.cp.zeros(max(n, 1), dtype)
        import pyopencl.array as cla

        return cla.zeros(self.queue, max(n, 1), dtype)

    def upload(self, a: np.ndarray):
        if self.kind == "cuda":
            return self.cp.asarray(a)
        import pyopencl.array as cla

        return cla.to_device(self.queue, a)

    def get(self, a) -> np.ndarray:
        return a.get()

    def fill0(self, a):
        a.fill(0)

    def launch(self, kernel, n_items: int, args):
        groups = (n_items + GROUP - 1) // GROUP
        if self.kind == "cuda":
            kernel((groups,), (GROUP,), tuple(args))
        else:
            cl_args = [a.data if hasattr(a, "data") and not isinstance(a, np.generic) else a for a in args]
            kernel(self.queue, (groups * GROUP,), (GROUP,), *cl_args)

    def sync(self):
        if self.kind == "cuda":
            self.cp.cuda.get_current_stream().synchronize()
        else:
            self.queue.finish()


def run_grid(dev: Device, medium: str, n: int, bb: int, photons: int, launch: int, repeats: int,
             sigma_ln: float = 1.0, draw_variant: int = 0, threads: int = 0, draw_flat: int = 0,
             modes=("direct", "binned"), phases_run: bool = True, seed: int = 7) -> dict:
    nblk = n // bb
    nb3 = nblk ** 3
    kappa = TAU / n
    base = {"N": n, "BB": bb, "NBLK": nblk, "KAPPA": f"{kappa:.9e}f", "ALBEDO": f"{ALBEDO}f", "G": f"{G}f",
            "SCALE": f"{SCALE:.1f}f", "P_SRC": f"{n / 2:.1f}f", "DENSITY": int(medium != "uniform"), "DRAW_VARIANT": draw_variant, "DRAW_FLAT": draw_flat,
            **MODES}
    if medium == "uniform":
        rho_host = None
        rho = rho_max = dev.zeros(1, np.float32)
    else:
        from bench_mcx import lognormal_medium  # the same medium as the MCX comparison

        rho_host = np.ascontiguousarray(lognormal_medium(n, sigma_ln).transpose(2, 1, 0))  # x fastest
        blocks = rho_host.reshape(nblk, bb, nblk, bb, nblk, bb).max(axis=(1, 3, 5))
        rho, rho_max = dev.upload(rho_host.ravel()), dev.upload(np.ascontiguousarray(blocks).ravel())
    base["HIST_GLOBAL"] = int(nb3 * 4 > LOCAL_HIST_BYTES)
    k = {m: dev.build(dict(base, MODE=MODES[m])) for m in MODES}
    cells = n ** 3
    launch = min(launch, photons)
    if not threads:  # one packet per work item, or for large grids (global counts per group) 2^18
        threads = launch if nb3 * 4 <= LOCAL_HIST_BYTES else 1 << 18
    groups = (min(launch, threads) + GROUP - 1) // GROUP
    sums = dev.zeros(cells, np.uint64)
    counts = dev.zeros(3, np.uint64)
    hist_global = nb3 * 4 > LOCAL_HIST_BYTES
    # the counting walk of launch k + 1 runs while the host lays out launch k's buckets, so its
    # block totals and offsets (and, for large grids, its counts per group) come in two sets
    block_count = [dev.zeros(nb3, np.uint32) for _ in range(2)]
    group_off = [dev.zeros(groups * nb3, np.uint32) for _ in range(2)]
    ghist = [dev.zeros(groups * nb3 if hist_global else 1, np.uint32) for _ in range(3)]  # 2 counts, 1 slots
    dummy_u32 = dev.zeros(1, np.uint32)
    dummy_f = dev.zeros(1, np.float32)
    dummy_u64 = dev.zeros(1, np.uint64)
    rec_cap = [0]
    rec = [dummy_f]
    phases = {"count": 0.0, "host": 0.0, "write": 0.0, "draw": 0.0}

    def walk(mode, first, last, j=0, bucket=dummy_u32, rec_buf=dummy_f, out=dummy_u64):
        if hist_global and mode != "MODE_DIRECT":
            dev.fill0(ghist[j if mode == "MODE_COUNT" else 2])
        dev.launch(k[mode]["probe_walk"], min(last - first, threads),
                   [np.uint64(seed), np.uint64(first), np.uint64(last), block_count[j], group_off[j], bucket,
                    rec_buf, out, counts, rho, rho_max, ghist[j if mode == "MODE_COUNT" else 2]])

    def layout(bc):
        """Bucket starts and the drawing kernel's chunks from the block totals (host)."""
        starts = np.zeros(nb3, np.int64)
        np.cumsum(bc[:-1], out=starts[1:])
        total = int(bc.sum())
        if total > rec_cap[0]:
            dev.sync()
            rec_cap[0] = int(total * 1.25) + 1
            rec[0] = None
            rec[0] = dev.zeros(rec_cap[0] * 8, np.float32)
        n_chunks = (bc + CHUNK - 1) // CHUNK
        cblk = np.repeat(np.arange(nb3, dtype=np.uint32), n_chunks)
        cidx = np.arange(cblk.size) - np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
        cstart = (starts[cblk] + cidx * CHUNK).astype(np.uint32)
        clen = np.minimum(CHUNK, bc[cblk] - cidx * CHUNK).astype(np.uint32)
        return dev.upload(starts.astype(np.uint32)), [dev.upload(cblk), dev.upload(cstart), dev.upload(clen)], cblk.size

    def binned(timed: bool):
        """All launches; timed: each phase synchronised and timed (no overlap)."""
        t = time.perf_counter
        spans = [(f, min(photons, f + launch)) for f in range(0, photons, launch)]
        for j, (first, last) in enumerate(spans):
            t0 = t()
            if j == 0 or timed:
                dev.fill0(block_count[j % 2])
                walk("MODE_COUNT", first, last, j % 2)
            bc = dev.get(block_count[j % 2]).astype(np.int64)  # (waits for the counting walk)
            t1 = t()
            if not timed and j + 1 < len(spans):
                dev.fill0(block_count[(j + 1) % 2])
                walk("MODE_COUNT", *spans[j + 1], (j + 1) % 2)
            bucket, chunks, n_chunks = layout(bc)
            t2 = t()
            walk("MODE_WRITE", first, last, j % 2, bucket=bucket, rec_buf=rec[0])
            if timed:
                dev.sync()
            t3 = t()
            dev.launch(k["MODE_COUNT"]["probe_draw_chunks"], n_chunks * GROUP, [*chunks, rec[0], sums])
            if timed:
                dev.sync()
                phases["count"] += t1 - t0
                phases["host"] += t2 - t1
                phases["write"] += t3 - t2
                phases["draw"] += t() - t3
        dev.sync()

    def direct():
        for first in range(0, photons, launch):
            walk("MODE_DIRECT", first, min(photons, first + launch), out=sums)
        dev.sync()

    def timed_run(fn):
        dev.fill0(sums)
        dev.fill0(counts)
        dev.sync()
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    row = {"medium": medium, "grid": n, "block": bb, "photons": photons, "launch": launch,
           "draw_variant": draw_variant, "chunk": CHUNK, "threads": threads, "draw_flat": draw_flat}
    # warm-up (compile, allocation): a whole run of each
    for m in modes:
        timed_run(direct if m == "direct" else lambda: binned(False))
    secs = {m: [] for m in modes}
    digests = {}
    direct_sums = None
    for _ in range(repeats):
        for m in modes:
            secs[m].append(timed_run(direct if m == "direct" else lambda: binned(False)))
            s = dev.get(sums)
            c = dev.get(counts)
            digests.setdefault(m, (hash(s.tobytes()), c.tolist()))
            if m == "direct":
                direct_sums = s
    if phases_run:
        timed_run(lambda: binned(True))
    binned_sums = dev.get(sums)
    c = dev.get(counts)
    absorbed = c[0] / photons
    path = binned_sums.astype(np.float64) if rho_host is None else binned_sums * rho_host.ravel().astype(np.float64)
    track = float(path.sum()) / SCALE * kappa * (1.0 - ALBEDO) / photons
    for m in secs:
        med = statistics.median(secs[m])
        row[m] = {"seconds": secs[m], "median_s": med, "packets_per_ms": photons / (med * 1e3)}
    row["binned_phases_s"] = phases
    row["records_per_packet"] = c[2] / photons
    if direct_sums is not None:
        row["same_sums"] = bool(np.array_equal(direct_sums, binned_sums))
        row["same_sums_and_counts_every_repeat"] = digests["direct"] == digests["binned"]
    row["absorbed_fraction"] = {"counted": absorbed, "counted_sigma": math.sqrt(absorbed * (1 - absorbed) / photons),
                                "track_length": track}
    row["escaped_fraction"] = c[1] / photons
    return row


def main(argv=None) -> int:
    global CHUNK
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("cuda", "opencl"), default="cuda")
    ap.add_argument("--device", default="", help="OpenCL device selector (nebula_rt's)")
    ap.add_argument("--media", nargs="+", choices=("uniform", "turbulent"), default=["uniform"])
    ap.add_argument("--sigma-ln", type=float, default=1.0, help="the turbulent medium's sigma of ln rho")
    ap.add_argument("--grids", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--blocks", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--photons", type=float, default=2.1e7)
    ap.add_argument("--launch", type=int, default=1 << 21)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--draw-variant", type=int, choices=(0, 1, 2), default=0,
                    help="1, 2: timing only, wrong sums (one local atomic per visit; plain local adds)")
    ap.add_argument("--chunk", type=int, default=4096, help="records per work group of the drawing kernel")
    ap.add_argument("--threads", type=int, default=0,
                    help="work items of a walk, each tracing packets in turn (0: one packet each, 2^18 for large grids)")
    ap.add_argument("--modes", nargs="+", choices=("direct", "binned"), default=["direct", "binned"])
    ap.add_argument("--no-phases", action="store_true", help="skip the run with each phase timed")
    ap.add_argument("--draw-flat", type=int, choices=(0, 1), default=0,
                    help="1: one voxel visit per loop iteration, lanes load their next record at once")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    CHUNK = a.chunk
    dev = Device(a.backend, a.device)
    print(f"# {dev.name}", flush=True)
    rows = []
    for medium, n, bb in ((m, n, bb) for m in a.media for n in a.grids for bb in a.blocks):
        if n % bb:
            continue
        r = run_grid(dev, medium, n, bb, int(a.photons), a.launch, a.repeats, a.sigma_ln, a.draw_variant,
                     a.threads, a.draw_flat, tuple(a.modes), not a.no_phases)
        rows.append(r)
        ph = r["binned_phases_s"]
        rates = "  ".join(f"{m} {r[m]['packets_per_ms'] / 1e3:8.1f}k/ms" for m in a.modes)
        print(f"{medium:9s} grid {n:4d} block {bb:2d}: {rates}  (phases: count {ph['count'] * 1e3:.1f}, host "
                  f"{ph['host'] * 1e3:.1f}, write {ph['write'] * 1e3:.1f}, draw {ph['draw'] * 1e3:.1f} ms)  "
                  f"records/packet {r['records_per_packet']:.2f}  same sums {r.get('same_sums')}  absorbed "
                  f"{r['absorbed_fraction']['counted']:.5f} +- {r['absorbed_fraction']['counted_sigma']:.5f}"
                  f" (track length {r['absorbed_fraction']['track_length']:.5f})", flush=True)
    if a.out:
        a.out.write_text(json.dumps({"device": dev.name, "backend": a.backend,
                                     "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                                     "argv": sys.argv[1:], "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
