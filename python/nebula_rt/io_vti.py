"""Reading and writing VTK XML image data (``.vti``).

VTK is imported lazily inside the functions, so ``import nebula_rt`` (and
``import nebula_rt.io_vti``) works on a machine without VTK. Only the VTK
modules needed are imported (``vtkmodules.vtkCommonCore``,
``vtkmodules.vtkCommonDataModel``, ``vtkmodules.vtkIOXML`` and
``vtkmodules.util.numpy_support``), never the ``vtk`` meta-module.

Array layout
------------
Point arrays are NumPy arrays of shape ``(nx, ny, nz)`` (scalars) or
``(nx, ny, nz, c)`` (``c`` components, e.g. RGBA ``uint8`` with ``c = 4``),
indexed ``[i, j, k]`` = ``[x, y, z]``. VTK stores points x-fastest, so point
``[i, j, k]`` is VTK point ``i + nx * (j + ny * k)``. The image's points are the
voxel centres: its dimensions are ``(nx, ny, nz)`` and its origin is the
centre of voxel ``[0, 0, 0]``.

Field data
----------
``field_data`` maps names to

* ``float`` (and NumPy floating scalars): a one-value ``vtkDoubleArray``;
* ``int``, ``bool`` and NumPy integer scalars: a one-value
  ``vtkTypeInt64Array`` (exact over the whole int64 range; a ``bool`` reads
  back as ``int``); NumPy unsigned 64-bit scalars, and ints in [2**63, 2**64),
  a one-value ``vtkTypeUInt64Array`` (XML type ``UInt64``, read back as ``int``:
  the seed's whole range);
* ``str``: a one-value ``vtkStringArray`` (UTF-8);
* 1-D numeric arrays (or lists/tuples of numbers): ``vtkDoubleArray`` (any
  floating dtype), ``vtkTypeUInt64Array`` (``uint64``) or ``vtkTypeInt64Array``
  (any other integer or bool dtype), read back as ``float64`` / ``uint64`` /
  ``int64`` arrays. A one-element array keeps being an
  array on reading (it is marked through its component name).
"""

from __future__ import annotations

import errno
import math
import numbers
import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import NebulaError

__all__ = [
    "ArrayNotFoundError",
    "read_density_array",
    "read_vti",
    "write_vti",
]

#: Component name given to 1-D field-data arrays of a single element, so that
#: :func:`read_vti` returns them as arrays and not as scalars.
_ARRAY_MARKER = "nebula_rt:array"

_NUMERIC_KINDS = "iuf"


class ArrayNotFoundError(NebulaError, KeyError, ValueError):
    """A named array is not present in a data file.

    Attributes
    ----------
    path : pathlib.Path
        The file searched.
    array_name : str
        The name asked for.
    available : list of str
        The names of the arrays that the file has.
    """

    def __init__(self, path: Path, array_name: str, available: list[str]):
        self.path = Path(path)
        self.array_name = array_name
        self.available = list(available)
        listed = ", ".join(repr(a) for a in self.available) if self.available else "none"
        self.message = (
            f"{self.path}: no array named {array_name!r}; available arrays: {listed}"
        )
        super().__init__(self.message)

    def __str__(self) -> str:  # KeyError would quote the message
        return self.message


# --------------------------------------------------------------------------- helpers


class _ErrorCatcher:
    """Observer collecting the ErrorEvent/WarningEvent messages of a VTK object.

    While an object has an ErrorEvent observer, VTK does not print its errors
    to the output window: they end up here and in the exception raised.
    """

    def __init__(self) -> None:
        self.errors: list[str] = []
        self.warnings: list[str] = []

    def attach(self, obj) -> None:
        obj.AddObserver("ErrorEvent", self._on_error)
        obj.AddObserver("WarningEvent", self._on_warning)

    def _on_error(self, _obj, _event, calldata=None) -> None:
        self.errors.append(_clean_vtk_message(calldata))

    def _on_warning(self, _obj, _event, calldata=None) -> None:
        self.warnings.append(_clean_vtk_message(calldata))

    # VTK passes the message as call data only when the callback asks for a
    # string (vtkmodules.util.vtkConstants.VTK_STRING == 13; hard-coded here so
    # that this module imports without VTK).
    _on_error.CallDataType = 13
    _on_warning.CallDataType = 13


def _clean_vtk_message(msg: Any) -> str:
    """The substance of a VTK message: its first line after the source location."""
    if msg is None:
        return "(no message)"
    lines = [ln.strip() for ln in str(msg).splitlines() if ln.strip()]
    # VTK messages read "ERROR: In file.cxx, line N\nvtkClass (0x...): text\n<details>".
    if len(lines) > 1 and lines[0].startswith(("ERROR: In ", "Warning: In ")):
        lines = lines[1:]
    return lines[0] if lines else "(no message)"


class _CapturedVtkMessages:
    """Context manager that captures what VTK would print, instead of printing it.

    Errors of helper objects that a reader creates internally (its XML parser,
    for instance) do not reach an observer on the reader: VTK sends them to the
    global output window and to its logger, i.e. to stderr. Within this context
    the output window is a :class:`vtkStringOutputWindow` and the logger's
    stderr sink is off; the error messages are in :attr:`errors` afterwards and
    go into the exception raised. (The swap is process-global: do not read
    ``.vti`` files from several threads at once.)
    """

    def __enter__(self):
        from vtkmodules.vtkCommonCore import (
            vtkLogger,
            vtkOutputWindow,
            vtkStringOutputWindow,
        )

        self._vtkOutputWindow = vtkOutputWindow
        self._vtkLogger = vtkLogger
        self._previous_window = vtkOutputWindow.GetInstance()
        self._previous_verbosity = vtkLogger.GetCurrentVerbosityCutoff()
        self._window = vtkStringOutputWindow()
        vtkOutputWindow.SetInstance(self._window)
        vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
        self.errors: list[str] = []
        return self

    def __exit__(self, *exc) -> None:
        self._vtkOutputWindow.SetInstance(self._previous_window)
        self._vtkLogger.SetStderrVerbosity(self._previous_verbosity)
        text = self._window.GetOutput() or ""
        for block in text.split("ERROR: In ")[1:]:
            self.errors.append(_clean_vtk_message("ERROR: In " + block.split("Warning: In ")[0]))


def _as_path(path: str | os.PathLike) -> Path:
    return Path(os.fspath(path))


def _check_numeric_dtype(name: str, dtype: np.dtype, what: str) -> None:
    if dtype.kind not in _NUMERIC_KINDS or dtype.itemsize > 8 or dtype == np.float16:
        raise TypeError(
            f"{what} {name!r} has dtype {dtype}, which VTK image data cannot hold; "
            "use a signed/unsigned integer of 8-64 bits, float32 or float64"
        )


def _grid_to_vtk_order(name: str, arr: np.ndarray) -> np.ndarray:
    """(nx,ny,nz) or (nx,ny,nz,c) -> (N,) or (N,c), point index i + nx*(j + ny*k)."""
    if arr.ndim == 3:
        return np.ravel(arr, order="F")
    if arr.ndim == 4:
        c = arr.shape[3]
        # (nx,ny,nz,c) -> (nz,ny,nx,c), C-order flattening makes i fastest.
        return np.ascontiguousarray(arr.transpose(2, 1, 0, 3)).reshape(-1, c)
    raise ValueError(
        f"point array {name!r} has shape {arr.shape}; expected (nx, ny, nz) or (nx, ny, nz, c)"
    )


def _vtk_order_to_grid(flat: np.ndarray, dims: tuple[int, int, int]) -> np.ndarray:
    """Inverse of :func:`_grid_to_vtk_order`; always returns a fresh C-ordered copy."""
    nx, ny, nz = dims
    if flat.ndim == 1:
        return np.ascontiguousarray(flat.reshape((nx, ny, nz), order="F"))
    c = flat.shape[1]
    return np.ascontiguousarray(flat.reshape(nz, ny, nx, c).transpose(2, 1, 0, 3))


def _field_value_to_vtk(name: str, value: Any):
    from vtkmodules.vtkCommonCore import (
        vtkDoubleArray,
        vtkStringArray,
        vtkTypeInt64Array,
        vtkTypeUInt64Array,
    )

    if isinstance(value, str):
        arr = vtkStringArray()
        arr.SetName(name)
        arr.SetNumberOfValues(1)
        arr.SetValue(0, value)
        return arr

    if isinstance(value, (bool, np.bool_, numbers.Integral)):
        iv = int(value)
        if isinstance(value, np.uint64) or 2**63 <= iv < 2**64:
            if not 0 <= iv < 2**64:
                raise OverflowError(f"field data {name!r} = {iv} does not fit in uint64")
            kind = vtkTypeUInt64Array
        elif -(2**63) <= iv < 2**63:
            kind = vtkTypeInt64Array
        else:
            raise OverflowError(f"field data {name!r} = {iv} does not fit in int64 or uint64")
        arr = kind()
        arr.SetName(name)
        arr.SetNumberOfValues(1)
        arr.SetValue(0, iv)
        return arr

    if isinstance(value, numbers.Real):
        arr = vtkDoubleArray()
        arr.SetName(name)
        arr.SetNumberOfValues(1)
        arr.SetValue(0, float(value))
        return arr

    if isinstance(value, (np.ndarray, list, tuple)):
        a = np.asarray(value)
        if a.ndim != 1:
            raise ValueError(
                f"field data {name!r} has shape {a.shape}; only scalars, strings and "
                "1-D numeric arrays are supported"
            )
        if a.size == 0 and a.dtype.kind not in _NUMERIC_KINDS + "b":
            a = a.astype(np.float64)  # an empty list: no dtype to keep
        if a.dtype.kind == "f":
            arr = vtkDoubleArray()
            a = a.astype(np.float64, copy=False)
        elif a.dtype == np.uint64:
            arr = vtkTypeUInt64Array()
        elif a.dtype.kind in "iub":
            if a.dtype.kind == "u" and a.size and int(a.max()) >= 2**63:
                raise OverflowError(f"field data {name!r} has values that do not fit in int64")
            arr = vtkTypeInt64Array()
            a = a.astype(np.int64, copy=False)
        else:
            raise TypeError(
                f"field data {name!r} has dtype {a.dtype}; 1-D arrays must be numeric"
            )
        arr.SetName(name)
        arr.SetNumberOfComponents(1)
        arr.SetNumberOfTuples(a.size)
        for idx, v in enumerate(a.tolist()):
            arr.SetValue(idx, v)
        if a.size == 1:
            arr.SetComponentName(0, _ARRAY_MARKER)
        return arr

    raise TypeError(
        f"field data {name!r} has type {type(value).__name__}; supported: float, int, "
        "str and 1-D numeric arrays"
    )


def _field_value_from_vtk(arr) -> Any:
    from vtkmodules.util import numpy_support

    if arr.IsA("vtkStringArray"):
        n = arr.GetNumberOfValues()
        values = [arr.GetValue(i) for i in range(n)]
        return values[0] if n == 1 else values
    if not arr.IsA("vtkDataArray"):
        return None  # e.g. a vtkVariantArray: not something we write
    ntup = arr.GetNumberOfTuples()
    ncomp = arr.GetNumberOfComponents()
    a = np.array(numpy_support.vtk_to_numpy(arr), copy=True)
    marked = ncomp == 1 and arr.GetComponentName(0) == _ARRAY_MARKER
    if ntup == 1 and ncomp == 1 and not marked:
        v = a.reshape(-1)[0]
        return int(v) if a.dtype.kind in "iu" else float(v)
    if ncomp == 1:
        return a.reshape(-1)
    return a.reshape(ntup, ncomp)


def _unlink_quietly(p: Path) -> None:
    try:
        p.unlink()
    except FileNotFoundError:
        pass
    except OSError:
        pass


# --------------------------------------------------------------------------- in memory


def _build_image(flat_arrays: dict, dims, field_data: dict, spacing, origin, deep: bool = True):
    """A vtkImageData of the flat (x fastest) arrays. ``deep`` False shares the arrays' memory
    (no copy of a grid's worth of outputs on the host): only while the caller keeps them alive,
    as :func:`write_vti` does until the file is written."""
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkCommonDataModel import vtkImageData

    img = vtkImageData()
    img.SetDimensions(*dims)
    img.SetSpacing(*spacing)
    img.SetOrigin(*origin)
    pd = img.GetPointData()
    for name, flat in flat_arrays.items():
        varr = numpy_support.numpy_to_vtk(flat, deep=deep or not flat.flags.c_contiguous)
        varr.SetName(name)
        pd.AddArray(varr)
    if len(flat_arrays) == 1:
        pd.SetActiveScalars(next(iter(flat_arrays)))
    fd = img.GetFieldData()
    for name, value in field_data.items():
        fd.AddArray(_field_value_to_vtk(name, value))
    return img


def add_point_arrays(img, point_arrays: dict[str, np.ndarray]) -> None:
    """Add (nx, ny, nz[, c]) grids as point-data arrays of ``img`` (x fastest)."""
    from vtkmodules.util import numpy_support

    pd = img.GetPointData()
    for name, arr in point_arrays.items():
        a = np.asarray(arr)
        _check_numeric_dtype(name, a.dtype, "point array")
        varr = numpy_support.numpy_to_vtk(_grid_to_vtk_order(name, a), deep=True)
        varr.SetName(name)
        pd.AddArray(varr)


def add_field_data(img, field_data: dict[str, object]) -> None:
    """Add scalars, strings and 1-D arrays as field data of ``img`` (replacing same names)."""
    fd = img.GetFieldData()
    for name, value in field_data.items():
        if fd.HasArray(name):
            fd.RemoveArray(name)
        fd.AddArray(_field_value_to_vtk(name, value))


def to_image_data(point_arrays: dict[str, np.ndarray], field_data: dict[str, object] | None,
                  spacing, origin=(0.0, 0.0, 0.0)):
    """A vtkImageData holding ``point_arrays`` (all (nx, ny, nz[, c])) and ``field_data``."""
    flat, dims = {}, None
    for name, arr in point_arrays.items():
        a = np.asarray(arr)
        _check_numeric_dtype(name, a.dtype, "point array")
        if dims is None:
            dims = tuple(int(n) for n in a.shape[:3])
        flat[name] = _grid_to_vtk_order(name, a)
    if dims is None:
        raise ValueError("to_image_data needs at least one point array")
    return _build_image(flat, dims, field_data or {}, spacing, origin)


def point_array(img, name: str) -> np.ndarray:
    """Point-data array ``name`` of a vtkImageData as an (nx, ny, nz[, c]) grid (a copy)."""
    from vtkmodules.util import numpy_support

    dims, _, _ = _geometry(img)
    varr = img.GetPointData().GetArray(name)
    if varr is None:
        available = [img.GetPointData().GetArrayName(i) for i in range(img.GetPointData().GetNumberOfArrays())]
        raise KeyError(f"point array {name!r} not found; available: {available}")
    return _vtk_order_to_grid(numpy_support.vtk_to_numpy(varr), dims)


def cell_array(img, name: str) -> np.ndarray:
    """Cell-data array ``name`` of a vtkImageData as an (nx-1, ny-1, nz-1[, c]) grid (a copy)."""
    from vtkmodules.util import numpy_support

    dims, _, _ = _geometry(img)
    varr = img.GetCellData().GetArray(name)
    if varr is None:
        raise KeyError(f"cell array {name!r} not found")
    return _vtk_order_to_grid(numpy_support.vtk_to_numpy(varr), tuple(max(d - 1, 1) for d in dims))


def field_data_dict(img) -> dict[str, object]:
    """All field data of ``img`` as Python values (see :func:`read_vti`)."""
    out: dict[str, object] = {}
    fd = img.GetFieldData()
    for idx in range(fd.GetNumberOfArrays()):
        arr = fd.GetAbstractArray(idx)
        value = _field_value_from_vtk(arr)
        if value is not None:
            out[arr.GetName()] = value
    return out


def image_geometry(img):
    """(dimensions, spacing, origin of the first point) of a vtkImageData."""
    return _geometry(img)


# --------------------------------------------------------------------------- writing


def write_vti(
    path: str | os.PathLike,
    point_arrays: dict[str, np.ndarray],
    field_data: dict[str, object] | None,
    spacing: tuple[float, float, float],
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    compress: bool = True,
) -> Path:
    """Write point arrays and field data to a VTK XML image file, atomically.

    Parameters
    ----------
    path : path-like
        Target file (normally ending in ``.vti``).
    point_arrays : dict of str to numpy.ndarray
        Arrays of shape ``(nx, ny, nz)`` or ``(nx, ny, nz, c)``, all with the
        same ``(nx, ny, nz)``; integer (8-64 bit) or float32/float64 dtype.
    field_data : dict of str to object, or None
        Metadata: floats, ints, strings and 1-D numeric arrays (see module doc).
    spacing : tuple of 3 floats
        Voxel size along x, y, z (positive).
    origin : tuple of 3 floats
        Position of the centre of voxel ``[0, 0, 0]``.
    compress : bool
        ZLib-compress the appended binary data.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    ValueError, TypeError
        Bad shapes, dtypes or metadata. Nothing is written.
    OSError
        The file could not be written (missing directory, no permission, disk
        full, VTK writer failure). No file and no temporary file is left.

    Notes
    -----
    The data go first to a temporary file unique to this call in the target's
    directory (``.nrt-<random>.tmp.vti``), which is then renamed onto the
    target, so readers never see a half-written file and concurrent writers
    never share one.
    """
    path = _as_path(path)
    field_data = {} if field_data is None else dict(field_data)

    # ---- validate everything before touching the file system
    if not point_arrays:
        raise ValueError("write_vti needs at least one point array")
    spacing = tuple(float(s) for s in spacing)
    origin = tuple(float(o) for o in origin)
    if len(spacing) != 3 or len(origin) != 3:
        raise ValueError("spacing and origin must have 3 components each")
    if not all(math.isfinite(s) and s > 0 for s in spacing):
        raise ValueError(f"spacing must be positive and finite, got {spacing}")
    if not all(math.isfinite(o) for o in origin):
        raise ValueError(f"origin must be finite, got {origin}")

    dims: tuple[int, int, int] | None = None
    flat_arrays: dict[str, np.ndarray] = {}
    for name, arr in point_arrays.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"point array names must be non-empty strings, got {name!r}")
        a = np.asarray(arr)
        _check_numeric_dtype(name, a.dtype, "point array")
        if a.ndim not in (3, 4):
            raise ValueError(
                f"point array {name!r} has shape {a.shape}; expected (nx, ny, nz) or (nx, ny, nz, c)"
            )
        shape3 = tuple(int(n) for n in a.shape[:3])
        if min(shape3) < 1 or (a.ndim == 4 and a.shape[3] < 1):
            raise ValueError(f"point array {name!r} has an empty axis: shape {a.shape}")
        if dims is None:
            dims = shape3  # type: ignore[assignment]
        elif shape3 != dims:
            raise ValueError(
                f"point array {name!r} has grid shape {shape3}, others have {dims}"
            )
        # Native byte order for VTK.
        if not a.dtype.isnative:
            a = a.astype(a.dtype.newbyteorder("="))
        flat_arrays[name] = _grid_to_vtk_order(name, a)
    assert dims is not None

    for name in field_data:
        if not isinstance(name, str) or not name:
            raise ValueError(f"field data names must be non-empty strings, got {name!r}")

    if not path.parent.is_dir():
        raise FileNotFoundError(
            2, f"cannot write {path}: directory {path.parent} does not exist", str(path)
        )

    # ---- build the VTK image
    from vtkmodules.vtkIOXML import vtkXMLImageDataWriter

    # the image shares the arrays' memory: flat_arrays lives until the writer is done
    img = _build_image(flat_arrays, dims, field_data, spacing, origin, deep=False)

    # ---- write to a temporary file unique to this call, then rename
    from .outputs import Publication

    writer = vtkXMLImageDataWriter()
    catcher = _ErrorCatcher()
    catcher.attach(writer)
    writer.SetInputData(img)
    writer.SetDataModeToAppended()
    writer.EncodeAppendedDataOff()  # raw binary, not base64
    writer.SetHeaderTypeToUInt64()  # arrays larger than 4 GiB
    if compress:
        writer.SetCompressorTypeToZLib()
    else:
        writer.SetCompressorTypeToNone()
    with Publication() as pub:
        tmp = pub.stage(path)
        writer.SetFileName(str(tmp))
        with _CapturedVtkMessages() as captured:
            ok = writer.Write()
        errors = catcher.errors + captured.errors
        if ok != 1 or writer.GetErrorCode() != 0 or errors:
            detail = "; ".join(errors) or f"VTK error code {writer.GetErrorCode()}"
            # VTK reports the system error (errno) or its own OutOfDiskSpaceError (20007)
            if writer.GetErrorCode() in (errno.ENOSPC, 20007):
                raise OSError(errno.ENOSPC, f"No space left on device ({detail})", str(path))
            raise OSError(f"could not write {path}: {detail}")
        # Make the data durable before the rename makes them visible.
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        pub.publish()
    return path


# --------------------------------------------------------------------------- reading


def _raise_unreadable(path: Path, reader, errors: list[str]) -> None:
    detail = "; ".join(errors) or f"VTK error code {reader.GetErrorCode()}"
    raise ValueError(f"{path}: unreadable .vti file: {detail}")


def _open_reader(path: Path):
    """A vtkXMLImageDataReader with its information read; raises clean exceptions."""
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    if not path.exists():
        raise FileNotFoundError(2, f"no such file: {path}", str(path))
    if path.is_dir():
        raise IsADirectoryError(21, f"is a directory, not a .vti file: {path}", str(path))
    reader = vtkXMLImageDataReader()
    catcher = _ErrorCatcher()
    catcher.attach(reader)
    with _CapturedVtkMessages() as captured:
        readable = reader.CanReadFile(str(path))
        if readable:
            reader.SetFileName(str(path))
            reader.UpdateInformation()
    if not readable:
        raise ValueError(f"{path}: not a VTK XML image data (.vti) file")
    errors = catcher.errors + captured.errors
    if reader.GetErrorCode() != 0 or errors:
        _raise_unreadable(path, reader, errors)
    return reader, catcher


def _update_reader(path: Path, reader, catcher: _ErrorCatcher):
    with _CapturedVtkMessages() as captured:
        reader.Update()
    img = reader.GetOutput()
    errors = catcher.errors + captured.errors
    if reader.GetErrorCode() != 0 or errors or img is None:
        _raise_unreadable(path, reader, errors)
    return img


def _geometry(img) -> tuple[tuple[int, int, int], tuple[float, float, float], tuple[float, float, float]]:
    dims = tuple(int(d) for d in img.GetDimensions())
    spacing = tuple(float(s) for s in img.GetSpacing())
    origin = list(float(o) for o in img.GetOrigin())
    # An extent that does not start at 0 shifts the first point.
    ext = img.GetExtent()
    for ax in range(3):
        origin[ax] += ext[2 * ax] * spacing[ax]
    return dims, spacing, tuple(origin)  # type: ignore[return-value]


def _array_to_numpy(path: Path, varr, n_expected: int) -> np.ndarray:
    from vtkmodules.util import numpy_support

    a = numpy_support.vtk_to_numpy(varr)
    if a.shape[0] != n_expected:
        raise ValueError(
            f"{path}: array {varr.GetName()!r} has {a.shape[0]} tuples, expected {n_expected}"
        )
    return a


def read_vti(
    path: str | os.PathLike,
) -> tuple[
    dict[str, np.ndarray],
    dict[str, object],
    tuple[float, float, float],
    tuple[float, float, float],
    tuple[int, int, int],
]:
    """Read a ``.vti`` file written by :func:`write_vti` (or any VTK XML image).

    Returns
    -------
    point_arrays : dict of str to numpy.ndarray
        Shapes ``(nx, ny, nz)`` or ``(nx, ny, nz, c)``, dtypes as stored.
    field_data : dict of str to object
        ``float``, ``int``, ``str``, or 1-D ``float64`` / ``int64`` arrays
        (2-D for multi-component arrays from other writers).
    spacing : tuple of 3 floats
    origin : tuple of 3 floats
        Position of the first point (voxel centre ``[0, 0, 0]``).
    dimensions : tuple of 3 ints
        ``(nx, ny, nz)``.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ValueError
        ``path`` is not a readable VTK XML image file.
    """
    path = _as_path(path)
    reader, catcher = _open_reader(path)
    img = _update_reader(path, reader, catcher)
    dims, spacing, origin = _geometry(img)
    npts = dims[0] * dims[1] * dims[2]

    point_arrays: dict[str, np.ndarray] = {}
    pd = img.GetPointData()
    for idx in range(pd.GetNumberOfArrays()):
        varr = pd.GetArray(idx)
        if varr is None:  # not a vtkDataArray
            continue
        flat = _array_to_numpy(path, varr, npts)
        point_arrays[varr.GetName()] = _vtk_order_to_grid(flat, dims)

    return point_arrays, field_data_dict(img), spacing, origin, dims


def read_density_array(path: str | os.PathLike, array_name: str) -> np.ndarray:
    """Read one scalar array of a ``.vti`` file as a ``float64`` grid.

    The array is looked up among the point data first (shape ``(nx, ny, nz)``
    with ``(nx, ny, nz)`` the image dimensions), then among the cell data,
    for images whose cells are the voxels (shape ``dimensions - 1``). Only the
    array asked for is read from the file.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ArrayNotFoundError
        (a ``KeyError`` and ``ValueError``) no point or cell array has that
        name; the message lists the arrays available.
    ValueError
        Unsupported file type, unreadable file, or the array has more than one
        component.
    """
    path = _as_path(path)
    if path.suffix.lower() != ".vti":
        if not path.exists():
            raise FileNotFoundError(2, f"no such file: {path}", str(path))
        raise ValueError(f"{path}: unsupported density file type {path.suffix!r}; expected .vti")

    reader, catcher = _open_reader(path)
    psel = reader.GetPointDataArraySelection()
    csel = reader.GetCellDataArraySelection()
    point_names = [psel.GetArrayName(i) for i in range(psel.GetNumberOfArrays())]
    cell_names = [csel.GetArrayName(i) for i in range(csel.GetNumberOfArrays())]
    if array_name in point_names:
        where = "point"
    elif array_name in cell_names:
        where = "cell"
    else:
        available = [f"{n} (point)" for n in point_names] + [f"{n} (cell)" for n in cell_names]
        raise ArrayNotFoundError(path, array_name, available)

    # Read only the array asked for.
    psel.DisableAllArrays()
    csel.DisableAllArrays()
    (psel if where == "point" else csel).EnableArray(array_name)
    img = _update_reader(path, reader, catcher)
    dims, _spacing, _origin = _geometry(img)

    if where == "point":
        grid = dims
        varr = img.GetPointData().GetArray(array_name)
    else:
        grid = tuple(max(d - 1, 1) for d in dims)
        varr = img.GetCellData().GetArray(array_name)
    if varr is None:
        raise ValueError(f"{path}: array {array_name!r} is not a numeric array")
    if varr.GetNumberOfComponents() != 1:
        raise ValueError(
            f"{path}: array {array_name!r} has {varr.GetNumberOfComponents()} components; "
            "a density must be a scalar array"
        )
    n = grid[0] * grid[1] * grid[2]
    flat = _array_to_numpy(path, varr, n)
    return _vtk_order_to_grid(flat.astype(np.float64), grid)  # type: ignore[arg-type]
