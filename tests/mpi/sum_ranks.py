"""Run by tests/test_mpi.py (mpiexec python) and tests/paraview/test_paraview.py (mpiexec pvbatch --mpi):
the ranks sum uint64 counts with ``sum_u64`` and ``sum_checked`` of :mod:`nebula_rt.backends.parallel`;
rank 0 saves the sums and the flags (.npz) for the test to hold against Python's integers.

    mpiexec -n N python tests/mpi/sum_ranks.py OUT.npz mpi4py
    mpiexec -n N python tests/mpi/sum_ranks.py OUT.npz cuda
    mpiexec -n N pvbatch --mpi --symmetric tests/mpi/sum_ranks.py OUT.npz vtk

``cuda``: the numbers live on the GPUs (CuPy arrays, a GPU per local rank where there are
enough) and are summed where they are (:func:`nebula_rt.backends.parallel.device_reducer`: NCCL where
every rank has its own GPU, else through a host buffer); ``reducer`` in the .npz says which.

``inputs(rank, size)`` gives each rank's numbers (the test calls it too). The in-place sums run
in chunks of ``CHUNK`` elements, so that the arrays cross several chunk boundaries.
"""

import sys

import numpy as np

#: elements per call of the chunked sums here (the library's SUM_CHUNK is 2^20)
CHUNK = 1000
#: the headroom limit of the checked cells (the transport's default, 2^63)
LIMIT_BITS = 63
#: checked cells: 4 rows (batch slots) of 700 cells; then 9 counts that are not checked
ROWS, COLS, EXTRA = 4, 700, 9


def inputs(rank: int, size: int):
    """(wrapping, checked) of one rank: ``wrapping``: 2 CHUNK + 3 numbers spread over all of
    [0, 2^64), whose sums wrap; ``checked``: ROWS x COLS checked cells (each below 2^63, as a
    rank's checked adds leave them) followed by EXTRA plain counts, as one flat array.

    Checked rows: 0 small numbers (no flag); 1 one cell of 0.6 x 2^63 on every rank (two
    ranks' sum passes the limit, no wrap); 2 one cell of 0.7 x 2^63 on every rank (three ranks'
    sum passes 2^64: a single wrapping sum would read 0.1 x 2^63 and miss the flag); 3 large
    cells of rank 0 only (2^63 - 1: flagged only with another rank's small ones)."""
    i = np.arange(2 * CHUNK + 3, dtype=np.uint64)
    with np.errstate(over="ignore"):
        wrapping = i * np.uint64(0x9E3779B97F4A7C15 + 2 * rank) + np.uint64(0xD1B54A32D192ED03 ^ rank)
    rng = np.random.default_rng(100 + rank)
    cells = rng.integers(0, 1 << 40, size=(ROWS, COLS), dtype=np.uint64)
    cells[1, 17] = np.uint64(int(0.6 * 2**63))
    cells[2, 301] = np.uint64(int(0.7 * 2**63))
    cells[3, :] = np.uint64(2**63 - 1) if rank == 0 else np.uint64(rank)
    extra = rng.integers(0, 1 << 50, size=EXTRA, dtype=np.uint64)
    return wrapping, np.concatenate([cells.reshape(-1), extra])


def main() -> None:
    out, kind = sys.argv[1], sys.argv[2]
    from nebula_rt.backends import parallel

    if kind in ("mpi4py", "cuda"):
        comm = parallel.world()
    else:
        from nebula_rt.filters.controller import vtk_world

        comm = vtk_world()
    parallel.SUM_CHUNK = CHUNK
    wrapping, checked = inputs(comm.rank, comm.size)
    reducer = ""
    if kind == "cuda":
        import cupy

        from nebula_rt.backends import get_backend

        backend = get_backend("cuda", str(comm.local_rank % cupy.cuda.runtime.getDeviceCount()))
        red = parallel.device_reducer(comm, backend) or parallel.StagedReducer(comm, backend)  # one rank: None
        reducer = red.kind
        sums = parallel.DeviceSums(comm, red)
        d_wrapping, d_checked = backend.to_device(wrapping), backend.to_device(checked)
        sums.sum_u64(d_wrapping)
        copied = comm.allreduce_u64(checked)
        flags = parallel.sum_checked(sums, [(d_checked, [(0, ROWS * COLS)])], ROWS, LIMIT_BITS)
        wrapping, checked = d_wrapping.get(), d_checked.get()
    else:
        comm.sum_u64(wrapping)
        copied = comm.allreduce_u64(checked)  # a new array, the input left as it was
        flags = parallel.sum_checked(comm, [(checked, [(0, ROWS * COLS)])], ROWS, LIMIT_BITS)
    if comm.rank == 0:
        np.savez(out, size=comm.size, kind=type(comm).__name__, wrapping=wrapping, checked=checked,
                 flags=flags, copied=copied, reducer=reducer)
    comm.barrier()


if __name__ == "__main__":
    main()  # no sys.exit: pvbatch would leave without finalising MPI (an error of mpiexec)
