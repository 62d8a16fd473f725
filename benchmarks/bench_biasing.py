"""Analog against biased transport: figure of merit 1 / (sigma^2 t) over optical depth.

Two scenes, each over optical depths 0.1 to 100 (``--taus``):

- ``slab``: a uniform slab 0.25 <= z < 0.75 of vertical optical depth tau, lit by a star
  above it (0.5, 0.5, 0.9), seen from below: the peel-off image is the light the slab
  transmits;
- ``sphere``: a uniform sphere of radius 0.5 and radial optical depth tau, lit from its
  centre, seen along -z.

For each method and depth the same packets are traced with ``--seeds`` seeds and two errors are
measured: the lit-region error of J (the run's own batch-means figure,
``nebula_rt.transport.lit_region_error``, whose honesty the tests check) and the relative
error of the peel-off image's total (from its batch totals: one pixel group over the whole
image). Time t is the run's wall time (``timings["total_s"]``, kernels built beforehand).
FOM = 1 / (sigma^2 t), larger is better; a method whose image total is zero has no image FOM.

    python benchmarks/bench_biasing.py --backend cuda --out results.json [--plot docs/biasing.png]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
import warnings

import numpy as np

from nebula_rt.backends import get_backend
from nebula_rt.optics.bands import Band
from nebula_rt.errors import NebulaWarning
from nebula_rt.scene import Star
from nebula_rt.observe.sky import Camera
from nebula_rt.transport.estimate import lit_region_error
from nebula_rt.transport import trace


def scene(kind: str, n: int, tau: float):
    """(density, star position, camera, extinction per box unit at density 1)."""
    c = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
    if kind == "slab":
        rho = ((Z >= 0.25) & (Z < 0.75)).astype(np.float32)
        return rho, (0.5, 0.5, 0.9), Camera(direction=(0.0, 0.0, 1.0), size=(32, 32)), tau / 0.5
    rho = (((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2) < 0.25).astype(np.float32)
    return rho, (0.5, 0.5, 0.5), Camera(direction=(0.0, 0.0, -1.0), size=(32, 32)), tau / 0.5


def measure(backend, kind, n, tau, method, photons, seeds, albedo, g):
    rho, star, cam, kappa = scene(kind, n, tau)
    band = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=albedo, g=g)]
    stars = [Star(position=star, luminosity=1.0, temperature=None, bump_radius=0.0)]
    bins = np.zeros(cam.size, np.int64)  # one pixel group: the image total per batch
    sigma = (kappa * rho.astype(np.float64))[None]
    lit, img, t = [], [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        trace(rho, band, stars, tau=kappa, photons=min(photons, 20000), backend=backend, method=method,
              peel=cam, peel_bins=bins)  # builds the kernels of this option set
        for seed in range(1, seeds + 1):
            t0 = time.perf_counter()
            r = trace(rho, band, stars, tau=kappa, photons=photons, seed=seed, backend=backend, method=method,
                      peel=cam, peel_bins=bins)
            t.append(time.perf_counter() - t0)
            lit.append(lit_region_error(r.J, r.rel_error, sigma))
            batch_totals = r.peel_bin_batches[:, 0, 0]
            total = batch_totals.sum()
            m = batch_totals.size
            se = math.sqrt(batch_totals.var(ddof=1) * m) if m > 1 else math.inf
            img.append(se / total if total > 0 else math.inf)
    tm = float(np.mean(t))
    e_lit, e_img = float(np.mean(lit)), float(np.mean(img))
    return {"scene": kind, "tau": tau, "method": method, "photons": photons, "seeds": seeds,
            "time_s": tm, "lit_error": e_lit, "image_error": e_img,
            "fom_lit": 1.0 / (e_lit**2 * tm) if e_lit > 0 else math.inf,
            "fom_image": 1.0 / (e_img**2 * tm) if math.isfinite(e_img) and e_img > 0 else 0.0}


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharex=True)
    for ax, key, title in ((axes[0], "fom_lit", "lit region of J"), (axes[1], "fom_image", "peel-off image total")):
        for kind, ls in [(k, l) for k, l in (("slab", "-"), ("sphere", "--")) if any(r["scene"] == k for r in rows)]:
            ffs = sorted({r["forced_flights"] for r in rows if r["method"] == "biased"})
            ff = 0 if 0 in ffs else ffs[0]  # the library's default, else the first measured
            for method, colour in (("analog", "tab:blue"), ("biased", "tab:red")):
                pts = [(r["tau"], r[key]) for r in rows if r["scene"] == kind and r["method"] == method
                       and (method == "analog" or r["forced_flights"] == ff)]
                x, y = zip(*pts)
                y = [v if v > 0 else np.nan for v in y]
                ax.plot(x, y, ls, color=colour, marker="o", label=f"{method}, {kind}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("optical depth (slab: vertical; sphere: radial)")
        ax.set_ylabel("figure of merit 1 / (sigma^2 t)  [1/s]")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--device", default="")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--photons", type=float, default=2e5)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--taus", type=float, nargs="+", default=[0.1, 0.3, 1, 3, 10, 30, 100])
    ap.add_argument("--scenes", nargs="+", default=["slab", "sphere"])
    ap.add_argument("--albedo", type=float, default=0.6)
    ap.add_argument("--g", type=float, default=0.6)
    ap.add_argument("--forced-flights", type=int, nargs="+", default=[0],
                    help="biased: forced flights per packet (kernel option NRT_FORCED_FLIGHTS; 0: the "
                         "kernel's default, every flight), one row each")
    ap.add_argument("--program", default=None,
                    help="a variant of kernels/transport.cl to time instead (e.g. transport_x.cl)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--plot", default=None)
    a = ap.parse_args(argv)
    backend = get_backend(a.backend, a.device)
    if a.program:
        backend.transport_program = a.program
    rows = []
    tuning = dict(backend.transport_tuning)
    for kind in a.scenes:
        for tau in a.taus:
            for method, ff in [("analog", 0)] + [("biased", f) for f in a.forced_flights]:
                backend.transport_tuning = dict(tuning, **({"NRT_FORCED_FLIGHTS": ff} if ff else {}))
                row = measure(backend, kind, a.grid, tau, method, int(a.photons), a.seeds, a.albedo, a.g)
                row["forced_flights"] = ff
                rows.append(row)
                label = method if not ff else f"{method}{ff}"
                print(f"{kind:6s} tau {tau:7.3g} {label:8s}  t {row['time_s']:8.3f} s  lit err {row['lit_error']:.3e}"
                      f"  image err {row['image_error']:.3e}  FOM lit {row['fom_lit']:.3e}  image {row['fom_image']:.3e}",
                      flush=True)
    backend.transport_tuning = tuning
    result = {"benchmark": "bench_biasing", "device": backend.device_name, "backend": a.backend,
              "grid": a.grid, "albedo": a.albedo, "g": a.g, "python": platform.python_version(), "rows": rows}
    if a.out:
        with open(a.out, "w") as f:
            json.dump(result, f, indent=1)
    if a.plot:
        plot(rows, a.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
