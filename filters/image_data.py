"""NumPy grids and field data in a vtkImageData, through VTK's ``dataset_adapter``.

Grids are NumPy arrays of shape ``(nx, ny, nz)`` (scalars) or ``(nx, ny, nz, c)`` (``c``
components, e.g. RGBA ``uint8``), indexed ``[i, j, k]`` = ``[x, y, z]``. VTK stores the points
x fastest, point ``[i, j, k]`` being VTK point ``i + nx * (j + ny * k)``: the grid's Fortran
order. That reordering (:func:`to_vtk_order`, :func:`from_vtk_order`) is all this module adds;
arrays go in and out through :mod:`vtkmodules.numpy_interface.dataset_adapter`, which works in
ParaView's Python as in the VTK wheel (pyvista is not used here: ParaView has none).

Field data values (:func:`add_field_data`, :func:`field_data_dict`):

* ``float`` (and NumPy floating scalars): a one-value ``float64`` array;
* ``int``, ``bool`` and NumPy integer scalars: a one-value ``int64`` array (a ``bool`` reads
  back as ``int``); NumPy ``uint64`` scalars and ints in [2**63, 2**64): ``uint64`` (XML type
  ``UInt64``), read back as ``int``;
* ``str``: a one-value ``vtkStringArray`` (UTF-8);
* 1-D numeric arrays (or lists/tuples of numbers): ``float64`` (any floating dtype),
  ``uint64`` (``uint64``) or ``int64`` (any other integer or bool dtype), read back as arrays;
  a one-element array stays an array on reading (its component is named
  :data:`ARRAY_MARKER`).

The light field's own entries and their types are declared in :mod:`nebula_rt.pipeline.output_contract`.
"""

from __future__ import annotations

import numbers

import numpy as np
from vtkmodules.numpy_interface import dataset_adapter as dsa
from vtkmodules.vtkCommonCore import vtkStringArray
from vtkmodules.vtkCommonDataModel import vtkImageData

__all__ = [
    "ARRAY_MARKER", "add_field_data", "add_point_arrays", "cell_array", "field_data_dict",
    "from_vtk_order", "image_geometry", "point_array", "to_image_data", "to_vtk_order",
]

#: Component name of 1-D field-data arrays of one element, so that :func:`field_data_dict`
#: returns them as arrays and not as scalars.
ARRAY_MARKER = "nebula_rt:array"


def check_numeric_dtype(name: str, dtype: np.dtype, what: str = "point array") -> None:
    """VTK image data holds 8-64 bit integers, float32 and float64."""
    if dtype.kind not in "iuf" or dtype.itemsize > 8 or dtype == np.float16:
        raise TypeError(
            f"{what} {name!r} has dtype {dtype}, which VTK image data cannot hold; "
            "use a signed/unsigned integer of 8-64 bits, float32 or float64"
        )


def to_vtk_order(name: str, grid: np.ndarray) -> np.ndarray:
    """(nx, ny, nz) or (nx, ny, nz, c) -> (N,) or (N, c), point index i + nx*(j + ny*k)."""
    if grid.ndim == 3:
        return np.ravel(grid, order="F")
    if grid.ndim == 4:
        # (nx,ny,nz,c) -> (nz,ny,nx,c): C-order flattening then makes i fastest
        return np.ascontiguousarray(grid.transpose(2, 1, 0, 3)).reshape(-1, grid.shape[3])
    raise ValueError(f"point array {name!r} has shape {grid.shape}; expected (nx, ny, nz) or (nx, ny, nz, c)")


def from_vtk_order(flat: np.ndarray, dims) -> np.ndarray:
    """Inverse of :func:`to_vtk_order`: a fresh C-ordered NumPy grid."""
    nx, ny, nz = dims
    flat = np.asarray(flat)
    if flat.ndim == 1:
        grid = flat.reshape((nx, ny, nz), order="F")
    else:
        grid = flat.reshape(nz, ny, nx, flat.shape[1]).transpose(2, 1, 0, 3)
    return np.array(grid, order="C", copy=True)  # never a view of VTK's memory


def image_geometry(img):
    """(dimensions, spacing, origin of the first point) of a vtkImageData (an extent that does
    not start at 0 shifts the first point)."""
    dims = tuple(int(d) for d in img.GetDimensions())
    spacing = tuple(float(s) for s in img.GetSpacing())
    ext = img.GetExtent()
    origin = tuple(float(o) + ext[2 * ax] * spacing[ax] for ax, o in enumerate(img.GetOrigin()))
    return dims, spacing, origin


# --------------------------------------------------------------------------- point and cell data


def add_point_arrays(img, point_arrays: dict) -> None:
    """Add (nx, ny, nz[, c]) grids as point-data arrays of ``img`` (its dimensions), x fastest."""
    pd = dsa.WrapDataObject(img).PointData
    dims = tuple(img.GetDimensions())
    for name, arr in point_arrays.items():
        a = np.asarray(arr)
        check_numeric_dtype(name, a.dtype)
        if a.ndim not in (3, 4) or tuple(a.shape[:3]) != dims:
            # dataset_adapter would repeat a short array over the points: refuse instead
            raise ValueError(f"point array {name!r} has shape {a.shape}; the image's points are {dims}")
        if not a.dtype.isnative:
            a = a.astype(a.dtype.newbyteorder("="))
        pd.append(to_vtk_order(name, a), name)


def _array(attributes, name: str, dims, what: str) -> np.ndarray:
    arr = attributes[name]
    if not isinstance(arr, np.ndarray):  # dsa.NoneArray, or a vtkStringArray
        raise KeyError(f"{what} array {name!r} not found; available: {attributes.keys()}")
    return from_vtk_order(arr, dims)


def point_array(img, name: str) -> np.ndarray:
    """Point-data array ``name`` of a vtkImageData as an (nx, ny, nz[, c]) grid (a copy).

    Raises
    ------
    KeyError
        No numeric point array of that name (the message lists those there are).
    """
    dims, _, _ = image_geometry(img)
    return _array(dsa.WrapDataObject(img).PointData, name, dims, "point")


def cell_array(img, name: str) -> np.ndarray:
    """Cell-data array ``name`` of a vtkImageData as an (nx-1, ny-1, nz-1[, c]) grid (a copy)."""
    dims, _, _ = image_geometry(img)
    return _array(dsa.WrapDataObject(img).CellData, name, tuple(max(d - 1, 1) for d in dims), "cell")


# --------------------------------------------------------------------------- field data


def _field_array(name: str, value) -> tuple[np.ndarray, bool]:
    """A field-data value as a 1-D array of the type the module notes give, and whether it was
    an array (not a scalar)."""
    if isinstance(value, (bool, np.bool_, numbers.Integral)):
        iv = int(value)
        if isinstance(value, np.uint64) or 2**63 <= iv < 2**64:
            if not 0 <= iv < 2**64:
                raise OverflowError(f"field data {name!r} = {iv} does not fit in uint64")
            return np.array([iv], np.uint64), False
        if not -(2**63) <= iv < 2**63:
            raise OverflowError(f"field data {name!r} = {iv} does not fit in int64 or uint64")
        return np.array([iv], np.int64), False
    if isinstance(value, numbers.Real):
        return np.array([float(value)], np.float64), False
    if isinstance(value, (np.ndarray, list, tuple)):
        a = np.asarray(value)
        if a.ndim != 1:
            raise ValueError(f"field data {name!r} has shape {a.shape}; only scalars, strings and "
                             "1-D numeric arrays are supported")
        if a.size == 0 and a.dtype.kind not in "iufb":
            a = a.astype(np.float64)  # an empty list: no dtype to keep
        if a.dtype.kind == "f":
            return a.astype(np.float64), True
        if a.dtype == np.uint64:
            return a.astype(np.uint64), True
        if a.dtype.kind in "iub":
            if a.dtype.kind == "u" and a.size and int(a.max()) >= 2**63:
                raise OverflowError(f"field data {name!r} has values that do not fit in int64")
            return a.astype(np.int64), True
        raise TypeError(f"field data {name!r} has dtype {a.dtype}; 1-D arrays must be numeric")
    raise TypeError(f"field data {name!r} has type {type(value).__name__}; supported: float, int, "
                    "str and 1-D numeric arrays")


def add_field_data(img, field_data: dict) -> None:
    """Add scalars, strings and 1-D arrays as field data of ``img`` (replacing same names)."""
    fd = dsa.WrapDataObject(img).FieldData
    typed = {}
    for name, value in field_data.items():  # check every value before changing anything
        if not isinstance(name, str) or not name:
            raise ValueError(f"field data names must be non-empty strings, got {name!r}")
        if isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
            typed[name] = list(value)  # a string array
            continue
        typed[name] = value if isinstance(value, str) else _field_array(name, value)
    for name, value in typed.items():
        if fd.VTKObject.HasArray(name):
            fd.VTKObject.RemoveArray(name)
        if isinstance(value, (str, list)):  # dataset_adapter holds numbers only
            s = vtkStringArray()
            s.SetName(name)
            for v in ([value] if isinstance(value, str) else value):
                s.InsertNextValue(v)
            fd.VTKObject.AddArray(s)
            continue
        a, is_array = value
        fd.append(a, name)
        if is_array and a.size == 1:
            fd.VTKObject.GetArray(name).SetComponentName(0, ARRAY_MARKER)


def field_data_dict(img) -> dict[str, object]:
    """All field data of ``img`` as Python values (the module notes; 2-D arrays for
    multi-component arrays of other writers)."""
    fd = dsa.WrapDataObject(img).FieldData
    out: dict[str, object] = {}
    for idx in range(fd.VTKObject.GetNumberOfArrays()):
        raw = fd.VTKObject.GetAbstractArray(idx)
        name = raw.GetName()
        if raw.IsA("vtkStringArray"):
            values = [raw.GetValue(i) for i in range(raw.GetNumberOfValues())]
            out[name] = values[0] if len(values) == 1 else values
            continue
        if not raw.IsA("vtkDataArray"):
            continue  # e.g. a vtkVariantArray: not something NebulaRT writes
        a = np.array(fd[idx], copy=True)
        marked = raw.GetNumberOfComponents() == 1 and raw.GetComponentName(0) == ARRAY_MARKER
        if a.size == 1 and not marked:
            v = a.reshape(-1)[0]
            out[name] = int(v) if a.dtype.kind in "iu" else float(v)
        else:
            out[name] = a
    return out


def to_image_data(point_arrays: dict, field_data: dict | None, spacing, origin=(0.0, 0.0, 0.0)):
    """A vtkImageData holding ``point_arrays`` (all (nx, ny, nz[, c])) and ``field_data``;
    ``origin``: the first point (voxel centre [0, 0, 0])."""
    if not point_arrays:
        raise ValueError("to_image_data needs at least one point array")
    first = np.asarray(next(iter(point_arrays.values())))
    if first.ndim not in (3, 4):
        raise ValueError(f"point array {next(iter(point_arrays))!r} has shape {first.shape}; "
                         "expected (nx, ny, nz) or (nx, ny, nz, c)")
    img = vtkImageData()
    img.SetDimensions(*(int(n) for n in first.shape[:3]))
    img.SetSpacing(*spacing)
    img.SetOrigin(*origin)
    add_point_arrays(img, point_arrays)
    if len(point_arrays) == 1:
        img.GetPointData().SetActiveScalars(next(iter(point_arrays)))
    add_field_data(img, field_data or {})
    return img
