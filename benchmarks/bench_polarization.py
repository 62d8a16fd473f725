#!/usr/bin/env python
"""The cost of polarized packets: kernel packets per ms with Stokes vectors against intensity alone.

The neb medium (uniform dust, optical depth 1 from the centre to a face, albedo 0.6, g 0.6, a
star at the centre) on n^3 voxels, traced four ways per configuration: ``bands.polarization``
none, rayleigh, white (p_l 0.5) and mie (MRN astronomical silicate, whose own albedo 0.86 and
g 0.55 change the paths too), each for the light field alone and with a peel-off image along
-z (``--image`` pixels a side), where polarized packets also peel off Q and U (and V). The median
of ``--repeat`` runs (kernels built beforehand) of the transport kernel's time
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
         "mie": Polarization("mie", grains=Grains())}


def measure(backend, n: int, photons: int, kind: str, image: int, repeat: int, method: str = "analog") -> dict:
    rho = np.ones((n, n, n), np.float32)
    bands = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
    if kind == "mie":  # MRN astronomical silicate: the grains' own albedo and g (0.86, 0.55 at 550 nm)
        bands = mie_bands(bands, KINDS[kind].grains)
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(image, image)) if image else None
    kw = dict(tau=2.0, photons=photons, backend=backend, peel=cam, polarization=KINDS[kind], method=method,
              seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        trace(rho, bands, stars, **dict(kw, photons=min(photons, 20_000)))  # kernels built
        kernel, wall, res = [], [], None
        for _ in range(repeat):
            t0 = time.perf_counter()
            res = trace(rho, bands, stars, **kw)
            wall.append(time.perf_counter() - t0)
            kernel.append(float(res.timings["kernel_s"]))
    k = statistics.median(kernel)
    return {"grid": n, "photons": photons, "polarization": kind, "method": method, "image": image, "kernel_s": k,
            "wall_s": statistics.median(wall), "kernel_packets_per_ms": photons / (k * 1e3),
            "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0]),
            "net_q_over_i": None if res.peel_stokes is None else float(res.peel_stokes[0, 0].sum() / res.peel_image.sum())}


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
        base = None
        for kind in KINDS:
            rec = measure(backend, n, int(args.photons), kind, image, args.repeat, method)
            base = base or rec["kernel_packets_per_ms"]
            rec["relative_to_unpolarized"] = rec["kernel_packets_per_ms"] / base
            records.append(rec)
            print(f"{n}^3 {method} image {image:>4} {kind:<9} kernel {rec['kernel_s']:.4f} s  "
                  f"{rec['kernel_packets_per_ms']:>12,.0f} pkt/ms  x{rec['relative_to_unpolarized']:.3f}  "
                  f"absorbed {rec['absorbed_fraction']:.5f}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"benchmark": "bench_polarization", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                       "device": backend.device_name, "host": platform.node(),
                       "command": " ".join(["benchmarks/bench_polarization.py"] + list(argv or sys.argv[1:])),
                       "records": records}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
