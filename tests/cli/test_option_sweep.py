"""No internal error is reachable from the command line: every option of every command, and
every column of the observed tables, against hostile values.

The table is built, not written out. The options come from the real parser
(:func:`nebula_rt.cli.commands.build_parser`, walked command by command), so an option added
later is swept too; each option has a *kind* (a number, an integer, a pair or triple of numbers,
a path read or written, a choice, a flag, or one of the free-text forms: a scene override, a
length with its unit, a fit parameter, an image error, plain text), given by rule (argparse's
type, choices or flag) or in :data:`KIND`, and each kind has its hostile values in
:data:`HOSTILE`: NaN, infinities, 0, -1, 1e308, the denormal 1e-320, empty and non-numeric text,
an overflowing exponent, 10,000 characters; wrong counts and zero vectors; missing files,
folders, /dev/zero, a FIFO, a symlink loop, a byte of garbage; outputs that are folders, under a
missing, a read-only or a non-folder parent, or have no name. An option without a kind fails
:func:`test_every_option_has_hostile_values`. The columns come from
:mod:`nebula_rt.observe.observed_tables` (``REQUIRED`` and ``OPTIONAL``): each gets NaN, infinities,
+-1e308, 1e-320, a negative value where it must be positive, text and an empty cell, in a table
that is otherwise good; each is also left out and given twice, and the unit headers are given
units of the wrong kind.

Each row is one command line, run in process (:func:`nebula_rt.cli.commands.main`) on the 8^3
scenes of ``test_hostile_numbers`` from a command line that succeeds as it is (:data:`BASES`: the
options that act only with ``--table`` or ``--image`` are swept with those). The contract: exit 2
with one line on stderr that names the option (or its scene key; for a table the file and the
column), no traceback or internal error, nothing traced and no file written; or exit 0 with
valid outputs. argparse's own refusals (a bad choice, an int that is not one) exit 2 with its
usage and one error line naming the option. Which rows are accepted is part of the table
(:data:`ACCEPTED`): a hostile value that starts to be accepted (clipped, ignored) shows. The
accepted rows trace, so they are few; the refused ones trace nothing and take milliseconds.
Values ``test_hostile_numbers`` already covers are left out (:data:`COVERED_ELSEWHERE`).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import re
import shlex
import signal
import stat
import subprocess
import time
import tomllib
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from nebula_rt.cli import commands as cli
from nebula_rt.errors import NebulaWarning
from nebula_rt.observe import observed_tables
from nebula_rt import scene as scene_keys
from nebula_rt.scene import Scene
from test_hostile_numbers import COLOUR_SCENE, SKY_SCENE, TABLES, traces  # noqa: F401 (a fixture)

# --- the command lines the sweep starts from --------------------------------------------------

IMAGE_OPTIONS = ("--image", "--image-hdu", "--image-band", "--image-unit", "--image-error", "--reproject",
                 "--mask-stars", "--fits")
TABLE_OPTIONS = ("--table", "--distance", "--box-length", "--normalisation", "--annulus")

#: A command line per context that succeeds as it is; the sweep replaces one option's value. The
#: tables: ``ratio.csv`` (wavelengths in nm, one annulus) and ``arcsec.csv`` (offsets in arcsec,
#: through --distance and --box-length: a 0.05 pc box at 136 pc spans 76 arcsec).
BASES = {
    "render": "render {colour} --photons 2000 --output {dir}/out/r.vti --quiet",
    "sky": "sky {sky} --photons 2000 --size 16 --fits {dir}/out/s.fits --quiet",
    "compare": "compare {colour} --photons 2000 --size 16 --png {dir}/out/c.png",
    "compare --table": "compare {colour} --photons 2000 --size 16 --png {dir}/out/c.png --table {dir}/ratio.csv "
                       "--table {dir}/arcsec.csv --box-length 0.05pc --distance 136pc",
    "compare --image": "compare {sky} --photons 2000 --size 16 --png {dir}/out/i.png --image {dir}/obs.fits "
                       "--image-band G --image-error 5%",
    # one free parameter, no grid, no Nelder-Mead, no uncertainties: the fewest traces a fit makes
    "fit": "fit {colour} --photons 2000 --table {dir}/colour.csv --table {dir}/arcsec.csv --box-length 0.05pc "
           "--distance 136pc --free albedo --size 16 --uncertainty none --grid 0 --starts 0 "
           "--png {dir}/out/f.png --quiet",
}


def context(command: str, option: str) -> str:
    """The base command line an option is swept in: compare's table and image options act only
    with a table or an image."""
    if command == "compare" and option in IMAGE_OPTIONS:
        return "compare --image"
    if command == "compare" and option in TABLE_OPTIONS:
        return "compare --table"
    return command


# --- the options, from the parser -------------------------------------------------------------


def commands() -> dict:
    """{command: its argparse parser}, from the real parser."""
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def option_name(action) -> str:
    """The long name of an option (``--output`` for ``-o/--output``), the dest of a positional."""
    return max(action.option_strings, key=len) if action.option_strings else action.dest


def sweep_actions():
    """(command, action) of every option and positional of every command, help aside."""
    for command, parser in commands().items():
        for action in parser._actions:
            if not isinstance(action, argparse._HelpAction):
                yield command, action


#: The kind of the options no rule finds (plain strings); the rest by argparse's type,
#: choices or flag (:func:`kind_of`).
KIND = {
    "scene": "path-in", "--table": "path-in", "--image": "path-in",
    "--output": "path-out", "--png": "path-out", "--json": "path-out", "--fits": "path-out",
    "--scene-out": "path-out", "--tree": "path-out",
    "--photons": "number", "--target-error": "number",
    "--direction": "triple", "--annulus": "pair",
    "--set": "override", "--free": "free", "--image-error": "image-error",
    "--distance": "length", "--box-length": "length",
    "--device": "text", "--image-hdu": "text", "--image-band": "text", "--image-unit": "text",
    # observed Stokes images: swept without --stokes, where each of its options is refused (it
    # would describe nothing); --stokes itself as a path read (tests/observe/test_polarization_compare.py
    # runs it with its options)
    "--stokes": "path-in", "--stokes-hdus": "text", "--stokes-annuli": "text", "--stokes-error": "image-error",
}


def kind_of(action):
    """The option's kind: :data:`KIND`, else by argparse's rule; None if neither says."""
    name = option_name(action)
    if name in KIND:
        return KIND[name]
    if action.choices:
        return "choice"
    if action.nargs == 0:  # store_true and the like
        return "flag"
    if action.type is int:
        return "integer"
    if action.type is float:
        return "number"
    return None


LONG = "9" * 10_000
NUMBER = ["nan", "inf", "-inf", "-1", "0", "1e308", "1e-320", "", "abc", "1e999", LONG]
#: Hostile values of each kind. In paths, {dir} is the test's folder and {sfx} the suffix the
#: option reads or writes (:data:`SUFFIX`), so a path gets past the suffix check to the
#: file's kind.
HOSTILE = {
    "number": NUMBER,
    "integer": NUMBER + [str(2**63), "1.5"],
    "pair": ["", "1", "0,0.5,1", "nan,0.5", "0,nan", "0,inf", "0,0", "0.4,0.1", "-1,0.5", "1e308,1e308", "a,b"],
    "triple": ["", "1,0", "1,0,0,0", "nan,0,1", "0,inf,0", "0,0,0", "1e308,1e308,0", "1e-320,0,0", "a,b,c", "1,,0"],
    "path-in": ["", "{dir}/missing{sfx}", "{dir}/folder{sfx}", "/dev/zero", "{dir}/fifo{sfx}", "{dir}/loop{sfx}",
                "{dir}/garbage{sfx}"],
    "path-out": ["", "{dir}/folder{sfx}", "{dir}/nowhere/x{sfx}", "{dir}/readonly/x{sfx}", "{dir}/garbage.csv/x{sfx}",
                 "{dir}/out/x.wrong"],
    "choice": ["", "bogus"],
    "flag": ["yes"],  # given as --quiet=yes
    "text": ["", "nope", 'a"b', "\n", "-1", "x" * 10_000],
    "length": ["", "abc", "430", "nan pc", "inf pc", "-1 pc", "0 pc", "1e-320 pc", "1e308 pc", "1 kg", LONG],
    "override": ["", "noequals", "=1", "transport.photons=", "transport.photons=nan", "nosuch.key=1",
                 "stars.99.luminosity=1", "transport.photons.x=1", "transport=1", "x" * 10_000 + "=1"],
    "free": ["", "nosuch", "albedo=", "albedo=nan:0.5", "albedo=0.5:0.1", "albedo=0.1:0.5:sqrt", "tau=0:10:log",
             "tau=1e-320:1:log", "depth=0:1e308", "albedo=0.1:0.2:log:4", "x" * 10_000],
    "image-error": ["", "abc", "nan%", "-5%", "0%", "inf%", "1e308%", "1e-320%", "1e308 MJy/sr", "1e-320 MJy/sr",
                    "0 MJy/sr", "-1 MJy/sr", "0.2 kg", "NOHDU", "99", "x" * 10_000],
}
#: What a path option reads or writes.
SUFFIX = {"scene": ".toml", "--table": ".csv", "--image": ".fits", "--stokes": ".fits", "--output": ".vti", "--png": ".png",
          "--json": ".json", "--fits": ".fits", "--scene-out": ".toml", "--tree": ".htg"}
#: The scene key an option sets (its message may name either).
SCENE_KEY = {"--photons": "transport.photons", "--target-error": "transport.target_error",
             "--quality": "transport.quality", "--backend": "transport.backend", "--device": "transport.device",
             "--stretch": "colour.stretch"}
#: A path under a read-only folder: root writes into a folder whatever its mode, so as root the
#: folder is a read-only tmpfs (as tests/conftest.py's small_fs; where it cannot be mounted
#: these rows are skipped with the mount's reason)
READ_ONLY = "{dir}/readonly/"
#: why the read-only folder could not be made (None: it is there)
_read_only_refused: dict = {}

#: (command, option, value) that test_hostile_numbers already runs (the rows that match values of
#: HOSTILE are left out of the sweep; the others are listed so that they stay out).
COVERED_ELSEWHERE = {
    ("compare", "--direction", "1e308,1e308,0"), ("compare", "--direction", "1e-320,0,0"),
    ("sky", "--direction", "1e-320,0,0"), ("compare", "--target-error", "1e-300"),
    ("compare", "--mask-stars", "1e308"), ("fit", "--grid", "-5"), ("fit", "--starts", "-3"),
}

#: The rows accepted (exit 0, valid outputs), by (command, option, value) or (table kind,
#: column, cell); every other row is refused. Each is a value that means what it says: a device
#: selector of white space (selectors are stripped: "" is any device), a star mask of 1e-320
#: arcsec (no pixel masked), an annulus from 1e-320 box units, a colour or ratio of 1e-320 (read
#: as 0 or as the denormal).
ACCEPTED = {
    ("render", "--device", "\n"), ("sky", "--device", "\n"), ("compare", "--device", "\n"), ("fit", "--device", "\n"),
    ("compare", "--mask-stars", "1e-320"),
    ("colour", "offset_lo", "1e-320"), ("colour", "delta_bv", "1e-320"), ("ratio", "ratio", "1e-320"),
    ("arcsec", "offset_lo", "1e-320"),
}

#: Exit status 3 (the backend or device cannot be used, :func:`nebula_rt.cli.commands.main`)
#: is the refusal of a device selector that selects nothing.
DEVICE_OPTIONS = ("--device",)


@dataclass(frozen=True)
class Case:
    id: str
    argv: tuple  # tokens after nebula-rt; {colour}, {sky}, {dir} filled in by the test
    names: tuple  # groups of names: the message holds one name of every group
    accepted: bool = False
    files: tuple = ()  # (name, text) written into the folder before the run
    statuses: tuple = (2,)  # the refusal's exit status


def _label(value: str) -> str:
    v = value.replace("{dir}/", "").replace("{sfx}", "")
    if len(v) > 24:
        v = f"{v[:3]}*{len(v)}"
    return v.replace("\n", "NL") or "EMPTY"


def _replace(tokens: list, action, value: str) -> list:
    """``tokens`` with the option's value(s) taken out and ``value`` given (``--opt=value``: a
    value that starts with '-' stays the option's)."""
    if not action.option_strings:  # the positional: the token after the command
        return [tokens[0], value] + tokens[2:]
    out, skip = [], False
    for tok in tokens:
        if skip:
            skip = False
            continue
        if tok in action.option_strings:
            skip = action.nargs != 0
            continue
        if any(tok.startswith(o + "=") for o in action.option_strings):
            continue
        out.append(tok)
    return out + [f"{option_name(action)}={value}"]


def _same(value: str, given) -> bool:
    if given is None:
        return False
    try:
        return float(value) == float(given)
    except (TypeError, ValueError):
        return value == str(given)


def _usual(value: str, tokens: list, action) -> bool:
    """Whether a value is the one the base command line gives, the option's default or its
    scene key's (``--target-error 0``: off; ``--device ""``: any): not hostile, and every
    accepted row runs it anyway."""
    if not action.option_strings or (action.choices is not None and value not in action.choices):
        return False  # a positional has no default; argparse refuses a value not among the choices
    name = option_name(action)
    usual = [_given(tokens, action), action.default, scene_keys.default(SCENE_KEY[name]) if name in SCENE_KEY else None]
    return any(_same(value, u) for u in usual)


def _given(tokens: list, action):
    """The option's value in a command line, else its default."""
    for i, tok in enumerate(tokens):
        if tok in action.option_strings and action.nargs != 0 and i + 1 < len(tokens):
            return tokens[i + 1]
    return action.default


def option_cases() -> list:
    cases = []
    for command, action in sweep_actions():
        kind = kind_of(action)
        if kind is None:
            continue  # test_every_option_has_hostile_values fails
        name = option_name(action)
        base = shlex.split(BASES[context(command, name)])
        for value in HOSTILE[kind]:
            value = value.replace("{sfx}", SUFFIX.get(name, ""))
            if (command, name, value) in COVERED_ELSEWHERE or _usual(value, base, action):
                continue
            if kind == "override":  # the message names the key given
                key = value.split("=", 1)[0].strip()
                names = (("--set", key[:20]),)
            else:
                names = (tuple(action.option_strings) + ((SCENE_KEY[name],) if name in SCENE_KEY else ()) or
                         (name,),)
            cases.append(Case(f"{command}{name if name.startswith('-') else ' ' + name}={_label(value)}",
                              tuple(_replace(base, action, value)), names,
                              accepted=(command, name, value) in ACCEPTED,
                              statuses=(2, 3) if name in DEVICE_OPTIONS else (2,)))
    return cases


# --- the tables -------------------------------------------------------------------------------

#: Good tables with every column (offset_lo and offset_hi included); row 1 is made hostile.
GOOD_TABLES = {
    "colour": {"offset": ["0.1", "0.3"], "offset_lo": ["0.05", "0.2"], "offset_hi": ["0.15", "0.4"],
               "delta_bv": ["-0.2", "-0.1"], "delta_bv_err": ["0.05", "0.05"]},
    "ratio": {"wavelength [nm]": ["455", "555", "655"], "ratio": ["1.2", "1.0", "0.9"],
              "ratio_err": ["0.1", "0.1", "0.1"], "offset_lo": ["0", "0", "0"], "offset_hi": ["0.5", "0.5", "0.5"]},
}
CELL = ["nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "-1", "abc", ""]
#: Columns whose values may be negative (a colour difference; a ratio measured in noise).
SIGNED = ("delta_bv", "ratio")
#: Unit headers of the wrong kind, or none where one is needed (kind, header, replaced column).
UNIT_HEADERS = [
    ("colour", "offset [km/s]", "offset"), ("colour", "offset [", "offset"),
    ("colour", "offset [nosuchunit]", "offset"),
    ("colour", "delta_bv [nm]", "delta_bv"), ("colour", "delta_bv_err [Jy]", "delta_bv_err"),
    ("ratio", "wavelength", "wavelength [nm]"), ("ratio", "wavelength [kg]", "wavelength [nm]"),
    ("ratio", "wavelength [mag]", "wavelength [nm]"), ("ratio", "ratio [mag]", "ratio"),
    ("ratio", "ratio_err [nm]", "ratio_err"), ("ratio", "offset_lo [kg]", "offset_lo"),
]
TABLE_BASE = "compare {colour} --photons 2000 --size 16 --png {dir}/out/c.png --table {dir}/t.csv"
#: A colour table with its offsets in arcsec: a 0.05 pc box at 136 pc spans 76 arcsec, so the
#: annuli are 0.13-0.4 and 0.4-0.66 box units.
ARCSEC_TABLE = {"offset [arcsec]": ["20", "40"], "offset_lo [arcsec]": ["10", "30"], "offset_hi [arcsec]": ["30", "50"],
                "delta_bv": ["-0.2", "-0.1"], "delta_bv_err": ["0.05", "0.05"]}
ARCSEC_BASE = TABLE_BASE + " --box-length 0.05pc --distance 136pc"


def _csv(columns: dict) -> str:
    rows = zip(*columns.values())
    return "\n".join([",".join(columns)] + [",".join(r) for r in rows]) + "\n"


def table_cases() -> list:
    cases = []

    def add(id_, cols, column, accepted=False, argv=TABLE_BASE):
        name = column.split(" ")[0]
        cases.append(Case(id_, tuple(shlex.split(argv)), (("t.csv",), (name,)), accepted=accepted,
                          files=(("t.csv", _csv(cols)),)))

    for kind, good in GOOD_TABLES.items():
        for column in good:
            name = column.split(" ")[0]
            for cell in CELL:
                if cell == "-1" and name in SIGNED:
                    continue
                cols = {c: list(v) for c, v in good.items()}
                cols[column][0] = cell
                add(f"{kind}-{name}={_label(cell)}", cols, column, (kind, name, cell) in ACCEPTED)
            missing = {c: v for c, v in good.items() if c != column}
            add(f"{kind}-{name}-missing", missing, column)
            twice = dict(good)
            twice[column + " "] = good[column]  # the same name again (astropy strips the space)
            add(f"{kind}-{name}-twice", twice, column)
    # offsets in arcsec, through --distance and --box-length into box units
    for column in ARCSEC_TABLE:
        if "[" not in column:
            continue
        name = column.split(" ")[0]
        for cell in CELL:
            cols = {c: list(v) for c, v in ARCSEC_TABLE.items()}
            cols[column][0] = cell
            add(f"arcsec-{name}={_label(cell)}", cols, column, ("arcsec", name, cell) in ACCEPTED, ARCSEC_BASE)
    for kind, header, column in UNIT_HEADERS:
        cols = {(header if c == column else c): v for c, v in GOOD_TABLES[kind].items()}
        add(f"{kind}-header={header}", cols, header)
    return cases


def test_the_columns_swept_are_the_readers():
    """Every column the reader knows has a good value to make hostile."""
    for kind, good in GOOD_TABLES.items():
        names = {c.split(" ")[0] for c in good}
        assert names == set(observed_tables.REQUIRED[kind]) | set(observed_tables.OPTIONAL), kind


CASES = option_cases() + table_cases()


def test_every_option_has_hostile_values():
    """An option the parser has and the sweep cannot give values to (no kind) fails here:
    give it a kind in KIND."""
    missing = [f"{command} {option_name(a)}" for command, a in sweep_actions() if kind_of(a) not in HOSTILE]
    assert not missing, f"options without hostile values (add them to KIND): {missing}"
    swept = {(c.argv[0], c.argv[-1].split("=", 1)[0]) for c in CASES}
    for command, action in sweep_actions():
        if action.option_strings:
            assert (command, option_name(action)) in swept


def test_the_accepted_rows_are_few():
    """Accepted rows trace (about a second each); the rest trace nothing."""
    assert sum(c.accepted for c in CASES) <= 15


# --- running a row ----------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _observed_image() -> bytes:
    """A FITS image of constant surface brightness on the sky scene's own 16-pixel WCS."""
    import io

    from astropy.io import fits

    from nebula_rt.observe import calibrate

    scene = Scene.from_dict(SKY_SCENE)
    header = calibrate.celestial_wcs(scene, calibrate.camera_for(scene, size=16)).to_header()
    header["BUNIT"] = "MJy/sr"
    buf = io.BytesIO()
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.ones((16, 16)), header=header, name="SCI")]).writeto(buf)
    return buf.getvalue()


#: The files of the inputs' folder, by folder: what a row adds is removed after it.
INPUT_FILES = {}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """One folder for every row (the rows only read it; a fresh one per row would be 600 folders
    of 40 files each, which pytest then deletes for seconds): test_hostile_numbers' scenes and
    tables, the observed image, and the hostile paths: for every suffix a folder, a FIFO, a
    symlink loop and a byte of garbage, and a read-only folder."""
    root = tmp_path_factory.mktemp("sweep")
    for name, text in TABLES.items():
        (root / name).write_text(text)
    (root / "colour.toml").write_text(Scene.from_dict(COLOUR_SCENE).to_toml())
    (root / "sky.toml").write_text(Scene.from_dict(SKY_SCENE).to_toml())
    (root / "obs.fits").write_bytes(_observed_image())
    (root / "out").mkdir()
    for sfx in set(SUFFIX.values()):
        (root / f"folder{sfx}").mkdir()
        os.mkfifo(root / f"fifo{sfx}")
        os.symlink(f"loop{sfx}", root / f"loop{sfx}")
        (root / f"garbage{sfx}").write_bytes(b"\xff")
    ro = root / "readonly"
    ro.mkdir()
    if os.geteuid() == 0:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k,ro", "tmpfs", str(ro)], capture_output=True,
                           text=True)
        _read_only_refused[root] = None if r.returncode == 0 else f"cannot mount a read-only tmpfs: {r.stderr.strip()}"
    else:
        ro.chmod(0o555)
        _read_only_refused[root] = None
    INPUT_FILES[root] = set(_files(root))
    yield root
    if os.geteuid() == 0:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)
    else:
        ro.chmod(0o755)


@pytest.fixture
def world(inputs, monkeypatch):
    """The folder of the inputs as the working directory (a relative output lands there); what
    a row leaves in it is removed after the row, so that the next starts from the same files."""
    monkeypatch.chdir(inputs)
    yield inputs
    for path in sorted(set(_files(inputs)) - INPUT_FILES[inputs], key=len, reverse=True):
        if os.path.isdir(path) and not os.path.islink(path):
            os.rmdir(path)
        else:
            os.unlink(path)


class Hang(BaseException):
    """A row ran past its time (not an Exception: the command line's handler must not catch it)."""


def _on_alarm(signum, frame):
    raise Hang()


def _files(root) -> dict:
    """{path: (kind, size)} of everything under root (links not followed)."""
    out, folders = {}, [str(root)]
    while folders:
        with os.scandir(folders.pop()) as entries:
            for e in entries:
                st = e.stat(follow_symlinks=False)
                out[e.path] = (stat.S_IFMT(st.st_mode), st.st_size if stat.S_ISREG(st.st_mode) else 0)
                if stat.S_ISDIR(st.st_mode):
                    folders.append(e.path)
    return out


def _run(world: Path, case: Case, capsys, limit: float = 10.0):
    """(status, stdout, stderr, seconds, the warnings not the project's) of the row's command
    line, in process."""
    subs = {"{colour}": str(world / "colour.toml"), "{sky}": str(world / "sky.toml"), "{dir}": str(world)}
    argv = []
    for tok in case.argv:
        for k, v in subs.items():
            tok = tok.replace(k, v)
        argv.append(tok)
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, limit)
    t0 = time.monotonic()
    # the warnings other than the project's: outside pytest each is a line of its own on stderr
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            status = cli.main(argv)
        except SystemExit as e:  # argparse's refusals
            status = e.code
        except Hang:
            pytest.fail(f"{case.id}: still running after {limit:g} s")
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    seconds = time.monotonic() - t0
    out = capsys.readouterr()
    foreign = [f"{w.category.__name__}: {w.message}" for w in caught if not issubclass(w.category, NebulaWarning)]
    return status, out.out, out.err, seconds, foreign


def _strict_json(text: str):
    def refuse(name):
        raise ValueError(f"{name} in JSON")

    return json.loads(text, parse_constant=refuse)


def _check_output(path: Path) -> None:
    """An output is a complete file of its format."""
    assert path.is_file() and path.stat().st_size > 0, path
    data = path.read_bytes()
    sfx = path.suffix
    if sfx == ".png":
        assert data.startswith(b"\x89PNG\r\n\x1a\n"), path
    elif sfx == ".json":
        _strict_json(data.decode())
    elif sfx == ".vti":
        assert b"<VTKFile" in data[:200], path
    elif sfx == ".fits":
        from astropy.io import fits

        with fits.open(path) as hdul:
            assert any(h.data is not None for h in hdul), path
    elif sfx == ".toml":
        tomllib.loads(data.decode())
        Scene.loads(data.decode())


def _output_paths(argv, world: Path) -> set:
    """The outputs a command line names (the options of kind path-out)."""
    parser = commands()[argv[0]]
    args = parser.parse_args(argv[1:])
    out = set()
    for action in parser._actions:
        if kind_of(action) == "path-out" and getattr(args, action.dest, None):
            out.add((world / getattr(args, action.dest)).resolve())
    return out


def _subject(line: str) -> str:
    """What a refusal is about, not what it advises: argparse's ``argument --png``; a scene
    error's parameter (``--table 't.csv', column 'offset', row 1`` before `` = value``); an
    output's option (``--png`` before its path)."""
    m = re.search(r": error: argument (\S+):", line)
    if m:
        return m.group(1)
    rest = line.removeprefix("nebula-rt: ").removeprefix("invalid scene: ")
    return rest.split(" = ", 1)[0] if " = " in rest else rest.split(" '", 1)[0]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_hostile_value_is_refused_or_gives_valid_outputs(world, traces, capsys, case):  # noqa: F811
    if READ_ONLY in "".join(case.argv) and _read_only_refused[world]:
        pytest.skip(_read_only_refused[world])
    for name, text in case.files:  # (removed after the row, with what it wrote)
        (world / name).write_text(text)
    before = _files(world)
    status, out, err, seconds, foreign = _run(world, case, capsys)
    assert "Traceback" not in err and "internal error" not in err, err
    assert seconds < 10, seconds
    after = _files(world)
    assert not foreign, foreign  # outside pytest, a line of its own on stderr
    if status == 0:
        assert case.accepted, f"accepted, not refused: {err[-2000:]}"
        argv = [t.replace("{dir}", str(world)).replace("{colour}", "c").replace("{sky}", "s") for t in case.argv]
        outputs = _output_paths(argv, world)
        new = {Path(p).resolve() for p in set(after) - set(before)}
        assert new == outputs, (new, outputs)
        for p in outputs:
            _check_output(p)
        if out.strip():
            _strict_json(out)
        return
    assert not case.accepted, f"refused, not accepted: status {status}: {err[-2000:]}"
    assert status in case.statuses, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("nebula-rt: warning:")]
    said = [ln for ln in lines if ln.startswith("nebula-rt")]
    if said and ": error: " in said[-1]:  # argparse: its usage, then one line
        assert len(said) == 1 and lines[-1] == said[0] and lines[0].startswith("usage:"), err
    else:
        assert len(lines) == 1 and lines[0].startswith("nebula-rt:"), err
    subject = _subject(said[0])
    for group in case.names:
        assert any(n in subject for n in group), (group, said[0])
    assert traces == []
    assert after == before  # nothing written (and the inputs untouched)
