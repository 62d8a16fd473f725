"""Default displays of NebulaRT's outputs: what Apply (in the GUI) or Show (in a script) shows.

The proxies' XML hints pick the representation type and the view (Volume for the light field
and its colour, Points for the light field's Stars port, Slice in a ``NebulaSkyView`` for the
sky image); ParaView would then colour the result with a colour map. This behaviour, installed
by ``plugin/NebulaRT.py`` in every process that has a client (the GUI, pvpython, pvbatch), does
what hints cannot, before the render that first shows a new representation:

- ``rgba`` of a light field or a colour (or of a reader of a NebulaRT file, e.g. the command
  line's ``.vti``): a direct-RGBA volume, Map Scalars off, the alpha channel as opacity
  composited per voxel (:func:`nebula_rt_paraview.view.configure_rgba_volume`); the light
  field's stars are shown with it (in a script ``Show(light)`` shows port 0 only); a view still
  on the colour palette's background turns black (emission against the sky);
- the stars: discs of a few pixels in each star's own colour, drawn over the volume as markers
  (:func:`nebula_rt_paraview.view.set_points_on_top`);
- a sky image: its ``rgb`` as it is, filling its view (a sky view's camera reset fills it too);
- polarization vectors: their line segments white over the sky image;
- the light field's light per leaf (port 2), shown by Apply with the volume: hidden, so that
  the volume is seen (a script's ``Show`` of that port keeps it shown).

Representations made by a state file keep what the state says, its camera included (a loaded
state stops paraview.simple's camera reset at a session's first Render); a new one is set up
once, and what the user changes afterwards is theirs. For every rgba volume whose opacity
function is still a per-voxel mapping (a state's included, and the per-world-unit one of
states written before the mapping followed the alpha range), the mapping is refitted before
each render when the data's spacing or alpha range changed (a new grid, Tau, Opacity Scale);
the alpha channel's unit distance and the stars' depth offset, which a state cannot store, are
set on the rendering objects. A function the user edited is left alone.
"""

from __future__ import annotations

import sys

#: the behaviour of this process (install() makes it once)
_BEHAVIOUR = None

#: producers whose port 0 carries ``rgba``
RGBA_PRODUCERS = ("NebulaLightField", "NebulaColour")


def install():
    """Set up the behaviour where this process has a client (GUI, pvpython, pvbatch); a no-op
    on a server process and when it is already installed. Returns the behaviour or None."""
    global _BEHAVIOUR
    if _BEHAVIOUR is not None:
        return _BEHAVIOUR
    try:
        from paraview.modules import vtkRemotingViews  # noqa: F401 - views wrapped as their own classes
        from paraview.modules.vtkRemotingCore import vtkProcessModule
        from paraview.modules.vtkRemotingServerManager import vtkSMProxyManager
    except ImportError:
        return None
    if vtkProcessModule.GetProcessModule() is None or vtkProcessModule.GetProcessType() not in (
            vtkProcessModule.PROCESS_CLIENT, vtkProcessModule.PROCESS_BATCH):
        return None
    _BEHAVIOUR = _Behaviour(vtkSMProxyManager.GetProxyManager())
    return _BEHAVIOUR


def _gid(proxy) -> int:
    return int(proxy.GetGlobalID())


def _key(obj) -> str:
    """A key for a VTK object that outlives its Python wrapper (the C++ address)."""
    return obj.__this__


class _Behaviour:
    """Observers on the session proxy managers (new representations and views) and on the
    views (a pass over their representations before each render)."""

    def __init__(self, manager):
        self.manager = manager
        self.pxms = {}  # key -> session proxy manager (GlobalIDs are per session: state per manager)
        self.pending = {}  # pxm key -> GlobalIDs of new representations not yet set up
        self.known = {}  # pxm key -> GlobalIDs of the representations registered
        self.views = {}  # pxm key -> GlobalIDs of the views observed
        self.fitted = {}  # (pxm key, representation GlobalID) -> (voxel, alpha range, unit, points)
        self.luts = {}  # pxm key -> GlobalIDs of the colour maps of NebulaRT's displays
        self.busy = False
        self.busy_reset = False
        self.reset_watched = {}  # key -> vtkPVRenderView of a sky view whose camera resets fit the image
        self.overlays = {}  # (view key, representation GlobalID) -> StarOverlay (client/server)
        self.warned = False
        from paraview.modules.vtkRemotingServerManager import vtkSMProxyManager

        manager.AddObserver(vtkSMProxyManager.ActiveSessionChanged, self._on_session)
        self._on_session(manager, None)

    # -- sessions, registrations -----------------------------------------------------------------
    def _on_session(self, manager, _event):
        pxm = manager.GetActiveSessionProxyManager()
        if pxm is None or _key(pxm) in self.pxms:
            return
        self.pxms[_key(pxm)] = pxm
        self.pending[_key(pxm)] = set()
        self.known[_key(pxm)] = set(_gid(p) for p in self._group(pxm, "representations"))
        self.views[_key(pxm)] = set()
        pxm.AddObserver("RegisterEvent", self._on_register)
        pxm.AddObserver("LoadStateEvent", self._on_state_loaded)
        self._watch_views(pxm)

    @staticmethod
    def _on_state_loaded(_pxm, _event):
        """A state brings its own camera: paraview.simple's first Render of a session would
        reset it (``LoadState(...); Render()`` lost the states' cameras)."""
        simple = sys.modules.get("paraview.simple")
        if simple is not None and hasattr(simple, "_DisableFirstRenderCameraReset"):
            simple._DisableFirstRenderCameraReset()

    @staticmethod
    def _group(pxm, group):
        from paraview.modules.vtkRemotingServerManager import vtkSMProxyIterator

        it = vtkSMProxyIterator()
        it.SetSessionProxyManager(pxm)
        it.SetModeToOneGroup()
        it.Begin(group)
        out = []
        while not it.IsAtEnd():
            out.append(it.GetProxy())
            it.Next()
        return out

    def _on_register(self, pxm, _event):
        try:
            key = _key(pxm)
            current = {_gid(rep) for rep in self._group(pxm, "representations")}
            new = current - self.known[key]
            self.known[key] = current  # (the unregistered ones drop out: ids are not reused)
            if new and not pxm.GetInLoadXMLState():
                self.pending[key] |= new
            self.pending[key] &= current
            self._watch_views(pxm)
        except Exception as exc:  # noqa: BLE001 - a display default must never break a pipeline
            self._warn(exc)

    def _watch_views(self, pxm):
        key = _key(pxm)
        views = {_gid(v): v for v in self._group(pxm, "views") if v.IsA("vtkSMViewProxy")}
        for g, view in views.items():
            if g not in self.views[key]:
                view.AddObserver("StartEvent", lambda v, e, pxm=pxm: self._on_render(pxm, v))
        self.views[key] = set(views)

    def _warn(self, exc):
        if not self.warned:  # once: the messages would repeat on every render
            self.warned = True
            sys.stderr.write(f"NebulaRT warning: setting up the default display failed ({type(exc).__name__}: {exc})\n")

    # -- before each render ----------------------------------------------------------------------
    def _on_render(self, pxm, view):
        if self.busy:
            return
        self.busy = True
        try:
            self._pass(pxm, view)
        except Exception as exc:  # noqa: BLE001
            self._warn(exc)
        finally:
            self.busy = False

    def _pass(self, pxm, view):
        if view.GetXMLName() == "NebulaSkyView":
            self._watch_camera_resets(view)
        reps = self._nebula_representations(view)
        self._drop_overlays(view, {_gid(rep) for kind, rep, *_ in reps if kind == "stars"})
        if not reps:
            return
        from paraview import servermanager

        from . import view as helpers

        pending = self.pending[_key(pxm)]
        # light fields whose volume is shown for the first time in this pass (Apply shows all
        # of a filter's ports at once; a script shows the port it names)
        new_volumes = {_gid(src) for kind, rep, src, port in reps if kind == "rgba" and _gid(rep) in pending}
        if any(kind == "rgba" for kind, *_ in reps):
            view.Update()  # the data a render would show, before its ranges are read
        pyview = servermanager._getPyProxy(view)
        shown_stars = {_gid(src) for kind, rep, src, port in reps if kind == "stars"}
        luts = self.luts.setdefault(_key(pxm), set())  # colour maps NebulaRT displays use or used
        for kind, rep, src, port in reps:
            g = _gid(rep)
            new = g in pending
            pending.discard(g)
            display = servermanager._getPyProxy(rep)
            lut = rep.GetProperty("LookupTable")
            if lut is not None and lut.GetNumberOfProxies() and lut.GetProxy(0) is not None:
                luts.add(_gid(lut.GetProxy(0)))  # (before a set-up: the colour map it replaces)
            if kind == "rgba":
                if new:
                    self._set_up_rgba(pxm, display, pyview)
                    if src.GetXMLName() == "NebulaLightField" and _gid(src) not in shown_stars:
                        stars = helpers.show_stars(servermanager._getPyProxy(src), pyview)
                        pending.discard(_gid(stars.SMProxy))  # set up already
                        shown_stars.add(_gid(src))
                else:
                    self._follow_rgba(pxm, display, pyview)
            elif kind == "stars":
                if new:
                    helpers.configure_star_points(display, pyview)
                elif display.SMProxy.GetProperty("Representation").GetElement(0) == "Points":
                    helpers.set_points_on_top(display)  # not in a state: the rendering object's
                if servermanager.ActiveConnection is not None and servermanager.ActiveConnection.IsRemote():
                    overlay = self.overlays.get((_key(view), g))
                    if overlay is None:
                        overlay = self.overlays[(_key(view), g)] = helpers.StarOverlay(pyview)
                    overlay.follow(display)
            elif kind == "sky" and new:
                helpers.configure_sky_image(display, pyview, fit_camera=self._alone(view, rep))
            elif kind == "vectors" and new:
                helpers.configure_polarization_vectors(display, pyview)
            elif kind == "tree" and new and _gid(src) in new_volumes:
                # shown with the volume (Apply shows every port): the light per leaf starts
                # hidden, its eye in the pipeline browser shows it; its surface hid the volume
                rep.GetProperty("Visibility").SetElement(0, 0)
                rep.UpdateVTKObjects()
            lut = rep.GetProperty("LookupTable")
            if lut is not None and lut.GetNumberOfProxies() and lut.GetProxy(0) is not None:
                luts.add(_gid(lut.GetProxy(0)))
        self._hide_unused_colour_bars(view, luts)

    def _drop_overlays(self, view, shown):
        """Remove the star overlays of ``view`` whose stars display is gone (``shown``: the
        GlobalIDs of its stars displays)."""
        for key in [k for k in self.overlays if k[0] == _key(view) and k[1] not in shown]:
            self.overlays.pop(key).remove()

    @staticmethod
    def _hide_unused_colour_bars(view, luts):
        """Hide the colour bars of ``luts`` that no visible representation of ``view`` maps
        scalars through: the direct colours of rgba, star_rgb and rgb have none (ParaView's
        Apply shows one anyway), nor has the colour map a set-up replaced."""
        prop = view.GetProperty("Representations")
        used, bars = set(), []
        for i in range(prop.GetNumberOfProxies()):
            rep = prop.GetProxy(i)
            if rep is None:
                continue
            if rep.GetXMLName() == "ScalarBarWidgetRepresentation":
                bars.append(rep)
                continue
            vis, ms, lut = (rep.GetProperty(n) for n in ("Visibility", "MapScalars", "LookupTable"))
            if (vis is not None and vis.GetElement(0) and ms is not None and ms.GetElement(0)
                    and lut is not None and lut.GetNumberOfProxies() and lut.GetProxy(0) is not None):
                color = rep.GetProperty("ColorArrayName")
                if color is None or color.GetElement(4):  # coloured by an array
                    used.add(_gid(lut.GetProxy(0)))
        for bar in bars:
            lut = bar.GetProperty("LookupTable")
            vis = bar.GetProperty("Visibility")
            if (lut is not None and lut.GetNumberOfProxies() and lut.GetProxy(0) is not None
                    and _gid(lut.GetProxy(0)) in luts and _gid(lut.GetProxy(0)) not in used and vis.GetElement(0)):
                vis.SetElement(0, 0)
                bar.UpdateVTKObjects()

    def _watch_camera_resets(self, view):
        """A sky view's Reset Camera (ParaView's, after Apply, or the button) fits the image to
        the view instead of the bounds' sphere (nebula_rt_paraview.view.fit_sky_camera)."""
        pvview = view.GetClientSideObject()  # the vtkPVRenderView: it says when it reset its camera
        if pvview is None or not pvview.IsA("vtkPVRenderView") or _key(pvview) in self.reset_watched:
            return
        self.reset_watched[_key(pvview)] = pvview
        pvview.AddObserver("ResetCameraEvent", lambda r, e, view=view: self._on_camera_reset(view, r))

    def _on_camera_reset(self, view, pvview):
        if self.busy_reset:
            return
        self.busy_reset = True
        try:
            from . import view as helpers

            for kind, rep, src, port in self._nebula_representations(view):
                vis = rep.GetProperty("Visibility")
                if kind == "sky" and vis is not None and vis.GetElement(0):
                    helpers.fit_sky_camera(pvview.GetActiveCamera(), src, port, pvview.GetSize())
                    break
        except Exception as exc:  # noqa: BLE001
            self._warn(exc)
        finally:
            self.busy_reset = False

    @staticmethod
    def _nebula_representations(view):
        """(kind, representation, producer, port) of the NebulaRT outputs in ``view``."""
        prop = view.GetProperty("Representations")
        out = []
        if prop is None:
            return out
        for i in range(prop.GetNumberOfProxies()):
            rep = prop.GetProxy(i)
            inp = rep.GetProperty("Input") if rep is not None else None
            if inp is None or inp.GetNumberOfProxies() == 0:
                continue
            src, port = inp.GetProxy(0), inp.GetOutputPortForConnection(0)
            name = src.GetXMLName()
            if name == "NebulaLightField" and port == 1:
                out.append(("stars", rep, src, port))
            elif name == "NebulaLightField" and port == 2:
                out.append(("tree", rep, src, port))
            elif name == "NebulaSkyImage":
                out.append(("sky", rep, src, port))
            elif name == "NebulaPolarizationVectors":
                out.append(("vectors", rep, src, port))
            elif _carries_rgba(src, port, name in RGBA_PRODUCERS):
                out.append(("rgba", rep, src, port))
        return out

    @staticmethod
    def _alone(view, rep) -> bool:
        """Whether ``rep`` is the only visible representation of ``view`` (or the view is a sky
        view): then its camera is fitted to the image."""
        if view.GetXMLName() == "NebulaSkyView":
            return True
        prop = view.GetProperty("Representations")
        for i in range(prop.GetNumberOfProxies()):
            other = prop.GetProxy(i)
            vis = other.GetProperty("Visibility")
            if (_gid(other) != _gid(rep) and vis is not None and vis.GetElement(0)
                    and other.GetProperty("Input") is not None):
                return False
        return True

    # -- rgba volumes -------------------------------------------------------------------------------
    def _set_up_rgba(self, pxm, display, view):
        from . import view as helpers

        voxel, arange, unit = helpers.configure_rgba_volume(display, view)
        # emission is seen against the dark sky: a view still on the palette's background
        # (not one the user chose) turns black
        if "UseColorPaletteForBackground" in view.ListProperties() and view.UseColorPaletteForBackground:
            view.UseColorPaletteForBackground = 0
            view.Background = [0.0, 0.0, 0.0]
        self.fitted[(_key(pxm), _gid(display.SMProxy))] = (voxel, arange, unit, tuple(display.ScalarOpacityFunction.Points))

    def _follow_rgba(self, pxm, display, view):
        """Refit the per-voxel mapping when the data changed; adopt a representation whose
        function is a per-voxel mapping (a state's); leave a user's own function alone."""
        from . import view as helpers

        if display.SMProxy.GetProperty("Representation").GetElement(0) != "Volume":
            return
        key = (_key(pxm), _gid(display.SMProxy))
        src, port = helpers.display_input(display)
        voxel = helpers.voxel_size(src, port)
        arange = helpers.alpha_range(src, "rgba", port)
        points = tuple(display.ScalarOpacityFunction.Points)
        last = self.fitted.get(key)
        if last is None:
            if not _is_mapping(points):
                return
        elif points != last[3]:
            del self.fitted[key]  # the user changed the function: theirs from now on
            return
        unit = voxel if helpers.set_alpha_unit_distance(display, voxel) else 1.0
        if last is not None and last[:3] == (voxel, arange, unit):
            return
        display.ScalarOpacityUnitDistance = voxel
        display.ScalarOpacityFunction.Points = helpers.per_voxel_opacity_points(voxel, alpha_range=arange,
                                                                                 unit_distance=unit)
        self.fitted[key] = (voxel, arange, unit, tuple(display.ScalarOpacityFunction.Points))


def _carries_rgba(src, port, nebula_proxy: bool) -> bool:
    """Whether an output holds a light field's ``rgba`` (uint8 x 4 point array): a NebulaRT
    proxy's port 0, or any other source's output with the light-field field data
    (``band_names``): a reader of the command line's ``.vti`` or of a saved ``.pvti``."""
    info = src.GetDataInformation(port)
    arr = info.GetPointDataInformation().GetArrayInformation("rgba")
    if arr is None or arr.GetNumberOfComponents() != 4 or arr.GetDataType() != 3:  # VTK_UNSIGNED_CHAR
        return False
    if nebula_proxy:
        return port == 0
    return info.GetFieldDataInformation().GetArrayInformation("band_names") is not None


def _is_mapping(points, n: int = 256, tol: float = 1e-6) -> bool:
    """Whether opacity points are a per-voxel mapping of
    :func:`nebula_rt_paraview.view.per_voxel_opacity_points` (any alpha range, voxel and unit
    distance): 256 points whose x rise evenly from 0 or the alpha range's start and whose y is
    1 - (1 - t)^p for one power p (found from the second point)."""
    import math

    if len(points) != 4 * n:
        return False
    xs, ys = points[0::4], points[1::4]
    span = xs[-1] - xs[0]
    if span <= 0 or ys[0] != 0.0 or ys[-1] != 1.0 or not 0.0 < ys[1] < 1.0:
        return False
    if any(abs(x - (xs[0] + span * i / (n - 1))) > tol * max(1.0, span) for i, x in enumerate(xs)):
        return False
    p = math.log1p(-ys[1]) / math.log1p(-1.0 / (n - 1))
    return all(abs(y - (1.0 - (1.0 - i / (n - 1)) ** p)) <= tol for i, y in enumerate(ys[:-1]))
