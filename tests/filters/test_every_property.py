"""Every property of every NebulaRT algorithm changes the output, or says why it does not.

A property that a script can set but that changes nothing without a word is a trap (Albedo
without OverrideOptics did exactly that). For each algorithm of the pipeline (plain VTK, the
same classes ParaView's proxies subclass) every bound property and every property of the
algorithm's own is set to another valid value on a fresh pipeline: the output (its point
arrays and field data, less what names the run: the scene text, timings, memory) must differ
from the unchanged pipeline's, or the execution must warn naming the property (a property
greyed out in the panel, ``filters.properties.inert_properties``), or the property is one of
UNCHANGED below, each with the reason its effect does not show on this small run.

Alternative values come from the scene schema's declaration (another choice, the other flag, a
number inside the declared range), so a new property is walked without editing this file.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from conftest import TEST_DEVICE
from nebula_rt.filters import NebulaColour, NebulaDustDensity, NebulaLightField, NebulaSkyImage

#: property -> why setting it to another valid value leaves this run's output as it was
UNCHANGED = {
    "Backend": "the same kernels on the same device give the same bits (auto finds the OpenCL device)",
    "Device": "one device here: another selector of it gives the same bits",
    "TimeLimit": "a limit this run of 5,000 packets does not reach",
    "MaxScatterings": "a bound no packet of this optically thin run reaches",
    "BoxLength": "the light field is in box units: the length goes into the output's scene (field data "
                 "'scene'), from which the calibrated sky image downstream takes it",
    "OverrideOptics": "the panel's Albedo and G are the default preset's own (every thesis-rgb band has "
                      "albedo 0.6 and g 0.6): overriding them with themselves changes nothing",
    "GrainMaterial": "one material is shipped (astronomical-silicate): there is no other to choose",
}
#: values whose valid range depends on other properties (PHOTONS), or that are text
SPECIFIC = {"BatchSize": 1000, "Distance": "140 pc", "BoxLength": "1 pc", "Offset": (0.5, 0.25, 0.0),
            "ParticleMass": "m", "ParticleSmoothing": "h",
            # (a tabulated matrix needs its file: GrainMatrix's own case)
            "Polarization": "mie",
            "GrainMatrix": str(Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "pinte2009"
                               / "mueller_matrix_1um.dat")}
#: field data that names the run rather than its result
VOLATILE = {"scene", "device_memory_peak_bytes", "device", "timings"}
PHOTONS = 5000


def _pipeline():
    dust = NebulaDustDensity()
    dust.SetGridShape(8, 8, 8)
    dust.SetDevice(TEST_DEVICE)
    light = NebulaLightField()
    light.SetInputConnection(dust.GetOutputPort())
    light.SetDevice(TEST_DEVICE)
    light.SetPhotons(PHOTONS)
    colour = NebulaColour()
    colour.SetInputConnection(light.GetOutputPort())
    sky = NebulaSkyImage()
    sky.SetInputConnection(light.GetOutputPort())
    sky.SetImageSize(16, 16)
    return {"NebulaDustDensity": dust, "NebulaLightField": light, "NebulaColour": colour, "NebulaSkyImage": sky}


def _digest(alg) -> str:
    alg.Update()
    out = alg.GetOutputDataObject(0)
    h = hashlib.sha256()
    for data in (out.GetPointData(), out.GetFieldData()):
        for i in range(data.GetNumberOfArrays()):
            arr = data.GetAbstractArray(i)
            name = arr.GetName()
            if name in VOLATILE or name.startswith("timing"):
                continue
            h.update(name.encode())
            if arr.IsA("vtkDataArray"):
                h.update(np.ascontiguousarray(vtk_to_numpy(arr)).tobytes())
            else:
                h.update("\n".join(arr.GetValue(k) for k in range(arr.GetNumberOfValues())).encode())
    h.update(repr(out.GetDimensions() if hasattr(out, "GetDimensions") else None).encode())
    return h.hexdigest()


def _other_value(prop):
    """Another valid value of a bound property, from its declaration."""
    if prop.name in SPECIFIC:
        return SPECIFIC[prop.name]
    p, d = prop.param, prop.default
    if prop.choices:
        others = [c for c in prop.choices if c != d and c != ""]
        return others[-1]
    if p.type == "bool":
        return not d
    if isinstance(d, (tuple, list)):
        if all(isinstance(x, float) for x in d):  # a direction: another one (a scaled one is the same)
            return tuple(d[1:]) + (d[0],)
        return tuple(x + 2 for x in d)
    if p.type == "str":
        return "1 pc" if prop.key == "grid.length" else None
    lo = p.lo if p.lo is not None and math.isfinite(p.lo) else -1e3
    hi = p.hi if p.hi is not None and math.isfinite(p.hi) else 1e3
    number = d if isinstance(d, (int, float)) and not isinstance(d, bool) else p.number
    if number is None:  # omitted by default (bands.albedo: each band's own)
        return (lo + hi) / 2
    for v in (number * 0.5, number * 2, (lo + hi) / 2, number + 1, lo, hi):
        if p.type == "int":
            v = int(round(v))
        if lo <= v <= hi and v != number and not (getattr(p, "lo_open", False) and v == lo) \
                and not (getattr(p, "hi_open", False) and v == hi):
            return v
    raise AssertionError(f"no other value for {prop.name}")


def _cases():
    algs = _pipeline()
    cases = []
    for name, alg in algs.items():
        for prop in alg.BOUND_PROPERTIES:
            cases.append((name, prop.name, "bound"))
    cases += [("NebulaLightField", own, "own") for own in
              ("OverrideOptics", "StarsFromInput", "Stars", "LuminosityUnit", "SpectralTypes", "SpectralCalibration")]
    cases += [("NebulaColour", "AutoExposure", "own"), ("NebulaColour", "AutoOpacity", "own"),
              ("NebulaSkyImage", "AutoExposure", "own"), ("NebulaSkyImage", "Units", "own"),
              ("NebulaDustDensity", "Stars", "own")]
    return cases


OWN_VALUES = {
    ("NebulaLightField", "OverrideOptics"): 1,  # with Albedo and G at the panel's values: the bands' own differ
    ("NebulaLightField", "GrainMaterial"): "astronomical-silicate",
    ("NebulaLightField", "StarsFromInput"): 0,  # the Stars property's star (a luminosity of 1 here too) ...
    ("NebulaLightField", "Stars"): [0.3, 0.5, 0.5, 1.0, 0.0, 0.0],
    ("NebulaLightField", "LuminosityUnit"): 1,
    ("NebulaLightField", "SpectralTypes"): "B2V",
    ("NebulaLightField", "SpectralCalibration"): "de-jager-1987",  # (with SpectralTypes B2V against B2V alone)
    ("NebulaColour", "AutoExposure"): 0,
    ("NebulaColour", "AutoOpacity"): 0,
    ("NebulaSkyImage", "AutoExposure"): 0,
    ("NebulaSkyImage", "Units"): 1,
    ("NebulaDustDensity", "Stars"): [0.3, 0.5, 0.5, 1.0, 0.0, 0.05],
}


@pytest.fixture(scope="module")
def baseline():
    algs = _pipeline()
    return {name: _digest(alg) for name, alg in algs.items()}


@pytest.mark.parametrize("alg_name,prop_name,kind", _cases(), ids=lambda v: str(v))
def test_a_changed_property_changes_the_output_or_says_why(baseline, alg_name, prop_name, kind):
    algs = _pipeline()
    alg = algs[alg_name]
    if prop_name in UNCHANGED:
        if (alg_name, prop_name) in OWN_VALUES:
            getattr(alg, "Set" + prop_name)(OWN_VALUES[(alg_name, prop_name)])
        elif prop_name not in ("Device", "Backend"):
            getattr(alg, "Set" + prop_name)(_other_value(next(p for p in alg.BOUND_PROPERTIES if p.name == prop_name)))
        assert _digest(alg) == baseline[alg_name] and alg.last_error is None  # as the reason says
        return
    if kind == "bound":
        prop = next(p for p in alg.BOUND_PROPERTIES if p.name == prop_name)
        value = _other_value(prop)
        setter = getattr(alg, "Set" + prop_name)
        setter(*value) if isinstance(value, tuple) else setter(value)
    else:
        getattr(alg, "Set" + prop_name)(OWN_VALUES[(alg_name, prop_name)])
    if alg_name == "NebulaLightField" and prop_name == "StarsFromInput":
        alg.SetStars([0.3, 0.5, 0.5, 1.0, 0.0, 0.0])  # ... placed elsewhere than the density's
    if (alg_name, prop_name) == ("NebulaLightField", "LuminosityUnit"):
        algs["NebulaDustDensity"].SetStars([0.5, 0.5, 0.5, 1.0, 10000.0, 0.0])  # L_sun needs a blackbody
        baseline_of = _pipeline()
        baseline_of["NebulaDustDensity"].SetStars([0.5, 0.5, 0.5, 1.0, 10000.0, 0.0])
        baseline = {alg_name: _digest(baseline_of[alg_name])}
    if (alg_name, prop_name) == ("NebulaLightField", "SpectralCalibration"):
        alg.SetSpectralTypes("B2V")  # Pecaut & Mamajek's 20600 K against de Jager's 19737 K
        baseline_of = _pipeline()
        baseline_of[alg_name].SetSpectralTypes("B2V")
        baseline = {alg_name: _digest(baseline_of[alg_name])}
    if (alg_name, prop_name) == ("NebulaSkyImage", "Units"):
        # MJy/sr: the box placed on the sky, its star in physical units
        algs["NebulaDustDensity"].SetStars([0.5, 0.5, 0.5, 100.0, 10000.0, 0.0])
        algs["NebulaLightField"].SetLuminosityUnit(1)
        alg.SetDistance("140 pc")
    changed = _digest(alg) != baseline[alg_name]
    said = [w for w in alg.last_warnings if prop_name in w]
    assert alg.last_error is None, alg.last_error
    assert changed or said, f"{alg_name}.{prop_name}: the output did not change and nothing said why"


@pytest.mark.parametrize("empty", ["", None])
def test_an_empty_distance_is_no_setting(empty):
    """ParaView's panel sends Distance "" (its empty text box) where the algorithm starts from
    None: setting it so, or back, is no change, so no property is reported as set to no
    effect (the default pipeline's sky image once warned "Distance = None has no effect")."""
    from nebula_rt.filters.properties import inert_properties

    sky = NebulaSkyImage()
    sky.SetDistance(empty)
    sky.SetDistance("" if empty is None else None)
    assert inert_properties(sky) == [] and sky.inert_messages() == []


def test_a_spectral_calibration_without_spectral_types_says_it_sets_nothing():
    """SpectralCalibration chooses how SpectralTypes set temperatures: with none given it
    changes nothing, and the execution's warnings say so by name; with a type, no warning."""
    algs = _pipeline()
    light = algs["NebulaLightField"]
    light.SetSpectralCalibration(2)  # (by index: de-jager-1987)
    before = _digest(light)
    assert any("SpectralCalibration = 'de-jager-1987' has no effect" in w for w in light.last_warnings), \
        light.last_warnings
    assert before == _digest(_pipeline()["NebulaLightField"])
    light.SetSpectralTypes("B7V")
    _digest(light)
    assert light.last_error is None and not [w for w in light.last_warnings if "SpectralCalibration" in w]
