"""An octree through ParaView's own VTK: written as a vtkHyperTreeGrid, to an .htg file with
ParaView's writer, read back with its reader and converted again (nebula_rt.filters.adaptive).

    pvpython adaptive_htg.py OUT.htg

RESULT: the VTK version, the leaves and depth of the tree and of the one read back, and whether
the voxel averages of the two (16 x 8 x 16) are equal.
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
_common.result(vtk=vtkVersion.GetVTKVersion(), leaves=[tree.n_leaves, back.n_leaves], depth=[tree.depth(), back.depth()],
               same=bool(np.array_equal(box_averages(*a, rho.shape), box_averages(*b, rho.shape))))
