"""Physical units in scene files: each converts to the box-unit key it replaces exactly as the
hand calculations written out here say, a physical scene traces the same bits as its box-unit
equivalent, and bad values are refused naming their units.

The reference numbers are written out from their sources, not taken from the code under test:
the IAU's definitions of the parsec, the astronomical unit and the nominal solar luminosity,
rows of Draine's (2003) R_V = 3.1 table (kext_albedo_WD_MW_3.1_60_D03.dat: wavelength in um,
C_ext / H in cm^2), the dust mass per H of its header, the Planck integral as its series, and
the AB magnitude's definition.
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.scene import units
from nebula_rt.errors import SceneError
from nebula_rt.scene import Scene

AU_M = 149_597_870_700.0  # IAU 2012 Resolution B2
PC_M = 648_000.0 / math.pi * AU_M  # IAU 2015 Resolution B2
LYR_M = 365.25 * 86400.0 * 299_792_458.0  # Julian year x c
#: Draine (2003) R_V = 3.1, rows near 550 nm: (wavelength um, C_ext / H cm^2)
ROWS_31 = [(0.524807, 5.172e-22), (0.537032, 5.018e-22), (0.547000, 4.896e-22), (0.549541, 4.866e-22),
           (0.555000, 4.802e-22), (0.562341, 4.717e-22), (0.575440, 4.572e-22), (0.588844, 4.429e-22)]
C_V_31 = 4.896e-22  # the row marked "V filter" (0.547 um)
M_DUST_PER_H_31 = 1.870e-26  # g per H, the table's header
M_DUST_PER_H_55 = 2.199e-26  # the R_V = 5.5 table's header
MAG_PER_TAU = 2.5 * math.log10(math.e)


def c_ext_31(wavelength_nm):
    """C_ext / H of R_V = 3.1 dust interpolated linearly between the rows above."""
    nm = [1000.0 * w for w, _ in ROWS_31]
    return np.interp(wavelength_nm, nm, [c for _, c in ROWS_31])


def scene(**tables):
    base = {"grid": {"shape": [8, 8, 8]}, "transport": {"photons": 2000, "backend": TEST_BACKEND,
                                                        "device": TEST_DEVICE}}
    for k, v in tables.items():
        base[k] = {**base.get(k, {}), **v} if isinstance(v, dict) else v
    return Scene.from_dict(base)


# --- lengths ----------------------------------------------------------------------------------


@pytest.mark.parametrize("length, unit, metres", [
    (1.0, "pc", PC_M), ("0.1 pc", "pc", 0.1 * PC_M), (2e5, "AU", 2e5 * AU_M), ("2e5 au", "pc", 2e5 * AU_M),
    ("1 ly", "pc", LYR_M), ("3 lyr", "pc", 3 * LYR_M), (4.0, "km", 4e3), ("7pc", "AU", 7 * PC_M)])
def test_the_box_edge_in_physical_units(length, unit, metres):
    s = scene(grid={"length": length, "unit": unit})
    assert units.box_length_cm(s.grid) == pytest.approx(100.0 * metres, rel=1e-14)


@pytest.mark.parametrize("key, value, words", [
    ("grid.length", "3 furlong", "units: pc, kpc, Mpc, AU, ly, lyr"),
    ("grid.length", "3 kg", "a finite length > 0"),
    ("grid.length", "pc", "a quantity such as '3 pc'"),
    ("grid.unit", "kg", "must be a length unit: pc, kpc, Mpc, AU, ly"),
    ("observer.distance", "140 s", "a distance > 0: a number (in pc)"),
])
def test_bad_lengths_are_refused_naming_the_units(key, value, words):
    table, name = key.split(".")
    with pytest.raises(SceneError) as info:
        scene(**{table: {name: value}})
    assert info.value.parameter == key and repr(value) in str(info.value) and words in str(info.value)


def test_the_distance_is_a_quantity_or_a_number_of_parsecs():
    assert units.distance_metres(scene(observer={"distance": "140 pc"}).observer) == pytest.approx(140 * PC_M, rel=1e-14)
    assert units.distance_metres(scene(observer={"distance": 140}).observer) == pytest.approx(140 * PC_M, rel=1e-14)
    assert units.distance_metres(scene().observer) == 0.0  # not given


# --- dust -------------------------------------------------------------------------------------


def test_hydrogen_density_to_tau_thesis_bands():
    """thesis-rgb: C_ref is R_V = 3.1 at the reference band's 550 nm, between the rows at
    549.541 and 555.000 nm; tau = n_H C_ref L."""
    c_ref = 4.866e-22 + (550.0 - 549.541) / (555.0 - 549.541) * (4.802e-22 - 4.866e-22)
    box_cm = 0.1 * PC_M * 100.0
    s = scene(grid={"length": "0.1 pc"}, dust={"hydrogen_density": 100.0})
    assert s.dust.tau == pytest.approx(100.0 * c_ref * box_cm, rel=1e-12)  # 0.0150


def test_mass_density_to_tau_uses_the_models_dust_mass_per_h():
    c_ref = float(c_ext_31(550.0))
    box_cm = 0.1 * PC_M * 100.0
    s = scene(grid={"length": "0.1 pc"}, dust={"mass_density": 1e-24})
    assert s.dust.tau == pytest.approx(1e-24 / M_DUST_PER_H_31 * c_ref * box_cm, rel=1e-12)
    # R_V = 5.5 (spectral-8-dense): its own table's header
    from nebula_rt.optics import dust_tables

    assert dust_tables.dust_mass_per_h("5.5") == M_DUST_PER_H_55
    assert dust_tables.v_filter_cext("3.1") == C_V_31


def test_visual_extinction_to_tau():
    """tau_ref = A_V / 1.0857 x C_ext(550 nm) / C_ext(V filter row)."""
    s = scene(dust={"visual_extinction": 2.0})
    assert s.dust.tau == pytest.approx(2.0 / MAG_PER_TAU * float(c_ext_31(550.0)) / C_V_31, rel=1e-12)


def test_spectral_preset_uses_the_reference_bands_average():
    """spectral-8: the reference band is 530-580 nm; C_ref is the mean of the table on its 1 nm
    grid, the scale the preset's relative extinctions are divided by, so each band's tau x
    extinction is n_H L times its own band-averaged C_ext / H."""
    c_ref = float(np.mean(c_ext_31(np.arange(530.0, 581.0))))
    box_cm = 2e5 * AU_M * 100.0
    s = scene(grid={"length": "2e5 AU"}, bands={"preset": "spectral-8"}, dust={"hydrogen_density": 30.0})
    assert s.dust.tau == pytest.approx(30.0 * c_ref * box_cm, rel=1e-12)
    ref = [b for b in s.bands.resolve() if b.wavelength == 555.0][0]
    assert ref.extinction == 1.0


# --- stars ------------------------------------------------------------------------------------


def planck_fraction_below(wavelength_nm, temperature):
    """Fraction of a blackbody's power at wavelengths below lambda: the series
    15/pi^4 sum_n e^{-n x} (x^3/n + 3 x^2/n^2 + 6 x/n^3 + 6/n^4), x = h c / (lambda k T)."""
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23  # exact in the 2019 SI
    x = h * c / (wavelength_nm * 1e-9 * k * temperature)
    n = np.arange(1, 200)
    return float(15 / math.pi**4 * np.sum(np.exp(-n * x) * (x**3 / n + 3 * x**2 / n**2 + 6 * x / n**3 + 6 / n**4)))


@pytest.mark.parametrize("temperature", [5772.0, 10000.0, 20000.0])
def test_bolometric_luminosity_to_the_part_inside_the_bands(temperature):
    inside = planck_fraction_below(780.0, temperature) - planck_fraction_below(380.0, temperature)
    s = scene(stars=[{"luminosity_lsun": 1000.0, "temperature": temperature}])
    # the 1 nm trapezoid rule of the band luminosities: relative error below 1e-5 here
    assert s.stars[0].luminosity == pytest.approx(1000.0 * inside, rel=1e-5)


def ab_magnitude_by_hand(temperature, l_bol_w, distance_m):
    """AB magnitude through Bessell V, photon counting, of a blackbody of luminosity l_bol_w at
    distance_m: -2.5 log10(int f_lambda R lambda dl / int (3631 Jy c / lambda^2) R lambda dl),
    on the passband's own tabulated wavelengths."""
    import speclite.filters

    from scipy.constants import Boltzmann as k, Stefan_Boltzmann as sigma, c, h

    f = speclite.filters.load_filter("bessell-V")
    lam = np.asarray(f.wavelength, float) * 1e-10
    resp = np.asarray(f.response, float)
    b = 2 * h * c**2 / lam**5 / np.expm1(h * c / (lam * k * temperature))
    f_lam = l_bol_w / (4 * math.pi * distance_m**2) * math.pi * b / (sigma * temperature**4)
    f_ab = 3631e-26 * c / lam**2
    return -2.5 * math.log10(np.trapezoid(f_lam * resp * lam, lam) / np.trapezoid(f_ab * resp * lam, lam)), f


def test_absolute_magnitude_to_luminosity():
    t = 10000.0
    m1, filt = ab_magnitude_by_hand(t, 3.828e26, 10 * PC_M)  # M_V(AB) of 1 L_sun at this temperature
    # speclite's own photometry of the same spectrum agrees (a third implementation)
    import astropy.units as u
    from scipy.constants import Boltzmann as k, Stefan_Boltzmann as sigma, c, h

    lam = np.linspace(3000.0, 10000.0, 20001) * 1e-10
    f_lam = 3.828e26 / (4 * math.pi * (10 * PC_M) ** 2) * math.pi * 2 * h * c**2 / lam**5 / np.expm1(
        h * c / (lam * k * t)) / (sigma * t**4)
    m_speclite = filt.get_ab_magnitude(f_lam * 1e-7 * u.erg / u.s / u.cm**2 / u.Angstrom, lam * 1e10 * u.Angstrom)
    assert m1 == pytest.approx(float(m_speclite), abs=1e-3)
    assert units.blackbody_absolute_magnitude(t) == pytest.approx(m1, abs=1e-4)
    s = scene(stars=[{"absolute_magnitude": 1.0, "temperature": t}])
    l_bol = 10 ** (-0.4 * (1.0 - m1))
    inside = planck_fraction_below(780.0, t) - planck_fraction_below(380.0, t)
    assert s.stars[0].luminosity == pytest.approx(l_bol * inside, rel=2e-4)  # 1e-4 mag is 9e-5 in L


def test_the_sun_as_a_blackbody_is_near_its_measured_absolute_magnitude():
    """Plausibility, not a hand calculation: a 5772 K blackbody of 1 L_sun has M_V(AB) within
    0.1 mag of the Sun's measured M_V = 4.81 (Willmer 2018, ApJS 236, 47); the real spectrum's
    lines and the AB-Vega offset of V (0.02 mag) make up the rest."""
    assert abs(units.blackbody_absolute_magnitude(5772.0) - 4.81) < 0.1


# --- spectral type -> T_eff (Pecaut & Mamajek 2013; de Jager & Nieuwenhuijzen 1987) -----------

#: rows of Pecaut & Mamajek's dwarf sequence (E. Mamajek's table, version 2024.05.15, read from
#: the published table for this test: SpT, Teff, B-V, U-B, V-Rc, V-Ic)
PM13_ROWS = {"B1.5V": (24500, -0.252, -0.910, -0.114, -0.281), "B2V": (20600, -0.215, -0.790, -0.094, -0.230),
             "B7V": (14000, -0.128, -0.459, -0.058, -0.133), "A0V": (9700, 0.000, -0.005, 0.001, 0.004),
             "G2V": (5770, 0.650, 0.133, 0.363, 0.713), "M9.5V": (2330, math.nan, math.nan, 2.510, 4.73)}


@pytest.mark.parametrize("spt", sorted(PM13_ROWS))
def test_a_dwarf_takes_pecaut_and_mamajeks_values(spt):
    """A class V type that is a row of the sequence: its T_eff and intrinsic colours exactly
    (as the table prints them), under "auto" and by name."""
    t_eff, *colours = PM13_ROWS[spt]
    assert units.temperature_from_spectral_type(spt) == t_eff
    assert units.temperature_from_spectral_type(spt, "pecaut-mamajek-2013") == t_eff
    got = units.dwarf_properties(spt)
    assert got["T_eff"] == t_eff
    for name, want in zip(units.DWARF_COLOURS, colours):
        assert got[name] == want or (math.isnan(want) and math.isnan(got[name])), name


def test_between_rows_the_sequence_is_interpolated():
    """B1.75V lies between B1.5V and B2V: T_eff at the geometric mean of theirs (linear in
    log T_eff), B-V at the mean; B8.5V between B8V (12300 K) and B9V (10700 K)."""
    got = units.dwarf_properties("B1.75 V")
    assert got["T_eff"] == pytest.approx(math.sqrt(24500 * 20600), rel=1e-12)
    assert got["B-V"] == pytest.approx(0.5 * (-0.252 - 0.215), abs=1e-12)
    assert units.temperature_from_spectral_type("B8.5V") == pytest.approx(math.sqrt(12300 * 10700), rel=1e-12)


def test_the_old_calibration_is_there_by_name_and_for_other_classes():
    """de Jager & Nieuwenhuijzen (1987) by name (PyAstronomy's evaluation of their Eq. 2b, the
    oracle), and under "auto" for every class but V and for dwarfs outside O3V-M9.5V; it is
    9.3 % cooler than Pecaut & Mamajek at B7V."""
    from PyAstronomy.pyasl import SpecTypeDeJager

    def dj87(spt, lclass):
        return 10.0 ** SpecTypeDeJager().lumAndTeff(spt, lclass)[1]

    assert units.temperature_from_spectral_type("B2.5 IV") == dj87("B2.5", "IV")
    assert units.temperature_from_spectral_type("K0III", "de-jager-1987") == dj87("K0", "III")
    assert units.temperature_from_spectral_type("B7V", "de-jager-1987") == dj87("B7", "V")
    assert units.temperature_from_spectral_type("O2V") == dj87("O2", "V")  # (before O3V)
    assert 1 - dj87("B7", "V") / 14000.0 == pytest.approx(0.093, abs=0.001)
    with pytest.raises(ValueError, match="class V"):
        units.temperature_from_spectral_type("K0III", "pecaut-mamajek-2013")


def test_spectral_type_sets_the_temperature_and_the_luminosity_follows_it():
    """The scene's temperature is its calibration's, and an absolute magnitude then gives the
    bits of the same star with that temperature given."""
    from PyAstronomy.pyasl import SpecTypeDeJager

    t = 10.0 ** SpecTypeDeJager().lumAndTeff("B2.5", "IV")[1]
    s = scene(stars=[{"spectral_type": "B2.5 IV", "absolute_magnitude": -1.0}])
    assert s.stars[0].temperature == t
    same = scene(stars=[{"temperature": t, "absolute_magnitude": -1.0}])
    assert s.stars[0].luminosity == same.stars[0].luminosity
    assert Scene.loads(s.to_toml()) == s  # the file holds the temperature too, as converted
    cooler = s.with_overrides(['stars.0.spectral_type="A0V"'])  # converted again, a dwarf: PM13's row
    assert cooler.stars[0].temperature == 9700.0
    assert cooler.stars[0].luminosity != s.stars[0].luminosity
    old = cooler.with_overrides(['stars.0.spectral_calibration="de-jager-1987"'])
    assert old.stars[0].temperature == pytest.approx(10.0 ** SpecTypeDeJager().lumAndTeff("A0", "V")[1], rel=1e-15)
    assert Scene.loads(old.to_toml()) == old


def test_spectral_types_order_as_temperatures_do():
    """Plausibility of both calibrations over their ranges: hotter along M10 .. O1 on the main
    sequence, giants cooler than dwarfs of the same late type, the Sun (G2V) within 5 % of its
    nominal 5772 K (IAU 2015 Resolution B3)."""
    for calibration in ("auto", "de-jager-1987"):
        # (under "auto" up to M9V: M10V is past the dwarf sequence's M9.5V, and DJ87's M10V is
        # hotter than the sequence's M9.5V, 2596 K against 2330 K)
        seq = [f"{c}{n}V" for c in "OBAFGKM" for n in range(10) if f"{c}{n}" != "O0"]
        seq += ["M10V"] if calibration == "de-jager-1987" else []
        temps = [units.temperature_from_spectral_type(t, calibration) for t in seq]
        assert all(a > b for a, b in zip(temps, temps[1:])), list(zip(seq, temps))
        assert 2000.0 < temps[-1] < 3500.0 and 40000.0 < temps[0] < 60000.0
        assert temps[seq.index("O3V")] < temps[seq.index("O2V")]  # (where auto changes calibration)
        for sub in ("G8", "K0", "K5"):
            assert (units.temperature_from_spectral_type(sub + "III", calibration)
                    < units.temperature_from_spectral_type(sub + "V", calibration))
        assert units.temperature_from_spectral_type("G2V", calibration) == pytest.approx(5772.0, rel=0.05)
    assert units.temperature_from_spectral_type("M10V") == pytest.approx(
        units.temperature_from_spectral_type("M9.99999V", "de-jager-1987"), rel=1e-5)


@pytest.mark.parametrize("star, key, words", [
    ({"spectral_type": "B2V", "temperature": 20000.0}, "stars[0].temperature", "is set by stars[0].spectral_type"),
    ({"spectral_type": "B2"}, "stars[0].spectral_type", "luminosity class"),
    ({"spectral_type": "K0III", "spectral_calibration": "pecaut-mamajek-2013"}, "stars[0].spectral_type",
     "'de-jager-1987' holds every luminosity class"),
    ({"spectral_type": "O2V", "spectral_calibration": "pecaut-mamajek-2013"}, "stars[0].spectral_type", "O3V to M9.5V"),
    # (a flat spectrum, temperature 0, has no bolometric correction)
    ({"luminosity_lsun": 100.0, "temperature": 0.0}, "stars[0].luminosity_lsun", "or stars[0].spectral_type"),
])
def test_spectral_type_errors(star, key, words):
    with pytest.raises(SceneError) as info:
        scene(stars=[star])
    assert info.value.parameter == key and words in str(info.value), str(info.value)


@pytest.mark.parametrize("star, key, words", [
    ({"luminosity_lsun": 100.0, "temperature": 0.0}, "stars[0].luminosity_lsun", "give stars[0].temperature"),
    ({"luminosity_lsun": 100.0, "temperature": 9000.0, "spectrum": [[400, 1], [700, 1]]},
     "stars[0].luminosity_lsun", "no measured spectrum"),
    ({"luminosity_lsun": 100.0, "absolute_magnitude": 1.0, "temperature": 9000.0},
     "stars[0].absolute_magnitude", "give one of"),
    ({"luminosity_lsun": 100.0, "luminosity": 3.0, "temperature": 9000.0}, "stars[0].luminosity",
     "is set by stars[0].luminosity_lsun"),
])
def test_star_luminosity_errors(star, key, words):
    with pytest.raises(SceneError) as info:
        scene(stars=[star])
    assert info.value.parameter == key and words in str(info.value), str(info.value)


def test_physical_and_scene_unit_stars_do_not_mix():
    with pytest.raises(SceneError) as info:
        scene(stars=[{"luminosity_lsun": 100.0, "temperature": 9000.0}, {"luminosity": 2.0, "position": [0.2, 0.5, 0.5]}])
    assert info.value.parameter == "stars[1].luminosity" and "do not mix" in str(info.value)


def test_dust_errors():
    with pytest.raises(SceneError) as info:
        scene(dust={"hydrogen_density": 10.0, "visual_extinction": 1.0})
    assert info.value.parameter == "dust.visual_extinction" and "give one of" in str(info.value)
    with pytest.raises(SceneError) as info:
        scene(dust={"hydrogen_density": 10.0, "tau": 5.0})
    assert info.value.parameter == "dust.tau" and "is set by dust.hydrogen_density" in str(info.value)
    with pytest.raises(SceneError) as info:  # tau 1.5e297: beyond float32, named by its source
        scene(dust={"hydrogen_density": 1e300})
    assert info.value.parameter == "dust.hydrogen_density" and "gives dust.tau" in str(info.value)


# --- round trips, overrides, bits --------------------------------------------------------------


def test_a_physical_scene_round_trips_and_overrides_convert_again():
    s = scene(grid={"length": "0.1 pc"}, dust={"hydrogen_density": 100.0},
              stars=[{"luminosity_lsun": 1000.0, "temperature": 10000.0}])
    assert Scene.loads(s.to_toml()) == s  # the file holds tau and luminosity too, as converted
    twice = s.with_overrides(["grid.length='0.2 pc'"])
    assert twice.dust.tau == pytest.approx(2.0 * s.dust.tau, rel=1e-15)
    assert s.with_overrides(["dust.hydrogen_density=300"]).dust.tau == pytest.approx(3.0 * s.dust.tau, rel=1e-15)
    brighter = s.with_overrides(["stars.0.luminosity_lsun=2000"])
    assert brighter.stars[0].luminosity == pytest.approx(2.0 * s.stars[0].luminosity, rel=1e-15)
    with pytest.raises(SceneError) as info:  # a tau of its own conflicts with the density
        s.with_overrides(["dust.tau=3"])
    assert info.value.parameter == "dust.tau"


def test_a_box_unit_scene_is_written_as_before():
    """No physical key: the scene's tables hold no new dust or star keys and no [observer]."""
    d = scene().to_dict()
    assert "observer" not in d
    assert not set(d["dust"]) & {"hydrogen_density", "mass_density", "visual_extinction"}
    assert not set(d["stars"][0]) & {"luminosity_lsun", "absolute_magnitude"}


def test_box_unit_scenes_do_not_import_astropy():
    """astropy's import takes about 0.6 s: a scene in box units (grid.unit = "pc", the
    default) never needs it."""
    code = ("import sys; from nebula_rt.scene import Scene; Scene.default(); "
            "Scene.from_dict({'grid': {'length': 3.0}}); print('astropy.units' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_a_physical_scene_traces_the_bits_of_its_box_unit_equivalent(backend):
    from nebula_rt.pipeline import Pipeline

    phys = scene(grid={"length": "0.2 pc"}, dust={"hydrogen_density": 2000.0},
                 stars=[{"luminosity_lsun": 500.0, "temperature": 12000.0}])
    box = scene(dust={"tau": phys.dust.tau}, stars=[{"luminosity": phys.stars[0].luminosity, "temperature": 12000.0}])
    a = Pipeline(backend).run(phys, colour=False)
    b = Pipeline(backend).run(box, colour=False)
    assert a.transport.counts.tolist() == b.transport.counts.tolist()
    assert np.array_equal(a.J, b.J) and np.array_equal(a.rel_error, b.rel_error)
    assert a.transport.counts[:, 1].sum() > 0  # the dust absorbed: the optical depth mattered


def test_the_example_on_the_sky_is_the_merope_scene_in_physical_units():
    """examples/scenes/merope-sky.toml: n_H 2700 cm^-3 in a 0.5 pc box gives merope.toml's
    tau of 2 (within 0.2 %), the rest of the scene the same."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "examples" / "scenes"
    sky, box = Scene.load(root / "merope-sky.toml"), Scene.load(root / "merope.toml")
    assert sky.dust.tau == pytest.approx(box.dust.tau, rel=2e-3)
    assert (sky.grid.shape, sky.bands, sky.transport) == (box.grid.shape, box.bands, box.transport)
    assert sky.stars[0].temperature == box.stars[0].temperature == 14000.0
