"""Ctrl-C, SIGTERM, SIGHUP and SIGQUIT as a clean cancel for the command line.

A long run must stop within about a second of a signal, publish nothing and leave no
temporary file. The signal handlers only set a flag (Python runs them between bytecodes, so
a handler that raised could strike in the middle of a rename or inside VTK's writer); the run
polls the flag: the transport before every launch (launches last at most
``nebula_rt.transport.LAUNCH_SECONDS``), the command line between its stages and once more
before it publishes, with the signals held back while it renames (:func:`held`).

A second signal aborts at once, but not by raising: an exception thrown into VTK's renderer
crashed the process (SIGSEGV) and one thrown into an import left a half-initialised module
(an ImportError later). The handler runs the registered abort hooks instead (the
publications remove their temporary files: :func:`on_abort`) and ends the process with the
signal's exit status (``os._exit``).

SIGQUIT (Ctrl-\\) and SIGHUP (the terminal closed) cancel as SIGINT and SIGTERM do; the exit
status is 128 + the signal number, the shell's convention (130, 143, 129, 131).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from typing import Callable, Optional

from .errors import CancelledError

#: the signals that cancel a run (those this platform has)
SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n))
#: exit status of a run cancelled by each signal (128 + the signal number, the shell's convention)
EXIT_STATUS = {sig: 128 + int(sig) for sig in SIGNALS}

#: the handler installed now (the innermost ``with SignalCancel()``), or None
_active: Optional["SignalCancel"] = None
#: what a second signal runs before the process ends (each publication's clean-up)
_abort_hooks: list = []


def cancel_requested() -> Optional[int]:
    """The signal that asked the running command to cancel, or None (also None when no
    handler is installed: a library call in a notebook)."""
    return None if _active is None else _active.requested


def on_abort(hook: Callable[[], None]) -> Callable[[], None]:
    """Run ``hook`` (no arguments; it must not block) if a second signal ends the process;
    returns a function that removes it again."""
    _abort_hooks.append(hook)

    def remove() -> None:
        with contextlib.suppress(ValueError):
            _abort_hooks.remove(hook)
    return remove


@contextlib.contextmanager
def held():
    """Hold the cancelling signals back inside the block (delivered when it ends): the block
    (the renames that publish a run's outputs) completes or does not start. Inert outside the
    main thread or where the platform cannot mask signals."""
    mask = getattr(signal, "pthread_sigmask", None)
    if mask is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = mask(signal.SIG_BLOCK, SIGNALS)
    try:
        yield
    finally:
        mask(signal.SIG_SETMASK, old)


class SignalCancel:
    """Install SIGINT and SIGTERM handlers that request a cancel; a callable for the run's
    ``cancel`` polls.

    Parameters
    ----------
    quiet : bool
        Do not print the "cancelling" notice on stderr.

    Notes
    -----
    Handlers can only be installed from the main thread; elsewhere this object is inert
    (``requested`` stays None) and the signals keep their old handlers.
    """

    SIGNALS = SIGNALS

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.requested: Optional[int] = None  # the signal that asked for the cancel
        self._old: dict = {}

    # -- the flag -------------------------------------------------------------------------
    def __call__(self) -> bool:
        """True once a cancel was requested (the ``cancel`` callback of the pipeline)."""
        self._reassert()
        return self.requested is not None

    def _reassert(self) -> None:
        """Install the handlers again: LLVM (inside PoCL's kernel compiler) installs its own
        for SIGQUIT, SIGHUP and others when it first runs, and its SIGQUIT handler swallowed
        the signal. Every poll re-installs ours (a few sigaction calls, at most a few per
        second); only the main thread may."""
        if self._old and threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                signal.signal(sig, self._handler)

    def check(self, what: str = "run") -> None:
        """Raise :class:`CancelledError` if a cancel was requested."""
        self._reassert()
        if self.requested is not None:
            raise CancelledError(f"{what} cancelled by {signal.Signals(self.requested).name}")

    @property
    def exit_status(self) -> int:
        return EXIT_STATUS.get(self.requested, 130)

    # -- installation -----------------------------------------------------------------------
    def _handler(self, signum, frame):
        if self.requested is not None:
            self._abort(signum)
        self.requested = signum
        self._say(f"\n{signal.Signals(signum).name}: cancelling (nothing will be written; "
                  "press Ctrl-C again to abort at once)")

    def _say(self, text: str) -> None:
        if not self.quiet:
            try:
                print(text, file=sys.stderr, flush=True)
            except (OSError, ValueError):  # stderr closed: the cancel still happens
                pass

    def _abort(self, signum) -> None:
        """A second signal: remove the temporary files (the abort hooks) and end the process
        now with the first signal's status, raising nothing into whatever runs."""
        for hook in list(_abort_hooks):
            try:
                hook()
            except Exception:  # noqa: BLE001 - the others still run, the process still ends
                pass
        try:
            print(f"nebula-rt: aborted by a second {signal.Signals(signum).name}; nothing written",
                  file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass
        os._exit(EXIT_STATUS.get(self.requested, 130))

    def __enter__(self) -> "SignalCancel":
        global _active
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handler)
            self._outer, _active = _active, self
        return self

    def __exit__(self, *exc) -> None:
        global _active
        for sig, old in self._old.items():
            signal.signal(sig, old)
        if self._old:
            _active = self._outer
        self._old.clear()
