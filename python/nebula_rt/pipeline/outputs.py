"""Output files of a run: checked before any work starts, written to private temporary files,
published together.

Three rules keep a user's files safe:

1. Every output is checked before tracing (:func:`check_outputs`): the suffix matches what is
   written, no two outputs name the same file, none is an existing folder, the folder exists
   and accepts a new file (a probe file is created and removed, which finds read-only file
   systems and missing permissions), the name fits the file system, and the free space holds
   the estimated size. A long trace must not end in "cannot write".
2. Each output is written to its own temporary file in the target's folder, named uniquely per
   process (:func:`tempfile.mkstemp`), so concurrent runs onto one path never share a file.
3. :meth:`Publication.publish` renames the temporary files onto their targets only when all
   of them are complete; the rename is the only step that publishes. If one rename fails the
   targets already replaced are restored from hard-link backups: both or neither. Leaving the
   ``with`` block without publishing (an error, a cancel) removes every temporary file.

A signal cannot break these rules: the renames run with the cancelling signals held back,
after a last look at the cancel flag (:func:`nebula_rt.interrupts.held`); a second signal,
which ends the process at once, first removes the temporary files
(:func:`nebula_rt.interrupts.on_abort`). The temporary files carry the process's number and
host, so a run that was killed outright (SIGKILL, a power cut) leaves files the next run into
that folder removes (:func:`remove_stale`).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import signal
import socket
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

from .. import interrupts
from ..errors import CancelledError, OutputError

#: prefix of every temporary file (hidden; ``.nrt-<pid>@<host>-<random>.tmp.<suffix>``: the
#: suffix last, so writers that choose the format by suffix still do)
TMP_PREFIX = ".nrt-"
#: a temporary file's name: the process that made it, its host (tempfile's 8 random characters)
_TMP_NAME = re.compile(r"^\.nrt-(\d+)@(.+)-[a-z0-9_]{8}\.(tmp|bak)")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9._-]", "_", socket.gethostname()) or "host"


def _own_prefix() -> str:
    return f"{TMP_PREFIX}{os.getpid()}@{_host()}-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (EPERM): alive
        return True
    return True


def remove_stale(folder) -> list:
    """Remove the temporary files a dead process of this host left in ``folder`` (killed
    outright, it could not remove them); another host's files and a live process's stay.
    Returns the names removed."""
    removed = []
    host = _host()
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        m = _TMP_NAME.match(name)
        if m and m.group(2) == host and int(m.group(1)) != os.getpid() and not _alive(int(m.group(1))):
            try:
                os.unlink(os.path.join(folder, name))
                removed.append(name)
            except OSError:
                pass
    return removed


@dataclass(frozen=True)
class Output:
    """One file a run will write.

    Attributes
    ----------
    option : str
        The option or parameter naming it (``--output``), for messages.
    path : Path
    suffix : str
        The suffix the file must have (``.vti``, ``.png``, ``.json``), lower case.
    size : int
        Estimated size in bytes (an upper bound), checked against the free space.
    """

    option: str
    path: Path
    suffix: str
    size: int = 0


def _mib(n: float) -> str:
    return f"{n / 2**20:.1f} MiB" if n < 2**30 else f"{n / 2**30:.2f} GiB"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_outputs(outputs: Iterable[Output], inputs: Iterable[tuple[str, object]] = ()) -> list[Output]:
    """Check every output before any work starts (see the module notes).

    ``inputs``: (parameter, path) of the files the run reads (the scene file, ``dust.file``);
    an output may not replace one of them.

    Raises
    ------
    OutputError
        Naming the option, the path and the cause; nothing is created.
    """
    outputs = list(outputs)
    seen: dict[str, Output] = {}
    read = {}
    for param, path in inputs:
        try:
            read[os.path.normcase(os.path.realpath(path))] = (param, path)
        except (OSError, ValueError):
            pass
    need: dict[str, int] = {}  # bytes per folder
    for o in outputs:
        p = Path(o.path)
        if p.suffix.lower() != o.suffix:
            raise OutputError(o.option, p, f"must end in {o.suffix}")
        parent = p.parent if str(p.parent) else Path(".")
        try:
            name_max = os.pathconf(parent if parent.is_dir() else ".", "PC_NAME_MAX")
        except (OSError, ValueError):
            name_max = 255
        if len(os.fsencode(p.name)) > name_max:
            raise OutputError(o.option, p, f"file name is {len(os.fsencode(p.name))} bytes; "
                                           f"this file system allows {name_max}")
        try:
            key = os.path.normcase(os.path.realpath(p))
            is_dir, exists = p.is_dir(), p.exists()
        except OSError as exc:
            raise OutputError(o.option, p, exc.strerror or str(exc)) from None
        if key in seen:
            raise OutputError(o.option, p, f"is the same file as {seen[key].option} {seen[key].path}")
        if key in read:
            raise OutputError(o.option, p, f"would replace an input of the run ({read[key][0]} {read[key][1]})")
        for other in seen.values():  # hard links, or a path reached two ways
            try:
                same = exists and Path(other.path).exists() and os.path.samefile(p, other.path)
            except OSError:
                same = False
            if same:
                raise OutputError(o.option, p, f"is the same file as {other.option} {other.path}")
        seen[key] = o
        if is_dir:
            raise OutputError(o.option, p, "is an existing folder; give a file name")
        if not parent.exists():
            raise OutputError(o.option, p, f"folder {parent} does not exist")
        if not parent.is_dir():
            raise OutputError(o.option, p, f"{parent} is not a folder")
        try:  # can a new file be made there? (permissions, read-only file systems, quotas)
            fd, probe = tempfile.mkstemp(dir=parent, prefix=TMP_PREFIX, suffix=".probe")
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise OutputError(o.option, p, f"cannot write in {parent}: {exc.strerror or exc}") from None
        need[str(parent.resolve())] = need.get(str(parent.resolve()), 0) + int(o.size)
    for folder, size in need.items():
        free = shutil.disk_usage(folder).free
        if size > free:
            o = next(o for o in outputs if str(Path(o.path).parent.resolve()) == folder)
            raise OutputError(o.option, o.path,
                              f"No space left on device: the output needs up to {_mib(size)}, "
                              f"{folder} has {_mib(free)} free")
    return outputs


def describe_os_error(exc: OSError) -> str:
    """A one-line cause for an OSError of a write ("No space left on device" when it is that)."""
    if exc.errno == errno.ENOSPC:
        return "No space left on device"
    return exc.strerror or str(exc)


class Publication:
    """Stage outputs in private temporary files and publish them together.

    Use as a context manager::

        with Publication() as pub:
            write_vti(pub.stage(out), ...)
            render_png(pub.stage(png), ...)
            pub.publish()

    Leaving the block without :meth:`publish` (an exception, a cancel) removes the temporary
    files; the targets keep their old contents.
    """

    def __init__(self):
        self._staged: list[tuple[Path, Path]] = []  # (temporary, target)
        self.published = False
        self._cleaned: set = set()
        self._unhook = None

    def stage(self, target) -> Path:
        """A new, empty temporary file beside ``target`` (unique to this call) to write into;
        the first in a folder also removes what dead runs left there (:func:`remove_stale`)."""
        target = Path(target)
        folder = target.parent if str(target.parent) else Path(".")
        if folder not in self._cleaned:
            self._cleaned.add(folder)
            remove_stale(folder)
        if self._unhook is None:  # a second signal ends the process: the files go first
            self._unhook = interrupts.on_abort(self.discard)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=_own_prefix(), suffix=".tmp" + target.suffix)
        os.close(fd)
        # mkstemp makes the file private (0600); a published output gets the usual mode
        os.chmod(tmp, 0o666 & ~_umask())
        self._staged.append((Path(tmp), target))
        return Path(tmp)

    def publish(self) -> None:
        """Rename every staged file onto its target; on a failure restore the targets already
        replaced (from hard-link backups of their old contents) and raise.

        Raises
        ------
        CancelledError
            A signal asked the command to cancel (nothing is renamed); the renames run with
            the signals held back, so a signal either comes before them or after them.
        """
        with interrupts.held():
            requested = interrupts.cancel_requested()
            if requested is not None:
                raise CancelledError(f"run cancelled by {signal.Signals(requested).name}")
            self._publish()

    def _publish(self) -> None:
        done: list[tuple[Path, Optional[Path]]] = []  # (target, backup of its old contents)
        try:
            for tmp, target in self._staged:
                backup = None
                if target.exists():
                    backup = Path(tempfile.mktemp(dir=target.parent, prefix=_own_prefix(), suffix=".bak"))
                    try:
                        os.link(target, backup)
                    except OSError:  # no hard links here: publish without a way back
                        backup = None
                try:
                    os.replace(tmp, target)
                except BaseException:
                    if backup is not None:
                        _unlink(backup)
                    raise
                done.append((target, backup))
        except BaseException:
            for target, backup in reversed(done):
                try:
                    if backup is not None:
                        os.replace(backup, target)
                    else:
                        _unlink(target)
                except OSError:
                    pass
            raise
        finally:
            for _, backup in done:
                if backup is not None:
                    _unlink(backup)
        self._staged.clear()
        self.published = True

    def discard(self) -> None:
        """Remove every staged temporary file."""
        for tmp, _ in self._staged:
            _unlink(tmp)
        self._staged.clear()

    def __enter__(self) -> "Publication":
        return self

    def __exit__(self, *exc) -> None:
        self.discard()
        if self._unhook is not None:
            self._unhook()
            self._unhook = None


def _unlink(p: Path) -> None:
    try:
        os.unlink(p)
    except OSError:
        pass
