"""Published numbers about real reflection nebulae (nebula_rt.observe.published): the shipped
tables against values read here from their sources, the example scenes' stars made from them,
and the scene's dust beside them in ``nebula-rt compare``."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import TEST_DEVICE
from nebula_rt.observe import published
from nebula_rt.scene import Scene, units

ROOT = Path(__file__).resolve().parents[2]

#: rows as the source files print them (karllark/DGFit, dgfit/old/old_data/Scat_Data/: wave in
#: Angstrom, albedo, delta, g, delta), copied for this test: (nebula, nm, albedo, unc, g, unc)
SOURCE_ROWS = [
    ("NGC 7023", 551.5, 0.60, 0.05, 0.63, 0.1),      # witt82.dat, 5515.0
    ("NGC 7023", 250.0, 0.47, 0.05, None, None),     # witt82.dat, 2500.0: g -1 (not determined)
    ("NGC 2023", 126.75, 0.35, 0.09, 0.83, 0.08),    # burgh02.dat, 1267.5
    ("IC 435", 550.0, 0.49, 0.05, 0.64, 0.05),       # calzetti95.dat, 5500.00
    ("Sco OB2", 97.3, 0.28, 0.07, 0.49, 0.48),       # lewis07_spinr.dat, 973.0
]


def test_the_dust_table_holds_the_sources_values_with_their_references():
    rows = published.dust()
    assert len(rows) == 76
    assert {r.nebula for r in rows} == {"NGC 7023", "NGC 2023", "IC 435", "Pleiades", "Sco OB2", "Orion"}
    for nebula, nm, a, a_unc, g, g_unc in SOURCE_ROWS:
        (r,) = [r for r in rows if r.nebula == nebula and r.wavelength_nm == nm]
        assert (r.albedo, r.albedo_unc, r.g, r.g_unc) == (a, a_unc, g, g_unc), r
    for r in rows:
        assert r.reference and (r.albedo is not None or r.g is not None), r
        assert r.albedo is None or (0.0 <= r.albedo <= 1.0 and r.albedo_unc > 0), r
        assert r.g is None or (-1.0 <= r.g <= 1.0 and r.g_unc > 0), r
    # no "not determined" sentinel survives, no superseded file is shipped
    assert not [r for r in rows if r.albedo == -1.0 or r.g == -1.0]
    text = (ROOT / "python/nebula_rt/data/published_dust.csv").read_text()
    assert "witt82_save.dat" not in text.split("\nobject,")[1] and "/lewis07.dat" not in text.split("\nobject,")[1]


def test_the_stars_are_as_their_tables_give_them():
    """Values as Fitzpatrick & Massa 2007 (tables 1, 3, 4) and Gordon et al. 2009 (Table 2)
    print them, copied for this test."""
    stars = published.stars()
    assert set(stars) == {"HD200775", "HD037903"}
    hd37903, hd200775 = stars["HD037903"], stars["HD200775"]
    assert (hd37903.nebula, hd37903.spectral_type, hd37903.v_mag, hd37903.e_bv, hd37903.r_v, hd37903.t_eff,
            hd37903.t_eff_unc, hd37903.distance_pc) == ("NGC 2023", "B1.5 V", 7.83, 0.33, 3.95, 22677.0, 476.0, 719.0)
    assert (hd200775.nebula, hd200775.spectral_type, hd200775.v_mag, hd200775.e_bv, hd200775.r_v) == (
        "NGC 7023", "B2Ve", 7.39, 0.57, 5.61)
    assert hd200775.t_eff is None and hd200775.distance_pc is None  # (no cited table gives them)
    assert "Fitzpatrick & Massa 2007" in hd37903.sources["T_eff"] and "Gordon+2009" in hd200775.sources["V"]


def test_the_example_scenes_take_their_stars_from_the_tables():
    """ngc2023.toml: T_eff and M_V = V - R_V E(B-V) - 5 log10(d / 10 pc) + (AB - Vega)_V from
    HD 37903's row, placed at its distance; ngc7023.toml: HD 200775's type (B2Ve, a B2 dwarf
    with emission lines) through Pecaut & Mamajek's sequence, 20600 K."""
    hd37903 = published.stars()["HD037903"]
    s2023 = Scene.load(ROOT / "examples/scenes/ngc2023.toml")
    want_mv = 7.83 - 3.95 * 0.33 - 5.0 * math.log10(71.9) + units.ab_minus_vega()["V"]
    keys = published.scene_star(hd37903, units.ab_minus_vega()["V"])
    assert keys["absolute_magnitude"] == pytest.approx(want_mv, abs=1e-12)
    assert s2023.stars[0].temperature == keys["temperature"] == 22677.0
    assert s2023.stars[0].absolute_magnitude == pytest.approx(keys["absolute_magnitude"], abs=1e-12)
    assert units.distance_metres(s2023.observer) == pytest.approx(719.0 * units._pc_metres(), rel=1e-12)
    s7023 = Scene.load(ROOT / "examples/scenes/ngc7023.toml")
    assert s7023.stars[0].spectral_type == published.stars()["HD200775"].spectral_type.rstrip("e")
    assert s7023.stars[0].temperature == 20600.0


def test_compare_plots_and_says_the_scenes_dust_beside_the_published():
    """``nebula-rt compare --table``: the JSON holds the scene's band albedo and g and the
    published values inside the bands' range (NGC 7023's 409-552 nm, IC 435's 440 and 550 nm),
    and the plot gains their row."""
    scene = Scene.load(ROOT / "examples/scenes/ngc7023.toml")
    side = published.beside(scene)
    inside = {(p.nebula, p.wavelength_nm) for p in side.in_range()}
    assert inside == {("NGC 7023", 551.5), ("NGC 7023", 473.3), ("NGC 7023", 409.3), ("IC 435", 440.0),
                      ("IC 435", 550.0)}
    assert [b[0] for b in side.bands] == [b.name for b in scene.bands.resolve()]


def test_the_compare_command_writes_the_dust_beside_the_published(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "nebula_rt.cli", "compare", str(ROOT / "examples/scenes/ngc7023.toml"),
         "--set", "grid.shape=[16,16,16]", "--photons", "4000", "--device", TEST_DEVICE, "--size", "32",
         "--table", str(ROOT / "examples/observations/synthetic-colour.ecsv"),
         "--png", str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    d = json.loads((tmp_path / "c.json").read_text())["dust_optics"]
    assert len(d["scene_bands"]) == 8 and len(d["published_in_band_range"]) == 5
    assert "not truth" in d["note"]
    import matplotlib.image

    # two rows of panels (the table, the dust) at 100 dpi, 3.6 inches each
    assert matplotlib.image.imread(str(tmp_path / "c.png")).shape[0] == 720
