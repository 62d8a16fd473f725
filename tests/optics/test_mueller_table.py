"""A tabulated scattering matrix (``bands.polarization = "matrix"``): what is read, what is
refused, and the kernel table made of it, against numbers it did not make.

- The Pinte et al. (2009) benchmark's table: its phase function's mean cosine is the g the
  benchmark states for the same grains (0.6296066, computed by its authors from Mie theory, not
  from the table), and the table's polarization is the file's at its own angles.
- A table written from Mie amplitudes (miepython, directly) on a one-degree grid gives the
  grains' g and the Mie path's polarization to the table's resolution.
- A scene with the matrix: the bands' g is the table's; what cannot go with it is refused by
  name.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from nebula_rt.errors import SceneError
from nebula_rt.optics.mie import Grains, mie_optics
from nebula_rt.optics.mueller_table import MuellerTable, parse_matrix, read_matrix
from nebula_rt.optics.polarization import Polarization
from nebula_rt.scene import Scene

PINTE = Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "pinte2009" / "mueller_matrix_1um.dat"
#: the benchmark's stated asymmetry of its grains at 1 micron (its web site's optical properties)
PINTE_G = 0.6296066


def _rows(theta, s11, s12, s33, s34) -> str:
    return "\n".join(f"{t:.6f} {a:.9e} {b:.9e} {c:.9e} {d:.9e}" for t, a, b, c, d in zip(theta, s11, s12, s33, s34))


def test_the_benchmark_table_gives_the_benchmarks_g():
    m = read_matrix(PINTE)
    assert len(m.theta_deg) == 180 and m.theta_deg[0] == 0.5 and m.theta_deg[-1] == 179.5
    # a one-degree table of a smooth phase function: g to 2e-4
    assert m.g == pytest.approx(PINTE_G, abs=2e-4)
    t = m.kernel_table()
    mu, cdf, p = t[0], t[1], t[2]
    assert mu[0] == 1.0 and mu[-1] == -1.0 and cdf[0] == 0.0 and cdf[-1] == 1.0
    assert np.all(np.diff(cdf) >= 0.0)
    # the piecewise-linear p integrates to 1 over mu
    assert np.sum(0.5 * (p[1:] + p[:-1]) * (mu[:-1] - mu[1:])) == pytest.approx(1.0, rel=1e-12)
    # at the file's own angles (on the table's nodes: 0.5 + k degrees) the ratios are the file's
    a = np.loadtxt(PINTE)
    nodes = np.rint(a[:, 0] * 4).astype(int)
    for row, k in ((3, 4), (4, 5)):  # S33 / S11, S34 / S11
        np.testing.assert_allclose(t[k][nodes], a[:, row] / a[:, 1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(t[3][nodes], a[:, 2] / a[:, 1], rtol=0, atol=1e-12)
    # the ends: the exact forward and backward matrices
    assert (t[3][0], t[4][0], t[5][0]) == (0.0, 1.0, 0.0) and (t[3][-1], t[4][-1], t[5][-1]) == (0.0, -1.0, 0.0)


def _mie_rows(grains: Grains, wavelength_um: float, step_deg: float = 1.0):
    """A table written from miepython's amplitudes of one sphere, Bohren & Huffman's signs."""
    import miepython

    theta = np.arange(0.0, 180.0 + step_deg / 2, step_deg)
    mu = np.cos(np.radians(theta))
    x = 2 * math.pi * grains.radius_min / wavelength_um
    s1, s2 = miepython.S1_S2(complex(grains.n, -grains.k), x, mu, norm="wiscombe")
    a1, a2 = np.abs(s1) ** 2, np.abs(s2) ** 2
    c = s1 * np.conj(s2)  # (miepython's m = n - i k: Im S1 S2* is Bohren & Huffman's Im S2 S1*)
    return _rows(theta, 0.5 * (a1 + a2), 0.5 * (a2 - a1), c.real, c.imag)


def test_a_table_of_mie_amplitudes_gives_the_mie_grains_optics():
    grains = Grains(n=1.6, k=0.02, radius_min=0.24, radius_max=0.24)
    m = parse_matrix(_mie_rows(grains, 0.55), "mie.dat")
    mie = mie_optics(grains, [550.0])
    assert m.g == pytest.approx(float(mie.g[0]), abs=2e-3)
    t, ref = m.kernel_table(), mie.table[0]
    assert t.shape == ref.shape
    # polarization and the phase function, to the one-degree table's interpolation
    np.testing.assert_allclose(t[3:], ref[3:], atol=2e-3)
    np.testing.assert_allclose(t[2], ref[2], rtol=5e-3)
    pol = Polarization("matrix", matrix=m)
    assert pol.stokes == 3 and pol.kernel_kind == Polarization("mie", grains=grains).kernel_kind
    params = pol.kernel_params(2)
    assert params.size == 2 * 4 + 2 * (6 * t.shape[1] + 65)


GOOD = _rows(np.linspace(0, 180, 19), np.ones(19), -0.5 * np.sin(np.radians(np.linspace(0, 180, 19))) ** 2,
             np.cos(np.radians(np.linspace(0, 180, 19))) * 0.8, np.zeros(19))


@pytest.mark.parametrize("text, why", [
    ("", "0 rows"),
    ("1 2 3\n" * 20, "holds 3 numbers"),
    ("a b c d e\n", "is not numbers"),
    (GOOD.replace("20.000000", "nan", 1), "not a finite number"),
    (GOOD.replace("20.000000", "5.000000", 1).replace("10.000000", "30.000000", 1), "must increase"),
    ("\n".join(GOOD.splitlines()[1:]), "must start within"),
    ("\n".join(GOOD.splitlines()[:-1]), "end within"),
    (GOOD.replace("1.000000000e+00", "-1.000000000e+00", 1), "S11 must be positive"),
    (GOOD.replace("0.000000000e+00", "9.000000000e-01", 1), "beyond 100 %"),
])
def test_bad_tables_are_refused_by_name(text, why):
    with pytest.raises(SceneError) as info:
        parse_matrix(text, "m.dat")
    assert info.value.parameter == "bands.grain_matrix" and why in str(info.value), str(info.value)
    assert "m.dat" in str(info.value)


def test_a_missing_or_special_file_is_refused(tmp_path):
    for path in (tmp_path / "none.dat", tmp_path):
        with pytest.raises(SceneError) as info:
            read_matrix(path)
        assert info.value.parameter == "bands.grain_matrix"


def test_a_scene_takes_the_tables_g_and_refuses_what_cannot_go_with_it(tmp_path):
    (tmp_path / "m.dat").write_text(PINTE.read_text())
    text = """
[bands]
polarization = "matrix"
grain_matrix = "m.dat"
[[bands.list]]
name = "J"
wavelength = 1000.0
extinction = 1.0
albedo = 0.6474786
"""
    (tmp_path / "s.toml").write_text(text)
    scene = Scene.load(tmp_path / "s.toml")  # relative to the scene file's folder
    (band,) = scene.bands.resolve()
    assert band.g == read_matrix(PINTE).g and band.albedo == 0.6474786
    from nebula_rt.optics.polarization import polarization_of

    assert polarization_of(scene).matrix == read_matrix(tmp_path / "m.dat")
    refusals = [
        (text + "g = 0.5\n", "bands.list[0].g"),
        (text.replace('grain_matrix = "m.dat"\n', ""), "bands.grain_matrix"),
        (text.replace('polarization = "matrix"', 'polarization = "white"') + "g = 0.5\n", "bands.grain_matrix"),
        (text.replace("[bands]\n", "[dust]\nvisual_extinction = 1.0\n[bands]\n"), "dust.visual_extinction"),
        (text.replace('grain_matrix = "m.dat"', 'grain_matrix = "m.dat"\ng = 0.3'), "bands.g"),
    ]
    for bad, key in refusals:
        with pytest.raises(SceneError) as info:
            Scene.loads(bad, base_dir=tmp_path)
        assert info.value.parameter == key, (key, str(info.value))


def test_tables_are_values():
    a, b = read_matrix(PINTE), read_matrix(PINTE)
    assert a == b and hash(a) == hash(b)
    assert isinstance(a, MuellerTable) and a.kernel_table() is b.kernel_table()
