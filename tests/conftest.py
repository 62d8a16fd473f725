"""Shared fixtures: every test runs on PoCL (OpenCL on the CPU), pinned by name.

Two PoCL platforms may be present (the pip wheel and Debian's ICD); the selector picks the
first usable device whose name contains the text, so results are reproducible on a machine.
Set NEBULA_RT_TEST_DEVICE to run the suite on another OpenCL device (e.g. "NVIDIA"), or
NEBULA_RT_TEST_BACKEND=cuda to run the physics tests on the CUDA backend (device selector from
NEBULA_RT_TEST_DEVICE, default the first CUDA device).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from nebula_rt.backends import get_backend
from nebula_rt.optics.bands import Band
from nebula_rt.scene import Star

TEST_BACKEND = os.environ.get("NEBULA_RT_TEST_BACKEND", "opencl")
TEST_DEVICE = os.environ.get("NEBULA_RT_TEST_DEVICE", "Portable Computing Language" if TEST_BACKEND == "opencl" else "")


@pytest.fixture(scope="session")
def backend():
    return get_backend(TEST_BACKEND, TEST_DEVICE)


def tuned_backend(tuning):
    """A new backend of the test device with transport kernel options ``tuning`` (see
    ``backends.base.TRANSPORT_TUNING``; ``NRT_REGIONS`` and the ``region_*`` keys for the
    transport by regions)."""
    if TEST_BACKEND == "cuda":
        from nebula_rt.backends.cuda import CUDABackend

        return CUDABackend(TEST_DEVICE, transport_tuning=tuning)
    from nebula_rt.backends.opencl import OpenCLBackend

    return OpenCLBackend(TEST_DEVICE, transport_tuning=tuning)


def one_band(albedo=0.6, g=0.6, extinction=1.0, name="V", wavelength=550.0):
    """A single band; extinction 1 makes it the reference band, so sigma = tau * rho."""
    return [Band(name=name, wavelength=wavelength, extinction=extinction, albedo=albedo, g=g)]


def centre_star(luminosity=1.0, position=(0.5, 0.5, 0.5)):
    return [Star(position=tuple(position), luminosity=luminosity, temperature=None, bump_radius=0.0)]


def voxel_centres(shape):
    axes = [(np.arange(n) + 0.5) / n for n in shape]
    return np.meshgrid(*axes, indexing="ij")


@pytest.fixture
def small_fs(tmp_path):
    """A real 256 KiB file system (tmpfs) to fill up, and a read-only one; root only (mount),
    skipped elsewhere with the reason. Yields (writable folder, read-only folder)."""
    import subprocess

    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    rw, ro = tmp_path / "small", tmp_path / "readonly"
    rw.mkdir()
    ro.mkdir()
    for path, opts in ((rw, "size=256k"), (ro, "size=64k,ro")):
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True, text=True)
        if r.returncode != 0:
            subprocess.run(["umount", str(rw)], capture_output=True)
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield rw, ro
    finally:
        for path in (rw, ro):
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


# -- ParaView (tests/paraview/test_paraview.py, tests/paraview/test_paraview_gui.py) ----------------------------
REPO = Path(__file__).resolve().parents[1]
PV_ENV = REPO / "scripts" / "pv-env.sh"
#: variables of the test process that must not leak into ParaView's Python
SCRUB = ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "NEBULA_RT_SITE_PACKAGES", "PV_PLUGIN_PATH",
         "VTK_DEFAULT_OPENGL_WINDOW", "DISPLAY")


@pytest.fixture(scope="session")
def pv_env():
    """os.environ as scripts/pv-env.sh leaves it (sourced in a clean bash)."""
    missing = [exe for exe in ("pvpython", "pvbatch", "Xvfb") if shutil.which(exe) is None]
    if missing:
        pytest.fail(f"ParaView tests need {', '.join(missing)}: run `bash scripts/setup.sh` as root "
                    "(apt packages paraview python3-paraview xvfb pocl-opencl-icd)")
    base = {k: v for k, v in os.environ.items() if k not in SCRUB}
    proc = subprocess.run(["bash", "-c", 'source "$1" && source "$1" && env -0', "pv-env", str(PV_ENV)],
                          env=base, capture_output=True, check=False, timeout=60)
    if proc.returncode != 0:
        pytest.fail(f"sourcing {PV_ENV} failed: {proc.stderr.decode(errors='replace')}")
    env = dict(item.split("=", 1) for item in proc.stdout.decode().split("\0") if "=" in item)
    site = env.get("NEBULA_RT_SITE_PACKAGES", "")
    if not site or not all(os.path.isdir(d) for d in site.split(os.pathsep)):
        pytest.fail(f"ParaView's packages ({site or 'NEBULA_RT_SITE_PACKAGES unset'}) are missing: "
                    "run `bash scripts/setup.sh` (it makes .venv-pv)")
    # sourced twice: nothing is added twice
    real = os.path.realpath
    assert [real(p) for p in env["PYTHONPATH"].split(os.pathsep)].count(real(REPO / "plugin" / "site")) == 1
    assert [real(p) for p in env["PV_PLUGIN_PATH"].split(os.pathsep)] == [real(REPO / "plugin")]
    assert len(site.split(os.pathsep)) == 1
    env.setdefault("NEBULA_RT_TEST_DEVICE", "Portable Computing Language")
    return env


@pytest.fixture(scope="session")
def xdisplay(pv_env, tmp_path_factory):
    """One Xvfb for the whole session on a free display number (killed at the end).

    Its messages go to a file, never to a pipe: Xvfb writes the keymap compiler's warnings
    (about 1 KB) each time its last client leaves and it resets, and a pipe that nobody reads
    fills after some dozens of ParaView runs; Xvfb then blocks in write() and refuses every
    later connection ("bad X server connection"). ``-noreset`` keeps it from resetting at all."""
    log = tmp_path_factory.mktemp("xvfb") / "xvfb.log"
    start = 100 + os.getpid() % 300
    for n in list(range(start, 420)) + list(range(100, start)):
        if os.path.exists(f"/tmp/.X11-unix/X{n}") or os.path.exists(f"/tmp/.X{n}-lock"):
            continue
        with open(log, "ab") as err:
            proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", "1280x1024x24", "-nolisten", "tcp",
                                     "-noreset"], stdout=subprocess.DEVNULL, stderr=err)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and proc.poll() is None:
            if os.path.exists(f"/tmp/.X11-unix/X{n}") and _accepts(f"/tmp/.X11-unix/X{n}"):
                break
            time.sleep(0.05)
        if proc.poll() is None and os.path.exists(f"/tmp/.X11-unix/X{n}"):
            break
        # lost a race for this number (or Xvfb failed): try the next one
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    else:
        pytest.fail("could not start Xvfb on any display :100-:419")
    try:
        yield f":{n}"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _accepts(path) -> bool:
    """The X server listens on its socket (the file can appear before it accepts)."""
    import socket

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        try:
            sock.connect(path)
            return True
        except OSError:
            return False
