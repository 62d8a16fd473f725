"""A fit's result in ParaView (pvpython/pvbatch): the parameters with their errors and the
best fit against the observed tables, one chart per observable kind.

    nebula-rt fit examples/scenes/thesis-default.toml --table rings.ecsv --free albedo --free g \
        --json out/fit.json
    source scripts/pv-env.sh
    pvpython plugin/examples/fit_result.py out/fit.json [--png out/fit-chart.png]

``OpenDataFile`` picks the plugin's reader ("NebulaRT fit result") for the ``--json`` file of
``nebula-rt fit``: output port 0 holds one row per free parameter (value, err_minus, err_plus,
bounds; chi^2 in the field data), port 1 one row per observed point (data, data_err, model,
model_err, residual, pull over x). Prints the parameters as ``name = value -err +err`` and the
chi^2; with --png, saves the fit's picture: a Python View (matplotlib) with the parameters'
table first, then colour against offset and ratio against wavelength, observed points with
their error bars and the model with its Monte Carlo band (nebula_rt_paraview.fit_view; the
state file state_files/fit_result.pvsm opens a fit result into the same layout).
"""

import argparse
import json
import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))  # plugin/

from paraview import servermanager, simple  # noqa: E402
from nebula_rt_paraview.view import load_plugin, show_fit_result  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("fit_json", help="the file of nebula-rt fit --json")
ap.add_argument("--png", default=None, help="save the parameters and the charts of the fit")
ap.add_argument("--result", action="store_true", help=argparse.SUPPRESS)  # one RESULT line (tests)
args = ap.parse_args()

load_plugin()
reader = simple.OpenDataFile(args.fit_json)  # the plugin's NebulaFitResultReader
reader.UpdatePipeline()
last_error = reader.GetClientSideObject().last_error
params = servermanager.Fetch(reader, idx=0)
comparison = servermanager.Fetch(reader, idx=1)


def columns(table):
    """A vtkTable's columns as lists (NaN where the fit gave no value)."""
    out = {}
    for i in range(table.GetNumberOfColumns()):
        col = table.GetColumn(i)
        n = col.GetNumberOfTuples()
        out[col.GetName()] = [col.GetValue(j) if col.IsA("vtkStringArray") else col.GetTuple1(j) for j in range(n)]
    return out


if last_error:  # not a fit result: the reader said why (also on ParaView's output window)
    if args.result:
        print("RESULT " + json.dumps({"proxy": reader.GetXMLName(), "last_error": last_error,
                                      "rows": params.GetNumberOfRows() + comparison.GetNumberOfRows()}))
        sys.exit(0)
    sys.exit(last_error)
p, c = columns(params), columns(comparison)
fd = params.GetFieldData()
chi2, dof = fd.GetArray("chi2").GetValue(0), fd.GetArray("dof").GetValue(0)
if not args.result:
    for i, name in enumerate(p["parameter"]):
        print(f"{name} = {p['value'][i]:.5g}  -{p['err_minus'][i]:.3g} +{p['err_plus'][i]:.3g}"
              + ("  (interval reaches a bound)" if p["at_bound"][i] else ""))
    print(f"chi2 = {chi2:.3f} for {dof:.0f} degrees of freedom; {len(c.get('x', []))} observed points")

if args.png:
    # the parameters first, then one chart per observable kind (colour against offset, ratio
    # against wavelength) with error bars: a Python View drawn by nebula_rt_paraview.fit_view
    view = show_fit_result(reader)
    simple.SaveScreenshot(args.png, view, ImageResolution=[900, 900])

if args.result:
    def clean(v):
        return None if isinstance(v, float) and math.isnan(v) else v

    print("RESULT " + json.dumps({
        "proxy": reader.GetXMLName(), "last_error": last_error, "ports": reader.GetNumberOfOutputPorts(),
        "parameters": {k: [clean(v) for v in vals] for k, vals in p.items()},
        "comparison": {k: [clean(v) for v in vals] for k, vals in c.items()},
        "chi2": chi2, "dof": dof, "uncertainty": fd.GetAbstractArray("uncertainty").GetValue(0),
        "png": bool(args.png and os.path.exists(args.png))}))
