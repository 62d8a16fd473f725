"""Packets error estimate: same bits across kernel configurations (regions, group tallies)."""
import sys, numpy as np
from nebula_rt.transport import trace
from nebula_rt.bands import Band
from nebula_rt.scene import Star
kind = sys.argv[1]
if kind == "cuda":
    from nebula_rt.backends.cuda import CUDABackend as B
    mk = lambda t: B("", transport_tuning=t)
else:
    from nebula_rt.backends.opencl import OpenCLBackend as B
    mk = lambda t: B("portable", transport_tuning=t)
rng = np.random.default_rng(2)
n = 48
rho = rng.gamma(2.0, 0.5, (n, n, n)).astype(np.float32)
bands = [Band(name="B", wavelength=450.0, extinction=1.3, albedo=0.6, g=0.5),
         Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.7, g=0.6)]
stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0),
         Star(position=(0.3, 0.6, 0.45), luminosity=0.5, temperature=None, bump_radius=0.0)]
P = int(sys.argv[2]) if len(sys.argv) > 2 else 300000
ref = None
for tun in ({}, {"NRT_REGIONS": 3}, {"NRT_REGIONS": 2, "NRT_SORTED": 1}, {"NRT_GROUP_TALLY": 0}, {"NRT_GROUP_TALLY": 1}):
    for est in ("track-length", "collision-filter"):
        r = trace(rho, bands, stars, tau=3.0, photons=P, backend=mk(tun), error_estimate="packets", seed=9,
                  estimator=est)
        key = (est,)
        s1, m2 = np.asarray(r.raw_sum), np.asarray(r.raw_m2)
        if tun == {}:
            globals().setdefault("refs", {})[key] = (s1, m2, r.counts)
            print(est, "batches", r.batches, "median rel", float(np.median(r.rel_error[r.J > np.median(r.J)])))
        else:
            a = refs[key]
            same = np.array_equal(a[0], s1) and np.array_equal(a[1], m2) and np.array_equal(a[2], r.counts)
            print(est, tun, "same bits:", same)
rb = trace(rho, bands, stars, tau=3.0, photons=P, backend=mk({}), error_estimate="batches", seed=9)
rp = trace(rho, bands, stars, tau=3.0, photons=P, backend=mk({}), error_estimate="packets", seed=9)
lit = rb.J > np.median(rb.J)
print("J max rel diff", float(np.max(np.abs(rb.J - rp.J)[lit] / rb.J[lit])),
      "mean rel_err^2 packets/batches", float(np.mean(rp.rel_error[lit]**2) / np.mean(rb.rel_error[lit]**2)))
