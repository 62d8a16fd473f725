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

Python runs a handler only between bytecodes of the main thread, and a run polls only between
its steps; a kernel compile in PoCL (seconds on a cold cache), VTK's renderer or a slow import
hold the main thread longer than that. A watchdog thread therefore hears every signal at once
(``signal.set_wakeup_fd``) and, if no poll has seen the cancel within
:data:`GRACE_SECONDS`, ends the process as a second signal would: the temporary files go, the
exit status is the signal's, nothing is published (the renames that publish hold the signals
back and the watchdog waits for them). Runs under an MPI launcher keep the polls alone: their
ranks agree on a cancel together, and one rank ending on its own would end the job.

The command line hears the signals from its first import on (:func:`install_early`), before
its modules (a third of a second of numpy, astropy and the scene) have loaded: a signal then
cancels the run as soon as its handlers are installed, before anything starts. A SIGHUP the
process inherited as ignored stays ignored (:data:`KEPT_IGNORED`: ``nohup``'s whole purpose);
SIGINT and SIGQUIT, which a shell ignores in a job it starts in the background, still cancel
(``kill -INT`` of such a run, as the tests send).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
import threading
import time
from typing import Callable, Optional

from .errors import CancelledError

#: the signals that cancel a run (those this platform has)
SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n))
#: the signals that stay ignored where the process inherited them so: SIGHUP under ``nohup``
KEPT_IGNORED = tuple(getattr(signal, n) for n in ("SIGHUP",) if hasattr(signal, n))
#: exit status of a run cancelled by each signal (128 + the signal number, the shell's convention)
EXIT_STATUS = {sig: 128 + int(sig) for sig in SIGNALS}

#: how long a signal may wait for a poll of the run before the watchdog ends the process (s)
GRACE_SECONDS = 1.0

#: the handler installed now (the innermost ``with SignalCancel()``), or None
_active: Optional["SignalCancel"] = None
#: what a second signal runs before the process ends (each publication's clean-up)
_abort_hooks: list = []
#: held by the renames that publish (:func:`held`) and by the watchdog as it ends the process,
#: so a publication completes or does not start
_publishing = threading.Lock()


#: the signals heard by :func:`install_early`'s handler before a SignalCancel was installed
_early: list = []
#: whether :func:`install_early` ran: this process is the command, which ends when its run does
_command = False


def _early_handler(signum, frame) -> None:
    """Record a signal that came before the run's handlers; a second one ends the process now
    with the first's status (nothing has started that could leave a file)."""
    if _early:
        SignalCancel._end(EXIT_STATUS.get(_early[0], 128 + signum),
                          f"cancelled by {signal.Signals(_early[0]).name} before the run started")
    _early.append(signum)


def install_early() -> None:
    """Hear the cancelling signals from now on (the command line's first import), before the
    run's :class:`SignalCancel` is installed: the first such signal cancels the run when it is.
    Only the main thread may install."""
    global _command
    if threading.current_thread() is not threading.main_thread():
        return
    _command = True
    for sig in SIGNALS:
        if not (sig in KEPT_IGNORED and signal.getsignal(sig) is signal.SIG_IGN):
            signal.signal(sig, _early_handler)


def is_command() -> bool:
    """Whether this process is the command line (:func:`install_early` ran), not Python that
    called its ``main`` (a test, a notebook), whose signals a run must leave as it found them."""
    return _command


def cancel_requested() -> Optional[int]:
    """The signal that asked the running command to cancel, or None (also None when no
    handler is installed: a library call in a notebook)."""
    if _active is None:
        return None
    _active._seen()
    return _active.requested


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
    with _publishing:
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
    watchdog : bool
        End the process if no poll sees a cancel within :data:`GRACE_SECONDS` of its signal
        (the module's notes); off for the ranks of an MPI job.
    ends_process : bool
        The process ends when the block does (the command line): once a cancel was requested,
        the block leaves the signals ignored, so that one coming while the process exits does
        not end it by the signal's default action (or a KeyboardInterrupt) instead of the
        cancel's status.

    Notes
    -----
    Handlers can only be installed from the main thread; elsewhere this object is inert
    (``requested`` stays None) and the signals keep their old handlers.
    """

    SIGNALS = SIGNALS

    def __init__(self, quiet: bool = False, watchdog: bool = True, ends_process: bool = False):
        self.quiet = quiet
        self.watchdog = watchdog
        self.ends_process = ends_process
        self.requested: Optional[int] = None  # the signal that asked for the cancel
        self.noticed = False  # a poll has seen the cancel: the run is unwinding by itself
        self._old: dict = {}
        self._wakeup: Optional[tuple] = None  # (read end, write end, the old wakeup fd)
        self._stop = threading.Event()

    # -- the flag -------------------------------------------------------------------------
    def __call__(self) -> bool:
        """True once a cancel was requested (the ``cancel`` callback of the pipeline)."""
        self._reassert()
        self._seen()
        return self.requested is not None

    def _seen(self) -> None:
        if self.requested is not None:
            self.noticed = True

    def _reassert(self) -> None:
        """Install the handlers again: LLVM (inside PoCL's kernel compiler) installs its own
        for SIGQUIT, SIGHUP and others when it first runs, and its SIGQUIT handler swallowed
        the signal. Every poll re-installs ours (a few sigaction calls, at most a few per
        second); only the main thread may."""
        if self._old and threading.current_thread() is threading.main_thread():
            for sig in self._old:  # (not a SIGHUP the process inherited as ignored)
                signal.signal(sig, self._handler)

    def check(self, what: str = "run") -> None:
        """Raise :class:`CancelledError` if a cancel was requested."""
        self._reassert()
        self._seen()
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
        self._end(EXIT_STATUS.get(self.requested, 130), f"aborted by a second {signal.Signals(signum).name}")

    @staticmethod
    def _end(status: int, why: str) -> None:
        """Run the abort hooks (the temporary files go), say why, end the process now."""
        for hook in list(_abort_hooks):
            try:
                hook()
            except Exception:  # noqa: BLE001 - the others still run, the process still ends
                pass
        try:
            print(f"nebula-rt: {why}; nothing written", file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass
        os._exit(status)

    # -- the watchdog -------------------------------------------------------------------------
    def _start_watchdog(self) -> None:
        read, write = os.pipe()
        os.set_blocking(write, False)  # set_wakeup_fd needs it: a full pipe must not block
        os.set_blocking(read, False)
        try:
            old = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        except (ValueError, OSError):  # not the main thread, or an embedding that forbids it
            os.close(read)
            os.close(write)
            return
        self._wakeup = (read, write, old)
        self._stop.clear()
        threading.Thread(target=self._watch, args=(read,), name="nebula-rt signal watchdog",
                         daemon=True).start()

    def _stop_watchdog(self) -> None:
        if self._wakeup is None:
            return
        read, write, old = self._wakeup
        self._wakeup = None
        signal.set_wakeup_fd(old)
        self._stop.set()
        os.close(write)  # the watchdog's select wakes up (end of file) and it closes ``read``

    def _watch(self, read: int) -> None:
        """Wait for signals; after each, give the run :data:`GRACE_SECONDS` to poll."""
        try:
            while not self._stop.is_set():
                select.select([read], [], [], 1.0)
                try:
                    data = os.read(read, 64)
                except BlockingIOError:
                    continue
                if not data or self._stop.is_set():  # the write end closed: the run is over
                    return
                signum = data[-1]
                deadline = time.monotonic() + GRACE_SECONDS
                while time.monotonic() < deadline and not self.noticed and not self._stop.is_set():
                    time.sleep(0.02)
                if self.noticed or self._stop.is_set():
                    continue
                # the main thread is inside a call that does not return to Python (a kernel
                # compile, VTK's renderer): end the process, but never inside the renames
                with _publishing:
                    if not self.noticed and not self._stop.is_set():
                        status = EXIT_STATUS.get(self.requested or signum, 128 + signum)
                        name = signal.Signals(self.requested or signum).name
                        self._end(status, f"cancelled by {name} (the step under way could not stop "
                                          "by itself)")
        finally:
            os.close(read)

    def __enter__(self) -> "SignalCancel":
        global _active
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                if sig in KEPT_IGNORED and signal.getsignal(sig) is signal.SIG_IGN:  # nohup: left so
                    continue
                self._old[sig] = signal.signal(sig, self._handler)
            self._outer, _active = _active, self
            if _early and self.requested is None:  # a signal during the imports (install_early)
                self.requested = _early.pop(0)
                _early.clear()
                if self.watchdog:  # nothing has started: end now (the ranks of a job cancel together)
                    self._end(self.exit_status, f"cancelled by {signal.Signals(self.requested).name} before "
                                                "the run started")
            if self.watchdog:
                self._start_watchdog()
        return self

    def __exit__(self, *exc) -> None:
        global _active
        self._stop_watchdog()
        for sig, old in self._old.items():
            # a cancelled command line is ending with the cancel's status: a later signal is
            # ignored (a Python handler would be reset to the default action, which kills the
            # process, once the interpreter's shutdown removes its handlers)
            signal.signal(sig, signal.SIG_IGN if self.ends_process and self.requested is not None else old)
        if self._old:
            _active = self._outer
        self._old.clear()
