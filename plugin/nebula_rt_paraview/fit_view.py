"""A fit result drawn for reading: the parameters first, then one chart per observable kind.

ParaView's own views do not serve a fit result well: its spreadsheet orders a table's columns
by name (so ``value`` comes after ``at_bound``, ``err_minus``, ``lower``, ``parameter``), and
its line chart has no error bars and draws every row on one x axis, joined by lines (colours
against offset in box units and ratios against wavelength in nm together). This module is the
script of a ParaView *Python View* (matplotlib, rendered on the client) for the two ports of
``NebulaFitResultReader``:

- a table of the free parameters: name, best value, -1 sigma, +1 sigma, the bounds, and a mark
  where an interval reaches a bound; chi^2, degrees of freedom and how the errors were made;
- one chart per observable kind present: *colour against projected offset* (box units) and
  *ratio against wavelength* (nm); the observed points with their 1-sigma error bars, the model
  at the best fit as a line with its own Monte Carlo error as a band, one colour per table.

Use: :func:`nebula_rt_paraview.view.show_fit_result` (pvpython), or in the GUI a Python View
whose Script is :data:`SCRIPT`, showing the reader's Parameters and Comparison ports; the
example state ``state_files/fit_result.pvsm`` opens a fit result into that layout.
"""

from __future__ import annotations

import math

#: the Python View's script: the two functions a Python View calls, from this module
SCRIPT = "from nebula_rt_paraview.fit_view import setup_data, render  # NebulaRT fit result\n"

#: (kind, x axis title, y axis title) of the charts, in their order
KINDS = (("colour", "projected offset (box units)", "colour (mag)"),
         ("ratio", "wavelength (nm)", "surface brightness ratio"))


def setup_data(view):
    """Ask for every column of every shown table (a Python View moves none by default)."""
    view.EnableAllAttributeArrays()


def _columns(table) -> dict:
    out = {}
    for i in range(table.GetNumberOfColumns()):
        col = table.GetColumn(i)
        n = col.GetNumberOfTuples()
        if col.IsA("vtkStringArray"):
            out[col.GetName()] = [col.GetValue(j) for j in range(n)]
        else:
            out[col.GetName()] = [col.GetTuple1(j) for j in range(n)]
    return out


def _field(table, name):
    arr = table.GetFieldData().GetAbstractArray(name)
    if arr is None or arr.GetNumberOfValues() == 0:
        return None
    return arr.GetValue(0) if arr.IsA("vtkStringArray") else arr.GetTuple1(0)


def _tables(view):
    """(parameters, comparison) shown in ``view``, told apart by their columns (None: absent)."""
    params = comparison = None
    for i in range(view.GetNumberOfVisibleDataObjects()):
        t = view.GetVisibleDataObjectForRendering(i)
        if t is None or not t.IsA("vtkTable"):
            continue
        names = {t.GetColumnName(c) for c in range(t.GetNumberOfColumns())}
        if "parameter" in names:
            params = t
        elif "kind" in names:
            comparison = t
    return params, comparison


def _number(v, digits=4) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}g}"


def draw(figure, params, comparison) -> None:
    """Draw the parameters' table and the charts of a fit result into a matplotlib ``figure``
    (the two reader outputs as vtkTables; either may be None)."""
    p = _columns(params) if params is not None else {}
    c = _columns(comparison) if comparison is not None else {}
    kinds = [k for k in KINDS if k[0] in set(c.get("kind", []))]
    n_rows = len(p.get("parameter", []))
    heights = [0.6 + 0.3 * n_rows] + [3.0] * len(kinds)
    grid = figure.add_gridspec(len(heights), 1, height_ratios=heights, hspace=0.45, top=0.95, bottom=0.06)
    ax = figure.add_subplot(grid[0])
    ax.axis("off")
    if n_rows:
        cells = []
        for i, name in enumerate(p["parameter"]):
            bound = " (at a bound)" if p.get("at_bound", [0] * n_rows)[i] else ""
            cells.append([name, _number(p["value"][i]), "-" + _number(p["err_minus"][i], 3),
                          "+" + _number(p["err_plus"][i], 3),
                          f"[{_number(p['lower'][i])}, {_number(p['upper'][i])}]" + bound])
        table = ax.table(cellText=cells, colLabels=["parameter", "value", "-1 sigma", "+1 sigma", "bounds"],
                         loc="center", cellLoc="left")
        table.auto_set_font_size(False)
        table.set_fontsize(10)
        table.scale(1.0, 1.3)
        chi2, dof = _field(params, "chi2"), _field(params, "dof")
        how = _field(params, "uncertainty") or "none"
        ax.set_title(f"best fit: chi^2 = {_number(chi2)} for {_number(dof)} degrees of freedom "
                     f"(errors: {how})", fontsize=11)
    else:
        ax.set_title("no fit result shown: show the reader's Parameters port here", fontsize=11)
    for row, (kind, xtitle, ytitle) in enumerate(kinds, start=1):
        ax = figure.add_subplot(grid[row])
        rows = [j for j, k in enumerate(c["kind"]) if k == kind]
        for colour_index, key in enumerate(dict.fromkeys(_series(c, j) for j in rows)):
            own = sorted((j for j in rows if _series(c, j) == key), key=lambda j: c["x"][j])
            x = [c["x"][j] for j in own]
            colour = f"C{colour_index % 10}"
            model = [c["model"][j] for j in own]
            merr = [c["model_err"][j] for j in own]
            ax.plot(x, model, "-", color=colour, label=f"model, {_label(key)}")
            ax.fill_between(x, [m - e for m, e in zip(model, merr)], [m + e for m, e in zip(model, merr)],
                            color=colour, alpha=0.2, linewidth=0)
            ax.errorbar(x, [c["data"][j] for j in own], yerr=[c["data_err"][j] for j in own], fmt="o",
                        color=colour, capsize=3, label=f"observed, {_label(key)}")
        ax.set_xlabel(xtitle)
        ax.set_ylabel(ytitle)
        ax.set_title(f"{kind}: observed (1 sigma) and the model at the best fit (band: its Monte Carlo "
                     "1 sigma)", fontsize=10)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)


def _series(c: dict, j: int) -> tuple:
    """The series a comparison row belongs to: its table, and for a ratio (x = wavelength) the
    annulus of projected offset it was measured in (a ratio table holds one spectrum per
    annulus; a colour table's annuli are its x)."""
    if c["kind"][j] == "ratio":
        return c["table"][j], c["offset_lo"][j], c["offset_hi"][j]
    return (c["table"][j],)


def _label(key: tuple) -> str:
    import os

    name = os.path.basename(key[0]) or "table"
    if len(key) == 3:
        return f"{name}, offset {_number(key[1], 3)}-{_number(key[2], 3)}"
    return name


def render(view, width, height):
    """The Python View's picture (a vtkImageData) of the fit result shown in ``view``."""
    import numpy as np
    from paraview import python_view

    figure = python_view.matplotlib_figure(width, height)
    params, comparison = _tables(view)
    draw(figure, params, comparison)
    # (ParaView 5.11's figure_to_image reads the canvas with numpy.fromstring, which numpy 2
    # removed: the RGBA buffer is read here, its rows turned bottom-up as VTK's images are)
    figure.canvas.draw()
    rgba = np.asarray(figure.canvas.buffer_rgba())
    return python_view.numpy_to_image(np.ascontiguousarray(rgba[::-1]))
