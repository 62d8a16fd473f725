"""The OpenCL compilers' kernel caches: where they are, whether a folder can be used, and
whether a failed build failed in the cache rather than in the source.

Two caches can take part in an OpenCL build:

- PoCL caches every build itself (pyopencl then builds from source each time and leaves the
  caching to it: ``pyopencl.characterize.has_src_build_cache``). PoCL fixes its folder when
  it initialises, at the process's first device query: ``POCL_CACHE_DIR``, else
  ``$XDG_CACHE_HOME/pocl/kcache``, else ``$HOME/.cache/pocl/kcache``, else
  ``/tmp/pocl/kcache`` (``uncached`` instead of ``kcache`` with ``POCL_KERNEL_CACHE=0``). When
  it cannot create that folder it reports no devices at all, and tries again at the next
  query, so ``POCL_CACHE_DIR`` set before then still takes effect; once it has initialised, the
  process cannot move its cache. A folder removed while the process runs is not made again:
  every later build fails, with nothing in the log but "failed to build the program".
  (PoCL 3.0 and 3.1, ``lib/CL/pocl_cache.c`` and ``devices/devices.c``.)
- pyopencl's binary cache, for the other drivers (not NVIDIA's, which caches by itself):
  ``Program.build(cache_dir=...)``, by default the user cache folder of ``platformdirs``
  (``$XDG_CACHE_HOME/pyopencl`` or ``~/.cache/pyopencl``). When that cache fails, pyopencl
  2026.1 reads ``PYOPENCL_CACHE_FAILURE_FATAL`` with ``os.environ[...]``: unset, the cache's
  ``OSError`` surfaces as a ``KeyError`` raised while handling it.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Optional


def pocl_cache_folder(environ=None) -> Path:
    """The folder PoCL keeps its kernel cache in, by the rule PoCL itself applies when it
    initialises (``environ``: the environment then; default ``os.environ``)."""
    env = os.environ if environ is None else environ
    if env.get("POCL_CACHE_DIR"):
        return Path(env["POCL_CACHE_DIR"])
    cached = env.get("POCL_KERNEL_CACHE", "1").startswith("1")  # PoCL's booleans: "1..." is true
    leaf = Path("pocl") / ("kcache" if cached else "uncached")
    if env.get("XDG_CACHE_HOME"):
        return Path(env["XDG_CACHE_HOME"]) / leaf
    if env.get("HOME") is not None:
        return Path(env["HOME"]) / ".cache" / leaf
    return Path("/tmp") / leaf


def pyopencl_cache_folder() -> Path:
    """The folder of pyopencl's binary cache for this Python (as ``pyopencl.cache`` makes it)."""
    import platformdirs

    version = ".".join(str(i) for i in sys.version_info)
    return Path(platformdirs.user_cache_dir("pyopencl", "pyopencl")) / f"pyopencl-compiler-cache-v2-py{version}"


def folder_problem(folder) -> Optional[str]:
    """None if a file can be created in ``folder`` (made first, with its parents, where it is
    missing: what the compilers do too), else why not, in the operating system's words, e.g.
    ``"Not a directory: '/home/u/.cache'"``. The probe file is removed again."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".nebula-rt-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        # name the folder above that failed, if it was one (not the probe file's random name)
        above = exc.filename is not None and Path(exc.filename) in folder.parents
        return f"{exc.strerror or type(exc).__name__}" + (f": {str(exc.filename)!r}" if above else "")
    return None


#: what a compiler's build log says when a build failed in its files rather than in the source
#: (clang's words for a rename that lost a race with another process included)
FILE_TROUBLE = ("unable to rename temporary", "no such file or directory", "permission denied",
                "read-only file system", "no space left on device", "disk quota exceeded",
                "could not write", "unable to open output file")


def build_log_blames_files(log: str) -> bool:
    """Whether a failed build's log points at the compiler's files rather than at the source:
    it names a file-system failure, or it has no diagnostic at all (PoCL's whole log, when its
    cache folder went away, is "Device ... failed to build the program"; a source the
    compiler rejects always has an ``error`` line)."""
    text = log.lower()
    return any(words in text for words in FILE_TROUBLE) or "error" not in text


#: the variable pyopencl reads when its cache failed
FAILURE_FATAL = "PYOPENCL_CACHE_FAILURE_FATAL"


def cache_failure(exc: BaseException) -> bool:
    """Whether an exception raised by ``pyopencl.Program.build`` is pyopencl's binary cache
    failing (its ``OSError``, or the ``KeyError`` it raises while handling one, see the
    module's notes) rather than the build."""
    if isinstance(exc, OSError):
        return True
    if not (isinstance(exc, KeyError) and exc.args == (FAILURE_FATAL,)):
        return False
    cause = exc.__context__  # os.environ's KeyError, raised while handling the cache's OSError
    while cause is not None and not isinstance(cause, OSError):
        cause = cause.__context__
    return cause is not None
