"""Regression tests of the input validation: every value the device cannot carry (float32,
int32, uint64) and every input that used to fail late is refused before any work, with a
SceneError naming the parameter, the value and the allowed range (nebula_rt.limits).

Most tests trace nothing. The few that do use 8^3 grids and a few thousand packets; their
assertions are exact (bounds that hold for every packet, bit-exact round trips), so no Monte
Carlo tolerance is involved, except the offset-precision test (see its docstring).
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE, centre_star, one_band
from nebula_rt import limits
from nebula_rt.errors import SceneError
from nebula_rt.filters.vti import read_vti, write_vti
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene
from nebula_rt.transport import trace

F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).tiny)


def tiny_scene(**tables) -> Scene:
    """An 8^3 scene with 2000 packets per band; ``stars={...}`` sets keys of its one star."""
    d = {"grid": {"shape": [8, 8, 8]}, "stars": [{}],
         "transport": {"photons": 2000, "backend": TEST_BACKEND, "device": TEST_DEVICE}}
    for k, v in tables.items():
        (d["stars"][0] if k == "stars" else d.setdefault(k, {})).update(v)
    return Scene.from_dict(d)


def image_input(alg, density):
    """Connect ``density`` ((nx, ny, nz) array named "density") as the algorithm's input."""
    from vtkmodules.vtkCommonExecutionModel import vtkTrivialProducer

    from nebula_rt.filters.image_data import to_image_data

    producer = vtkTrivialProducer()
    producer.SetOutput(to_image_data({"density": density}, None, (1, 1, 1)))
    alg.SetInputConnection(producer.GetOutputPort())
    alg._producer = producer  # keep it alive with the algorithm


def pinned_light_field(photons=None):
    """A Nebula Light Field on a uniform 8^3 input, on the test device (``photons`` if given)."""
    from nebula_rt.filters import NebulaLightField

    lf = NebulaLightField()
    image_input(lf, np.ones((8, 8, 8), np.float32))
    lf.SetBackend(TEST_BACKEND)
    lf.SetDevice(TEST_DEVICE)
    if photons is not None:
        lf.SetPhotons(photons)
    return lf


def refused(fn, parameter, *fragments):
    with pytest.raises(SceneError) as info:
        fn()
    err = info.value
    assert err.parameter == parameter, str(err)
    for f in fragments:
        assert f in str(err), str(err)
    return err


def test_limits_are_float32s():
    assert limits.FLOAT32_MAX == F32_MAX and limits.FLOAT32_TINY == F32_TINY
    assert limits.INT32_MAX == np.iinfo(np.int32).max
    assert limits.SEED_LIMIT - 1 == np.iinfo(np.uint64).max


# --- 1. values beyond float32 ----------------------------------------------------------------
@pytest.mark.parametrize("override,parameter", [
    ("dust.tau=1e39", "dust.tau"), ("dust.tau=1e300", "dust.tau"), ("dust.tau=1e-40", "dust.tau"),
    ("stars.0.luminosity=1e308", "stars[0].luminosity"), ("stars.0.luminosity=1e-300", "stars[0].luminosity"),
    ("dust.scale=1e39", "dust.scale"), ("dust.floor=1e39", "dust.floor"), ("dust.density=1e39", "dust.density"),
    ("bands.albedo=1e-40", "bands.albedo"), ("bands.g=-1e-45", "bands.g"), ("stars.0.bump_radius=1e-40", "stars[0].bump_radius"),
    ("colour.exposure=1e39", "colour.exposure"),
])
def test_scene_values_beyond_float32_are_refused(override, parameter):
    value = float(override.split("=", 1)[1])
    bound = limits.fmt(limits.FLOAT32_MAX if abs(value) > 1 else limits.FLOAT32_TINY)
    refused(lambda: tiny_scene().with_overrides([override]), parameter, repr(value), bound)


def test_band_extinction_beyond_float32_is_refused():
    band = {"name": "V", "wavelength": 550.0, "extinction": 1e39, "albedo": 0.5, "g": 0.0}
    refused(lambda: tiny_scene(bands={"list": [band]}), "bands.list[0].extinction", "1e+39", limits.FLOAT32_RANGE_TEXT)


@pytest.mark.parametrize("suffix", [".npy", ".vti"])
@pytest.mark.parametrize("bad,what", [(1e39, "at most 3.4028235e+38"), (1e-40, "at least 1.1754944e-38")])
def test_density_file_beyond_float32_is_refused(tmp_path, backend, suffix, bad, what):
    data = np.ones((8, 8, 8))
    data[3, 4, 5] = bad
    path = tmp_path / f"d{suffix}"
    if suffix == ".npy":
        np.save(path, data)
    else:  # a float64 array: the .vti holds the value as written
        write_vti(path, {"density": data}, {}, (1, 1, 1))
    p = Pipeline(backend)
    scene = tiny_scene(dust={"model": "file", "file": str(path), "floor": 0.0})
    refused(lambda: p.run(scene), "dust.file", str(path), what)
    assert "transport" not in p.executions  # nothing traced


def test_products_beyond_float32_are_refused_before_tracing(backend):
    """tau and the density are each within float32, their product is not."""
    p = Pipeline(backend)
    scene = tiny_scene(dust={"model": "uniform", "density": 1e30, "tau": 1e10},
                       transport={"estimator": "collision-filter"})  # (track-length refuses it earlier)
    err = refused(lambda: p.run(scene), "dust.tau", repr(1e10), "tau x extinction x density")
    # the range given is the one that works: the largest tau allowed runs
    hi = float(str(err).split(", ")[1].split("]")[0])
    assert hi == pytest.approx(F32_MAX / 1e30 / 1.324, rel=1e-6)
    assert "transport" not in p.executions


def test_free_path_below_the_fixed_point_unit_is_refused(backend):
    """tau = 1e30 at density ~1 traced J = 0 everywhere (every flight shorter than one
    fixed-point unit); it is refused for the track-length estimator, which resolves paths in
    units of 1 / (2^32 max(shape)) box units, and allowed for the collision estimator."""
    scene = tiny_scene(dust={"model": "uniform", "density": 1.0, "tau": 1e30}, stars={})
    err = refused(lambda: Pipeline(backend).run(scene), "dust.tau", "1e+30", "collision-filter")
    assert "fixed-point" in str(err)
    coll = scene.with_overrides(['transport.estimator="collision-filter"'])
    light = Pipeline(backend).run(coll, colour=False)
    counts = light.transport.counts
    assert np.all(counts[:, 0] == 2000) and np.all(counts[:, 0] == counts[:, 1:].sum(axis=1))
    assert np.all(np.isfinite(light.J)) and light.J.max() > 0


def test_luminosity_within_float32_whose_J_would_overflow_is_refused(backend):
    p = Pipeline(backend)
    refused(lambda: p.run(tiny_scene().with_overrides(["stars.0.luminosity=1e38"])), "stars[0].luminosity",
            "1e+38", "allowed total luminosity of the stars <=")
    assert "transport" not in p.executions


def test_faint_star_whose_J_would_underflow_is_refused(backend):
    refused(lambda: Pipeline(backend).run(tiny_scene().with_overrides(["stars.0.luminosity=1e-27"])),
            "stars[0].luminosity", "1e-27", "allowed total luminosity of the stars >=")


@pytest.mark.parametrize("estimator", ["track-length", "collision-filter"])
def test_J_and_emissivity_bounds_hold(backend, estimator):
    """The a-priori bounds limits.check_transport uses are bounds: albedo 1 and optical depth
    ~1 per voxel make packets scatter through the star's voxel many times, and still the
    largest J and a sigma J stay below L (M) h / (4 pi V) and a L M min(17, sigma h) / (4 pi V)
    (track-length), L M / (4 pi V sigma) and a L M / (4 pi V) (collision), M = max_scatterings
    + 1. These hold for every packet (no statistics involved)."""
    shape, ms, tau = (8, 8, 8), 40, 8.0
    rho = np.ones(shape, np.float32)
    res = trace(rho, one_band(albedo=1.0, g=0.0), centre_star(), tau=tau, photons=4000, max_scatterings=ms,
                estimator=estimator, backend=backend)
    assert res.counts[0, 3] > 0  # some packets reached max_scatterings
    V = 1.0 / 512
    h = math.sqrt(3) / 8
    M = ms + 1
    J = res.J[0]
    e = 1.0 * tau * rho * J
    if estimator == "track-length":
        assert J.max() <= M * h / (4 * math.pi * V)
        assert e.max() <= M * min(limits.MAX_FLIGHT_TAU, tau * h) / (4 * math.pi * V)
        # and the smallest non-zero J is at least one fixed-point unit
        assert J[J > 0].min() >= res.j_scale[0] * (1 - 1e-12)
    else:
        assert J.max() <= M / (4 * math.pi * V * tau)
        assert e.max() <= M / (4 * math.pi * V)
    # the bound is not absurdly loose for the star's voxel: within 1e3 of what is reached
    assert J.max() * 1e3 > M * h / (4 * math.pi * V) / (tau if estimator != "track-length" else 1.0)


def test_light_field_filter_refuses_tau_beyond_float32():
    lf = pinned_light_field(photons=1000)
    lf.SetTau(1e39)
    lf.Update()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    # named as the panel shows it, then the scene key, the value and what is allowed
    assert lf.last_error.startswith("NebulaLightField: Tau (dust.tau) = 1e+39: ") or "Tau (dust.tau) = 1e+39: " in lf.last_error
    assert limits.FLOAT32_RANGE_TEXT in lf.last_error


def test_light_field_filter_refuses_density_beyond_float32():
    from nebula_rt.filters import NebulaLightField

    rho = np.ones((8, 8, 8))
    rho[1, 1, 1] = 1e39
    lf = NebulaLightField()
    image_input(lf, rho)
    lf.Update()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert "density array" in lf.last_error and "3.4028235e+38" in lf.last_error


def test_offset_limit_is_where_the_float32_turbulence_keeps_its_structure(backend):
    """The limit of dust.offset (limits.MAX_OFFSET) is where the float32 kernel's turbulence
    stays within 1 % (rms, of the density's standard deviation) of the float64 oracle; at 100x
    the limit it is far off (measured 40-50 %), which is why larger offsets are refused. The
    oracle gets the float32-rounded offset, so only the kernel's arithmetic is compared."""
    from oracles import reference_density as ref
    from nebula_rt.backends.base import MODEL_TURBULENCE

    def rms_error(o):
        off = (o, 0.5, -o)
        off32 = tuple(float(np.float32(x)) for x in off)
        got = backend.generate_density((32, 32, 32), MODEL_TURBULENCE, off, 1.0, 0.0, 0.0, np.zeros((0, 4), np.float32), 8)
        want = ref.density_turbulence((32, 32, 32), off32, 1.0, 0.0, [])
        return float(np.sqrt(np.mean((got - want) ** 2)) / np.std(want))

    assert rms_error(limits.MAX_OFFSET) < 0.01
    assert rms_error(100 * limits.MAX_OFFSET) > 0.1
    ok = tiny_scene(dust={"offset": [limits.MAX_OFFSET, -limits.MAX_OFFSET, 0.5]})
    assert ok.dust.offset[0] == limits.MAX_OFFSET
    refused(lambda: tiny_scene(dust={"offset": [1e7, 0.5, 0.5]}), "dust.offset", "[10000000.0, 0.5, 0.5]", "10000")


# --- 2. integers: seed, max_scatterings, batches -------------------------------------------
def test_largest_seed_is_traced_and_written_losslessly(tmp_path, backend):
    from nebula_rt.cli import commands as cli

    seed = 2**53  # the scene's largest: what a double (ParaView's panel, pvpython) holds exactly
    scene = tiny_scene(transport={"seed": seed})
    light = Pipeline(backend).run(scene)
    path = write_vti(tmp_path / "a.vti", light.point_arrays(), light.field_data(), light.spacing, light.origin)
    _, fd, *_ = read_vti(path)
    assert fd["seed"] == seed and isinstance(fd["seed"], int)
    assert Scene.loads(fd["scene"]).transport.seed == seed
    # the XML holds an unsigned 64-bit array, which ParaView's reader (this one) reads as such
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    r = vtkXMLImageDataReader()
    r.SetFileName(str(path))
    r.Update()
    arr = r.GetOutput().GetFieldData().GetAbstractArray("seed")
    assert arr.GetClassName() == "vtkTypeUInt64Array" and arr.GetValue(0) == seed
    assert b'type="UInt64" Name="seed"' in path.read_bytes()
    # and the CLI writes it
    sfile = tmp_path / "s.toml"
    sfile.write_text(scene.to_toml())
    assert cli.main(["render", str(sfile), "-o", str(tmp_path / "b.vti"), "-q"]) == 0
    assert read_vti(tmp_path / "b.vti")[1]["seed"] == seed


def test_largest_seed_through_the_filter():
    from nebula_rt.filters.image_data import field_data_dict

    lf = pinned_light_field(photons=1000)
    lf.SetSeed(float(2**53))  # as ParaView hands it over: a double
    lf.Update()
    assert lf.last_error is None
    assert field_data_dict(lf.GetOutputDataObject(0))["seed"] == 2**53
    lf.SetSeed(2**53 + 1)  # past what a double holds: refused, naming the property
    lf.Update()
    assert "Seed (transport.seed) = 9007199254740993" in lf.last_error and "[0, 2**53]" in lf.last_error


@pytest.mark.parametrize("value", [3e9, 2**31])
def test_max_scatterings_beyond_int32(value):
    refused(lambda: tiny_scene(transport={"max_scatterings": value}), "transport.max_scatterings",
            str(int(value)), "[0, 2147483647]")
    assert tiny_scene(transport={"max_scatterings": 2**31 - 1}).transport.max_scatterings == 2**31 - 1


def test_batch_count_beyond_int32():
    refused(lambda: tiny_scene(transport={"photons": 2**40, "batch_size": 1}), "transport.batch_size",
            "1099511627776 batches", "2147483647")


@pytest.mark.parametrize("bad", [3e9, -1])
def test_filter_refuses_max_scatterings_beyond_int32(bad):
    from nebula_rt.filters import NebulaLightField

    lf = NebulaLightField()
    image_input(lf, np.ones((8, 8, 8), np.float32))
    lf.SetMaxScatterings(bad)
    lf.Update()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert "Max Scatterings (transport.max_scatterings) = " in lf.last_error


# --- 3. filters: any exception is one clean error ------------------------------------------
class _Capture:
    """VTK's output window as a string, for counting the messages an update prints."""

    def __enter__(self):
        from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow

        self._prev = vtkOutputWindow.GetInstance()
        self._verb = vtkLogger.GetCurrentVerbosityCutoff()
        self.window = vtkStringOutputWindow()
        vtkOutputWindow.SetInstance(self.window)
        vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
        return self

    def __exit__(self, *exc):
        from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow

        vtkOutputWindow.SetInstance(self._prev)
        vtkLogger.SetStderrVerbosity(self._verb)
        self.text = self.window.GetOutput()


def test_foreign_exceptions_become_one_error_and_an_empty_output(monkeypatch):
    import pyopencl as cl

    import nebula_rt.filters.light_field as lf_module
    from nebula_rt.filters import NebulaColour

    def failing(*a, **k):
        raise cl.LogicError("create_buffer failed: INVALID_BUFFER_SIZE")

    monkeypatch.setattr(lf_module, "compute_light", failing)
    lf = pinned_light_field()
    c = NebulaColour()
    c.SetInputConnection(lf.GetOutputPort())
    with _Capture() as cap:
        c.Update()
    assert "LogicError" in lf.last_error and "INVALID_BUFFER_SIZE" in lf.last_error
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0 and c.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert c.last_error is None  # the empty input is passed on, not reported again
    assert cap.text.count("NebulaRT error") == 1 and "Traceback" not in cap.text and "ERR" not in cap.text


@pytest.mark.parametrize("shape,fragment", [((16.5, 16, 16), "[16.5, 16, 16]"), ((1e300, 16, 16), "1e+300"),
                                             ((2**31, 8, 8), "2147483648"), (("a", 8, 8), "'a'")])
def test_bad_grid_shape_in_the_density_source(shape, fragment):
    from nebula_rt.filters import NebulaDustDensity

    d = NebulaDustDensity()
    d.SetGridShape(*shape)
    with _Capture() as cap:
        d.Update()
    assert d.GetOutputDataObject(0).GetNumberOfPoints() == 0
    # named as the panel shows it, then the scene key, the value and what is allowed
    assert d.last_error.startswith("NebulaDustDensity: Grid Shape (grid.shape) = ") and fragment in d.last_error
    assert cap.text.count("NebulaRT error") == 1 and "Traceback" not in cap.text


def test_grid_too_large_for_the_device_is_refused_before_allocating(backend):
    p = Pipeline(backend)
    err = refused(lambda: p.run(tiny_scene(grid={"shape": [100000, 100000, 100000]})), "grid.shape",
                  "[100000, 100000, 100000]", "GiB of device memory")
    assert backend.device_name in str(err)


@pytest.mark.parametrize("stars,fragment", [([0.5, 0.5, 0.5, 1.0, float("nan"), 0.0], "temperature"),
                                             ([0.5, 0.5, 0.5, 1.0, -5000.0, 0.0], "temperature"),
                                             ([0.5, 0.5, 0.5, "bright", 0.0, 0.0], "6 numbers per star")])
def test_star_temperature_nan_or_negative_is_an_error_not_a_flat_spectrum(stars, fragment):
    from nebula_rt.filters import NebulaLightField

    lf = NebulaLightField()
    image_input(lf, np.ones((8, 8, 8), np.float32))
    lf.SetStars(stars)
    lf.Update()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert "Stars" in lf.last_error and fragment in lf.last_error


def test_sky_image_refuses_fractional_sizes():
    from nebula_rt.filters import NebulaSkyImage

    s = NebulaSkyImage()
    image_input(s, np.ones((4, 4, 4), np.float32))
    s.SetImageSize(16.5, 16)
    s.Update()
    assert s.GetOutputDataObject(0).GetNumberOfPoints() == 0 and s.last_error.startswith("NebulaSkyImage: Image Size (sky.size) = (16.5, 16)")


# --- 4. weak spots ---------------------------------------------------------------------------
def test_scene_file_missing_folder_unreadable(tmp_path):
    refused(lambda: Scene.load(tmp_path / "none.toml"), "scene file", str(tmp_path / "none.toml"), "no such file")
    refused(lambda: Scene.load(tmp_path), "scene file", str(tmp_path), "it is a folder")
    f = tmp_path / "f.toml"
    f.write_text("")
    refused(lambda: Scene.load(f / "scene.toml"), "scene file", str(f / "scene.toml"), "is a file, not a folder")


def test_scene_file_binary_garbage_and_bad_utf8(tmp_path):
    p = tmp_path / "bin.toml"
    p.write_bytes(b"[grid]\nunit = \"\xff\xfe\"\n")
    refused(lambda: Scene.load(p), "scene file", str(p), "UTF-8", "0xff")
    p.write_bytes(bytes(range(256)) * 4)
    refused(lambda: Scene.load(p), "scene file", str(p), "UTF-8")
    p.write_bytes(b"\x00\x01\x02 = 3")  # valid UTF-8, not TOML
    refused(lambda: Scene.load(p), "(toml)", str(p), "not valid TOML")
    refused(lambda: Scene.loads(b"[grid]"), "(toml)", "bytes")


def test_deeply_nested_toml(tmp_path):
    text = "x = " + "[" * 5000
    refused(lambda: Scene.loads(text), "(toml)", "nested too deeply")
    p = tmp_path / "deep.toml"
    p.write_text(text)
    refused(lambda: Scene.load(p), "(toml)", str(p))
    refused(lambda: Scene.default().with_overrides(["transport.photons=" + "[" * 5000]), "transport.photons")


@pytest.mark.parametrize("spectrum,fragment", [([[100.0, 1.0], [200.0, 1.0]], "380-780 nm"),
                                                ([[900.0, 1.0], [1000.0, 1.0]], "380-780 nm"),
                                                ([[779.5, 1.0], [779.9, 1.0]], "380-780 nm"),
                                                ([[620.0, 1.0], [700.0, 1.0]], "band 'G'")])
def test_star_spectrum_outside_the_bands_is_refused(spectrum, fragment):
    """These failed half-way through a run ("the star's spectrum has no power in the bands'
    range", from the band integration in colour_convert) or left a band without light (the
    colour matrix divides by the band luminosity)."""
    refused(lambda: tiny_scene(stars={"spectrum": spectrum}), "stars[0].spectrum", str(spectrum), fragment)


def test_star_spectrum_lighting_every_band_is_accepted():
    s = tiny_scene(stars={"spectrum": [[420.0, 1.0], [700.0, 1.0]]})
    assert s.stars[0].spectrum[0] == (420.0, 1.0)
    # a second star may light the band the first one misses
    two = Scene.from_dict({"stars": [{"spectrum": [[620.0, 1.0], [700.0, 1.0]]}, {"temperature": 20000.0}]})
    assert len(two.stars) == 2


@pytest.mark.parametrize("t", [10.0, 999.0, 1.1e7, 1e300])
def test_star_temperature_range(t):
    refused(lambda: tiny_scene(stars={"temperature": t}), "stars[0].temperature", repr(t), "[1000, 1e+07]")


def test_batch_size_must_leave_two_batches():
    refused(lambda: tiny_scene(transport={"batch_size": 2000}), "transport.batch_size", "2000",
            "at least 2 batches", "at most 1000", "0 (automatic)")
    assert tiny_scene(transport={"batch_size": 1999}).transport.batch_size == 1999
    assert tiny_scene(transport={"batch_size": 0}).transport.batch_size == 0


def test_density_cache_sees_new_content_with_the_same_mtime(tmp_path, backend):
    path = tmp_path / "d.npy"
    np.save(path, np.ones((8, 8, 8)))
    stamp = path.stat()
    p = Pipeline(backend)
    scene = tiny_scene(dust={"model": "file", "file": str(path), "floor": 0.0})
    assert np.all(p.density(scene) == 1)
    np.save(path, np.full((8, 8, 8), 2.0))
    os.utime(path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))  # the rewrite kept the mtime
    assert path.stat().st_mtime_ns == stamp.st_mtime_ns
    assert np.all(p.density(scene) == 2) and p.executions["density"] == 2
    p.density(scene)  # same content: cached
    assert p.executions["density"] == 2


def test_output_records_the_density_file_absolutely(tmp_path, backend, monkeypatch):
    data = np.random.default_rng(3).uniform(0.5, 2.0, (8, 8, 8))
    (tmp_path / "clouds").mkdir()
    np.save(tmp_path / "clouds" / "d.npy", data)
    sfile = tmp_path / "scene.toml"
    sfile.write_text(tiny_scene(dust={"model": "file", "file": "clouds/d.npy", "floor": 0.0}).to_toml())
    scene = Scene.load(sfile)
    assert scene.dust.file == "clouds/d.npy"
    light = Pipeline(backend).run(scene)
    fd = light.field_data()
    assert fd["dust_file_sha256"] == hashlib.sha256((tmp_path / "clouds" / "d.npy").read_bytes()).hexdigest()
    stored = Scene.loads(fd["scene"])  # no base_dir: loaded elsewhere
    assert Path(stored.dust.file).is_absolute() and Path(stored.dust.file) == (tmp_path / "clouds" / "d.npy").resolve()
    monkeypatch.chdir("/")
    again = Pipeline(backend).run(stored)
    assert again.J.tobytes() == light.J.tobytes()  # the stored scene reproduces the run


def test_generated_density_overflow_names_its_parameter(backend):
    refused(lambda: Pipeline(backend).run(tiny_scene(dust={"scale": 3e38})), "dust.scale", "3e+38", "allowed scale <=")


def test_an_empty_input_is_reported_unless_an_upstream_filter_said_why():
    """An empty image into the Light Field (a reader's or source's empty output) ends with one
    message naming the input; an empty output of a NebulaRT filter that failed upstream is
    passed on quietly (that filter already said why)."""
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkCommonExecutionModel import vtkTrivialProducer

    from nebula_rt.filters import NebulaDustDensity, NebulaLightField

    producer = vtkTrivialProducer()
    producer.SetOutput(vtkImageData())
    lf = NebulaLightField()
    lf.SetInputConnection(producer.GetOutputPort())
    lf.Update()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert lf.last_error.startswith("NebulaLightField: input = 'an empty image (0 points)'")
    dust = NebulaDustDensity()
    dust.SetGridShape(0, 4, 4)
    lf = NebulaLightField()
    lf.SetInputConnection(dust.GetOutputPort())
    lf.Update()
    assert "grid.shape" in dust.last_error and lf.last_error is None
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
