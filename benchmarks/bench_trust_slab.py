"""The TRUST I slab benchmark: NebulaRT's scattered light against an independent solution.

The scene of tests/transport/test_trust_slab.py (tests/trust_scene.py: a star 6 pc above a 10 x 10 x 3 pc
uniform slab, vertical optical depth 10 at 550 nm, Milky Way dust at 13 wavelengths from 150 nm
to 2.2 um, those with vertical depth up to 35), seen from the benchmark's 7 polar angles. The
reference is tests/oracles/slab_mc.py (NumPy, its own variance reduction, checked against the
exact plane-parallel answer by tests/transport/test_slab_oracle_mc.py). For each angle and wavelength:
NebulaRT's scattered power per steradian (over the band's luminosity), the oracle's, both
stated errors, their ratio, the pull, whether the ratio is within the 10 % target, and the
heavy-tail check of NebulaRT's image (nebula_rt.transport.tails).

The oracle's answers are kept in ``--oracle FILE`` (computed and written there when the file
does not exist), so a GPU run reuses those computed on a CPU.

    python benchmarks/bench_trust_slab.py --backend opencl --photons 2e5 --out results.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import trust_scene as ts  # noqa: E402
from oracles.slab_mc import scattered  # noqa: E402

from provenance import provenance  # noqa: E402  (benchmarks/provenance.py)
from nebula_rt.backends import get_backend  # noqa: E402
from nebula_rt.errors import NebulaWarning  # noqa: E402
from nebula_rt.transport import trace  # noqa: E402

TARGET = 0.10


def oracle(wls, photons: int, path) -> dict:
    """(packets, {wavelength: (values, errors) per angle}), read from ``path`` (any file of at
    least ``photons`` packets) or computed and written."""
    if path and Path(path).exists():
        data = json.loads(Path(path).read_text())
        if data["photons"] >= photons and all(str(w) in data["values"] for w in wls):
            return data["photons"], {w: (np.array(data["values"][str(w)]), np.array(data["errors"][str(w)]))
                                     for w in wls}
    dirs = [ts.observer(a) for a in ts.ANGLES]
    t0 = time.perf_counter()
    out = {w: scattered(ts.oracle_slab(w), dirs, photons, seed=20261203) for w in wls}
    print(f"oracle: {photons:.3g} packets x {len(wls)} wavelengths in {time.perf_counter() - t0:.1f} s")
    if path:
        Path(path).write_text(json.dumps({"photons": photons, "angles": list(ts.ANGLES),
                                          "values": {str(w): out[w][0].tolist() for w in wls},
                                          "errors": {str(w): out[w][1].tolist() for w in wls}}, indent=1))
    return photons, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--device", default="")
    ap.add_argument("--photons", type=float, default=2e5, help="NebulaRT packets per band and angle")
    ap.add_argument("--oracle-photons", type=float, default=1e6)
    ap.add_argument("--oracle", default=None, help="the oracle's answers (JSON), reused or written")
    ap.add_argument("--method", default="auto")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    backend = get_backend(a.backend, a.device)
    wls = ts.wavelengths()
    oracle_photons, ref = oracle(wls, int(a.oracle_photons), a.oracle)
    rho, bands, stars, tau = ts.scene(wls)
    rows = []
    for j, angle in enumerate(ts.ANGLES):
        cam = ts.camera(angle)
        kw = dict(tau=tau, backend=backend, method=a.method, peel=cam, peel_bins=np.zeros(cam.size, np.int64))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NebulaWarning)
            trace(rho, bands, stars, photons=10_000, **kw)  # builds the kernels
            t0 = time.perf_counter()
            r = trace(rho, bands, stars, photons=int(a.photons), seed=a.seed, **kw)
            seconds = time.perf_counter() - t0
        val, err = ts.scattered_per_sr(r, cam)
        for b, w in enumerate(wls):
            rv, re = float(ref[w][0][j]), float(ref[w][1][j])
            ratio = float(val[b]) / rv
            row = dict(angle=angle, wavelength_nm=w, tau_z=ts.TAU_V * ts.dust(w)[0], nebula=float(val[b]),
                       nebula_error=float(err[b]), oracle=rv, oracle_error=re, ratio=ratio,
                       ratio_error=ratio * float(np.hypot(err[b] / val[b], re / rv)),
                       pull=float((val[b] - rv) / np.hypot(err[b], re)), within_target=abs(ratio - 1.0) <= TARGET,
                       tail_reliable=bool(r.tail_image[b].reliable), method=r.method, seconds=seconds)
            rows.append(row)
            print(f"{angle:5.0f} deg {w:7.1f} nm tau_z {row['tau_z']:5.1f}: NebulaRT {val[b]:.4e} +- "
                  f"{100 * err[b] / val[b]:.2f} %, oracle {rv:.4e} +- {100 * re / rv:.2f} %, ratio {ratio:.3f} "
                  f"(pull {row['pull']:+.1f}){'' if row['within_target'] else '  OUTSIDE 10 %'}"
                  f"{'' if row['tail_reliable'] else '  [tail check failed]'}")
    worst = max(rows, key=lambda x: abs(x["ratio"] - 1.0))
    inside = sum(x["within_target"] for x in rows)
    print(f"within 10 %: {inside} of {len(rows)}; worst {worst['angle']:.0f} deg {worst['wavelength_nm']:g} nm: "
          f"ratio {worst['ratio']:.3f} +- {worst['ratio_error']:.3f}")
    result = {"benchmark": "trust_slab", "backend": a.backend, "device": backend.device_name,
              "host": platform.node(), "photons": int(a.photons), "oracle_photons": int(oracle_photons),
              "target": TARGET, "within_target": inside, "cases": len(rows),
              "command": " ".join(sys.argv), **provenance(), "rows": rows}
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        with open(a.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
