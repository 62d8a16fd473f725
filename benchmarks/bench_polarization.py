#!/usr/bin/env python
"""The cost of polarized packets: kernel packets per ms with Stokes vectors against intensity alone.

The neb medium (uniform dust, optical depth 1 from the centre to a face, albedo 0.6, g 0.6, a
star at the centre) on n^3 voxels, traced per configuration with ``bands.polarization``
none, rayleigh, white (p_l 0.5) and mie (MRN astronomical silicate), each for the light field
alone and with a peel-off image along -z (``--image`` pixels a side), where polarized packets
also peel off Q and U (and V). Mie's grains have their own albedo 0.86 and g 0.55, so its cost
is taken against "none-mie": intensity alone with those in the Henyey-Greenstein kernel. The median
of ``--repeat`` rounds (kernels built beforehand; each round runs every kind once, in turn, and
the ratio to the reference is the median of the rounds' ratios) of the transport kernel's time
(``timings["kernel_s"]``) and of the wall time; the absorbed fractions beside them (polarization
changes the paths through the azimuths, not the absorption's expectation).

    python benchmarks/bench_polarization.py --backend cuda --grid 128 --photons 2.1e7 --out pol.json
    python benchmarks/bench_polarization.py --backend opencl --device "Portable" --grid 64 --photons 2e5
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
import warnings

import numpy as np

from nebula_rt.backends import get_backend
from nebula_rt.errors import NebulaWarning
from nebula_rt.observe.sky import Camera
from nebula_rt.optics.bands import Band
from nebula_rt.optics.mie import Grains, mie_bands
from nebula_rt.optics.polarization import Polarization
from nebula_rt.scene import Star
from nebula_rt.transport import trace

KINDS = {"none": Polarization(), "rayleigh": Polarization("rayleigh"), "white": Polarization("white", peak=0.5),
         "none-mie": Polarization(), "mie": Polarization("mie", grains=Grains())}
#: each kind's unpolarized reference: Mie's, intensity alone with the grains' albedo and g (HG)
BASE = {"mie": "none-mie"}


def _run(backend, n: int, photons: int, kind: str, image: int, method: str):
    """A function that traces one configuration and returns (kernel s, wall s, result)."""
    rho = np.ones((n, n, n), np.float32)
    bands = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
    if kind in ("mie", "none-mie"):  # MRN astronomical silicate: the grains' albedo and g (0.86, 0.55 at 550 nm)
        bands = mie_bands(bands, KINDS["mie"].grains)
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(image, image)) if image else None
    kw = dict(tau=2.0, photons=photons, backend=backend, peel=cam, polarization=KINDS[kind], method=method,
              seed=1)

    def run(count=photons):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NebulaWarning)
            t0 = time.perf_counter()
            res = trace(rho, bands, stars, **dict(kw, photons=count))
            return float(res.timings["kernel_s"]), time.perf_counter() - t0, res

    run(min(photons, 20_000))  # kernels built
    return run


def measure_all(backend, n: int, photons: int, image: int, repeat: int, method: str = "analog") -> list:
    """Every kind, ``repeat`` rounds of one run each in turn (a drift of the machine's speed
    then reaches every kind alike), each kind's median and its per-round ratio to its
    unpolarized reference (the median of the rounds' ratios)."""
    runs = {kind: _run(backend, n, photons, kind, image, method) for kind in KINDS}
    times = {kind: [] for kind in KINDS}
    last = {}
    for _ in range(repeat):
        for kind, run in runs.items():
            k, w, last[kind] = run()
            times[kind].append((k, w))
    out = []
    for kind in KINDS:
        k = statistics.median(t[0] for t in times[kind])
        base = BASE.get(kind, "none")
        ratios = [b[0] / t[0] for t, b in zip(times[kind], times[base])]
        res = last[kind]
        out.append({"grid": n, "photons": photons, "polarization": kind, "method": method, "image": image,
                    "kernel_s": k, "kernel_s_runs": [t[0] for t in times[kind]],
                    "wall_s": statistics.median(t[1] for t in times[kind]), "kernel_packets_per_ms": photons / (k * 1e3),
                    "relative_to_unpolarized": statistics.median(ratios), "reference": base,
                    "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0]),
                    "net_q_over_i": None if res.peel_stokes is None else
                    float(res.peel_stokes[0, 0].sum() / res.peel_image.sum())})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--grid", type=int, nargs="+", default=[128])
    ap.add_argument("--photons", type=float, default=2.1e7)
    ap.add_argument("--image", type=int, default=64, help="peel-off image pixels a side (0: none)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=["analog"], choices=["analog", "biased"],
                    help="transport.method: analog packets, or weighted ones (biased)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    backend = get_backend(args.backend, args.device)
    records = []
    for n, method, image in ((n, m, i) for n in args.grid for m in args.methods for i in (0, args.image)):
        for rec in measure_all(backend, n, int(args.photons), image, args.repeat, method):
            records.append(rec)
            print(f"{n}^3 {method} image {image:>4} {rec['polarization']:<9} kernel {rec['kernel_s']:.4f} s  "
                  f"{rec['kernel_packets_per_ms']:>12,.0f} pkt/ms  x{rec['relative_to_unpolarized']:.3f} "
                  f"(of {rec['reference']})  absorbed {rec['absorbed_fraction']:.5f}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"benchmark": "bench_polarization", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                       "device": backend.device_name, "host": platform.node(),
                       "command": " ".join(["benchmarks/bench_polarization.py"] + list(argv or sys.argv[1:])),
                       "records": records}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
