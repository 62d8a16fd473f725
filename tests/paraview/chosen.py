"""What "auto" chose, read from the proxies (pvpython).

    pvpython chosen.py

Nebula Dust Density -> Nebula Light Field -> Nebula Colour and a Nebula Sky Image, small, with
Auto Exposure and Auto Opacity on (the defaults), then ``UpdatePropertyInformation``. RESULT:
per proxy, the information properties ExposureChosen / OpacityScaleChosen and the output's
field data ``exposure`` / ``opacity_scale``; the values before the first update.
"""

import _common
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_plugin

load_plugin()
dust = simple.NebulaDustDensity(Device=_common.TEST_DEVICE, GridShape=[16, 16, 16])
light = simple.NebulaLightField(dust, Device=_common.TEST_DEVICE, Photons=20_000)
colour = simple.NebulaColour(light)
sky = simple.NebulaSkyImage(light, ImageSize=[32, 32])
before = colour.GetPropertyValue("ExposureChosen")
out = {}
for name, proxy, keys in (("colour", colour, ("Exposure", "OpacityScale")), ("sky", sky, ("Exposure",))):
    proxy.UpdatePipeline()
    proxy.UpdatePropertyInformation()
    fd = servermanager.Fetch(proxy).GetFieldData()
    out[name] = {key: [proxy.GetPropertyValue(key + "Chosen"),
                       fd.GetArray("exposure" if key == "Exposure" else "opacity_scale").GetValue(0)]
                 for key in keys}
_common.result(before=before, chosen=out)
