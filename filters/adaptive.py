"""Adaptive densities in and out of VTK: a ``vtkHyperTreeGrid`` to and from
:class:`nebula_rt.density.octree.Octree`, and a ``vtkOverlappingAMR`` to one
(docs/adaptive_grids.md).

The hyper tree grid must be 3-D with branch factor 2 over a uniform root grid (evenly spaced
coordinates on each axis); its bounds become the unit box. Every root tree must exist and no
leaf may be masked (a tree with holes is refused, as the transport needs density everywhere).
The AMR hierarchy must refine by 2 from level to level, its level 0 must cover its bounds
(each level-0 cell becomes a root), and its finer blocks must lie on their parents' cells;
the cells a finer level covers are found from the blocks' boxes, not from blanking arrays.
"""

from __future__ import annotations

import numpy as np

from nebula_rt.density.octree import Octree, from_boxes

__all__ = ["octree_from_amr", "octree_from_htg", "octree_to_htg", "read_adaptive_density",
           "read_particles"]


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


def octree_from_amr(amr, array: str = "density") -> Octree:
    """The :class:`Octree` of a ``vtkOverlappingAMR`` with the values of cell array ``array``
    on the cells no finer level covers (refinement ratio 2; VTK 9.2's and 9.6+'s block access
    both). Raises ValueError naming what does not fit (the ratio, a missing array, holes or
    overlaps, NaN or negative values)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules import vtkCommonDataModel as dm

    new_api = hasattr(dm, "vtkOverlappingAMRMetaData")  # VTK 9.6: blocks by GetNumberOfBlocks(level)
    levels = amr.GetNumberOfLevels()
    if levels < 1:
        raise ValueError("the AMR hierarchy has no levels")
    for L in range(levels - 1):
        if amr.GetRefinementRatio(L) != 2:
            raise ValueError(f"level {L} refines by {amr.GetRefinementRatio(L)}; an octree needs 2")
    boxes = []  # per level: [(lo (3,), hi (3,) inclusive cell indices, block)]
    for L in range(levels):
        n = amr.GetNumberOfBlocks(L) if new_api else amr.GetNumberOfDataSets(L)
        level = []
        for i in range(n):
            grid = amr.GetDataSetAsImageData(L, i) if new_api else amr.GetDataSet(L, i)
            if grid is None:
                continue
            lo, hi = [0] * 3, [0] * 3
            amr.GetAMRBox(L, i).GetDimensions(lo, hi)
            level.append((np.array(lo, np.int64), np.array(hi, np.int64), grid))
        boxes.append(level)
    if not boxes[0]:
        raise ValueError("the AMR hierarchy has no block on level 0")
    root_lo = np.min([b[0] for b in boxes[0]], axis=0)
    roots = np.max([b[1] for b in boxes[0]], axis=0) - root_lo + 1
    out_lo, out_hi, out_v = [], [], []
    for L, level in enumerate(boxes):
        finer = [(b[0] // 2, b[1] // 2) for b in boxes[L + 1]] if L + 1 < levels else []
        for lo, hi, grid in level:
            arr = grid.GetCellData().GetArray(array)
            if arr is None or arr.GetNumberOfComponents() != 1:
                names = [grid.GetCellData().GetArrayName(k) for k in range(grid.GetCellData().GetNumberOfArrays())]
                raise ValueError(f"level {L}: no one-component cell array {array!r}; the block has {names}")
            dims = hi - lo + 1
            ijk = np.stack(np.unravel_index(np.arange(int(dims.prod())), tuple(dims), order="F"), axis=1) + lo
            values = vtk_to_numpy(arr).astype(np.float64)
            if values.size != ijk.shape[0]:
                raise ValueError(f"level {L}: a block of {ijk.shape[0]} cells holds {values.size} values of {array!r}")
            covered = np.zeros(len(ijk), bool)
            for flo, fhi in finer:
                covered |= np.all((ijk >= flo) & (ijk <= fhi), axis=1)
            keep = ~covered
            cells = roots * (1 << L)
            corner = ijk[keep] - root_lo * (1 << L)
            out_lo.append(corner / cells)
            out_hi.append((corner + 1) / cells)
            out_v.append(values[keep])
    return from_boxes(np.concatenate(out_lo), np.concatenate(out_hi), np.concatenate(out_v),
                      tuple(int(r) for r in roots))



#: VTKHDF files (one HDF5 file for any VTK data type): read where the VTK in use reads hyper
#: tree grids and AMR hierarchies from them (VTK 9.7 both; ParaView 5.11's 9.2 AMR only)
VTKHDF_SUFFIXES = (".vtkhdf", ".hdf")


def read_adaptive_density(path, array: str = "density") -> Octree:
    """The octree of an adaptive density file: a ``vtkHyperTreeGrid`` (``.htg``, VTK's
    ``vtkXMLHyperTreeGridReader``), a ``vtkOverlappingAMR`` (``.vthb``,
    ``vtkXMLUniformGridAMRReader``), or either in a VTKHDF file (``.vtkhdf``, ``.hdf``:
    ``vtkHDFReader``), its cell array ``array`` the density (:func:`octree_from_htg`,
    :func:`octree_from_amr`). Raises ValueError saying why a file cannot be one (the reader's
    own errors included)."""
    from pathlib import Path

    from vtkmodules import vtkIOXML

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".htg", ".vthb") + VTKHDF_SUFFIXES:
        raise ValueError(f"a hyper tree grid or AMR file is .htg, .vthb or VTKHDF (.vtkhdf, .hdf), "
                         f"not {suffix or 'no suffix'}")
    if suffix in VTKHDF_SUFFIXES:
        try:
            from vtkmodules.vtkIOHDF import vtkHDFReader
        except ImportError:
            raise ValueError("this VTK has no VTKHDF reader (vtkIOHDF)") from None
        reader = vtkHDFReader()
        if hasattr(reader, "SetMaximumLevelsToReadByDefaultForAMR"):
            reader.SetMaximumLevelsToReadByDefaultForAMR(0)  # every level of an AMR hierarchy
    else:
        reader = (vtkIOXML.vtkXMLHyperTreeGridReader() if suffix == ".htg" else vtkIOXML.vtkXMLUniformGridAMRReader())
    from vtkmodules.vtkCommonCore import vtkCommand

    errors = []
    reader.AddObserver(vtkCommand.ErrorEvent, lambda obj, ev: errors.append(ev))
    reader.GetExecutive().AddObserver(vtkCommand.ErrorEvent, lambda obj, ev: errors.append(ev))
    reader.SetFileName(str(path))
    if suffix == ".vthb":
        reader.SetMaximumLevelsToReadByDefault(0)  # every level
    reader.Update()
    out = reader.GetOutputDataObject(0)
    if errors or out is None:
        raise ValueError(f"VTK's {type(reader).__name__} could not read it")
    if suffix in VTKHDF_SUFFIXES:
        kind = out.GetClassName()
        if out.IsA("vtkHyperTreeGrid"):
            return octree_from_htg(out, array)
        if out.IsA("vtkOverlappingAMR"):
            return octree_from_amr(out, array)
        raise ValueError(f"it holds a {kind}, not a hyper tree grid or an overlapping AMR hierarchy (a uniform "
                         f"density: .npy or .vti)")
    if suffix == ".htg":
        if out.GetNumberOfCells() == 0:
            raise ValueError("it holds no hyper tree grid")
        return octree_from_htg(out, array)
    if out.GetNumberOfLevels() == 0:
        raise ValueError("it holds no AMR hierarchy")
    return octree_from_amr(out, array)


def read_particles(path, mass: str = "mass", smoothing: str = "smoothing_length"):
    """An SPH particle snapshot from a ``.vtp`` (VTK's XML poly data: one point per particle,
    its ``mass`` and ``smoothing`` point-data arrays): (positions (n, 3), masses (n,),
    smoothing lengths (n,)), float64, in the file's coordinates. VTK's own format because every
    tool that converts simulation snapshots for ParaView (yt, pyvista, ParaView's own readers
    of Gadget and Phantom files) can write it; Gadget/Phantom's native files need those
    readers first. Raises ValueError saying what is missing."""
    from vtkmodules.vtkCommonCore import vtkCommand
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    errors = []
    reader.AddObserver(vtkCommand.ErrorEvent, lambda obj, ev: errors.append(ev))
    reader.GetExecutive().AddObserver(vtkCommand.ErrorEvent, lambda obj, ev: errors.append(ev))
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    if errors or poly is None or poly.GetPoints() is None or poly.GetNumberOfPoints() == 0:
        raise ValueError("VTK's vtkXMLPolyDataReader found no particles in it")
    return particles_of_polydata(poly, mass, smoothing)


def particles_of_polydata(poly, mass: str = "mass", smoothing: str = "smoothing_length"):
    """(positions (n, 3), masses (n,), smoothing lengths (n,)), float64, of a vtkPolyData's
    points and its ``mass`` and ``smoothing`` point arrays (:func:`read_particles`; the Light
    Field filter's particle input). Raises ValueError saying what is missing."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    if poly is None or poly.GetPoints() is None or poly.GetNumberOfPoints() == 0:
        raise ValueError("it holds no particles (points)")
    pd = poly.GetPointData()
    names = [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())]
    out = [vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64).reshape(-1, 3)]
    for what, name in (("mass", mass), ("smoothing length", smoothing)):
        arr = pd.GetArray(name) if name else None
        if arr is None or arr.GetNumberOfComponents() != 1:
            raise ValueError(f"it has no one-component point array {name!r} for the particles' {what}; it has {names}")
        out.append(vtk_to_numpy(arr).astype(np.float64).reshape(-1))
    return tuple(out)

