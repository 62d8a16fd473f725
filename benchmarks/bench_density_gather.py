#!/usr/bin/env python
"""Nebula Light Field in ParaView's MPI engine: how each rank should get the whole density.

    python benchmarks/bench_density_gather.py [--ranks 2 3] [--grids 64 128 256]
        [--upstreams zlib raw source] [--repeats 3] [--workdir DIR] [--out FILE.json]

The transport needs every voxel on every rank. Two ways to get there, measured here:

  whole   what the filter does (filters/base.py RequestUpdateExtent): ask the upstream for
          the whole extent as piece 0 of 1, so that every rank reads (or makes) the whole grid;
  gather  let the upstream produce the rank's piece (the extent ParaView asks of the rank)
          and all-gather the pieces' arrays through the VTK controller
          (vtkMultiProcessController.AllGather of the extents, AllGatherV of the float32
          values), each placed into the whole array by its extent.

Upstreams, as users bring them:

  zlib    a .vti on disk (NebulaRT's write_vti: appended raw binary, ZLib-compressed, as
          ParaView's SaveData writes by default) read by ParaView's XMLImageDataReader;
  raw     the same file uncompressed;
  source  the Nebula Dust Density source (it generates the whole grid on the device and crops
          it to the piece asked, so a piece costs it as much as the whole).

The density is the thesis default nebula (turbulence, NebulaRT's generator) on n^3. Each
configuration (ranks, grid, upstream, mode) runs as its own ``mpiexec --oversubscribe -n N
pvbatch --mpi --symmetric`` job (environment of scripts/pv-env.sh; PoCL pinned by name). Per
rank, after a barrier, it times the pipeline update (``UpdatePiece(rank, N, 0)``, what
ParaView's UpdatePipeline asks) of a probe filter in the light field's place, until the probe
holds the whole density as a numpy array: the upstream's execution plus the data movement,
not the transport. The update is repeated ``--repeats`` times (the upstream marked modified
before each; the first includes the source's device start-up and the file's first read
through the page cache); a repetition's time is the slowest rank's (the transport's first
collective waits for it). Memory: each rank's peak RSS (VmHWM) at the end and its RSS before
the first update; the figure is the largest over the ranks, in MiB. The probe also checks
that every rank's whole density has the same SHA-256 in both modes, and records how many
points the upstream gave each rank (the whole grid, or its piece).

On this 2-core machine the ranks share the cores (3 ranks oversubscribe them), and the file is
read from the page cache: the figures measure the readers' decoding and the data movement,
not a file system's bandwidth (which the whole request multiplies by N).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEVICE = os.environ.get("NEBULA_RT_TEST_DEVICE", "Portable Computing Language")


# -- the pvbatch side ------------------------------------------------------------------------
def _status_kib(key: str) -> int:
    """A line of /proc/self/status in KiB (VmHWM: peak RSS, VmRSS: RSS now)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return -1


def _probe_class():
    """The probe: a vtkImageData filter in Nebula Light Field's place that ends holding the
    whole density (``self.whole``, x-fastest flat float32) by one of the two modes."""
    import numpy as np
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
    from vtkmodules.vtkCommonCore import vtkFloatArray, vtkIntArray
    from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp
    from vtkmodules.vtkParallelCore import vtkMultiProcessController

    class DensityProbe(VTKPythonAlgorithmBase):
        def __init__(self, mode: str):
            super().__init__(nInputPorts=1, inputType="vtkImageData", nOutputPorts=1,
                             outputType="vtkImageData")
            self.mode = mode
            self.whole = None

        def RequestInformation(self, request, inInfo, outInfo):
            outInfo.GetInformationObject(0).Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
            return 1

        def RequestUpdateExtent(self, request, inInfo, outInfo):
            info = inInfo[0].GetInformationObject(0)
            if self.mode == "whole":  # filters/base.py: the whole input, as piece 0 of 1
                info.Set(sddp.UPDATE_PIECE_NUMBER(), 0)
                info.Set(sddp.UPDATE_NUMBER_OF_PIECES(), 1)
                info.Set(sddp.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)
                info.Set(sddp.UPDATE_EXTENT(), *info.Get(sddp.WHOLE_EXTENT()))
            else:  # this rank's piece, as ParaView asks it of the output
                out = outInfo.GetInformationObject(0)
                for key in (sddp.UPDATE_PIECE_NUMBER(), sddp.UPDATE_NUMBER_OF_PIECES()):
                    info.Set(key, out.Get(key))
                info.Set(sddp.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)
            return 1

        def RequestData(self, request, inInfo, outInfo):
            info = inInfo[0].GetInformationObject(0)
            inp = self.GetInputData(inInfo, 0, 0)
            whole_ext = list(info.Get(sddp.WHOLE_EXTENT()))
            dims = [whole_ext[2 * a + 1] - whole_ext[2 * a] + 1 for a in range(3)]
            local = vtk_to_numpy(inp.GetPointData().GetArray("density"))
            self.input_points = int(local.size)  # what the upstream gave this rank
            if self.mode == "whole":
                self.whole = local
                return 1
            ctrl = vtkMultiProcessController.GetGlobalController()
            n = ctrl.GetNumberOfProcesses()
            ext = vtkIntArray()
            ext.SetNumberOfTuples(6)
            for i, v in enumerate(inp.GetExtent()):
                ext.SetValue(i, v)
            exts = vtkIntArray()
            ctrl.AllGather(ext, exts)
            send = numpy_to_vtk(np.ascontiguousarray(local, np.float32), deep=False)
            recv = vtkFloatArray()
            ctrl.AllGatherV(send, recv)  # rank order, each rank's piece x-fastest
            flat = vtk_to_numpy(recv)
            whole = np.empty(dims[::-1], np.float32)  # (z, y, x): x fastest
            at = 0
            for r in range(n):
                e = [exts.GetValue(6 * r + i) - whole_ext[2 * (i // 2)] for i in range(6)]
                shape = (e[5] - e[4] + 1, e[3] - e[2] + 1, e[1] - e[0] + 1)
                size = shape[0] * shape[1] * shape[2]
                if size > 0 and min(shape) > 0:
                    whole[e[4]:e[5] + 1, e[2]:e[3] + 1, e[0]:e[1] + 1] = flat[at:at + size].reshape(shape)
                    at += size
            self.whole = whole.reshape(-1)
            return 1

    return DensityProbe


def child(upstream: str, path: str, n: int, mode: str, repeats: int) -> None:
    """One configuration under pvbatch; rank 0 prints ``RESULT <json>``."""
    from paraview import simple
    from vtkmodules.vtkCommonCore import vtkDoubleArray
    from vtkmodules.vtkParallelCore import vtkMultiProcessController

    ctrl = vtkMultiProcessController.GetGlobalController()
    rank, size = ctrl.GetLocalProcessId(), ctrl.GetNumberOfProcesses()
    if upstream == "source":
        up = simple.NebulaDustDensity()
        up.GridShape = [n, n, n]
        up.Device = DEVICE
    else:
        up = simple.XMLImageDataReader(FileName=[path])
    algo = up.GetClientSideObject()
    probe = _probe_class()(mode)
    probe.SetInputConnection(algo.GetOutputPort())
    rss0 = _status_kib("VmRSS")
    times = []
    for i in range(repeats):
        if i:
            algo.Modified()
        ctrl.Barrier()
        t0 = time.perf_counter()
        probe.UpdatePiece(rank, size, 0)
        times.append(time.perf_counter() - t0)
    digest = hashlib.sha256(probe.whole.tobytes()).hexdigest()
    ok = probe.whole.size == n ** 3
    row = times + [rss0, _status_kib("VmHWM"), float(ok), int(digest[:12], 16), probe.input_points]
    send = vtkDoubleArray()
    send.SetNumberOfTuples(len(row))
    for i, v in enumerate(row):
        send.SetValue(i, float(v))
    recv = vtkDoubleArray()
    ctrl.Gather(send, recv, 0)
    if rank == 0:
        rows = [[recv.GetValue(r * len(row) + i) for i in range(len(row))] for r in range(size)]
        per_rank_t = [r[:repeats] for r in rows]
        slowest = [max(r[i] for r in per_rank_t) for i in range(repeats)]
        print("RESULT " + json.dumps({
            "ranks": size, "grid": n, "upstream": upstream, "mode": mode,
            "time_s": [round(t, 4) for t in slowest],
            "time_first_s": round(slowest[0], 4),
            "time_best_later_s": round(min(slowest[1:]), 4) if repeats > 1 else None,
            "per_rank_time_s": [[round(t, 4) for t in r] for r in per_rank_t],
            "rss_before_mib": round(max(r[repeats] for r in rows) / 1024, 1),
            "peak_rss_mib": round(max(r[repeats + 1] for r in rows) / 1024, 1),
            "per_rank_peak_rss_mib": [round(r[repeats + 1] / 1024, 1) for r in rows],
            "whole_density_on_every_rank": all(r[repeats + 2] == 1.0 for r in rows),
            "digest": "%012x" % int(rows[0][repeats + 3]),
            "same_digest_on_every_rank": len({r[repeats + 3] for r in rows}) == 1,
            "upstream_points_per_rank": [int(r[repeats + 4]) for r in rows],
        }), flush=True)


# -- the driver ------------------------------------------------------------------------------
def pv_environment() -> dict:
    """os.environ as scripts/pv-env.sh leaves it."""
    proc = subprocess.run(["bash", "-c", 'source "$1" && env -0', "pv-env", str(ROOT / "scripts" / "pv-env.sh")],
                          capture_output=True, check=True)
    return dict(item.split("=", 1) for item in proc.stdout.decode().split("\0") if "=" in item)


def write_density(workdir: Path, n: int) -> dict:
    """The thesis default nebula on n^3 as .vti files (zlib and raw); returns the paths."""
    from nebula_rt.backends import get_backend
    from nebula_rt.density import generate_density
    from nebula_rt.pipeline.io_vti import write_vti
    from nebula_rt.scene import Scene

    scene = Scene.from_dict({"grid": {"shape": [n, n, n]}})
    rho = generate_density(scene, get_backend("opencl", DEVICE))
    paths = {}
    for kind, compress in (("zlib", True), ("raw", False)):
        p = workdir / f"density-{n}-{kind}.vti"
        if not p.exists():
            write_vti(p, {"density": rho}, {}, (1 / n,) * 3, (0.5 / n,) * 3, compress=compress)
        paths[kind] = p
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ranks", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--grids", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--upstreams", nargs="+", default=["zlib", "raw", "source"], choices=("zlib", "raw", "source"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workdir", default=None, help="folder for the .vti files (default: a temporary one)")
    ap.add_argument("--timeout", type=float, default=600)
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        upstream, path, n, mode = args.child
        child(upstream, path, int(n), mode, args.repeats)
        return 0
    import tempfile

    for exe in ("mpiexec", "pvbatch"):
        if shutil.which(exe) is None:
            print(f"{exe} not found (Debian: openmpi-bin, paraview)", file=sys.stderr)
            return 1
    env = pv_environment()
    env.pop("POCL_CPU_MAX_CU_COUNT", None)
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="nrt-gather-")
    workdir = Path(args.workdir or tmp.name)
    workdir.mkdir(parents=True, exist_ok=True)
    records = []
    try:
        for n in args.grids:
            files = write_density(workdir, n) if set(args.upstreams) - {"source"} else {}
            sizes = {k: p.stat().st_size for k, p in files.items()}
            for r in args.ranks:
                for upstream in args.upstreams:
                    for mode in ("whole", "gather"):
                        path = str(files.get(upstream, "-"))
                        cmd = [shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe", "-n", str(r),
                               "pvbatch", "--mpi", "--symmetric", str(Path(__file__).resolve()),
                               "--repeats", str(args.repeats), "--child", upstream, path, str(n), mode]
                        t0 = time.perf_counter()
                        try:
                            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=args.timeout)
                            lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                            failed = proc.returncode != 0 or not lines
                            err = (proc.stderr or proc.stdout)[-800:]
                        except subprocess.TimeoutExpired:
                            failed, lines, err = True, [], f"timed out after {args.timeout} s"
                        if failed:
                            rec = {"ranks": r, "grid": n, "upstream": upstream, "mode": mode, "error": err}
                        else:
                            rec = json.loads(lines[-1][len("RESULT "):])
                            rec["job_wall_s"] = round(time.perf_counter() - t0, 2)
                            if upstream in sizes:
                                rec["file_mib"] = round(sizes[upstream] / 2**20, 2)
                        records.append(rec)
                        print(json.dumps(rec), flush=True)
    finally:
        if tmp is not None:
            tmp.cleanup()
    # whole vs gather side by side, and the same density both ways
    summary = []
    for rec in records:
        if rec.get("mode") != "whole" or "error" in rec:
            continue
        other = next((g for g in records if g.get("mode") == "gather" and "error" not in g and
                      all(g[k] == rec[k] for k in ("ranks", "grid", "upstream"))), None)
        if other is None:
            continue
        summary.append({
            "ranks": rec["ranks"], "grid": rec["grid"], "upstream": rec["upstream"],
            "whole_first_s": rec["time_first_s"], "gather_first_s": other["time_first_s"],
            "whole_best_later_s": rec["time_best_later_s"], "gather_best_later_s": other["time_best_later_s"],
            "gather_over_whole_best_later": (round(other["time_best_later_s"] / rec["time_best_later_s"], 2)
                                             if rec["time_best_later_s"] else None),
            "whole_peak_rss_mib": rec["peak_rss_mib"], "gather_peak_rss_mib": other["peak_rss_mib"],
            "same_density": rec["digest"] == other["digest"],
        })
    out = {"benchmark": "bench_density_gather", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
           "cpu_count": os.cpu_count(), "device": DEVICE,
           "note": ("ranks share the cores (3 ranks oversubscribe 2) and the files are read from the page "
                    "cache: reader decoding and data movement, not file-system bandwidth"
                    if max(args.ranks) >= (os.cpu_count() or 1) else ""),
           "command": " ".join(["benchmarks/bench_density_gather.py"] + (argv if argv is not None else sys.argv[1:])),
           "summary": summary, "records": records}
    print(json.dumps(summary, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    status = main()
    if status:  # not sys.exit(0): under pvbatch that would leave without finalising MPI
        sys.exit(status)
