#!/usr/bin/env python
"""Large grids on a CUDA GPU: NebulaRT against MCX, peak memory, and the atomic-add limit.

    python benchmarks/bench_large_grids.py [--grids 64 128 256 512 1024] [--photons 1e7 1e8]
        [--bands 1 [3]] [--mcx pmcx|none] [--mcx-max-grid 1024] [--skip TOKEN ...]
        [--repeats 3] [--timeout 300] [--out FILE.json] [--dry-run]

Scene: the neb128 medium (benchmarks/bench_neb128.py) on n^3 voxels: uniform dust, optical
depth 1 from the centre to a face (dust.tau = 2 across the box, so mu_t = 2/n per voxel),
albedo 0.6, g 0.6, no reflection, an isotropic point source at the centre, 1000 scatterings
at most. The optical depth does not change with n, so the absorbed fraction is the same at
every size: MCX's figure for neb128 is 0.4078, reported beside each measurement (to 4 digits:
its rounding, up to 5e-5, is as large as the statistical error of 1e8 packets, 4.9e-5, so at 1e8
compare with MCX's own figure of the same run, ``absorbed_diff_vs_mcx``). ``--bands 3``
runs the same medium with three bands of identical optics (the memory target of three bands);
``--bands 1 3`` runs both.

Every configuration runs in its own process after a warm-up on 16^3 (kernels compiled, the
CUDA context made), so its memory peaks are its own; one that fails (out of memory, refused by
the resource check, past --timeout) is recorded with its error and the rest go on.

Per configuration (grid n, photons P per band, bands B):
  NebulaRT  Pipeline.run (colour off): the transport kernel time (light.timings["kernel_s"],
            the sum over its launches), the end-to-end wall time of Pipeline.run, packets per
            ms of kernel time (P * B packets), the absorbed fraction per band; medians of
            --repeats runs (one run once a run takes more than --repeat-below-s).
  memory    a CuPy memory hook (cupy.cuda.MemoryHook) over the runs: the peak of the pool's
            used_bytes() and total_bytes() at every allocation from the pool, and the peak of
            the driver's used memory (memGetInfo) at every cudaMalloc; the pool's total_bytes()
            after the run; the budget target 2 * (4 B + 8 B * B) * n^3 + 1 GiB and whether the
            used peak meets it; the process's peak RSS (ru_maxrss).
  MCX       pmcx in its own process (after a warm-up on 32^3) on the same medium, up to
            --mcx-max-grid: MCX's own kernel time (stat runtime, ms) and photons per ms, its
            absorbed fraction (energyabs / energytot), its wall time; NebulaRT / MCX photons
            per ms. ``mcx`` is null when pmcx does not import. The source sits at the box centre
            (issrcfrom0 = 1, srcpos n/2: bench_neb128's srcpos 64 with issrcfrom0 = 0 is the
            point 63 in MCX's 0-based grid units, one voxel off the centre along each axis).
  limit     deposits per packet ~ voxel visits per packet = 1.5 x (track length in voxel
            edges) + flights; the track length from the device sums (sum of the fixed-point
            track units / (2^FIXED_POINT_BITS n), as bench_empty_space.py and
            tests/transport/test_extremes.py convert raw_sum; cross-checked with J 4 pi V / q of band 0),
            the flights 1 + scatterings, the scatterings albedo x sigma x track (their expected
            number); limit packets per ms = (atomic walk adds per second on n^3, below) / (visits
            per packet), and NebulaRT's fraction of it. The kernel's deposits into the star's
            voxel are summed per work group (NRT_GROUP_TALLY), so the visits slightly overcount
            its global adds.

Atomic microbenchmark (its own process, CuPy RawKernels, CUDA events, median of 3 after a
warm-up; for 128^3 .. 1024^3 and every grid asked for), 64-bit unsigned atomicAdd into a
uint64 array of s^3 elements, the return value unused (a reduction, as the transport's
unchecked adds), about --micro-adds adds per size:
  random    64 adds per thread at indices from a splitmix64 hash of (thread, k), scaled to
            [0, s^3) by a 64-bit multiply-high;
  walk      photon-like: each thread starts at a hashed point in the central voxel (s/2,
            s/2, s/2), takes a hashed isotropic direction and steps voxel by voxel with a 3D DDA
            (Amanatides-Woo: next face on each axis, step across the nearest), one add per voxel
            visited, until it leaves the grid; x fastest in the index, as the transport. The
            first voxel's add goes to a per-block shared counter flushed once per block (as the
            transport's star-voxel sum), the visits are counted per block and added once.
The figures are G adds per second (all adds, shared included); the sum of each array is checked
against the adds made.

--skip takes tokens: ``micro`` (no microbenchmark), ``mcx`` (no MCX), or fields joined by
``-`` that a configuration must all match to be skipped: ``n1024`` (grid), ``p1e8`` (photons),
``b3`` (bands); e.g. ``--skip n1024-p1e8-b3 micro``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib.util
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
#: MCX's absorbed fraction of neb128 (REFERENCES.md), the same at every grid size here
EXPECTED_ABSORBED = 0.4078
ALBEDO, G, TAU = 0.6, 0.6, 2.0
GIB = 2**30
DEFAULT_GRIDS = [64, 128, 256, 512, 1024]
DEFAULT_PHOTONS = [1e7, 1e8]
MICRO_SIZES = [128, 256, 512, 1024]
#: E[(|dx| + |dy| + |dz|) / max |d|] over isotropic directions: voxel faces crossed per (n/2)
#: of a walk from the centre (Monte Carlo, 2e6 directions); sizes the walk benchmark's launch
WALK_CROSSINGS_PER_HALF_EDGE = 1.851


# --------------------------------------------------------------------------------------------
# scene
def scene_dict(n: int, photons: int, n_bands: int) -> dict:
    names = ["V"] if n_bands == 1 else [f"V{i}" for i in range(n_bands)]
    bands = [{"name": nm, "wavelength": 550.0 + 10.0 * i, "extinction": 1.0, "albedo": ALBEDO, "g": G}
             for i, nm in enumerate(names)]
    return {
        "grid": {"shape": [n, n, n]},
        "dust": {"model": "uniform", "density": 1.0, "floor": 0.0, "tau": TAU},
        # no dust bump (the scene default's r = 0.01 is MCX-less extra dust at the source:
        # absorbed 0.4100 against 0.4083 without it at 256^3, benchmarks/results/h200-2026-12-04h/)
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0, "bump_radius": 0.0}],
        "bands": {"list": bands},
        "transport": {"photons": int(photons), "max_scatterings": 1000, "seed": 1, "backend": "cuda",
                      "batch_size": _batch_size_from_env(),
                      "error_estimate": os.environ.get("NRT_BENCH_ERROR_ESTIMATE", "auto")},
    }


def _batch_size_from_env() -> int:
    """``--batch-size`` (passed to the child processes as NRT_BENCH_BATCH_SIZE; 0 automatic)."""
    return int(float(os.environ.get("NRT_BENCH_BATCH_SIZE", "0")))


def budget_target(n: int, n_bands: int) -> int:
    """The device-memory target: twice (4 B density + 8 B per band) per voxel, plus 1 GiB."""
    return 2 * (4 + 8 * n_bands) * n**3 + GIB


# --------------------------------------------------------------------------------------------
# child: one NebulaRT configuration
def _peak_hook(cp, pool):
    class PeakHook(cp.cuda.MemoryHook):
        """Peak of the pool's used and total bytes at every pool allocation, and of the
        driver's used memory at every cudaMalloc."""

        name = "bench_large_grids_peak"

        def __init__(self):
            self.used = int(pool.used_bytes())
            self.total = int(pool.total_bytes())
            free, tot = cp.cuda.runtime.memGetInfo()
            self.driver = int(tot - free)

        def malloc_postprocess(self, **kwargs):
            self.used = max(self.used, int(pool.used_bytes()))
            self.total = max(self.total, int(pool.total_bytes()))

        def alloc_postprocess(self, **kwargs):
            free, tot = cp.cuda.runtime.memGetInfo()
            self.driver = max(self.driver, int(tot - free))

    return PeakHook()


def _tuning_from_env() -> dict:
    """Transport kernel options (``--tuning KEY=VALUE ...``, passed to the child processes as
    NRT_BENCH_TUNING) overriding the backend's defaults."""
    import os

    text = os.environ.get("NRT_BENCH_TUNING", "").strip()
    return {k: int(v) for k, v in (item.split("=", 1) for item in text.split())} if text else {}


def _build_kernels(backend, n: int, photons: int, n_bands: int) -> None:
    """Build the transport kernels of the measured configuration before timing it: their
    options depend on the grid and the batch size (sorted order from 512^3, unchecked adds
    while no cell can wrap), so the 16^3 warm-up may not have built them, and a build inside
    the measured run (up to 1 s per option set) would be counted in its end-to-end time."""
    import numpy as np

    from nebula_rt.optics.bands import Band
    from nebula_rt.scene import Star
    from nebula_rt.transport import TransportRequest
    from nebula_rt.transport.plan import plan_transport

    bands = [Band(name=f"b{i}", wavelength=450.0 + 100.0 * i, extinction=1.0, albedo=ALBEDO, g=G)
             for i in range(n_bands)]
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
    request = TransportRequest(bands=tuple(bands), stars=tuple(stars), tau=TAU, photons=int(photons),
                               method="analog", batch_size=_batch_size_from_env(),
                               error_estimate=os.environ.get("NRT_BENCH_ERROR_ESTIMATE", "auto"))
    plan = plan_transport(np.ones((n, n, n), np.float32), request, backend)
    backend.transport_session(plan.setup, plan.launches.slots, plan.launches.bands_per_launch).close()


def _watch_region_passes() -> list:
    """Give every transport session a pass log (transport by regions; the tail pass is then
    waited for, a few microseconds per launch); returns the list the sessions are appended to."""
    from nebula_rt.backends.session import DeviceTransport

    sessions = []
    init = DeviceTransport.__init__

    def watched(self, *a, **k):
        init(self, *a, **k)
        self.region_log = []
        sessions.append(self)

    DeviceTransport.__init__ = watched
    return sessions


def _region_summary(sessions) -> dict | None:
    """The last run's passes: how many, the packets they stopped (region crossings), the time
    in region passes and in tail passes, and the first group's passes one by one
    (``launch_parts``: the streams that ended in a tail pass, one per group of batches)."""
    s = sessions[-1] if sessions else None
    if s is None or not s.region_shift:
        return None
    log = s.region_log
    region = [e for e in log if e[3] != 31]
    tail = [e for e in log if e[3] == 31]
    first, launches = [], sum(1 for e in log if e[3] == 31) or 1
    for e in log:
        first.append({"in": e[0], "new": e[4], "stopped": e[1], "ms": round(e[2] * 1e3, 3)})
        if e[3] == 31 or e[1] == 0:
            break
    return {"shift": s.region_shift, "capacity": s.region_capacity, "tail_below": s.region_tail,
            "passes": len(log), "launch_parts": launches, "crossings": int(sum(e[1] for e in log)),
            "region_pass_s": float(sum(e[2] for e in region)), "tail_pass_s": float(sum(e[2] for e in tail)),
            "first_part": first}


def child_nebula(n: int, photons: int, n_bands: int, repeats: int, repeat_below_s: float) -> dict:
    import resource

    import cupy as cp
    import numpy as np

    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene
    from nebula_rt.transport.plan import FIXED_POINT_BITS

    tuning = _tuning_from_env()
    if tuning:
        from nebula_rt.backends.cuda import CUDABackend

        backend = CUDABackend("", transport_tuning=tuning)
    else:
        backend = get_backend("cuda", "")
    Pipeline(backend).run(Scene.from_dict(scene_dict(16, 10_000, n_bands)), colour=False)  # compile, warm up
    sessions = _watch_region_passes()
    scene = Scene.from_dict(scene_dict(n, photons, n_bands))
    _build_kernels(backend, n, photons, n_bands)
    pool = cp.get_default_memory_pool()
    pool.free_all_blocks()
    cp.cuda.Device().synchronize()
    base_used = int(pool.used_bytes())
    free0, total_dev = cp.cuda.runtime.memGetInfo()
    hook = _peak_hook(cp, pool)
    runs = []
    pool_total_after = []  # the pool's total_bytes() after each run
    light = None
    with hook:
        for _ in range(max(1, repeats)):
            light = None  # the previous run's arrays go before the next run allocates
            t0 = time.perf_counter()
            light = Pipeline(backend).run(scene, colour=False)
            cp.cuda.Device().synchronize()
            wall = time.perf_counter() - t0
            runs.append((wall, float(light.timings["kernel_s"])))
            pool_total_after.append(int(pool.total_bytes()))
            if wall > repeat_below_s:
                break

    tr = light.transport
    counts = np.asarray(tr.counts, np.int64)
    packets = photons * n_bands
    kernel_s = statistics.median(r[1] for r in runs)
    wall_s = statistics.median(r[0] for r in runs)
    absorbed = [float(counts[b, 1]) / photons for b in range(n_bands)]

    # track length per band, box units: device sums (fixed point, 2^32 units per voxel edge)
    nvox = n**3
    scale = 2.0**FIXED_POINT_BITS * n
    ds = tr.device_sums
    packets_estimate = tr.batches == photons and photons > 1  # its own fixed point: from J
    if ds is not None and type(ds.sum1).__module__.startswith("cupy") and not packets_estimate:
        s1 = ds.sum1.reshape(n_bands, nvox)
        track = [float(s1[b].sum()) / scale for b in range(n_bands)]
        track_source = "device sums / (2^FIXED_POINT_BITS n)"
    else:
        track = [float(np.sum(light.J[b], dtype=np.float64)) * 4.0 * math.pi / nvox / float(tr.packet_energy[b])
                 for b in range(n_bands)]
        track_source = "J 4 pi V / q"
    # cross-check with J (float32 on the host): track = J 4 pi V / q, band 0
    track_j0 = float(np.sum(light.J[0], dtype=np.float64)) * 4.0 * math.pi / nvox / float(tr.packet_energy[0])
    sigma = TAU * 1.0  # extinction per box unit at density 1
    per_band = []
    for b in range(n_bands):
        edges = track[b] * n / photons  # path per packet in voxel edges
        scatterings = ALBEDO * sigma * track[b] / photons  # expected scatterings per packet
        flights = 1.0 + scatterings
        per_band.append({
            "absorbed_fraction": absorbed[b],
            "track_box_units": track[b],
            "path_voxel_edges_per_packet": edges,
            "scatterings_per_packet": scatterings,
            "scatterings_per_packet_from_absorbed": absorbed[b] * ALBEDO / (1.0 - ALBEDO),
            "flights_per_packet": flights,
            "voxel_visits_per_packet": 1.5 * edges + flights,
            "terminated": int(counts[b, 3]),
        })
    visits = statistics.fmean(p["voxel_visits_per_packet"] for p in per_band)
    p_abs = statistics.fmean(absorbed)
    target = budget_target(n, n_bands)
    out = {
        "device": backend.device_name,
        "kernel_s": kernel_s,
        "end_to_end_s": wall_s,
        "runs": [{"end_to_end_s": w, "kernel_s": k} for w, k in runs],
        "kernel_packets_per_ms": packets / (kernel_s * 1e3),
        "kernel_photons_per_ms_per_band": photons / (kernel_s * 1e3),
        "absorbed_fraction": p_abs,
        "absorbed_fraction_per_band": absorbed,
        "absorbed_sigma": math.sqrt(p_abs * (1 - p_abs) / packets),
        "absorbed_expected": EXPECTED_ABSORBED,
        "absorbed_z_vs_expected": (p_abs - EXPECTED_ABSORBED) / math.sqrt(p_abs * (1 - p_abs) / packets),
        "batches": int(tr.batches),
        "error_estimate": "packets" if packets_estimate else "batches",
        "timings": {k: float(v) for k, v in light.timings.items()},
        "track_source": track_source,
        "track_box_units_band0_from_J": track_j0,
        "per_band": per_band,
        "voxel_visits_per_packet": visits,
        "region_passes": _region_summary(sessions),
        "memory": {
            "pool_used_peak_bytes": hook.used,
            "pool_used_before_bytes": base_used,
            "pool_total_peak_bytes": hook.total,
            "pool_total_after_run_bytes": pool_total_after[0],
            "pool_total_after_each_run_bytes": pool_total_after,
            "driver_used_peak_bytes": hook.driver,
            "driver_used_before_bytes": int(total_dev - free0),
            "device_total_bytes": int(total_dev),
            "nebula_reported": {k: int(v) for k, v in light.memory.items()},
            "transport_device_bytes": int(tr.device_bytes),
            "budget_target_bytes": target,
            "budget_target_rule": "2 * (4 B density + 8 B per band) * voxels + 1 GiB",
            "budget_met": bool(hook.used <= target),
            "host_peak_rss_bytes": int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024,
        },
    }
    return out


# --------------------------------------------------------------------------------------------
# child: one MCX configuration
def mcx_scene(n: int, photons: int) -> dict:
    """bench_neb128's MCX configuration on n^3 voxels: mu_t = tau / n per voxel (unitinmm 1),
    mu_a = (1 - albedo) mu_t, mu_s = albedo mu_t, source at the box centre."""
    sys.path.insert(0, str(HERE))
    from bench_neb128 import mcx_config

    import numpy as np

    cfg = mcx_config(photons)
    mu_t = TAU / n
    cfg.update(vol=np.ones([n] * 3, "uint8"), srcpos=[n / 2.0] * 3, issrcfrom0=1,
               prop=[[0, 0, 1, 1], [(1.0 - ALBEDO) * mu_t, ALBEDO * mu_t, G, 1.0]])
    return cfg


def child_mcx(n: int, photons: int, repeats: int) -> dict:
    import resource

    try:
        import pmcx
    except Exception as exc:  # not installed, or its CUDA runtime does not load
        return {"mcx": None, "reason": f"pmcx does not import: {exc}"}
    pmcx.run(mcx_scene(32, 10_000))  # first call: the driver JIT-compiles MCX's PTX
    runs = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = pmcx.run(mcx_scene(n, photons))
        wall = time.perf_counter() - t0
        stat = {k: (float(v) if isinstance(v, (int, float)) else None) for k, v in res.get("stat", {}).items()}
        del res
        runs.append((stat.get("runtime") or 0.0, wall, stat))
    runs.sort(key=lambda r: r[0])
    runtime, wall, stat = runs[len(runs) // 2]
    e_abs, e_tot = stat.get("energyabs"), stat.get("energytot")
    return {"mcx": {
        "code": "pmcx", "version": getattr(pmcx, "__version__", None),
        "kernel_ms": runtime, "photons_per_ms": photons / runtime if runtime > 0 else None,
        "end_to_end_s": wall, "absorbed_fraction": (e_abs / e_tot) if e_abs is not None and e_tot else None,
        "repeats": len(runs), "stat": stat,
        "host_peak_rss_bytes": int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024,
    }}


# --------------------------------------------------------------------------------------------
# child: the atomic microbenchmark
ATOMIC_SRC = r"""
typedef unsigned long long u64;

__device__ __forceinline__ u64 mix64(u64 z)
{
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

/* per_thread adds of 1 at hashed indices in [0, size) */
extern "C" __global__ void random_adds(u64 *acc, u64 size, unsigned int per_thread, u64 threads, u64 seed)
{
    u64 t = (u64)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= threads)
        return;
    u64 key = seed + t * (u64)per_thread * 0x9E3779B97F4A7C15ULL;
    for (unsigned int k = 0; k < per_thread; ++k) {
        u64 h = mix64(key + (u64)k * 0x9E3779B97F4A7C15ULL);
        atomicAdd(&acc[__umul64hi(h, size)], 1ULL);
    }
}

/* one photon-like walk per thread from the central voxel to the grid's edge, one add per
   voxel visited (3D DDA); the first voxel's adds summed per block in shared memory */
extern "C" __global__ void walk_adds(u64 *acc, int n, u64 threads, u64 seed, u64 *visits)
{
    __shared__ u64 hot, count;
    if (threadIdx.x == 0) {
        hot = 0;
        count = 0;
    }
    __syncthreads();
    u64 t = (u64)blockIdx.x * blockDim.x + threadIdx.x;
    if (t < threads) {
        const float inv24 = 1.0f / 16777216.0f;
        const float inf = __int_as_float(0x7f800000);
        u64 h1 = mix64(seed + (2 * t + 1) * 0x9E3779B97F4A7C15ULL);
        u64 h2 = mix64(h1 ^ 0xD1B54A32D192ED03ULL);
        float cz = 2.0f * (float)(h1 >> 40) * inv24 - 1.0f;
        float sz = sqrtf(fmaxf(0.0f, 1.0f - cz * cz));
        float s, c;
        sincospif(2.0f * (float)((h1 >> 16) & 0xFFFFFF) * inv24, &s, &c);
        float dx = sz * c, dy = sz * s, dz = cz;
        /* start inside the central voxel: fractions of its edge */
        float fx = (float)(h2 >> 40) * inv24, fy = (float)((h2 >> 16) & 0xFFFFFF) * inv24;
        float fz = (float)(h2 & 0xFFFF) * (1.0f / 65536.0f);
        int ix = n / 2, iy = n / 2, iz = n / 2;
        int sx = dx > 0.0f ? 1 : -1, sy = dy > 0.0f ? 1 : -1, sgz = dz > 0.0f ? 1 : -1;
        float tdx = dx != 0.0f ? fabsf(1.0f / dx) : inf;
        float tdy = dy != 0.0f ? fabsf(1.0f / dy) : inf;
        float tdz = dz != 0.0f ? fabsf(1.0f / dz) : inf;
        float tmx = dx != 0.0f ? (dx > 0.0f ? 1.0f - fx : fx) * tdx : inf;
        float tmy = dy != 0.0f ? (dy > 0.0f ? 1.0f - fy : fy) * tdy : inf;
        float tmz = dz != 0.0f ? (dz > 0.0f ? 1.0f - fz : fz) * tdz : inf;
        const u64 nn = (u64)n;
        u64 steps = 1;
        atomicAdd(&hot, 1ULL);
        for (;;) {
            if (tmx <= tmy && tmx <= tmz) {
                ix += sx;
                tmx += tdx;
                if ((unsigned)ix >= (unsigned)n)
                    break;
            } else if (tmy <= tmz) {
                iy += sy;
                tmy += tdy;
                if ((unsigned)iy >= (unsigned)n)
                    break;
            } else {
                iz += sgz;
                tmz += tdz;
                if ((unsigned)iz >= (unsigned)n)
                    break;
            }
            atomicAdd(&acc[(u64)ix + nn * ((u64)iy + nn * (u64)iz)], 1ULL);
            ++steps;
        }
        atomicAdd(&count, steps);
    }
    __syncthreads();
    if (threadIdx.x == 0) {
        u64 c0 = (u64)(n / 2);
        atomicAdd(&acc[c0 + (u64)n * (c0 + (u64)n * c0)], hot);
        atomicAdd(visits, count);
    }
}
"""


def _time_kernel(cp, launch, repeats: int = 3) -> tuple[float, list]:
    """Median seconds of ``launch()`` over ``repeats`` timed runs after one warm-up, by CUDA
    events."""
    launch()
    cp.cuda.Device().synchronize()
    times = []
    for _ in range(repeats):
        a, b = cp.cuda.Event(), cp.cuda.Event()
        a.record()
        launch()
        b.record()
        b.synchronize()
        times.append(cp.cuda.get_elapsed_time(a, b) * 1e-3)
    return statistics.median(times), times


def child_micro(sizes, target_adds: int) -> dict:
    import cupy as cp
    import numpy as np

    mod = cp.RawModule(code=ATOMIC_SRC, options=("--std=c++14",))
    k_random, k_walk = mod.get_function("random_adds"), mod.get_function("walk_adds")
    props = cp.cuda.runtime.getDeviceProperties(cp.cuda.Device().id)
    block = 256
    rows = []
    pool = cp.get_default_memory_pool()
    for s in sizes:
        size = s**3
        row = {"size": s, "elements": size, "bytes": 8 * size}
        try:
            acc = cp.zeros(size, cp.uint64)
            # (a) random adds
            per = 64
            threads = max(1, target_adds // per)
            args = (acc, np.uint64(size), np.uint32(per), np.uint64(threads), np.uint64(12345))
            sec, times = _time_kernel(cp, lambda: k_random(((threads + block - 1) // block,), (block,), args))
            adds = threads * per
            ok = int(acc.sum()) == adds * (1 + len(times))
            row["random"] = {"adds": adds, "seconds": sec, "times_s": times, "G_adds_per_s": adds / sec / 1e9,
                             "sum_check": bool(ok)}
            # (b) photon-like walks
            acc.fill(0)
            visits = cp.zeros(1, cp.uint64)
            threads = max(1, int(target_adds / (1.0 + WALK_CROSSINGS_PER_HALF_EDGE * s / 2)))
            wargs = (acc, np.int32(s), np.uint64(threads), np.uint64(777), visits)
            sec, times = _time_kernel(cp, lambda: k_walk(((threads + block - 1) // block,), (block,), wargs))
            total = int(visits.get()[0])
            adds = total // (1 + len(times))
            ok = int(acc.sum()) == total and total % (1 + len(times)) == 0
            row["walk"] = {"threads": threads, "adds": adds, "adds_per_walk": adds / threads, "seconds": sec,
                           "times_s": times, "G_adds_per_s": adds / sec / 1e9, "sum_check": bool(ok)}
        except Exception as exc:  # out of memory at the largest sizes
            row["error"] = f"{type(exc).__name__}: {exc}"[:400]
        acc = visits = None
        pool.free_all_blocks()
        rows.append(row)
    return {"device": f"CUDA: {props['name'].decode()}", "block": block, "target_adds_per_size": target_adds,
            "rows": rows,
            "method": ("64-bit atomicAdd(unsigned long long), return value unused; random: 64 adds per thread "
                       "at splitmix64-hashed indices; walk: a 3D DDA from a hashed point of the central voxel "
                       "in a hashed isotropic direction, one add per voxel visited until the walk leaves the "
                       "grid, the first voxel's adds summed per block in shared memory; CUDA events, median "
                       "of 3 after a warm-up")}


# --------------------------------------------------------------------------------------------
# parent
def _fmt_p(p: float) -> str:
    e = int(math.floor(math.log10(p))) if p > 0 else 0
    m = p / 10**e
    return f"{m:g}e{e}"


def label(n: int, p: int, b: int) -> str:
    return f"n{n}-p{_fmt_p(p)}-b{b}"


def skipped(token_set, n: int, p: int, b: int) -> bool:
    fields = set(label(n, p, b).split("-"))
    for tok in token_set:
        parts = [t for t in tok.lower().split("-") if t]
        norm = set()
        for t in parts:
            if t.startswith("p"):
                try:
                    t = "p" + _fmt_p(float(t[1:]))
                except ValueError:
                    pass
            norm.add(t)
        if norm and norm <= fields:
            return True
    return False


def plan(args) -> list[dict]:
    out = []
    for n in args.grids:
        for p in (int(x) for x in args.photons):
            for b in args.bands:
                out.append({"grid": n, "photons": p, "bands": b, "label": label(n, p, b),
                            "skip": skipped(args.skip, n, p, b),
                            "mcx": (args.mcx != "none" and "mcx" not in args.skip and n <= args.mcx_max_grid),
                            "budget_target_bytes": budget_target(n, b)})
    return out


def _child(argv: list, timeout: float) -> tuple[dict | None, str | None, float]:
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve())] + argv, capture_output=True,
                              text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, f"timeout: killed after {timeout:g} s", time.perf_counter() - t0
    line = next((l for l in proc.stdout.splitlines() if l.startswith("RESULT")), None)
    if line is None:
        tail = [l for l in proc.stderr.strip().splitlines() if l.strip()] or ["(no output)"]
        return None, f"exit {proc.returncode}: {tail[-1][:400]}", time.perf_counter() - t0
    return json.loads(line[len("RESULT"):]), None, time.perf_counter() - t0


def _gib(x) -> str:
    return "-" if x is None else f"{x / GIB:.2f}"


def _num(x, fmt="{:,.0f}") -> str:
    return "-" if x is None else fmt.format(x)


def print_row(r: dict) -> None:
    head = f"{r['grid']:5d}^3 {r['bands']}b {r['photons']:>11,d}"
    if r.get("skipped"):
        print(f"{head}  skipped", flush=True)
        return
    neb = r.get("nebula")
    if neb is None:
        print(f"{head}  NebulaRT FAILED: {r.get('nebula_error')}", flush=True)
    else:
        m = neb["memory"]
        lim = r.get("limit") or {}
        print(f"{head}  kernel {neb['kernel_s']:8.3f} s  e2e {neb['end_to_end_s']:8.3f} s  "
              f"{neb['kernel_packets_per_ms']:>9,.0f} pkt/ms  abs {neb['absorbed_fraction']:.5f} (exp {EXPECTED_ABSORBED})  "
              f"peak {_gib(m['pool_used_peak_bytes'])} GiB / target {_gib(m['budget_target_bytes'])} GiB "
              f"{'met' if m['budget_met'] else 'NOT met'}  pool total {_gib(m['pool_total_peak_bytes'])} GiB  "
              f"RSS {_gib(m['host_peak_rss_bytes'])} GiB  visits/pkt {neb['voxel_visits_per_packet']:.1f}  "
              f"limit {_num(lim.get('limit_packets_per_ms'))} pkt/ms  frac {_num(lim.get('fraction_of_limit'), '{:.3f}')}",
              flush=True)
        rp = neb.get("region_passes")
        if rp:
            print(f"{'':22s}  regions 2^{rp['shift']}: {rp['passes']} passes, {rp['launch_parts']} ending in a tail pass, "
                  f"{rp['crossings'] / max(neb['kernel_packets_per_ms'] * neb['kernel_s'] * 1e3, 1):.2f} stops/packet, "
                  f"region passes {rp['region_pass_s']:.3f} s, tail passes {rp['tail_pass_s']:.3f} s; first part "
                  + " ".join(f"{e['in']}>{e['stopped']}:{e['ms']:.1f}" for e in rp["first_part"]), flush=True)
    mcx = r.get("mcx")
    if mcx:
        print(f"{'':22s}  MCX kernel {mcx['kernel_ms'] / 1e3:8.3f} s  e2e {mcx['end_to_end_s']:8.3f} s  "
              f"{_num(mcx['photons_per_ms'])} ph/ms  abs {_num(mcx['absorbed_fraction'], '{:.5f}')}  "
              f"NebulaRT/MCX {_num(r.get('ratio_vs_mcx'), '{:.3f}')}", flush=True)
    elif r.get("mcx_error"):
        print(f"{'':22s}  MCX: {r['mcx_error']}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", type=int, nargs="+", default=DEFAULT_GRIDS, help="grid sizes n (n^3 voxels)")
    ap.add_argument("--photons", type=float, nargs="+", default=DEFAULT_PHOTONS, help="packets per band")
    ap.add_argument("--bands", type=int, nargs="+", choices=(1, 3), default=[1],
                    help="1: one band; 3: three bands of identical optics; both: '1 3'")
    ap.add_argument("--mcx", default="pmcx", choices=("pmcx", "none"))
    ap.add_argument("--mcx-max-grid", type=int, default=1024, help="largest grid MCX runs on")
    ap.add_argument("--mcx-repeats", type=int, default=1, help="MCX runs per configuration (median by kernel time)")
    ap.add_argument("--repeats", type=int, default=3, help="NebulaRT runs per configuration (medians)")
    ap.add_argument("--repeat-below-s", type=float, default=2.0,
                    help="no further NebulaRT run once one took longer than this (s)")
    ap.add_argument("--skip", nargs="*", default=[], help="micro, mcx, or configuration fields (see above)")
    ap.add_argument("--micro-sizes", type=int, nargs="+", default=None,
                    help="array sizes s (s^3 elements) of the microbenchmark (default 128 256 512 1024 and --grids)")
    ap.add_argument("--micro-adds", type=float, default=2.0**30, help="adds per size and kind")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per child process")
    ap.add_argument("--tuning", nargs="*", default=[], metavar="KEY=VALUE",
                    help="transport kernel options for NebulaRT, e.g. NRT_SORTED=1 (base.TRANSPORT_TUNING)")
    ap.add_argument("--batch-size", type=float, default=0,
                    help="transport.batch_size of every configuration (0: automatic)")
    ap.add_argument("--error-estimate", default="auto", choices=("auto", "batches", "packets"),
                    help="transport.error_estimate of every configuration")
    ap.add_argument("--out", default=None)
    ap.add_argument("--dry-run", action="store_true", help="print the configurations and exit")
    ap.add_argument("--child-nebula", nargs=3, type=float, help=argparse.SUPPRESS)
    ap.add_argument("--child-mcx", nargs=2, type=float, help=argparse.SUPPRESS)
    ap.add_argument("--child-micro", type=int, nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.skip = [s.lower() for s in args.skip]
    if not (args.child_nebula or args.child_mcx or args.child_micro):  # the children read it
        os.environ["NRT_BENCH_ERROR_ESTIMATE"] = args.error_estimate
    if args.batch_size:  # the children read it
        os.environ["NRT_BENCH_BATCH_SIZE"] = str(int(args.batch_size))
    if args.tuning:  # the children read it
        os.environ["NRT_BENCH_TUNING"] = " ".join(args.tuning)

    if args.child_nebula:
        n, p, b = (int(x) for x in args.child_nebula)
        print("RESULT" + json.dumps(child_nebula(n, p, b, args.repeats, args.repeat_below_s)), flush=True)
        return 0
    if args.child_mcx:
        n, p = (int(x) for x in args.child_mcx)
        print("RESULT" + json.dumps(child_mcx(n, p, args.mcx_repeats)), flush=True)
        return 0
    if args.child_micro:
        print("RESULT" + json.dumps(child_micro(args.child_micro, int(args.micro_adds))), flush=True)
        return 0

    configs = plan(args)
    micro_sizes = args.micro_sizes or sorted(set(MICRO_SIZES) | set(args.grids))
    run_micro = "micro" not in args.skip
    if args.dry_run:
        print(f"microbenchmark: {'sizes ' + ' '.join(f'{s}^3' for s in micro_sizes) if run_micro else 'skipped'}"
              f" ({int(args.micro_adds):,d} adds per size and kind)")
        for c in configs:
            print(f"{c['label']:18s} {c['grid']:5d}^3 {c['bands']} band(s) {c['photons']:>12,d} photons/band  "
                  f"MCX {'yes' if c['mcx'] and not c['skip'] else 'no '}  "
                  f"target {c['budget_target_bytes'] / GIB:7.2f} GiB{'  SKIPPED' if c['skip'] else ''}")
        return 0

    from provenance import provenance  # benchmarks/provenance.py

    t_start = time.perf_counter()
    result = {"benchmark": "large_grids", "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
              **provenance(), "tuning": args.tuning, "batch_size": int(args.batch_size),
              "error_estimate": args.error_estimate, "command": " ".join(["benchmarks/bench_large_grids.py"] + (argv or sys.argv[1:])),
              "scene": {"dust_tau_across_box": TAU, "optical_depth_centre_to_face": TAU / 2, "albedo": ALBEDO,
                        "g": G, "max_scatterings": 1000, "source": "isotropic point at the box centre"},
              "absorbed_expected": EXPECTED_ABSORBED, "budget_target_rule": "2 * (4 B + 8 B * bands) * voxels + 1 GiB",
              "limit_rule": ("voxel visits per packet = 1.5 * path in voxel edges + flights (1 + albedo * sigma * "
                             "track per packet); limit packets/ms = walk G adds/s on the same grid / visits"),
              "microbenchmark": None, "configs": []}

    def save():
        result["elapsed_s"] = time.perf_counter() - t_start
        if args.out:
            tmp = Path(args.out + ".tmp")
            tmp.write_text(json.dumps(result, indent=2) + "\n")
            tmp.replace(args.out)

    walk = {}
    if run_micro:
        res, err, dt = _child(["--child-micro"] + [str(s) for s in micro_sizes]
                              + ["--micro-adds", str(int(args.micro_adds))], args.timeout)
        if res is None:
            result["microbenchmark"] = {"error": err}
            print(f"microbenchmark FAILED: {err}", flush=True)
        else:
            result["microbenchmark"] = res
            print(f"atomic adds on {res['device']} (G adds/s):", flush=True)
            for row in res["rows"]:
                if "error" in row:
                    print(f"  {row['size']:5d}^3  FAILED: {row['error']}", flush=True)
                    continue
                walk[row["size"]] = row["walk"]["G_adds_per_s"]
                print(f"  {row['size']:5d}^3 ({row['bytes'] / GIB:6.2f} GiB)  random {row['random']['G_adds_per_s']:7.2f}"
                      f"  walk {row['walk']['G_adds_per_s']:7.2f} ({row['walk']['adds_per_walk']:.0f} adds per walk)"
                      f"  checks {row['random']['sum_check'] and row['walk']['sum_check']}", flush=True)
        save()

    mcx_ok = args.mcx != "none" and "mcx" not in args.skip
    mcx_missing = None
    if mcx_ok and importlib.util.find_spec(args.mcx) is None:
        mcx_missing = f"{args.mcx} is not importable"
    mcx_cache: dict = {}
    for c in configs:
        n, p, b = c["grid"], c["photons"], c["bands"]
        rec = {"grid": n, "photons": p, "bands": b, "label": c["label"], "absorbed_expected": EXPECTED_ABSORBED,
               "budget_target_bytes": c["budget_target_bytes"]}
        result["configs"].append(rec)
        if c["skip"]:
            rec["skipped"] = True
            print_row(rec)
            save()
            continue
        neb, err, dt = _child(["--child-nebula", str(n), str(p), str(b), "--repeats", str(args.repeats),
                               "--repeat-below-s", str(args.repeat_below_s)], args.timeout)
        rec["nebula"] = neb
        rec["nebula_process_s"] = dt
        if err:
            rec["nebula_error"] = err
        # MCX: once per (grid, photons), shared by the band variants
        rec["mcx"] = None
        if c["mcx"]:
            if mcx_missing:
                rec["mcx_error"] = mcx_missing
            else:
                if (n, p) not in mcx_cache:
                    res, merr, mdt = _child(["--child-mcx", str(n), str(p), "--mcx-repeats", str(args.mcx_repeats)],
                                            args.timeout)
                    mcx_cache[(n, p)] = (None, merr) if res is None else (res.get("mcx"), res.get("reason"))
                    if res is not None and res.get("mcx") is None:
                        mcx_missing = res.get("reason")  # pmcx does not import: no more tries
                rec["mcx"], merr = mcx_cache[(n, p)]
                if merr:
                    rec["mcx_error"] = merr
        if neb is not None:
            mcx = rec["mcx"]
            rec["ratio_vs_mcx"] = (neb["kernel_packets_per_ms"] / mcx["photons_per_ms"]
                                   if mcx and mcx.get("photons_per_ms") else None)
            if mcx and mcx.get("absorbed_fraction") is not None:
                # MCX's absorbed fraction is weight-based; its noise is not included in the z
                rec["absorbed_diff_vs_mcx"] = neb["absorbed_fraction"] - mcx["absorbed_fraction"]
                rec["absorbed_z_vs_mcx"] = rec["absorbed_diff_vs_mcx"] / neb["absorbed_sigma"]
            g = walk.get(n)
            visits = neb["voxel_visits_per_packet"]
            if g is not None and visits > 0:
                limit = g * 1e9 / visits / 1e3
                rec["limit"] = {"walk_G_adds_per_s": g, "voxel_visits_per_packet": visits,
                                "limit_packets_per_ms": limit,
                                "fraction_of_limit": neb["kernel_packets_per_ms"] / limit}
            else:
                rec["limit"] = None
        print_row(rec)
        save()
    result["elapsed_s"] = time.perf_counter() - t_start
    save()
    print(f"done in {result['elapsed_s']:.0f} s" + (f"; saved {args.out}" if args.out else ""), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
