"""Numbers that break deep inside are refused where they enter, and nothing is compared with
nothing.

Each row of CASES is one command line with a number that used to fail far from where it
entered: an internal error (exit 1), an image of NaN or of zeros, a chi^2 of null with a p-value
of 0, a trace that failed only once it had run, an option clipped into range without a word.
Each must now exit with status 2 before anything is traced, naming the key or option (and, for a
table, the file and the row) on one line of stderr, and write nothing.

``nebula_rt.cli.main`` runs in process on 8^3 scenes of 20,000 packets per band; the refused
rows trace nothing (``TransportRequest.trace`` is watched), so the table takes seconds. The
library's rule for comparisons (no row, ring or pixel compared with nothing) is tested below it
on hand-made geometry and ring sums.
"""

from __future__ import annotations

import json
import math
import shlex
from dataclasses import dataclass

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.cli import commands as cli
from nebula_rt.errors import SceneError
from nebula_rt.observe import calibrate, comparison, fit
from nebula_rt.observe.observed_tables import ObservedTable, read_table
from nebula_rt.observe.sky import Camera
from nebula_rt.scene import Scene, sky_schema
from nebula_rt.transport.request import TransportRequest

#: Delta(B-V) needs bands at or below 480 nm and at or above 520 nm: spectral-8
COLOUR_SCENE = {
    "grid": {"shape": [8, 8, 8]},
    "dust": {"model": "uniform", "density": 1.0, "tau": 1.0},
    "stars": [{"position": [0.5, 0.5, 0.5], "temperature": 10000.0}],
    "bands": {"preset": "spectral-8"},
    "transport": {"photons": 20_000, "backend": TEST_BACKEND, "device": TEST_DEVICE},
}
#: a scene in physical units on the sky, for calibrated images (nebula-rt sky, compare --image)
SKY_SCENE = {
    "grid": {"shape": [8, 8, 8], "length": "0.5 pc"},
    "dust": {"model": "uniform", "density": 1.0, "hydrogen_density": 2700.0},
    "stars": [{"position": [0.5, 0.5, 0.5], "absolute_magnitude": -1.5, "temperature": 14000.0}],
    "bands": {"preset": "thesis-rgb"},
    "transport": {"photons": 20_000, "backend": TEST_BACKEND, "device": TEST_DEVICE},
    "observer": {"distance": "136 pc", "psf_fwhm": 2.0},
}

#: the observed tables of the rows, CSV text by file name; the box seen along -z from its
#: centre reaches sqrt(0.5) = 0.7071 box units
TABLES = {
    "colour.csv": "offset,delta_bv,delta_bv_err\n0.1,-0.2,0.05\n0.3,-0.1,0.05\n",
    "far.csv": "offset,offset_lo,offset_hi,delta_bv,delta_bv_err\n0.3,0.2,0.4,-0.1,0.05\n5,4,6,0.1,0.05\n",
    "thin.csv": "offset,offset_lo,offset_hi,delta_bv,delta_bv_err\n0.1,0.1,0.1001,-0.2,0.05\n0.3,0.2,0.4,-0.1,0.05\n",
    "huge-offset.csv": "offset,delta_bv,delta_bv_err\n0.1,-0.2,0.05\n1e308,-0.1,0.05\n",
    "huge-value.csv": "offset,delta_bv,delta_bv_err\n0.1,1e308,0.05\n0.3,-0.1,0.05\n",
    "huge-error.csv": "offset,delta_bv,delta_bv_err\n0.1,-0.2,1e308\n0.3,-0.1,0.05\n",
    "tiny-error.csv": "offset,delta_bv,delta_bv_err\n0.1,-0.2,1e-320\n0.3,-0.1,0.05\n",
    "ratio.csv": "wavelength [nm],ratio,ratio_err\n455,1.2,0.1\n555,1.0,0.1\n655,0.9,0.1\n",
    "huge-ratio.csv": "wavelength [nm],ratio,ratio_err\n455,1e308,0.1\n555,1.0,0.1\n",
    "arcsec.csv": "offset [arcsec],delta_bv,delta_bv_err\n20,-0.2,0.05\n40,-0.1,0.05\n",
}


@dataclass(frozen=True)
class Case:
    id: str
    args: str  # the command line after nebula-rt; {colour} and {sky} are the scenes, {dir} the folder
    names: tuple  # what stderr must name: the key or option, and the file, row and range where there is one
    before: str  # what the command did before


FIT = "fit {colour} --table {dir}/colour.csv --size 16 --uncertainty none --png {dir}/out/f.png"
COMPARE = "compare {colour} --size 16 --png {dir}/out/c.png"
SKY = "sky {sky} --size 16 --fits {dir}/out/s.fits"

CASES = [
    # 1. comparisons that compare nothing
    Case("table-beyond-the-image", COMPARE + " --table {dir}/far.csv",
         ("--table", "far.csv", "row 2", "0.7071"), "exit 0, chi2 null, p_value 0.0"),
    Case("annulus-beyond-the-image", COMPARE + " --table {dir}/ratio.csv --annulus 5,6",
         ("--table", "ratio.csv", "row 1", "0.7071"), "exit 0, chi2 null, p_value 0.0"),
    Case("annulus-between-pixels", COMPARE + " --table {dir}/thin.csv",
         ("--table", "thin.csv", "row 1", "--size"), "exit 0, chi2 null (a ring of no pixel)"),
    Case("huge-offset", COMPARE + " --table {dir}/huge-offset.csv",
         ("--table", "huge-offset.csv", "row 2", "0.7071"), "internal error: Camera.extent infinite"),
    Case("fit-table-beyond-the-image", FIT.replace("colour.csv", "far.csv") + " --free albedo",
         ("--table", "far.csv", "row 2"), "a fit of infinite chi^2 at every trial"),
    # 2. numbers that break deep inside
    Case("direction-overflows", COMPARE + " --direction=1e308,1e308,0", ("--direction", "1e150"),
         "internal error: broadcast of a NaN image"),
    Case("direction-underflows", COMPARE + " --direction=1e-320,0,0", ("--direction", "1e-150"),
         "internal error: broadcast of a NaN image"),
    Case("sky-direction-underflows", SKY + " --direction=1e-320,0,0", ("--direction", "1e-150"),
         "internal error"),
    Case("absolute-magnitude", SKY + " --set stars.0.absolute_magnitude=-1e308",
         ("stars[0].absolute_magnitude", "M_V in ["), "internal error: OverflowError"),
    Case("target-error", COMPARE + " --set transport.target_error=1e-300",
         ("transport.target_error", "[1e-08, 1)"), "internal error: OverflowError after tracing"),
    Case("target-error-option", COMPARE + " --target-error 1e-300",
         ("transport.target_error", "[1e-08, 1)"), "internal error: OverflowError after tracing"),
    Case("distance", SKY + " --set 'observer.distance=\"1e308 Mpc\"'",
         ("observer.distance", "1e150] m"), "internal error: ZeroDivisionError"),
    Case("psf-fwhm", SKY + " --set observer.psf_fwhm=1e308", ("observer.psf_fwhm", "[0, 648000]"),
         "exit 0, an image of zeros"),
    Case("table-value", COMPARE + " --table {dir}/huge-value.csv", ("huge-value.csv", "'delta_bv', row 1", "1e50"),
         "exit 0, chi2 null, p_value 0.0"),
    Case("table-error", COMPARE + " --table {dir}/huge-error.csv", ("huge-error.csv", "'delta_bv_err', row 1"),
         "internal error: arange of the plot's axis"),
    Case("table-error-underflows", COMPARE + " --table {dir}/tiny-error.csv",
         ("tiny-error.csv", "'delta_bv_err', row 1", "1e-50"), "exit 0, the data's error left out of chi^2"),
    Case("table-ratio", COMPARE + " --table {dir}/huge-ratio.csv", ("huge-ratio.csv", "'ratio', row 1"),
         "exit 0, chi2 null, p_value 0.0"),
    Case("table-distance", COMPARE + " --table {dir}/arcsec.csv --box-length 0.5pc --distance 1e308Mpc",
         ("--distance", "1e150] m"), "exit 2 naming the table's offsets, not the distance"),
    Case("fit-grid", FIT + " --free albedo --grid -5", ("--grid", ">= 0"), "exit 0, no grid"),
    Case("fit-grid-points", FIT + " --free albedo --free g --grid 400", ("--grid", "100,000"),
         "160,000 traces started"),
    Case("fit-starts", FIT + " --free albedo --starts -3", ("--starts", ">= 0"), "exit 0, clipped to 0"),
    Case("fit-albedo-bounds", FIT + " --free albedo=-5:5", ("--free albedo", "[0, 1]"),
         "exit 0, every band's albedo clipped to [0, 1]"),
    Case("fit-g-bounds", FIT + " --free g=-3:3", ("--free g", "[-1, 1]"), "exit 0, g clipped to [-1, 1]"),
    Case("fit-band-bounds", FIT + " --free g.555nm=0:2", ("--free g.555nm", "[-1, 1]"), "exit 0, clipped"),
    Case("fit-slope-bounds", FIT + " --free albedo_slope=-100:100", ("--free albedo_slope", "[-1, 1]"),
         "exit 0, every band clipped to 0 or 1"),
    Case("fit-tau-bounds", FIT + " --free tau=-1:1", ("--free tau", "dust.tau"),
         "exit 2 naming dust.tau once the device was opened"),
]


@pytest.fixture
def folder(tmp_path):
    """The scenes and tables of the rows, an empty output folder, and a watch on the transport."""
    for name, text in TABLES.items():
        (tmp_path / name).write_text(text)
    (tmp_path / "colour.toml").write_text(Scene.from_dict(COLOUR_SCENE).to_toml())
    (tmp_path / "sky.toml").write_text(Scene.from_dict(SKY_SCENE).to_toml())
    (tmp_path / "out").mkdir()
    return tmp_path


@pytest.fixture
def traces(monkeypatch):
    """Every trace a command starts (a refused command starts none)."""
    started = []
    real = TransportRequest.trace

    def watched(self, *a, **k):
        started.append(self)
        return real(self, *a, **k)

    monkeypatch.setattr(TransportRequest, "trace", watched)
    return started


def _run(folder, args: str, capsys):
    line = args.format(colour=folder / "colour.toml", sky=folder / "sky.toml", dir=folder)
    status = cli.main(shlex.split(line))
    out = capsys.readouterr()
    return status, out.out, out.err


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_hostile_number_is_refused_where_it_enters(folder, traces, capsys, case):
    status, _, err = _run(folder, case.args, capsys)
    lines = [ln for ln in err.splitlines() if ln.startswith("nebula-rt:") and "warning" not in ln]
    assert status == 2, err
    assert len(lines) == 1 and "internal error" not in err and "Traceback" not in err, err
    for name in case.names:
        assert name in lines[0], (name, lines[0])
    assert traces == []  # refused before any trace
    assert list((folder / "out").iterdir()) == []


def test_an_annulus_past_the_box_is_the_box_not_an_infinite_image(folder, traces, capsys):
    """A ratio table's annulus out to 1e308 box units (was: an internal error, the field of view
    infinite) compares the light of the whole box: the image stops at the box's reach, so it is
    the same comparison, to the bit, as an annulus out to 2 (beyond every pixel either way)."""
    chi2 = {}
    for hi in ("2", "1e308"):
        status, out, err = _run(folder, COMPARE + " --table {dir}/ratio.csv --annulus 0," + hi, capsys)
        assert status == 0, err
        summary = json.loads(out)
        chi2[hi] = summary["chi2"]
        assert summary["chi2"] is not None and summary["p_value"] is not None
        (folder / "out" / "c.png").unlink()
    assert chi2["2"] == chi2["1e308"] and math.isfinite(chi2["2"])
    assert len(traces) == 2


def test_mask_stars_that_leave_no_pixel_are_refused_before_the_trace(folder, traces, capsys):
    """``compare --image --mask-stars`` with a radius covering every model pixel (was: refused
    after the trace, naming observed_err): refused before it, naming --mask-stars. The image is
    a constant surface brightness on the model image's own WCS (no trace needed to make it)."""
    from astropy.io import fits

    scene = Scene.from_dict(SKY_SCENE)
    cam = calibrate.camera_for(scene, size=16)
    header = calibrate.celestial_wcs(scene, cam).to_header()
    header["BUNIT"] = "MJy/sr"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.ones((16, 16)), header=header, name="SCI")]).writeto(
        folder / "obs.fits")
    args = ("compare {sky} --image {dir}/obs.fits --image-band G --image-error 5% --size 16 "
            "--png {dir}/out/i.png --mask-stars 1e308")
    status, _, err = _run(folder, args, capsys)
    assert status == 2 and "--mask-stars" in err and "internal error" not in err, err
    assert traces == [] and list((folder / "out").iterdir()) == []


# --- the library: directions ------------------------------------------------------------------


@pytest.mark.parametrize("field", ["direction", "up"])
@pytest.mark.parametrize("value", [(1e308, 1e308, 0.0), (1e-320, 0.0, 0.0), (1e200, 0.0, 0.0), (0.0, 0.0, 0.0)])
def test_the_camera_refuses_a_direction_that_does_not_normalise(field, value):
    """sky.direction and sky.up are normalised in float64: components within +-1e150 and a
    length of at least 1e-150 (the declared range and rule); the message names the field."""
    with pytest.raises(ValueError, match=f"Camera.{field} must be .*1e-150"):
        Camera(**{field: value})
    assert not sky_schema.valid_direction(value)


def test_the_direction_rule_is_declared_and_holds_at_its_ends():
    for key in ("sky.direction", "sky.up"):
        p = sky_schema.declaration(key)
        assert (p.lo, p.hi) == (-1e150, 1e150) and p.check is sky_schema.valid_direction
    # the extremes the rule admits make an orthonormal basis, the refused ones would not
    for d in [(1e150, 1e150, 1e150), (1e-150, 0.0, 0.0), (0.0, -1e150, 0.0)]:
        dd, u, v = Camera(direction=d, up=(1e-150, 1e-150, 1e-150)).basis()
        np.testing.assert_allclose([dd @ dd, u @ u, v @ v, dd @ u, dd @ v, u @ v], [1, 1, 1, 0, 0, 0], atol=1e-12)


# --- the library: comparisons of nothing ------------------------------------------------------


def _colour_table(lo, hi, path="t.csv"):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    n = len(lo)
    return ObservedTable("colour", path, 0.5 * (lo + hi), np.zeros(n), np.full(n, 0.05), lo, hi)


@pytest.mark.parametrize("star, direction, reach", [
    ((0.5, 0.5, 0.5), (0.0, 0.0, -1.0), math.sqrt(0.5)),  # the square's half-diagonal
    ((0.5, 0.5, 0.5), (1.0, 1.0, 1.0), math.sqrt(2.0 / 3.0)),  # the hexagon's circumradius
    ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), math.sqrt(2.0)),  # a corner star: the far corner of the square
    ((0.5, 0.5, 0.2), (0.0, 1.0, 0.0), math.hypot(0.5, 0.8)),  # along y: the x-z square, off centre
])
def test_the_box_reach_is_its_farthest_corner_on_the_sky(star, direction, reach):
    assert comparison.box_reach(star, direction) == pytest.approx(reach, rel=1e-12)


def test_compare_refuses_rows_beyond_the_box_before_tracing(backend, traces):
    scene = Scene.from_dict(COLOUR_SCENE)
    inside, beyond = _colour_table([0.1, 0.3], [0.3, 0.5]), _colour_table([0.1, 0.71], [0.3, 0.9], "beyond.csv")
    comparison.check_tables_against_scene(scene, [inside], direction=(0, 0, -1), size=16)  # no error
    with pytest.raises(SceneError) as e:
        comparison.compare(scene, [inside, beyond], size=16, backend=backend)
    assert e.value.parameter == "table 'beyond.csv', row 2" and "0.7071" in e.value.allowed
    # seen along the diagonal the box reaches farther (0.8165): the same row compares something
    comparison.check_tables_against_scene(scene, [beyond], direction=(1, 1, 1), size=16)
    with pytest.raises(SceneError) as e:
        fit.fit_observations(scene, [beyond], ["albedo"], size=16, backend=backend)
    assert "row 2" in e.value.parameter
    assert traces == []


def test_rings_without_a_pixel_that_sees_the_box_are_refused():
    """An annulus between two pixel centres of the model image (0.1 to 0.1001 on a 16-pixel
    image of 0.0459-box-unit pixels) holds none: refused before the trace, and by
    compare_tables for ring sums that count their pixels."""
    scene = Scene.from_dict(COLOUR_SCENE)
    thin = _colour_table([0.1, 0.2], [0.1001, 0.4])
    with pytest.raises(SceneError, match="no pixel centre") as e:
        comparison.check_tables_against_scene(scene, [thin], direction=(0, 0, -1), size=16, option="--table")
    assert e.value.parameter == "--table 't.csv', row 1"
    # a finer image has pixel centres in it (about 100 at 1024 pixels of 0.0008 box units)
    comparison.check_tables_against_scene(scene, [thin], direction=(0, 0, -1), size=1024)
    edges = comparison.ring_edges([thin])
    cam, labels, pixels = comparison.ring_pixels((0.5, 0.5, 0.5), (0, 0, -1), 16, edges)
    assert pixels[0] == 0 and pixels[-1] > 0 and pixels.sum() <= (labels >= 0).sum()
    nb, nr = 8, len(edges) - 1
    rings = comparison.RingSums(edges=edges, sums=np.ones((nb, nr)), batches=np.ones((4, nb, nr)) / 4,
                                band_luminosity=np.ones(nb), wavelength_nm=np.linspace(405, 755, nb),
                                pixel_area=cam.pixel_size ** 2, star_tau=np.zeros(nb), source=10000.0,
                                pixels=pixels)
    with pytest.raises(SceneError, match="no pixel centre"):
        comparison.compare_tables(rings, [thin])
    # the same sums without the count (made elsewhere): compared as given
    rings.pixels = None
    assert len(comparison.compare_tables(rings, [thin]).results) == 1


def test_no_p_value_without_a_chi2():
    """A row the model gives no colour (no light in its annulus: NaN) makes chi^2 undefined:
    the summary reports neither chi^2 nor a p-value (was: chi2 null and p_value 0.0)."""
    edges = np.array([0.0, 0.2, 0.4])
    nb = 8
    sums = np.ones((nb, 2))
    sums[:, 1] = 0.0  # no light in the outer ring
    rings = comparison.RingSums(edges=edges, sums=sums, batches=np.repeat(sums[None] / 4, 4, axis=0),
                                band_luminosity=np.ones(nb), wavelength_nm=np.linspace(405, 755, nb),
                                pixel_area=1e-3, star_tau=np.zeros(nb), source=10000.0)
    comp = comparison.compare_tables(rings, [_colour_table([0.0, 0.2], [0.2, 0.4])])
    d = comp.to_dict()
    assert not math.isfinite(comp.chi2) and d["chi2"] is None and d["p_value"] is None and d["dof"] == 2
    assert d["tables"][0]["model"][0] is not None and d["tables"][0]["model"][1] is None
    comp = comparison.compare_tables(rings, [_colour_table([0.0], [0.2])])  # the lit ring alone
    assert comp.to_dict()["p_value"] is not None


def test_observed_tables_hold_what_chi2_can_square(tmp_path):
    """Values within +-1e50 and errors in [1e-50, 1e50] (the ends are accepted, beyond refused,
    naming the column and row); offsets that become infinite in box units are refused by row."""
    import astropy.units as u

    from nebula_rt.observe.observed_tables import OffsetScale

    ok = tmp_path / "ok.csv"
    ok.write_text("offset,delta_bv,delta_bv_err\n0.1,1e50,1e-50\n0.2,-1e50,1e50\n")
    assert read_table(ok).value.tolist() == [1e50, -1e50]
    for text, where in (("0.1,1.01e50,0.1", "'delta_bv', row 1"), ("0.1,0.1,9.9e-51", "'delta_bv_err', row 1"),
                        ("0.1,0.1,1.01e50", "'delta_bv_err', row 1")):
        bad = tmp_path / "bad.csv"
        bad.write_text("offset,delta_bv,delta_bv_err\n" + text + "\n0.2,0.1,0.1\n")
        with pytest.raises(SceneError) as e:
            read_table(bad)
        assert where in e.value.parameter, e.value
    arc = tmp_path / "arc.csv"
    arc.write_text(TABLES["arcsec.csv"].replace("40,", "1e300,"))
    with pytest.raises(SceneError) as e:  # 1e300 arcsec over a box that subtends 1e-15 arcsec
        read_table(arc, scale=OffsetScale(box_length=1e-20 * u.pc, distance=1e5 * u.pc))
    assert "'offset', row 2" in e.value.parameter and "finite in box units" in e.value.allowed


def test_fit_options_are_refused_not_clipped(backend, traces):
    scene = Scene.from_dict(COLOUR_SCENE)
    table = _colour_table([0.1, 0.3], [0.3, 0.5])
    for options, name in (({"grid": -1}, "--grid"), ({"grid": 2.5}, "--grid"), ({"starts": -1}, "--starts"),
                          ({"maxfev": 0}, "maxfev"), ({"fatol": float("nan")}, "fatol"),
                          ({"mcmc_steps": 1}, "mcmc_steps"), ({"start": [1.5]}, "start"),
                          ({"direction": (1e-320, 0.0, 0.0)}, "direction")):
        with pytest.raises(SceneError) as e:
            fit.fit_observations(scene, [table], ["albedo"], size=16, backend=backend, **options)
        assert e.value.parameter == name, (options, e.value)
    assert traces == []


def test_offsets_in_arcsec_take_the_box_edge_of_a_scene_in_physical_units(folder, traces, capsys):
    """A table of offsets in arcsec and --distance, against a scene whose box edge is a
    quantity (grid.length = "0.5 pc", as the shipped merope-sky.toml): the box length was
    formed as the text times grid.unit, 0.5 pc^2 (with astropy's deprecation warning on
    stderr), and the command ended in an internal error. It is the scene's 0.5 pc, the same
    comparison as with --box-length '0.5 pc'."""
    base = ("compare {sky} --size 16 --png {dir}/out/c.png --table {dir}/arcsec.csv --distance '136 pc'")
    summaries = []
    for extra in ("", " --box-length '0.5 pc'"):
        status, out, err = _run(folder, base + extra, capsys)
        assert status == 0 and "Warning" not in err and "internal error" not in err, err
        summaries.append(json.loads(out))
        (folder / "out" / "c.png").unlink()
    assert summaries[0]["tables"][0]["offset_lo"] == summaries[1]["tables"][0]["offset_lo"]
    assert summaries[0]["chi2"] == summaries[1]["chi2"] and math.isfinite(summaries[0]["chi2"])


def test_a_fits_header_claiming_more_data_than_the_file_holds_is_one_line(folder):
    """--image whose header declares 100000 x 100000 pixels over one block of data: refused
    before any trace (as before) in one line; astropy's "File may have been truncated"
    warning was a line of its own before it."""
    from astropy.io import fits

    h = fits.Header()
    h["SIMPLE"], h["BITPIX"], h["NAXIS"], h["NAXIS1"], h["NAXIS2"] = True, -32, 2, 100000, 100000
    (folder / "huge.fits").write_bytes(h.tostring().encode() + b"\0" * 2880)
    import subprocess
    import sys

    # in a process of its own: astropy's logger writes to the stderr it found at import
    line = "compare {sky} --size 16 --png {dir}/out/c.png --image {dir}/huge.fits --image-error 5%"
    p = subprocess.run([sys.executable, "-m", "nebula_rt.cli", *shlex.split(line.format(sky=folder / "sky.toml",
                                                                                          dir=folder))],
                       capture_output=True, text=True, timeout=120)
    status, err = p.returncode, p.stderr
    assert status == 2 and len(err.strip().splitlines()) == 1, err
    assert "huge.fits" in err and "40000000000 bytes" in err and "WARNING" not in err, err
    assert list((folder / "out").iterdir()) == []


@pytest.mark.parametrize("preset", ["thesis-rgb", "spectral-8"])
@pytest.mark.parametrize("key,value", [("hydrogen_density", 2700.0), ("visual_extinction", 1.0)])
def test_a_fit_of_the_optics_keeps_a_physical_scene_optical_depth(preset, key, value):
    """--free albedo (or g, a slope, a band's) on a scene whose dust is given in physical
    units: each trial's scene lists the bands, whose reference band gives another dust.tau for
    the same n_H or A_V (0.1 % for spectral-8), and the trial scene, holding both, was refused
    ('is set by dust.hydrogen_density ...: give one of them') before the fit started. The trials
    keep the base scene's dust.tau."""
    d = {**SKY_SCENE, "dust": {"model": "uniform", "density": 1.0, key: value}, "bands": {"preset": preset}}
    from nebula_rt.observe import fit_parameters

    base = Scene.from_dict(d)
    for name in ("albedo", "g", "albedo_slope"):
        p = fit_parameters.make_parameter(name, base)
        trial = fit_parameters.scene_with(base, [p], [0.5 * (p.lo + p.hi)])
        assert trial.dust.tau == base.dust.tau


def test_a_fit_without_an_interval_says_so_not_nan(folder, traces, capsys):
    """fit --uncertainty none: the summary on stderr gave each parameter as 'albedo = 0.5
    -nan +nan'."""
    status, _, err = _run(folder, FIT + " --free albedo --grid 0", capsys)
    assert status == 0, err
    line = next(ln for ln in err.splitlines() if ln.strip().startswith("albedo ="))
    assert "nan" not in line and "(no interval)" in line, line


def test_a_table_entry_that_is_not_a_number_is_named_by_its_row(tmp_path):
    """A word among a column's numbers: the message gave the column's dtype ('<U3') as the
    value; it names the row and the entry."""
    p = tmp_path / "t.csv"
    p.write_text("offset,delta_bv,delta_bv_err\n0.1,-0.2,0.05\n0.3,x1,0.05\n")
    with pytest.raises(SceneError) as e:
        read_table(p, option="--table")
    assert e.value.parameter.endswith("column 'delta_bv', row 2") and e.value.value == "x1", e.value
