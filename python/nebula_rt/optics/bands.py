"""Wavelength bands: optical properties of the dust per band.

A band is one independent radiative-transfer problem (one set of photon
packets).  The dust's optical properties in a band are given *relative to the
reference band* (the band whose extinction is closest to 1.0), so that the
scene's ``dust.tau`` -- the optical depth across one box edge at density 1 in
the reference band -- fixes the absolute scale in every band.

The scene file chooses the bands with ``[bands]``: either ``preset = "<name>"``
(see :data:`PRESETS`) or an explicit ``[[bands.list]]`` array of tables with
keys ``name``, ``wavelength``, ``extinction``, ``albedo`` and ``g``.  The
optional ``bands.albedo`` / ``bands.g`` override every band.
"""

from __future__ import annotations

import numbers
import re
from dataclasses import asdict, dataclass, replace
from typing import Any, Dict, List, Mapping, Optional, Sequence

from .dust_tables import spectral_band_properties
from ..errors import SceneError
from ..limits import FLOAT32_RANGE_TEXT, FLOAT32_TINY, fmt, in_float32_range

__all__ = [
    "Band",
    "MAX_BANDS",
    "PRESETS",
    "resolve_bands",
    "reference_band_index",
    "spectral_bands",
]

#: Largest number of bands a scene may have.
MAX_BANDS = 32

#: Largest allowed wavelength in nm (100 um).
MAX_WAVELENGTH_NM = 1.0e5
#: Smallest allowed band wavelength in nm: the band integrals run on a 1 nm grid from the
#: shortest band centre rounded down, and at 0 nm the Planck law is 0 x infinity (NaN).
MIN_WAVELENGTH_NM = 1.0

_NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")

#: Keys of one ``[[bands.list]]`` table.
BAND_KEYS = ("name", "wavelength", "extinction", "albedo", "g")
#: The ranges of a band's albedo and g, declared once: a band's own values and the scene's
#: overrides (``bands.albedo``, ``bands.g``: nebula_rt.scene.sections) are held to them
ALBEDO_RANGE = (0.0, 1.0)
G_RANGE = (-1.0, 1.0)


@dataclass(frozen=True)
class Band:
    """Optical properties of the dust in one wavelength band.

    Parameters
    ----------
    name : str
        Band name, made of ``[A-Za-z0-9_-]``; unique within a scene.  It names
        the output arrays (``J_<name>``, ``emissivity_<name>``).
    wavelength : float
        Representative (central) wavelength in nm, in ``[1, 1e5]``.
    extinction : float
        Extinction cross-section relative to the reference band (> 0).  The
        extinction coefficient in this band is
        ``sigma_t = extinction * tau * density`` per box edge.
    albedo : float
        Single-scattering albedo, in ``[0, 1]``.
    g : float
        Henyey-Greenstein asymmetry parameter, in ``[-1, 1]``.
    """

    name: str
    wavelength: float
    extinction: float
    albedo: float
    g: float


def _thesis_rgb() -> List[Band]:
    return [
        Band("R", 677.0, 0.748, 0.6, 0.6),
        Band("G", 550.0, 1.0, 0.6, 0.6),
        Band("B", 439.0, 1.324, 0.6, 0.6),
    ]


class _Presets(Mapping):
    """Named band sets, built on first use (the spectral ones read Draine's dust tables)."""

    _makers = {
        "thesis-rgb": _thesis_rgb,
        "spectral-8": lambda: spectral_bands(8, "3.1"),
        "spectral-16": lambda: spectral_bands(16, "3.1"),
        "spectral-8-dense": lambda: spectral_bands(8, "5.5"),
    }

    def __init__(self):
        self._built: Dict[str, List[Band]] = {}

    def __getitem__(self, name: str) -> List[Band]:
        if name not in self._makers:
            raise KeyError(name)
        if name not in self._built:
            self._built[name] = self._makers[name]()
        return self._built[name]

    def __iter__(self):
        return iter(self._makers)

    def __len__(self) -> int:
        return len(self._makers)


def spectral_bands(n: int, rv: str = "3.1") -> List[Band]:
    """``n`` equal bands across 380-780 nm with Draine's dust of ``rv`` (band averages of
    :func:`nebula_rt.optics.dust_tables.spectral_band_properties`). Band names are their centre
    wavelengths ("405nm"); the band holding 550 nm is the reference band (extinction 1.0)."""
    return [Band(f"{centre:g}nm".replace(".", "p"), centre, extinction, albedo, g)
            for centre, extinction, albedo, g in spectral_band_properties(n, rv)]


#: Named band sets:
#:
#: - ``"thesis-rgb"``: the three bands of the 2010 thesis (R 677 nm, G 550 nm, B 439 nm;
#:   extinction relative to G; albedo 0.6 and g 0.6 in every band), in the order R, G, B;
#: - ``"spectral-8"``, ``"spectral-16"``: 8 or 16 equal bands across 380-780 nm with Milky Way
#:   dust, R_V = 3.1 (Draine 2003; :mod:`nebula_rt.optics.dust_tables`), band-averaged extinction
#:   (relative to the band holding 550 nm), albedo and g;
#: - ``"spectral-8-dense"``: 8 bands with the dense-cloud dust, R_V = 5.5.
PRESETS: Mapping[str, List[Band]] = _Presets()


def _allowed_presets() -> str:
    return "one of: " + ", ".join(repr(k) for k in PRESETS)


def _as_float(param: str, value: Any, allowed: str) -> float:
    """Convert an int/float (not bool) to float, or raise SceneError."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SceneError(param, value, allowed)
    try:
        return float(value)
    except (OverflowError, ValueError, TypeError):
        raise SceneError(param, value, allowed) from None


#: Albedo and g reach the device as float32: 0, or a magnitude of at least FLOAT32_TINY.
_TINY_TEXT = f"0 or at least {fmt(FLOAT32_TINY)} in magnitude (float32)"
#: What each entry of a ``[[bands.list]]`` table may be (the refusals' words), by key
ENTRY_ALLOWED = {
    "name": "must be a non-empty name made of [A-Za-z0-9_-]",
    "wavelength": f"must be a wavelength in nm in [{MIN_WAVELENGTH_NM:g}, {MAX_WAVELENGTH_NM:.0e}]".replace("e+0", "e"),
    "extinction": f"must be a number > 0 (relative to the reference band) in {FLOAT32_RANGE_TEXT} (float32)",
    "albedo": f"must be in [{ALBEDO_RANGE[0]:g}, {ALBEDO_RANGE[1]:g}], {_TINY_TEXT}",
    "g": f"must be in [{G_RANGE[0]:g}, {G_RANGE[1]:g}], {_TINY_TEXT}",
}


def _check_albedo(param: str, value: Any) -> float:
    allowed = ENTRY_ALLOWED["albedo"]
    v = _as_float(param, value, allowed)
    if not (ALBEDO_RANGE[0] <= v <= ALBEDO_RANGE[1] and in_float32_range(v)):  # False for NaN
        raise SceneError(param, value, allowed)
    return v


def _check_g(param: str, value: Any) -> float:
    allowed = ENTRY_ALLOWED["g"]
    v = _as_float(param, value, allowed)
    if not (G_RANGE[0] <= v <= G_RANGE[1] and in_float32_range(v)):
        raise SceneError(param, value, allowed)
    return v


def _check_extinction(param: str, value: Any) -> float:
    allowed = ENTRY_ALLOWED["extinction"]
    v = _as_float(param, value, allowed)
    if not (v > 0.0 and in_float32_range(v, zero=False)):
        raise SceneError(param, value, allowed)
    return v


def _check_wavelength(param: str, value: Any) -> float:
    allowed = ENTRY_ALLOWED["wavelength"]
    v = _as_float(param, value, allowed)
    if not (MIN_WAVELENGTH_NM <= v <= MAX_WAVELENGTH_NM):
        raise SceneError(param, value, allowed)
    return v


def _check_name(param: str, value: Any) -> str:
    allowed = ENTRY_ALLOWED["name"]
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise SceneError(param, value, allowed)
    return value


#: the keys of a band that Mie grains give (``bands.polarization = "mie"``)
GRAIN_KEYS = ("extinction", "albedo", "g")


def _band_from_entry(i: int, entry: Any, albedo: Optional[float], g: Optional[float],
                     grain_optics: bool = False, phase_g: Optional[float] = None) -> Band:
    prefix = f"bands.list[{i}]"
    if isinstance(entry, Band):
        entry = asdict(entry)
    if not isinstance(entry, Mapping):
        raise SceneError(prefix, entry, "must be a table with keys " + ", ".join(BAND_KEYS))
    for key in entry:
        if key not in BAND_KEYS:
            raise SceneError(
                f"{prefix}.{key}",
                entry[key],
                "unknown key; allowed keys: " + ", ".join(repr(k) for k in BAND_KEYS),
            )
    if grain_optics:  # the grains give the rest (nebula_rt.optics.mie.mie_bands): placeholders until then
        for key in GRAIN_KEYS:
            if key in entry:
                raise SceneError(f"{prefix}.{key}", entry[key], "must be omitted with bands.polarization = 'mie' "
                                 "(the grains give each band's extinction, albedo and g)")
        for key in ("name", "wavelength"):
            if key not in entry:
                raise SceneError(f"{prefix}.{key}", None, "required key is missing")
        return Band(name=_check_name(f"{prefix}.name", entry["name"]),
                    wavelength=_check_wavelength(f"{prefix}.wavelength", entry["wavelength"]),
                    extinction=1.0, albedo=0.0, g=0.0)
    if phase_g is not None:  # a tabulated phase function's g (bands.polarization = 'matrix')
        if "g" in entry:
            raise SceneError(f"{prefix}.g", entry["g"], "must be omitted with bands.polarization = 'matrix' "
                             "(the table's phase function gives g)")
        g = phase_g
    required = ["name", "wavelength", "extinction"]
    if albedo is None:
        required.append("albedo")
    if g is None:
        required.append("g")
    for key in required:
        if key not in entry:
            raise SceneError(
                f"{prefix}.{key}",
                None,
                "required key is missing (albedo and g may be omitted only when "
                "bands.albedo / bands.g are given)",
            )
    return Band(
        name=_check_name(f"{prefix}.name", entry["name"]),
        wavelength=_check_wavelength(f"{prefix}.wavelength", entry["wavelength"]),
        extinction=_check_extinction(f"{prefix}.extinction", entry["extinction"]),
        albedo=(
            _check_albedo(f"{prefix}.albedo", entry["albedo"]) if albedo is None else albedo
        ),
        g=_check_g(f"{prefix}.g", entry["g"]) if g is None else g,
    )


def resolve_bands(
    preset: Optional[str],
    band_list: Optional[Sequence[Mapping[str, Any]]],
    albedo: Optional[float] = None,
    g: Optional[float] = None,
    grain_optics: bool = False,
    phase_g: Optional[float] = None,
) -> List[Band]:
    """Build the validated list of bands of a scene.

    Parameters
    ----------
    preset : str or None
        Name of a preset in :data:`PRESETS`.  Ignored when `band_list` is given.
    band_list : sequence of mapping or None
        Explicit bands, each a mapping with keys ``name``, ``wavelength`` (nm),
        ``extinction`` (relative to the reference band), ``albedo`` and ``g``
        (a :class:`Band` is accepted too).  ``albedo`` / ``g`` may be omitted
        when the corresponding override below is given.
    albedo : float or None
        If not None, the single-scattering albedo of every band, in [0, 1].
    g : float or None
        If not None, the Henyey-Greenstein asymmetry of every band, in [-1, 1].
    grain_optics : bool
        The dust's grains give every band's extinction, albedo and g (Mie grains): explicit
        bands give name and wavelength alone (their other keys are refused), and come back
        with extinction 1, albedo 0 and g 0 for :func:`nebula_rt.optics.mie.mie_bands` to set.
    phase_g : float or None
        The asymmetry of a tabulated phase function (``bands.polarization = "matrix"``):
        every band's g; explicit bands then give no g (refused).

    Returns
    -------
    list of Band
        1 to :data:`MAX_BANDS` bands with unique names, in the given order.

    Raises
    ------
    SceneError
        With ``parameter`` ``"bands.preset"``, ``"bands.list"``,
        ``"bands.list[i].<key>"``, ``"bands.albedo"`` or ``"bands.g"``.
    """
    if albedo is not None:
        albedo = _check_albedo("bands.albedo", albedo)
    if g is not None:
        g = _check_g("bands.g", g)

    if band_list is None:
        if not isinstance(preset, str) or preset not in PRESETS:
            allowed = _allowed_presets()
            if preset is None:
                allowed += " (or give an explicit [[bands.list]])"
            raise SceneError("bands.preset", preset, allowed)
        bands = list(PRESETS[preset])
        if albedo is not None:
            bands = [replace(b, albedo=albedo) for b in bands]
        if g is not None:
            bands = [replace(b, g=g) for b in bands]
        if phase_g is not None:
            bands = [replace(b, g=float(phase_g)) for b in bands]
        return bands

    if isinstance(band_list, (str, bytes, Mapping)) or not isinstance(band_list, Sequence):
        raise SceneError("bands.list", band_list, "must be an array of tables [[bands.list]]")
    n = len(band_list)
    if not (1 <= n <= MAX_BANDS):
        raise SceneError("bands.list", n, f"must contain 1 to {MAX_BANDS} bands")
    bands = [_band_from_entry(i, entry, albedo, g, grain_optics, phase_g) for i, entry in enumerate(band_list)]
    seen = set()
    for i, b in enumerate(bands):
        if b.name in seen:
            raise SceneError(f"bands.list[{i}].name", b.name, "band names must be unique")
        seen.add(b.name)
    return bands


def reference_band_index(bands: Sequence[Band]) -> int:
    """Index of the reference band: the one whose extinction is closest to 1.0.

    Parameters
    ----------
    bands : sequence of Band
        At least one band.

    Returns
    -------
    int
        Index into `bands`; on ties the first such band.
    """
    if len(bands) == 0:
        raise SceneError("bands", [], f"must contain 1 to {MAX_BANDS} bands")
    best = 0
    best_d = abs(bands[0].extinction - 1.0)
    for i, b in enumerate(bands[1:], start=1):
        d = abs(b.extinction - 1.0)
        if d < best_d:
            best, best_d = i, d
    return best
