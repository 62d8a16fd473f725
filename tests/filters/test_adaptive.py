"""Adaptive densities in and out of VTK (nebula_rt.filters.adaptive) with the VTK of the
library's environment: an octree written as a vtkHyperTreeGrid (and through an .htg file)
comes back as the same field; what the transport cannot take is refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from nebula_rt.density.octree import coarsen
from nebula_rt.density.resample import box_averages
from nebula_rt.filters.adaptive import octree_from_htg, octree_to_htg


def clumpy(n=16):
    x = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    rho = np.ones((n, n, n))
    rho += 30.0 * np.exp(-((X - 0.3) ** 2 + (Y - 0.6) ** 2 + (Z - 0.4) ** 2) / 0.004)
    return np.round(rho, 1)  # equal values in the background: they merge


def _same_field(a, b, shape):
    la, ha, va = a.leaves()
    lb, hb, vb = b.leaves()
    assert a.n_leaves == b.n_leaves and a.depth() == b.depth() and a.roots == b.roots
    np.testing.assert_array_equal(box_averages(la, ha, va, shape), box_averages(lb, hb, vb, shape))


def test_an_octree_goes_through_a_hyper_tree_grid_and_an_htg_file(tmp_path):
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridReader, vtkXMLHyperTreeGridWriter

    tree = coarsen(clumpy()[:, 4:12, :], (2, 1, 2))  # root cells of 8^3 voxels
    assert 16 < tree.n_leaves < 16 * 8 * 16 and tree.depth() == 3
    htg = octree_to_htg(tree, {"density": tree.density}, bounds=(0.0, 2.0, -1.0, 0.0, 5.0, 7.0))
    assert htg.GetNumberOfLeaves() == tree.n_leaves
    _same_field(octree_from_htg(htg), tree, (16, 8, 16))
    path = tmp_path / "tree.htg"
    writer = vtkXMLHyperTreeGridWriter()
    writer.SetInputData(htg)
    writer.SetFileName(str(path))
    assert writer.Write() == 1
    reader = vtkXMLHyperTreeGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    _same_field(octree_from_htg(reader.GetOutput()), tree, (16, 8, 16))


def test_refined_cells_hold_their_childrens_mean():
    from vtkmodules.util.numpy_support import vtk_to_numpy

    tree = coarsen(clumpy(8), (1, 1, 1))
    htg = octree_to_htg(tree, {"density": tree.density})
    values = vtk_to_numpy(htg.GetCellData().GetArray("density"))
    assert values.size == htg.GetNumberOfCells() == len(tree.child)
    lo, hi, v = tree.leaves()
    root_mean = (v * np.prod(hi - lo, axis=1)).sum()
    assert np.isclose(values.max(), v.max()) and any(np.isclose(values, root_mean, rtol=1e-6))


def test_what_the_transport_cannot_take_is_refused():
    from vtkmodules.vtkCommonCore import vtkBitArray

    tree = coarsen(clumpy(8), (1, 1, 1))
    with pytest.raises(ValueError, match="no cell array 'rho'.*density"):
        octree_from_htg(octree_to_htg(tree, {"density": tree.density}), "rho")
    htg = octree_to_htg(tree, {"density": tree.density})
    mask = vtkBitArray()
    mask.SetNumberOfTuples(htg.GetNumberOfCells())
    mask.Fill(0)
    mask.SetValue(htg.GetNumberOfCells() - 1, 1)  # hide one leaf
    htg.SetMask(mask)
    with pytest.raises(ValueError, match="holes"):
        octree_from_htg(htg)
    bad = tree.density.copy()
    bad[3] = -2.0
    with pytest.raises(ValueError, match="density -2.0 must be finite and >= 0"):
        octree_from_htg(octree_to_htg(tree, {"density": bad}))
    with pytest.raises(ValueError, match="values for"):
        octree_to_htg(tree, {"density": tree.density[:-1]})
