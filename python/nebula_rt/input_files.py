"""What an input file is, checked before it is read.

Every file a user names (the scene, ``dust.file``, ``--table``, ``--image``, a ``.vti`` into
a filter, a fit result) is read through here: it must be a regular file (a FIFO would block
the read, ``/dev/zero`` would never end, a folder or a symlink loop gives a misleading
reason), small enough for what it is (a table larger than ``MAX_TABLE_BYTES`` is not a
table), and it is opened without blocking (``O_NONBLOCK``), then checked again on the open
descriptor (``fstat``), so a file swapped for a FIFO between the check and the open cannot
hang the run. Regular files never block a read, so the reads that follow need no polling.
"""

from __future__ import annotations

import errno
import os
import stat
from typing import Optional, Union

from .errors import SceneError

#: Bytes of a text table (``--table``: CSV or ECSV rows of annuli): far above any observed
#: profile (a thousand rows are about 100 kB), far below what would strain memory.
MAX_TABLE_BYTES = 64 << 20
#: Bytes of a scene file (TOML text; the largest shipped is about 10 kB).
MAX_SCENE_BYTES = 16 << 20
#: Bytes of a fit result (JSON).
MAX_JSON_BYTES = 64 << 20

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _kind(mode: int) -> Optional[str]:
    """What a non-regular file is (None: a regular file)."""
    if stat.S_ISREG(mode):
        return None
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def _refuse(parameter: str, path, what: str, reason: str) -> SceneError:
    return SceneError(parameter, str(path), f"must be {what} ({reason})")


def check_input_file(parameter: str, path: Union[str, os.PathLike], what: str = "a readable file",
                     max_bytes: Optional[int] = None) -> os.stat_result:
    """Refuse ``path`` unless it is an existing, readable regular file of at most
    ``max_bytes`` bytes.

    Parameters
    ----------
    parameter : str
        The key or option that names the file (``dust.file``, ``--table``).
    path : str or path-like
    what : str
        What the file must be, for the message (``"a .npy or .vti file"``).
    max_bytes : int, optional
        The largest size accepted.

    Returns
    -------
    os.stat_result
        The file's status.

    Raises
    ------
    SceneError
        Naming ``parameter``, the path and why: no such file, a folder, a FIFO, a device or a
        socket, a symlink loop, no permission, or larger than ``max_bytes``.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise _refuse(parameter, path, what, "no such file") from None
    except OSError as e:
        reason = {errno.ELOOP: "a symbolic link loop",
                  errno.ENOTDIR: "a part of the path is a file, not a folder",
                  errno.EACCES: "no permission to reach it"}.get(e.errno, e.strerror or str(e))
        raise _refuse(parameter, path, what, reason) from None
    kind = _kind(st.st_mode)
    if kind is not None:
        raise _refuse(parameter, path, what, f"it is {kind}")
    if max_bytes is not None and st.st_size > max_bytes:
        raise _refuse(parameter, path, what, f"{st.st_size} bytes, more than the {max_bytes} such a file may have")
    if not os.access(path, os.R_OK):
        raise _refuse(parameter, path, what, "no permission to read it")
    return st


def open_input(parameter: str, path: Union[str, os.PathLike], what: str = "a readable file",
               max_bytes: Optional[int] = None):
    """:func:`check_input_file`, then the file opened for binary reading without blocking
    (a file replaced by a FIFO after the check is refused on the open descriptor)."""
    check_input_file(parameter, path, what, max_bytes)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as e:
        raise _refuse(parameter, path, what, e.strerror or str(e)) from None
    try:
        st = os.fstat(fd)
        kind = _kind(st.st_mode)
        if kind is not None:
            raise _refuse(parameter, path, what, f"it is {kind}")
        if max_bytes is not None and st.st_size > max_bytes:
            raise _refuse(parameter, path, what, f"{st.st_size} bytes, more than the {max_bytes} such a file may have")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_input_bytes(parameter: str, path, what: str = "a readable file", max_bytes: Optional[int] = None) -> bytes:
    """The bytes of a checked input file (:func:`open_input`)."""
    with open_input(parameter, path, what, max_bytes) as fh:
        try:
            return fh.read()
        except OSError as e:  # a regular file the kernel cannot read (EIO: /proc/self/mem, a failing disk)
            raise _refuse(parameter, path, what, e.strerror or str(e)) from None


def read_input_text(parameter: str, path, what: str = "UTF-8 text", max_bytes: Optional[int] = None) -> str:
    """The text of a checked input file, UTF-8 with or without a byte-order mark; SceneError
    naming the first byte that is not UTF-8."""
    data = read_input_bytes(parameter, path, what, max_bytes)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise _refuse(parameter, path, what, f"byte 0x{data[e.start]:02x} at offset {e.start} is not UTF-8") from None
