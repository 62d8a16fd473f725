"""Polarization in the VTK layer (plain VTK and pyvista, no ParaView): Nebula Light Field's
Polarization, Nebula Sky Image's peel-off with Stokes Q and U, Nebula Polarization Vectors.

- The sky image's peel-off is the library's trace of the light field's own scene through its
  density with the same camera, bit for bit (I, Q, U and their errors);
- the vectors are the block sums of :func:`nebula_rt.observe.polarimetry.vector_field`: one
  segment per kept block, centred on it, along the angle (north +y, east -x), P x scale
  blocks long; pyvista plots them as lines;
- the refusals name the property: a sky image without Stokes, a band it has not, a block
  larger than the image; the ray march of a polarized scene warns that it has no Q and U.
"""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.backends import get_backend
from nebula_rt.filters import NebulaDustDensity, NebulaLightField, NebulaPolarizationVectors, NebulaSkyImage
from nebula_rt.filters.image_data import field_data_dict, point_array
from nebula_rt.observe.polarimetry import vector_field
from nebula_rt.observe.sky import Camera
from nebula_rt.pipeline import output_contract as contract
from nebula_rt.scene import Scene
from nebula_rt.transport.request import TransportRequest


@pytest.fixture(scope="module")
def polarized():
    d = NebulaDustDensity()
    d.SetGridShape(16, 16, 16)
    d.SetModel("uniform")
    d.SetFloor(0.0)
    d.SetBackend(TEST_BACKEND)
    d.SetDevice(TEST_DEVICE)
    lf = NebulaLightField()
    lf.SetInputConnection(d.GetOutputPort())
    lf.SetBackend(TEST_BACKEND)
    lf.SetDevice(TEST_DEVICE)
    lf.SetPhotons(60_000)
    lf.SetTau(2.0)
    lf.SetPolarization("rayleigh")
    sky = NebulaSkyImage()
    sky.SetInputConnection(lf.GetOutputPort())
    sky.SetImageSize(32, 32)
    sky.SetExtent(1.0)
    sky.SetMethod("peel-off")
    sky.Update()
    assert lf.last_error is None and sky.last_error is None, (lf.last_error, sky.last_error)
    return lf, sky


def test_the_peel_off_sky_image_is_the_librarys_trace(polarized):
    lf, sky = polarized
    img = sky.GetOutputDataObject(0)
    fd = field_data_dict(lf.GetOutputDataObject(0))
    scene = Scene.loads(fd["scene"])
    assert scene.bands.polarization == "rayleigh"
    rho = point_array(lf.GetOutputDataObject(0), contract.DENSITY.name())
    cam = Camera(size=(32, 32), extent=1.0)
    ref = TransportRequest.from_scene(scene, peel=cam, light_field=False).trace(
        rho, get_backend(TEST_BACKEND, TEST_DEVICE))
    for b, name in enumerate(band.name for band in scene.bands.resolve()):
        np.testing.assert_array_equal(point_array(img, contract.SKY_SCATTERED.name(name))[:, :, 0],
                                      ref.peel_image[b].astype(np.float32))
        for k, (val, err) in enumerate(((contract.SKY_Q, contract.SKY_Q_ERROR), (contract.SKY_U, contract.SKY_U_ERROR))):
            np.testing.assert_array_equal(point_array(img, val.name(name))[:, :, 0],
                                          ref.peel_stokes[b, k].astype(np.float32))
            np.testing.assert_array_equal(point_array(img, err.name(name))[:, :, 0],
                                          ref.peel_stokes_error[b, k].astype(np.float32))
    out_fd = field_data_dict(img)
    assert out_fd["polconv"] == "IAU" and out_fd["sky_method"] == "peel-off"


def test_the_vectors_are_the_block_sums_as_segments(polarized):
    pv = pytest.importorskip("pyvista")
    _, sky = polarized
    vec = NebulaPolarizationVectors()
    vec.SetInputConnection(sky.GetOutputPort())
    vec.SetBand("G")
    vec.SetBlockSize(4)
    vec.SetVectorScale(2.0)
    vec.SetMinSignalToNoise(2.0)
    vec.Update()
    assert vec.last_error is None, vec.last_error
    img, out = sky.GetOutputDataObject(0), vec.GetOutputDataObject(0)

    def a(spec):
        return point_array(img, spec.name("G"))[:, :, 0].astype(np.float64)

    centres, p, p_err, chi, keep = vector_field(a(contract.SKY_SCATTERED), a(contract.SKY_Q), a(contract.SKY_U),
                                                a(contract.SKY_SCATTERED_ERROR), a(contract.SKY_Q_ERROR),
                                                a(contract.SKY_U_ERROR), step=4, snr=2.0)
    n = int(keep.sum())
    assert n > 10 and out.GetNumberOfCells() == n and out.GetNumberOfPoints() == 2 * n
    pts = vtk_to_numpy(out.GetPoints().GetData()).astype(np.float64)
    mid, seg = 0.5 * (pts[0::2] + pts[1::2]), pts[1::2] - pts[0::2]
    spacing, origin = np.array(img.GetSpacing()), np.array(img.GetOrigin())
    np.testing.assert_allclose(mid[:, :2], origin[:2] + centres[keep] * spacing[:2], atol=1e-12)
    np.testing.assert_allclose(np.hypot(seg[:, 0], seg[:, 1]), 2.0 * 4 * spacing[0] * p[keep], rtol=1e-12)
    ang = np.mod(np.degrees(np.arctan2(-seg[:, 0], seg[:, 1])), 180.0)  # from north (+y) through east (-x)
    np.testing.assert_allclose(((ang - chi[keep]) + 90.0) % 180.0 - 90.0, 0.0, atol=1e-6)
    cell = out.GetCellData()
    np.testing.assert_allclose(vtk_to_numpy(cell.GetArray("P")), p[keep], rtol=1e-6)
    np.testing.assert_allclose(vtk_to_numpy(cell.GetArray("P_error")), p_err[keep], rtol=1e-6)
    assert np.all(pts[:, 2] == origin[2] + spacing[0])  # in front of the picture
    # a tangential pattern about the star at the image's centre (Rayleigh, single and multiple
    # scattering alike): the angle is the position angle + 90 degrees, within the blocks' spread
    c = origin[:2] + 0.5 * (np.array(img.GetDimensions()[:2]) - 1) * spacing[:2]
    pa = np.degrees(np.arctan2(-(mid[:, 0] - c[0]), mid[:, 1] - c[1]))
    off = np.abs(((chi[keep] - pa - 90.0) + 90.0) % 180.0 - 90.0)
    assert np.median(off) < 10.0, off
    wrapped = pv.wrap(out)
    assert wrapped.n_lines == n and "angle" in wrapped.cell_data


def test_refusals_name_the_property(polarized):
    lf, sky = polarized
    for setter, value, name in (("SetBand", "K", "Band (sky.vector_band)"),
                                ("SetBlockSize", 64, "Block Size (sky.vector_block)"),
                                ("SetBlockSize", 0, "Block Size (sky.vector_block)"),
                                ("SetMinSignalToNoise", -1.0, "Min Signal To Noise (sky.vector_snr)")):
        vec = NebulaPolarizationVectors()
        vec.SetInputConnection(sky.GetOutputPort())
        getattr(vec, setter)(value)
        vec.Update()
        assert vec.last_error is not None and name in vec.last_error, (setter, vec.last_error)
        assert vec.GetOutputDataObject(0).GetNumberOfPoints() == 0
    plain = NebulaSkyImage()
    plain.SetInputConnection(lf.GetOutputPort())
    plain.SetImageSize(16, 16)
    plain.Update()  # the ray march: no Stokes, said so
    assert plain.last_error is None and any("ray-march has no Stokes" in w for w in plain.last_warnings)
    vec = NebulaPolarizationVectors()
    vec.SetInputConnection(plain.GetOutputPort())
    vec.Update()
    assert vec.last_error is not None and "input" in vec.last_error and "peel-off" in vec.last_error
