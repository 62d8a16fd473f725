"""The output contract (nebula_rt.pipeline.output_contract) is what the writers write and the readers
read: names, stored types and values, through real .vti files and the VTK algorithms.

Every comparison is exact: the storage is lossless (float64 stays float64, the integers are
64-bit), so a value that comes back different is a defect, not noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.pipeline import output_contract as contract
from nebula_rt.errors import SceneError
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene

ONE_BAND = 'bands.list=[{name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6}]'


def _light(*overrides):
    scene = Scene.load("examples/scenes/thesis-default.toml").with_overrides(
        ["grid.shape=[6,5,4]", "transport.photons=3000", f'transport.device="{TEST_DEVICE}"',
         f'transport.backend="{TEST_BACKEND}"', *overrides])
    return Pipeline().run(scene)


@pytest.fixture(scope="module", params=["three bands", "one band"])
def light(request):
    return _light() if request.param == "three bands" else _light(ONE_BAND)


def _expected_keys(cls, bands, present):
    """The table's names for these bands; optional entries only where ``present`` says."""
    keys = []
    for name, spec in contract.field_specs(cls).items():
        if spec.optional and not present(name):
            continue
        keys += spec.keys(bands)
    return keys


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.asarray(a).shape == np.asarray(b).shape and np.array_equal(a, b, equal_nan=True)
    return a == b or (a != a and b != b)  # NaN (achieved_error of a fixed-photon run)


def test_the_run_writes_exactly_the_table(light):
    """LightField.field_data() has the table's names for the run's bands, no others, with the
    declared Python types; the per-band energies obey emitted = absorbed + escaped +
    terminated bit for bit."""
    fd = light.field_data()
    bands = [b.name for b in light.bands]
    # optional: the device peak (measured here), the analog run's packet counts and the method
    # (present); the biased transport's biasing energy (absent)
    assert sorted(fd) == sorted(_expected_keys(
        contract.LightFieldData, bands, lambda n: n in ("device_memory_peak_bytes", "packets", "transport_method", "error_estimate")))
    # band names: a list of str, one per band (a string array with one value per band in VTK)
    py = {"float64": float, "int64": int, "uint64": np.uint64, "str": str, "names": list}
    for spec in contract.field_specs(contract.LightFieldData).values():
        for key in spec.keys(bands):
            if spec.optional and key not in fd:
                continue
            want = np.ndarray if spec.array else py[spec.dtype]
            assert type(fd[key]) is want, (key, type(fd[key]), want)
            if spec.array:
                assert fd[key].dtype == np.float64 and fd[key].shape == (len(bands),)
    for b in bands:
        assert fd[f"emitted_{b}"] == fd[f"absorbed_{b}"] + fd[f"escaped_{b}"] + fd[f"terminated_{b}"]
    assert fd["band_names"] == bands
    # per-band fractions as arrays in band order, from the packet counts
    for i, b in enumerate(bands):
        assert fd["escaped_fraction"][i] == fd[f"packets_escaped_{b}"] / fd[f"packets_emitted_{b}"]
        assert fd["absorbed_fraction"][i] == fd[f"packets_absorbed_{b}"] / fd[f"packets_emitted_{b}"]


def test_a_vti_file_stores_the_declared_types_and_reads_back_the_record(light, tmp_path):
    """Through a real .vti: each field-data array has the declared VTK type (float64 ->
    Float64, int64 -> Int64, uint64 -> UInt64, str/names -> a string array), each point array
    the declared dtype and components; read back and decoded by the contract, the record equals
    the one written, field by field (the one-band run's per-band arrays stay arrays)."""
    pytest.importorskip("pyvista")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    from nebula_rt.filters.vti import read_vti, write_vti

    path = write_vti(tmp_path / "run.vti", light.point_arrays(), light.field_data(), light.spacing, light.origin)
    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    img = reader.GetOutput()
    bands = [b.name for b in light.bands]
    fd_vtk = img.GetFieldData()
    vtk_kind = {"float64": ("f", 8), "int64": ("i", 8), "uint64": ("u", 8)}
    for name, spec in contract.field_specs(contract.LightFieldData).items():
        for key in spec.keys(bands):
            arr = fd_vtk.GetAbstractArray(key)
            if arr is None:
                assert spec.optional, key
                continue
            if spec.dtype in ("str", "names"):
                n = len(bands) if spec.dtype == "names" else 1
                assert arr.IsA("vtkStringArray") and arr.GetNumberOfValues() == n, key
                continue
            values = vtk_to_numpy(arr)
            assert (values.dtype.kind, values.dtype.itemsize) == vtk_kind[spec.dtype], (key, values.dtype)
            assert values.shape == ((len(bands),) if spec.array else (1,)), (key, values.shape)
    pd = img.GetPointData()
    for spec in contract.LIGHT_FIELD_ARRAYS:
        for key in [spec.name(b) for b in bands] if "{band}" in spec.key else [spec.name()]:
            arr = pd.GetArray(key)
            if arr is None:
                assert spec in (contract.RGBA, contract.RGB_LINEAR), key  # colour: not every run
                continue
            assert vtk_to_numpy(arr).dtype == np.dtype(spec.dtype), key
            assert arr.GetNumberOfComponents() == spec.components, key

    _arrays, fd, *_ = read_vti(path)
    back = contract.LightFieldData.from_field_data(fd)
    written = light.record()
    for name, spec in contract.field_specs(contract.LightFieldData).items():
        want = getattr(written, name)
        if want is None:  # an optional field this run does not write
            assert spec.optional and getattr(back, name) is None, name
            continue
        if spec.array or spec.per_band:  # the record was given lists and the transport's arrays
            want = np.asarray(want)
        assert _same(getattr(back, name), want), name
    assert back.band_names == tuple(bands) and back.band_luminosity.shape == (len(bands),)


def test_readers_name_what_is_missing():
    """A reader that needs fields the input lacks is told which (a SceneError on the input,
    per-band names with <band>); asking for a field the table does not have is a defect."""
    fd = {"band_names": "R,G", "tau": 2.0, "emitted_R": 1.0}
    data = contract.LightFieldData.from_field_data(fd, need=("band_names", "tau"))
    assert data.band_names == ("R", "G") and data.tau == 2.0 and data.energy is None
    with pytest.raises(SceneError) as err:
        contract.LightFieldData.from_field_data(fd, need=("tau", "energy", "band_wavelength_nm"))
    assert err.value.parameter == "input"
    assert "Nebula Light Field" in str(err.value)
    assert "<tally>_<band>" in str(err.value)
    assert "band_wavelength_nm" in str(err.value) and "tau" not in str(err.value).split("missing")[1]
    with pytest.raises(ValueError, match="no field"):
        contract.LightFieldData.from_field_data(fd, need=("band_name",))


@pytest.mark.parametrize("ref", [-1, 2, 2**40])
def test_a_reference_band_outside_the_bands_is_refused(ref):
    """A crafted reference band (an index the Colour filter and the sky image use to pick a
    band's arrays) is refused as the input's, naming the index and the bands' range, instead
    of an IndexError further down."""
    fd = {"band_names": "R,G", "tau": 2.0, "reference_band": ref}
    with pytest.raises(SceneError, match=rf"reference_band = {ref}'?: must be a band index in \[0, 1\]") as e:
        contract.LightFieldData.from_field_data(fd, need=("band_names",))
    assert e.value.parameter == "input"
    assert contract.LightFieldData.from_field_data({**fd, "reference_band": 1}).reference_band == 1


def test_writers_must_give_the_whole_contract():
    """A record missing a required field is refused when the whole contract is written (a
    filter adding one field writes a partial one on purpose); per-band values must match the
    bands; an int64 field outside int64 and a seed outside uint64 are refused."""
    with pytest.raises(ValueError, match="no value for") as err:
        contract.LightFieldData(exposure=1.0).to_field_data()
    assert "band_names" in str(err.value) and "dust_file_sha256" not in str(err.value)
    assert contract.LightFieldData(exposure=2.0).to_field_data(complete=False) == {"exposure": 2.0}
    with pytest.raises(ValueError, match="3 values for 2"):
        contract.LightFieldData(band_names=("R", "G"), terminated_bias=[0.0, 0.1, 0.2]).to_field_data(complete=False)
    with pytest.raises(OverflowError):
        contract.LightFieldData(photons=2**63).to_field_data(complete=False)
    with pytest.raises(OverflowError):
        contract.LightFieldData(seed=2**64).to_field_data(complete=False)
    top = contract.LightFieldData(seed=2**64 - 1).to_field_data(complete=False)["seed"]
    assert type(top) is np.uint64 and int(top) == 2**64 - 1


def test_the_vtk_algorithms_write_the_same_contract():
    """Nebula Light Field's output field data has exactly the table's names (as the CLI's file
    has, exposure included: its rgba is the scene's default colour), Nebula Colour adds only
    rgb_linear and replaces rgba and exposure, and Nebula Sky Image adds the SkyImageData table
    to the light field's."""
    from nebula_rt.filters import NebulaColour, NebulaDustDensity, NebulaLightField, NebulaSkyImage
    from nebula_rt.filters.image_data import field_data_dict

    d = NebulaDustDensity()
    d.SetGridShape(8, 8, 8)
    d.SetDevice(TEST_DEVICE)
    d.SetBackend(TEST_BACKEND)
    lf = NebulaLightField()
    lf.SetInputConnection(d.GetOutputPort())
    lf.SetPhotons(2000)
    lf.SetDevice(TEST_DEVICE)
    lf.SetBackend(TEST_BACKEND)
    c = NebulaColour()
    c.SetInputConnection(lf.GetOutputPort())
    sky = NebulaSkyImage()
    sky.SetInputConnection(lf.GetOutputPort())
    sky.SetImageSize(8, 8)
    c.Update()
    sky.Update()
    assert lf.last_error is None and c.last_error is None and sky.last_error is None
    bands = list(lf.last_light.scene.bands.resolve())
    names = [b.name for b in bands]
    lf_fd = field_data_dict(lf.GetOutputDataObject(0))
    assert sorted(lf_fd) == sorted(_expected_keys(
        contract.LightFieldData, names, lambda n: n in ("device_memory_peak_bytes", "packets", "transport_method", "error_estimate")))
    c_out = c.GetOutputDataObject(0)
    c_fd = field_data_dict(c_out)
    assert sorted(c_fd) == sorted(lf_fd) and c_fd["exposure"] > 0 and lf_fd["exposure"] > 0
    pd = c_out.GetPointData()
    lf_pd = lf.GetOutputDataObject(0).GetPointData()
    lf_names = {lf_pd.GetArrayName(i) for i in range(lf_pd.GetNumberOfArrays())}
    assert contract.RGBA.name() in lf_names
    added = {pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())} - lf_names
    assert added == {contract.RGB_LINEAR.name()}
    # the Stars port: the contract's star arrays
    st = lf.GetOutputDataObject(1).GetPointData()
    assert {st.GetArrayName(i) for i in range(st.GetNumberOfArrays())} == {a.name() for a in contract.STAR_ARRAYS}
    # the executive passes the input's field data on; the sky image's own replace same names
    sky_fd = field_data_dict(sky.GetOutputDataObject(0))
    # optional: the star's optical depth (there is a star) and the method (always written; absent
    # from images made before it was); the calibrated image's entries only with Units "MJy/sr"
    # (tests/observe/test_calibrate.py), the polarization convention only for a polarized peel-off
    # (tests/filters/test_polarization_filters.py)
    own = _expected_keys(contract.SkyImageData, names, lambda n: n in ("tau_star", "sky_method"))
    assert sorted(sky_fd) == sorted(set(own) | set(lf_fd))
    sky_data = contract.SkyImageData.from_field_data(sky_fd, need=("view_direction", "tau_star"))
    np.testing.assert_array_equal(sky_data.view_direction, [0.0, 0.0, -1.0])
    assert sky_data.tau_star.shape == (len(names),) and np.all(sky_data.tau_star > 0)
