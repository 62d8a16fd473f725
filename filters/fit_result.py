"""Reading the result of ``nebula-rt fit --json`` as VTK tables.

``nebula-rt fit SCENE --table ... --free ... --json fit.json`` (and ``FitResult.to_dict`` of
:mod:`nebula_rt.observe.fit`) writes the best-fit parameters with their 1-sigma errors, chi^2 and the
best fit held against every observed table. :class:`NebulaFitResultReader` is a plain VTK
algorithm (no inputs, two ``vtkTable`` outputs) that makes them reachable where VTK is: in
ParaView (File > Open, "NebulaRT fit result"; the plugin's thin wrapper), pvpython and
pyvista.

Output 0, the parameters: one row per free parameter, columns ``parameter`` (its name as
``--free`` gave it), ``value``, ``err_minus``, ``err_plus`` (1 sigma below and above; NaN
without uncertainties), ``lower``, ``upper`` (the fit's bounds), ``log`` (1 where fitted in
log), ``at_bound`` (1 where the interval reaches a bound); field data ``chi2``, ``dof``,
``reduced_chi2``, ``traces_total`` and ``uncertainty`` (profile, mcmc or none).

Output 1, the best fit against the tables: one row per observed point of every table, columns
``table`` (its file), ``kind`` (colour or ratio), ``x`` (projected offset in box units, or
wavelength in nm), ``offset_lo``, ``offset_hi``, ``data``, ``data_err``, ``model``,
``model_err``, ``residual`` and ``pull`` ((data - model) / combined error) -- a line chart of
``data`` and ``model`` over ``x`` is the fit's picture.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import vtkDoubleArray, vtkIntArray, vtkStringArray
from vtkmodules.vtkCommonDataModel import vtkTable

from nebula_rt.errors import SceneError
from nebula_rt.input_files import MAX_JSON_BYTES, read_input_text

__all__ = ["FitResultError", "read_fit_result", "parameters_table", "comparison_table", "NebulaFitResultReader"]

#: numeric columns of the comparison table, as ``Comparison.to_dict`` names them
COMPARISON_COLUMNS = ("x", "offset_lo", "offset_hi", "data", "data_err", "model", "model_err", "residual", "pull")


class FitResultError(ValueError):
    """A file that is not a NebulaRT fit result; the message names the file and what is wrong."""


def _number(v) -> float:
    """JSON's null (a value the fit could not give) as NaN."""
    return math.nan if v is None else float(v)


def read_fit_result(path) -> dict:
    """The fit result in ``path`` (JSON as ``nebula-rt fit --json`` writes it), checked.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    FitResultError
        Not JSON, or without the parameters, chi^2 or comparison of a fit result.
    """
    path = Path(os.fspath(path))
    if not path.exists():
        raise FileNotFoundError(2, f"no such file: {path}", str(path))
    try:
        text = read_input_text("file", path, "a fit result (JSON, UTF-8)", MAX_JSON_BYTES)
    except SceneError as exc:  # a FIFO, a device, too large, not UTF-8: this reader's error type
        raise FitResultError(f"{path}: {exc.allowed}") from None
    try:
        result = json.loads(text)
    except json.JSONDecodeError as exc:
        raise FitResultError(f"{path}: not a NebulaRT fit result (not JSON: {exc})") from None
    if not isinstance(result, dict):
        raise FitResultError(f"{path}: not a NebulaRT fit result (a JSON {type(result).__name__}, not an object)")
    missing = [k for k in ("parameters", "chi2", "dof", "comparison") if k not in result]
    if missing or not isinstance(result["parameters"], dict):
        raise FitResultError(f"{path}: not a NebulaRT fit result (no {', '.join(missing) or 'parameters object'}; "
                             "write one with `nebula-rt fit ... --json FILE`)")
    for name, p in result["parameters"].items():
        if not isinstance(p, dict) or "value" not in p or len(p.get("bounds", ())) != 2:
            raise FitResultError(f"{path}: parameter {name!r} has no value and bounds")
    return result


def _column(table: vtkTable, name: str, values, kind=vtkDoubleArray) -> None:
    arr = kind()
    arr.SetName(name)
    for v in values:
        arr.InsertNextValue(v)
    table.AddColumn(arr)


def _field(table: vtkTable, name: str, value) -> None:
    if isinstance(value, str):
        arr = vtkStringArray()
        arr.InsertNextValue(value)
    else:
        arr = vtkDoubleArray()
        arr.InsertNextValue(_number(value))
    arr.SetName(name)
    table.GetFieldData().AddArray(arr)


def parameters_table(result: dict, out: vtkTable | None = None) -> vtkTable:
    """Output 0 of the reader (see the module notes) from a fit result."""
    t = out if out is not None else vtkTable()
    params = result["parameters"]
    names = list(params)
    _column(t, "parameter", names, vtkStringArray)
    for col, key in (("value", "value"), ("err_minus", "err_minus"), ("err_plus", "err_plus")):
        _column(t, col, [_number(params[n].get(key)) for n in names])
    _column(t, "lower", [_number(params[n]["bounds"][0]) for n in names])
    _column(t, "upper", [_number(params[n]["bounds"][1]) for n in names])
    _column(t, "log", [int(bool(params[n].get("log"))) for n in names], vtkIntArray)
    _column(t, "at_bound", [int(any(params[n].get("at_bound") or ())) for n in names], vtkIntArray)
    for key in ("chi2", "dof", "reduced_chi2", "traces_total"):
        _field(t, key, result.get(key))
    _field(t, "uncertainty", str(result.get("uncertainty", "")))
    return t


def comparison_table(result: dict, out: vtkTable | None = None) -> vtkTable:
    """Output 1 of the reader (see the module notes) from a fit result."""
    t = out if out is not None else vtkTable()
    tables = result["comparison"].get("tables", []) if isinstance(result["comparison"], dict) else []
    rows = [(tab, i) for tab in tables for i in range(len(tab.get("x", ())))]
    _column(t, "table", [str(tab.get("table") or "") for tab, _ in rows], vtkStringArray)
    _column(t, "kind", [str(tab.get("kind") or "") for tab, _ in rows], vtkStringArray)
    for col in COMPARISON_COLUMNS:
        _column(t, col, [_number((tab.get(col) or [None] * (i + 1))[i]) for tab, i in rows])
    _field(t, "chi2", result["comparison"].get("chi2") if isinstance(result["comparison"], dict) else None)
    return t


class NebulaFitResultReader(VTKPythonAlgorithmBase):
    """The parameters (output 0) and the best fit against the tables (output 1) of a
    ``nebula-rt fit --json`` file, as ``vtkTable``s (see :mod:`nebula_rt.filters.fit_result`)."""

    def __init__(self):
        super().__init__(nInputPorts=0, nOutputPorts=2, outputType="vtkTable")
        self._file_name = ""
        #: the message of the last failed execution (None after a success); the outputs are
        #: then empty and the message is on VTK's output window, as the NebulaRT filters report
        self.last_error: str | None = None

    def SetFileName(self, name):
        name = "" if name is None else str(name)
        if name != self._file_name:
            self._file_name = name
            self.Modified()

    def GetFileName(self):
        return self._file_name

    def RequestData(self, request, in_info, out_info):
        self.last_error = None
        try:
            if not self._file_name:
                raise FitResultError("FileName is not set (a `nebula-rt fit --json` file)")
            result = read_fit_result(self._file_name)
            parameters_table(result, vtkTable.GetData(out_info, 0))
            comparison_table(result, vtkTable.GetData(out_info, 1))
        except Exception as exc:  # noqa: BLE001 - reported, as the NebulaRT filters report
            from vtkmodules.vtkCommonCore import vtkOutputWindow

            for port in range(2):
                vtkTable.GetData(out_info, port).Initialize()  # nothing half-made
            self.last_error = f"{type(self).__name__}: {exc}"
            vtkOutputWindow.GetInstance().DisplayErrorText(f"NebulaRT error: {self.last_error}\n")
        return 1


def as_arrays(table: vtkTable) -> dict:
    """The columns of a table as NumPy arrays (strings as lists), for scripts and tests."""
    out = {}
    for i in range(table.GetNumberOfColumns()):
        col = table.GetColumn(i)
        n = col.GetNumberOfTuples()
        if isinstance(col, vtkStringArray):
            out[col.GetName()] = [col.GetValue(j) for j in range(n)]
        else:
            out[col.GetName()] = np.array([col.GetTuple1(j) for j in range(n)])
    return out
