"""Tests of the scene model (nebula_rt.scene) and band definitions (nebula_rt.optics.bands)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from nebula_rt.optics.bands import PRESETS, Band, reference_band_index, resolve_bands
from nebula_rt.errors import SceneError
from nebula_rt.scene import BandsConfig, Colour, Dust, Grid, Star, Transport
from nebula_rt.scene import Scene

NAN = float("nan")
INF = float("inf")


def _scene_dict(table, key, value):
    """A minimal scene dict with one key set (``stars.0.x`` style for stars)."""
    if table == "stars":
        return {"stars": [{key: value}]}
    return {table: {key: value}}


# ---------------------------------------------------------------------------
# round trip, defaults
# ---------------------------------------------------------------------------


def test_default_round_trip():
    s = Scene.default()
    text = s.to_toml()
    assert Scene.loads(text) == s
    assert Scene.from_dict(s.to_dict()) == s


def test_default_values_match_contract():
    s = Scene.default()
    assert s.grid == Grid((64, 64, 64), 1.0, "pc")
    assert s.dust.model == "turbulence" and s.dust.tau == 128.0 and s.dust.floor == 1e-4
    assert s.stars == [Star((0.5, 0.5, 0.5), 1.0, 20000.0, 0.01)]
    assert s.bands.preset == "thesis-rgb"
    assert s.transport.photons == 2_100_000 and s.transport.estimator == "track-length"
    assert s.colour == Colour("auto", "D65", "auto")


def test_empty_dict_is_default():
    assert Scene.from_dict({}) == Scene.default()
    assert Scene.loads("") == Scene.default()


def test_full_round_trip_non_default():
    s = Scene.default().with_overrides(
        [
            "grid.shape=[16, 8, 4]",
            "grid.length=3.5",
            "dust.model=file",
            "dust.file=cloud.npy",
            "stars.0.temperature=20000",
            "stars.0.bump_radius=0.01",
            "bands.g=0.2",
            "transport.estimator=collision-filter",
            "transport.seed=9007199254740992",
            "colour.exposure=1.5",
            "colour.white_point=star",
        ]
    )
    assert Scene.loads(s.to_toml()) == s
    assert s.stars[0].temperature == 20000.0
    assert s.transport.seed == 2**53


def test_contract_example_file_loads(tmp_path: Path):
    text = """
[grid]
shape = [64, 64, 32]
length = 1.0
unit = "pc"

[dust]
model = "file"
density = 1.0
file = "cloud.npy"
array = "density"
scale = 0.15
offset = [0.5, 0.5, 0.5]
floor = 1.0e-4
tau = 1.0

[[stars]]
position = [0.5, 0.5, 0.5]
luminosity = 1.0
temperature = 20000.0
bump_radius = 0.01

[[stars]]
position = [0.1, 0.2, 0.3]
luminosity = 2

[bands]
preset = "thesis-rgb"
albedo = 0.6
g = 0.6

[transport]
photons = 2_100_000
estimator = "track-length"
filter_radius = 0.02
max_scatterings = 1000
seed = 1
backend = "auto"
device = ""
"""
    p = tmp_path / "scene.toml"
    p.write_text(text)
    s = Scene.load(p)
    assert s.grid.shape == (64, 64, 32)
    assert len(s.stars) == 2 and s.stars[1].luminosity == 2.0
    assert isinstance(s.stars[1].luminosity, float)
    assert s.stars[1].temperature == 20000.0  # the default star's
    assert s.base_dir == tmp_path.absolute()
    assert s.dust_file_path() == tmp_path.absolute() / "cloud.npy"
    assert Scene.loads(s.to_toml()) == s  # base_dir is not compared


def test_dust_file_path_absolute_and_without_base_dir(tmp_path: Path):
    s = Scene.from_dict({"dust": {"model": "file", "file": "a/b.vti"}})
    assert s.dust_file_path() == Path("a/b.vti")
    s = Scene.from_dict({"dust": {"model": "file", "file": str(tmp_path / "x.npy")}}, base_dir="/nowhere")
    assert s.dust_file_path() == tmp_path / "x.npy"
    with pytest.raises(SceneError):
        Scene.default().dust_file_path()


def test_integer_floats_and_int_floats_are_coerced():
    s = Scene.from_dict(
        {"transport": {"photons": 1e6, "seed": 7.0}, "grid": {"shape": [8.0, 8, 4], "length": 2}}
    )
    assert s.transport.photons == 1_000_000 and type(s.transport.photons) is int
    assert type(s.transport.seed) is int
    assert s.grid.shape == (8, 8, 4) and all(type(n) is int for n in s.grid.shape)
    assert s.grid.length == 2.0 and type(s.grid.length) is float


def test_invalid_toml_raises_scene_error():
    with pytest.raises(SceneError):
        Scene.loads("[grid\nshape = 3")


# ---------------------------------------------------------------------------
# bad values
# ---------------------------------------------------------------------------

BAD_VALUES = [
    # (table, key, value, parameter)
    ("grid", "shape", [1, 64, 64], "grid.shape"),
    ("grid", "shape", [64, 64, 0], "grid.shape"),
    ("grid", "shape", [64, 64, 2.5], "grid.shape"),
    ("grid", "shape", [64, 64], "grid.shape"),
    ("grid", "shape", [64, 64, 64, 64], "grid.shape"),
    ("grid", "shape", 64, "grid.shape"),
    ("grid", "length", 0.0, "grid.length"),
    ("grid", "length", -1.0, "grid.length"),
    ("grid", "length", INF, "grid.length"),
    ("grid", "length", NAN, "grid.length"),
    ("grid", "unit", 3, "grid.unit"),
    ("dust", "model", "fractal", "dust.model"),
    ("dust", "density", -0.5, "dust.density"),
    ("dust", "density", NAN, "dust.density"),
    ("dust", "density", INF, "dust.density"),
    ("dust", "density", "thick", "dust.density"),
    ("dust", "floor", -1e-4, "dust.floor"),
    ("dust", "floor", NAN, "dust.floor"),
    ("dust", "floor", INF, "dust.floor"),
    ("dust", "tau", -1.0, "dust.tau"),
    ("dust", "tau", NAN, "dust.tau"),
    ("dust", "tau", INF, "dust.tau"),
    ("dust", "scale", -0.1, "dust.scale"),
    ("dust", "scale", NAN, "dust.scale"),
    ("dust", "scale", INF, "dust.scale"),
    ("dust", "offset", [0.5, NAN, 0.5], "dust.offset"),
    ("dust", "offset", [0.5, 0.5, INF], "dust.offset"),
    ("dust", "offset", [0.5, 0.5], "dust.offset"),
    ("stars", "position", [1.5, 0.5, 0.5], "stars[0].position"),
    ("stars", "position", [0.5, -0.1, 0.5], "stars[0].position"),
    ("stars", "position", [0.5, 0.5, NAN], "stars[0].position"),
    ("stars", "position", [0.5, 0.5, INF], "stars[0].position"),
    ("stars", "position", [0.5, 0.5], "stars[0].position"),
    ("stars", "luminosity", 0.0, "stars[0].luminosity"),
    ("stars", "luminosity", -2.0, "stars[0].luminosity"),
    ("stars", "luminosity", INF, "stars[0].luminosity"),
    ("stars", "luminosity", NAN, "stars[0].luminosity"),
    ("stars", "temperature", 500.0, "stars[0].temperature"),
    ("stars", "temperature", -5000.0, "stars[0].temperature"),
    ("stars", "temperature", NAN, "stars[0].temperature"),
    ("stars", "bump_radius", -0.01, "stars[0].bump_radius"),
    ("stars", "bump_radius", 1.0, "stars[0].bump_radius"),
    ("stars", "bump_radius", NAN, "stars[0].bump_radius"),
    ("bands", "albedo", 1.5, "bands.albedo"),
    ("bands", "albedo", -0.1, "bands.albedo"),
    ("bands", "albedo", NAN, "bands.albedo"),
    ("bands", "g", 1.01, "bands.g"),
    ("bands", "g", -1.5, "bands.g"),
    ("bands", "g", NAN, "bands.g"),
    ("bands", "preset", "thesis-rgbx", "bands.preset"),
    ("transport", "photons", 0, "transport.photons"),
    ("transport", "photons", -10, "transport.photons"),
    ("transport", "photons", 2**53 + 1, "transport.photons"),
    ("transport", "photons", 1.5, "transport.photons"),
    ("transport", "photons", "many", "transport.photons"),
    ("transport", "photons", True, "transport.photons"),
    ("transport", "estimator", "path-length", "transport.estimator"),
    ("transport", "filter_radius", 0.0, "transport.filter_radius"),
    ("transport", "filter_radius", -0.02, "transport.filter_radius"),
    ("transport", "filter_radius", INF, "transport.filter_radius"),
    ("transport", "filter_radius", NAN, "transport.filter_radius"),
    ("transport", "max_scatterings", -1, "transport.max_scatterings"),
    ("transport", "seed", -1, "transport.seed"),
    ("transport", "seed", 2**53 + 1, "transport.seed"),
    ("transport", "seed", 2**64, "transport.seed"),
    ("transport", "backend", "metal", "transport.backend"),
    ("transport", "batch_size", -1, "transport.batch_size"),
    ("transport", "device", 0, "transport.device"),
    ("colour", "exposure", "bright", "colour.exposure"),
    ("colour", "exposure", 0.0, "colour.exposure"),
    ("colour", "exposure", -1.0, "colour.exposure"),
    ("colour", "exposure", INF, "colour.exposure"),
    ("colour", "exposure", NAN, "colour.exposure"),
    ("colour", "white_point", "D50", "colour.white_point"),
    ("colour", "opacity_scale", 0.0, "colour.opacity_scale"),
    ("colour", "opacity_scale", -1.0, "colour.opacity_scale"),
]


@pytest.mark.parametrize("table,key,value,parameter", BAD_VALUES)
def test_bad_value_raises(table, key, value, parameter):
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict(_scene_dict(table, key, value))
    err = exc_info.value
    assert err.parameter == parameter
    assert repr(value) in str(err) or str(value) in str(err)
    assert err.allowed and err.allowed in str(err)


@pytest.mark.parametrize(
    "parameter,value,expected",
    [
        ("transport.photons", 0, "must be an integer"),
        ("transport.estimator", "x", "one of: 'track-length', 'collision-filter'"),
        ("bands.g", 2.0, "must be a number in [-1, 1]"),
        ("bands.albedo", 2.0, "must be a number in [0, 1]"),
        ("transport.backend", "x", "one of: 'auto', 'opencl', 'cuda'"),
        ("dust.model", "x", "one of: 'turbulence', 'uniform', 'file'"),
    ],
)
def test_messages_say_what_is_allowed(parameter, value, expected):
    table, key = parameter.split(".")
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict(_scene_dict(table, key, value))
    assert expected in str(exc_info.value)


def test_file_model_needs_file():
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"dust": {"model": "file"}})
    assert exc_info.value.parameter == "dust.file"


def test_no_stars_rejected():
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"stars": []})
    assert exc_info.value.parameter == "stars"


def test_second_star_is_named_by_index():
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"stars": [{}, {"luminosity": -1.0}]})
    assert exc_info.value.parameter == "stars[1].luminosity"


def test_validate_catches_direct_construction():
    s = Scene(transport=Transport(photons=0))
    with pytest.raises(SceneError) as exc_info:
        s.validate()
    assert exc_info.value.parameter == "transport.photons"
    with pytest.raises(SceneError) as exc_info:
        Scene(stars=[]).validate()
    assert exc_info.value.parameter == "stars"
    with pytest.raises(SceneError) as exc_info:
        Scene(grid=Grid(shape=("a", 2, 2))).validate()
    assert exc_info.value.parameter == "grid.shape"
    Scene(dust=Dust(model="uniform"), stars=[Star(), Star((0.0, 1.0, 0.0))]).validate()


# ---------------------------------------------------------------------------
# unknown keys and tables
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "d,parameter,allowed_word",
    [
        ({"transport": {"photon": 5}}, "transport.photon", "'photons'"),
        ({"grid": {"size": [4, 4, 4]}}, "grid.size", "'shape'"),
        ({"stars": [{"lum": 1.0}]}, "stars[0].lum", "'luminosity'"),
        ({"bands": {"presets": "thesis-rgb"}}, "bands.presets", "'preset'"),
        ({"color": {}}, "color", "[colour]"),
        ({"bands": {"list": [{"name": "a", "wavelength": 500, "extinction": 1, "albedo": 0.5, "g": 0, "x": 1}]}},
         "bands.list[0].x", "'extinction'"),
    ],
)
def test_unknown_key_rejected(d, parameter, allowed_word):
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict(d)
    assert exc_info.value.parameter == parameter
    assert allowed_word in str(exc_info.value)


def test_wrong_table_types_rejected():
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"grid": 3})
    assert exc_info.value.parameter == "grid"
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"stars": {"luminosity": 1.0}})
    assert exc_info.value.parameter == "stars"


# ---------------------------------------------------------------------------
# overrides
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "item,getter,expected",
    [
        ("transport.photons=1e6", lambda s: s.transport.photons, 1_000_000),
        ("transport.photons = 500", lambda s: s.transport.photons, 500),
        ("grid.shape=[32,32,16]", lambda s: s.grid.shape, (32, 32, 16)),
        ("stars.0.luminosity=2", lambda s: s.stars[0].luminosity, 2.0),
        ("stars[0].position=[0.25, 0.5, 0.75]", lambda s: s.stars[0].position, (0.25, 0.5, 0.75)),
        ("transport.backend=opencl", lambda s: s.transport.backend, "opencl"),
        ('transport.backend="cuda"', lambda s: s.transport.backend, "cuda"),
        ("transport.device=", lambda s: s.transport.device, ""),
        ("transport.device=0:1", lambda s: s.transport.device, "0:1"),
        ("bands.albedo=0.3", lambda s: [b.albedo for b in s.bands.resolve()], [0.3] * 3),
        ("bands.g=-0.2", lambda s: [b.g for b in s.bands.resolve()], [-0.2] * 3),
        ("colour.exposure=auto", lambda s: s.colour.exposure, "auto"),
        ("colour.exposure=2", lambda s: s.colour.exposure, 2.0),
        ("dust.model=uniform", lambda s: s.dust.model, "uniform"),
        ("transport.batch_size=65536", lambda s: s.transport.batch_size, 65536),
    ],
)
def test_override(item, getter, expected):
    base = Scene.default()
    s = base.with_overrides([item])
    assert getter(s) == expected
    assert base == Scene.default()  # unchanged


def test_overrides_apply_in_order_and_return_new_scene():
    base = Scene.default()
    s = base.with_overrides(["transport.photons=10", "transport.photons=20"])
    assert s.transport.photons == 20 and s is not base
    assert Scene.loads(s.to_toml()) == s


def test_override_bands_list_and_preset():
    s = Scene.default().with_overrides(
        ['bands.list=[{name="V", wavelength=550, extinction=1, albedo=0.5, g=0.4}]']
    )
    assert s.bands.preset is None
    assert s.bands.resolve() == [Band("V", 550.0, 1.0, 0.5, 0.4)]
    s2 = s.with_overrides(["bands.list.0.g=0.1"])
    assert s2.bands.resolve()[0].g == 0.1
    s3 = s.with_overrides(["bands.preset=thesis-rgb"])
    assert s3.bands.list is None and len(s3.bands.resolve()) == 3


@pytest.mark.parametrize(
    "item,parameter",
    [
        ("transport.photon=5", "transport.photon"),
        ("transprt.photons=5", "transprt.photons"),
        ("stars.1.luminosity=2", "stars.1.luminosity"),
        ("stars.x.luminosity=2", "stars.x.luminosity"),
        ("grid.shape.0=4", "grid.shape.0"),
        ("grid", "grid"),
        ("=3", ""),
        ("transport.photons=0", "transport.photons"),
        ("transport.photons=1e6x", "transport.photons"),
        ("grid.shape=[32,32,1]", "grid.shape"),
        ("stars.0.position=[2,0,0]", "stars[0].position"),
        ("transport.backend=metal", "transport.backend"),
        ("bands.preset=nope", "bands.preset"),
    ],
)
def test_bad_override(item, parameter):
    with pytest.raises(SceneError) as exc_info:
        Scene.default().with_overrides([item])
    assert exc_info.value.parameter == parameter


# ---------------------------------------------------------------------------
# bands
# ---------------------------------------------------------------------------


def test_thesis_preset():
    bands = PRESETS["thesis-rgb"]
    assert [b.name for b in bands] == ["R", "G", "B"]
    assert [b.wavelength for b in bands] == [677.0, 550.0, 439.0]
    assert [b.extinction for b in bands] == [0.748, 1.0, 1.324]
    assert all(b.albedo == 0.6 and b.g == 0.6 for b in bands)
    assert reference_band_index(bands) == 1
    assert Scene.default().bands.resolve() == bands


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_resolves(preset):
    bands = resolve_bands(preset, None, None, None)
    assert 1 <= len(bands) <= 32
    assert len({b.name for b in bands}) == len(bands)
    assert 0 <= reference_band_index(bands) < len(bands)


def test_preset_overrides():
    bands = resolve_bands("thesis-rgb", None, 0.2, -0.3)
    assert all(b.albedo == 0.2 and b.g == -0.3 for b in bands)
    assert PRESETS["thesis-rgb"][0].albedo == 0.6  # preset not modified


def test_reference_band_index_ties_and_order():
    mk = lambda e: Band("x", 500.0, e, 0.5, 0.0)  # noqa: E731
    assert reference_band_index([mk(0.5), mk(1.5), mk(1.2)]) == 2
    assert reference_band_index([mk(0.9), mk(1.1)]) == 0
    assert reference_band_index([mk(3.0)]) == 0


def test_bands_list_scene_resolves():
    text = """
[bands]
preset = "thesis-rgb"
g = 0.1

[[bands.list]]
name = "u"
wavelength = 365
extinction = 1.5
albedo = 0.4

[[bands.list]]
name = "V_band"
wavelength = 551.0
extinction = 1.0
albedo = 0.5
g = 0.9
"""
    s = Scene.loads(text)
    assert s.bands.preset is None  # preset ignored when a list is given
    assert s.bands.resolve() == [
        Band("u", 365.0, 1.5, 0.4, 0.1),
        Band("V_band", 551.0, 1.0, 0.5, 0.1),
    ]
    assert reference_band_index(s.bands.resolve()) == 1
    assert Scene.loads(s.to_toml()) == s


def test_bands_config_list_clears_preset():
    cfg = BandsConfig(list=[{"name": "a", "wavelength": 500.0, "extinction": 1.0, "albedo": 0.5, "g": 0.0}])
    assert cfg.preset is None
    assert cfg.resolve()[0].name == "a"


def _entry(**kw):
    e = {"name": "a", "wavelength": 500.0, "extinction": 1.0, "albedo": 0.5, "g": 0.0}
    e.update(kw)
    return e


@pytest.mark.parametrize(
    "band_list,parameter",
    [
        ([], "bands.list"),
        ([_entry(name=f"b{i}") for i in range(33)], "bands.list"),
        ([_entry(), _entry()], "bands.list[1].name"),
        ([_entry(name="")], "bands.list[0].name"),
        ([_entry(name="J R")], "bands.list[0].name"),
        ([_entry(name="a.b")], "bands.list[0].name"),
        ([_entry(albedo=1.1)], "bands.list[0].albedo"),
        ([_entry(albedo=NAN)], "bands.list[0].albedo"),
        ([_entry(g=-1.1)], "bands.list[0].g"),
        ([_entry(g=NAN)], "bands.list[0].g"),
        ([_entry(extinction=0.0)], "bands.list[0].extinction"),
        ([_entry(extinction=-1.0)], "bands.list[0].extinction"),
        ([_entry(extinction=INF)], "bands.list[0].extinction"),
        ([_entry(extinction=NAN)], "bands.list[0].extinction"),
        ([_entry(), _entry(name="b", wavelength=0.0)], "bands.list[1].wavelength"),
        ([_entry(wavelength=-500.0)], "bands.list[0].wavelength"),
        ([_entry(wavelength=1.5e5)], "bands.list[0].wavelength"),
        ([_entry(wavelength=NAN)], "bands.list[0].wavelength"),
        ([{"name": "a", "wavelength": 500.0, "albedo": 0.5, "g": 0.0}], "bands.list[0].extinction"),
    ],
)
def test_bad_band_list(band_list, parameter):
    with pytest.raises(SceneError) as exc_info:
        resolve_bands(None, band_list, None, None)
    assert exc_info.value.parameter == parameter
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"bands": {"list": band_list}})
    assert exc_info.value.parameter == parameter


def test_band_list_wavelength_upper_bound_inclusive():
    assert resolve_bands(None, [_entry(wavelength=1e5)], None, None)[0].wavelength == 1e5
    assert len(resolve_bands(None, [_entry(name=f"b{i}") for i in range(32)], None, None)) == 32


def test_unknown_preset_lists_presets():
    with pytest.raises(SceneError) as exc_info:
        resolve_bands("rgb", None, None, None)
    err = exc_info.value
    assert err.parameter == "bands.preset" and "'rgb'" in str(err) and "thesis-rgb" in err.allowed


def test_nan_is_reported_as_nan():
    with pytest.raises(SceneError) as exc_info:
        Scene.from_dict({"dust": {"tau": NAN}})
    assert "nan" in str(exc_info.value)
    assert math.isnan(exc_info.value.value)
