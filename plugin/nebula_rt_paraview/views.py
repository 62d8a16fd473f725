"""The plugin's view: ``NebulaSkyView``, a render view for sky images.

Nebula Sky Image's hint ``<View type="NebulaSkyView"/>`` makes Apply show the image in a view
of this type: a new one next to the 3D view (ParaView creates the preferred view when the
active one is of another type), or the active one if it is a sky view already. It is a plain
render view (vtkPVRenderView, every property of "RenderView") whose defaults suit a picture: 2D
interaction, parallel projection, black background, no orientation axes; they are settings
(``vtkSMSettings``) of the lowest priority, so a user's own settings win.

``NebulaSkyView`` is a proxy name: states store it.
"""

import json

#: the proxy definition the plugin loader picks up (get_plugin_xmls looks for _pvsm_proxy_xml)
SKY_VIEW_XML = """
<ServerManagerConfiguration>
  <ProxyGroup name="views">
    <RenderViewProxy name="NebulaSkyView" label="Nebula Sky View" class="vtkPVRenderView"
                     processes="client|renderserver|dataserver"
                     base_proxygroup="views" base_proxyname="RenderView">
      <Documentation>A render view for NebulaRT's sky images: 2D interaction, parallel
        projection and a black background by default.</Documentation>
    </RenderViewProxy>
  </ProxyGroup>
</ServerManagerConfiguration>
"""

#: default property values of NebulaSkyView (settings keyed by the proxy's group and name)
SKY_VIEW_DEFAULTS = {
    "InteractionMode": 1,  # 2D
    "CameraParallelProjection": 1,
    "OrientationAxesVisibility": 0,
    "UseColorPaletteForBackground": 0,
    "Background": [0.0, 0.0, 0.0],
}


class NebulaSkyView:
    """Carries the view's proxy XML into the plugin (``plugin/NebulaRT.py`` imports it)."""

    _pvsm_proxy_xml = SKY_VIEW_XML


def install_view_defaults(priority: float = 0.0) -> bool:
    """Add :data:`SKY_VIEW_DEFAULTS` to ParaView's settings (lowest priority by default);
    False where there is no settings object (a process without the server manager)."""
    try:
        from paraview.modules.vtkRemotingServerManager import vtkSMSettings
    except ImportError:
        return False
    settings = vtkSMSettings.GetInstance()
    if settings is None:
        return False
    return bool(settings.AddCollectionFromString(json.dumps({"views": {"NebulaSkyView": SKY_VIEW_DEFAULTS}}),
                                                 float(priority)))
