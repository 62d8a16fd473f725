"""pvpython helpers for NebulaRT in ParaView (import after ``paraview.simple``).

- :func:`load_plugin`            load plugin/NebulaRT.py unless its proxies are already known
- :func:`show_rgba_volume`       show the ``rgba`` array of Nebula Colour as a volume, composited right
- :func:`show_sky_image`         show the ``rgb`` image of Nebula Sky Image as it is
- :func:`show_stars`             show the Stars output of Nebula Light Field, a point per star
- :func:`show_fit_result`        a fit result's parameters and one chart per observable kind (Python View)
- :func:`set_orbit_camera`       the camera of ``nebula_rt.filters.render`` (``nebula-rt render --png``)
- :func:`set_compute_device`     pin the Device property of every NebulaRT proxy
- :func:`load_state_safely`      LoadState, then check that the expected proxies exist

Compositing of ``rgba`` (ParaView 5.11's GPU ray caster, VTK 9.2; read from VTK's
vtkVolumeInputHelper / vtkOpenGLVolumeOpacityTable / vtkOpenGLGPUVolumeRayCastMapper and measured
under Xvfb/llvmpipe, Smart and GPU Based modes alike). With MapScalars off, a 4-component uint8
array is rendered with *dependent* components: RGB is the colour as it is, and the alpha channel
goes through the opacity function. Two things stand between that and per-voxel compositing:

1. the opacity table is corrected for the sample distance with the ScalarOpacityUnitDistance
   of component 3 (the alpha channel), which ParaView never sets (it sets component 0's): the
   function's value is applied as the opacity per **1.0 world unit**;
2. the table is sampled over the data's alpha range [a0, a1] (the mapper's default "scalar"
   transfer-function range; ParaView 5.11 offers no other) but looked up at a/255 (dependent
   components get no scale and bias): the opacity of alpha a is f(a0 + (a/255)(a1 - a0)).
   A constant-alpha box hides this (a0 = a1: the table is f(a) throughout); a 10-voxel slab of
   alpha 30 in an empty box rendered 26 where per-voxel compositing gives 143.

NebulaRT's alpha is the opacity of one voxel, so :func:`show_rgba_volume` gives the opacity
function the points ``x = a0 + t (a1 - a0)``, ``y = 1 - (1 - t)^(1/s)`` (t in [0, 1], s = the
voxel edge in world units, the geometric mean of the spacing): the lookup at t = a/255 then
finds the opacity of the 1/s voxels in one world unit. With it white boxes of constant alpha
render 235 / 235 / 254 / 235 for 234.7 / 234.7 / 254.5 / 234.5 and the slab 142
(tests/paraview/compositing.py). The mapping depends on the spacing and on the alpha range of
the data shown, so it is fitted again when either changes (:mod:`nebula_rt_paraview.display`
does so before each render; in scripts call :func:`show_rgba_volume` again). In a parallel
render every rank's mapper samples its own piece's alpha range: the mapping is exact where the
pieces share the whole range. ScalarOpacityUnitDistance is set to 1.0 so that the mapping stays
right on a ParaView that honours it. The data keep their box-unit geometry.
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
    from . import renamed

    if not plugin_loaded():
        simple.LoadPlugin(path or PLUGIN_FILE, remote=False)
        if servermanager.ActiveConnection is not None and servermanager.ActiveConnection.IsRemote():
            simple.LoadPlugin(path or PLUGIN_FILE, remote=True)
        if not plugin_loaded():
            raise RuntimeError(f"loading {path or PLUGIN_FILE} did not define the NebulaRT proxies "
                               f"{_missing_definitions()} (see the messages above; docs/paraview.md explains the set-up)")
    renamed.install()  # paraview.simple is imported now: its former function names too


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


def display_input(display):
    """(vtkSMSourceProxy, output port) that a representation shows."""
    prop = display.SMProxy.GetProperty("Input")
    return prop.GetProxy(0), prop.GetOutputPortForConnection(0)


def alpha_range(source, array: str = "rgba", port: int = 0) -> tuple[float, float]:
    """(min, max) of the alpha channel (component 3) of ``array`` in ``source``'s output, as
    the data information has it (the whole dataset's range in a parallel session)."""
    info = source.GetDataInformation(port).GetPointDataInformation().GetArrayInformation(array)
    if info is None or info.GetNumberOfComponents() < 4:
        raise ValueError(f"{source.GetXMLName()} has no 4-component point array {array!r} to show")
    lo, hi = info.GetComponentRange(3)
    return float(lo), float(hi)


def per_voxel_opacity_points(voxel: float, n: int = 256, top: float = 255.0, alpha_range=None,
                             unit_distance: float = 1.0) -> list[float]:
    """Opacity-function points (x, y, midpoint, sharpness) that make VTK's GPU mapper composite
    a per-voxel alpha channel (0..top) voxel by voxel (module doc).

    ``y = 1 - (1 - t)^(unit_distance/voxel)`` is the opacity over ``unit_distance`` (the
    distance the mapper corrects the alpha channel's opacity to: 1.0 world unit unless
    :func:`set_alpha_unit_distance` made it the voxel, where ``y = t``) of alpha ``a = t top``;
    the points sit at ``x = a0 + t (a1 - a0)`` because the mapper samples the function over
    the data's alpha range ``alpha_range = (a0, a1)`` and looks it up at ``t = a/top``. Without
    a range, or for a constant alpha (a0 = a1: the whole table is the function's value at a0),
    ``x = a``."""
    a0, a1 = (0.0, top) if alpha_range is None else (float(alpha_range[0]), float(alpha_range[1]))
    stretch = a1 > a0
    power = float(unit_distance) / float(voxel)
    pts = []
    for i in range(n):
        t = i / (n - 1)
        y = 1.0 - (1.0 - t) ** power if t < 1.0 else 1.0
        pts += [a0 + t * (a1 - a0) if stretch else top * t, y, 0.5, 0.0]
    return pts


def set_alpha_unit_distance(display, distance: float) -> bool:
    """Set the unit distance of the alpha channel (component 3 of the volume property) that
    VTK's mapper corrects dependent RGBA opacities with; ParaView's ScalarOpacityUnitDistance
    sets component 0's only. Reaches the rendering object directly, so it works where this
    process renders (the GUI's and pvpython's built-in server, pvbatch): returns False
    elsewhere (a remote server), where the opacity stays per world unit."""
    conn = servermanager.ActiveConnection
    if conn is None or conn.IsRemote():
        return False
    try:
        rep = display.GetClientSideObject().GetActiveRepresentation()
        prop = rep.GetActor().GetProperty()
    except AttributeError:  # not a volume representation (or another ParaView's classes)
        return False
    if prop.GetScalarOpacityUnitDistance(3) != distance:
        prop.SetScalarOpacityUnitDistance(3, float(distance))
    return True


def show_rgba_volume(source, view=None, array: str = "rgba", mode: str = "Smart", voxel: float | None = None,
                     port: int = 0):
    """Show ``array`` (uint8 RGBA, alpha = opacity of one voxel) of ``source`` as a volume.

    The REFERENCES recipe (Volume; ColorBy first; MapScalars 0; transfer functions fixed to
    0..255) with this representation's own colour and opacity functions and the per-voxel
    opacity mapping of the module doc. ``voxel``: the voxel size in world units (default: from
    the data). The mapping follows the data's spacing and alpha range: call again if they
    change (in the GUI, and wherever the plugin is loaded, nebula_rt_paraview.display refits it
    before each render). ``mode``: "Smart" or "GPU Based" (not "Ray Cast Only"). Returns the
    representation.
    """
    view = view or simple.GetActiveViewOrCreate("RenderView")
    source.UpdatePipeline()
    display = simple.Show(source if port == 0 else simple.OutputPort(source, port), view)
    configure_rgba_volume(display, view, array=array, mode=mode, voxel=voxel)
    return display


def configure_rgba_volume(display, view, array: str = "rgba", mode: str = "Smart", voxel: float | None = None):
    """Make an existing image representation show ``array`` as a direct-RGBA volume
    (:func:`show_rgba_volume` without the Show). Returns the (voxel, alpha range, unit
    distance) it fitted."""
    src, out_port = display_input(display)
    if voxel is None:
        voxel = voxel_size(src, out_port)
    arange = alpha_range(src, array, out_port)
    display.SetRepresentationType("Volume")
    display.UseSeparateColorMap = 1  # the opacity mapping depends on this volume's spacing and alpha range
    simple.ColorBy(display, ("POINTS", array))  # first: it re-fits the functions
    display.MapScalars = 0  # 4 components -> RGB colour + alpha channel (dependent components)
    lut = display.LookupTable
    lut.AutomaticRescaleRangeMode = "Never"
    lut.RescaleTransferFunction(0.0, 255.0)
    pwf = display.ScalarOpacityFunction
    if "AutomaticRescaleRangeMode" in pwf.ListProperties():  # ParaView >= 5.12
        pwf.AutomaticRescaleRangeMode = "Never"
    display.VolumeRenderingMode = mode
    display.ScalarOpacityUnitDistance = voxel  # component 0's: the same distance where ParaView honours it
    unit = voxel if set_alpha_unit_distance(display, voxel) else 1.0
    pwf.Points = per_voxel_opacity_points(voxel, alpha_range=arange, unit_distance=unit)
    if "Shade" in display.ListProperties():
        display.Shade = 0
    display.SetScalarBarVisibility(view, False)
    return voxel, arange, unit


def show_sky_image(source, view=None, array: str = "rgb"):
    """Show the ``rgb`` (uint8 x 3) image of Nebula Sky Image with its own colours, 2D camera
    fitted to the image."""
    view = view or simple.GetActiveViewOrCreate("RenderView")
    source.UpdatePipeline()
    display = simple.Show(source, view)
    configure_sky_image(display, view, array=array)
    return display


def configure_sky_image(display, view, array: str = "rgb", fit_camera: bool = True):
    """Make an existing representation show a sky image's ``rgb`` as it is (Slice, Map
    Scalars off, no colour bar); ``fit_camera``: look at the image face-on, 2D, parallel."""
    display.SetRepresentationType("Slice")
    simple.ColorBy(display, ("POINTS", array))
    display.MapScalars = 0
    display.SetScalarBarVisibility(view, False)
    if fit_camera:
        src, port = display_input(display)
        b = src.GetDataInformation(port).GetBounds()
        cx, cy = 0.5 * (b[0] + b[1]), 0.5 * (b[2] + b[3])
        view.InteractionMode = "2D"
        view.CameraParallelProjection = 1
        view.CameraFocalPoint = [cx, cy, 0.0]
        view.CameraPosition = [cx, cy, 10.0]
        view.CameraViewUp = [0.0, 1.0, 0.0]
        simple.ResetCamera(view)  # (the clipping range)
        view.CameraParallelScale = sky_parallel_scale(src, port, view.ViewSize)
    return display


def configure_polarization_vectors(display, view=None):
    """Make an existing representation of Nebula Polarization Vectors draw its line segments
    white over the sky image."""
    display.SetRepresentationType("Surface")
    simple.ColorBy(display, None)
    display.AmbientColor = display.DiffuseColor = [1.0, 1.0, 1.0]
    display.LineWidth = 2.0
    return display


def sky_parallel_scale(src, port, view_size) -> float:
    """The parallel scale (half the height seen) at which a 2D image fills a view of
    ``view_size`` pixels: its width or its height, whichever the aspect ratio lets (pixel
    edges, not centres; ResetCamera fits the bounds' sphere instead, a 40 % margin)."""
    info = src.GetDataInformation(port)
    b, ext = info.GetBounds(), info.GetExtent()
    w, h = b[1] - b[0], b[3] - b[2]
    px = w / max(ext[1] - ext[0], 1)
    vw, vh = (max(int(v), 1) for v in view_size)
    return 0.5 * max(h + px, (w + px) * vh / vw)


def fit_sky_camera(camera, src, port, view_size) -> None:
    """Give a (parallel) camera the scale of :func:`sky_parallel_scale`."""
    camera.SetParallelScale(sky_parallel_scale(src, port, view_size))


#: how the stars (port 1 of Nebula Light Field) are drawn: a sphere of this many pixels each
STAR_POINT_SIZE = 9.0


def show_stars(light, view=None):
    """Show the Stars output (port 1) of a Nebula Light Field: a point per star in its own
    colour (:func:`configure_star_points`). Returns the representation."""
    view = view or simple.GetActiveViewOrCreate("RenderView")
    port = simple.OutputPort(light, 1)
    light.UpdatePipeline()
    display = simple.Show(port, view)
    configure_star_points(display, view)
    return display


def configure_star_points(display, view, array: str = "star_rgb", size: float = STAR_POINT_SIZE):
    """Draw star points as discs of ``size`` pixels in their own colour (``star_rgb``, Map
    Scalars off), lit flat so the colour is the star's, no colour bar, over the volume
    (:func:`set_points_on_top`)."""
    display.SetRepresentationType("Points")
    simple.ColorBy(display, ("POINTS", array))
    display.MapScalars = 0
    display.PointSize = size
    if "RenderPointsAsSpheres" in display.ListProperties():
        display.RenderPointsAsSpheres = 1
    display.Ambient = 1.0
    display.Diffuse = 0.0
    display.SetScalarBarVisibility(view, False)
    set_points_on_top(display)
    return display


#: depth offset of star points (VTK adds offset/65000 to a point's depth): to the near plane
ON_TOP_POINT_OFFSET = -66000.0


def set_points_on_top(display, offset: float = ON_TOP_POINT_OFFSET) -> bool:
    """Draw a representation's points at the front of the depth buffer: the volume's rays stop
    there, so a star inside the nebula is seen as a marker instead of behind the dust in front
    of it (its attenuated light is what Nebula Sky Image shows). Set on the rendering object's
    mappers (the coincident-topology point offset; ParaView has no property for it), so it
    works where this process renders, like :func:`set_alpha_unit_distance`; returns False
    elsewhere (the points are then depth-tested like any geometry)."""
    conn = servermanager.ActiveConnection
    if conn is None or conn.IsRemote():
        return False
    try:
        actor = display.GetClientSideObject().GetActiveRepresentation().GetActor()
    except AttributeError:
        return False
    for mapper in (actor.GetMapper(), actor.GetLODMapper()):
        if mapper is not None:
            mapper.SetRelativeCoincidentTopologyPointOffsetParameter(offset)  # (Modified only on a change)
    return True


class StarOverlay:
    """The stars drawn by the client over the server's composited picture (client/server).

    A pvserver of several ranks composites the ranks' pictures in depth order, and the star
    points, made on rank 0, lie under the other ranks' dust: at tau 128 they are not seen (the
    depth offset of :func:`set_points_on_top` acts within one rank's picture only). The
    client's render view draws its annotations in a renderer of its own after compositing (the
    view's non-composited renderer, which shares the view's camera); an actor there with the
    star points, fetched once per change of the Stars output, is drawn over the picture as the
    built-in session draws them. It follows the stars display's visibility, point size and
    representation."""

    def __init__(self, view):
        from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

        self.renderer = view.GetClientSideObject().GetNonCompositedRenderer()
        self.mapper = vtkPolyDataMapper()
        self.mapper.SetScalarModeToUsePointFieldData()
        self.mapper.SetColorModeToDirectScalars()
        self.actor = vtkActor()
        self.actor.SetMapper(self.mapper)
        prop = self.actor.GetProperty()
        prop.SetAmbient(1.0)
        prop.SetDiffuse(0.0)
        prop.SetRenderPointsAsSpheres(True)
        self.signature = None
        self.renderer.AddActor(self.actor)

    def follow(self, display, array: str = "star_rgb") -> None:
        """Match the stars display (fetching its points again where its output changed)."""
        src, port = display_input(display)
        info = src.GetDataInformation(port)
        rgb = info.GetPointDataInformation().GetArrayInformation(array)
        signature = (info.GetNumberOfPoints(), tuple(info.GetBounds()),
                     None if rgb is None else tuple(rgb.GetComponentRange(-1)))
        if signature != self.signature:
            from vtkmodules.vtkFiltersGeneral import vtkVertexGlyphFilter

            glyphs = vtkVertexGlyphFilter()  # a vertex per point: the Stars output has none
            glyphs.SetInputData(servermanager.Fetch(servermanager._getPyProxy(src), idx=port))
            glyphs.Update()
            self.mapper.SetInputData(glyphs.GetOutput())
            self.mapper.SelectColorArray(array)
            self.mapper.SetScalarVisibility(bool(rgb is not None))
            self.signature = signature
        self.actor.GetProperty().SetPointSize(float(display.PointSize))
        self.actor.SetVisibility(bool(display.Visibility)
                                 and display.SMProxy.GetProperty("Representation").GetElement(0) == "Points")

    def remove(self) -> None:
        self.renderer.RemoveActor(self.actor)


def show_fit_result(reader, view=None):
    """Show a ``NebulaFitResultReader``'s two ports in a Python View drawn by
    :mod:`nebula_rt_paraview.fit_view`: the parameters with their errors first, then one
    chart per observable kind with error bars (a new view unless ``view``, a Python View, is
    given). Returns the view."""
    from .fit_view import SCRIPT

    if view is None:
        view = simple.CreateView("PythonView")
    view.Script = SCRIPT
    for port in (0, 1):
        simple.Show(simple.OutputPort(reader, port), view)
    return view


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
