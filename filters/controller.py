"""The communicator of a VTK pipeline: ParaView's parallel engine (pvbatch, pvserver) runs the
light-field filter on every rank, which trace together through the global
``vtkMultiProcessController`` with the reductions of :mod:`nebula_rt.backends.parallel`."""

from __future__ import annotations

import os

import numpy as np
from vtkmodules.vtkCommonCore import vtkDoubleArray, vtkTypeUInt64Array

from nebula_rt.backends import parallel
from nebula_rt.backends.parallel import Serial, _flat_u64

try:
    from vtkmodules.vtkParallelCore import vtkCommunicator, vtkMultiProcessController
except ImportError:  # a VTK built without its parallel module: always one process
    vtkCommunicator = vtkMultiProcessController = None


class VTKControllerComm:
    """A VTK multi-process controller (ParaView's parallel engine: pvbatch, pvserver), with
    the same reductions as :class:`nebula_rt.backends.parallel.MPIComm` through ``vtkMultiProcessController.AllReduce``
    and ``Broadcast`` (numbers only)."""

    def __init__(self, controller):
        self.controller = controller
        self.rank = int(controller.GetLocalProcessId())
        self.size = int(controller.GetNumberOfProcesses())
        # a controller knows no nodes: the launcher's node-local rank if it says, else the rank
        self.local_rank = int(os.environ.get("OMPI_COMM_WORLD_LOCAL_RANK", os.environ.get("MPI_LOCALRANKID", self.rank)))
        self.local_size = int(os.environ.get("OMPI_COMM_WORLD_LOCAL_SIZE", self.size))

    def sum_u64(self, buf: np.ndarray) -> np.ndarray:
        """In place, in chunks of :data:`nebula_rt.backends.parallel.SUM_CHUNK` elements: each chunk is copied into a
        send array and reduced straight into ``buf``'s memory (both ``vtkTypeUInt64Array``
        views of numpy memory, so nothing is converted; MPI forbids the same buffer for both)."""
        flat = _flat_u64(buf)
        chunk = parallel.SUM_CHUNK
        scratch = np.empty(min(flat.size, chunk), np.uint64)
        for lo in range(0, flat.size, chunk):
            part = flat[lo:lo + chunk]
            send = scratch[:part.size]
            send[...] = part
            self._allreduce(_vtk_view(vtkTypeUInt64Array, send), _vtk_view(vtkTypeUInt64Array, part),
                            vtkCommunicator.SUM_OP)
        return buf

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        return self.sum_u64(np.array(a, np.uint64, copy=True))

    def _allreduce(self, send, recv, op) -> None:
        if not self.controller.AllReduce(send, recv, op):
            raise RuntimeError("vtkMultiProcessController.AllReduce failed")

    def allreduce_max(self, x: float) -> float:
        send, recv = np.array([float(x)]), np.empty(1)
        self._allreduce(_vtk_view(vtkDoubleArray, send), _vtk_view(vtkDoubleArray, recv), vtkCommunicator.MAX_OP)
        return float(recv[0])

    def bcast(self, obj, root: int = 0):
        """Broadcast a number (int, float or bool) from ``root``."""
        arr = vtkDoubleArray()
        arr.SetNumberOfTuples(1)
        arr.SetValue(0, float(obj) if self.rank == root else 0.0)
        self.controller.Broadcast(arr, root)
        v = arr.GetValue(0)
        return type(obj)(v) if self.rank == root else (int(v) if float(v).is_integer() else v)

    def barrier(self) -> None:
        self.controller.Barrier()

    def abort(self, code: int) -> None:
        """End every rank of the job (MPI_Abort through mpi4py, which Debian's ParaView's
        Python has; else the controller's own break of its remote-method loop)."""
        try:
            from mpi4py import MPI

            MPI.COMM_WORLD.Abort(int(code))
        except ImportError:
            self.controller.TriggerBreakRMIs()
            os._exit(int(code))


def _vtk_view(cls, a: np.ndarray):
    """A VTK array of class ``cls`` over the memory of the flat contiguous numpy array ``a``
    (no copy; VTK neither frees nor reallocates it, and a reduction of the same length into it
    keeps its memory)."""
    v = cls()
    v.SetNumberOfComponents(1)
    v.SetVoidArray(a, a.size, 1)
    v._numpy = a  # keep the memory alive as long as the view
    return v


def vtk_world():
    """The communicator of a VTK pipeline: :class:`VTKControllerComm` over the global
    controller when it has several processes (ParaView's MPI engine), else :class:`Serial`."""
    if vtkMultiProcessController is None:
        return Serial()
    controller = vtkMultiProcessController.GetGlobalController()
    if controller is None or controller.GetNumberOfProcesses() < 2:
        return Serial()
    return VTKControllerComm(controller)
