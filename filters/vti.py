"""Reading and writing VTK XML image data (``.vti``) files.

Needs the ``io`` extra (VTK and pyvista). The arrays go through
:mod:`nebula_rt.filters.image_data` (layout: ``(nx, ny, nz[, c])`` grids indexed [x, y, z], the
image's points at the voxel centres; field-data types: see there), so a file holds what the
VTK algorithms' outputs hold.

- Writing (:func:`write_vti`): ``vtkXMLImageDataWriter``, appended raw binary, ZLib, 64-bit
  headers (arrays above 4 GiB), into a temporary file of its own in the target's folder that
  is renamed onto the target once complete (:class:`nebula_rt.pipeline.outputs.Publication`): readers
  never see a half-written file and concurrent writers never share one.
- Reading (:func:`read_vti`): pyvista's XML image reader; :func:`read_density_array` (one
  array, with the reader's array selection) is :mod:`nebula_rt.filters.density_file`'s, which
  needs VTK only (ParaView's Python has no pyvista).

VTK's messages of a read or write (the reader's, the writer's and those of their helpers, such
as the XML parser) are caught by pyvista's ``VtkErrorCatcher`` with VTK's logger silenced, and
go into the exception raised instead of stderr. Both are process-global, so one read or write
runs at a time.
"""

from __future__ import annotations

import errno
import math
import os
from pathlib import Path

import numpy as np
import pyvista as pv
from vtkmodules.vtkIOXML import vtkXMLImageDataWriter

from nebula_rt.pipeline.outputs import Publication

from nebula_rt.backends.capacity import host_available_bytes
from nebula_rt.input_files import check_input_file

from .density_file import ArrayNotFoundError, declared_points, one_line, read_density_array  # noqa: F401 - this module's API too
from .image_data import check_numeric_dtype, field_data_dict, image_geometry, point_array, to_image_data
from .vtk_messages import VtkMessages

__all__ = ["ArrayNotFoundError", "read_density_array", "read_vti", "write_vti"]


# --------------------------------------------------------------------------- writing


def write_vti(path, point_arrays: dict, field_data: dict | None, spacing, origin=(0.0, 0.0, 0.0),
              compress: bool = True) -> Path:
    """Write point arrays and field data to a VTK XML image file, atomically.

    Parameters
    ----------
    path : path-like
        Target file (normally ending in ``.vti``).
    point_arrays : dict of str to numpy.ndarray
        Arrays of shape ``(nx, ny, nz)`` or ``(nx, ny, nz, c)``, all with the same
        ``(nx, ny, nz)``; integer (8-64 bit) or float32/float64 dtype.
    field_data : dict of str to object, or None
        Floats, ints, strings and 1-D numeric arrays (:mod:`nebula_rt.filters.image_data`).
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
        The file could not be written (missing folder, no permission, disk full, VTK writer
        failure; ``errno.ENOSPC`` for a full disk). No file and no temporary file is left, an
        old file at ``path`` is unchanged.
    """
    path = Path(os.fspath(path))
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
    dims = None
    for name, arr in point_arrays.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"point array names must be non-empty strings, got {name!r}")
        a = np.asarray(arr)
        check_numeric_dtype(name, a.dtype)
        if a.ndim not in (3, 4):
            raise ValueError(f"point array {name!r} has shape {a.shape}; expected (nx, ny, nz) or (nx, ny, nz, c)")
        if min(a.shape) < 1:
            raise ValueError(f"point array {name!r} has an empty axis: shape {a.shape}")
        if dims is not None and tuple(a.shape[:3]) != dims:
            raise ValueError(f"point array {name!r} has grid shape {tuple(a.shape[:3])}, others have {dims}")
        dims = tuple(a.shape[:3])
    img = to_image_data(point_arrays, field_data, spacing, origin)  # checks the field data too
    if not path.parent.is_dir():
        raise FileNotFoundError(2, f"cannot write {path}: directory {path.parent} does not exist", str(path))

    writer = vtkXMLImageDataWriter()
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
        with VtkMessages() as messages:
            ok = writer.Write()
        code = writer.GetErrorCode()
        if ok != 1 or code != 0 or messages.errors:
            detail = "; ".join(messages.errors) or f"VTK error code {code}"
            # VTK reports the system error (errno) or its own OutOfDiskSpaceError (20007)
            if code in (errno.ENOSPC, 20007):
                raise OSError(errno.ENOSPC, f"No space left on device ({detail})", str(path))
            raise OSError(f"could not write {path}: {detail}")
        with open(tmp, "rb") as fh:  # durable before the rename makes it visible
            os.fsync(fh.fileno())
        pub.publish()
    return path


# --------------------------------------------------------------------------- reading


def _open(path: Path):
    """pyvista's reader of ``path`` with the file's information read (array names, extent)."""
    if not path.exists():
        raise FileNotFoundError(2, f"no such file: {path}", str(path))
    if path.is_dir():
        raise IsADirectoryError(21, f"is a directory, not a .vti file: {path}", str(path))
    check_input_file("file", path, "a .vti file")  # (a FIFO or a device: refused before VTK reads)
    with VtkMessages() as messages:
        reader = pv.XMLImageDataReader(str(path))
    if reader.reader.GetErrorCode() != 0 or messages.errors:
        _unreadable(path, reader, messages.errors)
    # the extent the header declares, before the data is read: a crafted 400-byte file
    # claiming 10^15 points would make VTK allocate them (and abort the process)
    points = math.prod(max(n, 0) for n in declared_points(reader.reader))
    arrays = max(1, reader.reader.GetNumberOfPointArrays() + reader.reader.GetNumberOfCellArrays())
    available = host_available_bytes()
    if points * 8 * arrays > available:
        raise ValueError(f"{path}: the file declares {points} points with {arrays} arrays, about "
                         f"{points * 8 * arrays} bytes, more than the {available} bytes of memory available")
    return reader


def _unreadable(path: Path, reader, errors) -> None:
    detail = one_line(errors) or f"VTK error code {reader.reader.GetErrorCode()}"
    raise ValueError(f"{path}: unreadable .vti file: {detail}")


def _read(path: Path, reader):
    with VtkMessages() as messages:
        img = reader.read()
    if reader.reader.GetErrorCode() != 0 or messages.errors or img is None:
        _unreadable(path, reader, messages.errors)
    return img


def read_vti(path):
    """Read a ``.vti`` file written by :func:`write_vti` (or any VTK XML image).

    Returns
    -------
    point_arrays : dict of str to numpy.ndarray
        Shapes ``(nx, ny, nz)`` or ``(nx, ny, nz, c)``, dtypes as stored.
    field_data : dict of str to object
        ``float``, ``int``, ``str``, or 1-D ``float64`` / ``int64`` / ``uint64`` arrays (2-D for
        multi-component arrays of other writers).
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
    path = Path(os.fspath(path))
    img = _read(path, _open(path))
    dims, spacing, origin = image_geometry(img)
    pd = img.GetPointData()
    names = [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays()) if pd.GetArray(i) is not None]
    return {n: point_array(img, n) for n in names}, field_data_dict(img), spacing, origin, dims
