"""Adaptive densities in and out of VTK: a ``vtkHyperTreeGrid`` to and from
:class:`nebula_rt.density.octree.Octree` (docs/adaptive_grids.md).

The hyper tree grid must be 3-D with branch factor 2 over a uniform root grid (evenly spaced
coordinates on each axis); its bounds become the unit box. Every root tree must exist and no
leaf may be masked (a tree with holes is refused, as the transport needs density everywhere).
"""

from __future__ import annotations

import numpy as np

from nebula_rt.density.octree import Octree, from_boxes

__all__ = ["octree_from_htg", "octree_to_htg"]


def _uniform(coords, axis: str) -> tuple[float, float, int]:
    c = np.asarray(coords, np.float64)
    n = len(c) - 1
    if n < 1 or not np.all(np.diff(c) > 0):
        raise ValueError(f"the hyper tree grid's {axis} coordinates must increase ({len(c)} given)")
    step = (c[-1] - c[0]) / n
    if np.max(np.abs(np.diff(c) - step)) > 1e-9 * abs(step):
        raise ValueError(f"the hyper tree grid's {axis} coordinates must be evenly spaced (a uniform root grid)")
    return float(c[0]), float(c[-1]), n


def octree_from_htg(htg, array: str = "density") -> Octree:
    """The :class:`Octree` of a ``vtkHyperTreeGrid`` with the leaves' values of cell array
    ``array`` (one component). Raises ValueError naming what does not fit (dimension, branch
    factor, a non-uniform root grid, a missing or multi-component array, holes, NaN or
    negative values)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersHyperTree import vtkHyperTreeGridToUnstructuredGrid

    if htg.GetDimension() != 3 or htg.GetBranchFactor() != 2:
        raise ValueError(f"a hyper tree grid of dimension 3 and branch factor 2 is needed, got dimension "
                         f"{htg.GetDimension()} and branch factor {htg.GetBranchFactor()}")
    axes = [_uniform(vtk_to_numpy(c), a) for c, a in
            ((htg.GetXCoordinates(), "x"), (htg.GetYCoordinates(), "y"), (htg.GetZCoordinates(), "z"))]
    arr = htg.GetCellData().GetArray(array)
    if arr is None:
        names = [htg.GetCellData().GetArrayName(i) for i in range(htg.GetCellData().GetNumberOfArrays())]
        raise ValueError(f"the hyper tree grid has no cell array {array!r}; it has {names}")
    if arr.GetNumberOfComponents() != 1:
        raise ValueError(f"cell array {array!r} has {arr.GetNumberOfComponents()} components; 1 is needed")
    to_ug = vtkHyperTreeGridToUnstructuredGrid()
    to_ug.SetInputData(htg)
    to_ug.Update()
    ug = to_ug.GetOutput()
    n = ug.GetNumberOfCells()
    if n == 0:
        raise ValueError("the hyper tree grid has no leaves")
    pts = vtk_to_numpy(ug.GetPoints().GetData()).astype(np.float64)
    conn = vtk_to_numpy(ug.GetCells().GetConnectivityArray()).reshape(-1, 8)  # voxels: point 0 low, 7 high
    values = vtk_to_numpy(ug.GetCellData().GetArray(array))[:n].astype(np.float64)
    origin = np.array([a[0] for a in axes])
    extent = np.array([a[1] - a[0] for a in axes])
    roots = np.array([a[2] for a in axes])
    # the unstructured grid's points are float32: snap each leaf to its level and integer
    # corner (exact while a level has fewer than about 2^22 cells along an axis)
    lo = (pts[conn[:, 0]] - origin) / extent
    size = (pts[conn[:, 7]] - pts[conn[:, 0]]) / extent
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.rint(np.log2(1.0 / (roots[None, :] * size))).max(axis=1)
    level = np.clip(np.nan_to_num(level, nan=0.0, posinf=0.0, neginf=0.0), 0, 30)
    cells = roots[None, :] * 2.0 ** level[:, None]
    corner = np.rint(lo * cells)
    lo_exact, hi_exact = corner / cells, (corner + 1.0) / cells
    return from_boxes(lo_exact, hi_exact, values, tuple(int(r) for r in roots))


def octree_to_htg(tree: Octree, arrays: dict, bounds=(0.0, 1.0, 0.0, 1.0, 0.0, 1.0)):
    """A ``vtkHyperTreeGrid`` of ``tree`` over ``bounds`` with a float cell array per entry of
    ``arrays`` (name -> one value per leaf, in leaf order); a refined cell holds the mean of its
    children (the hyper tree grid keeps a value for every cell). Built cell by cell through a
    cursor: a few microseconds a cell."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkDoubleArray
    from vtkmodules.vtkCommonDataModel import vtkHyperTreeGrid
    from vtkmodules.vtkCommonDataModel import vtkHyperTreeGridNonOrientedGeometryCursor

    rx, ry, rz = tree.roots
    vals = {name: np.asarray(v, np.float64).reshape(-1) for name, v in arrays.items()}
    for name, v in vals.items():
        if v.size != tree.n_leaves:
            raise ValueError(f"array {name!r} has {v.size} values for {tree.n_leaves} leaves")
    htg = vtkHyperTreeGrid()
    htg.Initialize()
    htg.SetDimensions(rx + 1, ry + 1, rz + 1)
    htg.SetBranchFactor(2)
    for setter, (a, b), n in ((htg.SetXCoordinates, bounds[0:2], rx), (htg.SetYCoordinates, bounds[2:4], ry),
                              (htg.SetZCoordinates, bounds[4:6], rz)):
        setter(numpy_to_vtk(np.linspace(a, b, n + 1), deep=1))
    out = {}
    for name in vals:
        arr = vtkDoubleArray()
        arr.SetName(name)
        htg.GetCellData().AddArray(arr)
        out[name] = arr
    child = tree.child
    lo_b = np.array(bounds[0::2], np.float64)
    ext = np.array(bounds[1::2], np.float64) - lo_b
    cur = vtkHyperTreeGridNonOrientedGeometryCursor()
    box = [0.0] * 6

    def fill(node):
        """Set the cell's values (a leaf's, or its children's mean) and refine it like ``node``."""
        gid = cur.GetGlobalNodeIndex()
        c = int(child[node])
        if c < 0:
            v = {name: float(a[-1 - c]) for name, a in vals.items()}
        else:
            cur.GetBounds(box)
            mid = (np.array(box[0::2]) + np.array(box[1::2])) / 2.0
            cur.SubdivideLeaf()
            sums = dict.fromkeys(vals, 0.0)
            for k in range(8):
                cur.ToChild(k)
                cur.GetBounds(box)
                centre = (np.array(box[0::2]) + np.array(box[1::2])) / 2.0
                octant = int(centre[0] > mid[0]) + 2 * int(centre[1] > mid[1]) + 4 * int(centre[2] > mid[2])
                got = fill(c + octant)
                cur.ToParent()
                for name in sums:
                    sums[name] += got[name] / 8.0
            v = sums
        for name, x in v.items():
            out[name].InsertValue(gid, x)
        return v

    offset = 0
    for tid in range(htg.GetMaxNumberOfTrees()):
        htg.InitializeNonOrientedGeometryCursor(cur, tid, True)
        cur.SetGlobalIndexStart(offset)
        cur.GetBounds(box)
        centre = ((np.array(box[0::2]) + np.array(box[1::2])) / 2.0 - lo_b) / ext
        i, j, k = (min(int(centre[a] * n), n - 1) for a, n in enumerate((rx, ry, rz)))
        fill(i + rx * (j + ry * k))
        offset += cur.GetTree().GetNumberOfVertices()
    return htg
