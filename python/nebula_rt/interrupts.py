"""Ctrl-C and SIGTERM as a clean cancel for the command line.

A long run must stop within about a second of a Ctrl-C, publish nothing and leave no
temporary file. The signal handlers only set a flag (Python runs them between bytecodes, so
a handler that raised could strike in the middle of a rename or inside VTK's writer); the run
polls the flag: the transport before every launch (launches last at most
``nebula_rt.transport.LAUNCH_SECONDS``), the command line between its stages and once more
before it publishes. A second signal aborts at once (``KeyboardInterrupt``), and the
``finally`` blocks still remove the temporary files.
"""

from __future__ import annotations

import signal
import sys
import threading
from typing import Optional

from .errors import CancelledError

#: exit status of a run cancelled by each signal (128 + the signal number, the shell's convention)
EXIT_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}


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

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.requested: Optional[int] = None  # the signal that asked for the cancel
        self._old: dict = {}

    # -- the flag -------------------------------------------------------------------------
    def __call__(self) -> bool:
        """True once a cancel was requested (the ``cancel`` callback of the pipeline)."""
        return self.requested is not None

    def check(self, what: str = "run") -> None:
        """Raise :class:`CancelledError` if a cancel was requested."""
        if self.requested is not None:
            raise CancelledError(f"{what} cancelled by {signal.Signals(self.requested).name}")

    @property
    def exit_status(self) -> int:
        return EXIT_STATUS.get(self.requested, 130)

    # -- installation -----------------------------------------------------------------------
    def _handler(self, signum, frame):
        if self.requested is not None:
            # a second signal: abort now (cleanup still runs in the finally blocks)
            raise KeyboardInterrupt
        self.requested = signum
        if not self.quiet:
            try:
                print(f"\n{signal.Signals(signum).name}: cancelling (nothing will be written; "
                      "press Ctrl-C again to abort at once)", file=sys.stderr, flush=True)
            except (OSError, ValueError):  # stderr closed: the cancel still happens
                pass

    def __enter__(self) -> "SignalCancel":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()
