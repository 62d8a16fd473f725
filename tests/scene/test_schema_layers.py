"""One declaration per parameter: every layer shows the scene schema's defaults, ranges and
choices, and the same values give the same bits in ParaView, plain VTK and a scene file.

The schema is the scene dataclasses' field declarations (nebula_rt.scene.parameters); the
layers are the VTK filter's bound setters (nebula_rt.filters.light_field), the ParaView proxy
that ParaView builds from them (tests/paraview/schema_layers.py, under pvpython), the CLI's
choices, and the scene classes' docstrings. The bit comparisons are exact: the same scene,
seed and device give the same integer tallies, so any difference is a defect.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from nebula_rt import scene as sc
from nebula_rt.filters.colour import COLOUR_PROPERTIES, NebulaColour
from nebula_rt.filters.dust_density import DUST_DENSITY_PROPERTIES, NebulaDustDensity
from nebula_rt.filters.light_field import LIGHT_FIELD_PROPERTIES, NebulaLightField
from nebula_rt.scene.values import is_real

from conftest import TEST_DEVICE


def test_every_scene_field_is_declared_with_a_doc():
    import dataclasses

    from nebula_rt.scene import sky_schema

    for section, cls in sc.SECTIONS + sky_schema.SECTIONS:
        for f in dataclasses.fields(cls):
            p = f.metadata.get("param")
            assert p is not None, f"{section}.{f.name} has no declaration"
            assert p.doc.strip(), f"{section}.{f.name}"
            assert f.name in cls.__doc__ and p.doc.split()[0] in cls.__doc__, f"{section}.{f.name} not documented"


def test_the_schema_defaults_are_the_scene_defaults():
    d = sc.Scene.default()
    for key, _, default in sc.parameters():
        table, name = key.split(".")
        obj = d.stars[0] if table == "stars" else getattr(d, table)
        assert getattr(obj, name) == default, key


def test_the_defaults_are_the_thesis_nebula():
    """An empty scene is the 2010 thesis's nebula (sections 3.2.1-3.2.2): tau 128 across the
    box, one star of 20000 K at the centre in its cubic dust bump of half-size 0.01, the
    thesis-rgb bands (R 677, G 550, B 439 nm, extinction 0.748 / 1 / 1.324) with albedo and g
    0.6, smooth turbulence scaled by 0.15 at noise offset 0.5, 2.1 million packets per band.
    The numbers are the thesis's, written here from it, not read from the schema."""
    s = sc.Scene.loads("")
    assert s.dust.model == "turbulence" and s.dust.tau == 128.0
    assert s.dust.scale == 0.15 and tuple(s.dust.offset) == (0.5, 0.5, 0.5)
    (star,) = s.stars
    assert tuple(star.position) == (0.5, 0.5, 0.5) and star.temperature == 20000.0 and star.bump_radius == 0.01
    bands = s.bands.resolve()
    assert [b.name for b in bands] == ["R", "G", "B"]
    assert [b.wavelength for b in bands] == pytest.approx([677.0, 550.0, 439.0])
    assert [b.extinction for b in bands] == pytest.approx([0.748, 1.0, 1.324])
    assert all(b.albedo == pytest.approx(0.6) and b.g == pytest.approx(0.6) for b in bands)
    assert s.transport.effective() == (2_100_000, 0.0)


def test_a_flat_spectrum_is_temperature_0_and_survives_a_round_trip():
    """The default star has a spectrum, so a flat one is written temperature = 0 (None in
    Python); a scene file written from it reads back flat, not as the default 20000 K."""
    s = sc.Scene.loads("[[stars]]\ntemperature = 0\n")
    assert s.stars[0].temperature is None and s.stars[0].spectral_source() is None
    again = sc.Scene.loads(s.to_toml())
    assert again.stars[0].temperature is None
    assert sc.Scene.loads(sc.Scene.loads("").to_toml()).stars[0].temperature == 20000.0
    with pytest.raises(sc.SceneError, match=r"stars\[0\]\.temperature"):
        sc.Scene.loads("[[stars]]\ntemperature = 500\n")


def test_the_readme_scene_block_is_the_defaults():
    """README.md's "Scene files" block says it is exactly the defaults: read as a scene file it
    is the empty scene, and each of its keys is written with the default's own value."""
    import re
    import tomllib
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    section = text[text.index("## Scene files"):]
    block = re.search(r"```toml\n(.*?)```", section, re.S).group(1)
    assert sc.Scene.loads(block) == sc.Scene.loads("")
    defaults = sc.Scene.loads("").to_dict()
    for table, keys in tomllib.loads(block).items():
        for entry in (keys if isinstance(keys, list) else [keys]):
            want = defaults[table][0] if table == "stars" else defaults[table]
            for key, value in entry.items():
                assert key in want and want[key] == value, (table, key, value)


def test_choices_of_the_schema_are_what_the_scene_accepts():
    for key, p, default in sc.parameters():
        if not p.choices:
            continue
        table, name = key.split(".")
        assert default in p.choices, key
        for choice in p.choices:
            try:  # accepted (a choice may need other keys: dust.model = "file" needs dust.file)
                sc.Scene.from_dict({table: {name: choice}})
            except sc.SceneError as exc:
                assert exc.parameter != key, exc
        with pytest.raises(sc.SceneError):
            sc.Scene.from_dict({table: {name: "no-such-choice"}})


#: the grains' keys apply to Mie scattering (refused by name otherwise), n and k come together, and
#: the size distribution is checked whole (the smallest radius at most the largest)
GRAIN_PARTNERS = {"grain_n": {"grain_k": 0.0}, "grain_k": {"grain_n": 1.5},
                  "grain_radius_min": {"grain_radius_max": 1e-4}, "grain_radius_max": {"grain_radius_min": 1e-4}}


def _scene_with(key: str, value):
    table, name = key.split(".")
    if table == "stars":
        return sc.Scene.from_dict({"stars": [{"position": [0.5, 0.5, 0.5], name: value}]})
    if name == "peak_polarization":
        return sc.Scene.from_dict({table: {"polarization": "white", name: value}})
    if name.startswith("grain_"):
        partner = dict(GRAIN_PARTNERS.get(name, {}))
        if name == "grain_radius_min" and is_real(value) and value > 1e-4:
            partner["grain_radius_max"] = value  # (grains of one size)
        return sc.Scene.from_dict({table: {"polarization": "mie", name: value, **partner}})
    return sc.Scene.from_dict({table: {name: value}})


#: bounds a scene refuses for a reason of another key: 2**53 packets per batch exceed the
#: default 2.1M photons (transport.batch_size must be below transport.photons)
OTHER_KEYS = {("transport.batch_size", "hi"),
              # 1 mm grains scatter the thesis bands' light with a size parameter beyond what is traced
              ("bands.grain_radius_min", "hi"), ("bands.grain_radius_max", "hi")}


def test_numeric_bounds_of_the_schema_are_what_the_scene_accepts():
    """The declaration is the validation: for every declared numeric range, the scene accepts a
    closed bound and refuses an open one, and refuses the value just past either bound (the
    next integer, or a relative step of 1e-9), whatever the key (the ranges are written once,
    in the Params, and nothing else checks them)."""
    seen = []
    for key, p, _ in sc.parameters():
        if p.choices or (p.lo is None and p.hi is None):
            continue
        integer = p.type in ("int", "tuple of 3 int")
        vector = p.type.startswith("tuple of 3")
        for side, bound, is_open in (("lo", p.lo, p.lo_open), ("hi", p.hi, p.hi_open)):
            if bound is None or (key, side) in OTHER_KEYS:
                continue
            step = 1 if integer else max(abs(bound) * 1e-9, 1e-9)
            past = bound - step if side == "lo" else bound + step
            wrap = (lambda v: [v, v, v]) if vector else (lambda v: v)
            at_ok = not is_open or (p.off and bound == 0)
            if at_ok:
                _scene_with(key, wrap(bound))
            else:
                with pytest.raises(sc.SceneError):
                    _scene_with(key, wrap(bound))
            with pytest.raises(sc.SceneError) as e:
                _scene_with(key, wrap(past))
            assert key.split(".")[1] in e.value.parameter, (key, e.value.parameter)
            seen.append((key, side))
    assert {("transport.photons", "hi"), ("transport.seed", "hi"), ("observer.ra", "hi"),
            ("transport.target_error", "hi"), ("stars.bump_radius", "hi"), ("grid.shape", "lo")} <= set(seen)
    assert len(seen) >= 35, len(seen)


def test_vtk_filter_defaults_are_the_schema_defaults():
    lf = NebulaLightField()
    for prop in LIGHT_FIELD_PROPERTIES:
        want = sc.default(prop.key)
        if want is None:  # Albedo and G: the default preset's own values, applied only on request
            continue
        assert getattr(lf, "Get" + prop.name)() == want, prop.name
    # an untouched filter traces the scene file's defaults (its density from the input)
    s = lf.scene((8, 8, 8))
    d = sc.Scene.default()
    assert s.transport == d.transport and s.bands == d.bands and s.stars == d.stars
    assert s.dust.tau == d.dust.tau


def test_density_source_defaults_are_the_schema_defaults():
    d = NebulaDustDensity()
    for prop in DUST_DENSITY_PROPERTIES:
        assert getattr(d, "Get" + prop.name)() == sc.default(prop.key), prop.name
        assert set(prop.choices) <= set(prop.param.choices)
    s = d.scene()
    default = sc.Scene.default()
    assert s.grid == default.grid and s.dust == default.dust and s.stars == default.stars


def test_colour_defaults_are_the_schema_defaults():
    """The colour's properties start at the schema's defaults (an "auto or number" key as its
    check box on and the declared number), so an untouched Nebula Colour colours as a scene
    file with no [colour] table; the check box and the number make the key's value."""
    from nebula_rt.filters.properties import scene_values

    c = NebulaColour()
    for prop in COLOUR_PROPERTIES:
        want = sc.default(prop.key)
        if prop.widget == "auto":
            assert getattr(c, "Get" + prop.flag)() == int(want == "auto"), prop.flag
            assert getattr(c, "Get" + prop.name)() == prop.param.number, prop.name
        else:
            assert getattr(c, "Get" + prop.name)() == want, prop.name
    assert sc.Scene.from_dict(scene_values(c._values)).colour == sc.Scene.default().colour
    c.SetWhitePoint(2)
    assert c.GetWhitePoint() == sc.WHITE_POINTS[2]
    c.SetAutoOpacity(0)  # off: the number the panel shows
    assert c._values["colour.opacity_scale"] == 1.0
    c.SetOpacityScale(4.0)
    assert c._values["colour.opacity_scale"] == 4.0
    c.SetAutoOpacity(1)  # on again: "auto", the number kept for later
    assert c._values["colour.opacity_scale"] == "auto" and c.GetOpacityScale() == 4.0


def test_sky_image_defaults_are_the_declared_defaults():
    """Nebula Sky Image's properties are bound to declarations: the camera and the picture's
    stars and exposure to the sky image's own (nebula_rt.scene.sky_schema: one property per
    declaration), the tone curve and the observer to the scene's ([colour], [observer]); each
    starts at its declared default (Auto Exposure on, Exposure the declared number; Distance,
    declared None, empty: the light field's scene's own [observer]), so the untouched filter's
    tone curve and observer are a scene file's defaults. Units is the filter's own (box units).
    The camera they make is the library's default Camera, whose defaults and size range are the
    same declarations."""
    import dataclasses

    from nebula_rt.scene import sky_schema
    from nebula_rt.filters.properties import scene_values
    from nebula_rt.filters.sky_image import SKY_IMAGE_PROPERTIES, SKY_PANEL_DEFAULTS, SKY_UNITS, NebulaSkyImage
    from nebula_rt.observe.sky import Camera

    s = NebulaSkyImage()
    assert s.BOUND_PROPERTIES == SKY_IMAGE_PROPERTIES
    for prop in SKY_IMAGE_PROPERTIES:
        schema = sky_schema if prop.key.startswith("sky.") else sc
        want = schema.default(prop.key)
        assert prop.default == want and prop.param is schema.declaration(prop.key), prop.name
        if prop.widget == "auto":
            assert getattr(s, "Get" + prop.flag)() == int(want == "auto"), prop.flag
            assert getattr(s, "Get" + prop.name)() == prop.param.number, prop.name
        else:
            assert getattr(s, "Get" + prop.name)() == SKY_PANEL_DEFAULTS.get(prop.key, want), prop.name
    keys = [p.key for p in SKY_IMAGE_PROPERTIES]
    assert len(set(keys)) == len(keys)
    # the sky.vector_* keys are Nebula Polarization Vectors' (its own properties, bound the same way)
    from nebula_rt.filters.polarization_vectors import POLARIZATION_VECTOR_PROPERTIES

    vector_keys = {p.key for p in POLARIZATION_VECTOR_PROPERTIES}
    assert {k for k in keys if k.startswith("sky.")} == {k for k, _, _ in sky_schema.parameters()} - vector_keys
    assert vector_keys == {k for k, _, _ in sky_schema.parameters() if k.startswith("sky.vector_")}
    assert {k for k in keys if not k.startswith("sky.")} == {"colour.stretch", "colour.asinh_q"} | {
        k for k, _, _ in sc.parameters() if k.startswith("observer.")}
    # the panel's empty Distance is the scene's None: the rest is a scene file's defaults
    scene_keys = {k: v for k, v in s._values.items() if not k.startswith("sky.") and v != ""}
    d, default = sc.Scene.from_dict(scene_values(scene_keys)), sc.Scene.default()
    assert d.colour == default.colour and d.observer == default.observer
    assert s.GetUnits() == SKY_UNITS[0]
    assert s._camera() == Camera()
    for f in dataclasses.fields(Camera):
        if f"sky.{f.name}" in keys:
            assert f.default == sky_schema.default(f"sky.{f.name}"), f.name
    size = sky_schema.declaration("sky.size")
    Camera(size=(size.lo, size.hi))  # the declared bounds are accepted, and just past them refused
    for bad in ((size.lo - 1, 4), (4, size.hi + 1)):
        with pytest.raises(ValueError, match="Camera.size"):
            Camera(size=bad)
    # and nebula-rt's --size (sky, compare, fit) has the same range: one range in every layer
    from nebula_rt.cli.commands import check_size

    for ok in (size.lo, size.hi):
        check_size(ok)
    for bad in (size.lo - 1, size.hi + 1):
        with pytest.raises(sc.SceneError, match=rf"\[{size.lo}, {size.hi}\]") as e:
            check_size(bad)
        assert e.value.parameter == "--size"


def test_sky_image_messages_name_the_panel_label_and_the_key():
    """A bad value of any of Nebula Sky Image's bound properties, whichever declares it (the
    sky image's own camera and exposure, the scene's tone curve and observer), ends the run
    with an empty output and ``<Label> (<key>) = <value>: <allowed>``; Units, the filter's own,
    is named as it is. The checks come before the ray march, so a bare 2^3 image serves as
    the input."""
    from vtkmodules.vtkCommonExecutionModel import vtkTrivialProducer

    from nebula_rt.filters.image_data import to_image_data
    from nebula_rt.filters.sky_image import NebulaSkyImage

    cases = [
        (("SetImageSize", 0, 4), "Image Size (sky.size) = (0, 4): "),
        (("SetExtent", -1.0), "Extent (sky.extent) = -1.0: "),
        (("SetAutoExposure", 0), ("SetExposure", -2.0), "Exposure (sky.exposure) = -2.0: "),
        (("SetStretch", "log"), "Stretch (colour.stretch) = 'log': "),
        (("SetStretch", 1), ("SetAsinhQ", 0.0), "Asinh Q (colour.asinh_q) = 0.0: "),
        (("SetDistance", "3 s"), "Distance (observer.distance) = '3 s': "),
        (("SetDec", 90.5), "Dec (observer.dec) = 90.5: "),
        (("SetPSFFWHM", -1.0), "PSF FWHM (observer.psf_fwhm) = -1.0: "),
        (("SetUnits", "Jy"), "Units = 'Jy': must be one of 'box units', 'MJy/sr'"),
    ]
    producer = vtkTrivialProducer()
    producer.SetOutput(to_image_data({"density": np.ones((2, 2, 2), np.float32)}, None, (1, 1, 1)))
    for *calls, message in cases:
        s = NebulaSkyImage()
        s.SetInputConnection(producer.GetOutputPort())
        for name, *args in calls:
            getattr(s, name)(*args)
        s.Update()
        assert s.GetOutputDataObject(0).GetNumberOfPoints() == 0, message
        assert s.last_error is not None and s.last_error.startswith("NebulaSkyImage: " + message), s.last_error


def test_vtk_setters_take_enumeration_indices_and_whole_floats():
    lf = NebulaLightField()
    lf.SetEstimator(1)
    lf.SetQuality(2)
    lf.SetPhotons(1e5)
    s = lf.scene((8, 8, 8))
    assert s.transport.estimator == sc.ESTIMATORS[1] and s.transport.quality == sc.QUALITIES[2]
    assert s.transport.photons == 100_000 and isinstance(s.transport.photons, int)
    lf.SetQuality("custom")  # the panel's text of ""
    assert lf.scene((8, 8, 8)).transport.quality == ""


def test_cli_choices_are_the_schema_choices():
    from nebula_rt.cli import build_parser

    parser = build_parser()
    render = next(a for a in parser._subparsers._group_actions[0].choices.values() if a.prog.endswith("render"))
    opts = {a.dest: a for a in render._actions}
    assert tuple(opts["backend"].choices) == sc.BACKENDS
    assert tuple(opts["quality"].choices) == sc.QUALITIES[1:]


def make_density_files(d):
    """A random density (above the floor everywhere) as .npy and as .vti with the same values."""
    from nebula_rt.filters.vti import write_vti

    rng = np.random.default_rng(11)
    rho = (0.2 + rng.random((12, 10, 9))).astype(np.float32)
    np.save(d / "rho.npy", rho)
    write_vti(d / "rho.vti", {"density": rho}, None, (1.0, 1.0, 1.0))
    return d / "rho.npy", d / "rho.vti", rho


@pytest.fixture(scope="module")
def density_file(tmp_path_factory):
    return make_density_files(tmp_path_factory.mktemp("density"))


PHOTONS = 4000


def _hashes(arrays: dict) -> dict:
    return {k: hashlib.sha256(np.ascontiguousarray(v, np.float32).tobytes()).hexdigest() for k, v in arrays.items()}


def _vtk_run(vti):
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    from nebula_rt.filters.image_data import point_array

    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(vti))
    lf = NebulaLightField()
    lf.SetInputConnection(reader.GetOutputPort())
    lf.SetPhotons(PHOTONS)
    lf.SetDevice(TEST_DEVICE)
    lf.Update()
    assert lf.last_error is None, lf.last_error
    out = lf.GetOutputDataObject(0)
    names = [out.GetPointData().GetArrayName(i) for i in range(out.GetPointData().GetNumberOfArrays())]
    return {n: point_array(out, n) for n in names if n.startswith("J_")}


def _scene_file_run(npy, rho):
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline

    scene = sc.Scene.from_dict({"grid": {"shape": list(rho.shape)}, "dust": {"model": "file", "file": str(npy)},
                                "transport": {"photons": PHOTONS, "device": TEST_DEVICE}})
    light = Pipeline(get_backend(scene.transport.backend, TEST_DEVICE)).run(scene, colour=False)
    return {f"J_{b.name}": light.J[i] for i, b in enumerate(light.bands)}


def test_plain_vtk_and_scene_file_give_the_same_bits(density_file):
    npy, vti, rho = density_file
    assert _hashes(_vtk_run(vti)) == _hashes(_scene_file_run(npy, rho))


def test_schema_ranges_are_closed_numbers_or_none():
    for key, p, _ in sc.parameters():
        for b in (p.lo, p.hi):
            assert b is None or (isinstance(b, (int, float)) and math.isfinite(b)), key


def test_integer_ranges_are_what_a_panel_holds_exactly():
    """An integer past int32 travels as a double (ParaView's panel, pvpython, JSON), exact up to
    2^53: every integer parameter's declared range stays within it, so no layer rounds a value
    the scene accepts (the seed's 2^64 - 1 became 2^64 in a panel). The last integer of the
    range survives the trip through a double and the next one does not."""
    for key, p, _ in sc.parameters():
        if p.type.startswith("int") or p.type.endswith("int"):
            assert p.lo is not None and p.hi is not None, key
            assert -2**53 <= p.lo and p.hi <= 2**53, key
            assert int(float(p.hi)) == p.hi
    seed = sc.declaration("transport.seed")
    assert int(float(seed.hi + 1)) != seed.hi + 1  # 2^53 + 1: what a double cannot hold
    lf = NebulaLightField()
    lf.SetSeed(float(seed.hi))  # as the panel hands it over
    assert lf.scene((4, 4, 4)).transport.seed == 2**53
