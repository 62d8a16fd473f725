"""Fault injection: the command line's promises under interrupts, concurrency and failures.

The README promises: bad input exits 2 naming the parameter and writes nothing; a cancel
(Ctrl-C, SIGTERM) takes effect within about a second, publishes nothing, exits non-zero and
leaves no temporary file; outputs are replaced atomically, both or neither. These tests run the
real ``nebula-rt`` in subprocesses (real signals, real kernels on PoCL, real VTK files) with
faults injected at named points by ``tests/faults/cli_with_fault.py``, and check what is on
disk afterwards: the old outputs byte for byte, and no ``.nrt-*`` temporary file.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import TEST_DEVICE

HERE = Path(__file__).resolve().parents[1]  # tests/
FAULT = HERE / "faults" / "cli_with_fault.py"

SCENE = """
[grid]
shape = [16, 16, 16]
[dust]
tau = 4.0
[transport]
photons = 5000
"""


def _env():
    env = dict(os.environ)
    env.pop("DISPLAY", None)
    return env


def _cli(*args, device=True):
    dev = ["--device", TEST_DEVICE] if device and args and args[0] in ("render", "compare") else []
    return [sys.executable, "-m", "nebula_rt.cli", *args, *dev]


def run_cli(*args, timeout=120, **kw):
    return subprocess.run(_cli(*args), capture_output=True, text=True, timeout=timeout, env=_env(), **kw)


def run_fault(point, sig, *args, timeout=120):
    cmd = [sys.executable, str(FAULT), point, sig, "--", *args, "--device", TEST_DEVICE]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=_env())


@pytest.fixture
def scene_dir(tmp_path):
    (tmp_path / "s.toml").write_text(SCENE)
    return tmp_path


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".nrt-"))


def old_outputs(folder: Path, png=False):
    """Publish a first run's outputs; return their bytes (what every failed run must keep)."""
    args = ["render", str(folder / "s.toml"), "-o", str(folder / "out.vti"), "-q"]
    if png:
        args += ["--png", str(folder / "out.png")]
    r = run_cli(*args)
    assert r.returncode == 0, r.stderr
    return {name: (folder / name).read_bytes() for name in (["out.vti", "out.png"] if png else ["out.vti"])}


def assert_intact(folder: Path, before: dict):
    for name, data in before.items():
        assert (folder / name).read_bytes() == data, f"{name} changed"
    assert leftovers(folder) == []


# --------------------------------------------------------------------------- interrupts

@pytest.mark.parametrize("point,sig,status", [
    ("startup", "SIGINT", 130),
    ("mid-launch", "SIGINT", 130),
    ("mid-launch", "SIGTERM", 143),
    ("mid-launch", "SIGINTx2", 130),  # a second Ctrl-C aborts at once
    ("after-last-batch", "SIGINT", 130),  # the progress bar at 100 %: still nothing published
    ("during-write", "SIGINT", 130),
    ("during-write", "SIGTERM", 143),
    ("during-png", "SIGINT", 130),
    # a second signal inside VTK's renderer ended in SIGSEGV, and two SIGTERMs in an
    # ImportError: now the temporary files go and the process ends with the first's status
    ("during-png", "SIGINTx2", 130),
    ("during-png", "SIGTERMx2", 143),
    ("mid-launch", "SIGQUIT", 131),  # Ctrl-\\ was swallowed and the run published
])
def test_interrupt_publishes_nothing(scene_dir, point, sig, status):
    before = old_outputs(scene_dir, png=True)
    # enough packets for several launches (the first launch on a CPU is 2^16 packets)
    r = run_fault(point, sig, "render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"),
                  "--png", str(scene_dir / "out.png"), "--set", "transport.photons=200000")
    assert r.returncode == status, (r.returncode, r.stderr)
    assert "nothing written" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert_intact(scene_dir, before)


def test_a_run_removes_what_killed_runs_left_in_its_folder(scene_dir):
    """Temporary files of a process of this host that no longer runs (killed by SIGKILL, it
    could not remove them) are removed by the next run into that folder; a live process's
    and another host's stay."""
    from nebula_rt.pipeline.outputs import _host

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    host = _host()
    stale = [f".nrt-{dead}@{host}-abcd1234.tmp.vti", f".nrt-{dead}@{host}-efgh5678.bak"]
    kept = [f".nrt-{os.getpid()}@{host}-ijkl9012.tmp.png", f".nrt-{dead}@elsewhere.example-mnop3456.tmp.vti"]
    for name in stale + kept:
        (scene_dir / name).write_bytes(b"partial")
    r = run_cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"), "-q")
    assert r.returncode == 0, r.stderr
    assert leftovers(scene_dir) == sorted(kept)


@pytest.mark.parametrize("run", [
    # one batch of 3e6 packets per band: about 10 s of tracing on two cores
    ["--set", "transport.photons=6e6", "--set", "transport.batch_size=3e6"],
    # an error-targeted run with a huge budget and a time limit it will not reach first
    ["--set", "transport.photons=1e12", "--set", "transport.target_error=0.001",
     "--set", "transport.time_limit=30"],
], ids=["long-batch", "targeted-huge-budget"])
def test_ctrl_c_within_one_long_launch_is_honoured_at_once(scene_dir, run):
    """An outside SIGINT in the middle of a long run: it stops within about a second, exits 130
    and the old output stays."""
    before = old_outputs(scene_dir)
    cmd = _cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"), *run)
    import threading

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env())
    chunks: list[bytes] = []
    reader = threading.Thread(target=lambda: chunks.extend(iter(lambda: proc.stderr.read1(256), b"")))
    reader.start()
    t_start = time.monotonic()  # wait until the tracing has started (the progress bar)
    while b"tracing" not in b"".join(chunks) and time.monotonic() - t_start < 60:
        time.sleep(0.05)
    time.sleep(1.0)
    assert proc.poll() is None, "the run ended before the signal"
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:  # pragma: no cover - the defect this test is for
        proc.kill()
        pytest.fail("SIGINT ignored for 30 s")
    waited = time.monotonic() - t0
    reader.join(timeout=10)
    err = b"".join(chunks).decode(errors="replace")
    assert proc.returncode == 130, err
    # one launch lasts at most LAUNCH_SECONDS (0.25 s) plus the process's exit
    # (idle: 0.5-0.6 s; the bound leaves room for a loaded machine, the suite's other process)
    assert waited < 2.5, waited
    assert_intact(scene_dir, before)


def test_a_step_that_does_not_poll_is_ended_by_the_watchdog(scene_dir):
    """A signal while the main thread is held by a step that does not poll (here the PNG stage
    waits 120 s before rendering; in life a kernel compile in PoCL, VTK's renderer, an import):
    the watchdog ends the run GRACE_SECONDS after the signal, with the signal's status, the
    old outputs intact and no temporary file. The bound below is the stall's length, not a
    timing: only the watchdog can end the run before it."""
    before = old_outputs(scene_dir, png=True)
    t0 = time.monotonic()
    r = run_fault("stalled", "SIGTERM", "render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"),
                  "--png", str(scene_dir / "out.png"))
    assert time.monotonic() - t0 < 100, "the run waited for the stall"
    assert r.returncode == 143, (r.returncode, r.stderr)
    assert "could not stop by itself); nothing written" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert_intact(scene_dir, before)


def test_a_signal_during_a_cold_kernel_build(scene_dir, tmp_path_factory):
    """SIGINT 0.1 s into the first kernel build with every cache cold (PoCL's and pyopencl's:
    seconds of compiling on a CPU): exit 130, nothing written, no temporary file. Whether the
    build ends within the grace or the watchdog ends it, the outcome is the same."""
    before = old_outputs(scene_dir)
    caches = tmp_path_factory.mktemp("cold-caches")
    env = {**_env(), "POCL_CACHE_DIR": str(caches / "pocl"), "XDG_CACHE_HOME": str(caches / "xdg")}
    (caches / "pocl").mkdir()
    cmd = [sys.executable, str(FAULT), "during-build", "SIGINT", "--", "render", str(scene_dir / "s.toml"),
           "-o", str(scene_dir / "out.vti"), "--device", TEST_DEVICE]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert "nothing written" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert_intact(scene_dir, before)


def _has_loaded(pid: int, library: str) -> bool:
    """Whether process ``pid`` has mapped a shared library whose path contains ``library``."""
    try:
        return library in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc")
@pytest.mark.parametrize("sig,status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_while_the_command_imports_its_modules(scene_dir, sig, status):
    """A signal while the command is still importing its modules (numpy's core is loaded, the
    scene and astropy are not yet: a third of a second before its run's handlers exist): it
    ended the process by the signal's default action (a KeyboardInterrupt traceback for
    SIGINT). Now the run cancels as soon as it starts: the signal's status, one line, nothing
    written."""
    before = old_outputs(scene_dir)
    proc = subprocess.Popen(_cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti")),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    t0 = time.monotonic()
    while not _has_loaded(proc.pid, "_multiarray_umath") and proc.poll() is None and time.monotonic() - t0 < 30:
        time.sleep(0.001)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == status, (proc.returncode, err)
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("nebula-rt: "), err
    assert "nothing written" in err
    assert_intact(scene_dir, before)


def test_a_second_signal_while_a_cancelled_run_exits():
    """A second signal after a cancelled run has left its handlers, while the command exits
    (the interpreter's shutdown, which takes a moment after a trace or a PNG): it ended the
    process by the signal's default action (killed by SIGTERM, or a KeyboardInterrupt for
    SIGINT) instead of the cancel's status. The command line's handlers leave the signals
    ignored once a cancel was requested."""
    code = """if True:
        import os, signal, sys, time
        from nebula_rt.interrupts import SignalCancel
        with SignalCancel(quiet=True, ends_process=True) as cancel:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            assert cancel()
        os.kill(os.getpid(), signal.SIGTERM)  # after the block: the command is exiting
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        sys.exit(cancel.exit_status)
    """
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=_env())
    assert r.returncode == 130 and "Traceback" not in r.stderr, (r.returncode, r.stderr)


def test_importing_the_command_line_from_python_leaves_its_signals_alone():
    """Only the command (nebula-rt, python -m nebula_rt.cli) hears signals from its imports on
    and leaves them ignored after a cancel; Python that imports nebula_rt.cli (a notebook,
    these tests) keeps its Ctrl-C."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    import nebula_rt.cli  # noqa: F401
    from nebula_rt import interrupts

    assert not interrupts.is_command()
    assert {s: signal.getsignal(s) for s in before} == before


def test_nohup_keeps_sighup_ignored(scene_dir):
    """A run started with SIGHUP ignored (``nohup``) must not be cancelled by a SIGHUP (the
    terminal closing): the handlers took every signal, whatever the process inherited, and
    the run was cancelled with status 129."""
    proc = subprocess.Popen(_cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"),
                                 "--set", "transport.photons=1e6"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(),
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    err = b""
    while b"tracing" not in err and proc.poll() is None:
        err += proc.stderr.read1(256)
    proc.send_signal(signal.SIGHUP)
    err += proc.communicate(timeout=120)[1]
    assert proc.returncode == 0, err.decode(errors="replace")
    assert (scene_dir / "out.vti").exists() and leftovers(scene_dir) == []


def test_a_background_job_that_ignores_sigint_is_still_cancelled_by_it(scene_dir):
    """A shell without job control starts a background job with SIGINT and SIGQUIT ignored; a
    `kill -INT` of such a run (as these tests send) still cancels it: only SIGHUP's inherited
    ignore (nohup) is kept."""
    before = old_outputs(scene_dir)

    def background():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGQUIT, signal.SIG_IGN)

    proc = subprocess.Popen(_cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"),
                                 "--set", "transport.photons=5e7"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), preexec_fn=background)
    err = b""
    while b"tracing" not in err and proc.poll() is None:
        err += proc.stderr.read1(256)
    proc.send_signal(signal.SIGINT)
    err += proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err.decode(errors="replace")
    assert_intact(scene_dir, before)


# --------------------------------------------------------------------------- concurrency

def test_concurrent_renders_to_one_output(scene_dir):
    """Three renders with different seeds started together onto one path, twice: every one
    exits 0, the survivor is one run's complete output (bit for bit the J of the seed it
    names) and no temporary file remains."""
    from nebula_rt.filters.vti import read_vti

    out = scene_dir / "same.vti"
    for _ in range(2):
        procs = [subprocess.Popen(_cli("render", str(scene_dir / "s.toml"), "-o", str(out), "-q",
                                       "--set", f"transport.seed={seed}"),
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
                 for seed in (1, 2, 3)]
        results = [p.communicate(timeout=120) + (p.returncode,) for p in procs]
        assert [rc for _, _, rc in results] == [0, 0, 0], [e for _, e, _ in results]
        arrays, fd = read_vti(out)[:2]
        assert leftovers(scene_dir) == []
    seed = int(fd["seed"])
    assert seed in (1, 2, 3)
    alone = scene_dir / "alone.vti"
    r = run_cli("render", str(scene_dir / "s.toml"), "-o", str(alone), "-q", "--set", f"transport.seed={seed}")
    assert r.returncode == 0, r.stderr
    ref = read_vti(alone)[0]
    for name in ("J_R", "J_G", "J_B", "rgba"):
        np.testing.assert_array_equal(arrays[name], ref[name])


# --------------------------------------------------------------------------- outputs

@pytest.mark.parametrize("args,needle", [
    (["-o", "{d}/x.vti", "--png", "{d}/x.vti"], "--png"),          # the PNG would replace the .vti
    (["-o", "{d}/x.vti", "--png", "{d}/x.jpg"], "must end in .png"),
    (["-o", "{d}/x.png"], "must end in .vti"),
    (["-o", "{d}/folder.vti"], "existing folder"),
    (["-o", "{d}/missing/x.vti"], "does not exist"),
    (["-o", "{d}/" + "n" * 300 + ".vti"], "file name is"),
    (["-o", "{d}/x.vti", "--png", "{d}/link.png"], "same file"),
    (["-o", "{d}/dust.vti", "--set", 'dust.model="file"', "--set", 'dust.file="dust.vti"'], "input of the run"),
])
def test_bad_outputs_refused_before_tracing(scene_dir, args, needle):
    (scene_dir / "folder.vti").mkdir()
    (scene_dir / "x.vti").write_bytes(b"old")
    (scene_dir / "link.png").symlink_to(scene_dir / "x.vti")
    from nebula_rt.filters.vti import write_vti

    write_vti(scene_dir / "dust.vti", {"density": np.ones((16, 16, 16), np.float32)}, {}, (1 / 16,) * 3)
    dust = (scene_dir / "dust.vti").read_bytes()
    r = run_cli("render", str(scene_dir / "s.toml"), "-q", *[a.format(d=scene_dir) for a in args])
    assert r.returncode == 2, r.stderr
    assert needle in r.stderr and "nothing written" in r.stderr, r.stderr
    assert (scene_dir / "x.vti").read_bytes() == b"old" and leftovers(scene_dir) == []
    assert (scene_dir / "dust.vti").read_bytes() == dust


def test_full_and_read_only_disks(scene_dir, small_fs):
    """A disk too small for the estimate is refused before tracing ("No space left on
    device", exit 2); one that fills up during the write fails with the same words (exit 1);
    a read-only file system is refused before tracing. The old output stays in every case."""
    small, readonly = small_fs
    big = ["--set", "grid.shape=[48,48,48]"]  # about 5 MiB of arrays: more than the 256 KiB disk
    r = run_cli("render", str(scene_dir / "s.toml"), "-o", str(small / "out.vti"), "-q", *big)
    assert r.returncode == 2 and "No space left on device" in r.stderr, r.stderr
    assert list(small.iterdir()) == []
    tiny = ["--set", "grid.shape=[8,8,8]"]  # about 90 KiB
    r = run_cli("render", str(scene_dir / "s.toml"), "-o", str(small / "out.vti"), "-q", *tiny)
    assert r.returncode == 0, r.stderr
    before = {"out.vti": (small / "out.vti").read_bytes()}
    r = run_fault("fill-disk", "-", "render", str(scene_dir / "s.toml"), "-o", str(small / "out.vti"), "-q",
                  *tiny)
    assert r.returncode == 1 and "No space left on device" in r.stderr and "Traceback" not in r.stderr, r.stderr
    (small / "filler").unlink()
    assert_intact(small, before)
    r = run_cli("render", str(scene_dir / "s.toml"), "-o", str(readonly / "out.vti"), "-q")
    assert r.returncode == 2 and "cannot write" in r.stderr, r.stderr


def test_png_failure_keeps_both_old_outputs(scene_dir):
    """The .vti is staged, then the PNG fails: neither is published (both or neither)."""
    before = old_outputs(scene_dir, png=True)
    r = run_fault("png-fails", "-", "render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "out.vti"),
                  "--png", str(scene_dir / "out.png"), "--set", "transport.seed=9")
    assert r.returncode == 1 and "PNG renderer failed" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert_intact(scene_dir, before)


def test_closed_stdout_loses_only_the_summary(scene_dir):
    """With stdout closed (``1>&-``) or a reader that went away, the outputs are published and
    the exit status is 0, without a traceback."""
    import shlex

    cmd = shlex.join(_cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "c.vti")))
    r = subprocess.run(["bash", "-c", cmd + " 1>&-"], capture_output=True, text=True, timeout=120, env=_env())
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert (scene_dir / "c.vti").stat().st_size > 0
    proc = subprocess.Popen(_cli("render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "p.vti")),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    proc.stdout.close()  # the reader is gone before the summary
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 0 and "Traceback" not in err, err
    assert (scene_dir / "p.vti").stat().st_size > 0


def test_missing_vtk_is_found_before_tracing(scene_dir):
    """Without the io extra (VTK not importable) the run is refused before tracing, exit 2."""
    code = ("import sys; sys.modules['vtkmodules'] = None; from nebula_rt.cli import main; "
            f"sys.exit(main(['render', {str(scene_dir / 's.toml')!r}, '-o', {str(scene_dir / 'v.vti')!r}, "
            f"'--device', {TEST_DEVICE!r}, '-q']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=_env())
    assert r.returncode == 2 and "nebula-rt[io]" in r.stderr, r.stderr
    assert not (scene_dir / "v.vti").exists()


def test_device_that_cannot_build_the_kernels(monkeypatch, capsys, tmp_path):
    """A device whose compiler rejects the kernels is refused before a run (exit 3, the device
    and the reason named) and marked in ``nebula-rt devices``. The failure is real: the real
    PoCL compiler is given a source it cannot build."""
    from nebula_rt.cli import commands as cli
    from nebula_rt.backends import opencl

    real = opencl.kernel_source
    monkeypatch.setattr(opencl, "kernel_source", lambda name: real(name) + "\n#error this device cannot build\n")
    assert opencl.probe_device("0:0") is not None
    assert cli.main(["devices"]) == 0
    assert "NOT usable" in capsys.readouterr().out
    s = Path(__file__).resolve().parents[2] / "examples/scenes/thesis-default.toml"
    assert cli.main(["render", str(s), "-o", str(tmp_path / "x.vti"), "--device", TEST_DEVICE,
                     "--set", "grid.shape=[8,8,8]"]) == 3
    err = capsys.readouterr().err
    assert "cannot build the NebulaRT kernels" in err and TEST_DEVICE in err
    assert list(tmp_path.iterdir()) == []


def test_internal_errors_are_one_line(scene_dir):
    """An exception that is not NebulaRT's own (here raised inside the PNG renderer) is one line
    on stderr, not a traceback, and nothing is written."""
    r = run_fault("png-fails", "-", "render", str(scene_dir / "s.toml"), "-o", str(scene_dir / "new.vti"),
                  "--png", str(scene_dir / "new.png"), "-q")
    assert r.returncode == 1 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "RuntimeError" in r.stderr and not (scene_dir / "new.vti").exists()
