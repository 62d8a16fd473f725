"""Distributed runs with real mpiexec: every rank traces a share of each launch's packets, the
ranks' integer slots and tallies are added before each fold, and every rank holds the one-rank
run's sums. The result must be the same bits on 1, 2 and 3 ranks (3 ranks on this machine's 2
cores: --oversubscribe), for both estimators, through the overflow re-trace (whose checked
adds are summed so that no rank's cells can wrap together: sum_checked), and through the
command line, where rank 0 alone writes the .vti. The sums themselves are held against Python's
integers (tests/mpi/sum_ranks.py).

mpiexec (openmpi-bin) and mpi4py (the ``mpi`` extra) are installed by scripts/setup.sh; their
absence is a failure here, not a skip.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "mpi" / "trace_ranks.py"


def mpiexec(n: int, *argv, timeout: float = 300.0):
    exe = shutil.which("mpiexec")
    assert exe is not None, "mpiexec not found: scripts/setup.sh installs openmpi-bin"
    env = dict(os.environ)
    env.pop("POCL_CPU_MAX_CU_COUNT", None)
    r = subprocess.run([exe, "--allow-run-as-root", "--oversubscribe", "-n", str(n), *argv],
                       capture_output=True, text=True, timeout=timeout, env=env)
    assert r.returncode == 0, (n, r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    return r


def test_mpi4py_is_there():
    import mpi4py  # noqa: F401  (the mpi extra)


def _ranks(folder: Path, n: int, cases) -> dict:
    """Every (estimator, mode) of ``cases`` traced by one job of ``n`` ranks
    (tests/mpi/trace_ranks.py): {case: the saved arrays}."""
    folder.mkdir(parents=True, exist_ok=True)
    mpiexec(n, sys.executable, str(SCRIPT), str(folder), TEST_DEVICE, *(f"{e}:{m}" for e, m in cases))
    return {(e, m): np.load(folder / f"{e}-{m}.npz") for e, m in cases}


CASES = [("track-length", "plain"), ("collision-filter", "plain"),
         ("track-length", "checked"), ("track-length", "checked+copied"),
         ("track-length", "biased+checked"), ("collision-filter", "biased+copied"),
         ("track-length", "regions+checked"), ("track-length", "packets+regions"),
         ("collision-filter", "packets+copied"), ("track-length", "tree"), ("collision-filter", "tree+copied"),
         ("track-length", "tree+biased"), ("track-length", "polarized+checked"),
         ("collision-filter", "polarized+copied"), ("track-length", "polarized+biased"),
         ("track-length", "polarized+regions"), ("track-length", "mie+biased"),
         ("track-length", "binned+checked+copied")]


@pytest.fixture(scope="module")
def rank_runs(tmp_path_factory):
    """Every case of CASES on 1, 2 and 3 ranks: {ranks: {case: arrays}} (one job per rank count)."""
    folder = tmp_path_factory.mktemp("ranks")
    return {n: _ranks(folder / f"n{n}", n, CASES) for n in (1, 2, 3)}


@pytest.mark.parametrize("case", CASES, ids="-".join)
def test_trace_is_the_same_bits_on_1_2_3_ranks(rank_runs, case):
    """Sums, centred squares, packet counts, peel-off image and batches per band: identical
    bytes on 1, 2 and 3 ranks (two bands, two stars, 9001 packets in batches of 1500, several
    batches per launch; 'checked': headroom 2^36, so batches overflow and are re-traced;
    '+copied': the slots summed in a host copy, the path of GPUs, instead of in PoCL's mapped
    device memory; 'biased': weighted packets, whose 128-bit cells, images and tallies the
    ranks add limb by limb; 'regions': by regions of 4 voxels, each rank's share of a group
    streamed through launches of about 300 packets and drained at the group's last;
    'packets': the error estimate by packets, the ranks' squares added as well; 'tree': an
    octree of the cloud, its leaves the cells, with weighted packets too; 'polarized': Stokes
    vectors, the Q and U images' two's-complement sums added over the ranks; 'mie': Mie grains'
    tables made by every rank, and V's image too; 'binned': binned deposits, without the
    peel-off image)."""
    estimator, mode = case
    runs = {n: rank_runs[n][case] for n in (1, 2, 3)}
    one = runs[1]
    assert int(one["size"]) == 1 and int(runs[3]["size"]) == 3
    unit = 2**96 if "biased" in mode else 1  # weight units per packet
    assert [int(x) for x in one["counts"][:, 0]] == [9001 * unit, 9001 * unit]
    if "packets" in mode:
        assert one["band_batches"].tolist() == [9001, 9001]  # batches of one packet
    if "checked" in mode:
        assert one["band_batches"].min() > 7  # the overflow happened and batches were split
    if "polarized" in mode:
        assert one["stokes"].shape == (2, 2, 12, 10) and np.abs(one["stokes"]).sum() > 0
    if "mie" in mode:  # (Mie grains: V too)
        assert one["stokes"].shape == (2, 3, 12, 10) and np.abs(one["stokes"][:, 2]).sum() > 0
    for n in (2, 3):
        for key in ("raw_sum", "raw_m2", "counts", "peel", "band_batches", "tail_hist", "stokes"):
            assert runs[n][key].tobytes() == one[key].tobytes(), (n, key)
        # how the slots were added: on a GPU where they are (NCCL, or ranks sharing one GPU
        # through a host buffer), on PoCL in the mapped device memory unless told to copy
        path = str(runs[n]["reduce_path"])
        if TEST_BACKEND == "cuda":
            assert path in ("nccl", "host"), path
        else:
            assert path == ("copied" if "copied" in mode else "mapped"), path
    assert str(one["reduce_path"]) == ""


def test_tail_histograms_do_not_depend_on_the_path(tmp_path):
    """A packet's contribution does not depend on how it was traced: the heavy-tail histograms
    (nebula_rt.transport.tails) of one rank plain, with batches re-traced after overflows, and by regions
    (the packets' image scores saved and resumed across passes) are the same bits."""
    cases = [("track-length", mode) for mode in ("plain", "checked", "regions+checked")]
    runs = list(_ranks(tmp_path, 1, cases).values())
    assert runs[0]["tail_hist"].sum() > 0
    for r in runs[1:]:
        assert r["tail_hist"].tobytes() == runs[0]["tail_hist"].tobytes()


def test_allreduce_choice_is_checked_before_tracing(tmp_path):
    """A wrong NEBULA_RT_ALLREDUCE ends every rank of a distributed run with an error naming
    the variable, the value and the choices, and nothing is saved."""
    out = tmp_path / "track-length-plain.npz"
    env = dict(os.environ, NEBULA_RT_ALLREDUCE="gpu")
    env.pop("POCL_CPU_MAX_CU_COUNT", None)
    r = subprocess.run([shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe", "-n", "2", sys.executable,
                        str(SCRIPT), str(tmp_path), TEST_DEVICE, "track-length:plain"],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode != 0
    assert "NEBULA_RT_ALLREDUCE = 'gpu': expected one of auto, nccl, host" in r.stderr, r.stderr[-2000:]
    assert not out.exists()


def load_sum_script():
    """tests/mpi/sum_ranks.py as a module (its ``inputs`` give every rank's numbers)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("sum_ranks", ROOT / "tests" / "mpi" / "sum_ranks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def check_rank_sums(res, n: int) -> None:
    """The sums and flags of tests/mpi/sum_ranks.py on ``n`` ranks against Python's integers:
    every sum is the exact sum modulo 2^64 (the wrapping ones and the checked ones alike), the
    input of ``allreduce_u64`` is left unchanged, and a checked row is flagged exactly when one
    of its exact (unwrapped) sums reaches 2^63."""
    mod = load_sum_script()
    per_rank = [mod.inputs(r, n) for r in range(n)]
    exact = [sum(np.array(p[k], dtype=object) for p in per_rank) for k in (0, 1)]
    assert int(res["size"]) == n
    assert res["wrapping"].tolist() == [int(v) % 2**64 for v in exact[0]]
    assert res["checked"].tolist() == [int(v) % 2**64 for v in exact[1]]
    assert res["copied"].tolist() == res["checked"].tolist()
    rows = exact[1][:mod.ROWS * mod.COLS].reshape(mod.ROWS, mod.COLS)
    expected = [any(int(v) >= 2**mod.LIMIT_BITS for v in row) for row in rows]
    assert res["flags"].tolist() == expected
    # what the rows stand for: two ranks pass the limit in rows 1-3, three wrap 2^64 in row 2
    assert expected == [False, n >= 2, n >= 2, n >= 2]
    if n >= 3:
        assert int(rows[2].max()) >= 2**64


@pytest.mark.parametrize("n", [1, 2, 3])
def test_rank_sums_are_exact_and_flag_the_headroom_limit(tmp_path, n):
    """``sum_u64`` (in place, in chunks: arrays across two chunk boundaries), ``allreduce_u64``
    and ``sum_checked`` under mpiexec with mpi4py: exact modulo 2^64, and the checked cells'
    flags as one rank's checked adds would set them, also where three ranks' cells pass 2^64
    together (then summed in 32-bit halves) and where a single wrapping sum would miss it."""
    out = tmp_path / f"sums{n}.npz"
    mpiexec(n, sys.executable, str(ROOT / "tests" / "mpi" / "sum_ranks.py"), str(out), "mpi4py", timeout=120)
    res = np.load(out)
    assert str(res["kind"]) == ("Serial" if n == 1 else "MPIComm")
    check_rank_sums(res, n)


@pytest.mark.skipif(TEST_BACKEND != "cuda", reason="sums of GPU arrays: run with NEBULA_RT_TEST_BACKEND=cuda on a GPU machine")
@pytest.mark.parametrize("n", [1, 2, 3])
def test_rank_sums_of_device_arrays_are_exact_and_flag_the_headroom_limit(tmp_path, n):
    """The same numbers as CuPy arrays, summed where they are (``device_reducer``): NCCL
    where every rank has a GPU of its own, else through a host buffer (ranks sharing a GPU,
    which NCCL refuses); exact modulo 2^64, and the 32-bit halves of ``sum_checked`` on the
    device where three ranks' cells pass 2^64 together."""
    import cupy

    out = tmp_path / f"dsums{n}.npz"
    mpiexec(n, sys.executable, str(ROOT / "tests" / "mpi" / "sum_ranks.py"), str(out), "cuda", timeout=180)
    res = np.load(out)
    check_rank_sums(res, n)
    gpus = cupy.cuda.runtime.getDeviceCount()
    assert str(res["reducer"]) == ("nccl" if 1 < n <= gpus else "host"), (n, gpus, str(res["reducer"]))


@pytest.mark.skipif(TEST_BACKEND != "cuda", reason="NCCL: run with NEBULA_RT_TEST_BACKEND=cuda on a GPU machine")
def test_nccl_loads_and_sums_in_place():
    """NCCL loads with CuPy on a GPU machine, and the reducer's in-place all-reduce of a
    uint64 array (here over a one-rank communicator: every value kept, past 2^63 too) runs
    on the current stream after the kernel that wrote the array."""
    import cupy

    from nebula_rt.backends import parallel

    nccl = parallel._nccl()
    assert nccl is not None, "cupy.cuda.nccl does not load"
    reducer = parallel.NcclReducer(nccl, nccl.NcclCommunicator(1, nccl.get_unique_id(), 0), cupy)
    a = cupy.arange(3_000_001, dtype=cupy.uint64) * cupy.uint64(0x9E3779B97F4A7C15)
    want = a.get()
    assert reducer.sum_u64(a) is a
    assert a.get().tobytes() == want.tobytes()
    with pytest.raises(TypeError):
        reducer.sum_u64(cupy.zeros(4, cupy.uint32))


def test_cli_render_under_mpiexec_writes_the_one_rank_file(tmp_path):
    """`mpiexec -n N nebula-rt render`: rank 0 writes the .vti (one file, no temporaries left)
    and its arrays are the one-rank run's, byte for byte, for N = 1, 2, 3."""
    from nebula_rt.filters.vti import read_vti

    scene = ROOT / "examples" / "scenes" / "thesis-default.toml"
    exe = str(Path(sys.executable).with_name("nebula-rt"))
    arrays = {}
    for n in (1, 2, 3):
        out = tmp_path / f"n{n}" / "out.vti"
        out.parent.mkdir()
        mpiexec(n, exe, "render", str(scene), "-o", str(out), "--device", TEST_DEVICE,
                "--set", "grid.shape=[20,20,20]", "--set", "transport.photons=20000", "-q")
        assert sorted(p.name for p in out.parent.iterdir()) == ["out.vti"]
        arrays[n] = read_vti(out)[0]
    for n in (2, 3):
        assert arrays[n].keys() == arrays[1].keys()
        for name, a in arrays[1].items():
            assert arrays[n][name].tobytes() == a.tobytes(), (n, name)


def _long_render(out, quiet=True):
    """`mpiexec -n 2 nebula-rt render` of 1e9 packets into ``out``, started (a Popen).
    ``quiet=False``: rank 0 shows its progress bar on stderr (see :class:`_Stderr`)."""
    scene = ROOT / "examples" / "scenes" / "thesis-default.toml"
    exe = str(Path(sys.executable).with_name("nebula-rt"))
    return subprocess.Popen([shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe", "-n", "2", exe,
                             "render", str(scene), "-o", str(out), "--device", TEST_DEVICE,
                             "--set", "grid.shape=[16,16,16]", "--set", "transport.photons=1e9",
                             *(["-q"] if quiet else [])],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


class _Stderr:
    """The stderr of a running job, read as it comes (a thread), so that a test can wait until
    the trace runs: rank 0's progress bar shows a speed once packets are traced."""

    def __init__(self, proc):
        import threading

        self.proc, self.parts = proc, []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for chunk in iter(lambda: self.proc.stderr.read(256), ""):
            self.parts.append(chunk)

    @property
    def text(self) -> str:
        return "".join(self.parts)

    def wait_for_tracing(self, timeout: float = 120.0) -> None:
        """Until the bar shows a measured speed ("65.5kpkt/s"): the start-up (kernel builds
        included, seconds on a cold cache) is over and launches run, each of about 0.25 s."""
        import re
        import time

        deadline = time.monotonic() + timeout
        while not re.search(r"\d[kMG]?pkt/s", self.text):
            assert self.proc.poll() is None and time.monotonic() < deadline, self.text[-2000:]
            time.sleep(0.1)

    def finish(self, timeout: float) -> str:
        self.proc.wait(timeout=timeout)
        self.thread.join(timeout=10)
        return self.text


def _rank_pids(out, n: int = 2, timeout: float = 60.0) -> list:
    """The process ids of the ranks of the job writing ``out``, in rank order."""
    import time

    pids = {}
    deadline = time.monotonic() + timeout
    while len(pids) < n and time.monotonic() < deadline:
        for pid in os.listdir("/proc"):
            if not pid.isdigit():
                continue
            try:
                env = open(f"/proc/{pid}/environ", "rb").read().split(b"\0")
                cmd = open(f"/proc/{pid}/cmdline", "rb").read()
            except OSError:
                continue
            ranks = [e for e in env if e.startswith(b"OMPI_COMM_WORLD_RANK=")]
            if ranks and str(out).encode() in cmd:
                pids[int(ranks[0].split(b"=")[1])] = int(pid)
        time.sleep(0.2)
    assert len(pids) == n, f"ranks not found: {pids}"
    return [pids[r] for r in range(n)]


def test_ctrl_c_under_mpiexec_ends_every_rank_and_writes_nothing(tmp_path):
    """A SIGINT to mpiexec during a long run: mpiexec passes SIGTERM to every rank one second
    later (Open MPI 4.1; SIGKILL one more second on), all ranks stop together after their
    current launch (they check for a cancel together after every launch of about 0.25 s),
    rank 0 alone says so, nothing is written and no temporary file is left. The job's status
    is mpiexec's own, 1: Open MPI's mpiexec sets it when it is signalled, whatever the ranks
    return (the ranks' 143 shows where the ranks are signalled themselves, below)."""
    import signal
    import time

    out = tmp_path / "o.vti"
    proc = _long_render(out, quiet=False)
    err = _Stderr(proc)
    err.wait_for_tracing()
    proc.send_signal(signal.SIGINT)
    t0 = time.perf_counter()
    text = err.finish(timeout=30)
    elapsed = time.perf_counter() - t0
    assert proc.returncode != 0 and elapsed < 5.0, (proc.returncode, elapsed, text[-1500:])
    assert text.count("nebula-rt: transport cancelled") == 1 and "rank 1" not in text, text[-1500:]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("sig,status", [("SIGTERM", 143), ("SIGINT", 130)])
def test_signalled_ranks_exit_with_the_serial_status(tmp_path, sig, status):
    """The signal sent to the ranks themselves (as a batch system stops a job's tasks): every
    rank exits with a serial run's status, 143 for SIGTERM and 130 for SIGINT, and so does
    mpiexec; rank 0 alone prints the cancel; nothing is written."""
    import signal
    import time

    out = tmp_path / "o.vti"
    proc = _long_render(out, quiet=False)
    err = _Stderr(proc)
    err.wait_for_tracing()
    for pid in _rank_pids(out):
        os.kill(pid, getattr(signal, sig))
    t0 = time.perf_counter()
    text = err.finish(timeout=30)
    assert proc.returncode == status and time.perf_counter() - t0 < 5.0, (proc.returncode, text[-1500:])
    assert text.count("transport cancelled") == 1 and "nebula-rt: transport cancelled" in text, text[-1500:]
    assert "MPI_ABORT" not in text and list(tmp_path.iterdir()) == []


def _mpiexec_cli(*argv, quiet=False, timeout=120):
    """`mpiexec -n 2 nebula-rt ARGV` (``quiet``: mpiexec's -q, which leaves out Open MPI's
    notice about ranks that exited non-zero); the finished CompletedProcess."""
    exe = str(Path(sys.executable).with_name("nebula-rt"))
    env = dict(os.environ)
    env.pop("POCL_CPU_MAX_CU_COUNT", None)
    return subprocess.run([shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe",
                           *(["-q"] if quiet else []), "-n", "2", exe, *argv],
                          capture_output=True, text=True, timeout=timeout, env=env)


def test_bad_input_under_mpiexec_is_one_message_and_the_serial_status(tmp_path):
    """A bad scene value, and a bad option, under mpiexec: rank 0 alone prints the serial run's
    message, no rank aborts the job (no MPI_ABORT notice), and every rank, so the job, exits 2.
    Open MPI's mpiexec adds a notice of its own for ranks that exit non-zero unless run with
    -q; with -q the message is all there is on stderr."""
    scene = ROOT / "examples" / "scenes" / "thesis-default.toml"
    out = tmp_path / "o.vti"
    bad = ["render", str(scene), "-o", str(out), "--set", "transport.photons=-5", "-q"]
    message = "nebula-rt: invalid scene: transport.photons = -5: must be an integer in [1, 2**53]; nothing written\n"
    r = _mpiexec_cli(*bad)
    assert r.returncode == 2 and r.stderr.count("invalid scene") == 1 and message in r.stderr, r.stderr
    assert "rank 1" not in r.stderr and "MPI_ABORT" not in r.stderr and "ORTE_ERROR" not in r.stderr, r.stderr
    r = _mpiexec_cli(*bad, quiet=True)
    assert (r.returncode, r.stderr) == (2, message)
    r = _mpiexec_cli("render", str(scene), "-o", str(out), "--no-such-option", quiet=True)
    assert r.returncode == 2 and r.stderr.count("usage: nebula-rt") == 1, r.stderr
    assert r.stderr.count("error: unrecognized arguments: --no-such-option") == 1, r.stderr
    assert list(tmp_path.iterdir()) == []


def test_one_rank_failing_at_start_up_is_reported_once(tmp_path):
    """Rank 1 alone cannot build kernels (its PoCL kernel cache folder cannot be made: its
    XDG_CACHE_HOME lies below a regular file) while rank 0 starts up fine: the ranks agree at
    the end of the start-up, rank 0 prints rank 1's message (the rank and the folder named),
    every rank exits 3 as a serial run would, and nothing is written."""
    scene = ROOT / "examples" / "scenes" / "thesis-default.toml"
    out = tmp_path / "out" / "o.vti"
    out.parent.mkdir()
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    exe = str(Path(sys.executable).with_name("nebula-rt"))
    args = [exe, "render", str(scene), "-o", str(out), "--device", TEST_DEVICE, "--set", "grid.shape=[8,8,8]",
            "--set", "transport.photons=1000", "-q"]
    env = dict(os.environ)
    env.pop("POCL_CPU_MAX_CU_COUNT", None)
    env.pop("POCL_CACHE_DIR", None)
    r = subprocess.run([shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe", "-q", "-n", "1", *args,
                        ":", "-n", "1", "-x", f"XDG_CACHE_HOME={blocker / 'cache'}",
                        "-x", f"MPLCONFIGDIR={tmp_path / 'mpl'}", *args],
                       capture_output=True, text=True, timeout=300, env=env)
    folder = str(blocker / "cache" / "pocl" / "kcache")
    assert r.returncode == 3, (r.returncode, r.stderr[-2000:])
    assert r.stderr.startswith("nebula-rt (rank 1 of 2): transport.backend = 'opencl': PoCL cannot use its "
                               f"kernel cache folder {folder!r} (Not a directory)"), r.stderr[-2000:]
    assert r.stderr.count("\n") == 1, r.stderr
    assert list(out.parent.iterdir()) == []


def test_one_rank_failing_ends_the_job_naming_the_rank(tmp_path):
    """Rank 1 alone raises a device error in its second launch (tests/faults/cli_with_fault.py
    wraps the real launch): it names itself and the cause, ends the whole job (MPI_Abort: rank
    0 would otherwise wait in its next reduction forever) with status 1, and nothing is
    written."""
    import time

    scene = ROOT / "examples" / "scenes" / "thesis-default.toml"
    out = tmp_path / "o.vti"
    t0 = time.perf_counter()
    r = subprocess.run([shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe", "-n", "2",
                        sys.executable, str(ROOT / "tests" / "faults" / "cli_with_fault.py"), "rank1-fails", "-", "--",
                        "render", str(scene), "-o", str(out), "--device", TEST_DEVICE,
                        "--set", "grid.shape=[16,16,16]", "--set", "transport.photons=3e6", "-q"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and time.perf_counter() - t0 < 60
    assert "nebula-rt (rank 1 of 2): the device lost its context (injected on rank 1)" in r.stderr, r.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []


def test_a_killed_rank_ends_the_job(tmp_path):
    """SIGKILL to rank 1 during a long run: mpiexec ends the other rank too (no hang), with a
    non-zero status, and nothing is written."""
    import signal
    import time

    out = tmp_path / "o.vti"
    proc = _long_render(out)
    rank1 = _rank_pids(out, timeout=30)[1]
    time.sleep(2.0)  # tracing by now
    os.kill(rank1, signal.SIGKILL)
    t0 = time.perf_counter()
    proc.communicate(timeout=60)
    assert proc.returncode != 0 and time.perf_counter() - t0 < 30
    assert list(tmp_path.iterdir()) == []


def _observing_case(tmp_path, command):
    """The command line of a ``sky``, ``compare --table`` or ``fit`` run on the small scenes of
    tests/cli/test_hostile_numbers.py, writing into ``tmp_path/out``, and the file to compare."""
    from test_hostile_numbers import COLOUR_SCENE, SKY_SCENE, TABLES
    from nebula_rt.scene import Scene

    (tmp_path / "colour.toml").write_text(Scene.from_dict(COLOUR_SCENE).to_toml())
    (tmp_path / "sky.toml").write_text(Scene.from_dict(SKY_SCENE).to_toml())
    (tmp_path / "colour.csv").write_text(TABLES["colour.csv"])
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    colour, table = str(tmp_path / "colour.toml"), str(tmp_path / "colour.csv")
    if command == "sky":
        return ["sky", str(tmp_path / "sky.toml"), "--size", "16", "--fits", str(out / "s.fits"), "-q"], out / "s.fits"
    if command == "compare":
        return ["compare", colour, "--table", table, "--size", "16", "--png", str(out / "c.png"),
                "--json", str(out / "c.json")], out / "c.json"
    return ["fit", colour, "--table", table, "--free", "albedo", "--grid", "3", "--starts", "1",
            "--uncertainty", "profile", "--size", "16", "--png", str(out / "f.png"), "--json", str(out / "f.json"),
            "-q"], out / "f.json"


def _observed(path: Path):
    """What a run's output says, without what names the run (paths, wall time)."""
    import json

    if path.suffix == ".fits":
        from astropy.io import fits

        with fits.open(path) as hdus:
            return [h.data.tobytes() for h in hdus if h.data is not None]
    data = json.loads(path.read_text())
    for key in ("png", "scene", "wall_s"):
        data.pop(key, None)
    return data


@pytest.mark.parametrize("command", ["sky", "compare", "fit"])
def test_observing_commands_under_mpiexec_give_the_serial_outputs(tmp_path, command):
    """`mpiexec -n 2 nebula-rt sky | compare --table | fit`: the ranks share every trace (a fit's
    every trial: each ends with the same bits on both ranks, so both take the same steps), rank
    0 alone writes, and the outputs are the serial run's (the FITS images' bytes; the
    summaries' every number: chi^2, the best fit and its errors)."""
    argv, out = _observing_case(tmp_path, command)
    exe = str(Path(sys.executable).with_name("nebula-rt"))
    serial = subprocess.run([exe, *argv], capture_output=True, text=True, timeout=300)
    assert serial.returncode == 0, serial.stderr[-2000:]
    one = _observed(out)
    written = sorted(p.name for p in out.parent.iterdir())
    for p in out.parent.iterdir():
        p.unlink()
    r = _mpiexec_cli(*argv, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in out.parent.iterdir()) == written
    assert _observed(out) == one
    assert "rank 1" not in r.stderr


@pytest.mark.parametrize("command", ["sky", "compare", "fit"])
def test_bad_input_to_observing_commands_under_mpiexec_is_one_message(tmp_path, command):
    """A bad scene value under mpiexec: one message from rank 0 and status 2 (not a message per
    rank and Open MPI's MPI_ABORT notice), nothing written."""
    argv, out = _observing_case(tmp_path, command)
    r = _mpiexec_cli(*argv, "--set", "transport.photons=-5", quiet=True)
    assert r.returncode == 2 and r.stderr.count("nebula-rt: invalid scene: transport.photons = -5") == 1, r.stderr
    assert r.stderr.count("\n") == 1, r.stderr
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize("case", ["mask-stars", "dust-file-fifo", "dust-file-truncated"])
def test_refusals_of_the_inputs_read_before_the_trace_are_one_message_under_mpiexec(tmp_path, case):
    """compare --image with --mask-stars covering every pixel, and a density file that is a
    FIFO or a truncated .npy: refused before the trace, but in a step each rank ran on its own
    (the comparison's preparation, the density's first read in the trace), so each rank told
    it and rank 0 aborted the job (MPI_ABORT). Now they are refused in the start-up: one
    message, status 2, nothing written."""
    from astropy.io import fits

    from test_hostile_numbers import SKY_SCENE
    from nebula_rt.observe import calibrate
    from nebula_rt.scene import Scene

    out = tmp_path / "out"
    out.mkdir()
    if case == "mask-stars":
        scene = Scene.from_dict(SKY_SCENE)
        (tmp_path / "sky.toml").write_text(scene.to_toml())
        header = calibrate.celestial_wcs(scene, calibrate.camera_for(scene, size=16)).to_header()
        header["BUNIT"] = "MJy/sr"
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.ones((16, 16)), header=header)]).writeto(
            tmp_path / "obs.fits")
        argv = ["compare", str(tmp_path / "sky.toml"), "--image", str(tmp_path / "obs.fits"), "--image-band", "G",
                "--image-error", "5%", "--size", "16", "--png", str(out / "c.png"), "--mask-stars", "1e308",
                "--device", TEST_DEVICE]
        words = "--mask-stars = 1e+308"
    else:
        density = tmp_path / "d.npy"
        if case == "dust-file-fifo":
            os.mkfifo(density)
        else:
            np.save(density, np.ones((8, 8, 8)))
            density.write_bytes(density.read_bytes()[:300])
        (tmp_path / "s.toml").write_text(f'[grid]\nshape = [8, 8, 8]\n[dust]\nmodel = "file"\nfile = "{density}"\n')
        argv = ["render", str(tmp_path / "s.toml"), "-o", str(out / "o.vti"), "--device", TEST_DEVICE]
        words = "dust.file = "
    r = _mpiexec_cli(*argv, quiet=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and words in r.stderr, r.stderr
    assert "rank 1" not in r.stderr and "MPI_ABORT" not in r.stderr, r.stderr
    assert list(out.iterdir()) == []


def test_signalled_ranks_of_a_fit_stop_together(tmp_path):
    """SIGTERM to both ranks of a fit between or within its traces: the ranks decide the cancel
    together (in the trace, and between traces: a rank that stopped alone would leave the other
    waiting in the next trace forever), exit 143 with one message, and write nothing."""
    import signal
    import time

    argv, out = _observing_case(tmp_path, "fit")
    argv = [a for a in argv if a != "-q"] + ["--free", "g", "--grid", "6", "--set", "transport.photons=40000"]
    exe = str(Path(sys.executable).with_name("nebula-rt"))
    proc = subprocess.Popen([shutil.which("mpiexec"), "--allow-run-as-root", "--oversubscribe", "-n", "2", exe,
                             *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err = _Stderr(proc)
    deadline = time.monotonic() + 120
    while "best chi2" not in err.text:  # the fit has traced its first trial
        assert proc.poll() is None and time.monotonic() < deadline, err.text[-2000:]
        time.sleep(0.1)
    for pid in _rank_pids(out.parent / "f.png"):
        os.kill(pid, signal.SIGTERM)
    text = err.finish(timeout=60)
    assert proc.returncode == 143, (proc.returncode, text[-1500:])
    assert text.count("nebula-rt: fit cancelled") == 1 and "rank 1" not in text and "MPI_ABORT" not in text, text[-1500:]
    assert list(out.parent.iterdir()) == []
