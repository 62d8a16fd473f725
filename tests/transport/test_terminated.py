"""Packets stopped at transport.max_scatterings: reported, warned about and counted in the error.

A packet terminated at max_scatterings still carries its energy; the light it would have gone
on to spread is missing from J. The bias bound of nebula_rt.transport.terminated_bias,
f / (A + f) (f terminated, A absorbed fraction), follows from the energy balance: every
interaction absorbs with probability 1 - albedo, so the expected absorbed fraction is
(1 - albedo) x the expected interactions per packet, and sum sigma J V is proportional to
those interactions; completing the terminated packets adds at most f to the absorbed fraction.
These tests check the bookkeeping and measure the bias against runs with ample
max_scatterings (where nothing is terminated).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE, centre_star, one_band
from nebula_rt.errors import NebulaWarning
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene
from nebula_rt.transport.result import TERMINATED_WARN_BIAS, terminated_bias, warn_if_terminated
from nebula_rt.transport.estimate import lit_region_error
from nebula_rt.transport import trace

#: tau 10 across the box at density 1: optical depth 5 from the central star to each face
CUBE = np.ones((16, 16, 16), np.float32)
TAU = 10.0


def _quiet_trace(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        return trace(*args, **kw)


def test_terminated_fraction_matches_the_tallies_and_warns(backend):
    """Albedo 1 at tau 5, max_scatterings 3: most packets are stopped; the fraction is the
    tallies' ratio exactly, the warning names it, and with albedo 1 the energy balance bounds
    nothing (bias bound 1)."""
    with pytest.warns(NebulaWarning, match="max_scatterings = 3") as caught:
        res = trace(CUBE, one_band(albedo=1.0, g=0.5), centre_star(), tau=TAU, photons=20_000,
                    max_scatterings=3, seed=2, backend=backend)
    c = res.counts[0]
    assert c[0] == c[1] + c[2] + c[3] and c[1] == 0  # albedo 1: nothing absorbed
    assert res.terminated_fraction[0] == c[3] / c[0]
    assert 0.5 < res.terminated_fraction[0] < 1.0
    assert res.terminated_bias[0] == 1.0
    assert f"{res.terminated_fraction[0]:.3g}" in str(caught[0].message)
    # with room to scatter nothing is terminated and nothing is said
    with warnings.catch_warnings():
        warnings.simplefilter("error", NebulaWarning)
        full = trace(CUBE, one_band(albedo=1.0, g=0.5), centre_star(), tau=TAU, photons=20_000,
                     max_scatterings=100_000, seed=2, backend=backend)
    assert full.counts[0, 3] == 0 and full.terminated_fraction[0] == 0.0 and full.terminated_bias[0] == 0.0


def test_warning_threshold():
    """The warning fires above TERMINATED_WARN_BIAS of bias bound, not at or below it."""
    n, absorbed = 1_000_000, 500_000
    just_below = int(TERMINATED_WARN_BIAS * absorbed)  # f / (A + f) = 0.000999
    for term, warns in ((0, False), (just_below, False), (2 * just_below, True)):
        counts = np.array([[n, absorbed, n - absorbed - term, term]])
        assert (terminated_bias(counts)[0] > TERMINATED_WARN_BIAS) == warns
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            warn_if_terminated(counts, ["V"], 7)
        assert [issubclass(w.category, NebulaWarning) for w in caught] == ([True] if warns else [])


@pytest.mark.parametrize("albedo,max_scat,position", [
    (0.9, 3, (0.5, 0.5, 0.5)),     # central star: the terminated fraction alone is no worse
    (0.99, 30, (0.5, 0.5, 0.03)),  # star near a face of a thick cloud: it falls short
])
def test_bias_of_J_is_within_the_bound(backend, albedo, max_scat, position):
    """The relative bias of sum sigma J (uniform sigma: sum J) against runs with ample
    max_scatterings lies below f / (A + f). Six seeds: the tolerance is 5 standard errors of
    the mean of their biases (each truncated run shares its packets' random numbers with its
    full run up to the termination, so a seed's bias has little noise of its own).
    The second case, a star 0.03 inside a face with tau 60 across, shows why the bare
    terminated fraction f is no bound: the packets stopped are those that wandered deep into
    the cloud, with most of their path still ahead."""
    tau = 60.0 if position[2] < 0.5 else TAU
    biases, fs, bounds = [], [], []
    for seed in range(1, 7):
        kw = dict(tau=tau, photons=10_000, seed=seed, backend=backend)
        short = _quiet_trace(CUBE, one_band(albedo=albedo, g=0.0), centre_star(position=position),
                             max_scatterings=max_scat, **kw)
        full = trace(CUBE, one_band(albedo=albedo, g=0.0), centre_star(position=position),
                     max_scatterings=100_000, **kw)
        assert full.counts[0, 3] == 0
        biases.append(1.0 - short.J[0].sum() / full.J[0].sum())
        fs.append(short.terminated_fraction[0])
        bounds.append(short.terminated_bias[0])
    bias = np.mean(biases)
    se = np.std(biases, ddof=1) / math.sqrt(len(biases))
    f, bound = np.mean(fs), np.mean(bounds)
    assert bias <= bound + 5 * se, (bias, bound, se)
    assert bias > 0.05 + 5 * se  # the test has teeth: a real bias, well above the noise
    if position[2] < 0.5:
        assert bias > f + 5 * se, (bias, f, se)


def test_targeted_error_includes_the_terminated_bias(backend):
    """An error-targeted run reports sqrt(statistical^2 + bias bound^2): the statistical part
    stops the run (more packets do not shrink the bias), the bound is added to what it
    reports. Albedo 0.9 at tau 5 with max_scatterings 3: bound about 0.64."""
    with pytest.warns(NebulaWarning):
        res = trace(CUBE, one_band(albedo=0.9, g=0.0), centre_star(), tau=TAU, photons=200_000,
                    max_scatterings=3, seed=4, backend=backend, target_error=0.08)
    sigma = TAU * CUBE.astype(np.float64)[None]
    stat = lit_region_error(res.J, res.rel_error, sigma)
    bound = float(res.terminated_bias.max())
    assert 0.5 < bound < 0.8
    assert stat <= 0.08 and res.photons < res.photons_budget  # stopped on the statistical part
    # the run forms the statistical part on the device from float32 keys (1e-5 of the float64
    # reference: tests/transport/test_target_error.py)
    assert res.achieved_error == pytest.approx(math.hypot(stat, bound), rel=1e-5)


def test_field_data_and_vtk_filter_report_it(backend):
    # the VTK filters are the io extra (absent on a bare GPU machine, always present in make test)
    vtk_core = pytest.importorskip("vtkmodules.vtkCommonCore")
    vtkOutputWindow, vtkStringOutputWindow = vtk_core.vtkOutputWindow, vtk_core.vtkStringOutputWindow
    """terminated_fraction_<band> and terminated_bias_<band> in the field data; the VTK light
    field filter shows the warning on VTK's output window."""
    scene = Scene.from_dict({
        "grid": {"shape": [12, 12, 12]},
        "dust": {"model": "uniform", "density": 1.0, "tau": TAU},
        "stars": [{"position": [0.5, 0.5, 0.5]}],
        "bands": {"albedo": 1.0},
        "transport": {"photons": 5000, "max_scatterings": 2, "backend": TEST_BACKEND, "device": TEST_DEVICE},
    })
    with pytest.warns(NebulaWarning):
        light = Pipeline(backend).run(scene, colour=False)
    fd = light.field_data()
    for b, band in enumerate(light.bands):
        c = light.transport.counts[b]
        assert fd[f"terminated_fraction_{band.name}"] == c[3] / c[0] > 0.1
        assert fd[f"terminated_bias_{band.name}"] == 1.0

    from nebula_rt.filters import NebulaDustDensity, NebulaLightField

    d = NebulaDustDensity()
    d.SetGridShape(12, 12, 12)
    d.SetDevice(TEST_DEVICE)
    d.SetBackend(TEST_BACKEND)
    lf = NebulaLightField()
    lf.SetInputConnection(d.GetOutputPort())
    lf.SetPhotons(5000)
    lf.SetTau(50.0)
    lf.SetMaxScatterings(0)
    lf.SetDevice(TEST_DEVICE)
    lf.SetBackend(TEST_BACKEND)
    window = vtkStringOutputWindow()
    previous = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(window)
    try:
        lf.Update()
    finally:
        vtkOutputWindow.SetInstance(previous)
    assert lf.last_error is None
    assert len(lf.last_warnings) == 1 and "max_scatterings = 0" in lf.last_warnings[0]
    assert "NebulaRT warning" in window.GetOutput() and "max_scatterings = 0" in window.GetOutput()
    assert lf.GetOutputDataObject(0).GetNumberOfPoints() == 12**3  # a warning, not an error


def test_cli_render_summary_reports_it(tmp_path):
    pytest.importorskip("vtkmodules")  # a render writes a .vti: the io extra
    """The render command's JSON summary holds terminated_fraction per band, equal to the
    field data's."""
    import json
    import subprocess
    import sys

    from nebula_rt.filters.vti import read_vti

    scene = tmp_path / "thick.toml"
    scene.write_text(Scene.from_dict({
        "grid": {"shape": [10, 10, 10]},
        "dust": {"model": "uniform", "density": 1.0, "tau": TAU},
        "stars": [{"position": [0.5, 0.5, 0.5]}],
        "bands": {"albedo": 0.9},
        "transport": {"photons": 4000, "max_scatterings": 1, "backend": TEST_BACKEND, "device": TEST_DEVICE},
    }).to_toml())
    out = tmp_path / "thick.vti"
    proc = subprocess.run([sys.executable, "-m", "nebula_rt.cli", "render", str(scene), "-o", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "nebula-rt: warning:" in proc.stderr and "max_scatterings = 1" in proc.stderr
    summary = json.loads(proc.stdout[proc.stdout.index("{"):])
    field = read_vti(out)[1]
    for name, f in summary["terminated_fraction"].items():
        assert f == field[f"terminated_fraction_{name}"] == field[f"packets_terminated_{name}"] / 4000 > 0.1
