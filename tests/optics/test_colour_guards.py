"""A light field without starlight in a band has no colour: refused with the parameter named,
never NaN or a silently black rgba."""

from __future__ import annotations

import numpy as np
import pytest

from nebula_rt.errors import SceneError
from nebula_rt.pipeline.rgba import colour_matrix


@pytest.mark.parametrize("lum", [[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [1.0, np.nan, 1.0], [1.0, np.inf, 1.0]])
def test_colour_matrix_refuses_bands_without_starlight(lum):
    with pytest.raises(SceneError) as err:
        colour_matrix([450.0, 550.0, 650.0], lum, 20000.0)
    assert err.value.parameter == "band_luminosity"


def test_colour_filter_on_a_dark_light_field():
    """NebulaColour on a light field whose band_luminosity is all zero: empty output and an
    error naming band_luminosity (it returned NaN rgb_linear and black rgba)."""
    from nebula_rt.filters import NebulaColour
    from nebula_rt.filters.image_data import to_image_data

    shape = (4, 4, 4)
    names = ["R", "G", "B"]
    arrays = {"density": np.ones(shape, np.float32)}
    for n in names:
        arrays[f"J_{n}"] = np.ones(shape, np.float32)
        arrays[f"emissivity_{n}"] = np.ones(shape, np.float32)
        arrays[f"rel_error_{n}"] = np.full(shape, 0.1, np.float32)
    fd = {"band_names": ",".join(names), "band_wavelength_nm": np.array([650.0, 550.0, 450.0]),
          "band_luminosity": np.zeros(3), "band_extinction": np.ones(3), "band_albedo": np.full(3, 0.6),
          "tau": 1.0, "reference_band": 1, "colour_temperature": 20000.0}
    img = to_image_data(arrays, fd, (0.25,) * 3, (0.125,) * 3)
    c = NebulaColour()
    c.SetInputDataObject(0, img)
    c.Update()
    assert c.last_error is not None and "band_luminosity" in c.last_error
    assert c.GetOutputDataObject(0).GetNumberOfPoints() == 0
