"""The user's own observations of a reflection nebula, as tables (CSV or ECSV).

Three kinds of table, told apart by their columns (one kind per file):

- **colour**: Delta(B-V) = (B-V)_nebula - (B-V)_star versus projected offset from the star,
  columns ``offset``, ``delta_bv``, ``delta_bv_err`` (mag, 1 sigma);
- **ratio**: the nebula/star flux ratio versus wavelength, columns ``wavelength``, ``ratio``,
  ``ratio_err`` (1 sigma);
- **polarization**: the degree of linear polarization of the nebula's light versus projected
  offset, at a wavelength, columns ``offset``, ``wavelength``, ``polarization``,
  ``polarization_err`` (a fraction, or with the unit ``%``): the tangential (centrosymmetric)
  degree, (Q cos 2psi + U sin 2psi) / I in the frame of each point's position angle psi about
  the star, which is P where the pattern is centrosymmetric, as about a reflection nebula's
  star, and negative where the light is polarized radially. Needs a scene with
  ``bands.polarization``.

Either may also have ``offset_lo`` and ``offset_hi``: the annulus of projected offset each
row was measured in. Without them a colour table's annuli reach halfway to the neighbouring
offsets (the first from max(0, offset - half a spacing), the last as far beyond), and a ratio
table is one annulus, ``annulus`` (box units, default 0 to 0.5).

Units. ECSV carries them (astropy.table reads them); a CSV header may give one in brackets or
parentheses, ``offset [arcsec]``, ``wavelength (nm)``. Offsets without a unit are in box units
(the box edge is 1); an angle (arcsec, arcmin, deg) needs the distance to the nebula and the
box's physical edge (:class:`OffsetScale`), a length (pc, AU) only the box's edge. Wavelengths
need a unit (nm, Angstrom, um, or a frequency). Delta(B-V) is in mag (or no unit), the ratio
and its error have none.

Ratio normalisation (``normalisation``):

- ``"free"`` (default): the ratios are relative, in any normalisation (e.g. to 1 at V): the
  model is scaled to the data per annulus by the weighted least-squares factor, which costs
  one degree of freedom per annulus;
- ``"absolute"``: each ratio is the nebula's flux summed over its annulus over the star's flux,
  both as the observer receives them. Unit-free and independent of the distance (the distance
  cancels), so it constrains the albedo and optical depth together.

Bad tables raise :class:`~nebula_rt.errors.SceneError` naming the file and column (and the
row), the value and what is allowed, before anything is traced.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from ..errors import SceneError
from ..input_files import MAX_TABLE_BYTES, check_input_file, read_input_text

KINDS = ("colour", "ratio", "polarization")
#: Columns of each kind: the required ones (the second names the kind); ``offset_lo`` and
#: ``offset_hi`` are optional for all.
REQUIRED = {
    "colour": ("offset", "delta_bv", "delta_bv_err"),
    "ratio": ("wavelength", "ratio", "ratio_err"),
    "polarization": ("offset", "polarization", "polarization_err", "wavelength"),
}
OPTIONAL = ("offset_lo", "offset_hi")
NORMALISATIONS = ("free", "absolute")
#: Default annulus of a ratio table without offset columns (box units).
DEFAULT_ANNULUS = (0.0, 0.5)
SUFFIXES = (".csv", ".ecsv")

#: The largest magnitude of a table's values and errors, and the smallest error. chi^2 squares
#: (data - model) / error and sums the squares over the rows in float64 (at most 1.8e308): a
#: value of 1e308 made chi^2 infinite and its p-value 0, an error of 1e-320 (its square 0) left
#: the data's error out. Values within +-1e50 and errors in [1e-50, 1e50] keep every pull below
#: 1e100 and its square below 1e200, whatever the number of rows.
MAX_VALUE = 1e50
MIN_ERROR = 1e-50

_HEADER_UNIT = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*[\[(]\s*([^\])]*?)\s*[\])]\s*$")


@dataclass(frozen=True)
class OffsetScale:
    """What turns offsets with units into box units.

    Parameters
    ----------
    box_length : astropy Quantity (length) or None
        Physical length of one box edge (e.g. ``1 * u.pc``).
    distance : astropy Quantity (length) or None
        Distance from the observer to the nebula; with ``box_length`` it gives the angle one
        box edge subtends (small-angle: box_length / distance radians).
    """

    box_length: object = None
    distance: object = None

    def box_units(self, values, unit, where: str) -> np.ndarray:
        """``values`` in ``unit`` as box units (``where`` names the column for errors)."""
        import astropy.units as u

        v = np.asarray(values, np.float64)
        if unit is None or unit == u.dimensionless_unscaled:
            return v
        if unit.is_equivalent(u.m):
            if self.box_length is None:
                raise SceneError(where, str(unit), "offsets in a length unit need the box's physical edge "
                                                   "(box_length= in the API, --box-length on the command line)")
            return (v * unit / self.box_length).to_value(u.dimensionless_unscaled)
        if unit.is_equivalent(u.arcsec):
            if self.box_length is None or self.distance is None:
                raise SceneError(where, str(unit), "offsets in an angle need the distance to the nebula and the "
                                                   "box's physical edge (distance= and box_length= in the API, "
                                                   "--distance and --box-length on the command line)")
            box_rad = (self.box_length / self.distance).to_value(u.dimensionless_unscaled)
            return (v * unit).to_value(u.rad) / box_rad
        raise SceneError(where, str(unit), "must be in box units (no unit), an angle (arcsec, arcmin, deg) or a "
                                           "length (pc, AU, ...)")


@dataclass
class ObservedTable:
    """One table of observations, validated, in the units the comparison works in.

    Attributes
    ----------
    kind : {"colour", "ratio", "polarization"}
    path : str
        Where it was read from (or a label).
    x : ndarray (n,)
        Offset (box units) for a colour or polarization table, wavelength (nm) for a ratio table.
    value, error : ndarray (n,)
        Delta(B-V) (mag), the ratio or the degree of polarization (a fraction), and its 1-sigma
        error (> 0).
    wavelength : ndarray (n,) or None
        A polarization table's wavelengths (nm).
    lo, hi : ndarray (n,)
        The annulus of each row, box units.
    x_display, x_unit : ndarray, str
        ``x`` as the table gave it and its unit (for plots and reports).
    normalisation : {"free", "absolute"}
        Ratio tables only (see the module's doc).
    """

    kind: str
    path: str
    x: np.ndarray
    value: np.ndarray
    error: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    x_display: np.ndarray = None
    x_unit: str = ""
    normalisation: str = "free"
    meta: dict = field(default_factory=dict)
    wavelength: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.x)

    def annuli(self) -> list[tuple[float, float]]:
        """The distinct annuli (lo, hi), in order of first appearance."""
        seen = []
        for a in zip(self.lo.tolist(), self.hi.tolist()):
            if a not in seen:
                seen.append(a)
        return seen

    def annulus_index(self) -> np.ndarray:
        """Index into :meth:`annuli` of each row."""
        ann = self.annuli()
        return np.array([ann.index(a) for a in zip(self.lo.tolist(), self.hi.tolist())], np.int64)


def _split_header(name: str):
    """``"offset [arcsec]"`` -> ("offset", "arcsec"); a plain name -> (name, None)."""
    m = _HEADER_UNIT.match(name)
    if m:
        return m.group(1), m.group(2)
    return name.strip(), None


def _check_names_once(text: str, fmt: str, where: str) -> None:
    """No column name twice in the names line (the first line that is not a comment). astropy
    renames a second ``offset`` to ``offset_1``, which was then refused as an unknown column."""
    import csv

    line = next((ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), None)
    if line is None:
        return
    comma = fmt == "ascii.csv" or re.search(r"^#\s*delimiter:\s*['\"]?,", text, re.M)
    try:
        names = next(csv.reader([line], delimiter="," if comma else " ", skipinitialspace=True), [])
    except csv.Error:  # (a NUL, a name beyond csv's field limit): astropy's reader says what is wrong
        return
    seen = set()
    for name in (_split_header(n)[0] for n in names):
        if name and name in seen:
            raise SceneError(f"{where}, column {name!r}", name, "appears twice")
        seen.add(name)


def _read_astropy(path: Path, where: str, option: str = "table"):
    import warnings

    from astropy.table import Table
    from astropy.utils.exceptions import AstropyWarning

    text = read_input_text(option, path, "a .csv or .ecsv file of UTF-8 text", MAX_TABLE_BYTES)
    if not text.strip():  # (astropy took the empty text for a file name: "Is a directory: '.'")
        raise SceneError(option, str(path), "is empty: a table needs its header line and a row per measurement")
    fmt = "ascii.ecsv" if text.lstrip().startswith("# %ECSV") else "ascii.csv"
    if path.suffix.lower() == ".ecsv" and fmt != "ascii.ecsv":
        raise SceneError(where, str(path), "an .ecsv file must start with the '# %ECSV' header line")
    _check_names_once(text, fmt, where)
    try:
        with warnings.catch_warnings():
            # a number beyond float64 (1e999, a denormal such as 1e-320): astropy warns that it
            # lost precision, a line of its own on stderr beside the refusal; the values are
            # checked, and named by column and row, below
            warnings.filterwarnings("ignore", message="OverflowError converting to", category=AstropyWarning)
            # as lines: a text of one line (a header without rows or newline) is not a file name
            return Table.read(text.splitlines(), format=fmt)
    except Exception as exc:  # astropy's parser errors are of many types
        raise SceneError(where, str(path), f"must be a readable {fmt[6:].upper()} table ({exc})") from None


def _columns(table, where: str) -> dict:
    """{name: (values, unit)} with header units parsed; a unit both in ECSV and in the name is refused."""
    import astropy.units as u

    out = {}
    for col in table.colnames:
        name, header_unit = _split_header(col)
        c = table[col]
        unit = c.unit
        if header_unit is not None:
            if unit is not None:
                raise SceneError(f"{where}, column {col!r}", str(unit), "give the unit once: in the ECSV header or "
                                                                        "in the column name, not both")
            try:
                unit = u.Unit(header_unit) if header_unit else None
            except ValueError:
                raise SceneError(f"{where}, column {col!r}", header_unit,
                                 "must be a unit astropy knows (nm, Angstrom, um, arcsec, pc, mag, ...)") from None
        if name in out:
            raise SceneError(f"{where}, column {name!r}", col, "appears twice")
        out[name] = (c, unit)
    return out


def _values(col, name: str, where: str) -> np.ndarray:
    """A column as finite float64; masked, missing or non-numeric entries name their row."""
    mask = np.zeros(len(col), bool)
    if hasattr(col, "mask") and col.mask is not None:
        mask = np.asarray(col.mask, bool).reshape(len(col), -1).any(axis=1)
    try:
        v = np.asarray(col, np.float64).reshape(len(col))
    except (TypeError, ValueError):
        # the first entry that is not a number, by its row (was: the column's dtype, '<U3')
        for row, cell in enumerate(np.asarray(col).reshape(len(col), -1)[:, 0], start=1):
            try:
                float(cell)
            except (TypeError, ValueError):
                raise SceneError(f"{where}, column {name!r}, row {row}", str(cell), "must be a number") from None
        raise SceneError(f"{where}, column {name!r}", str(col.dtype), "must hold numbers") from None
    bad = mask | ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{where}, column {name!r}, row {i + 1}", None if mask[i] else float(v[i]),
                         "must be a finite number (no empty, masked or NaN entries)")
    return v


def _check_unit(unit, name: str, where: str, allowed: Sequence, text: str):
    import astropy.units as u

    if unit is None:
        return
    if any(unit == a or (a is not u.dimensionless_unscaled and unit.is_equivalent(a)) for a in allowed):
        return
    raise SceneError(f"{where}, column {name!r}", str(unit), text)


def _positive(v, name: str, where: str) -> None:
    if np.any(v <= 0):
        i = int(np.flatnonzero(v <= 0)[0])
        raise SceneError(f"{where}, column {name!r}, row {i + 1}", float(v[i]), "must be > 0 (a 1-sigma error)")
    _bounded(v, name, where, MIN_ERROR)


def _bounded(v, name: str, where: str, smallest: float = 0.0) -> None:
    """Values (and, with ``smallest``, errors) within what chi^2 can square and sum
    (:data:`MAX_VALUE`, :data:`MIN_ERROR`)."""
    bad = (np.abs(v) > MAX_VALUE) | (np.abs(v) < smallest)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        span = (f"in [{MIN_ERROR:.0e}, {MAX_VALUE:.0e}]" if smallest else
                f"in [-{MAX_VALUE:.0e}, {MAX_VALUE:.0e}]").replace("e+", "e")
        raise SceneError(f"{where}, column {name!r}, row {i + 1}", float(v[i]),
                         f"must be {span} (chi^2 squares (data - model) / error in float64)")


def _annuli_from_offsets(x, where: str):
    """Annuli halfway to the neighbouring offsets (the first and last as far beyond)."""
    order = np.argsort(x)
    xs = x[order]
    if len(xs) < 2:
        raise SceneError(f"{where}, column 'offset'", x.tolist(),
                         "one row needs its annulus: add offset_lo and offset_hi columns")
    if np.any(np.diff(xs) <= 0):
        i = int(np.flatnonzero(np.diff(xs) <= 0)[0])
        raise SceneError(f"{where}, column 'offset'", float(xs[i]),
                         "must not repeat (give offset_lo and offset_hi for annuli of their own)")
    mid = 0.5 * (xs[1:] + xs[:-1])
    lo_s = np.concatenate([[max(0.0, xs[0] - (mid[0] - xs[0]))], mid])
    hi_s = np.concatenate([mid, [xs[-1] + (xs[-1] - mid[-1])]])
    lo, hi = np.empty_like(x), np.empty_like(x)
    lo[order], hi[order] = lo_s, hi_s
    return lo, hi


def _check_annuli(lo, hi, where: str, shared: bool) -> None:
    """lo < hi, lo >= 0; distinct annuli must not overlap (``shared``: rows may share one)."""
    bad = ~(lo < hi)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{where}, columns 'offset_lo', 'offset_hi', row {i + 1}", (float(lo[i]), float(hi[i])),
                         "offset_lo must be below offset_hi")
    if np.any(lo < 0):
        i = int(np.flatnonzero(lo < 0)[0])
        raise SceneError(f"{where}, column 'offset_lo', row {i + 1}", float(lo[i]), "must be >= 0")
    pairs = sorted(set(zip(lo.tolist(), hi.tolist())))
    if not shared and len(pairs) != len(lo):
        raise SceneError(f"{where}, columns 'offset_lo', 'offset_hi'", pairs,
                         "each row of a colour table needs an annulus of its own")
    for (a0, a1), (b0, b1) in zip(pairs, pairs[1:]):
        if b0 < a1:
            raise SceneError(f"{where}, columns 'offset_lo', 'offset_hi'", [(a0, a1), (b0, b1)],
                             "annuli must not overlap")


# One function though long (about 110 lines): a table's columns are recognised, converted
# and checked one after another against the same header, and every refusal names its column.
def read_table(source: Union[str, Path, "object"], *, scale: Optional[OffsetScale] = None,
               normalisation: str = "free", annulus=DEFAULT_ANNULUS, name: str = "",
               option: str = "table") -> ObservedTable:
    """Read and validate a table of observations.

    Parameters
    ----------
    source : str, Path or astropy.table.Table
        A ``.csv`` or ``.ecsv`` file, or a table already in memory.
    scale : OffsetScale, optional
        Turns offsets given in angles or lengths into box units.
    normalisation : {"free", "absolute"}
        How a ratio table's values are normalised (see the module's doc).
    annulus : (lo, hi), box units
        The annulus of a ratio table without offset columns.
    name : str
        A label for a table given in memory.
    option : str
        What names the file in messages (the command line's ``--table``).

    Raises
    ------
    SceneError
        Naming the file and column (and row) for a missing, unreadable or malformed file,
        missing columns, wrong units, non-finite values, errors that are not positive,
        values or errors beyond what chi^2 can square (:data:`MAX_VALUE`, :data:`MIN_ERROR`),
        overlapping annuli.
    """
    import astropy.units as u

    scale = scale or OffsetScale()
    if normalisation not in NORMALISATIONS:
        raise SceneError("normalisation", normalisation, f"must be one of {', '.join(NORMALISATIONS)}")
    if isinstance(source, (str, Path)):
        path = Path(source)
        where = f"{option} {str(path)!r}"
        if path.suffix.lower() not in SUFFIXES:
            raise SceneError(option, str(path), "must be a .csv or .ecsv file")
        check_input_file(option, path, "an existing .csv or .ecsv file", MAX_TABLE_BYTES)
        try:
            table = _read_astropy(path, where, option)
        except FileNotFoundError:
            raise SceneError(option, str(path), "must be an existing .csv or .ecsv file (no such file)") from None
        except IsADirectoryError:
            raise SceneError(option, str(path), "must be a file, not a folder") from None
        except UnicodeDecodeError:
            raise SceneError(option, str(path), "must be UTF-8 text") from None
        except OSError as e:
            raise SceneError(option, str(path), f"must be readable ({e.strerror or e})") from None
        label = str(path)
    else:
        table, label = source, name or "table"
        where = f"table {label!r}"
    cols = _columns(table, where)
    kinds = [k for k in KINDS if REQUIRED[k][1] in cols]
    if not kinds:
        # no delta_bv or ratio column: the kind whose other columns are there (offset and
        # delta_bv_err) is the one, and its missing column is named below (was: the columns
        # listed, the missing one not named)
        present = {k: sum(c in cols for c in REQUIRED[k]) for k in KINDS}
        best = max(present.values())
        if best and list(present.values()).count(best) == 1:
            kinds = [k for k in KINDS if present[k] == best]
    if len(kinds) != 1:
        have = ", ".join(cols) or "none"
        raise SceneError(f"{where}, columns", have,
                         "a colour table has columns offset, delta_bv, delta_bv_err; a ratio table wavelength, "
                         "ratio, ratio_err; a polarization table offset, wavelength, polarization, "
                         "polarization_err (each may add offset_lo, offset_hi)" +
                         ("; this one has more than one of delta_bv, ratio and polarization: one kind per file"
                          if len(kinds) > 1 else ""))
    kind = kinds[0]
    allowed = set(REQUIRED[kind]) | set(OPTIONAL)
    for c in cols:
        if c not in allowed:
            raise SceneError(f"{where}, column {c!r}", c, f"unknown column; a {kind} table has "
                                                          f"{', '.join(REQUIRED[kind] + OPTIONAL)}")
    for c in REQUIRED[kind]:
        if c not in cols:
            raise SceneError(f"{where}, column {c!r}", "missing", f"a {kind} table needs the columns "
                                                                  f"{', '.join(REQUIRED[kind])}")
    if len(table) == 0:
        raise SceneError(where, "no rows", "must have at least one row")
    if ("offset_lo" in cols) != ("offset_hi" in cols):
        missing = "offset_hi" if "offset_lo" in cols else "offset_lo"
        raise SceneError(f"{where}, column {missing!r}", "missing", "offset_lo and offset_hi come together")

    def offsets(name):
        col, unit = cols[name]
        v = _values(col, name, where)
        with np.errstate(over="ignore"):
            x = scale.box_units(v, unit, f"{where}, column {name!r}")
        if not np.all(np.isfinite(x)):  # an angle over a tiny box, a length over a tiny edge
            i = int(np.flatnonzero(~np.isfinite(x))[0])
            raise SceneError(f"{where}, column {name!r}, row {i + 1}", float(v[i]),
                             "must be finite in box units (through the distance and the box's edge)")
        return x, v, unit

    mag_text = "must be in mag (or have no unit)"
    meta = dict(getattr(table, "meta", {}) or {})
    wavelength = None
    if kind == "polarization":
        x, x_disp, x_unit = offsets("offset")
        if np.any(x < 0):
            i = int(np.flatnonzero(x < 0)[0])
            raise SceneError(f"{where}, column 'offset', row {i + 1}", float(x_disp[i]), "must be >= 0")
        wavelength = _wavelengths(cols["wavelength"], where)
        text = "must be a fraction (no unit) or in %"
        factor = []
        for c in ("polarization", "polarization_err"):
            _check_unit(cols[c][1], c, where, [u.dimensionless_unscaled, u.percent], text)
            unit = cols[c][1]
            factor.append(0.01 if unit is not None and unit == u.percent else 1.0)
        value = _values(cols["polarization"][0], "polarization", where) * factor[0]
        error = _values(cols["polarization_err"][0], "polarization_err", where) * factor[1]
        if np.any(np.abs(value) > 1.0):
            i = int(np.flatnonzero(np.abs(value) > 1.0)[0])
            raise SceneError(f"{where}, column 'polarization', row {i + 1}", float(value[i] / factor[0]),
                             "must be a degree of polarization in [-1, 1] (or [-100, 100] %)")
        _positive(error, "polarization_err", where)
        _bounded(error, "polarization_err", where, MIN_ERROR)
        if "offset_lo" in cols:
            lo, hi = offsets("offset_lo")[0], offsets("offset_hi")[0]
            _check_annuli(lo, hi, where, shared=True)
        else:  # (each distinct offset's annulus: a table may give several wavelengths at one offset)
            ux = np.unique(x)
            ulo, uhi = _annuli_from_offsets(ux, where)
            k = np.searchsorted(ux, x)
            lo, hi = ulo[k], uhi[k]
            _check_annuli(lo, hi, where, shared=True)
        return ObservedTable(kind=kind, path=label, x=np.asarray(x, np.float64), value=value, error=error,
                             lo=np.asarray(lo, np.float64), hi=np.asarray(hi, np.float64),
                             x_display=np.asarray(x_disp, np.float64),
                             x_unit="box units" if x_unit is None else str(x_unit), meta=meta,
                             wavelength=np.asarray(wavelength, np.float64))
    if kind == "colour":
        x, x_disp, x_unit = offsets("offset")
        if np.any(x < 0):
            i = int(np.flatnonzero(x < 0)[0])
            raise SceneError(f"{where}, column 'offset', row {i + 1}", float(x_disp[i]), "must be >= 0")
        for c in ("delta_bv", "delta_bv_err"):
            _check_unit(cols[c][1], c, where, [u.mag, u.dimensionless_unscaled], mag_text)
        value = _values(cols["delta_bv"][0], "delta_bv", where)
        _bounded(value, "delta_bv", where)
        error = _values(cols["delta_bv_err"][0], "delta_bv_err", where)
        _positive(error, "delta_bv_err", where)
        if "offset_lo" in cols:
            lo, hi = offsets("offset_lo")[0], offsets("offset_hi")[0]
            # the annuli first: an offset_lo above its offset_hi is theirs to name, not the
            # offset's (which no annulus of that row could hold)
            _check_annuli(lo, hi, where, shared=False)
            bad = (x < lo) | (x > hi)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise SceneError(f"{where}, column 'offset', row {i + 1}", float(x_disp[i]),
                                 "must lie in its annulus [offset_lo, offset_hi]")
        else:
            lo, hi = _annuli_from_offsets(x, where)
            _check_annuli(lo, hi, where, shared=False)
        norm = "free"
    else:
        x = _wavelengths(cols["wavelength"], where)
        x_disp, x_unit = _values(cols["wavelength"][0], "wavelength", where), cols["wavelength"][1]
        text = "must have no unit (a ratio of fluxes)"
        for c in ("ratio", "ratio_err"):
            _check_unit(cols[c][1], c, where, [u.dimensionless_unscaled], text)
        value = _values(cols["ratio"][0], "ratio", where)
        _bounded(value, "ratio", where)
        error = _values(cols["ratio_err"][0], "ratio_err", where)
        _positive(error, "ratio_err", where)
        if "offset_lo" in cols:
            lo, hi = offsets("offset_lo")[0], offsets("offset_hi")[0]
        else:
            a = tuple(float(v) for v in annulus)
            lo, hi = np.full(len(x), a[0]), np.full(len(x), a[1])
        _check_annuli(lo, hi, where, shared=True)
        for a in set(zip(lo.tolist(), hi.tolist())):
            rows = (lo == a[0]) & (hi == a[1])
            if len(np.unique(x[rows])) != rows.sum():
                raise SceneError(f"{where}, column 'wavelength'", x[rows].tolist(),
                                 "must not repeat within one annulus")
        norm = str(meta.get("normalisation", normalisation))
        if norm not in NORMALISATIONS:
            raise SceneError(f"{where}, meta 'normalisation'", norm, f"must be one of {', '.join(NORMALISATIONS)}")
    return ObservedTable(kind=kind, path=label, x=np.asarray(x, np.float64), value=value, error=error,
                         lo=np.asarray(lo, np.float64), hi=np.asarray(hi, np.float64),
                         x_display=np.asarray(x_disp, np.float64), x_unit="box units" if x_unit is None else
                         str(x_unit), normalisation=norm, meta=meta)


def _wavelengths(column, where: str) -> np.ndarray:
    """A wavelength column (values, unit) in nm: a unit of wavelength or frequency is needed,
    every value > 0."""
    import astropy.units as u

    col, unit = column
    wl_disp = _values(col, "wavelength", where)
    if unit is None or not unit.is_equivalent(u.nm, equivalencies=u.spectral()):
        raise SceneError(f"{where}, column 'wavelength'", None if unit is None else str(unit),
                         "needs a unit of wavelength (nm, Angstrom, um) or frequency: in the ECSV header, "
                         "or in a CSV header as 'wavelength [nm]'")
    x = (wl_disp * unit).to_value(u.nm, equivalencies=u.spectral())
    if np.any(x <= 0):
        i = int(np.flatnonzero(x <= 0)[0])
        raise SceneError(f"{where}, column 'wavelength', row {i + 1}", float(wl_disp[i]), "must be > 0")
    return x


def write_table(table: ObservedTable, path: Union[str, Path], meta: Optional[dict] = None) -> None:
    """Write an :class:`ObservedTable` as ECSV with units (offsets in box units), e.g. a
    synthetic observation to fit."""
    import astropy.units as u
    from astropy.table import Table

    t = Table(meta=dict(meta or {}))
    if table.kind == "colour":
        t["offset"] = table.x
        t["offset_lo"], t["offset_hi"] = table.lo, table.hi
        t["delta_bv"] = table.value * u.mag
        t["delta_bv_err"] = table.error * u.mag
    elif table.kind == "polarization":
        t["offset"] = table.x
        t["offset_lo"], t["offset_hi"] = table.lo, table.hi
        t["wavelength"] = table.wavelength * u.nm
        t["polarization"] = table.value
        t["polarization_err"] = table.error
    else:
        t["wavelength"] = table.x * u.nm
        t["ratio"] = table.value
        t["ratio_err"] = table.error
        t["offset_lo"], t["offset_hi"] = table.lo, table.hi
        t.meta["normalisation"] = table.normalisation
    t.write(str(path), format="ascii.ecsv", overwrite=True)


def finite_or_none(x):
    """A float for JSON: None where not finite."""
    x = float(x)
    return x if math.isfinite(x) else None
