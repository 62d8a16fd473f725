"""How a command fails: its exit status and its one line on stderr, in one process or agreed
by the ranks of a distributed run.

:func:`describe` maps the exception that ended a command to a :class:`Failure` (the statuses
of :func:`nebula_rt.cli.commands.main`).

Under ``mpiexec`` every rank runs the same command (``render``, ``sky``, ``compare``, ``fit``;
each rank traces a share of every trace, :class:`Ranks`). Most failures meet every rank
alike (a scene value, an output path, more memory than there is, a cancel), and a run whose
ranks each printed the message and ended the job with ``MPI_Abort`` said the same thing N
times under Open MPI's abort notice. So the ranks agree on how each step of the run ended:

- the start-up (the scene, the outputs, the device, the memory; :func:`together`): every rank
  does it, then the ranks exchange what went wrong, if anything;
- the trace: a cancel is decided together between launches already (the transport), and
  the ranks exchange it the same way;
- the outputs, which rank 0 alone writes (:func:`on_lead`): the other ranks wait for its
  outcome.

Where a step failed on any rank, every rank raises :class:`RanksFailed` with the first
failing rank's status and message (a cancel: the first rank that was signalled itself); rank
0 alone prints that message and every rank exits with that status, a serial run's (2 bad
input, 3 an unusable device, 130 / 143 cancelled). No rank aborts the job. Only a rank that
fails on its own during the trace, while the others wait for it in a reduction, still ends
the job with ``MPI_Abort`` (:func:`abort_the_other_ranks`), its message naming it.

Every rank that exits non-zero makes Open MPI's mpiexec add a notice of its own ("mpiexec
detected that one or more processes exited with non-zero status"); ``mpiexec -q`` leaves it
out. A signal to mpiexec itself makes mpiexec exit 1 whatever the ranks return (Open MPI 4.1).
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from dataclasses import dataclass
from typing import Callable, Optional

from ..errors import (
    BackendUnavailableError, CancelledError, NebulaError, OutputError, ResourceError, SceneError)


@dataclass(frozen=True)
class Failure:
    """How a command failed (on one rank).

    Attributes
    ----------
    status : int
        The exit status (:func:`nebula_rt.cli.commands.main`).
    message : str
        The one line to print, without the ``nebula-rt:`` prefix.
    own : bool
        False for a cancel this rank learned from the others (it was not signalled itself):
        the status is then another rank's to give.
    """

    status: int
    message: str
    own: bool = True


def describe(exc: BaseException, args, cancel, distributed: bool = False) -> Optional[Failure]:
    """The :class:`Failure` of an exception that ended a command (``args``: the parsed
    command line or None; ``cancel``: the run's :class:`~nebula_rt.interrupts.SignalCancel`).
    None for an internal error with ``NEBULA_RT_DEBUG`` set in one process: the caller shows
    its traceback. ``distributed``: one rank of several, which must agree with the others
    whatever the exception; the traceback is printed here instead."""
    if isinstance(exc, SceneError):
        from ..scene.units import attribute

        exc = attribute(exc, getattr(args, "scene_used", None))
        return Failure(2, f"invalid scene: {exc}; nothing written")
    if isinstance(exc, (OutputError, ResourceError)):
        return Failure(2, f"{exc}; nothing written")
    if isinstance(exc, BackendUnavailableError):
        return Failure(3, str(exc))
    if isinstance(exc, CancelledError):
        return Failure(cancel.exit_status, f"{exc}; nothing written", own=cancel.requested is not None)
    if isinstance(exc, KeyboardInterrupt):
        return Failure(130, "aborted; nothing written")
    if isinstance(exc, OSError):
        from ..pipeline.outputs import describe_os_error

        where = f"{exc.filename}: " if exc.filename else ""
        return Failure(1, f"{where}{describe_os_error(exc)}; nothing written")
    if isinstance(exc, NebulaError):
        return Failure(1, str(exc))
    # a defect: one line, not a traceback (NEBULA_RT_DEBUG=1 shows it)
    if os.environ.get("NEBULA_RT_DEBUG"):
        if not distributed:
            return None
        import traceback

        traceback.print_exception(exc)
    return Failure(1, f"internal error: {type(exc).__name__}: {exc} (set NEBULA_RT_DEBUG=1 for the "
                      "traceback; nothing written)")


class RanksFailed(Exception):
    """Raised on every rank of a distributed run together: the ranks agreed that the run
    failed as ``failure`` says, first (or as its own) on rank ``rank`` of ``size``."""

    def __init__(self, failure: Failure, rank: int, size: int):
        super().__init__(failure.message)
        self.failure, self.rank, self.size = failure, rank, size

    @property
    def status(self) -> int:
        return self.failure.status


def agreed(failures: list) -> Optional[tuple[int, Failure]]:
    """(rank, failure) the ranks report, from every rank's failure (None: none) in rank
    order: the first rank's whose failure is its own, else the first failing rank's; None if
    none failed."""
    failed = [(rank, f) for rank, f in enumerate(failures) if f is not None]
    own = [(rank, f) for rank, f in failed if f.own]
    return (own or failed or [None])[0]


@contextlib.contextmanager
def together(comm, describe_: Callable[[BaseException], Failure], catch=(Exception, KeyboardInterrupt)):
    """Run the block on every rank of ``comm``; if it raised one of ``catch`` on any rank,
    raise :class:`RanksFailed` on every rank (what ``describe_`` made of the reported
    exception). Collective: every rank must enter the block, and a failure the block can
    meet while other ranks wait for this one in a collective must not be in ``catch``. One
    process (``comm.size`` 1): the block's exceptions pass unchanged."""
    if comm.size < 2:
        yield
        return
    failure = None
    try:
        yield
    except catch as exc:
        if isinstance(exc, RanksFailed):
            raise
        failure = describe_(exc)
    first = agreed(comm.allgather(failure))
    if first is not None:
        rank, failure = first
        raise RanksFailed(failure, rank, comm.size)


def on_lead(comm, work: Callable[[], object], describe_: Callable[[BaseException], Failure]):
    """``work()`` on rank 0 alone, the other ranks waiting for its outcome: if it fails, every
    rank raises :class:`RanksFailed` with rank 0's status. Returns ``work()``'s value on rank
    0, None on the others. Collective, like :func:`together`."""
    if comm.size < 2:
        return work()
    if comm.rank != 0:
        failure = comm.bcast(None)
        if failure is not None:
            raise RanksFailed(failure, 0, comm.size)
        return None
    try:
        value = work()
    except (Exception, KeyboardInterrupt) as exc:
        failure = describe_(exc)
        comm.bcast(failure)
        raise RanksFailed(failure, 0, comm.size) from exc
    comm.bcast(None)
    return value


class Ranks:
    """The steps of a command on the ranks of an MPI job (one process: plain calls).

    Every rank runs the whole command; each trace is shared by the ranks (pass :attr:`comm`
    to it) and ends with the same bits on every rank, so every rank takes the same decisions
    after it (a fit's next trial too). The steps:

    - ``with ranks.start():`` the start-up (the scene, the options, the outputs, the device),
      :func:`together`: whatever fails on whichever rank;
    - ``with ranks.trace():`` the traces: a cancel is decided together (the transport, and
      :func:`nebula_rt.backends.parallel.any_rank` between traces); any other failure there
      is one rank's own;
    - ``ranks.publish(work)``: rank 0 writes the outputs, :func:`on_lead`.

    Parameters
    ----------
    args : argparse.Namespace
        The command line (for the failure's message).
    cancel : nebula_rt.interrupts.SignalCancel
        The command's cancel flag.
    """

    def __init__(self, args, cancel):
        from ..backends.parallel import world

        self.comm = world()
        self.lead = self.comm.rank == 0
        self.cancel = cancel
        self._failure = functools.partial(describe, args=args, cancel=cancel, distributed=True)

    def start(self):
        return together(self.comm, self._failure)

    def trace(self):
        return together(self.comm, self._failure, catch=CancelledError)

    def publish(self, work: Callable[[], object]):
        return on_lead(self.comm, work, self._failure)


def quiet_rank() -> bool:
    """Whether this process is a rank of an MPI job other than rank 0 (known from the
    launcher's environment, without starting MPI): under mpiexec rank 0 alone prints."""
    from ..backends.parallel import launched_rank

    return launched_rank() != 0


def _distributed():
    """The communicator when this process is one of several ranks, else None."""
    from ..backends.parallel import launched_by_mpi, world

    if not launched_by_mpi():
        return None
    comm = world()
    return comm if comm.size > 1 else None


def abort_the_other_ranks(status: int) -> None:
    """One rank of a distributed run failed on its own: the others would wait for it in their
    next reduction forever, so the whole job is ended (MPI_Abort) with this rank's status,
    after its message (which names the rank) is out."""
    comm = _distributed()
    if comm is not None:
        sys.stderr.flush()
        comm.comm.Abort(int(status))


def say(message: str, rank=None, size=None) -> None:
    """Print ``nebula-rt: message`` on stderr, or ``nebula-rt (rank R of N): message`` for a
    message of rank R."""
    who = "nebula-rt" if rank is None else f"nebula-rt (rank {rank} of {size})"
    try:
        print(f"{who}: {message}", file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def error(message: str) -> None:
    """Print this process's own message, naming its rank where it is one of several."""
    comm = _distributed()
    say(message, None if comm is None else comm.rank, None if comm is None else comm.size)
