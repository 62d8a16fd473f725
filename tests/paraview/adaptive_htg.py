"""Adaptive densities through ParaView's own VTK (nebula_rt.filters.adaptive): an octree written
as a vtkHyperTreeGrid to an .htg file with ParaView's writer, read back with its reader and
converted again; a two-level vtkOverlappingAMR written to a .vthb file and read back with every
level (the reader's default in ParaView 5.11 is level 0 only).

    pvpython adaptive_htg.py OUT.htg OUT.vthb

RESULT: the VTK version, the leaves and depth of the tree and of the one read back, whether the
voxel averages of the two (16 x 8 x 16) are equal, and the AMR's leaves as built and as read;
then the .htg read by ParaView's XMLHyperTreeGridReader into the Nebula Light Field proxy
(Resolution 16 x 8 x 16): its output's points, dimensions, bounds, arrays, error and the
leaves it traced; its third port (the light per leaf) shown by a script: whether it stays
visible, its cells and class, and how many times the proxy executed.
"""

import sys

import _common  # noqa: F401 - the plugin's paths
import numpy as np
from vtkmodules.vtkCommonCore import vtkVersion
from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridReader, vtkXMLHyperTreeGridWriter

from nebula_rt.density.octree import coarsen
from nebula_rt.density.resample import box_averages
from nebula_rt.filters.adaptive import octree_from_htg, octree_to_htg

n = 16
x = (np.arange(n) + 0.5) / n
X, Y, Z = np.meshgrid(x, x[4:12], x, indexing="ij")
rho = np.round(1.0 + 30.0 * np.exp(-((X - 0.3) ** 2 + (Y - 0.6) ** 2 + (Z - 0.4) ** 2) / 0.004), 1)
tree = coarsen(rho, (2, 1, 2))
writer = vtkXMLHyperTreeGridWriter()
writer.SetInputData(octree_to_htg(tree, {"density": tree.density}, bounds=(0.0, 2.0, -1.0, 0.0, 5.0, 7.0)))
writer.SetFileName(sys.argv[1])
writer.Write()
reader = vtkXMLHyperTreeGridReader()
reader.SetFileName(sys.argv[1])
reader.Update()
back = octree_from_htg(reader.GetOutput())
a, b = tree.leaves(), back.leaves()


def amr_two_levels():
    """Level 0: 8^3 cells over the unit box; level 1 refines level-0 cells [2, 5]^3."""
    from vtkmodules import vtkCommonDataModel as dm
    from vtkmodules.util.numpy_support import numpy_to_vtk

    amr = dm.vtkOverlappingAMR()
    amr.Initialize(2, [1, 1])
    amr.SetOrigin([0.0, 0.0, 0.0])
    for level, (lo, hi, h) in enumerate((((0, 0, 0), (7, 7, 7), 1 / 8), ((4, 4, 4), (11, 11, 11), 1 / 16))):
        n = np.array(hi) - np.array(lo) + 1
        g = dm.vtkUniformGrid()
        g.SetOrigin(*(np.array(lo) * h))
        g.SetSpacing(h, h, h)
        g.SetDimensions(*(n + 1))
        arr = numpy_to_vtk(np.linspace(1.0, 2.0, int(n.prod())), deep=1)
        arr.SetName("density")
        g.GetCellData().AddArray(arr)
        amr.SetSpacing(level, [h] * 3)
        amr.SetAMRBox(level, 0, dm.vtkAMRBox(list(lo), list(hi)))
        amr.SetDataSet(level, 0, g)
    amr.SetRefinementRatio(0, 2)
    return amr


from nebula_rt.filters.adaptive import octree_from_amr  # noqa: E402
from vtkmodules.vtkIOXML import vtkXMLUniformGridAMRReader, vtkXMLUniformGridAMRWriter  # noqa: E402

amr = amr_two_levels()
aw = vtkXMLUniformGridAMRWriter()
aw.SetInputData(amr)
aw.SetFileName(sys.argv[2])
aw.Write()
ar = vtkXMLUniformGridAMRReader()
ar.SetFileName(sys.argv[2])
ar.SetMaximumLevelsToReadByDefault(0)  # every level
ar.Update()
# the .htg through ParaView's own reader into the Light Field proxy (an adaptive input)
from paraview import simple  # noqa: E402
from nebula_rt_paraview.view import load_plugin  # noqa: E402

load_plugin()
htg_reader = simple.OpenDataFile(sys.argv[1])  # (ParaView picks its .htg reader)
light = simple.NebulaLightField(htg_reader, Photons=20000, Resolution=[16, 8, 16], Device=_common.TEST_DEVICE)
light.DensityArray = ["CELLS", "density"]
light.UpdatePipeline()
info = light.GetDataInformation()
alg = light.GetClientSideObject()
out = alg.GetOutputDataObject(0)
# a script's Show of the light per leaf (port 2) keeps it shown (Apply in the GUI, which shows
# every port with the volume, hides it)
leaf_view = simple.CreateRenderView()
leaf_display = simple.Show(simple.OutputPort(light, 2), leaf_view)
simple.Render(leaf_view)
leaf_info = light.GetDataInformation(2)
_common.result(leaf_shown=int(leaf_display.Visibility), leaf_cells=int(leaf_info.GetNumberOfCells()),
               leaf_class=leaf_info.GetDataClassName(),
               executions=alg.execution_count,vtk=vtkVersion.GetVTKVersion(), leaves=[tree.n_leaves, back.n_leaves], depth=[tree.depth(), back.depth()],
               same=bool(np.array_equal(box_averages(*a, rho.shape), box_averages(*b, rho.shape))),
               amr=[octree_from_amr(amr).n_leaves, octree_from_amr(ar.GetOutput()).n_leaves],
               light_points=int(info.GetNumberOfPoints()), light_dims=list(out.GetDimensions()),
               light_bounds=list(out.GetBounds()), light_error=alg.last_error,
               light_arrays=sorted(out.GetPointData().GetArrayName(i) for i in range(out.GetPointData().GetNumberOfArrays())),
               light_leaves=int(alg.last_light.transport.J.shape[1]) if alg.last_light is not None else 0)
