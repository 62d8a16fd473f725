"""Run under ``mpiexec -n N pvbatch --mpi --symmetric`` by tests/paraview/test_paraview.py: Nebula Light
Field in ParaView's parallel engine, fed by a piece-aware reader or by the Dust Density source,
saved with SaveData as a .pvti (each rank writes its own piece).

    mpiexec -n N pvbatch --mpi --symmetric mpi_light_field.py reader|source DENSITY.vti OUT.pvti ESTIMATOR

A Nebula Colour follows. RESULT (rank 0): the ranks, each rank's input and output extents, the
transport_ranks of the output's field data, and the colour's extent and exposure.
"""

import sys

import _common
from paraview import simple
from vtkmodules.vtkParallelCore import vtkMultiProcessController

kind, density_file, out_file, estimator = sys.argv[1:5]
controller = vtkMultiProcessController.GetGlobalController()
rank, size = controller.GetLocalProcessId(), controller.GetNumberOfProcesses()
if kind == "reader":
    up = simple.XMLImageDataReader(FileName=[density_file])
else:
    up = simple.NebulaDustDensity()
    up.GridShape = [16, 14, 12]
    up.Device = _common.TEST_DEVICE
lf = simple.NebulaLightField(Input=up)
lf.Photons = 6000
lf.Device = _common.TEST_DEVICE
lf.Estimator = estimator
lf.UpdatePipeline()
alg = lf.GetClientSideObject()
out = alg.GetOutputDataObject(0)
inp = alg.GetInputDataObject(0, 0)
ranks_fd = out.GetFieldData().GetArray("transport_ranks")
mine = {"rank": rank, "input_extent": list(inp.GetExtent()), "output_extent": list(out.GetExtent()),
        "transport_ranks": int(ranks_fd.GetValue(0)) if ranks_fd is not None else None,
        "error": alg.last_error}
simple.SaveData(out_file, proxy=lf)
# Nebula Colour downstream: it asks for the whole light field, so its exposure is global
col = simple.NebulaColour(Input=lf)
col.UpdatePipeline()
colour_out = col.GetClientSideObject().GetOutputDataObject(0)
exposure_fd = colour_out.GetFieldData().GetArray("exposure")
colour_row = list(colour_out.GetExtent()) + [exposure_fd.GetValue(0) if exposure_fd is not None else -1.0]
# gather the ranks' reports on rank 0 (numbers only: through the controller as doubles)
from vtkmodules.vtkCommonCore import vtkDoubleArray

row = (mine["input_extent"] + mine["output_extent"] + [mine["transport_ranks"] or 0, 0 if mine["error"] is None else 1]
       + colour_row)
send = vtkDoubleArray()
send.SetNumberOfTuples(len(row))
for i, v in enumerate(row):
    send.SetValue(i, float(v))
recv = vtkDoubleArray()
controller.Gather(send, recv, 0)
if rank == 0:
    rows = [[recv.GetValue(r * len(row) + i) for i in range(len(row))] for r in range(size)]
    _common.result(size=size, error=mine["error"], ranks=[
        {"input_extent": [int(v) for v in r[:6]], "output_extent": [int(v) for v in r[6:12]],
         "transport_ranks": int(r[12]), "failed": bool(r[13]),
         "colour_extent": [int(v) for v in r[14:20]], "exposure": r[20]} for r in rows])
