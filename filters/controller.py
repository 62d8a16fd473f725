"""The communicator of a VTK pipeline: ParaView's parallel engine (pvbatch, pvserver) runs the
light-field filter on every rank, which trace together through the global
``vtkMultiProcessController`` with the reductions of :mod:`nebula_rt.parallel`."""

from __future__ import annotations

import os

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkDoubleArray

from nebula_rt.parallel import Serial

try:
    from vtkmodules.vtkParallelCore import vtkCommunicator, vtkMultiProcessController
except ImportError:  # a VTK built without its parallel module: always one process
    vtkCommunicator = vtkMultiProcessController = None


class VTKControllerComm:
    """A VTK multi-process controller (ParaView's parallel engine: pvbatch, pvserver), with the
    same reductions as :class:`nebula_rt.parallel.MPIComm` through
    ``vtkMultiProcessController.AllReduce`` and ``Broadcast`` (numbers only)."""

    def __init__(self, controller):
        self.controller = controller
        self.rank = int(controller.GetLocalProcessId())
        self.size = int(controller.GetNumberOfProcesses())
        # a controller knows no nodes: the launcher's node-local rank if it says, else the rank
        self.local_rank = int(os.environ.get("OMPI_COMM_WORLD_LOCAL_RANK", os.environ.get("MPI_LOCALRANKID", self.rank)))
        self.local_size = int(os.environ.get("OMPI_COMM_WORLD_LOCAL_SIZE", self.size))

    def _allreduce(self, a: np.ndarray, op) -> np.ndarray:
        src = np.ascontiguousarray(a).reshape(-1)
        send = numpy_to_vtk(src, deep=False)
        recv = send.NewInstance()
        recv.SetNumberOfComponents(1)
        recv.SetNumberOfTuples(src.size)
        if not self.controller.AllReduce(send, recv, op):
            raise RuntimeError("vtkMultiProcessController.AllReduce failed")
        return vtk_to_numpy(recv).astype(src.dtype, copy=True).reshape(np.shape(a))

    def allreduce_u64(self, a: np.ndarray) -> np.ndarray:
        return self._allreduce(np.asarray(a, np.uint64), vtkCommunicator.SUM_OP)

    def allreduce_max(self, x: float) -> float:
        return float(self._allreduce(np.array([float(x)]), vtkCommunicator.MAX_OP)[0])

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


def vtk_world():
    """The communicator of a VTK pipeline: :class:`VTKControllerComm` over the global
    controller when it has several processes (ParaView's MPI engine), else :class:`Serial`."""
    if vtkMultiProcessController is None:
        return Serial()
    controller = vtkMultiProcessController.GetGlobalController()
    if controller is None or controller.GetNumberOfProcesses() < 2:
        return Serial()
    return VTKControllerComm(controller)
