"""Shared fixtures: every test runs on PoCL (OpenCL on the CPU), pinned by name.

Two PoCL platforms may be present (the pip wheel and Debian's ICD); the selector picks the
first usable device whose name contains the text, so results are reproducible on a machine.
Set NEBULA_RT_TEST_DEVICE to run the suite on another OpenCL device (e.g. "NVIDIA"), or
NEBULA_RT_TEST_BACKEND=cuda to run the physics tests on the CUDA backend (device selector from
NEBULA_RT_TEST_DEVICE, default the first CUDA device).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from nebula_rt.backends import get_backend
from nebula_rt.bands import Band
from nebula_rt.scene import Star

TEST_BACKEND = os.environ.get("NEBULA_RT_TEST_BACKEND", "opencl")
TEST_DEVICE = os.environ.get("NEBULA_RT_TEST_DEVICE", "Portable Computing Language" if TEST_BACKEND == "opencl" else "")


@pytest.fixture(scope="session")
def backend():
    return get_backend(TEST_BACKEND, TEST_DEVICE)


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
