"""Run under ``mpiexec -n 2 pvbatch --mpi --symmetric`` by tests/paraview/test_paraview.py: rank 1's
second transport launch raises a device error (the real launch wrapped); the job must end with
the rank and the cause on stderr instead of rank 0 waiting forever in its next reduction.

    mpiexec -n 2 pvbatch --mpi --symmetric mpi_rank_fails.py
"""

import _common
from paraview import simple
from vtkmodules.vtkParallelCore import vtkMultiProcessController

from nebula_rt.backends import session
from nebula_rt.errors import NebulaError

rank = vtkMultiProcessController.GetGlobalController().GetLocalProcessId()
launch = session.DeviceTransport.run_group
calls = {"n": 0}


def failing(self, *a, **kw):
    calls["n"] += 1
    if rank == 1 and calls["n"] == 2:
        raise NebulaError("the device lost its context (injected on rank 1)")
    return launch(self, *a, **kw)


session.DeviceTransport.run_group = failing
density = simple.NebulaDustDensity()
density.GridShape = [16, 16, 16]
density.Device = _common.TEST_DEVICE
lf = simple.NebulaLightField(Input=density)
lf.Photons = 400000
lf.BatchSize = 20000
lf.Device = _common.TEST_DEVICE
lf.UpdatePipeline()
_common.result(rank=rank, finished=True)  # must not be reached on any rank
