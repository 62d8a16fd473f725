"""The plugin's default display in pvpython: what Show + Render give, and how the opacity
mapping follows the data (nebula_rt_paraview.display).

    pvpython display_behaviour.py

1. Show(light field) and Render, no helper: the rgba volume and the Stars port;
2. a Nebula Colour shown the same way; Auto Opacity off, Opacity Scale 3 -> the alpha range grows -> the mapping
   is refitted at the next render;
3. the user's own opacity function is kept through a later data change;
4. a representation with the per-world-unit mapping of older states is adopted and refitted.

RESULT: the facts per step (representation settings, opacity points, the alpha ranges, the
unit distance of the alpha channel on the rendering object).
"""

import _common
from paraview import simple
from nebula_rt_paraview import display as behaviour
from nebula_rt_paraview.view import (alpha_range, display_input, load_plugin, per_voxel_opacity_points,
                                     voxel_size)

load_plugin()
installed = behaviour._BEHAVIOUR is not None
dev = _common.TEST_DEVICE
dust = simple.NebulaDustDensity(GridShape=[24, 24, 24], Device=dev)
light = simple.NebulaLightField(dust, Photons=20000, Tau=128.0, Device=dev)  # the thesis's optical depth
light.DensityArray = ["POINTS", "density"]
view = simple.CreateView("RenderView")
view.ViewSize = [200, 200]


def facts(display):
    src, port = display_input(display)
    voxel = voxel_size(src, port)
    arange = alpha_range(src, "rgba", port)
    prop = display.GetClientSideObject().GetActiveRepresentation().GetActor().GetProperty()
    return {"representation": display.SMProxy.GetProperty("Representation").GetElement(0),
            "color": [str(c) for c in display.ColorArrayName], "map_scalars": int(display.MapScalars),
            "points": list(display.ScalarOpacityFunction.Points), "voxel": voxel, "alpha_range": list(arange),
            "unit_distance_3": prop.GetScalarOpacityUnitDistance(3),
            "expected": per_voxel_opacity_points(voxel, alpha_range=arange, unit_distance=voxel)}


steps = {}
d_light = simple.Show(light, view)
simple.Render(view)
stars = simple.GetDisplayProperties(simple.OutputPort(light, 1), view)
steps["light"] = facts(d_light)
steps["stars"] = {"representation": stars.SMProxy.GetProperty("Representation").GetElement(0),
                  "color": [str(c) for c in stars.ColorArrayName], "map_scalars": int(stars.MapScalars),
                  "visible": int(stars.Visibility)}
simple.Hide(light, view)

colour = simple.NebulaColour(light)
d_colour = simple.Show(colour, view)
simple.Render(view)
steps["colour"] = facts(d_colour)
colour.AutoOpacity = 0  # the number from now on: 3 times the dust's own opacity (auto: 0.9 here)
colour.OpacityScale = 3.0
simple.Render(view)
steps["opacity_scale_3"] = facts(d_colour)

custom = [0.0, 0.0, 0.5, 0.0, 255.0, 1.0, 0.5, 0.0]
d_colour.ScalarOpacityFunction.Points = custom
simple.Render(view)
colour.OpacityScale = 1.5
simple.Render(view)
steps["user_function"] = facts(d_colour)
steps["user_function"]["custom"] = custom

# the mapping older states hold: per world unit, over 0..255 (no alpha range), 256 points
colour2 = simple.NebulaColour(light, OpacityScale=2.0)
d_old = simple.Show(colour2, view)
simple.Render(view)
d_old.ScalarOpacityFunction.Points = per_voxel_opacity_points(voxel_size(colour2))
behaviour._BEHAVIOUR.fitted.clear()  # as after a state load: nothing known about it
simple.Render(view)
steps["legacy"] = facts(d_old)

_common.result(installed=installed, steps=steps,
               errors=[p.GetClientSideObject().last_error for p in (light, colour, colour2)])
