"""Bad property values: a clear error, an empty output, and pvpython carries on.

    pvpython bad_input.py

Sequence on a 16^3 nebula: Photons 0 (error), Photons 20000 (valid), G 1.5 with Override
Optics (error), G 0.6 (valid). RESULT: per step the output's points, the arrays, last_error.
The errors themselves go to ParaView's output window (stderr), which the test reads.
"""

import sys

import _common
from paraview import simple
from nebula_rt_paraview.view import load_plugin

load_plugin()
dust = simple.NebulaDustDensity(GridShape=[16, 16, 16], Device=_common.TEST_DEVICE)
light = simple.NebulaLightField(dust, Photons=0, Device=_common.TEST_DEVICE)
light.DensityArray = ["POINTS", "density"]
colour = simple.NebulaColour(light)
alg = light.GetClientSideObject()


def step(label):
    sys.stderr.write(f"--- step {label}\n")
    sys.stderr.flush()
    summary = _common.output_summary(colour)
    light_points = int(light.GetDataInformation().GetNumberOfPoints())
    sys.stderr.flush()
    return {"label": label, "light_points": light_points, "colour_points": summary["points"],
            "arrays": sorted(summary["arrays"]), "last_error": alg.last_error,
            "executions": alg.execution_count}


steps = [step("photons-0")]
light.Photons = 20000
steps.append(step("photons-20000"))
light.OverrideOptics = 1
light.G = 1.5
steps.append(step("g-1.5"))
light.G = 0.6
steps.append(step("g-0.6"))
_common.result(steps=steps)
