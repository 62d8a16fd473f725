"""Reading a density array from a ``.vti`` file with VTK's own XML reader.

The reader of ``dust.model = "file"`` with a ``.vti`` (:func:`nebula_rt.density.load_density_file`
imports it when it meets one), in every Python that has VTK: the command line's (VTK and pyvista,
the ``io`` extra) and ParaView's, which has its own VTK but no pyvista (and must not get one, see
docs/paraview.md). Only ``vtkXMLImageDataReader`` with its array selection is used, so only the
array asked for is read; the grid comes out through :mod:`nebula_rt.filters.image_data` (shape
``(nx, ny, nz)`` indexed [x, y, z]).

The reader's own errors are observed (VTK then does not print them) and go into the exception
raised. With pyvista present, the messages of the XML parser and of any other helper are caught
as well (:class:`nebula_rt.filters.vtk_messages.VtkMessages`); in ParaView they go where ParaView puts
VTK's messages (Output Messages), and the exception still says what failed.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from nebula_rt.backends.capacity import host_available_bytes
from nebula_rt.errors import NebulaError
from nebula_rt.input_files import check_input_file

from .image_data import cell_array, point_array

__all__ = ["ArrayNotFoundError", "declared_density", "read_density_array"]


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
        self.message = f"{self.path}: no array named {array_name!r}; available arrays: {listed}"
        super().__init__(self.message)

    def __str__(self) -> str:  # KeyError would quote the message
        return self.message


def one_line(errors) -> str:
    """VTK's error messages as one line: each message's whitespace (VTK's multi-line dumps
    of a pipeline request) collapsed, repeats and bare numbers left out, and the executive's
    "returned failure for request" left out where a message says what failed."""
    texts = [" ".join(str(e).split()) for e in errors]
    texts = [t for t in texts if t and not t.isdigit()]
    said = [t for t in texts if "returned failure for request" not in t]
    return "; ".join(dict.fromkeys(said or texts))


def _messages():
    """pyvista's catcher of every VTK message where pyvista is installed, else nothing more
    than the reader's own observer."""
    try:
        from .vtk_messages import VtkMessages
    except ImportError:  # ParaView's Python: no pyvista
        return contextlib.nullcontext(None)
    return VtkMessages()


class _Reader:
    """``vtkXMLImageDataReader`` of one file, its errors observed."""

    def __init__(self, path: Path):
        from vtkmodules.vtkCommonCore import vtkCommand
        from vtkmodules.vtkIOXML import vtkXMLImageDataReader

        self.path = path
        self.errors: list[str] = []
        self.reader = vtkXMLImageDataReader()
        self.reader.AddObserver(vtkCommand.ErrorEvent, self._on_error)
        self.reader.SetFileName(str(path))

    def _on_error(self, _obj, _event, text=None):
        self.errors.append(" ".join(str(text or "VTK error").split()))

    _on_error.CallDataType = 8  # VTK_STRING: the message comes with the event

    def run(self, step) -> None:
        """``step`` (UpdateInformation or Update); ValueError naming the file if it failed."""
        with _messages() as caught:
            step()
        errors = self.errors + (caught.errors if caught is not None else [])
        if self.reader.GetErrorCode() != 0 or errors:
            detail = one_line(errors) or f"VTK error code {self.reader.GetErrorCode()}"
            raise ValueError(f"{self.path}: unreadable .vti file: {detail}")


def declared_points(reader) -> tuple:
    """Points per axis of the image an XML image reader's file declares (its header, read by
    UpdateInformation, before any data)."""
    ext = reader.GetOutputInformation(0).Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT())
    if ext is None:
        return (0, 0, 0)
    return tuple(int(ext[2 * i + 1]) - int(ext[2 * i]) + 1 for i in range(3))


def _check_declared_size(path: Path, where: str, shape: tuple, expected_shape, available_bytes) -> None:
    """Refuse, from the header alone, an image of another shape than the grid's or one whose
    array (read as float64) would not fit the memory there is: a 400-byte file claiming a huge
    extent would otherwise make VTK's reader allocate it (and abort the process)."""
    if expected_shape is not None and tuple(shape) != tuple(expected_shape):
        raise ValueError(f"{path}: the {where} array's shape {tuple(shape)} (from the file's extent) must equal "
                         f"grid.shape {tuple(expected_shape)}")
    values = 1
    for n in shape:
        values *= max(int(n), 0)
    if available_bytes is not None and values * 8 > available_bytes:
        raise ValueError(f"{path}: the file declares {values} values per array ({tuple(shape)}), "
                         f"{values * 8} bytes as float64, more than the {available_bytes} bytes of memory available")


def _open_header(path, array_name: str, expected_shape):
    """The reader of ``path`` with its header read and checked (the array is there, its
    declared shape is ``expected_shape`` or fits memory); returns (reader, where, points,
    arrays): "point" or "cell", the points per axis the extent declares, and how many
    arrays the file declares."""
    path = Path(os.fspath(path))
    if not path.exists():
        raise FileNotFoundError(2, f"no such file: {path}", str(path))
    if path.suffix.lower() != ".vti":
        raise ValueError(f"{path}: unsupported density file type {path.suffix!r}; expected .vti")
    if path.is_dir():
        raise IsADirectoryError(21, f"is a directory, not a .vti file: {path}", str(path))
    check_input_file("file", path, "a .vti file")  # a FIFO would block VTK's reader for ever
    r = _Reader(path)
    r.run(r.reader.UpdateInformation)
    psel, csel = r.reader.GetPointDataArraySelection(), r.reader.GetCellDataArraySelection()
    point_names = [psel.GetArrayName(i) for i in range(psel.GetNumberOfArrays())]
    cell_names = [csel.GetArrayName(i) for i in range(csel.GetNumberOfArrays())]
    if array_name in point_names:
        where = "point"
    elif array_name in cell_names:
        where = "cell"
    else:
        available = [f"{n} (point)" for n in point_names] + [f"{n} (cell)" for n in cell_names]
        raise ArrayNotFoundError(path, array_name, available)
    points = declared_points(r.reader)
    declared = points if where == "point" else tuple(max(n - 1, 1) for n in points)
    _check_declared_size(path, where, declared, expected_shape, host_available_bytes())
    return r, where, points, len(point_names) + len(cell_names)


def declared_density(path, array_name: str, expected_shape=None) -> tuple:
    """From the header of a ``.vti`` alone (no data read): the points per axis its extent
    declares and the number of arrays it declares, after the checks of
    :func:`read_density_array` that need no data (the array is there, of ``expected_shape``)."""
    _r, _where, points, arrays = _open_header(path, array_name, expected_shape)
    return points, arrays


def read_density_array(path, array_name: str, expected_shape=None) -> np.ndarray:
    """Read one scalar array of a ``.vti`` file as a ``float64`` grid.

    The array is looked up among the point data first (shape ``(nx, ny, nz)``, the image's
    dimensions), then among the cell data, for images whose cells are the voxels (shape
    ``dimensions - 1``). Only that array is read from the file.

    ``expected_shape`` (nx, ny, nz), if given, is checked against the extent the file
    declares before any data is read; without it the declared size must fit the host's
    available memory.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    IsADirectoryError
        ``path`` is a folder.
    nebula_rt.filters.vti.ArrayNotFoundError
        (a ``KeyError`` and ``ValueError``) no point or cell array has that name; the message
        lists the arrays there are.
    ValueError
        Unsupported file type, unreadable file, or the array has more than one component;
        a FIFO, a device or a socket (:class:`nebula_rt.errors.SceneError`, a ValueError:
        VTK's reader would wait on a FIFO for ever).
    """
    path = Path(os.fspath(path))
    r, where, _points, _arrays = _open_header(path, array_name, expected_shape)
    psel, csel = r.reader.GetPointDataArraySelection(), r.reader.GetCellDataArraySelection()
    psel.DisableAllArrays()
    csel.DisableAllArrays()
    (psel if where == "point" else csel).EnableArray(array_name)
    r.run(r.reader.Update)
    img = r.reader.GetOutput()
    try:
        grid = point_array(img, array_name) if where == "point" else cell_array(img, array_name)
    except KeyError:
        raise ValueError(f"{path}: array {array_name!r} is not a numeric array") from None
    if grid.ndim != 3:
        raise ValueError(f"{path}: array {array_name!r} has {grid.shape[3]} components; "
                         "a density must be a scalar array")
    return grid.astype(np.float64)
