"""The VTK algorithms of nebula_rt.filters in plain VTK and pyvista (no ParaView)."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.vtkCommonDataModel import vtkDataObject

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.filters import NebulaColour, NebulaDustDensity, NebulaLightField
from nebula_rt.filters.image_data import field_data_dict, point_array, to_image_data
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene


def chain(shape=(16, 12, 10), photons=5000):
    d = NebulaDustDensity()
    d.SetGridShape(*shape)
    d.SetDevice(TEST_DEVICE)
    d.SetBackend(TEST_BACKEND)
    lf = NebulaLightField()
    lf.SetInputConnection(d.GetOutputPort())
    lf.SetPhotons(photons)
    lf.SetTau(50.0)
    lf.SetDevice(TEST_DEVICE)
    lf.SetBackend(TEST_BACKEND)  # the same (cached) backend object as the fixture
    c = NebulaColour()
    c.SetInputConnection(lf.GetOutputPort())
    return d, lf, c


def counts(*algs):
    return tuple(a.execution_count for a in algs)


def test_chain_produces_the_output_contract():
    d, lf, c = chain()
    c.Update()
    out = c.GetOutputDataObject(0)
    assert out.GetDimensions() == (16, 12, 10)
    assert out.GetSpacing() == pytest.approx((1 / 16, 1 / 12, 1 / 10))
    assert out.GetOrigin() == pytest.approx((0.5 / 16, 0.5 / 12, 0.5 / 10))
    names = {out.GetPointData().GetArrayName(i) for i in range(out.GetPointData().GetNumberOfArrays())}
    assert names == {"density", "rgba", "rgb_linear"} | {f"{p}_{b}" for p in ("J", "emissivity", "rel_error") for b in "RGB"}
    fd = field_data_dict(out)
    for b in "RGB":
        assert fd[f"emitted_{b}"] == fd[f"absorbed_{b}"] + fd[f"escaped_{b}"] + fd[f"terminated_{b}"]
    rgba = point_array(out, "rgba")
    assert rgba.dtype == np.uint8 and rgba.shape == (16, 12, 10, 4)
    assert d.last_error is None and lf.last_error is None and c.last_error is None


def test_filters_match_the_library_pipeline():
    """Same scene through the VTK algorithms and through Pipeline: identical bits."""
    d, lf, c = chain()
    c.Update()
    out = c.GetOutputDataObject(0)
    scene = Scene.from_dict({
        "grid": {"shape": [16, 12, 10]},
        "dust": {"tau": 50.0},
        # the filters' untouched properties are the scene's defaults (one star at the centre)
        "transport": {"photons": 5000, "device": TEST_DEVICE},
    })
    light = Pipeline().run(scene)
    np.testing.assert_array_equal(point_array(out, "density"), light.density)
    np.testing.assert_array_equal(point_array(out, "J_B"), light.J[2])
    np.testing.assert_array_equal(point_array(out, "rgba"), light.rgba)
    # the light field carries the colour of the scene's defaults: the command line's rgba
    np.testing.assert_array_equal(point_array(lf.GetOutputDataObject(0), "rgba"), light.rgba)
    assert field_data_dict(lf.GetOutputDataObject(0))["exposure"] == light.exposure


def test_only_changed_stages_reexecute():
    d, lf, c = chain()
    c.Update()
    assert counts(d, lf, c) == (1, 1, 1)
    c.Update()
    assert counts(d, lf, c) == (1, 1, 1)
    lf_exposure = field_data_dict(lf.GetOutputDataObject(0))["exposure"]
    lf_rgba = point_array(lf.GetOutputDataObject(0), "rgba")
    c.SetAutoExposure(False)
    c.SetExposure(3.0)
    c.Update()  # colour change: no re-trace
    assert counts(d, lf, c) == (1, 1, 2)
    assert field_data_dict(c.GetOutputDataObject(0))["exposure"] == 3.0
    # the colour filter's field data and arrays are its own: the light field's are untouched
    assert field_data_dict(lf.GetOutputDataObject(0))["exposure"] == lf_exposure > 0
    np.testing.assert_array_equal(point_array(lf.GetOutputDataObject(0), "rgba"), lf_rgba)
    lf.SetAlbedo(0.3)
    c.Update()  # albedo change: re-trace, no new density
    assert counts(d, lf, c) == (1, 2, 3)
    d.SetOffset(1.5, 0.5, 0.5)
    c.Update()
    assert counts(d, lf, c) == (2, 3, 4)


def test_bad_input_gives_a_clear_error_and_no_output():
    d, lf, c = chain()
    lf.SetPhotons(0)
    c.Update()
    assert "transport.photons" in lf.last_error and "0" in lf.last_error
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert c.GetOutputDataObject(0).GetNumberOfPoints() == 0
    lf.SetPhotons(2000)  # and the pipeline recovers
    c.Update()
    assert lf.last_error is None and c.GetOutputDataObject(0).GetNumberOfPoints() == 16 * 12 * 10
    lf.SetOverrideOptics(True)
    lf.SetG(1.5)
    c.Update()
    assert "bands.g" in lf.last_error


def test_user_density_array_point_and_cell_data():
    """Bring your own density: a named point array, or cell data (voxels = cells)."""
    rng = np.random.default_rng(3)
    rho = rng.uniform(0, 0.2, size=(10, 8, 6)).astype(np.float32)
    img = to_image_data({"my_rho": rho, "other": rho * 2}, {}, spacing=(2.0, 2.0, 2.0), origin=(-5, -4, -3))
    lf = NebulaLightField()
    lf.SetInputDataObject(0, img)
    lf.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_POINTS, "my_rho")
    lf.SetPhotons(3000)
    lf.SetDevice(TEST_DEVICE)
    lf.Update()
    out = lf.GetOutputDataObject(0)
    assert lf.last_error is None
    assert out.GetDimensions() == (10, 8, 6) and out.GetSpacing() == (2.0, 2.0, 2.0)
    assert out.GetPointData().HasArray("my_rho") and out.GetPointData().HasArray("J_G")
    assert not out.GetPointData().HasArray("density")
    # cell data: an image of 11x9x7 points has 10x8x6 cells
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkCommonDataModel import vtkImageData

    cimg = vtkImageData()
    cimg.SetDimensions(11, 9, 7)
    arr = numpy_support.numpy_to_vtk(np.ravel(rho, order="F"), deep=True)
    arr.SetName("rho_cells")
    cimg.GetCellData().AddArray(arr)
    lf2 = NebulaLightField()
    lf2.SetInputDataObject(0, cimg)
    lf2.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_CELLS, "rho_cells")
    lf2.SetPhotons(3000)
    lf2.SetDevice(TEST_DEVICE)
    lf2.Update()
    out2 = lf2.GetOutputDataObject(0)
    assert lf2.last_error is None, lf2.last_error
    assert out2.GetDimensions() == (10, 8, 6)
    np.testing.assert_array_equal(point_array(out, "J_G"), point_array(out2, "J_G"))
    # a missing array is named
    lf.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_POINTS, "nope")
    lf.Update()
    assert "nope" in lf.last_error and lf.GetOutputDataObject(0).GetNumberOfPoints() == 0


def test_stars_output_marks_each_star_in_world_coordinates():
    """Port 1 of Nebula Light Field: one vertex per star where the star is in port 0's world
    coordinates (the box [0, 1]^3 is the voxels' outer faces: origin - spacing/2 to
    origin + (n - 1/2) spacing), its luminosity, and its own colour at full brightness: a
    20 000 K star blue-white (B > R), a 3000 K one red (R > B), the largest component 255."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    rho = np.full((10, 5, 4), 0.01, np.float32)
    img = to_image_data({"density": rho}, {}, spacing=(2.0, 2.0, 2.0), origin=(10.0, 0.0, 0.0))
    lf = NebulaLightField()
    lf.SetInputDataObject(0, img)
    lf.SetStars(0.25, 0.5, 0.75, 1.0, 20000.0, 0.0, 0.5, 0.5, 0.5, 0.5, 3000.0, 0.0)
    lf.SetPhotons(2000)
    lf.SetDevice(TEST_DEVICE)
    lf.Update()
    assert lf.last_error is None, lf.last_error
    assert lf.GetNumberOfOutputPorts() == 3  # the light field, the stars, the light per leaf (adaptive inputs)
    stars = lf.GetOutputDataObject(1)
    assert stars.GetClassName() == "vtkPolyData"
    assert stars.GetNumberOfPoints() == 2 and stars.GetNumberOfVerts() == 2
    xyz = vtk_to_numpy(stars.GetPoints().GetData())
    # x: [9, 29], y: [-1, 9], z: [-1, 7]
    np.testing.assert_allclose(xyz, [[9 + 0.25 * 20, -1 + 0.5 * 10, -1 + 0.75 * 8], [19.0, 4.0, 3.0]], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(vtk_to_numpy(stars.GetPointData().GetArray("luminosity")), [1.0, 0.5])
    rgb = vtk_to_numpy(stars.GetPointData().GetArray("star_rgb")).astype(int)
    assert rgb.shape == (2, 3) and list(rgb.max(axis=1)) == [255, 255]
    assert rgb[0, 2] > rgb[0, 0] and rgb[1, 0] > rgb[1, 2], rgb
    # a failed trace empties both ports
    lf.SetPhotons(0)
    lf.Update()
    assert lf.last_error and lf.GetOutputDataObject(1).GetNumberOfPoints() == 0


def test_progress_and_abort_between_batches(backend, monkeypatch):
    monkeypatch.setattr(backend, "launch_packets", 6000)  # one batch per launch
    d, lf, c = chain(photons=32_000)
    seen = []

    def on_progress(obj, event):
        seen.append(obj.GetProgress())
        if len(seen) == 3:
            obj.SetAbortExecute(1)

    lf.AddObserver("ProgressEvent", on_progress)
    lf.Update()
    assert "cancelled" in lf.last_error
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    # stopped after a few of the 16 batches (the executive adds a final 1.0 when it finishes)
    traced = [p for p in seen if p < 1.0]
    assert 0 < max(traced) < 0.5 and len(seen) <= 5


def test_pyvista_wraps_the_output():
    import pyvista as pv

    d, lf, c = chain()
    c.Update()
    mesh = pv.wrap(c.GetOutputDataObject(0))
    assert isinstance(mesh, pv.ImageData)
    assert mesh["rgba"].shape == (16 * 12 * 10, 4) and mesh["J_R"].dtype == np.float32


def test_sky_image_filter():
    """The sky image of a light field: per-band intensities, the star's attenuation, colour;
    changing the view re-runs only the sky image."""
    from nebula_rt.filters import NebulaSkyImage

    d, lf, c = chain(shape=(16, 16, 16))
    sky = NebulaSkyImage()
    sky.SetInputConnection(lf.GetOutputPort())
    sky.SetImageSize(40, 30)
    sky.Update()
    assert sky.last_error is None, sky.last_error
    out = sky.GetOutputDataObject(0)
    assert out.GetDimensions() == (40, 30, 1)
    fd = field_data_dict(out)
    I_B, I_R = point_array(out, "I_B")[:, :, 0], point_array(out, "I_R")[:, :, 0]
    assert np.all(np.isfinite(I_B)) and I_B.sum() > 0
    rel_B = point_array(out, "relative_B")[:, :, 0]
    L_B = np.atleast_1d(fd["band_luminosity"])[2]
    np.testing.assert_allclose(rel_B, I_B * 4 * np.pi / L_B, rtol=1e-6)
    # blue is extinguished more on the way from the star to the observer
    assert fd["tau_star_B"] > fd["tau_star_R"] > 0
    assert fd["tau_star_B"] / fd["tau_star_R"] == pytest.approx(1.324 / 0.748, rel=1e-6)
    rgb = point_array(out, "rgb")
    assert rgb.dtype == np.uint8 and rgb.shape == (40, 30, 1, 3) and rgb.max() > 0
    n = sky.execution_count
    sky.SetViewDirection(1.0, 0.0, 0.0)
    sky.SetViewUp(0.0, 0.0, 1.0)
    sky.Update()
    assert sky.execution_count == n + 1 and lf.execution_count == 1
    sky.SetImageSize(0, 10)
    sky.Update()
    assert "size" in sky.last_error.lower() and sky.GetOutputDataObject(0).GetNumberOfPoints() == 0


def test_light_field_takes_the_density_sources_stars():
    """Stars entered once: the density source passes its stars on in the field data, and the
    light field traces them (unless told to use its own); a .vti-like input without stars
    uses the light field's own Stars."""
    from nebula_rt.filters.image_data import field_data_dict

    d, lf, c = chain()
    two = [0.3, 0.5, 0.5, 1.0, 0.0, 0.02, 0.7, 0.4, 0.6, 2.0, 6000.0, 0.01]
    d.SetStars(two)
    lf.SetStars([0.5, 0.5, 0.5, 1.0, 0.0, 0.0])
    lf.Update()
    assert lf.last_error is None, lf.last_error
    np.testing.assert_array_equal(field_data_dict(d.GetOutputDataObject(0))["stars"], two)
    s = lf.scene((16, 12, 10))
    assert [list(st.position) for st in s.stars] == [[0.3, 0.5, 0.5], [0.7, 0.4, 0.6]]
    assert s.stars[1].temperature == 6000.0 and s.stars[1].luminosity == 2.0
    lf.SetStarsFromInput(False)
    lf.Update()
    assert [list(st.position) for st in lf.scene((16, 12, 10)).stars] == [[0.5, 0.5, 0.5]]


def test_an_unchosen_density_array_is_named_in_the_error():
    """An input without a "density" array and no array chosen (what ParaView leaves when the
    filter is made on an input that has not run): the message says so and lists the arrays."""
    from nebula_rt.filters.image_data import to_image_data

    from vtkmodules.vtkCommonExecutionModel import vtkTrivialProducer

    producer = vtkTrivialProducer()
    producer.SetOutput(to_image_data({"rho": np.ones((6, 5, 4), np.float32)}, None, (1, 1, 1)))
    lf = NebulaLightField()
    lf.SetInputConnection(producer.GetOutputPort())
    lf.SetPhotons(1000)
    lf.SetDevice(TEST_DEVICE)
    lf.Update()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 0
    assert "none was chosen" in lf.last_error and "'rho'" in lf.last_error, lf.last_error
    lf.SetDensityArrayName("rho")
    lf.Update()
    assert lf.last_error is None and lf.GetOutputDataObject(0).GetNumberOfPoints() == 6 * 5 * 4


class PressAt:
    """An abort source as ParaView's Abort button is one (the protocol of
    ``nebula_rt.filters.base.ABORT_SOURCES``: start, poll, stop around each execution), pressed
    at its ``n``-th poll of an execution of ``kind`` (never, for other algorithms)."""

    def __init__(self, kind, n):
        self.kind, self.n = kind, n
        self.log = []  # (algorithm class, polls, polls after the press) per execution

    def start(self, algorithm):
        self.alg, self.polls, self.after = type(algorithm).__name__, 0, 0

    def poll(self):
        if self.alg != self.kind:
            return False
        self.polls += 1
        self.after += self.polls > self.n
        return self.polls >= self.n

    def stop(self):
        self.log.append((self.alg, self.polls, self.after))


@pytest.mark.parametrize("stage", ["trace", "collision filter", "sky image"])
def test_an_abort_source_stops_each_stage_at_the_poll_that_heard_it(stage, monkeypatch):
    """Every stage of a NebulaRT execution polls the abort sources (ParaView's Abort button in
    the GUI, tests/paraview/test_paraview_gui.py) and stops at the very poll that heard the
    press, with an empty output and a message naming the stage: the trace (between launches),
    the collision filter's stage after it (per band) and the sky image; each execution's
    start and stop reach the source once, and the algorithms upstream are not touched."""
    from nebula_rt.filters import NebulaSkyImage, base

    d, lf, c = chain(shape=(16, 16, 16), photons=20_000)
    sky = NebulaSkyImage()
    sky.SetInputConnection(lf.GetOutputPort())
    sky.SetImageSize(32, 32)
    if stage == "collision filter":
        lf.SetEstimator("collision-filter")
        # the polls of an untouched run: the filter's stage comes after the trace's, so the
        # last poll of the light field's execution is in the filter's stage
        counter = PressAt("NebulaLightField", 10 ** 9)
        monkeypatch.setattr(base, "ABORT_SOURCES", [counter])
        lf.Update()
        assert lf.last_error is None, lf.last_error
        (_alg, total, _after), = [e for e in counter.log if e[0] == "NebulaLightField"]
        lf.SetTau(49.0)  # (a new execution)
        source = PressAt("NebulaLightField", total)
    else:
        source = PressAt("NebulaSkyImage" if stage == "sky image" else "NebulaLightField", 1)
    monkeypatch.setattr(base, "ABORT_SOURCES", [source])
    (sky if stage == "sky image" else lf).Update()
    alg = sky if stage == "sky image" else lf
    want = {"trace": "transport cancelled", "collision filter": "collision filter cancelled",
            "sky image": "sky image cancelled"}[stage]
    assert alg.last_error is not None and want in alg.last_error, alg.last_error
    assert alg.GetOutputDataObject(0).GetNumberOfPoints() == 0
    mine = [e for e in source.log if e[0] == type(alg).__name__]
    assert len(mine) == 1 and mine[0][2] == 0, source.log  # stopped at the poll that heard it
    if stage == "sky image":
        assert lf.last_error is None and lf.GetOutputDataObject(0).GetNumberOfPoints() == 16 ** 3
