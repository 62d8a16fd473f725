"""pvpython helpers for NebulaRT in ParaView (import after ``paraview.simple``).

- :func:`load_plugin`            load plugin/NebulaRT.py unless its proxies are already known
- :func:`show_rgba_volume`       show the ``rgba`` array of Nebula Colour as a volume, composited right
- :func:`show_sky_image`         show the ``rgb`` image of Nebula Sky Image as it is
- :func:`set_orbit_camera`       the camera of ``nebula_rt.filters.render`` (``nebula-rt render --png``)
- :func:`set_compute_device`     pin the Device property of every NebulaRT proxy
- :func:`load_state_safely`      LoadState, then check that the expected proxies exist

Compositing of ``rgba`` (measured with ParaView 5.11's GPU ray caster under Xvfb/llvmpipe,
Smart and GPU Based modes alike; VTK 9.7's mapper behaves the same). With MapScalars off, a
4-component array is rendered with *dependent* components: RGB is the colour, and the opacity
function of the alpha channel gives an opacity **per 1.0 world unit**, whatever
ScalarOpacityUnitDistance says. White voxels of constant alpha on black, centre pixel, with the
plain linear opacity ramp: alpha 20 through 32 voxels rendered 19 at spacing 1/32 (one voxel's
worth) and 235 at spacing 1; through 64 voxels at spacing 1/32 (two world units) 38; alpha 10
through 64 voxels at spacing 1/64 gave 10 -- with ScalarOpacityUnitDistance at its default, at
the spacing or at 1. Per-voxel compositing over the n - 1 voxel-centre intervals a ray crosses
expects 234.7 / 234.7 / 254.5 / 234.5. Scaling the actor (the representation's Scale) does
not help either. NebulaRT's alpha is the opacity of one voxel, so :func:`show_rgba_volume`
maps it through the opacity function ``opacity(a) = 1 - (1 - a/255)^(1/s)`` (s = the voxel
edge in world units, the geometric mean of the spacing): the opacity of the 1/s voxels in one
world unit. With it the same cases render 235 / 235 / 254 / 235 (and alpha 5: 117 for 117.0).
ScalarOpacityUnitDistance is set to 1.0 as well, so the mapping stays right on a ParaView
that honours it. The data keep their box-unit geometry (tests/paraview/compositing.py).
"""

from __future__ import annotations

import math
import os

from paraview import servermanager
from paraview import simple

#: proxy XML names of the plugin, by proxy group
PROXY_GROUPS = {
    "NebulaDustDensity": "sources",
    "NebulaLightField": "filters",
    "NebulaColour": "filters",
    "NebulaSkyImage": "filters",
}

PLUGIN_FILE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "NebulaRT.py")


class StateLoadError(RuntimeError):
    """A state file did not produce the proxies it should have."""


# -- plugin -----------------------------------------------------------------------------------
def plugin_loaded() -> bool:
    """Whether ParaView knows the NebulaRT proxies (the plugin is loaded)."""
    return not _missing_definitions()


def _missing_definitions() -> list:
    spm = servermanager.vtkSMProxyManager.GetProxyManager().GetActiveSessionProxyManager()
    return [name for name, group in PROXY_GROUPS.items() if not spm.HasDefinition(group, name)]


def load_plugin(path: str | None = None) -> None:
    """Load the plugin (``plugin/NebulaRT.py``) unless its proxies are already defined (with
    PV_PLUGIN_PATH set, ParaView loads it at start-up)."""
    if plugin_loaded():
        return
    simple.LoadPlugin(path or PLUGIN_FILE, remote=False)
    if servermanager.ActiveConnection is not None and servermanager.ActiveConnection.IsRemote():
        simple.LoadPlugin(path or PLUGIN_FILE, remote=True)
    if not plugin_loaded():
        raise RuntimeError(f"loading {path or PLUGIN_FILE} did not define the NebulaRT proxies {_missing_definitions()} "
                           "(see the messages above; docs/paraview.md explains the set-up)")


# -- showing ----------------------------------------------------------------------------------
def voxel_size(source, port: int = 0) -> float:
    """World size of one voxel of an image-data output: the geometric mean of its spacing."""
    info = source.GetDataInformation(port)
    ext = info.GetExtent()
    bounds = info.GetBounds()
    sizes = []
    for ax in range(3):
        n = ext[2 * ax + 1] - ext[2 * ax]
        if n > 0:
            sizes.append((bounds[2 * ax + 1] - bounds[2 * ax]) / n)
    sizes = [s for s in sizes if s > 0]
    if not sizes:
        raise ValueError(f"{source.GetXMLName()} has no image data to show (did it fail? see its error)")
    return math.exp(sum(math.log(s) for s in sizes) / len(sizes))


def per_voxel_opacity_points(voxel: float, n: int = 256, top: float = 255.0) -> list[float]:
    """Opacity-function points (x, y, midpoint, sharpness) turning a per-voxel alpha channel
    (0..top) into the opacity per world unit that the GPU mapper applies with dependent
    components: ``1 - (1 - a/top)^(1/voxel)``."""
    pts = []
    for i in range(n):
        x = top * i / (n - 1)
        a = min(max(x / top, 0.0), 1.0)
        y = 1.0 - (1.0 - a) ** (1.0 / voxel) if a < 1.0 else 1.0
        pts += [x, y, 0.5, 0.0]
    return pts


def show_rgba_volume(source, view=None, array: str = "rgba", mode: str = "Smart", voxel: float | None = None):
    """Show ``array`` (uint8 RGBA, alpha = opacity of one voxel) of ``source`` as a volume.

    The REFERENCES recipe (Volume; ColorBy first; MapScalars 0; transfer functions fixed to
    0..255) with this representation's own colour and opacity functions and the per-voxel
    opacity mapping of the module doc. ``voxel``: the voxel size in world units (default: from
    the data; call again if the grid changes). ``mode``: "Smart" or "GPU Based" (not "Ray Cast
    Only"). Returns the representation.
    """
    view = view or simple.GetActiveViewOrCreate("RenderView")
    source.UpdatePipeline()
    if voxel is None:
        voxel = voxel_size(source)
    display = simple.Show(source, view)
    display.SetRepresentationType("Volume")
    display.UseSeparateColorMap = 1  # the opacity mapping depends on this volume's spacing
    simple.ColorBy(display, ("POINTS", array))  # first: it re-fits the functions
    display.MapScalars = 0  # 4 components -> RGB colour + alpha channel (dependent components)
    lut = display.LookupTable
    lut.AutomaticRescaleRangeMode = "Never"
    lut.RescaleTransferFunction(0.0, 255.0)
    pwf = display.ScalarOpacityFunction
    if "AutomaticRescaleRangeMode" in pwf.ListProperties():  # ParaView >= 5.12
        pwf.AutomaticRescaleRangeMode = "Never"
    pwf.Points = per_voxel_opacity_points(voxel)
    display.ScalarOpacityUnitDistance = 1.0
    display.VolumeRenderingMode = mode
    if "Shade" in display.ListProperties():
        display.Shade = 0
    display.SetScalarBarVisibility(view, False)
    return display


def show_sky_image(source, view=None, array: str = "rgb"):
    """Show the ``rgb`` (uint8 x 3) image of Nebula Sky Image with its own colours, 2D camera."""
    view = view or simple.GetActiveViewOrCreate("RenderView")
    display = simple.Show(source, view)
    display.SetRepresentationType("Slice")
    simple.ColorBy(display, ("POINTS", array))
    display.MapScalars = 0
    display.SetScalarBarVisibility(view, False)
    source.UpdatePipeline()
    b = source.GetDataInformation().GetBounds()
    cx, cy = 0.5 * (b[0] + b[1]), 0.5 * (b[2] + b[3])
    view.InteractionMode = "2D"
    view.CameraParallelProjection = 1
    view.CameraFocalPoint = [cx, cy, 0.0]
    view.CameraPosition = [cx, cy, 10.0]
    view.CameraViewUp = [0.0, 1.0, 0.0]
    simple.ResetCamera(view)
    return display


def set_orbit_camera(view, bounds=None, azimuth: float = 30.0, elevation: float = 20.0, view_angle: float = 30.0):
    """The camera ``nebula_rt.filters.render.render_rgba_png`` uses: look down -z (x right, y up),
    rotate by ``azimuth`` then ``elevation`` (degrees) about the bounds' centre, then VTK's
    ResetCamera on ``bounds`` (default: the visible data). Perspective, view angle 30 degrees.
    Returns (position, focal point, view up)."""
    from vtkmodules.vtkRenderingCore import vtkRenderer

    if bounds is None:
        simple.Render(view)
        bounds = view.GetRenderer().ComputeVisiblePropBounds()
    bounds = [float(b) for b in bounds]
    centre = [0.5 * (bounds[2 * i] + bounds[2 * i + 1]) for i in range(3)]
    ren = vtkRenderer()
    cam = ren.GetActiveCamera()
    cam.SetFocalPoint(*centre)
    cam.SetPosition(centre[0], centre[1], centre[2] + 1.0)
    cam.SetViewUp(0.0, 1.0, 0.0)
    cam.SetViewAngle(view_angle)
    cam.Azimuth(float(azimuth))
    cam.Elevation(float(elevation))
    cam.OrthogonalizeViewUp()
    ren.ResetCamera(bounds)
    view.CameraParallelProjection = 0
    view.CameraViewAngle = view_angle
    view.CameraFocalPoint = list(cam.GetFocalPoint())
    view.CameraPosition = list(cam.GetPosition())
    view.CameraViewUp = list(cam.GetViewUp())
    return list(cam.GetPosition()), list(cam.GetFocalPoint()), list(cam.GetViewUp())


# -- devices and states -----------------------------------------------------------------------
def nebula_proxies(names=None) -> dict:
    """{proxy XML name: [pipeline proxies]} of the NebulaRT proxies in the session."""
    names = set(names or PROXY_GROUPS)
    found: dict = {}
    for (_label, _id), px in simple.GetSources().items():
        xml = px.GetXMLName()
        if xml in names:
            found.setdefault(xml, []).append(px)
    return found


def set_compute_device(selector: str, backend: str | None = None) -> int:
    """Set Device (and Backend, if given) on every Nebula Dust Density and Light Field proxy;
    e.g. ``set_compute_device("Portable Computing Language")`` after loading a state. Returns
    how many proxies were changed."""
    n = 0
    for name in ("NebulaDustDensity", "NebulaLightField"):
        for px in nebula_proxies([name]).get(name, []):
            px.Device = selector
            if backend is not None:
                px.Backend = backend
            n += 1
    return n


def load_state_safely(path: str, expected_proxies=(), data_directory: str | None = None, **kw) -> dict:
    """Load the plugin, ``LoadState(path)``, then check that the expected proxies exist.

    ParaView's LoadState only logs errors (e.g. for proxies of a plugin that is not loaded) and
    carries on with what it could make. ``expected_proxies``: proxy XML names, repeated to
    require several (e.g. ``["NebulaDustDensity"] + ["NebulaLightField"] * 4``), or a dict
    {name: minimum count}. Raises :class:`StateLoadError` naming what is missing. Returns
    :func:`nebula_proxies` (name -> list of proxies). ``kw`` goes to LoadState.
    """
    if not os.path.isfile(path):
        raise StateLoadError(f"state file {path} does not exist")
    load_plugin()
    if data_directory is not None:
        kw["data_directory"] = data_directory
    simple.LoadState(path, **kw)
    # keep the state's camera: paraview.simple resets it on a session's first Render otherwise
    if hasattr(simple, "_DisableFirstRenderCameraReset"):
        simple._DisableFirstRenderCameraReset()
    if isinstance(expected_proxies, dict):
        need = dict(expected_proxies)
    else:
        need = {}
        for name in expected_proxies:
            need[name] = need.get(name, 0) + 1
    found = nebula_proxies(need.keys() | set(PROXY_GROUPS))
    all_names: dict = {}
    for (_label, _id), px in simple.GetSources().items():
        all_names[px.GetXMLName()] = all_names.get(px.GetXMLName(), 0) + 1
    missing = {n: c for n, c in need.items() if all_names.get(n, 0) < c}
    if missing:
        have = ", ".join(f"{n} x{c}" for n, c in sorted(all_names.items())) or "nothing"
        want = ", ".join(f"{n} x{c}" for n, c in sorted(missing.items()))
        if plugin_loaded():
            why = "the state holds fewer of them, or they failed to load (see the messages above)"
        else:
            why = (f"the NebulaRT plugin ({PLUGIN_FILE}) is not loaded: are nebula_rt and its "
                   "dependencies importable (source scripts/pv-env.sh; see docs/paraview.md)?")
        raise StateLoadError(f"loading {path} did not create {want} (the session has: {have}): {why}")
    return found
