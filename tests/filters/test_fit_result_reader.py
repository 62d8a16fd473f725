"""The fit result as VTK tables (nebula_rt.filters.fit_result): what ``nebula-rt fit --json``
wrote comes back value for value, and files that are no fit result are refused clearly.

The result is a real fit (two free parameters, profile errors) of a small scene to a colour
table, so the reader is held against what the fit itself reports, not against a file written
for the test.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("vtkmodules", reason="the io extra (VTK) is needed for the VTK layer")

from test_fit import cube  # noqa: E402

from nebula_rt.observe import fit  # noqa: E402
from nebula_rt.filters.fit_result import FitResultError, NebulaFitResultReader, as_arrays, read_fit_result  # noqa: E402
from nebula_rt.observe.observed_tables import ObservedTable  # noqa: E402


@pytest.fixture(scope="module")
def fitted(tmp_path_factory, backend):
    col = ObservedTable("colour", "rings.csv", np.array([0.1, 0.2, 0.3]), np.array([-0.3, -0.28, -0.25]),
                        np.full(3, 0.05), np.array([0.05, 0.15, 0.25]), np.array([0.15, 0.25, 0.35]))
    res = fit.fit_observations(cube(photons=5_000), [col], ["g", "albedo"], uncertainty="profile", grid=2,
                               size=16, backend=backend)
    path = tmp_path_factory.mktemp("fit") / "fit.json"
    path.write_text(json.dumps(res.to_dict()))
    return res, path


def _same(a, b):
    """Equal, NaN for NaN (a parameter without an error)."""
    return (math.isnan(a) and math.isnan(b)) or a == b


def test_reader_gives_the_fits_parameters_and_comparison(fitted):
    res, path = fitted
    r = NebulaFitResultReader()
    r.SetFileName(str(path))
    r.Update()
    assert r.last_error is None
    params = as_arrays(r.GetOutputDataObject(0))
    assert params["parameter"] == [p.name for p in res.parameters] == ["g", "albedo"]
    for i, p in enumerate(res.parameters):
        assert _same(params["value"][i], float(res.best[i]))
        assert _same(params["err_minus"][i], float(res.err_minus[i]))
        assert _same(params["err_plus"][i], float(res.err_plus[i]))
        assert (params["lower"][i], params["upper"][i]) == (p.lo, p.hi)
        assert params["at_bound"][i] == int(any(res.at_bound[i]))
    fd = r.GetOutputDataObject(0).GetFieldData()
    assert fd.GetArray("chi2").GetValue(0) == res.chi2
    assert fd.GetArray("dof").GetValue(0) == res.dof
    assert fd.GetAbstractArray("uncertainty").GetValue(0) == "profile"
    comp = as_arrays(r.GetOutputDataObject(1))
    (table,) = res.comparison.results
    assert comp["table"] == ["rings.csv"] * 3 and comp["kind"] == ["colour"] * 3
    np.testing.assert_array_equal(comp["data"], table.table.value)
    np.testing.assert_array_equal(comp["model"], table.model)
    np.testing.assert_array_equal(comp["pull"], table.pull)
    # the chi^2 is the sum of the squared pulls
    assert np.sum(comp["pull"] ** 2) == pytest.approx(res.chi2, rel=1e-12)


def test_reader_refuses_what_is_no_fit_result(tmp_path, fitted):
    cases = {
        "missing.json": None,
        "text.json": "not json at all",
        "list.json": "[1, 2]",
        "scene.json": json.dumps({"grid": {"shape": [8, 8, 8]}}),
        "noparams.json": json.dumps({"parameters": {"g": {"value": 0.5}}, "chi2": 1.0, "dof": 1, "comparison": {}}),
    }
    for name, text in cases.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        with pytest.raises((FileNotFoundError, FitResultError)) as err:
            read_fit_result(path)
        assert str(path) in str(err.value)
        r = NebulaFitResultReader()
        r.SetFileName(str(path))
        r.Update()
        assert r.last_error is not None and str(path) in r.last_error
        assert r.GetOutputDataObject(0).GetNumberOfRows() == 0 == r.GetOutputDataObject(1).GetNumberOfRows()
    r = NebulaFitResultReader()
    r.Update()
    assert "FileName" in r.last_error
    # a good file after a bad one: the error is gone
    r.SetFileName(str(fitted[1]))
    r.Update()
    assert r.last_error is None and r.GetOutputDataObject(0).GetNumberOfRows() == 2


def _fit_view():
    """plugin/nebula_rt_paraview/fit_view.py, the Python View's script, loaded as a file: its
    package imports ParaView, which this process has not (the module itself does not)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "plugin" / "nebula_rt_paraview" / "fit_view.py"
    spec = importlib.util.spec_from_file_location("fit_view", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_fit_view_shows_the_parameters_first_and_a_chart_per_kind():
    """What a Python View shows of a fit result (nebula_rt_paraview.fit_view, drawn here into a
    matplotlib figure from the reader's two tables of the worked example's fit,
    examples/observations/fit-result.json): a table whose columns are parameter, value,
    -1 sigma, +1 sigma, bounds, one row per free parameter with the file's numbers; then one
    chart per observable kind, colour against projected offset and ratio against wavelength
    (never one axis for both), each observed point with the file's 1-sigma error as its bar,
    and a ratio table's annuli as series of their own (not joined across annuli)."""
    from pathlib import Path

    from matplotlib.container import ErrorbarContainer
    from matplotlib.figure import Figure

    path = Path(__file__).resolve().parents[2] / "examples" / "observations" / "fit-result.json"
    saved = json.loads(path.read_text())
    r = NebulaFitResultReader()
    r.SetFileName(str(path))
    r.Update()
    assert r.last_error is None
    fig = Figure(figsize=(9, 9))
    _fit_view().draw(fig, r.GetOutputDataObject(0), r.GetOutputDataObject(1))
    table_ax, colour_ax, ratio_ax = fig.axes
    cells = table_ax.tables[0].get_celld()
    assert [cells[(0, j)].get_text().get_text() for j in range(5)] == ["parameter", "value", "-1 sigma", "+1 sigma",
                                                                       "bounds"]
    for i, (name, p) in enumerate(saved["parameters"].items(), start=1):
        row = [cells[(i, j)].get_text().get_text() for j in range(4)]
        assert row[0] == name
        assert float(row[1]) == pytest.approx(p["value"], rel=1e-3)
        assert -float(row[2]) == pytest.approx(p["err_minus"], rel=1e-2)  # written "-0.038"
        assert float(row[3]) == pytest.approx(p["err_plus"], rel=1e-2)
    assert "chi^2 = 8.309 for 14" in table_ax.get_title()
    assert colour_ax.get_xlabel() == "projected offset (box units)"
    assert ratio_ax.get_xlabel() == "wavelength (nm)"
    for ax, kind, series in ((colour_ax, "colour", 1), (ratio_ax, "ratio", 3)):
        (table,) = [t for t in saved["comparison"]["tables"] if t["kind"] == kind]
        bars = [c for c in ax.containers if isinstance(c, ErrorbarContainer)]
        assert len(bars) == series
        drawn = []
        for bar in bars:
            points, _caps, (lines,) = bar.lines
            for x, y, seg in zip(points.get_xdata(), points.get_ydata(), lines.get_segments()):
                drawn.append((x, y, seg[1][1] - y))  # the bar's upper end above the point
        want = sorted(zip(table["x"], table["data"], table["data_err"]))
        np.testing.assert_allclose(sorted(drawn), want, rtol=1e-12)
