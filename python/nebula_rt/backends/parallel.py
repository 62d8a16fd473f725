"""Several processes tracing one run: the communicator the transport reduces its tallies with.

A distributed run splits every launch's packets between the ranks (packets are keyed by their
global index, so the union over the ranks is exactly the one-rank run), adds the ranks' batch
slots, packet tallies and images with an integer all-reduce before each fold, and folds the
same sums in the same order on every rank: every rank then holds the one-rank run's sums, bit
for bit, whatever the number of ranks. Integer addition is exact and associative, so the
reduction order of the MPI library does not matter.

:func:`world` gives the communicator of the process: mpi4py's ``COMM_WORLD`` when the process
was started by ``mpiexec`` with more than one rank (mpi4py is the optional ``mpi`` extra), else
:class:`Serial`.

Where the slots live on GPUs (the CUDA backend), :func:`device_reducer` adds them where they
are: with NCCL when every rank has a GPU of its own (the slots never leave the GPUs: at 512^3
one batch slot is 1 GiB, which through the host costs a copy each way and an MPI sum per
group), else through one host buffer kept for the run. The environment variable
``NEBULA_RT_ALLREDUCE`` (``auto``, ``nccl`` or ``host``) overrides the choice.
"""

from __future__ import annotations

import functools
import hashlib
import os
import socket

import numpy as np

from ..array_api import array_module, to_numpy

#: uint64 elements (8 MiB) of one call of a large in-place sum. The MPI library's temporary
#: buffers grow with the message, so one call on hundreds of MiB faults in fresh memory each
#: time; chunks of a few MiB reuse small ones. Open MPI 4.1, 2 ranks on 2 cores, 256 MiB in
#: place: 0.14-0.21 s in one call, 0.06-0.11 s in 8 MiB chunks.
SUM_CHUNK = 1 << 20


class Serial:
    """One process: every reduction is the identity."""

    rank = 0
    size = 1
    local_rank = 0
    local_size = 1

    def sum_u64(self, buf: np.ndarray) -> np.ndarray:
        """Replace the contiguous uint64 array ``buf`` by its element-wise sum over the ranks
        (wrapping modulo 2^64), in place; returns ``buf``."""
        return buf

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        """Element-wise sum over the ranks of a uint64 array (wrapping modulo 2^64), as a new
        array."""
        return self.sum_u64(np.array(a, np.uint64, copy=True))

    def allreduce_max(self, x: float) -> float:
        return float(x)

    def bcast(self, obj, root: int = 0):
        return obj

    def allgather(self, obj) -> list:
        """Every rank's ``obj`` (a small picklable value), in rank order."""
        return [obj]

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

    def sum_u64(self, buf: np.ndarray) -> np.ndarray:
        """In place (``MPI_IN_PLACE``, through mpi4py's buffer interface: no pickling, no
        copy), in chunks of :data:`SUM_CHUNK` elements."""
        flat = _flat_u64(buf)
        for lo in range(0, flat.size, SUM_CHUNK):
            self.comm.Allreduce(self._MPI.IN_PLACE, flat[lo:lo + SUM_CHUNK], op=self._MPI.SUM)
        return buf

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        return self.sum_u64(np.array(a, np.uint64, copy=True))

    def allreduce_max(self, x: float) -> float:
        return float(self.comm.allreduce(float(x), op=self._MPI.MAX))

    def bcast(self, obj, root: int = 0):
        return self.comm.bcast(obj, root=root)

    def allgather(self, obj) -> list:
        return self.comm.allgather(obj)

    def barrier(self) -> None:
        self.comm.Barrier()

    def abort(self, code: int) -> None:
        """End every rank of the job (MPI_Abort)."""
        self.comm.Abort(int(code))


def _flat_u64(buf: np.ndarray) -> np.ndarray:
    """``buf`` as a flat view (the sums are written into its memory): it must be a contiguous
    uint64 array."""
    if not (isinstance(buf, np.ndarray) and buf.dtype == np.uint64 and buf.flags.c_contiguous
            and buf.flags.writeable):
        raise TypeError("sum_u64 needs a writeable, C-contiguous uint64 numpy array")
    return buf.reshape(-1)


def any_rank(comm, flag: bool) -> bool:
    """Whether ``flag`` holds on any rank of ``comm`` (None or one rank: ``flag`` itself): a
    decision every rank takes alike, e.g. to cancel between traces (a rank that stopped alone
    would leave the others waiting in the next one). Collective."""
    if comm is None or comm.size < 2:
        return bool(flag)
    return comm.allreduce_max(1.0 if flag else 0.0) > 0


def launched_by_mpi() -> bool:
    """Whether an MPI launcher started this process (Open MPI, MPICH/Hydra, Slurm's PMI)."""
    return any(k in os.environ for k in ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK", "PMI_RANK"))


def launched_rank() -> int:
    """This process's rank as its MPI launcher's environment gives it, 0 where none started
    it: who prints, known before MPI starts (and without starting it)."""
    for key in ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK"):
        value = os.environ.get(key, "").strip()
        if value.isdigit():
            return int(value)
    return 0


@functools.lru_cache(maxsize=1)
def world():
    """The communicator of this process: :class:`MPIComm` over ``COMM_WORLD`` when started by
    an MPI launcher with several ranks and mpi4py imports, else :class:`Serial`. On the CPU the
    ranks of a node share its cores: PoCL is told to use cores / local ranks each (unless
    ``POCL_CPU_MAX_CU_COUNT`` is set)."""
    if not launched_by_mpi():
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


_LOW32 = np.uint64(0xFFFFFFFF)


def sum_checked(comm, parts, rows: int, limit_bits: int) -> np.ndarray:
    """Sum the ranks' counts in place (:meth:`sum_u64`), exactly where it matters, and flag
    the rows whose headroom-checked cells reach the limit in the sum.

    Parameters
    ----------
    comm : communicator
    parts : list of (buf, checked)
        ``buf``: this rank's counts (a contiguous uint64 array, NumPy or, where ``comm`` sums
        device arrays (:class:`DeviceSums`), CuPy), replaced by the sums over the ranks.
        ``checked``: the ranges (start, stop) of ``buf`` that hold headroom-checked cells, each ``rows`` rows of equal length (row g: batch slot g). In a row no rank
        flagged, every rank's checked cells are below ``2**limit_bits`` (a checked add flags
        the cell that reaches it); the other counts must be known not to pass 2^64 in the sum
        (counts whose bound covers all the ranks' packets).
    rows : int
    limit_bits : int
        The headroom limit 2^limit_bits.

    Returns
    -------
    ndarray of bool (rows,)
        Rows with a summed checked cell at or past the limit, as one rank's checked adds of
        all the packets would have flagged them.

    Notes
    -----
    One sum of each buffer is exact when the checked cells cannot pass 2^64 together: always
    when ``size * (2**limit_bits - 1) < 2**64`` (the default limit 2^63 with 2 ranks), else
    when the ranks' largest checked cells of each row add up to less than 2^64 (found by a sum
    of ``2 rows`` numbers first). Otherwise (three or more ranks with cells near 2^63) the
    high and low 32 bits are summed apart, so that no partial sum can wrap.
    """
    past = np.zeros(rows, bool)
    views = [(buf, a, b) for buf, checked in parts for a, b in checked if b > a]
    limit = 1 << int(limit_bits)
    wrap = False
    if comm.size > 1 and views and rows and comm.size * (limit - 1) >= 1 << 64:
        top = np.zeros(rows, np.uint64)
        for buf, a, b in views:
            np.maximum(top, to_numpy(buf[a:b].reshape(rows, -1).max(axis=1)), out=top)
        halves = comm.allreduce_u64(np.concatenate([top >> np.uint64(32), top & _LOW32]))
        wrap = any((int(h) << 32) + int(lo) >= 1 << 64 for h, lo in zip(halves[:rows], halves[rows:]))
    if not wrap:
        for buf, _ in parts:
            comm.sum_u64(buf)
        for buf, a, b in views:
            past |= to_numpy(buf[a:b].reshape(rows, -1).max(axis=1)) >= np.uint64(limit)
        return past
    for buf, checked in parts:
        hi = buf >> np.uint64(32)
        buf &= _LOW32
        comm.sum_u64(hi)
        comm.sum_u64(buf)  # the low halves: at most size * 2^32, no wrap
        for a, b in checked:  # limit_bits > 32 here (fewer than 2^31 ranks)
            if b > a:
                lo_v, hi_v = buf[a:b].reshape(rows, -1), hi[a:b].reshape(rows, -1)
                past |= to_numpy(((hi_v + (lo_v >> np.uint64(32))) >> np.uint64(int(limit_bits) - 32)).max(axis=1)) > 0
        hi <<= np.uint64(32)
        buf += hi  # exact (mod 2^64) wherever the true sum is below 2^64
    return past


def sum_wide(comm, buf) -> np.ndarray:
    """Sum the ranks' 128-bit integers in place, exactly (modulo 2^128).

    ``buf`` is a contiguous uint64 array (NumPy, or CuPy with :class:`DeviceSums`) of (low,
    high) word pairs. Each number is summed as
    four 32-bit limbs (no limb sum can wrap for fewer than 2^32 ranks) and the carries are
    propagated afterwards. Returns the high words of the sums, saturated to 2^64 - 1 where a
    sum passed 2^128, for a caller to compare with a headroom limit.
    """
    xp = array_module(buf)
    pairs = buf.reshape(-1, 2)
    lo, hi = pairs[:, 0].copy(), pairs[:, 1].copy()
    limbs = [lo & _LOW32, lo >> np.uint64(32), hi & _LOW32, hi >> np.uint64(32)]
    for limb in limbs:
        comm.sum_u64(limb)
    carry = xp.zeros_like(lo)
    words = []
    for limb in limbs:
        t = limb + carry
        words.append(t & _LOW32)
        carry = t >> np.uint64(32)
    pairs[:, 0] = words[0] | (words[1] << np.uint64(32))
    pairs[:, 1] = words[2] | (words[3] << np.uint64(32))
    return xp.where(carry > 0, np.uint64(0xFFFFFFFFFFFFFFFF), pairs[:, 1])


def share(start: int, count: int, comm) -> tuple[int, int]:
    """The packets [first, first + n) of ``[start, start + count)`` that rank ``comm.rank``
    traces: contiguous, disjoint, covering the range, in rank order."""
    lo = start + count * comm.rank // comm.size
    hi = start + count * (comm.rank + 1) // comm.size
    return lo, hi - lo


# --------------------------------------------------------------------------------------------
# sums of device arrays (the CUDA backend's slots)
#: environment variable choosing how the ranks' device slots are added: auto, nccl or host
ALLREDUCE_ENV = "NEBULA_RT_ALLREDUCE"
ALLREDUCE_CHOICES = ("auto", "nccl", "host")


class StagedReducer:
    """Sums of device arrays through the host: each array is copied into one page-locked
    buffer kept for the run, summed there in place (:meth:`MPIComm.sum_u64`) and copied back.
    The path of ranks that share a GPU (NCCL refuses two ranks on one device) or lack NCCL."""

    kind = "host"

    def __init__(self, comm, backend):
        self.comm, self.backend = comm, backend
        self._buf = None

    def sum_u64(self, dev):
        n = int(dev.size)
        if self._buf is None or self._buf.size < n:
            self._buf = None
            self._buf = self.backend.host_empty(n, np.uint64)
        host = self._buf[:n]
        self.backend.to_host(dev, out=host)
        self.comm.sum_u64(host)
        self.backend.upload(dev, host)
        return dev


class NcclReducer:
    """Sums of CuPy uint64 arrays in place on the GPUs with NCCL (``ncclAllReduce``, sum,
    on the current stream, so it follows the kernels that wrote the slots). Integer sums
    wrap modulo 2^64 like the host's, whatever order NCCL adds in: the same bits."""

    kind = "nccl"

    def __init__(self, nccl, communicator, cupy):
        self._nccl, self._comm, self._cp = nccl, communicator, cupy

    def sum_u64(self, dev):
        if dev.dtype != np.uint64 or not dev.flags.c_contiguous:
            raise TypeError("NCCL sums need a C-contiguous uint64 CuPy array")
        ptr = dev.data.ptr
        self._comm.allReduce(ptr, ptr, int(dev.size), self._nccl.NCCL_UINT64, self._nccl.NCCL_SUM,
                             self._cp.cuda.get_current_stream().ptr)
        return dev


class DeviceSums:
    """A communicator whose ``sum_u64`` also takes device arrays (through ``reducer``): what
    :func:`sum_checked` and :func:`sum_wide` are given where the slots stay on the device.
    Host (NumPy) arrays go to ``comm`` as before."""

    def __init__(self, comm, reducer):
        self.comm, self.reducer = comm, reducer
        self.rank, self.size = comm.rank, comm.size

    def sum_u64(self, buf):
        if isinstance(buf, np.ndarray):
            return self.comm.sum_u64(buf)
        return self.reducer.sum_u64(buf)

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        return self.comm.allreduce_u64(a)


def _nccl():
    """CuPy's NCCL bindings, or None where NCCL does not load."""
    try:
        from cupy.cuda import nccl
    except Exception:  # ImportError, or a libnccl that fails to load
        return None
    return nccl if getattr(nccl, "available", True) else None


def _device_key(backend) -> int:
    """A 63-bit number naming this rank's GPU (host name and PCI bus id): ranks with equal
    keys share a device."""
    name = f"{socket.gethostname()}/{backend.device.pci_bus_id}"
    return int.from_bytes(hashlib.blake2b(name.encode(), digest_size=8).digest(), "little") >> 1


def device_reducer(comm, backend):
    """How the ranks add the CUDA backend's device slots: a :class:`NcclReducer` where every
    rank has a GPU of its own and NCCL loads on every rank, else a :class:`StagedReducer`;
    None for one rank or a backend whose arrays are not CuPy's (OpenCL: the session copies or
    maps its slots itself). Collective: every rank calls it with its backend, and every rank
    makes the same choice (from the same all-reduced table).

    ``NEBULA_RT_ALLREDUCE`` = ``host`` takes the staged path; ``nccl`` requires NCCL (an error
    on every rank, naming the cause, where it cannot be used). NVLink multicast (NVLS) is left
    off unless ``NCCL_NVLS_ENABLE`` is set: it buys nothing at these message sizes and needs
    the fabric's multicast objects."""
    choice = os.environ.get(ALLREDUCE_ENV, "auto").strip().lower() or "auto"
    if choice not in ALLREDUCE_CHOICES:
        raise ValueError(f"{ALLREDUCE_ENV} = {choice!r}: expected one of {', '.join(ALLREDUCE_CHOICES)}")
    if comm.size < 2 or getattr(backend, "array_module", np) is np:
        return None
    nccl = None if choice == "host" else _nccl()
    size = comm.size
    # every rank's device key and whether NCCL loads there: one-hot rows summed over the ranks
    table = np.zeros(2 * size, np.uint64)
    table[comm.rank] = _device_key(backend)
    table[size + comm.rank] = 1 if nccl is not None else 0
    table = comm.allreduce_u64(table)
    distinct = len(set(table[:size].tolist())) == size
    usable = bool(table[size:].all())
    if choice == "nccl" and not (distinct and usable):
        why = "some ranks share a GPU" if not distinct else "NCCL does not load on every rank"
        raise RuntimeError(f"{ALLREDUCE_ENV} = 'nccl': {why}; use 'auto' or 'host'")
    if choice == "host" or not (distinct and usable):
        return StagedReducer(comm, backend)
    cached = getattr(comm, "_nccl_reducer", None)
    if cached is not None and cached[0] == int(table[comm.rank]):
        return cached[1]
    os.environ.setdefault("NCCL_NVLS_ENABLE", "0")
    uid = comm.bcast(nccl.get_unique_id() if comm.rank == 0 else None)
    with backend.device:
        communicator = nccl.NcclCommunicator(size, uid, comm.rank)
    reducer = NcclReducer(nccl, communicator, backend.cp)
    try:  # kept for the process's next runs (creating a communicator takes a collective set-up)
        comm._nccl_reducer = (int(table[comm.rank]), reducer)
    except AttributeError:
        pass
    return reducer
