"""Several processes tracing one run: the communicator the transport reduces its tallies with.

A distributed run splits every launch's packets between the ranks (packets are keyed by their
global index, so the union over the ranks is exactly the one-rank run), adds the ranks' batch
slots, packet tallies and images with an integer all-reduce before each fold, and folds the
same sums in the same order on every rank: every rank then holds the one-rank run's sums, bit
for bit, whatever the number of ranks. Integer addition is exact and associative, so the
reduction order of the MPI library does not matter.

:func:`world` gives the communicator of the process: mpi4py's ``COMM_WORLD`` when the process
was started by ``mpiexec`` with more than one rank (mpi4py is the optional ``mpi`` extra), else
:class:`Serial`. The communicator of a VTK pipeline (ParaView's MPI engine) is the VTK layer's:
:mod:`nebula_rt.filters.controller`.
"""

from __future__ import annotations

import functools
import os

import numpy as np


class Serial:
    """One process: every reduction is the identity."""

    rank = 0
    size = 1
    local_rank = 0
    local_size = 1

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        """Element-wise sum over the ranks of a uint64 array (wrapping modulo 2^64)."""
        return np.asarray(a, np.uint64)

    def allreduce_max(self, x: float) -> float:
        return float(x)

    def bcast(self, obj, root: int = 0):
        return obj

    def barrier(self) -> None:
        pass

    def abort(self, code: int) -> None:
        raise SystemExit(int(code))


class MPIComm:
    """An mpi4py communicator (``comm``), with the node-local rank for choosing a device."""

    def __init__(self, comm):
        from mpi4py import MPI

        self._MPI = MPI
        self.comm = comm
        self.rank = comm.Get_rank()
        self.size = comm.Get_size()
        local = comm.Split_type(MPI.COMM_TYPE_SHARED, key=self.rank)
        self.local_rank, self.local_size = local.Get_rank(), local.Get_size()
        local.Free()

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        src = np.ascontiguousarray(a, np.uint64)
        out = np.empty_like(src)
        self.comm.Allreduce(src, out, op=self._MPI.SUM)
        return out

    def allreduce_max(self, x: float) -> float:
        return float(self.comm.allreduce(float(x), op=self._MPI.MAX))

    def bcast(self, obj, root: int = 0):
        return self.comm.bcast(obj, root=root)

    def barrier(self) -> None:
        self.comm.Barrier()

    def abort(self, code: int) -> None:
        """End every rank of the job (MPI_Abort)."""
        self.comm.Abort(int(code))


def _launched_by_mpi() -> bool:
    """Whether an MPI launcher started this process (Open MPI, MPICH/Hydra, Slurm's PMI)."""
    return any(k in os.environ for k in ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK", "PMI_RANK"))


@functools.lru_cache(maxsize=1)
def world():
    """The communicator of this process: :class:`MPIComm` over ``COMM_WORLD`` when started by
    an MPI launcher with several ranks and mpi4py imports, else :class:`Serial`. On the CPU the
    ranks of a node share its cores: PoCL is told to use cores / local ranks each (unless
    ``POCL_CPU_MAX_CU_COUNT`` is set)."""
    if not _launched_by_mpi():
        return Serial()
    try:
        from mpi4py import MPI
    except ImportError:
        return Serial()
    if MPI.COMM_WORLD.Get_size() < 2:
        return Serial()
    comm = MPIComm(MPI.COMM_WORLD)
    if "POCL_CPU_MAX_CU_COUNT" not in os.environ:
        os.environ["POCL_CPU_MAX_CU_COUNT"] = str(max(1, (os.cpu_count() or 1) // comm.local_size))
    return comm


def share(start: int, count: int, comm) -> tuple[int, int]:
    """The packets [first, first + n) of ``[start, start + count)`` that rank ``comm.rank``
    traces: contiguous, disjoint, covering the range, in rank order."""
    lo = start + count * comm.rank // comm.size
    hi = start + count * (comm.rank + 1) // comm.size
    return lo, hi - lo
