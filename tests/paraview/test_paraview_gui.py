"""The ParaView GUI as a user drives it: menus and Apply, nothing typed.

ParaView's test utility (``paraview --test-script=EVENTS.xml --exit``) plays recorded Qt events
in the real GUI on the session's Xvfb: Sources > NebulaRT > Nebula Dust Density, Apply;
Filters > NebulaRT > Nebula Light Field, Apply; Nebula Colour, Apply; Nebula Sky Image, Apply.
Between the steps the events run tests/paraview/gui_probe.py in the GUI's Python shell, which
only records what is shown (screenshots of every view, its representations); the checks are
here. The one setting the GUI gets is the Device default of the two NebulaRT proxies (a
ParaView user settings file in a scratch HOME), so that every trace runs on PoCL, pinned by name
as in conftest.py; nothing about the display is set.

A state file loaded in the GUI (File > Load State's path, ``paraview --state``) is checked the
same way: its stored camera and every panel in the view.
"""

from __future__ import annotations

import colorsys
import json
import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pytest

from test_paraview import REPO, SCRIPTS, STATE_NAMES, read_png, run_pv, srgb_to_linear

PROBE = SCRIPTS / "gui_probe.py"
MAIN = "pqClientMainWindow"


def _event(obj, command, arguments=""):
    return f'  <pqevent object={quoteattr(obj)} command={quoteattr(command)} arguments={quoteattr(arguments)} />'


def menu(menu_name, category, proxy):
    return [_event(f"{MAIN}/menubar", "activate", menu_name),
            _event(f"{MAIN}/menubar/{menu_name}/{category}", "activate", proxy)]


def apply():
    return [_event(f"{MAIN}/propertiesDock/propertiesPanel/Accept", "activate")]


def check(obj, prop, arguments):
    """A check of the test utility (the playback fails, naming it, if the widget disagrees):
    ``modelItemData`` "row.column,text" (a column may be given by its header), ``modelRowCount``."""
    return [f'  <pqcheck object={quoteattr(obj)} property={quoteattr(prop)} arguments={quoteattr(arguments)} />']


#: the properties panel's widgets (ParaView names each property's widget after the property)
PANEL = f"{MAIN}/propertiesDock/propertiesPanel/scrollArea/qt_scrollarea_viewport/scrollAreaWidgetContents/PropertiesFrame/ProxyPanel"


def probe(step, grab=False):
    code = f"STEP = {step!r}; GRAB = {grab}; exec(open({str(PROBE)!r}).read())"
    return [_event(f"{MAIN}/pythonShellDock/pythonShell/consoleWidget", "executeCommand", code)]


def run_gui(pv_env, display, tmp_path, events, args=(), timeout=400, light_field=None, clicker=None):
    """Play ``events`` in ``paraview`` on ``display``; returns the folder the probes wrote.
    The user's saved settings pin the Device of the two tracing proxies (and set
    ``light_field``'s properties on the light field); ``clicker(out)``, if given, runs beside
    the GUI in this process (a thread) and is joined after it."""
    out = tmp_path / "gui"
    out.mkdir()
    home = tmp_path / "home"
    (home / ".config" / "ParaView").mkdir(parents=True)
    device = pv_env["NEBULA_RT_TEST_DEVICE"]
    settings = {"sources": {"NebulaDustDensity": {"Device": device}},
                "filters": {"NebulaLightField": dict({"Device": device}, **(light_field or {}))}}
    (home / ".config" / "ParaView" / "ParaView-UserSettings.json").write_text(json.dumps(settings))
    # no welcome dialog (it waits for a click): the Qt settings of this ParaView version
    version = subprocess.run(["paraview", "--version"], env=dict(pv_env, DISPLAY=display), capture_output=True,
                             text=True, timeout=60).stdout.split()[-1]
    (home / ".config" / "ParaView" / f"ParaView{version}.ini").write_text(
        "[General]\nGeneralSettings.ShowWelcomeDialog=false\n")
    xml = tmp_path / "events.xml"
    xml.write_text('<?xml version="1.0" ?>\n<pqevents>\n' + "\n".join(events) + "\n</pqevents>\n")
    env = dict(pv_env, DISPLAY=display, HOME=str(home), XDG_CONFIG_HOME=str(home / ".config"),
               XDG_RUNTIME_DIR=str(tmp_path), NEBULA_GUI_OUT=str(out))
    worker = None
    if clicker is not None:
        worker = threading.Thread(target=clicker, args=(out,), daemon=True)
        worker.start()
    proc = subprocess.run(["paraview", "-geometry", "1280x1024+0+0", *args, f"--test-script={xml}", "--exit"],
                          env=env, cwd=str(tmp_path), capture_output=True, text=True, timeout=timeout)
    (out / "done").touch()
    if worker is not None:
        worker.join(timeout=30)
    assert proc.returncode == 0 and "Success =  true" in proc.stdout + proc.stderr, (
        f"paraview exited {proc.returncode}\n--- stdout ---\n{proc.stdout[-3000:]}\n--- stderr ---\n{proc.stderr[-4000:]}")
    assert "NebulaRT warning: setting up the default display failed" not in proc.stdout + proc.stderr, proc.stderr[-3000:]
    return out


def step_record(out, step):
    path = out / f"{step}.json"
    assert path.exists(), f"the GUI never ran the probe of step {step!r}"
    r = json.loads(path.read_text())
    assert "error" not in r, r["error"]
    return r


def reps_of(view, producer, port=0):
    return [r for r in view["representations"] if r["producer"] == producer and r["port"] == port]


def lit_stats(im):
    m = im.max(axis=2)
    lit = m > 8
    return lit, m


# -- Apply shows the result -------------------------------------------------------------------
#: the Stars table's column headers (ShowComponentLabels)
STAR_COLUMNS = ["X", "Y", "Z", "Luminosity", "Temperature", "Bump Radius"]
#: the default star as the table shows it (each number as the table's model writes it): the
#: thesis's star, at the centre, luminosity 1, 20000 K, in its dust bump of half-size 0.01
DEFAULT_ROW = ["0.5", "0.5", "0.5", "1", "20000", "0.01"]


def stars_table(rows):
    """Checks of the Stars table shown in the panel: its number of rows and each cell, found
    by its column's header (a header that is not there fails the playback, naming the ones
    that are)."""
    table = f"{PANEL}/Stars/ScalarValueList/Table"
    out = check(table, "modelRowCount", str(len(rows)))
    for r, row in enumerate(rows):
        for column, text in zip(STAR_COLUMNS, row):
            out += check(table, "modelItemData", f"{r}.{column},{text}")
    return out


@pytest.fixture(scope="module")
def applied(pv_env, xdisplay, tmp_path_factory):
    """Density -> Light Field -> Colour -> Sky Image, each created from the menus and Applied
    with every property at its default (the user's settings pin only the Device); on the way
    the Stars tables are checked and the density's "+" and "-" pressed."""
    tmp = tmp_path_factory.mktemp("gui_apply")
    add, remove = (f"{PANEL}/Stars/ScalarValueList/{b}" for b in ("Add", "Remove"))
    events = (menu("menuSources", "NebulaRT", "NebulaDustDensity")
              + stars_table([DEFAULT_ROW])
              + [_event(add, "activate")]
              + stars_table([DEFAULT_ROW, DEFAULT_ROW])  # "+": a copy of the selected (last) star
              + [_event(remove, "activate")]  # "-": the new row (selected by "+") goes again
              + stars_table([DEFAULT_ROW])
              + apply()
              + menu("menuFilters", "NebulaRT", "NebulaLightField")
              + stars_table([DEFAULT_ROW])  # the light field's own table: the same headers and star
              + apply() + probe("light", grab=True)
              + menu("menuFilters", "NebulaRT", "NebulaColour") + apply() + probe("colour")
              + menu("menuFilters", "NebulaRT", "NebulaSkyImage") + apply() + probe("sky", grab=True))
    out = run_gui(pv_env, xdisplay, tmp, events)
    return {step: step_record(out, step) for step in ("light", "colour", "sky")}


def test_apply_on_the_light_field_shows_the_true_colour_volume_and_the_star(applied):
    """After Apply on Nebula Light Field, with no script: one render view holding the light
    field's rgba as a direct-RGBA volume (Map Scalars off, the 256-point per-voxel opacity
    mapping, no colour bar), its Stars port as points in their own colour, the density hidden,
    a black background."""
    r = applied["light"]
    assert len(r["layouts"]) == 1 and len(r["views"]) == 1
    view = r["views"][0]
    assert view["type"] == "RenderView"
    (vol,) = reps_of(view, "NebulaLightField", 0)
    assert vol["visible"] and vol["representation"] == "Volume", vol
    assert vol["color"] == ["POINTS", "rgba"] and vol["map_scalars"] == 0 and vol["scalar_bar"] == 0, vol
    assert vol["opacity_points"] == 256
    (stars,) = reps_of(view, "NebulaLightField", 1)
    assert stars["visible"] and stars["representation"] == "Points", stars
    assert stars["color"] == ["POINTS", "star_rgb"] and stars["map_scalars"] == 0 and stars["scalar_bar"] == 0
    (dust,) = reps_of(view, "NebulaDustDensity", 0)
    assert not dust["visible"]
    assert view["Background"] == [0.0, 0.0, 0.0] and view["UseColorPaletteForBackground"] == 0


def test_the_picture_is_bright_true_colour_with_the_star_drawn(applied, pv_env, xdisplay, tmp_path):
    """The light field's screenshot (64^3 default nebula at Tau 128, ParaView's
    own camera after Apply):

    - it is the direct-RGBA rendering of the data: the same pipeline shown in pvpython with
      show_rgba_volume and show_stars, the GUI's camera and size, gives the same picture (mean
      absolute difference under 1 level, 99 % of the pixels within 4: the same bits rendered
      by the same mapper; a colour map of any array would differ by tens of levels);
    - bright: the lit region (max channel > 8) fills > 15 % of the view and its 99th
      percentile is above 160 of 255 (the old recipe, whose opacity table spanned the data's
      alpha range, rendered the same nebula at 136; measured now: 186);
    - the star: at its projected position the 3 x 3 pixels hold the star's own colour (its
      disc is drawn over the volume), within 3 levels (the disc's antialiased edge);
    - its colours are the bands': the thesis-rgb nebula is blue (mean linear B/R of the lit
      region above 1.5; measured 2.7) and bluer near the star than far from it (B/R of the
      mean linear light; blue scatters more near the star), with a hue that varies over the
      lit pixels (spread above 0.01 of the circle)."""
    view = applied["light"]["views"][0]
    im = read_png(view["png"])
    h, w = im.shape[:2]
    assert [w, h] == view["size"]
    spec = tmp_path / "view.json"
    spec.write_text(json.dumps(view))
    ref, _ = run_pv(pv_env, xdisplay, "reference_render.py", spec, tmp_path / "reference.png")
    assert ref["error"] is None
    diff = np.abs(im - read_png(ref["png"]))
    assert diff.mean() < 1.0 and np.percentile(diff.max(axis=2), 99) <= 4.0, (diff.mean(), diff.max())
    lit, m = lit_stats(im)
    assert lit.mean() > 0.15, lit.mean()
    assert np.percentile(m[lit], 99) > 160, np.percentile(m[lit], 99)
    (stars,) = reps_of(view, "NebulaLightField", 1)
    for (x, y), rgb in zip(stars["stars"]["display"], stars["stars"]["rgb"]):
        px, py = int(x), h - 1 - int(y)
        block = im[py - 1:py + 2, px - 1:px + 2]
        assert np.abs(block - np.array(rgb, float)).max() <= 3.0, (block, rgb)
    pix = im[lit]
    mean = srgb_to_linear(pix).mean(axis=0)
    assert mean[2] / mean[0] > 1.5, mean
    (sx, sy), = stars["stars"]["display"]
    yy, xx = np.mgrid[0:h, 0:w]
    rr = np.hypot(xx - sx, (h - 1 - yy) - sy)
    near = lit & (rr > 12) & (rr < 0.08 * w)
    far = lit & (rr > 0.25 * w)
    ln, lf = srgb_to_linear(im[near]).mean(axis=0), srgb_to_linear(im[far]).mean(axis=0)
    assert ln[2] / ln[0] > 1.01 * lf[2] / lf[0], (ln, lf)
    hues = np.array([colorsys.rgb_to_hsv(*(p / 255.0))[0] for p in pix[::7]])
    assert hues.std() > 0.01, hues.std()


def test_nebula_colour_downstream_keeps_the_display(applied):
    """Apply on Nebula Colour (default settings: the light field's own colour) shows its rgba
    the same way, hides the light field's volume and keeps the stars; the picture is the light
    field's (the same rgba and camera: mean absolute difference under 1 level)."""
    light, colour = applied["light"]["views"][0], applied["colour"]["views"][0]
    (vol,) = reps_of(colour, "NebulaColour", 0)
    assert vol["visible"] and vol["representation"] == "Volume" and vol["color"] == ["POINTS", "rgba"]
    assert vol["map_scalars"] == 0 and vol["scalar_bar"] == 0 and vol["opacity_points"] == 256
    assert not reps_of(colour, "NebulaLightField", 0)[0]["visible"]
    assert reps_of(colour, "NebulaLightField", 1)[0]["visible"]
    a, b = read_png(light["png"]), read_png(colour["png"])
    assert np.abs(a - b).mean() < 1.0


def test_sky_image_opens_in_its_own_2d_view_in_true_colour(applied):
    """Apply on Nebula Sky Image opens a second view, a NebulaSkyView next to the 3D one in the
    same tab: 2D interaction, parallel projection, the image as a slice of its rgb with Map
    Scalars off and no colour bar, filling the view's width or height; the 3D view does not
    show it. The
    screenshot's pixels over the image average the rgb array's mean within 3 levels per channel
    (the view resamples 256^2 pixels onto its own)."""
    r = applied["sky"]
    assert len(r["layouts"]) == 1 and len(r["layouts"][0]["views"]) == 2
    types = sorted(v["type"] for v in r["views"])
    assert types == ["NebulaSkyView", "RenderView"]
    render = next(v for v in r["views"] if v["type"] == "RenderView")
    sky = next(v for v in r["views"] if v["type"] == "NebulaSkyView")
    assert not reps_of(render, "NebulaSkyImage", 0) or not reps_of(render, "NebulaSkyImage", 0)[0]["visible"]
    (img,) = reps_of(sky, "NebulaSkyImage", 0)
    assert img["visible"] and img["representation"] == "Slice" and img["color"] == ["POINTS", "rgb"]
    assert img["map_scalars"] == 0 and img["scalar_bar"] == 0
    assert sky["CameraParallelProjection"] == 1.0 and sky["InteractionMode"] == 1  # 2D
    im = read_png(sky["png"])
    h, w = im.shape[:2]
    (x0, y0), (x1, y1) = img["display_corners"]
    nx, ny = img["dimensions"][:2]
    # pixel centres -> pixel edges, display y up -> image rows down; 2 pixels in from each edge
    hx, hy = 0.5 * (x1 - x0) / (nx - 1), 0.5 * (y1 - y0) / (ny - 1)
    c0, c1 = int(np.ceil(x0 - hx)) + 2, int(np.floor(x1 + hx)) - 2
    r0, r1 = int(np.ceil(h - 1 - (y1 + hy))) + 2, int(np.floor(h - 1 - (y0 - hy))) - 2
    assert 0 <= c0 < c1 <= w and 0 <= r0 < r1 <= h, (c0, c1, r0, r1)
    # fitted: the image spans the view's width or its height (to 2 %)
    assert max((x1 - x0 + 2 * hx) / w, (y1 - y0 + 2 * hy) / h) > 0.98, "the image is not fitted in its view"
    shown = im[r0:r1, c0:c1].reshape(-1, 3).mean(axis=0)
    assert np.all(np.abs(shown - np.array(img["rgb_mean"])) <= 3.0), (shown, img["rgb_mean"])
    # the image's own colours: a blue nebula (mean linear B/R of the lit pixels above 1.5)
    sub = im[r0:r1, c0:c1]
    lit = sub.max(axis=2) > 8
    mean = srgb_to_linear(sub[lit]).mean(axis=0)
    assert mean[2] / mean[0] > 1.5, mean
    assert Path(r["window_png"]).exists()
    # every property at its default: no error and no warning anywhere in the pipeline (a
    # Distance left empty once read as "set while Units is box units")
    said = {p["xml"]: (p["last_error"], p["last_warnings"]) for p in r["proxies"].values()}
    assert all(e is None and not w for e, w in said.values()), said


def test_stars_table_has_headers_and_plus_adds_a_visible_star(applied):
    """The Stars tables (density and light field) show column headers X, Y, Z, Luminosity,
    Temperature, Bump Radius and start with the scene's default star, the thesis's; "+" adds a
    copy of the selected star (luminosity 1 at the box centre: a visible star, not a row of zeros) and "-"
    removes it (the playback's checks above; a failed check fails the playback). The applied
    density holds the one default star and traces without error."""
    from nebula_rt.filters.base import default_star_row

    proxies = applied["light"]["proxies"]
    dust = next(p for p in proxies.values() if p["xml"] == "NebulaDustDensity")
    light = next(p for p in proxies.values() if p["xml"] == "NebulaLightField")
    assert dust["Stars"] == default_star_row() == [0.5, 0.5, 0.5, 1.0, 20000.0, 0.01]
    assert dust["last_error"] is None and light["last_error"] is None


def test_counts_are_text_fields_not_sliders(applied):
    """Photons, Seed, Max Scatterings and Batch Size span 2^53 or 2^31: a slider there has its
    knob at the far left for every useful value, so the panel shows text fields (ParaView's
    line edits) and the scene's validation keeps the upper end (a value past it is refused at
    Apply, naming the property); Tau, unbounded above, was a text field already."""
    widgets = applied["light"]["panel_widgets"]
    assert set(widgets) >= {"Photons", "Seed", "MaxScatterings", "BatchSize", "Tau"}, widgets
    for name, kinds in widgets.items():
        assert not any("Range" in k or "Slider" in k for k in kinds), (name, kinds)
        assert any("LineEdit" in k for k in kinds), (name, kinds)


def test_plus_on_an_emptied_stars_table_gives_a_usable_star(pv_env, xdisplay, tmp_path):
    """The density's Stars table emptied ("Remove All"), then "+": ParaView adds a row of blank
    cells (it copies the selected row, and there is none), which reach the property as zeros.
    Apply makes the density with the default star in that row's place (the thesis's: its dust
    bump is there) and says so in a warning naming the row; no error."""
    table = f"{PANEL}/Stars/ScalarValueList"
    events = (menu("menuSources", "NebulaRT", "NebulaDustDensity")
              + [_event(f"{table}/RemoveAll", "activate")] + check(f"{table}/Table", "modelRowCount", "0")
              + [_event(f"{table}/Add", "activate")] + check(f"{table}/Table", "modelRowCount", "1")
              + apply() + probe("blank"))
    r = step_record(run_gui(pv_env, xdisplay, tmp_path, events), "blank")
    (dust,) = [p for p in r["proxies"].values() if p["xml"] == "NebulaDustDensity"]
    assert dust["Stars"] == [0.0] * 6, dust["Stars"]
    assert dust["last_error"] is None and dust["points"] == 64 ** 3, dust
    assert any("row 1 is blank" in w and "default star" in w for w in dust["last_warnings"]), dust["last_warnings"]


def test_the_icons_are_drawn(applied):
    """ParaView's icons are SVG: without Qt's SVG image plugin (libqt5svg5, which Debian's
    paraview does not pull in; scripts/setup.sh installs it) every toolbar button, the Stars
    table's + and -, the gear and the abort button are empty squares. The three toolbar rows
    of the window's screenshot hold coloured pixels over 600 columns with the plugin (measured
    602 of 1280) and over 26 without it (the one PNG icon)."""
    im = read_png(applied["light"]["window_png"])
    band = im[25:140]  # the three toolbar rows under the menu bar, 1280 x 1024 screen
    coloured = (band.max(axis=2) - band.min(axis=2)) > 60
    assert coloured.any(axis=0).sum() > 300, coloured.any(axis=0).sum()


def test_the_gui_demo_script_shows_its_pipeline_with_the_density_array_chosen(pv_env, xdisplay, tmp_path):
    """``paraview --script=plugin/examples/gui_demo.py``: the light field (selected, its
    properties in the panel) traced without error, its Density Array box showing the array
    the script chose ("density"), and the colour's volume shown."""
    out = run_gui(pv_env, xdisplay, tmp_path, probe("demo"),
                  args=(f"--script={REPO / 'plugin' / 'examples' / 'gui_demo.py'}",))
    r = step_record(out, "demo")
    assert r["panel_texts"].get("DensityArray") == "density", r["panel_texts"]
    errors = {p["xml"]: p["last_error"] for p in r["proxies"].values()}
    assert set(errors) == {"NebulaDustDensity", "NebulaLightField", "NebulaColour"} and not any(errors.values()), errors
    (view,) = r["views"]
    (vol,) = reps_of(view, "NebulaColour", 0)
    assert vol["visible"] and vol["representation"] == "Volume" and vol["color"] == ["POINTS", "rgba"], vol


# -- Abort -----------------------------------------------------------------------------------
def abort_clicker(display):
    """A user pressing ParaView's Abort button: a real mouse click on the X server (xdotool)
    at the button's place every 0.3 s, from the probe that found the place (step "ready")
    until the GUI ends. A click before the trace starts meets a disabled button and does
    nothing. Each click's time (``time.monotonic``: Linux's system-wide CLOCK_MONOTONIC, which
    the GUI's Python reads too) goes to ``clicks.json``."""
    import os

    def clicker(out):
        ready, done = out / "ready.json", out / "done"
        while not ready.exists() and not done.exists():
            time.sleep(0.1)
        if not ready.exists():
            return
        time.sleep(0.2)  # (the probe writes its file in one go; let it close)
        x, y = json.loads(ready.read_text())["abort_button"]["screen"]
        clicks = []
        while not done.exists():
            clicks.append(time.monotonic())
            subprocess.run(["xdotool", "mousemove", str(x), str(y), "click", "1"],
                           env=dict(os.environ, DISPLAY=display), timeout=30, check=True)
            (out / "clicks.json").write_text(json.dumps(clicks))
            time.sleep(0.3)

    return clicker


def test_abort_stops_a_trace_within_a_second(pv_env, xdisplay, tmp_path):
    """ParaView's Abort button, clicked with the mouse during a 5e7-packet trace of the
    default nebula (minutes on 2 CPU cores), stops it: the light field's output is empty, its
    message says it was cancelled and how far it came, the trace did not start again for the
    other consumers of the same Apply, and the button is disabled again afterwards.

    How fast: from the click that stopped it (the latest click before the plugin heard the
    press) to the end of the execution, under 3 s on a loaded 2-core machine (the polls come
    between launches of at most about 0.25 s, and the GUI's pending events are delivered at
    each, at most every 0.05 s; measured on 2 idle cores: docs/paraview.md, "Abort")."""
    events = (menu("menuSources", "NebulaRT", "NebulaDustDensity") + apply() + probe("ready")
              + menu("menuFilters", "NebulaRT", "NebulaLightField") + apply() + probe("aborted"))
    out = run_gui(pv_env, xdisplay, tmp_path, events, light_field={"Photons": 50_000_000},
                  clicker=abort_clicker(xdisplay))
    ready, r = step_record(out, "ready"), step_record(out, "aborted")
    assert ready["abort_button"]["screen"] and not ready["abort_button"]["enabled"], ready["abort_button"]
    light = next(p for p in r["proxies"].values() if p["xml"] == "NebulaLightField")
    assert light["points"] == 0, light
    m = re.search(r"transport cancelled after ([\d,]+) of 50,000,000 packets per band", light["last_error"] or "")
    assert m and int(m.group(1).replace(",", "")) < 50_000_000, light["last_error"]
    (src,) = r["abort_button"]["sources"]
    assert not r["abort_button"]["enabled"]
    assert src["pressed_at"] is not None and src["stopped_at"] >= src["pressed_at"], src
    clicks = [t for t in json.loads((out / "clicks.json").read_text()) if t <= src["pressed_at"]]
    assert clicks, "no click before the press was heard"
    assert src["stopped_at"] - clicks[-1] < 3.0, (src, clicks[-1])


@pytest.mark.parametrize("ranks", [2])
def test_abort_stops_a_trace_in_a_pvserver_within_a_second(pv_env, xdisplay, tmp_path, ranks):
    """The same click with the GUI connected to a pvserver of 2 ranks (``--server-url``), where
    the trace runs: the press reaches the server through the plugin's abort port
    (plugin/nebula_rt_paraview/remote_abort.py), both ranks stop and say so, the light
    field's output is empty, and the button is disabled again afterwards.

    How fast: from the click that stopped it (the latest click before the client heard the
    press) to the end of the execution as the client heard it, under 3 s on a loaded 2-core
    machine (progress messages every 0.2 s carry the press, the server's polls come between
    launches of at most about 0.25 s)."""
    from test_paraview import _pvserver

    log = tmp_path / "pvserver.log"
    server, port = _pvserver(pv_env, xdisplay, ranks, log=log)
    try:
        events = (menu("menuSources", "NebulaRT", "NebulaDustDensity") + apply() + probe("ready")
                  + menu("menuFilters", "NebulaRT", "NebulaLightField") + apply() + probe("aborted"))
        out = run_gui(pv_env, xdisplay, tmp_path, events, args=(f"--server-url=cs://localhost:{port}",),
                      light_field={"Photons": 50_000_000}, clicker=abort_clicker(xdisplay))
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=30)
    r = step_record(out, "aborted")
    light = next(p for p in r["proxies"].values() if p["xml"] == "NebulaLightField")
    assert light["remote"] and light["points"] == 0, light
    # every rank says so (the ranks decide together between launches)
    said = re.findall(r"NebulaRT cancelled: NebulaLightField: transport cancelled", log.read_text())
    assert len(said) == ranks, log.read_text()[-3000:]
    relay = r["abort_button"]["relay"]
    assert not r["abort_button"]["enabled"]
    assert relay["pressed_at"] is not None and relay["ended_at"] >= relay["sent_at"] >= relay["pressed_at"], relay
    clicks = [t for t in json.loads((out / "clicks.json").read_text()) if t <= relay["pressed_at"]]
    assert clicks, "no click before the press was heard"
    assert relay["ended_at"] - clicks[-1] < 3.0, (relay, clicks[-1])


def test_a_pvserver_of_2_ranks_shows_the_star_over_the_nebula(pv_env, xdisplay, tmp_path):
    """The GUI connected to a pvserver of 2 ranks: Apply on the density and the light field
    shows the nebula with the star's disc over it in the star's own colour (its 3 x 3 pixels
    within 3 levels, as in the built-in session). The server composites the ranks' pictures in
    depth order, and the star, made on rank 0, would lie under the other rank's dust; the
    client draws it over the composited picture (``view.StarOverlay``)."""
    from test_paraview import _pvserver

    server, port = _pvserver(pv_env, xdisplay, 2)
    try:
        events = (menu("menuSources", "NebulaRT", "NebulaDustDensity") + apply()
                  + menu("menuFilters", "NebulaRT", "NebulaLightField") + apply() + probe("light", grab=True))
        out = run_gui(pv_env, xdisplay, tmp_path, events, args=(f"--server-url=cs://localhost:{port}",),
                      light_field={"Photons": 200_000})
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=30)
    view = step_record(out, "light")["views"][0]
    im = read_png(view["png"])
    h = im.shape[0]
    lit, m = lit_stats(im)
    assert lit.mean() > 0.15, lit.mean()  # the nebula is there
    (stars,) = reps_of(view, "NebulaLightField", 1)
    assert len(stars["stars"]["display"]) == 1, stars["stars"]
    for (x, y), rgb in zip(stars["stars"]["display"], stars["stars"]["rgb"]):
        px, py = int(x), h - 1 - int(y)
        block = im[py - 1:py + 2, px - 1:px + 2]
        assert np.abs(block - np.array(rgb, float)).max() <= 3.0, (block, rgb)


# -- state files in the GUI --------------------------------------------------------------------
# one figure: the three share their structure (one tab, one view, four panels, the labels),
# and each figure's own picture, camera and labels are checked under pvpython and pvbatch
# (test_paraview.py); the GUI's part, a state loaded by File > Load State, is the same for all
@pytest.mark.parametrize("name", STATE_NAMES[1:2])
def test_state_file_in_the_gui_keeps_its_figure(pv_env, xdisplay, tmp_path, name):
    """``paraview --state=FILE`` (what File > Load State does) with a copy of the state whose
    Device is the test device: one tab with one view in preview mode at the figure's aspect
    (1600:540, within 1 %: the GUI scales the layout to fit its window), the stored camera,
    all four panels inside the view (their volumes' display boxes) and lit, and the labels'
    texts made from the data."""
    from test_paraview import _check_state_picture, stored_camera

    text = (REPO / "state_files" / f"{name}.pvsm").read_text()
    pinned = re.sub(r'(<Property name="Device" id="[^"]+" number_of_elements="1">\s*<Element index="0" value=)""',
                    lambda m: m.group(1) + quoteattr(pv_env["NEBULA_RT_TEST_DEVICE"]), text)
    assert pinned.count(pv_env["NEBULA_RT_TEST_DEVICE"]) == 5
    state = tmp_path / f"{name}.pvsm"
    state.write_text(pinned)
    out = run_gui(pv_env, xdisplay, tmp_path, probe("state", grab=True), args=(f"--state={state}",))
    r = step_record(out, "state")
    assert len(r["layouts"]) == 1 and len(r["layouts"][0]["views"]) == 1, r["layouts"]
    (view,) = r["views"]
    assert view["preview"] == [1600, 540]
    w, h = view["size"]
    assert abs(w / h - 1600 / 540) < 0.01 * 1600 / 540, view["size"]
    for key, value in stored_camera(text).items():
        np.testing.assert_allclose(view[key], value, rtol=0, atol=1e-9, err_msg=key)
    vols = [x for x in view["representations"] if x["producer"] == "NebulaColour" and x["visible"]]
    boxes = [{"albedo": x["albedo"], "band_preset": "thesis-rgb", "representation": x["representation"],
              "visible": x["visible"], "x0": x["box"][0], "x1": x["box"][1], "y0": x["box"][2], "y1": x["box"][3]}
             for x in vols]
    _check_state_picture({"size": view["size"], "boxes": boxes}, view["png"], name)
    texts = [x["text"] for x in view["representations"] if x["producer"] == "PythonAnnotation"]
    assert sorted(t for t in texts if t.startswith("albedo")) == [f"albedo {a}" for a in (0.2, 0.4, 0.6, 0.8)], texts
    assert sum("tau 128" in t and "albedo series" in t for t in texts) == 1, texts


@pytest.mark.parametrize("name", ["polarized_nebula", "mie_nebula"])
def test_the_polarization_state_in_the_gui_shows_the_vectors_over_the_picture(pv_env, xdisplay, tmp_path, name):
    """``paraview --state=state_files/polarized_nebula.pvsm`` (and ``mie_nebula.pvsm``, Mie
    grains; Device pinned to the test device): one sky view showing the peel-off sky image
    (Slice) and Nebula Polarization Vectors (their segments, white, over it); the window's
    picture holds the lit nebula and the segments."""
    text = (REPO / "state_files" / f"{name}.pvsm").read_text()
    pinned = re.sub(r'(<Property name="Device" id="[^"]+" number_of_elements="1">\s*<Element index="0" value=)""',
                    lambda m: m.group(1) + quoteattr(pv_env["NEBULA_RT_TEST_DEVICE"]), text)
    assert pinned.count(pv_env["NEBULA_RT_TEST_DEVICE"]) == 2
    state = tmp_path / f"{name}.pvsm"
    state.write_text(pinned)
    out = run_gui(pv_env, xdisplay, tmp_path, probe("state", grab=True), args=(f"--state={state}",))
    r = step_record(out, "state")
    (view,) = r["views"]
    reps = {x["producer"]: x for x in view["representations"] if x["visible"]}
    assert reps["NebulaSkyImage"]["representation"] == "Slice", reps
    assert reps["NebulaPolarizationVectors"]["representation"] == "Surface", reps
    im = read_png(view["png"])
    assert im.mean() > 10  # the nebula
    assert 0.001 < (im.min(axis=2) > 240).mean() < 0.2  # the white segments


def test_opening_the_command_lines_file_shows_its_true_colour(pv_env, xdisplay, tmp_path):
    """File > Open of the command line's ``.vti`` (``paraview --data=FILE``), Apply: the
    reader's rgba shown the same way (a direct-RGBA volume, Map Scalars off, the per-voxel
    mapping, no colour bar), a blue thesis-rgb nebula (mean linear B/R of the lit region above
    1.5), bright (99th percentile of the lit region above 160, as after Apply on the light field;
    measured 186)."""
    import sys

    vti = tmp_path / "neb.vti"
    cli = Path(sys.executable).with_name("nebula-rt")
    subprocess.run([str(cli), "render", str(REPO / "examples" / "scenes" / "thesis-default.toml"), "-o", str(vti),
                    "--set", "grid.shape=[24,24,24]", "--set", "transport.photons=40000",
                    "--device", pv_env["NEBULA_RT_TEST_DEVICE"], "-q"], check=True, timeout=300)
    out = run_gui(pv_env, xdisplay, tmp_path, apply() + probe("file"), args=(f"--data={vti}",))
    r = step_record(out, "file")
    (view,) = r["views"]
    (vol,) = [x for x in view["representations"] if x["producer"] == "XMLImageDataReader"]
    assert vol["visible"] and vol["representation"] == "Volume" and vol["color"] == ["POINTS", "rgba"], vol
    assert vol["map_scalars"] == 0 and vol["scalar_bar"] == 0 and vol["opacity_points"] == 256, vol
    im = read_png(view["png"])
    lit, m = lit_stats(im)
    assert lit.mean() > 0.1 and np.percentile(m[lit], 99) > 160, (lit.mean(), np.percentile(m[lit], 99))
    mean = srgb_to_linear(im[lit]).mean(axis=0)
    assert mean[2] / mean[0] > 1.5, mean


def test_a_hyper_tree_grid_opened_and_traced_shows_its_light_and_the_tree(pv_env, xdisplay, tmp_path):
    """File > Open of an ``.htg`` (``paraview --data=FILE``), Apply, Filters > Nebula Light
    Field, Apply: the light field's rgba volume is shown as for an image input (a bright,
    lit nebula), with no error; the third port (Light per Leaf, the light on the tree) carries
    the tree's leaves and arrays and starts hidden (its eye shows it)."""
    data = REPO / "examples" / "data" / "clumpy_cloud.htg"
    events = (apply() + menu("menuFilters", "NebulaRT", "NebulaLightField") + apply() + probe("tree", grab=True))
    out = run_gui(pv_env, xdisplay, tmp_path, events, args=(f"--data={data}",),
                  light_field={"Photons": 200000, "Resolution": [32, 32, 32], "Tau": 4.0})  # (the cloud's own, as its state file)
    r = step_record(out, "tree")
    (light,) = [p for p in r["proxies"].values() if p["xml"] == "NebulaLightField"]
    assert light["last_error"] is None, light
    leaf = light.get("port2")
    assert leaf is not None and leaf["class"] == "vtkHyperTreeGrid" and leaf["leaves"] > 1000, leaf
    assert {"J_G", "rel_error_G", "emissivity_G", "density"} <= set(leaf["arrays"]), leaf
    (view,) = r["views"]
    (vol,) = [x for x in reps_of(view, "NebulaLightField", 0)]
    assert vol["visible"] and vol["representation"] == "Volume" and vol["color"] == ["POINTS", "rgba"], vol
    # the light per leaf is there, hidden (its surface in front of the volume hid it)
    assert [x["visible"] for x in reps_of(view, "NebulaLightField", 2)] in ([], [0]), view["representations"]
    im = read_png(view["png"])
    lit, m = lit_stats(im)
    assert lit.mean() > 0.05 and np.percentile(m[lit], 99) > 120, (lit.mean(), np.percentile(m[lit], 99))
    # a blue nebula of the thesis's bands (mean linear B / R of the lit region), no flat surface:
    # the lit pixels' brightness varies
    mean = srgb_to_linear(im[lit]).mean(axis=0)
    assert mean[2] / mean[0] > 1.5 and np.std(m[lit]) > 10, (mean, np.std(m[lit]))
