"""Kernel builds and the compilers' kernel caches (nebula_rt.backends.kernel_cache).

A cache that cannot be used is reported as such, naming its folder (exit 3), not as a missing
OpenCL driver or a device that cannot build the kernels; a build that failed in the cache for
a moment (its folder removed while the process runs, a file in it that lost a race with
another process) is built once more, with a cache of its own. The builds are real PoCL builds;
where a failure cannot be made real on demand (a race) it is injected once
(tests/faults/cli_with_fault.py, or a wrapped pyopencl cache step).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest
from conftest import TEST_BACKEND, TEST_DEVICE

from nebula_rt.backends import kernel_cache, opencl
from nebula_rt.errors import KernelCacheError

pytestmark = pytest.mark.skipif(TEST_BACKEND != "opencl", reason="the OpenCL compilers' caches")

ROOT = Path(__file__).resolve().parents[2]
FAULT = ROOT / "tests" / "faults" / "cli_with_fault.py"
SCENE = ROOT / "examples" / "scenes" / "thesis-default.toml"
TINY = ["--set", "grid.shape=[8,8,8]", "--set", "transport.photons=1000", "-q"]

#: a kernel that writes a value, so that a build is seen to work
SOURCE = "__kernel void put(__global int *a, int v) { a[get_global_id(0)] = v; }\n"


def _env(tmp_path, **changes):
    """The test's environment with ``changes`` (None: removed); matplotlib (imported by
    colour-science) gets a cache of its own, so that an unusable XDG_CACHE_HOME does not make
    it warn."""
    env = dict(os.environ, MPLCONFIGDIR=str(tmp_path / "mpl"))
    env.pop("DISPLAY", None)
    for key, value in changes.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = str(value)
    return env


def _cli(env, *args, script=()):
    cmd = [sys.executable, *script] if script else [sys.executable, "-m", "nebula_rt.cli"]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=300, env=env)


def _works(program, context) -> bool:
    """The built program's kernel runs and writes its value."""
    queue = cl.CommandQueue(context)
    out = np.zeros(4, np.int32)
    buf = cl.Buffer(context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    program.put(queue, (4,), None, buf, np.int32(7))
    cl.enqueue_copy(queue, out, buf)
    queue.finish()
    return out.tolist() == [7, 7, 7, 7]


@pytest.mark.parametrize("env,expected", [
    ({"POCL_CACHE_DIR": "/c", "XDG_CACHE_HOME": "/x", "HOME": "/h"}, "/c"),
    ({"XDG_CACHE_HOME": "/x", "HOME": "/h"}, "/x/pocl/kcache"),
    ({"XDG_CACHE_HOME": "", "HOME": "/h"}, "/h/.cache/pocl/kcache"),
    ({"HOME": "/h", "POCL_KERNEL_CACHE": "0"}, "/h/.cache/pocl/uncached"),
    ({}, "/tmp/pocl/kcache"),
])
def test_pocl_cache_folder_follows_pocls_rule(env, expected):
    assert kernel_cache.pocl_cache_folder(env) == Path(expected)


@pytest.mark.parametrize("log,blames_files", [
    # the suite's failure under load: clang lost a rename in the shared cache
    ("error: unable to rename temporary '/root/.cache/pocl/kcache/tempfile_Ab12Cd.preproc.cl-3f9a1b2c' "
     "to output file '/root/.cache/pocl/kcache/tempfile_Ab12Cd.preproc.cl': 'No such file or directory'\n"
     "Device pthread-AMD EPYC failed to build the program\n", True),
    # PoCL's whole log when its cache folder went away
    ("Device pthread-AMD EPYC failed to build the program\n", True),
    # the compiler's verdict on the source
    ("error: /root/.cache/pocl/kcache/tempfile_x.cl:2:2: this device cannot build\n"
     "Device pthread-AMD EPYC failed to build the program\n", False),
    ("<kernel>:3:5: error: use of undeclared identifier 'x'\n", False),
])
def test_build_logs_that_blame_the_cache(log, blames_files):
    assert kernel_cache.build_log_blames_files(log) is blames_files


def test_unusable_cache_folder_is_named_not_a_missing_driver(tmp_path):
    """XDG_CACHE_HOME and HOME below a regular file: PoCL cannot make its cache folder and
    lists no devices. `nebula-rt devices` and `render` exit 3 naming the folder and what to
    set, not "no OpenCL platform found"; nothing is written."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    env = _env(tmp_path, XDG_CACHE_HOME=blocker / "cache", HOME=blocker, POCL_CACHE_DIR=None)
    folder = str(blocker / "cache" / "pocl" / "kcache")
    out = tmp_path / "out.vti"
    for args in (["devices"], ["render", str(SCENE), "-o", str(out), "--device", TEST_DEVICE, *TINY]):
        r = _cli(env, *args)
        assert r.returncode == 3, (args, r.returncode, r.stdout, r.stderr)
        assert r.stderr.count("\n") == 1 and f"PoCL cannot use its kernel cache folder {folder!r}" in r.stderr
        assert "Not a directory" in r.stderr and "POCL_CACHE_DIR" in r.stderr, r.stderr
        assert "no OpenCL platform" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()


def test_read_only_cache_folder_is_named(tmp_path, small_fs):
    """POCL_CACHE_DIR on a read-only file system: PoCL starts (the folder exists) but every
    build fails with nothing in its log. The render is refused before tracing (exit 3),
    naming the folder and the cause; `nebula-rt devices` says why the devices are not usable."""
    _, readonly = small_fs
    env = _env(tmp_path, POCL_CACHE_DIR=readonly)
    out = tmp_path / "out.vti"
    r = _cli(env, "render", str(SCENE), "-o", str(out), "--device", TEST_DEVICE, *TINY)
    assert r.returncode == 3, (r.returncode, r.stderr)
    assert f"PoCL cannot use its kernel cache folder {str(readonly)!r} (Read-only file system)" in r.stderr, r.stderr
    assert "cannot build the NebulaRT kernels" not in r.stderr and not out.exists()
    r = _cli(env, "devices")
    assert r.returncode == 0 and "NOT usable" in r.stdout and "Read-only file system" in r.stdout, r.stdout


def test_cache_folder_removed_while_running_is_made_again(tmp_path):
    """PoCL's cache folder is removed just before the first build of a process (the fault:
    the build then fails in PoCL for real, as when another process cleans the cache): the
    folder is made again, the build retried, and the device is usable."""
    folder = tmp_path / "kcache"
    folder.mkdir()
    r = _cli(_env(tmp_path, POCL_CACHE_DIR=folder), "cache-vanishes", "-", "--", "devices", script=[str(FAULT)])
    assert "fault: PoCL's kernel cache folder removed" in r.stderr, r.stderr
    assert r.returncode == 0 and "NOT usable" not in r.stdout and "(CPU/other; usable)" in r.stdout, (r.stdout, r.stderr)
    assert folder.is_dir() and any(folder.iterdir())


def test_a_source_error_is_built_once(backend, monkeypatch):
    """A source the compiler rejects is the compiler's verdict: one build, its error raised
    as it came (no retry, no cache blamed)."""
    builds = []
    real = cl.Program.build
    monkeypatch.setattr(cl.Program, "build", lambda self, *a, **kw: builds.append(kw) or real(self, *a, **kw))
    with pytest.raises(cl.RuntimeError, match="BUILD_PROGRAM_FAILURE"):
        opencl.build_program(backend.context, SOURCE + "#error rejected\n")
    assert len(builds) == 1


@pytest.fixture
def pyopencl_caches(backend, monkeypatch):
    """pyopencl's own binary cache used for the PoCL device (for PoCL pyopencl leaves the
    caching to the driver: has_src_build_cache), so that its failures can be met on this
    machine with real builds. PoCL has started before (``backend``), so a changed
    XDG_CACHE_HOME reaches pyopencl only."""
    import pyopencl.characterize

    monkeypatch.setattr(pyopencl.characterize, "has_src_build_cache", lambda dev: False)
    monkeypatch.delenv("PYOPENCL_NO_CACHE", raising=False)
    monkeypatch.delenv("PYOPENCL_CACHE_FAILURE_FATAL", raising=False)
    return backend


def test_unusable_pyopencl_cache_is_named(pyopencl_caches, monkeypatch, tmp_path):
    """pyopencl's cache folder below a regular file: the build is refused naming pyopencl's
    folder (not pyopencl's KeyError about PYOPENCL_CACHE_FAILURE_FATAL)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    folder = kernel_cache.pyopencl_cache_folder()
    assert str(folder).startswith(str(blocker))
    with pytest.raises(KernelCacheError, match="pyopencl cannot use its kernel cache folder") as info:
        opencl.build_program(pyopencl_caches.context, SOURCE)
    assert info.value.folder == str(folder) and "Not a directory" in info.value.reason


def test_transient_pyopencl_cache_failure_is_retried_with_a_private_cache(pyopencl_caches, monkeypatch, tmp_path):
    """pyopencl's cache step fails once (the fault: a lock file that vanished); the build is
    retried with a private cache folder (cache_dir) and works."""
    import pyopencl.cache

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    real = pyopencl.cache._create_built_program_from_source_cached
    calls = []

    def failing_once(ctx, src, options, devices, cache_dir, **kw):
        calls.append(cache_dir)
        if len(calls) == 1:
            raise FileNotFoundError(2, "No such file or directory", str(tmp_path / "xdg" / "lock"))
        return real(ctx, src, options, devices, cache_dir, **kw)
    monkeypatch.setattr(pyopencl.cache, "_create_built_program_from_source_cached", failing_once)
    program = opencl.build_program(pyopencl_caches.context, SOURCE)
    assert _works(program, pyopencl_caches.context)
    assert len(calls) == 2 and calls[0] is None
    assert calls[1] is not None and not str(calls[1]).startswith(str(tmp_path))  # a private folder
    assert not os.path.exists(calls[1])  # removed after the build


def test_an_empty_pocl_cache_dir_is_no_folder(tmp_path):
    """POCL_CACHE_DIR set but empty stands for unset (PoCL 3.1 took it for a folder and
    aborted the process on an assertion)."""
    r = _cli(_env(tmp_path, POCL_CACHE_DIR=""), "devices")
    assert r.returncode == 0 and "(CPU/other; usable)" in r.stdout, (r.returncode, r.stdout, r.stderr[-2000:])
