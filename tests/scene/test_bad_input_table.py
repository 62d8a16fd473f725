"""Every scene key against every kind of bad value that applies to it.

For each row (key, kind, value) of TABLE:

(a) ``Scene.loads`` (of TOML text holding the value) and ``Scene.with_overrides`` raise a
    SceneError whose ``.parameter`` is the key and whose message shows the value and the
    allowed range;
(b) ``nebula-rt render s.toml -o out.vti --set KEY=VALUE`` (``nebula_rt.cli.main`` in process)
    exits with status 2, names the key on stderr and writes nothing into the output folder;
(c) the VTK filter setter of the key, where there is one, gives an empty output and a
    ``last_error`` naming the property and the key.

Rows marked ALLOWED are values the scene legitimately accepts (the note says why); (a) checks
they are accepted and, where the run is cheap, (b) that the CLI renders them. Rows marked
RUNTIME pass the scene validation (they depend on the file system or on the grid, photons and
spectrum together) and are refused before tracing (b). The base scene is 8^3 with 2000 packets
per band, so an accepted row runs in a fraction of a second; a refused row traces nothing.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.cli import commands as cli
from nebula_rt.errors import SceneError
from nebula_rt.limits import FLOAT32_RANGE_TEXT
from nebula_rt.scene import Scene

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REFUSED, ALLOWED, RUNTIME = "refused", "allowed", "runtime"

BASE = {
    "grid": {"shape": [8, 8, 8]},
    "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0, "temperature": 20000.0, "bump_radius": 0.0}],
    "transport": {"photons": 2000, "backend": TEST_BACKEND, "device": TEST_DEVICE},
}
#: for dust.file: a density file (written beside the scene file by the CLI tests)
BASE_FILE = {**BASE, "dust": {"model": "file", "file": "cloud.npy"}}
#: for the grains' keys: Mie scattering (they are refused by name with any other polarization)
BASE_MIE = {**BASE, "bands": {"polarization": "mie"}}
#: for the tabulated matrix's file: the Pinte et al. 2009 benchmark's grains
PINTE_MATRIX = str(Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "pinte2009" / "mueller_matrix_1um.dat")
BASE_MATRIX = {**BASE, "bands": {"polarization": "matrix", "grain_matrix": PINTE_MATRIX, "albedo": 0.6475}}
#: for White's peak polarization (refused by name with any other polarization)
BASE_WHITE = {**BASE, "bands": {"polarization": "white"}}
#: for the [[bands.list]] keys: two explicit bands, a flat-spectrum star
BASE_LIST = {
    "grid": {"shape": [8, 8, 8]},
    "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0}],
    "bands": {"list": [{"name": "B", "wavelength": 450.0, "extinction": 1.3, "albedo": 0.6, "g": 0.5},
                       {"name": "R", "wavelength": 650.0, "extinction": 0.8, "albedo": 0.6, "g": 0.5}]},
    "transport": {"photons": 2000, "backend": TEST_BACKEND, "device": TEST_DEVICE},
}


@dataclass(frozen=True)
class Row:
    key: str  # the --set key (dotted; arrays by index)
    kind: str
    literal: str  # TOML literal of the value
    expect: str = REFUSED
    note: str = ""
    run: bool = True  # ALLOWED: cheap enough to render through the CLI

    @property
    def parameter(self) -> str:
        """The key as SceneError names it (stars.0.x -> stars[0].x)."""
        parts = self.key.split(".")
        if parts[0] == "stars":
            return f"stars[{parts[1]}]." + ".".join(parts[2:])
        if parts[:2] == ["bands", "list"]:
            return f"bands.list[{parts[2]}]." + ".".join(parts[3:])
        return self.key

    @property
    def value(self):
        return tomllib.loads("v = " + self.literal)["v"]

    @property
    def base(self) -> dict:
        if self.key.startswith("bands.list"):
            return BASE_LIST
        if self.key == "bands.grain_matrix":
            return BASE_MATRIX
        if self.key.startswith("bands.grain_"):
            return BASE_MIE
        if self.key == "bands.peak_polarization":
            return BASE_WHITE
        return BASE_FILE if self.key == "dust.file" else BASE


#: the allowed-range text each key's messages must contain (one of, for a tuple)
RANGES = {
    "grid.shape": "[2, 2147483647]", "grid.length": ("> 0", "units: pc"), "grid.unit": "length unit: pc",
    "dust.model": "'turbulence', 'uniform', 'file'", "dust.density": FLOAT32_RANGE_TEXT, "dust.file": "string",
    "dust.array": "string", "dust.scale": FLOAT32_RANGE_TEXT, "dust.offset": "[-10000, 10000]",
    "dust.particle_mass": "string", "dust.particle_smoothing": "string", "dust.particle_origin": "[-1e+30, 1e+30]",
    "dust.leaf_particles": "[1, 2147483647]", "dust.tree_depth": "[0, 20]",
    "dust.octree": "true or false", "dust.cell_tau": "> 0", "dust.cell_tau_spread": ">= 0",
    "dust.floor": FLOAT32_RANGE_TEXT, "dust.tau": FLOAT32_RANGE_TEXT,
    # the key's own rule, or the range of the dust.tau it converts to
    "dust.hydrogen_density": ("H nuclei per cm^3 >= 0", "gives dust.tau"),
    "dust.mass_density": ("g cm^-3 >= 0", "gives dust.tau"), "dust.visual_extinction": ("A_V in mag >= 0", "gives dust.tau"),
    "stars.0.luminosity_lsun": ("in L_sun > 0", "gives a luminosity"),
    "stars.0.absolute_magnitude": ("M_V in mag", "gives a luminosity"),
    "stars.0.spectral_type": "MK spectral type",
    "stars.0.spectral_calibration": "'auto', 'pecaut-mamajek-2013', 'de-jager-1987'",
    "stars.0.position": "[0, 1]", "stars.0.luminosity": FLOAT32_RANGE_TEXT,
    "stars.0.temperature": "[1000, 1e+07]", "stars.0.bump_radius": "[1.1754944e-38, 1)",
    # the pairs' own rule, or where a valid spectrum must have power
    "stars.0.spectrum": ("[wavelength nm, relative power] pairs", "inside 380-780 nm", "must give every band light"),
    "bands.preset": "preset", "bands.albedo": "[0, 1]", "bands.g": "[-1, 1]",
    "bands.polarization": "'none', 'rayleigh', 'white', 'mie', 'matrix'",
    "bands.grain_matrix": ("string", "a text table of rows"),
    "bands.grain_material": "'astronomical-silicate'",
    "bands.grain_n": ("[0.01, 100]", "one value per band", "must be given with bands.grain_k"),
    "bands.grain_k": ("[0, 100]", "one value per band", "must be given with bands.grain_n"),
    "bands.grain_radius_min": ("[0.0001, 1000]", "at most"),
    "bands.grain_radius_max": ("[0.0001, 1000]", "at least bands.grain_radius_min", "size parameter"),
    "bands.grain_size_slope": "[-10, 10]",
    "bands.peak_polarization": ("[0, 1]", "one value per band", "used only with bands.polarization = 'white'"),
    "bands.list.0.name": "[A-Za-z0-9_-]", "bands.list.0.wavelength": "[1, 1e5]",
    "bands.list.0.extinction": FLOAT32_RANGE_TEXT, "bands.list.0.albedo": "[0, 1]", "bands.list.0.g": "[-1, 1]",
    "transport.photons": "[1, 2**53]", "transport.estimator": "'track-length', 'collision-filter'",
    "transport.method": "'auto', 'analog', 'biased'",
    "transport.error_estimate": "'auto', 'batches', 'packets'",
    "transport.filter_radius": "(0, 1.73205]", "transport.max_scatterings": "[0, 2147483647]",
    "transport.seed": "[0, 2**53]", "transport.backend": "'auto', 'opencl', 'cuda'", "transport.device": "string",
    "transport.batch_size": ("[0, 2**53]", "less than the 2000 photons"), "transport.target_error": "[1e-08, 1)",
    "transport.time_limit": ">= 0", "transport.quality": "'preview'",
    "colour.exposure": FLOAT32_RANGE_TEXT, "colour.white_point": "'D65', 'E', 'star'", "colour.opacity_scale": "> 0",
    "colour.stretch": "'linear', 'asinh'", "colour.asinh_q": "(0, 1e+10]",
    "observer.distance": ("distance > 0", "units: pc"), "observer.ra": "[0, 360)", "observer.dec": "[-90, 90]",
    "observer.position_angle": "[-360, 360]", "observer.psf_fwhm": "arcsec in [0, 648000]",
    "observer.magnitude_system": "'AB', 'Vega', 'Vega-Blanton2007'",
}

FLOAT_KINDS = {"type": '"x"', "nan": "nan", "inf": "inf", "-inf": "-inf", "negative": "-1.5", "zero": "0.0",
               "huge": "1e300", "beyond-float32": "1e39", "below-float32": "1e-40"}
INT_KINDS = {"type": '"x"', "fraction": "1.5", "nan": "nan", "inf": "inf", "negative": "-1", "zero": "0",
             "huge": "1e300", "beyond-int32": str(2**31), "beyond-int64": str(2**63), "beyond-uint64": str(2**64)}


def floats(key, allowed=None, literal=None, vector=None, runtime=None):
    """Rows for a float key: every kind refused unless listed in ``allowed`` or ``runtime``
    ({kind: note}); ``vector``: the key is a 3-vector, the bad value goes into its first component."""
    allowed = allowed or {}
    runtime = runtime or {}
    rows = []
    for kind, lit in FLOAT_KINDS.items():
        lit = (literal or {}).get(kind, lit)
        if vector is not None:
            lit = f"[{lit}, {vector[1]}, {vector[2]}]"
        expect = ALLOWED if kind in allowed else RUNTIME if kind in runtime else REFUSED
        rows.append(Row(key, kind, lit, expect, allowed.get(kind, runtime.get(kind, ""))))
    return rows


def ints(key, allowed=None, vector=None, runs=True):
    allowed = allowed or {}
    rows = []
    for kind, lit in INT_KINDS.items():
        if vector is not None:
            lit = f"[{lit}, {vector[1]}, {vector[2]}]"
        rows.append(Row(key, kind, lit, ALLOWED if kind in allowed else REFUSED, allowed.get(kind, ""),
                        run=runs and kind in allowed and allowed[kind] != "not run"))
    return rows


def strings(key, bad_choices=(), allowed=None, runtime=None):
    rows = [Row(key, "type", "5")]
    rows += [Row(key, "choice", f'"{c}"') for c in bad_choices]
    rows += [Row(key, "string", f'"{v}"', ALLOWED, note) for v, note in (allowed or {}).items()]
    rows += [Row(key, "string", f'"{v}"', RUNTIME, note) for v, note in (runtime or {}).items()]
    return rows


LABEL = "host float64, never on the device (used by the physical keys and calibrated images only)"
SKY = "host float64: used by calibrated sky images only"
TREE = "host float64: an octree's refinement test only (dust.octree)"
TABLE = [
    *ints("grid.shape", vector=(None, 8, 8)),
    *floats("grid.length", {"huge": LABEL, "beyond-float32": LABEL, "below-float32": LABEL}),
    Row("grid.length", "quantity", '"0.3 pc"', ALLOWED, "a length with its unit"),
    Row("grid.length", "light-years", '"1 ly"', ALLOWED, "ly is astropy's lyr"),
    Row("grid.length", "not-a-length", '"3 kg"'),
    Row("grid.length", "unknown-unit", '"3 furlong"'),
    *strings("grid.unit", ["kg", "parsecs"], allowed={"au": "astropy's AU", "km": "any astropy length unit"}),
    *strings("dust.model", ["fractal"]),
    *floats("dust.density", {"zero": "no dust"}),
    *strings("dust.file", runtime={"missing.npy": "checked when the density is made (dust.model = 'file')"}),
    *strings("dust.array"),
    *strings("dust.particle_mass"),
    *strings("dust.particle_smoothing"),
    *floats("dust.particle_origin", {"negative": "a snapshot's coordinates", "zero": "a snapshot's coordinates",
                                     "below-float32": "host float64 (a snapshot's coordinates)"},
            vector=(None, 0.0, 0.0)),
    *ints("dust.leaf_particles"),
    *ints("dust.tree_depth", {"zero": "not run"}),
    Row("dust.octree", "type", '"yes"'),
    Row("dust.octree", "number", "2"),
    Row("dust.octree", "on", "true", ALLOWED, "the procedural density on an octree (its own tests)", run=False),
    *floats("dust.cell_tau", {"huge": TREE, "beyond-float32": TREE, "below-float32": TREE}),
    *floats("dust.cell_tau_spread", {"zero": "split wherever the density varies", "huge": TREE,
                                   "beyond-float32": TREE, "below-float32": TREE}),
    *floats("dust.scale", {"zero": "no turbulence: the floor and the bumps"}),
    *floats("dust.offset", {"negative": "any offset in [-1e4, 1e4]", "zero": "any offset in [-1e4, 1e4]",
                            "below-float32": "rounded to float32: moves the nebula by < 1e-38 box units"},
            vector=(None, 0.5, 0.5)),
    Row("dust.offset", "beyond-precision", "[2e4, 0.5, 0.5]"),
    *floats("dust.floor", {"zero": "no minimum density"}),
    *floats("dust.tau", {"zero": "vacuum"}),
    # tau = n_H x 4.86e-22 cm^2 x 3.09e18 cm (the base scene's 1 pc box) = 1.5e-3 n_H
    *floats("dust.hydrogen_density", {"zero": "no dust: tau 0"},
            runtime={"beyond-float32": "tau 1.5e36: the densest voxel's mean free path is below the track-length "
                                       "resolution"}),
    # tau = rho_d / 1.87e-26 g x 4.86e-22 cm^2 x 3.09e18 cm = 8.0e22 rho_d
    *floats("dust.mass_density", {"zero": "no dust: tau 0", "below-float32": "tau 8e-18: thin dust"}),
    # tau = 0.914 A_V
    *floats("dust.visual_extinction", {"zero": "no dust: tau 0"}),
    *floats("stars.0.position", {"zero": "on the box face",
                                 "below-float32": "rounded to float32: moves the star by < 1e-38 box units"},
            vector=(None, 0.5, 0.5)),
    *floats("stars.0.luminosity"),
    Row("stars.0.luminosity", "J-overflow", "1e38", RUNTIME, "J of this grid and max_scatterings overflows float32"),
    Row("stars.0.luminosity", "J-underflow", "1e-30", RUNTIME, "J's smallest tally underflows float32"),
    *floats("stars.0.temperature", {"zero": "a flat spectrum"}, literal={"negative": "-5000.0"}),
    # 13.3 % of a 20,000 K blackbody lies inside the bands' 380-780 nm
    *floats("stars.0.luminosity_lsun", runtime={"beyond-float32": "1.3e38 L_sun inside the bands: J overflows"}),
    *floats("stars.0.absolute_magnitude", {"negative": "a bright star, M_V = -1.5", "zero": "M_V = 0",
                                           "below-float32": "M_V = 1e-40, i.e. 0"}),
    # 10^(0.4 x 1e300) overflows float64: refused with the magnitudes that fit, not an OverflowError
    Row("stars.0.absolute_magnitude", "huge-negative", "-1e300"),
    Row("stars.0.temperature", "too-cool", "10.0"),
    # no luminosity class, O0 and B10 (no such types), a class letter DJ87 does not calibrate
    *strings("stars.0.spectral_type", ["B2", "O0V", "B10V", "X5III", "B2 VI"],
             allowed={"B2.5 IV": "a decimal subtype, a space", "M10V": "DJ87's coolest type",
                      "O1Ia+": "DJ87's hottest type, a hypergiant"}),
    *strings("stars.0.spectral_calibration", ["PM13", "Auto"],
             allowed={"de-jager-1987": "the old calibration by name", "pecaut-mamajek-2013": "dwarfs"}),
    *floats("stars.0.bump_radius", {"zero": "no bump"}),
    *[Row("stars.0.spectrum", kind, lit) for kind, lit in {
        "type": '"x"', "nan": "[[nan, 1.0], [700.0, 1.0]]", "inf": "[[400.0, inf], [700.0, 1.0]]",
        "negative": "[[400.0, -1.0], [700.0, 1.0]]", "zero": "[[400.0, 0.0], [700.0, 0.0]]",
        "huge": "[[400.0, 1.0], [1e300, 1.0]]", "outside-visible": "[[100.0, 1.0], [200.0, 1.0]]",
        "band-without-light": "[[620.0, 1.0], [700.0, 1.0]]"}.items()],
    *strings("bands.preset", ["ultraviolet"]),
    *floats("bands.albedo", {"zero": "no scattering"}),
    *floats("bands.g", {"zero": "isotropic"}),
    *strings("bands.polarization", ["Mie", "White"], allowed={"white": "HG with White's polarization",
                                                             "mie": "Mie grains: MRN astronomical silicate"}),
    *strings("bands.grain_material", ["silicate"]),
    # the refractive index alone is refused (n without k); with its partner see tests/optics/test_mie.py
    *[Row(f"bands.grain_{key}", kind, lit) for key in ("n", "k") for kind, lit in {
        "type": '"x"', "nan": "nan", "inf": "inf", "negative": "-1.5", "huge": "1e300", "alone": "1.5"}.items()],
    *floats("bands.grain_radius_min"),
    *floats("bands.grain_radius_max"),
    Row("bands.grain_radius_max", "below-radius_min", "0.001"),
    Row("bands.grain_radius_max", "beyond-size-parameter", "900.0"),
    Row("bands.grain_radius_max", "one-size", "0.005", ALLOWED, "grains of one size (0.005 micron)"),
    *floats("bands.grain_size_slope", {"zero": "n(a) flat in a", "negative": "more large grains than small",
                                       "below-float32": "as good as 0"}),
    *strings("bands.grain_matrix", allowed={PINTE_MATRIX: "the Pinte et al. 2009 benchmark's grains"}),
    Row("bands.grain_matrix", "empty", '""'),
    Row("bands.grain_matrix", "missing", '"missing.dat"'),
    Row("bands.grain_matrix", "folder", '"/tmp"'),
    Row("bands.grain_matrix", "not-a-table", f'"{__file__}"'),
    *floats("bands.peak_polarization", {"zero": "unpolarized light stays so (White's p_l = 0)",
                                        "below-float32": "p_l 1e-40: as good as 0"}),
    Row("bands.peak_polarization", "list", "[0.3, 0.4, 0.5]", ALLOWED, "one per band (thesis-rgb: 3)"),
    Row("bands.peak_polarization", "list-too-long", "[0.3, 0.4, 0.5, 0.6]"),
    Row("bands.peak_polarization", "list-above-1", "[0.3, 1.5, 0.5]"),
    *strings("bands.list.0.name", ["a b", ""]),
    *floats("bands.list.0.wavelength"),
    Row("bands.list.0.wavelength", "below-1-nm", "0.5"),
    *floats("bands.list.0.extinction"),
    *floats("bands.list.0.albedo", {"zero": "no scattering"}),
    *floats("bands.list.0.g", {"zero": "isotropic"}),
    *ints("transport.photons", {"beyond-int32": "not run"}),
    *strings("transport.estimator", ["photon-map"]),
    *strings("transport.method", ["weighted"]),
    *strings("transport.error_estimate", ["jackknife"]),
    *floats("transport.filter_radius", {"below-float32": "no smoothing (the kernel is one voxel)"}),
    *ints("transport.max_scatterings", {"zero": "single scattering off; packets terminate at the first"}),
    *ints("transport.seed", {"zero": "any integer up to 2**53", "beyond-int32": "any integer up to 2**53"}),
    Row("transport.seed", "largest", str(2**53), ALLOWED, "the largest: what a double holds exactly"),
    Row("transport.seed", "past-double", str(2**53 + 1), note="a double (the panel, pvpython) would round it"),
    *strings("transport.backend", ["metal"]),
    *strings("transport.device"),
    *ints("transport.batch_size", {"zero": "automatic"}),
    Row("transport.batch_size", "single-batch", "2000", note="one batch: no error estimate"),
    # below 1e-8 (1e-40 here) no budget of packets reaches the target: refused before tracing
    *floats("transport.target_error", {"zero": "off"}),
    Row("transport.target_error", "one", "1.0"),
    Row("transport.target_error", "beyond-any-budget", "1e-300"),
    Row("transport.target_error", "smallest", "1e-8", ALLOWED, "about 1 / sqrt(2**53): the largest budget's reach",
        run=False),
    *floats("transport.time_limit", {"zero": "none", "huge": "seconds, host float64",
                                     "beyond-float32": "seconds, host float64",
                                     "below-float32": "seconds, host float64 (used only with a target error)"}),
    *strings("transport.quality", ["best"]),
    *floats("colour.exposure", literal={"type": '"bright"'}),
    *strings("colour.white_point", ["D50"]),
    *floats("colour.opacity_scale", {"huge": "opacity 1 wherever there is dust (host float64)",
                                     "beyond-float32": "opacity 1 wherever there is dust (host float64)",
                                     "below-float32": "transparent (host float64)"}),
    Row("colour.opacity_scale", "auto", '"auto"', ALLOWED, "the factor chosen from the data (the default)"),
    *strings("colour.stretch", ["log"], allowed={"asinh": "Lupton et al. (2004)"}),
    *floats("colour.asinh_q", {"below-float32": "host float64: the linear curve in the limit"}),
    # 1e300 pc is 3e316 m, infinite in float64; 1e39 pc (3e55 m) and 1e-40 pc (3e-24 m) lie in [1e-150, 1e150] m
    *floats("observer.distance", {"beyond-float32": SKY, "below-float32": SKY}),
    Row("observer.distance", "quantity", '"140 pc"', ALLOWED, "a distance with its unit"),
    Row("observer.distance", "quantity-beyond-float64", '"1e308 Mpc"'),
    Row("observer.distance", "quantity-below-float64", '"1e-300 pc"'),
    Row("observer.distance", "not-a-length", '"3 s"'),
    *floats("observer.ra", {"zero": SKY, "below-float32": SKY}),
    Row("observer.ra", "full-circle", "360.0"),
    *floats("observer.dec", {"negative": SKY, "zero": SKY, "below-float32": SKY}),
    Row("observer.dec", "beyond-pole", "90.5"),
    *floats("observer.position_angle", {"negative": SKY, "zero": SKY, "below-float32": SKY}),
    # at most 180 deg (648000 arcsec): 1e300 arcsec made an image of zeros
    *floats("observer.psf_fwhm", {"zero": "no PSF", "below-float32": SKY}),
    Row("observer.psf_fwhm", "widest", "648000.0", ALLOWED, SKY + " (wider than the image: the light leaves it)"),
    *strings("observer.magnitude_system", ["ST", "ab"], allowed={"Vega": "CALSPEC", "Vega-Blanton2007": "Blanton & Roweis 2007"}),
]
# "negative" is -1.5 for every float key: below g's -1 too


def test_every_key_is_in_the_table():
    from nebula_rt.scene.rules import _SCHEMA

    keys = set()
    for table, rules in _SCHEMA.items():
        if isinstance(rules, list):
            keys |= {f"{table}.0.{k}" for k in rules[0]}
        else:
            for k, r in rules.items():
                if isinstance(r, list):
                    keys |= {f"{table}.{k}.0.{kk}" for kk in r[0]}
                else:
                    keys.add(f"{table}.{k}")
    assert keys == {r.key for r in TABLE} == set(RANGES)


def _ids(rows):
    return [f"{r.key}={r.kind}" for r in rows]


def _toml_with(row: Row) -> str:
    """The base scene with the row's value, as TOML text (the --set path would give the same)."""
    import tomli_w

    d = Scene.from_dict(row.base).to_dict()
    tokens = row.key.split(".")
    node = d
    for t in tokens[:-1]:
        node = node[int(t)] if t.isdigit() else node.setdefault(t, {})
    node[tokens[-1]] = row.value
    # a physical key sets the box-unit value it replaces: the file gives one of them
    if row.key in ("dust.hydrogen_density", "dust.mass_density", "dust.visual_extinction"):
        del node["tau"]
    if row.key in ("stars.0.luminosity_lsun", "stars.0.absolute_magnitude"):
        del node["luminosity"]
    if row.key == "stars.0.spectral_type":
        node.pop("temperature", None)
    return tomli_w.dumps(d)


def _check_message(err: SceneError, row: Row):
    assert err.parameter == row.parameter, str(err)
    text = str(err)
    v = row.value
    shown = repr(v)
    assert shown in text or (isinstance(v, float) and repr(float(v)) in text), (shown, text)
    expected = RANGES[row.key] if isinstance(RANGES[row.key], tuple) else (RANGES[row.key],)
    assert any(e in text for e in expected), (expected, text)


@pytest.mark.parametrize("row", [r for r in TABLE if r.expect == REFUSED], ids=_ids([r for r in TABLE if r.expect == REFUSED]))
def test_a_scene_refuses(row):
    with pytest.raises(SceneError) as info:
        Scene.from_dict(row.base).with_overrides([f"{row.key}={row.literal}"])
    _check_message(info.value, row)
    with pytest.raises(SceneError) as info:
        Scene.loads(_toml_with(row))
    _check_message(info.value, row)


@pytest.mark.parametrize("row", [r for r in TABLE if r.expect != REFUSED], ids=_ids([r for r in TABLE if r.expect != REFUSED]))
def test_a_scene_accepts(row):
    s = Scene.from_dict(row.base).with_overrides([f"{row.key}={row.literal}"])
    assert Scene.loads(_toml_with(row)) == s


def _cli(tmp_path, row: Row, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(Scene.from_dict(row.base).to_toml())
    np.save(tmp_path / "cloud.npy", np.ones((8, 8, 8)))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    status = cli.main(["render", str(scene), "-o", str(out_dir / "out.vti"), "--set", f"{row.key}={row.literal}", "-q"])
    return status, capsys.readouterr().err, sorted(p.name for p in out_dir.iterdir())


@pytest.mark.parametrize("row", [r for r in TABLE if r.expect != ALLOWED], ids=_ids([r for r in TABLE if r.expect != ALLOWED]))
def test_b_cli_refuses(tmp_path, capsys, row):
    status, err, written = _cli(tmp_path, row, capsys)
    assert status == 2, err
    assert row.parameter in err and "Traceback" not in err
    assert written == []


@pytest.mark.parametrize("row", [r for r in TABLE if r.expect == ALLOWED and r.run],
                         ids=_ids([r for r in TABLE if r.expect == ALLOWED and r.run]))
def test_b_cli_renders_allowed_values(tmp_path, capsys, row):
    status, err, written = _cli(tmp_path, row, capsys)
    assert status == 0, err
    assert written == ["out.vti"]


# --- (c) the VTK filters ---------------------------------------------------------------------
#: key -> (filter, setter, how the value becomes the setter's arguments)
STAR = [0.5, 0.5, 0.5, 1.0, 20000.0, 0.0]


def _star_with(index):
    def args(v):
        flat = list(STAR)
        flat[index] = v[0] if isinstance(v, list) else v
        return (flat,)
    return args


SETTERS = {
    "grid.shape": ("density", "SetGridShape", lambda v: tuple(v)),
    "dust.model": ("density", "SetModel", lambda v: (v,)),
    "dust.density": ("density", "SetUniformDensity", lambda v: (v,)),
    "dust.scale": ("density", "SetScale", lambda v: (v,)),
    "dust.offset": ("density", "SetOffset", lambda v: tuple(v)),
    "dust.floor": ("density", "SetFloor", lambda v: (v,)),
    "dust.tau": ("light", "SetTau", lambda v: (v,)),
    "stars.0.position": ("light", "SetStars", _star_with(0)),
    "stars.0.luminosity": ("light", "SetStars", _star_with(3)),
    "stars.0.temperature": ("light", "SetStars", _star_with(4)),
    "stars.0.bump_radius": ("density", "SetStars", _star_with(5)),
    "bands.preset": ("light", "SetBandPreset", lambda v: (v,)),
    "bands.albedo": ("light", "SetAlbedo", lambda v: (v,)),
    "bands.g": ("light", "SetG", lambda v: (v,)),
    "bands.polarization": ("light", "SetPolarization", lambda v: (v,)),
    "bands.peak_polarization": ("light", "SetPeakPolarization", lambda v: (v,)),
    "transport.photons": ("light", "SetPhotons", lambda v: (v,)),
    "transport.estimator": ("light", "SetEstimator", lambda v: (v,)),
    "transport.method": ("light", "SetMethod", lambda v: (v,)),
    "transport.error_estimate": ("light", "SetErrorEstimate", lambda v: (v,)),
    "transport.filter_radius": ("light", "SetFilterRadius", lambda v: (v,)),
    "transport.max_scatterings": ("light", "SetMaxScatterings", lambda v: (v,)),
    "transport.seed": ("light", "SetSeed", lambda v: (v,)),
    "transport.backend": ("light", "SetBackend", lambda v: (v,)),
    "transport.device": ("light", "SetDevice", lambda v: (v,)),
    "transport.batch_size": ("light", "SetBatchSize", lambda v: (v,)),
    "transport.target_error": ("light", "SetTargetError", lambda v: (v,)),
    "transport.quality": ("light", "SetQuality", lambda v: (v,)),
    "colour.exposure": ("colour", "SetExposure", lambda v: (v,)),
    "colour.white_point": ("colour", "SetWhitePoint", lambda v: (v,)),
    "colour.opacity_scale": ("colour", "SetOpacityScale", lambda v: (v,)),
    "colour.stretch": ("colour", "SetStretch", lambda v: (v,)),
    "colour.asinh_q": ("colour", "SetAsinhQ", lambda v: (v,)),
    "observer.distance": ("sky", "SetDistance", lambda v: (v,)),
    "observer.ra": ("sky", "SetRA", lambda v: (v,)),
    "observer.dec": ("sky", "SetDec", lambda v: (v,)),
    "observer.position_angle": ("sky", "SetPositionAngle", lambda v: (v,)),
    "observer.psf_fwhm": ("sky", "SetPSFFWHM", lambda v: (v,)),
    "observer.magnitude_system": ("sky", "SetMagnitudeSystem", lambda v: (v,)),
}
#: rows whose value means something else to the setter than to the scene file
SETTER_MEANS_ELSE = {
    ("stars.0.temperature", "type"): "refused as a whole by the Stars property (checked below by name only)",
    ("transport.backend", "type"): "an integer selects a backend by index",
    ("transport.estimator", "type"): "an integer selects an estimator by index",
    ("transport.method", "type"): "an integer selects a method by index",
    ("transport.error_estimate", "type"): "an integer selects an error estimate by index",
    ("colour.white_point", "type"): "an integer selects a white point by index",
    ("colour.stretch", "type"): "an integer selects a stretch by index",
    ("dust.model", "type"): "an integer selects a model by index",
    ("transport.quality", "type"): "an integer selects a quality by index",
    ("transport.batch_size", "single-batch"): "the filter's photon count is its own (100000)",
}
FILTER_ROWS = [r for r in TABLE if r.expect == REFUSED and r.key in SETTERS
               and (r.key, r.kind) not in SETTER_MEANS_ELSE]


@pytest.fixture(scope="module")
def light_field_image():
    """A tiny traced light field (the Colour filter's input)."""
    from nebula_rt.filters import NebulaLightField

    lf = _light()
    lf.SetPhotons(1000)
    lf.Update()
    assert lf.last_error is None
    assert isinstance(lf, NebulaLightField)
    return lf.GetOutputDataObject(0)


def _producer(img):
    from vtkmodules.vtkCommonExecutionModel import vtkTrivialProducer

    p = vtkTrivialProducer()
    p.SetOutput(img)
    return p


def _light():
    from nebula_rt.filters import NebulaLightField
    from nebula_rt.filters.image_data import to_image_data

    lf = NebulaLightField()
    lf._producer = _producer(to_image_data({"density": np.ones((8, 8, 8), np.float32)}, None, (1, 1, 1)))
    lf.SetInputConnection(lf._producer.GetOutputPort())
    lf.SetBackend(TEST_BACKEND)
    lf.SetDevice(TEST_DEVICE)
    lf.SetStars(STAR)
    lf.SetOverrideOptics(1)  # Albedo and G apply (the rows of bands.albedo and bands.g)
    return lf


@pytest.mark.parametrize("row", FILTER_ROWS, ids=_ids(FILTER_ROWS))
def test_c_filter_setter_refuses(row, light_field_image):
    from nebula_rt.filters import NebulaColour, NebulaDustDensity, NebulaSkyImage

    which, setter, args = SETTERS[row.key]
    if which == "density":
        alg = NebulaDustDensity()
        alg.SetGridShape(8, 8, 8)
        alg.SetBackend(TEST_BACKEND)
        alg.SetDevice(TEST_DEVICE)
    elif which == "light":
        alg = _light()
        if row.key == "bands.peak_polarization":
            alg.SetPolarization("white")  # (it applies to White's approximation alone)
    elif which == "sky":  # the observer is checked in box units too, before the ray march
        alg = NebulaSkyImage()
        alg._producer = _producer(light_field_image)
        alg.SetInputConnection(alg._producer.GetOutputPort())
        alg.SetImageSize(4, 4)
    else:
        alg = NebulaColour()
        alg._producer = _producer(light_field_image)
        alg.SetInputConnection(alg._producer.GetOutputPort())
        alg.SetAutoExposure(False)  # the numbers apply (the rows of colour.exposure and opacity_scale)
        alg.SetAutoOpacity(False)
    getattr(alg, setter)(*args(row.value))
    alg.Update()
    assert alg.GetOutputDataObject(0).GetNumberOfPoints() == 0
    from nebula_rt.scene.schema import label

    # the message names the property as the panel shows it (a bound property: its label)
    prop = setter[3:]
    shown = {p.name: label(p.key, p.param) for p in getattr(alg, "BOUND_PROPERTIES", ())}.get(prop, prop)
    assert alg.last_error is not None and shown in alg.last_error, alg.last_error
    if row.key.startswith("stars") and row.kind == "type":
        return  # the Stars vector is refused as a whole: "Stars = [...]: must hold 6 numbers per star"
    assert row.parameter in alg.last_error, alg.last_error


def test_table_covers_float32_and_integer_limits():
    kinds = {(r.key, r.kind) for r in TABLE}
    for key in ("dust.tau", "dust.density", "stars.0.luminosity", "bands.list.0.extinction"):
        assert (key, "beyond-float32") in kinds and (key, "below-float32") in kinds
    for key in ("grid.shape", "transport.max_scatterings", "transport.seed", "transport.photons"):
        assert {(key, "beyond-int32"), (key, "beyond-int64")} <= kinds
    assert math.isinf(Row("x", "inf", "inf").value)


def test_note_of_every_allowed_row():
    assert all(r.note for r in TABLE if r.expect != REFUSED)
