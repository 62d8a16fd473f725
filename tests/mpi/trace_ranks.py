"""Run by tests/test_mpi.py under mpiexec: every rank traces the same runs through
``trace(comm=world())``; rank 0 saves each run's sums, squares, counts, peel-off image and
heavy-tail histograms (.npz).

    mpiexec -n N python tests/mpi/trace_ranks.py OUTDIR DEVICE ESTIMATOR:MODE...

Each ESTIMATOR:MODE is one run, saved as OUTDIR/ESTIMATOR-MODE.npz (one process runs them all:
an MPI job's start-up costs more than a run).

MODE: ``plain``, ``checked`` (headroom lowered: batches overflow and are re-traced), ``biased``
(weighted packets, 128-bit cells), ``mie`` (Mie grains: Q, U and V), ``polarized`` (Stokes vectors: the Q and U images' signed
sums added over the ranks too), ``regions`` (the transport by regions, each group streamed
through launches of about 300 packets) or ``packets`` (the error estimate by packets: one batch,
its squares summed over the ranks too, no peel-off image) or ``tree`` (an octree of the cloud:
the packets walk its leaves) or ``binned`` (binned deposits, without the peel-off image), joined by ``+`` with ``copied``: the slots are summed in a
host copy, as on a GPU, instead of in the mapped device memory of PoCL (``Backend.map_host``).
With ``NEBULA_RT_TEST_BACKEND=cuda`` the ranks trace on CUDA (a GPU per local rank where there
are enough) and add their slots on the device (``nebula_rt.backends.parallel.device_reducer``); the
.npz's ``reduce_path`` says how.
"""

import os

import sys

import numpy as np

from nebula_rt.optics.bands import Band
from nebula_rt.backends.parallel import world
from nebula_rt.scene import Star
from nebula_rt.observe.sky import Camera
from nebula_rt.transport import trace


def run_case(out: str, estimator: str, mode: str, device: str, comm) -> None:
    """Trace one run on every rank of ``comm``; rank 0 saves it to ``out``."""
    import nebula_rt.transport.run as transport_mod

    parts = mode.split("+")
    checked, biased = "checked" in parts, "biased" in parts
    # a new backend per run (get_backend's are cached): the modes change it
    if os.environ.get("NEBULA_RT_TEST_BACKEND", "opencl") == "cuda":
        import cupy

        from nebula_rt.backends.cuda import CUDABackend

        backend = CUDABackend(device or str(comm.local_rank % cupy.cuda.runtime.getDeviceCount()))
    else:
        from nebula_rt.backends.opencl import OpenCLBackend

        backend = OpenCLBackend(device)
    if "+copied" in mode:
        backend.map_host = lambda dev, n: None
    rng = np.random.default_rng(11)
    cloud = (rng.random((20, 16, 12)) ** 3).astype(np.float32)
    bands = [Band(name="B", wavelength=450.0, extinction=1.3, albedo=0.6, g=0.5),
             Band(name="R", wavelength=650.0, extinction=0.8, albedo=0.7, g=-0.3)]
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0),
             Star(position=(0.25, 0.625, 0.4), luminosity=0.6, temperature=None, bump_radius=0.0)]
    kw = dict(tau=25.0, photons=9001, seed=4, estimator=estimator, backend=backend, batch_size=1500,
              peel=Camera(direction=(0.0, 0.0, -1.0), size=(12, 10)))
    if checked:  # headroom lowered: batches overflow and are re-traced in halves
        kw["_acc_limit_bits"] = 31 if biased else 36  # 128-bit cells: 2^95, 2^7 voxel crossings
    if biased:  # the stars' windows: J's depth-class histograms are added over the ranks too
        kw.update(method="biased", importance="stars")
    if "polarized" in parts:  # Stokes vectors (White's approximation): Q and U images, signed sums
        from nebula_rt.optics.polarization import Polarization

        kw["polarization"] = Polarization("white", peak=0.5)
    if "mie" in parts:  # Mie grains: their tables, each rank's own, and V's image besides Q and U
        from nebula_rt.optics.mie import Grains, mie_bands
        from nebula_rt.optics.polarization import Polarization

        grains = Grains(n=1.6, k=0.02, radius_min=0.05, radius_max=0.4)
        kw["polarization"] = Polarization("mie", grains=grains)
        bands = mie_bands(bands, grains)
    if "packets" in parts:  # one batch of every packet, no peel-off image (it needs batches)
        kw.update(error_estimate="packets", batch_size=0, peel=None, tau=2.5)
    backend.launch_packets = 2 * 3 * 1500  # several launches, each of several batches
    budget = transport_mod._Launcher._budget
    if "regions" in parts:  # by regions of 4 voxels, each group in launches of about 300 packets
        backend.transport_tuning.update({"NRT_REGIONS": 2, "region_tail": 50})
        transport_mod._Launcher._budget = lambda self, nb: 600  # packets (all bands) per launch
    if "binned" in parts:  # binned deposits (a tuning): no peel-off image, the walk's slots
        backend.transport_tuning = dict(backend.transport_tuning, binned_deposits=1)
        kw["peel"] = None
    medium = cloud
    if "tree" in parts:  # an octree of the cloud (roots of 4^3 voxels, blocks within 30 % merged)
        from nebula_rt.density.octree import coarsen

        medium = coarsen(cloud, (5, 4, 3), 0.3)
    try:
        res = trace(medium, bands, stars, comm=comm, **kw)
    finally:
        transport_mod._Launcher._budget = budget
    if comm.rank == 0:
        # counts: exact integers (128-bit weight sums when biased) as decimal text
        counts = np.array([[str(int(x)) for x in row] for row in res.counts])
        np.savez(out, raw_sum=res.raw_sum, raw_m2=res.raw_m2, counts=counts,
                 peel=np.zeros(0) if res.peel_image is None else res.peel_image,
                 band_batches=res.band_batches, size=comm.size, reduce_path=res.reduce_path,
                 tail_hist=res.tail_hist, stokes=np.zeros(0) if res.peel_stokes is None else res.peel_stokes)


def main() -> int:
    outdir, device = sys.argv[1], sys.argv[2]
    comm = world()
    for case in sys.argv[3:]:
        estimator, mode = case.split(":")
        run_case(os.path.join(outdir, f"{estimator}-{mode}.npz"), estimator, mode, device, comm)
    return 0


if __name__ == "__main__":
    sys.exit(main())
