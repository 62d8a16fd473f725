"""The scene model: plain dataclasses mirroring the TOML scene file.

Every TOML table has a dataclass and every key a field of the same name (the
keys are public API, see docs/design.md "Scene file contract")::

    [grid]          -> Grid
    [dust]          -> Dust
    [[stars]]       -> Star (one or more)
    [bands]         -> BandsConfig  (explicit bands: [[bands.list]])
    [transport]     -> Transport
    [colour]        -> Colour       (extension table)
    [observer]      -> Observer     (where the scene is on the sky; calibrated images)

Units
-----
Positions and lengths are in *box units*: the simulation box is ``[0, 1]^3``
whatever ``grid.shape`` is.  ``grid.length`` / ``grid.unit`` give the
physical size of one box edge.  ``dust.tau`` is the optical depth across one
box edge at density 1 in the reference band (see
:func:`nebula_rt.bands.reference_band_index`).  Physical quantities may replace
the box-unit ones (``dust.hydrogen_density``, ``dust.mass_density``,
``dust.visual_extinction`` set ``dust.tau``; ``stars.luminosity_lsun``,
``stars.absolute_magnitude`` set ``stars.luminosity``): they are converted
when the scene is built (:mod:`nebula_rt.units`), so the transport sees box
units only.

This module never imports VTK.
"""

from __future__ import annotations

import copy
import math
import numbers
import re
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from . import limits
from .bands import BAND_KEYS, PRESETS, Band, resolve_bands
from .errors import SceneError
from .limits import FLOAT32_RANGE_TEXT, INT32_MAX, MAX_OFFSET, TEMPERATURE_RANGE, float32_allowed, in_float32_range
from . import schema
from . import units
from .schema import document, param

__all__ = [
    "Grid",
    "Dust",
    "Star",
    "BandsConfig",
    "Transport",
    "Colour",
    "Observer",
    "Scene",
]

Vec3 = Tuple[float, float, float]

DUST_MODELS = ("turbulence", "uniform", "file")
ESTIMATORS = ("track-length", "collision-filter")
#: transport.method: chosen per run from the measurement (auto), analog packets, or weighted ones
METHODS = ("auto", "analog", "biased")
#: ``transport.method = "auto"``: the scene optical depths (nebula_rt.transport.
#: scene_optical_depth) between which a run with a peel-off image stays analog. Measured on
#: an H200 (benchmarks/bench_biasing.py, 64^3, 1e7 packets, slab and sphere, albedo 0.6, g 0.6;
#: benchmarks/results/h200-2026-12-03/; docs/physics.md): the image's figure of merit of the
#: weighted packets is 1.4-1.6 times the analog one at depth 0.1, 0.3-0.6 times at 0.3-3, equal
#: at 10, and 50-900 times at 20-30, where the analog image is also wrong (14 % low at 20, 92 %
#: at 30, empty at 60: benchmarks/bench_thick_slab.py); the light field is analog at every
#: depth (its figure of merit 3-60 times the weighted packets' over the lit region).
AUTO_THIN, AUTO_THICK = 0.2, 10.0
#: transport.error_estimate: how the error of J is estimated (nebula_rt.transport)
ERROR_ESTIMATES = ("auto", "batches", "packets")
BACKENDS = ("auto", "opencl", "cuda")
WHITE_POINTS = ("D65", "E", "star")
STRETCHES = ("linear", "asinh")
#: magnitude systems of calibrated sky images (nebula_rt.calibrate.AB_MINUS_VEGA)
MAG_SYSTEMS = ("AB", "Vega")
MAX_PHOTONS = 2**53
#: Seeds are [0, 2**53]: the RNG's key is 64 bits (any uint64 would work on the device), but a
#: seed travels as a double in ParaView's panel, in pvpython and in JSON, which hold every
#: integer exactly up to 2**53 and no further (2**53 + 1 becomes 2**53 without a word). So the
#: scene declares what every layer holds exactly rather than a range the panel would round.
MAX_SEED = 2**53


# ---------------------------------------------------------------------------
# dataclasses
# ---------------------------------------------------------------------------


#: Quality presets: a target for the lit-region error (1 sigma, brightness-weighted RMS over the
#: lit voxels; nebula_rt.transport.lit_region_error) with a photon budget per band. From the
#: measured curves (docs/trade_study.md, track-length on the thesis nebula): the error falls
#: as 127 / sqrt(N) at 64^3 and 240 / sqrt(N) at 128^3, so 10 % takes 1.6M packets per band at
#: 64^3 (5.8M at 128^3), 3 % 18M (64M) and 1 % 160M (580M); the budgets cover 128^3. At 10 %
#: a rendering is grainy, at 3 % clean, at 1 % indistinguishable from a 10x longer run.
QUALITY_PRESETS = {
    "preview": {"target_error": 0.10, "photons": 10_000_000},
    "balanced": {"target_error": 0.03, "photons": 100_000_000},
    "reference": {"target_error": 0.01, "photons": 1_000_000_000},
}
QUALITIES = ("",) + tuple(QUALITY_PRESETS)


# Panel groups, in the order of the workflow (density source, dust optics, stars, transport,
# quality, device)
G_GRID, G_DUST, G_OPTICS, G_STARS = "Dust", "Dust", "Dust optics", "Stars"
G_TRANSPORT, G_QUALITY, G_DEVICE, G_COLOUR = "Photon transport", "Quality", "Compute device", "Colour"
G_UNITS, G_OBSERVER = "Physical units", "Observer"


@document
@dataclass
class Grid:
    """The voxel grid, TOML table ``[grid]``."""

    shape: Tuple[int, int, int] = param(
        (64, 64, 64), type="tuple of 3 int", lo=2, hi=INT32_MAX, label="Grid Shape", group=G_GRID,
        doc="Voxels along x, y, z (non-cubic allowed). The grid spans the box [0, 1]^3 whatever its "
            "shape, so voxels need not be cubes; memory and trace time grow with the number of voxels "
            "(the thesis used 128^3)")
    length: Union[float, str] = param(
        1.0, type="float or str", lo=0.0, lo_open=True, label="Box Length", group=G_UNITS, advanced=True,
        doc="Physical length of one box edge: a number in `unit`, or a quantity with its own unit "
            "(\"3 pc\", \"2e5 AU\"; astropy.units). The transport works in box units; the length "
            "converts the physical dust keys to dust.tau and scales calibrated sky images")
    unit: str = param("pc", type="str", group=G_UNITS, advanced=True,
                      doc="Length unit of a numeric `length` (pc, AU, ly, km, ...; astropy.units)")


@document
@dataclass
class Dust:
    """The dust density field, TOML table ``[dust]``."""

    model: str = param(
        "turbulence", type="str", choices=DUST_MODELS, group=G_DUST,
        doc="How the density is made: procedural turbulence noise (the thesis, Eq. 3.2), a constant, "
            "or read from `file`; each star's dust bump and the floor are added")
    density: float = param(
        1.0, type="float", lo=0.0, label="Uniform Density", group=G_DUST,
        doc="\"uniform\": the density everywhere (dimensionless; `tau` is the optical depth across the "
            "box at density 1)")
    file: str = param(
        "", type="str", group=G_DUST,
        doc="\"file\": a .npy array in (x, y, z) order or a .vti image; a relative path is relative to "
            "the scene file's folder")
    array: str = param("density", type="str", group=G_DUST,
                       doc="\"file\" with .vti: the name of the point-data array to read")
    scale: float = param(
        0.15, type="float", lo=0.0, group=G_DUST,
        doc="\"turbulence\": amplitude of the noise (the thesis's densityScale, 0.15)")
    offset: Vec3 = param(
        (0.5, 0.5, 0.5), type="tuple of 3 float", lo=-MAX_OFFSET, hi=MAX_OFFSET, unit="box units", group=G_DUST,
        doc="\"turbulence\": offset into the noise; a different offset gives a different nebula")
    floor: float = param(
        1e-4, type="float", lo=0.0, group=G_DUST, advanced=True,
        doc="Minimum density everywhere (the thesis's clamp; keeps the medium from being empty)")
    tau: float = param(
        1.0, type="float", lo=0.0, label="Tau", group=G_DUST,
        doc="Optical depth across one box edge at density 1 in the reference band: the extinction "
            "per box edge is tau x extinction_b x density (the thesis's 128^3 nebula: 128, i.e. "
            "extinction = density per voxel). Set by hydrogen_density, mass_density or "
            "visual_extinction where one of them is given")
    hydrogen_density: Optional[float] = param(
        None, type="float or None", lo=0.0, unit="cm^-3", label="Hydrogen Density", group=G_UNITS, advanced=True,
        doc="H nuclei per cm^3 at density 1: sets tau = n_H x C_ext per H in the reference band "
            "(Draine 2003 dust of the band preset) x the box edge (grid.length) in cm")
    mass_density: Optional[float] = param(
        None, type="float or None", lo=0.0, unit="g cm^-3", label="Dust Mass Density", group=G_UNITS,
        advanced=True,
        doc="Grams of dust per cm^3 at density 1: sets tau through the dust model's dust mass per "
            "H nucleon (1.870e-26 g for R_V = 3.1, Draine's table) as hydrogen_density does")
    visual_extinction: Optional[float] = param(
        None, type="float or None", lo=0.0, unit="mag", label="Visual Extinction", group=G_UNITS, advanced=True,
        doc="A_V across one box edge at density 1: sets tau = A_V / 1.0857 x C_ext(reference band) "
            "/ C_ext(V) of the dust model")


@document
@dataclass
class Star:
    """A point source, one TOML ``[[stars]]`` table."""

    position: Vec3 = param(
        (0.5, 0.5, 0.5), type="tuple of 3 float", lo=0.0, hi=1.0, unit="box units", group=G_STARS,
        doc="Where the star is, inside [0, 1]^3")
    luminosity: float = param(
        1.0, type="float", lo=0.0, lo_open=True, unit="scene units", group=G_STARS,
        doc="Total luminosity over all bands; set (in L_sun inside the bands' range) by "
            "luminosity_lsun or absolute_magnitude where one is given")
    temperature: Optional[float] = param(
        None, type="float or None", lo=TEMPERATURE_RANGE[0], hi=TEMPERATURE_RANGE[1], unit="K", group=G_STARS,
        doc="Effective temperature: a blackbody spectrum then splits the luminosity over the bands "
            "and colours the star; None (omitted, 0 in a Stars table) gives every band an equal share")
    bump_radius: float = param(
        0.0, type="float", lo=0.0, hi=1.0, unit="box units", group=G_STARS,
        doc="Half-size of the thesis's cubic dust bump around the star (0 = none; the thesis used "
            "0.01); used where the density is made, not by the light field of a given density")
    spectrum: Optional[Tuple[Tuple[float, float], ...]] = param(
        None, type="tuple of (wavelength nm, relative power) pairs, or None", group=G_STARS,
        doc="A measured spectrum (at least 2 pairs, wavelengths increasing): it replaces the "
            "blackbody of `temperature` for the split over the bands and for the colour")
    luminosity_lsun: Optional[float] = param(
        None, type="float or None", lo=0.0, lo_open=True, unit="L_sun", group=G_STARS,
        doc="Bolometric luminosity in nominal solar luminosities (3.828e26 W): sets `luminosity` "
            "to the part of the blackbody of `temperature` inside the bands' range, in L_sun")
    absolute_magnitude: Optional[float] = param(
        None, type="float or None", unit="mag", group=G_STARS,
        doc="Absolute magnitude M_V (AB, Bessell V): sets `luminosity` as luminosity_lsun does, "
            "from the blackbody of `temperature` with that magnitude at 10 pc")
    spectral_type: Optional[str] = param(
        None, type="str or None", group=G_STARS,
        doc="MK spectral type and luminosity class (\"B2V\", \"B2.5 IV\", \"K0III\"; O1-M10): sets "
            "`temperature` from the calibration of de Jager & Nieuwenhuijzen (1987, A&A 177, 217), "
            "accurate to a few per cent")

    def spectral_source(self):
        """What sets the star's spectrum: the measured pairs, else the temperature (K), else
        None (flat); see :func:`nebula_rt.colour_convert.star_spectrum`."""
        return self.spectrum if self.spectrum else self.temperature


@document
@dataclass
class BandsConfig:
    """Band selection, TOML table ``[bands]``."""

    preset: Optional[str] = param(
        "thesis-rgb", type="str or None", choices=tuple(sorted(PRESETS)), label="Band Preset", group=G_OPTICS,
        doc="The wavelength bands traced, a preset of nebula_rt.bands.PRESETS (thesis-rgb: R 677, "
            "G 550, B 439 nm with the thesis's extinction factors 0.748 / 1 / 1.324); None whenever "
            "`list` is given")
    albedo: Optional[float] = param(
        None, type="float or None", lo=0.0, hi=1.0, group=G_OPTICS,
        doc="If given, the single-scattering albedo of the dust in every band (else each band's own)")
    g: Optional[float] = param(
        None, type="float or None", lo=-1.0, hi=1.0, label="G", group=G_OPTICS,
        doc="If given, the Henyey-Greenstein asymmetry parameter of every band (else each band's own)")
    list: Optional[List[Dict[str, Any]]] = param(
        None, type="list of dict or None", group=G_OPTICS,
        doc="Explicit bands, [[bands.list]] tables with keys name, wavelength (nm), extinction "
            "(relative to the reference band), albedo and g")

    def __post_init__(self) -> None:
        if self.list is not None:
            self.preset = None

    def resolve(self) -> List[Band]:
        """Return the validated bands (see :func:`nebula_rt.bands.resolve_bands`)."""
        return resolve_bands(self.preset, self.list, self.albedo, self.g)


@document
@dataclass
class Transport:
    """Monte Carlo transport settings, TOML table ``[transport]``."""

    photons: int = param(
        2_100_000, type="int", lo=1, hi=MAX_PHOTONS, unit="packets per band", group=G_QUALITY,
        doc="Photon packets traced per band (with a target error: the budget). The noise falls as "
            "1/sqrt(photons); the thesis used 2.1 million")
    estimator: str = param(
        "track-length", type="str", choices=ESTIMATORS, group=G_TRANSPORT,
        doc="Estimator of the mean intensity J per voxel. track-length: every packet's path through a "
            "voxel scores there (low noise); collision-filter: the thesis's estimator, collisions "
            "spread over filter_radius")
    method: str = param(
        "auto", type="str", choices=METHODS, label="Transport Method", group=G_TRANSPORT,
        doc="How packets are traced. analog: every packet is one unit of energy, absorbed or "
            "scattered with probability albedo; biased: weighted packets with forced scattering, "
            "composite path-length biasing and weight windows (splitting and Russian roulette), "
            "which sample light behind optically thick dust; auto: what was measured best for the run (docs/physics.md): "
            "analog for the light field, biased for a peel-off image when the optical depth from "
            f"the stars to the box's edge is below {AUTO_THIN:g} or above {AUTO_THICK:g}")
    error_estimate: str = param(
        "auto", type="str", choices=ERROR_ESTIMATES, label="Error Estimate", group=G_TRANSPORT, advanced=True,
        doc="How the error of J is estimated. batches: the spread of the totals of at least 16 batches "
            "of packets, each traced into its own slot; packets: from every packet's contribution to "
            "every voxel and its square (no batches: all packets in one stream, the memory of one "
            "64-bit slot per band more; analog packets without a target error, time limit or "
            "peel-off image; the errors are about 20 a % low where a = albedo x optical depth of a "
            "voxel edge, as packets scatter back into voxels they left); auto: packets for the transport "
            "by regions where batch slots would leave its passes poorly filled (on a CPU: always), "
            "a <= 0.025 and the memory target holds, else batches (docs/physics.md)")
    filter_radius: float = param(
        0.02, type="float", lo=0.0, lo_open=True, unit="box units", label="Filter Radius", group=G_TRANSPORT,
        doc="Radius of the collision filter (collision-filter only)")
    max_scatterings: int = param(
        1000, type="int", lo=0, hi=INT32_MAX, label="Max Scatterings", group=G_TRANSPORT, advanced=True,
        doc="A packet is terminated (and tallied as such) after this many scatterings")
    seed: int = param(
        1, type="int", lo=0, hi=MAX_SEED, group=G_TRANSPORT, advanced=True,
        doc="Random seed: the same seed, scene and device give the same bits")
    backend: str = param(
        "auto", type="str", choices=BACKENDS, group=G_DEVICE, advanced=True,
        doc="Compute backend: auto (CUDA if usable, else OpenCL), opencl or cuda")
    device: str = param(
        "", type="str", group=G_DEVICE, advanced=True,
        doc="Compute device: empty = automatic (a GPU if there is one), else a text contained in the "
            "device's name (e.g. NVIDIA, Portable Computing Language)")
    batch_size: int = param(
        0, type="int", lo=0, hi=MAX_PHOTONS, unit="packets per band", label="Batch Size", group=G_DEVICE,
        advanced=True,
        doc="Packets per band in one batch, the unit of the Monte Carlo error estimate (0 = automatic: "
            "at least 16 batches); progress and cancelling happen between kernel launches")
    target_error: float = param(
        0.0, type="float", lo=0.0, hi=1.0, label="Target Error", group=G_QUALITY,
        doc="0: trace `photons` packets. In (0, 1): trace until the relative error in the lit region "
            "(RMS over the lit voxels, 1 sigma) is at most this, `photons` being the budget")
    time_limit: float = param(
        0.0, type="float", lo=0.0, unit="s", label="Time Limit", group=G_QUALITY, advanced=True,
        doc="0: none. Above 0: end the run after this long (within one launch), keeping the batches "
            "finished by then; `photons` is then a budget")
    quality: str = param(
        "", type="str", choices=QUALITIES, choice_labels=("custom",) + QUALITIES[1:], group=G_QUALITY,
        doc="\"\" (custom: photons and target_error as given) or a preset: preview / balanced / "
            "reference trace until the lit region's error is 10 % / 3 % / 1 % (budgets of 10M / 100M "
            "/ 1000M packets per band); a preset replaces photons and target_error")

    def effective(self) -> tuple[int, float]:
        """(photons per band or budget, target error) after applying the quality preset."""
        if self.quality:
            preset = QUALITY_PRESETS[self.quality]
            return int(preset["photons"]), float(preset["target_error"])
        return int(self.photons), float(self.target_error)




@document
@dataclass
class Colour:
    """Conversion of the band results to sRGB, TOML table ``[colour]`` (extension)."""

    exposure: Union[float, str] = param(
        "auto", type="\"auto\" or float", lo=0.0, lo_open=True, auto=True, number=1.0, group=G_COLOUR,
        doc="Factor applied to the linear colour before the sRGB transfer; \"auto\": the one that maps "
            "the 95th percentile of the visible voxels' brightest colour component to full scale")
    white_point: str = param(
        "D65", type="str", choices=WHITE_POINTS, label="White Point", group=G_COLOUR,
        doc="White balance: D65 (daylight), E (equal energy) or star (the first star's blackbody "
            "colour is white)")
    opacity_scale: Union[float, str] = param(
        "auto", type="\"auto\" or float", lo=0.0, lo_open=True, auto=True, number=1.0, label="Opacity Scale",
        group=G_COLOUR,
        doc="Factor on each voxel's reference-band optical depth in the volume's alpha (1: the dust's own "
            "opacity); \"auto\": the factor that gives the box a mean optical depth of 3 across, so that a "
            "thin or a thick nebula is seen through as a whole (nebula_rt.pipeline.AUTO_OPACITY_MEAN_TAU)")
    stretch: str = param(
        "linear", type="str", choices=STRETCHES, label="Stretch", group=G_COLOUR,
        doc="Tone curve of the pictures: linear (the exposure, then the sRGB transfer curve) or "
            "asinh (Lupton et al. 2004, PASP 116, 133: colour-preserving, with softening asinh_q; "
            "the exposure's level still maps to full scale)")
    asinh_q: float = param(
        8.0, type="float", lo=0.0, lo_open=True, hi=1e10, label="Asinh Q", group=G_COLOUR,
        doc="The asinh stretch's softening Q: how far the faint light is lifted (about Q / asinh(Q) "
            "times the linear exposure)")


@document
@dataclass
class Observer:
    """Where the scene lies on the sky, for calibrated sky images, TOML table ``[observer]``."""

    distance: Optional[Union[float, str]] = param(
        None, type="float or str or None", lo=0.0, lo_open=True, unit="pc", group=G_OBSERVER,
        doc="Distance from the observer to the box centre: a quantity (\"140 pc\") or a number in "
            "pc; sets the image's angular scale and the stars' flux")
    ra: float = param(0.0, type="float", lo=0.0, hi=360.0, unit="deg", label="RA", group=G_OBSERVER,
                      doc="Right ascension (ICRS) of the box centre, the sky image's reference point")
    dec: float = param(0.0, type="float", lo=-90.0, hi=90.0, unit="deg", label="Dec", group=G_OBSERVER,
                       doc="Declination (ICRS) of the box centre")
    position_angle: float = param(
        0.0, type="float", lo=-360.0, hi=360.0, unit="deg", label="Position Angle", group=G_OBSERVER,
        doc="Position angle of the image's up axis, from north through east (0: up is north and "
            "east is left)")
    psf_fwhm: float = param(
        0.0, type="float", lo=0.0, unit="arcsec", label="PSF FWHM", group=G_OBSERVER,
        doc="FWHM of the Gaussian point-spread function the calibrated image is convolved with "
            "(0: none; a star then fills the pixel it falls in)")
    magnitude_system: str = param(
        "AB", type="str", choices=MAG_SYSTEMS, label="Magnitude System", group=G_OBSERVER,
        doc="Zero point of the calibrated images' magnitudes: AB (3631 Jy) or Vega (AB minus the "
            "passband's AB - Vega offset of Blanton & Roweis 2007, AJ 133, 734, Table 1)")


#: The scene file's tables with their dataclasses, in the file's order: the schema
#: (:mod:`nebula_rt.schema`). A star's keys are ``stars.<field>`` (the same for every star).
SECTIONS = (("grid", Grid), ("dust", Dust), ("stars", Star), ("bands", BandsConfig), ("transport", Transport),
            ("colour", Colour), ("observer", Observer))


def parameters():
    """Every scene parameter as (key, :class:`~nebula_rt.schema.Param`, default), in the file's order."""
    return schema.parameters(SECTIONS)


def declaration(key: str) -> "schema.Param":
    """The declaration of scene key ``key`` (``"transport.photons"``); KeyError if none."""
    return schema.declaration(SECTIONS, key)


def default(key: str):
    """The default value of scene key ``key``."""
    return schema.default(SECTIONS, key)


# ---------------------------------------------------------------------------
# type coercion and per-key rules
# ---------------------------------------------------------------------------


def _is_real(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _to_float(v: Any) -> float:
    if not _is_real(v):
        raise TypeError
    return float(v)  # may raise OverflowError for huge ints


def _to_int(v: Any) -> int:
    if isinstance(v, bool):
        raise TypeError
    if isinstance(v, numbers.Integral):
        return int(v)
    if _is_real(v):
        f = float(v)
        # a whole float (2.1e6) is an integer; beyond 2**53 a float no longer says which one
        if math.isfinite(f) and f == math.floor(f) and abs(f) <= 2.0**53:
            return int(f)
    raise TypeError


def _to_spectrum(v: Any):
    if v is None:
        return None
    if isinstance(v, (str, bytes)) or not isinstance(v, (list, tuple)):
        raise TypeError
    pairs = []
    for p in v:
        if isinstance(p, (str, bytes)) or not isinstance(p, (list, tuple)) or len(p) != 2:
            raise TypeError
        pairs.append((_to_float(p[0]), _to_float(p[1])))
    return tuple(pairs)


def _valid_spectrum(v) -> bool:
    if v is None:
        return True
    wl = [p[0] for p in v]
    power = [p[1] for p in v]
    return (len(v) >= 2 and all(math.isfinite(x) and 0.0 < x <= 1e5 for x in wl)
            and all(b > a for a, b in zip(wl, wl[1:]))
            and all(math.isfinite(x) and x >= 0.0 for x in power) and any(x > 0.0 for x in power))


def _to_str(v: Any) -> str:
    if not isinstance(v, str):
        raise TypeError
    return v


def _to_opt_str(v: Any) -> Optional[str]:
    return None if v is None else _to_str(v)


def _to_opt_float(v: Any) -> Optional[float]:
    return None if v is None else _to_float(v)


def _three(v: Any) -> list:
    """The 3 items of a list, tuple or 1-d array; TypeError otherwise."""
    if isinstance(v, (str, bytes, Mapping)):
        raise TypeError
    items = list(v)  # TypeError if not iterable
    if len(items) != 3:
        raise TypeError
    return items


def _to_vec3(v: Any) -> Vec3:
    return tuple(_to_float(x) for x in _three(v))  # type: ignore[return-value]


def _to_ivec3(v: Any) -> Tuple[int, int, int]:
    return tuple(_to_int(x) for x in _three(v))  # type: ignore[return-value]


def _to_length(v: Any) -> Union[float, str]:
    """A length: a number (float) or a quantity string ("3 pc"), checked by units.valid_length."""
    return v if isinstance(v, str) else _to_float(v)


def _to_opt_length(v: Any) -> Optional[Union[float, str]]:
    return None if v is None else _to_length(v)


def _finite(v: Optional[float]) -> bool:
    return v is None or math.isfinite(v)


def _opt_nonneg(v: Optional[float]) -> bool:
    return v is None or (math.isfinite(v) and v >= 0)


def _to_auto_or_float(v: Any) -> Union[float, str]:
    if v == "auto" and isinstance(v, str):
        return v
    return _to_float(v)


def _finite_pos(v: float) -> bool:
    return math.isfinite(v) and v > 0


def _finite_nonneg(v: float) -> bool:
    return math.isfinite(v) and v >= 0


def _float32_nonneg(v: float) -> bool:
    """0, or positive within the normal float32 range (limits.FLOAT32_TINY .. FLOAT32_MAX)."""
    return v >= 0 and in_float32_range(v)


def _float32_pos(v: float) -> bool:
    return v > 0 and in_float32_range(v, zero=False)


def _one_of(options: Sequence[str]) -> str:
    return "one of: " + ", ".join(repr(o) for o in options)


class _Rule:
    """How one TOML key is converted (type) and checked (range)."""

    __slots__ = ("convert", "check", "allowed")

    def __init__(
        self,
        convert: Callable[[Any], Any],
        allowed: str,
        check: Optional[Callable[[Any], bool]] = None,
    ):
        self.convert = convert
        self.allowed = allowed
        self.check = check

    def coerce(self, param: str, value: Any) -> Any:
        try:
            return self.convert(value)
        except (TypeError, ValueError, OverflowError):
            raise SceneError(param, value, self.allowed) from None

    def validate(self, param: str, value: Any) -> None:
        v = self.coerce(param, value)
        if self.check is not None and not self.check(v):
            # Report vectors as the TOML writes them: [x, y, z].
            raise SceneError(param, list(value) if isinstance(value, tuple) else value, self.allowed)


_ANY_STR = _Rule(_to_str, "must be a string")

GRID_RULES: Dict[str, _Rule] = {
    "shape": _Rule(
        _to_ivec3,
        f"must be a list of 3 integers, each in [2, {INT32_MAX}] (int32 on the device)",
        lambda v: all(2 <= n <= INT32_MAX for n in v),
    ),
    "length": _Rule(_to_length, units.length_allowed("a finite length > 0"), units.valid_length),
    "unit": _Rule(_to_str, f"must be a length unit: {units.LENGTH_UNITS_TEXT}", units.is_length_unit),
}

DUST_RULES: Dict[str, _Rule] = {
    "model": _Rule(_to_str, _one_of(DUST_MODELS), lambda v: v in DUST_MODELS),
    "density": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "file": _ANY_STR,
    "array": _ANY_STR,
    "scale": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "offset": _Rule(
        _to_vec3,
        f"must be a list of 3 numbers in [-{MAX_OFFSET:g}, {MAX_OFFSET:g}] (box units; beyond, the float32 "
        "turbulence loses its structure: docs/physics.md)",
        lambda v: all(abs(x) <= MAX_OFFSET for x in v),  # False for NaN
    ),
    "floor": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "tau": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "hydrogen_density": _Rule(_to_opt_float, "must be a number of H nuclei per cm^3 >= 0 (finite; or omitted)",
                              _opt_nonneg),
    "mass_density": _Rule(_to_opt_float, "must be a dust mass density in g cm^-3 >= 0 (finite; or omitted)",
                          _opt_nonneg),
    "visual_extinction": _Rule(_to_opt_float, "must be an A_V in mag >= 0 (finite; or omitted)", _opt_nonneg),
}

STAR_RULES: Dict[str, _Rule] = {
    "position": _Rule(
        _to_vec3,
        "must be a list of 3 finite numbers in [0, 1] (box units)",
        lambda v: all(0.0 <= x <= 1.0 for x in v),
    ),
    "luminosity": _Rule(_to_float, float32_allowed("a number > 0", zero=False), _float32_pos),
    "temperature": _Rule(
        _to_opt_float,
        f"must be in [{TEMPERATURE_RANGE[0]:g}, {TEMPERATURE_RANGE[1]:g}] (K), or omitted",
        lambda v: v is None or TEMPERATURE_RANGE[0] <= v <= TEMPERATURE_RANGE[1],
    ),
    "bump_radius": _Rule(
        _to_float,
        f"must be 0 or a number in [{limits.fmt(limits.FLOAT32_TINY)}, 1) (box units; float32)",
        lambda v: v == 0.0 or limits.FLOAT32_TINY <= v < 1.0,
    ),
    "spectrum": _Rule(
        _to_spectrum,
        "must be a list of at least 2 [wavelength nm, relative power] pairs, wavelengths "
        "increasing in (0, 1e5], powers finite, >= 0 and not all 0 (or omitted)",
        _valid_spectrum,
    ),
    "luminosity_lsun": _Rule(_to_opt_float, "must be a bolometric luminosity in L_sun: a finite number > 0 "
                             "(or omitted)", lambda v: v is None or _finite_pos(v)),
    "absolute_magnitude": _Rule(_to_opt_float, "must be an absolute magnitude M_V in mag (AB, Bessell V): a "
                                "finite number (or omitted)", _finite),
    "spectral_type": _Rule(_to_opt_str, "must be " + units.SPECTRAL_TYPE_FORM + " (or omitted)",
                           lambda v: v is None or units.parse_spectral_type(v) is not None),
}

# Type-only rules for [bands]; ranges are checked by resolve_bands().
BANDS_RULES: Dict[str, _Rule] = {
    "preset": _Rule(_to_opt_str, "must be a preset name (string)"),
    "albedo": _Rule(_to_opt_float, "must be in [0, 1]"),
    "g": _Rule(_to_opt_float, "must be in [-1, 1]"),
    # "list" is handled separately (array of tables).
}
BAND_ENTRY_RULES: Dict[str, _Rule] = {
    "name": _Rule(_to_str, "must be a non-empty name made of [A-Za-z0-9_-]"),
    "wavelength": _Rule(_to_float, "must be a wavelength in nm in [1, 1e5]"),
    "extinction": _Rule(_to_float, "must be a number > 0 (relative to the reference band) in " + FLOAT32_RANGE_TEXT),
    "albedo": _Rule(_to_float, "must be in [0, 1]"),
    "g": _Rule(_to_float, "must be in [-1, 1]"),
}
assert tuple(BAND_ENTRY_RULES) == BAND_KEYS

TRANSPORT_RULES: Dict[str, _Rule] = {
    "photons": _Rule(
        _to_int, "must be an integer in [1, 2**53]", lambda v: 1 <= v <= MAX_PHOTONS
    ),
    "estimator": _Rule(_to_str, _one_of(ESTIMATORS), lambda v: v in ESTIMATORS),
    "method": _Rule(_to_str, _one_of(METHODS), lambda v: v in METHODS),
    "error_estimate": _Rule(_to_str, _one_of(ERROR_ESTIMATES), lambda v: v in ERROR_ESTIMATES),
    "filter_radius": _Rule(_to_float, "must be a finite number > 0 (box units)", _finite_pos),
    "max_scatterings": _Rule(_to_int, f"must be an integer in [0, {INT32_MAX}] (int32 on the device)",
                             lambda v: 0 <= v <= INT32_MAX),
    "seed": _Rule(_to_int, "must be an integer in [0, 2**53] (exact as a double: ParaView's panel, pvpython)",
                  lambda v: 0 <= v <= MAX_SEED),
    "backend": _Rule(_to_str, _one_of(BACKENDS), lambda v: v in BACKENDS),
    "device": _ANY_STR,
    "batch_size": _Rule(_to_int, f"must be an integer in [0, {MAX_PHOTONS}] (0 = automatic)",
                        lambda v: 0 <= v <= MAX_PHOTONS),
    "target_error": _Rule(_to_float, "must be 0 (off) or a number in (0, 1)", lambda v: v == 0 or 0 < v < 1),
    "time_limit": _Rule(_to_float, "must be a finite number >= 0 (seconds; 0 = none)",
                        lambda v: math.isfinite(v) and v >= 0),
    "quality": _Rule(_to_str, "must be one of: '' (none), " + ", ".join(repr(q) for q in QUALITY_PRESETS),
                     lambda v: v in QUALITIES),
}

COLOUR_RULES: Dict[str, _Rule] = {
    "exposure": _Rule(
        _to_auto_or_float,
        "must be 'auto' or a number > 0 in " + FLOAT32_RANGE_TEXT + " (the colours are float32)",
        lambda v: v == "auto" or _float32_pos(v),
    ),
    "white_point": _Rule(_to_str, _one_of(WHITE_POINTS), lambda v: v in WHITE_POINTS),
    "opacity_scale": _Rule(_to_auto_or_float, "must be 'auto' or a finite number > 0",
                           lambda v: v == "auto" or _finite_pos(v)),
    "stretch": _Rule(_to_str, _one_of(STRETCHES), lambda v: v in STRETCHES),
    "asinh_q": _Rule(_to_float, "must be a number in (0, 1e10] (the asinh softening Q)",
                     lambda v: 0.0 < v <= 1e10),
}

OBSERVER_RULES: Dict[str, _Rule] = {
    "distance": _Rule(_to_opt_length, units.length_allowed("a distance > 0", "pc") + " (or omitted)",
                      lambda v: v is None or units.valid_length(v)),
    "ra": _Rule(_to_float, "must be a right ascension in degrees in [0, 360)", lambda v: 0.0 <= v < 360.0),
    "dec": _Rule(_to_float, "must be a declination in degrees in [-90, 90]", lambda v: -90.0 <= v <= 90.0),
    "position_angle": _Rule(_to_float, "must be an angle in degrees in [-360, 360] (east of north)",
                            lambda v: -360.0 <= v <= 360.0),
    "psf_fwhm": _Rule(_to_float, "must be a FWHM in arcsec >= 0 (finite; 0 = no PSF)", _finite_nonneg),
    "magnitude_system": _Rule(_to_str, _one_of(MAG_SYSTEMS), lambda v: v in MAG_SYSTEMS),
}

# Schema tree, used by from_dict and with_overrides: a dict is a table, a
# one-element list an array of tables, a _Rule a leaf value.
_SCHEMA: Dict[str, Any] = {
    "grid": GRID_RULES,
    "dust": DUST_RULES,
    "stars": [STAR_RULES],
    "bands": {**BANDS_RULES, "list": [BAND_ENTRY_RULES]},
    "transport": TRANSPORT_RULES,
    "colour": COLOUR_RULES,
    "observer": OBSERVER_RULES,
}
_TABLE_NAMES = {
    "grid": "[grid]",
    "dust": "[dust]",
    "stars": "[[stars]]",
    "bands": "[bands]",
    "transport": "[transport]",
    "colour": "[colour]",
    "observer": "[observer]",
}


def _unknown_key(param: str, value: Any, allowed_keys: Sequence[str]) -> SceneError:
    return SceneError(
        param, value, "unknown key; allowed keys: " + ", ".join(repr(k) for k in allowed_keys)
    )


def _parse_table(name: str, d: Any, rules: Mapping[str, _Rule]) -> Dict[str, Any]:
    """Check keys, convert types and check the range of each value of one table."""
    if not isinstance(d, Mapping):
        raise SceneError(name, d, "must be a table")
    out = {}
    for key, value in d.items():
        param = f"{name}.{key}"
        if key not in rules:
            raise _unknown_key(param, value, list(rules))
        out[key] = rules[key].coerce(param, value)
        check = rules[key].check
        if check is not None and not check(out[key]):  # here, so that the message shows the value as given
            raise SceneError(param, value, rules[key].allowed)
    return out


def _parse_array(name: str, d: Any) -> list:
    if isinstance(d, (str, bytes, Mapping)) or not isinstance(d, Sequence):
        raise SceneError(name, d, f"must be an array of tables [[{name}]]")
    return list(d)


def _check_dataclass(prefix: str, obj: Any, rules: Mapping[str, _Rule]) -> None:
    for f in fields(obj):
        rules[f.name].validate(f"{prefix}.{f.name}", getattr(obj, f.name))


def _check_star_spectra(stars: Sequence[Star], bands: Sequence[Band]) -> None:
    """Every star's spectrum must overlap the visible range it is integrated over, and every band
    must get light from some star.

    The band luminosities integrate each spectrum over the bands' range (380-780 nm, widened to
    the outermost band centres) and the colours over the CIE range (360-830 nm); a spectrum
    with no power in 380-780 nm made a run fail half-way ("no power in the bands' range") or
    gave NaN colours, and a band without light divides the colour matrix by 0. Only scenes with
    a measured spectrum or a temperature import the colour module for this (a flat spectrum
    lights every band).
    """
    if not any(s.spectral_source() is not None for s in stars):
        return
    import numpy as np

    from . import colour_convert

    with np.errstate(over="ignore", under="ignore"):  # exp overflows far in the Wien tail: power 0 there
        _check_spectra_overlap(stars, bands, colour_convert)


def _check_spectra_overlap(stars, bands, colour_convert) -> None:
    def key_value(i):
        s = stars[i]
        if s.spectrum:
            return f"stars[{i}].spectrum", [list(p) for p in s.spectrum]
        return f"stars[{i}].temperature", s.temperature

    wl = [b.wavelength for b in bands]
    lo, hi = colour_convert.LUMINOSITY_RANGE_NM
    light = [0.0] * len(bands)
    for i, s in enumerate(stars):
        source = s.spectral_source()
        try:
            # one band centred in the visible: its range is exactly 380-780 nm
            colour_convert.band_luminosity_fractions([0.5 * (lo + hi)], source)
            fractions = colour_convert.band_luminosity_fractions(wl, source)
        except ValueError:
            raise SceneError(*key_value(i), f"must have power inside {lo}-{hi} nm, the visible range over "
                                            "which the band luminosities and colours are integrated") from None
        for b, f in enumerate(fractions):
            light[b] += s.luminosity * float(f)
    for b, band in enumerate(bands):
        if not light[b] > 0:  # also NaN
            i = max(range(len(stars)), key=lambda j: stars[j].luminosity)
            raise SceneError(*key_value(i), f"must give every band light: band {band.name!r} "
                                            f"({band.wavelength:g} nm) gets none from any star")


# ---------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------


@dataclass
class Scene:
    """A complete scene: the contents of one TOML scene file.

    Parameters
    ----------
    grid : Grid
    dust : Dust
    stars : list of Star
        One or more stars.
    bands : BandsConfig
    transport : Transport
    colour : Colour
    observer : Observer
    base_dir : Path or None
        Folder against which a relative ``dust.file`` is resolved (the scene
        file's folder for :meth:`load`).  Not part of the TOML, and not
        compared by ``==``.

    Notes
    -----
    Build scenes with :meth:`default`, :meth:`from_dict`, :meth:`load`,
    :meth:`loads` or :meth:`with_overrides`, which validate.  A scene built
    field by field should be checked with :meth:`validate`.
    """

    grid: Grid = field(default_factory=Grid)
    dust: Dust = field(default_factory=Dust)
    stars: List[Star] = field(default_factory=lambda: [Star()])
    bands: BandsConfig = field(default_factory=BandsConfig)
    transport: Transport = field(default_factory=Transport)
    colour: Colour = field(default_factory=Colour)
    observer: Observer = field(default_factory=Observer)
    base_dir: Optional[Path] = field(default=None, compare=False)

    # -- constructors -------------------------------------------------------

    @classmethod
    def default(cls) -> "Scene":
        """The default scene: 64^3 turbulence, one central star, thesis RGB bands."""
        scene = cls()
        scene.validate()
        return scene

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], base_dir: Optional[Union[str, Path]] = None) -> "Scene":
        """Build and validate a scene from a dict shaped like the TOML file.

        Missing tables and keys take their defaults; a missing ``stars`` array
        gives one default star at the box centre.

        Parameters
        ----------
        d : mapping
            ``{"grid": {...}, "dust": {...}, "stars": [{...}, ...], "bands":
            {..., "list": [{...}, ...]}, "transport": {...}, "colour": {...}}``.
        base_dir : str or Path, optional
            Folder for a relative ``dust.file``.

        Raises
        ------
        SceneError
            For unknown tables or keys, wrong types and out-of-range values.
        """
        if not isinstance(d, Mapping):
            raise SceneError("(scene)", d, "must be a table of tables")
        for key, value in d.items():
            if key not in _SCHEMA:
                raise SceneError(
                    key,
                    value,
                    "unknown table; allowed tables: " + ", ".join(_TABLE_NAMES.values()),
                )

        grid = Grid(**_parse_table("grid", d.get("grid", {}), GRID_RULES))
        dust = Dust(**_parse_table("dust", d.get("dust", {}), DUST_RULES))
        if "stars" in d:
            stars = [
                Star(**_parse_table(f"stars[{i}]", s, STAR_RULES))
                for i, s in enumerate(_parse_array("stars", d["stars"]))
            ]
        else:
            stars = [Star()]

        bands_d = d.get("bands", {})
        if not isinstance(bands_d, Mapping):
            raise SceneError("bands", bands_d, "must be a table")
        band_list = None
        if "list" in bands_d:
            band_list = []
            for i, entry in enumerate(_parse_array("bands.list", bands_d["list"])):
                band_list.append(_parse_table(f"bands.list[{i}]", entry, BAND_ENTRY_RULES))
        bands_kw = _parse_table("bands", {k: v for k, v in bands_d.items() if k != "list"}, BANDS_RULES)
        bands = BandsConfig(**bands_kw, list=band_list)

        transport = Transport(**_parse_table("transport", d.get("transport", {}), TRANSPORT_RULES))
        colour = Colour(**_parse_table("colour", d.get("colour", {}), COLOUR_RULES))
        observer = Observer(**_parse_table("observer", d.get("observer", {}), OBSERVER_RULES))

        scene = cls(
            grid=grid,
            dust=dust,
            stars=stars,
            bands=bands,
            transport=transport,
            colour=colour,
            observer=observer,
            base_dir=Path(base_dir) if base_dir is not None else None,
        )
        # the box-unit values a physical key sets, where the table gave them too: they must agree
        given_tau = dust.tau if "tau" in d.get("dust", {}) else None
        given_lum = {i: s.luminosity for i, s in enumerate(stars)
                     if "stars" in d and "luminosity" in d["stars"][i]}
        given_temp = {i: s.temperature for i, s in enumerate(stars)
                      if "stars" in d and d["stars"][i].get("temperature") is not None}
        scene._apply_units(given_tau, given_lum, given_temp)
        scene.validate()
        return scene

    @classmethod
    def loads(cls, text: str, base_dir: Optional[Union[str, Path]] = None) -> "Scene":
        """Parse a scene from TOML text (see :meth:`from_dict`)."""
        if not isinstance(text, str):
            raise SceneError("(toml)", type(text).__name__, "the scene must be given as text (str)")
        return cls.from_dict(_parse_toml(text, "<string>"), base_dir=base_dir)

    @classmethod
    def load(cls, path: Union[str, Path]) -> "Scene":
        """Read a TOML scene file; ``base_dir`` becomes the file's folder.

        Raises
        ------
        SceneError
            With parameter ``"scene file"`` when the path is missing, a folder or unreadable, or
            the file is not UTF-8 TOML; else as :meth:`from_dict`.
        """
        path = Path(path)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise SceneError("scene file", str(path), "must be an existing TOML file (no such file)") from None
        except IsADirectoryError:
            raise SceneError("scene file", str(path), "must be a TOML file, not a folder") from None
        except OSError as e:  # permission denied, a device, an I/O error
            raise SceneError("scene file", str(path), f"must be a readable TOML file ({e.strerror or e})") from None
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as e:
            raise SceneError("scene file", str(path), f"must be UTF-8 TOML text (byte 0x{data[e.start]:02x} at "
                                                      f"offset {e.start} is not UTF-8)") from None
        return cls.from_dict(_parse_toml(text, str(path)), base_dir=path.absolute().parent)

    # -- serialisation ------------------------------------------------------

    def to_dict(self) -> Dict[str, Any]:
        """The scene as a TOML-shaped dict (None values omitted, tuples as lists)."""

        def table(obj: Any) -> Dict[str, Any]:
            out = {}
            for f in fields(obj):
                v = getattr(obj, f.name)
                if v is None:
                    continue
                if isinstance(v, tuple):
                    v = [list(x) if isinstance(x, tuple) else x for x in v]
                elif isinstance(v, list):
                    v = copy.deepcopy(v)
                out[f.name] = v
            return out

        out = {
            "grid": table(self.grid),
            "dust": table(self.dust),
            "stars": [table(s) for s in self.stars],
            "bands": table(self.bands),
            "transport": table(self.transport),
            "colour": table(self.colour),
        }
        if self.observer != Observer():  # a scene that does not place itself on the sky has no [observer]
            out["observer"] = table(self.observer)
        return out

    def to_toml(self) -> str:
        """The scene as TOML text; ``Scene.loads(s.to_toml()) == s``."""
        import tomli_w

        text = tomli_w.dumps(self.to_dict())
        # Put short numeric arrays (shape, position, offset) on one line.
        return _NUMERIC_ARRAY.sub(
            lambda m: "= [" + ", ".join(x.rstrip(",") for x in m.group(1).split()) + "]",
            text,
        )

    # -- paths --------------------------------------------------------------

    def dust_file_path(self) -> Path:
        """``dust.file`` as a path, resolved against `base_dir` if relative.

        Raises
        ------
        SceneError
            If ``dust.file`` is empty.
        """
        if not self.dust.file:
            raise SceneError("dust.file", self.dust.file, "must name a .npy or .vti file")
        p = Path(self.dust.file).expanduser()
        if not p.is_absolute() and self.base_dir is not None:
            p = Path(self.base_dir) / p
        return p

    # -- validation ---------------------------------------------------------

    def validate(self) -> None:
        """Check every value; raise :class:`SceneError` on the first bad one.

        The error's ``parameter`` is the dotted TOML name (``"transport.photons"``,
        ``"stars[0].position"``, ``"bands.list[1].albedo"``), ``value`` the
        offending value and ``allowed`` what is allowed.
        """
        _check_dataclass("grid", self.grid, GRID_RULES)
        _check_dataclass("dust", self.dust, DUST_RULES)
        if self.dust.model == "file":
            if not self.dust.file:
                raise SceneError(
                    "dust.file", self.dust.file, "must name a .npy or .vti file when dust.model = 'file'"
                )
            if self.dust.file.lower().endswith(".vti") and not self.dust.array:
                raise SceneError(
                    "dust.array", self.dust.array, "must name the density array of the .vti file"
                )
        if not isinstance(self.stars, list) or len(self.stars) == 0:
            raise SceneError("stars", self.stars, "must contain at least one [[stars]] table")
        for i, s in enumerate(self.stars):
            if not isinstance(s, Star):
                raise SceneError(f"stars[{i}]", s, "must be a Star")
            _check_dataclass(f"stars[{i}]", s, STAR_RULES)
        for key, rule in BANDS_RULES.items():
            rule.coerce(f"bands.{key}", getattr(self.bands, key))
        bands = self.bands.resolve()
        self._apply_units()
        _check_dataclass("transport", self.transport, TRANSPORT_RULES)
        _check_dataclass("colour", self.colour, COLOUR_RULES)
        if not isinstance(self.observer, Observer):
            raise SceneError("observer", self.observer, "must be an Observer")
        _check_dataclass("observer", self.observer, OBSERVER_RULES)
        self._check_batches()
        _check_star_spectra(self.stars, bands)

    def _apply_units(self, given_tau: Optional[float] = None, given_luminosity: Optional[Mapping[int, float]] = None,
                     given_temperature: Optional[Mapping[int, float]] = None) -> None:
        """Set ``dust.tau``, the stars' ``temperature`` and ``luminosity`` from the physical keys
        that are given (:mod:`nebula_rt.units`); ``given_*``: the values the scene table gave for
        them too, which must then be the converted ones (bit for bit: a scene written by
        :meth:`to_toml` holds both)."""
        for i, s in enumerate(self.stars):
            if s.spectral_type is None:
                continue
            temperature = units.temperature_from_spectral_type(s.spectral_type)
            if given_temperature and i in given_temperature and given_temperature[i] != temperature:
                raise SceneError(f"stars[{i}].temperature", given_temperature[i],
                                 f"is set by stars[{i}].spectral_type = {s.spectral_type!r}, which gives "
                                 f"{temperature!r} K (de Jager & Nieuwenhuijzen 1987): give one of them")
            s.temperature = temperature
        key = units.physical_dust_key(self.dust)
        physical = [units.physical_star(s) for s in self.stars]
        if key is None and not any(physical):
            return
        bands = self.bands.resolve()
        if key is not None:
            value = getattr(self.dust, key)
            try:
                tau, how = units.dust_tau(self, bands)
            except (ValueError, OverflowError):
                tau, how = math.inf, "overflow"
            if not DUST_RULES["tau"].check(tau):
                raise SceneError(f"dust.{key}", value, f"gives dust.tau = {tau:.6g} ({how}), which "
                                 + DUST_RULES["tau"].allowed)
            if given_tau is not None and given_tau != tau:
                raise SceneError("dust.tau", given_tau, f"is set by dust.{key} = {value!r}, which gives {tau!r} "
                                 f"({how}): give one of them")
            self.dust.tau = tau
        if not any(physical):
            return
        j = physical.index(True)
        for i, s in enumerate(self.stars):
            if not physical[i]:
                raise SceneError(f"stars[{i}].luminosity", s.luminosity,
                                 f"must be physical too (luminosity_lsun or absolute_magnitude), as stars[{j}]'s is: "
                                 "scene units and L_sun do not mix")
            lum, lbol = units.star_luminosity(s, i, bands)
            k = "luminosity_lsun" if s.luminosity_lsun is not None else "absolute_magnitude"
            if not STAR_RULES["luminosity"].check(lum):
                raise SceneError(f"stars[{i}].{k}", getattr(s, k),
                                 f"gives a luminosity of {lum:.6g} L_sun inside the bands (bolometric {lbol:.6g} "
                                 f"L_sun), which " + STAR_RULES["luminosity"].allowed)
            if given_luminosity and i in given_luminosity and given_luminosity[i] != lum:
                raise SceneError(f"stars[{i}].luminosity", given_luminosity[i],
                                 f"is set by stars[{i}].{k} = {getattr(s, k)!r}, which gives {lum!r} L_sun inside "
                                 "the bands: give one of them")
            s.luminosity = lum

    def _check_batches(self) -> None:
        """An explicit batch size must leave at least 2 batches: the error estimate is the
        spread of the batch totals (one batch has none, and would report 100 % everywhere)."""
        t = self.transport
        photons, _ = t.effective()
        if t.batch_size:
            limits.check_batch_count(-(-photons // t.batch_size), t.batch_size)
        if t.batch_size and photons >= 2 and t.batch_size >= photons:
            raise SceneError(
                "transport.batch_size", t.batch_size,
                f"must be 0 (automatic) or less than the {photons} photons per band, so that there are "
                f"at least 2 batches for the error estimate (e.g. at most {photons // 2})")

    # -- overrides ----------------------------------------------------------

    def with_overrides(self, items: Sequence[str]) -> "Scene":
        """Return a new scene with ``dotted.key=value`` overrides applied.

        Parameters
        ----------
        items : sequence of str
            Each ``"table.key=value"``; ``value`` is parsed as a TOML value
            (``1e6``, ``[32, 32, 16]``, ``"cuda"``, ``{...}``) and taken as
            the raw string when it is not valid TOML (``opencl``).  Array
            elements are addressed by index: ``stars.0.luminosity=2`` (also
            ``stars[0].luminosity=2``), ``bands.list.1.g=0.3``.  Setting
            ``bands.preset`` drops an explicit ``bands.list``.

        Returns
        -------
        Scene
            A new, validated scene (this one is unchanged).

        Raises
        ------
        SceneError
            For a malformed item, an unknown key or index, or a bad value.
        """
        if isinstance(items, str):
            items = [items]
        d = self.to_dict()
        overridden = set()
        for item in items:
            if not isinstance(item, str) or "=" not in item:
                raise SceneError(str(item), item, "an override has the form dotted.key=value")
            key, raw = item.split("=", 1)
            key, raw = key.strip(), raw.strip()
            _apply_override(d, key, _parse_value(raw))
            overridden.add(re.sub(r"\[(\d+)\]", r".\1", key))
        _drop_derived(d, overridden)
        return Scene.from_dict(d, base_dir=self.base_dir)


def _drop_derived(d: Dict[str, Any], overridden) -> None:
    """Drop the box-unit values that physical keys set (dust.tau, a star's luminosity) from
    the scene dict of :meth:`Scene.with_overrides`, so that they are converted again from the
    physical keys as overridden; one overridden itself stays (and must then agree)."""
    dust = d.get("dust")
    if isinstance(dust, dict) and any(dust.get(k) is not None for k in units.DUST_KEYS) \
            and not overridden & {"dust.tau", "dust"}:
        dust.pop("tau", None)
    stars = d.get("stars")
    if isinstance(stars, list) and "stars" not in overridden:
        for i, s in enumerate(stars):
            if isinstance(s, dict) and (s.get("luminosity_lsun") is not None or s.get("absolute_magnitude")
                                        is not None) and not overridden & {f"stars.{i}.luminosity", f"stars.{i}"}:
                s.pop("luminosity", None)
            if isinstance(s, dict) and s.get("spectral_type") is not None \
                    and not overridden & {f"stars.{i}.temperature", f"stars.{i}"}:
                s.pop("temperature", None)


def _parse_toml(text: str, where: str) -> Dict[str, Any]:
    """TOML text -> dict; SceneError("(toml)", where, ...) on malformed or pathologically
    nested text (tomllib recurses once per nesting level)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError("(toml)", where, f"not valid TOML: {e}") from None
    except RecursionError:
        raise SceneError("(toml)", where, "not valid TOML: arrays or tables nested too deeply") from None


_NUMERIC_ARRAY = re.compile(r"= \[\n((?:[ \t]+[-+0-9.eE_infa]+,\n)+)\]")


def _parse_value(raw: str) -> Any:
    try:
        parsed = tomllib.loads("v = " + raw)
    except Exception:
        return raw
    if set(parsed) != {"v"}:  # e.g. an embedded newline: not a single value
        return raw
    return parsed["v"]


def _apply_override(d: Dict[str, Any], key: str, value: Any) -> None:
    norm = re.sub(r"\[(\d+)\]", r".\1", key)
    tokens = norm.split(".")
    if not key or any(t == "" for t in tokens):
        raise SceneError(key, value, "an override key is dotted, e.g. transport.photons")

    container: Any = d
    schema: Any = _SCHEMA
    for depth, tok in enumerate(tokens):
        last = depth == len(tokens) - 1
        where = ".".join(tokens[:depth]) or "(scene)"
        if isinstance(schema, dict):
            if tok not in schema:
                if depth == 0:
                    allowed = "unknown table; allowed tables: " + ", ".join(_TABLE_NAMES.values())
                else:
                    allowed = "unknown key; allowed keys: " + ", ".join(repr(k) for k in schema)
                raise SceneError(key, value, allowed)
            if last:
                container[tok] = value
                if tokens[:depth] == ["bands"] and tok == "preset":
                    container.pop("list", None)
                return
            sub = schema[tok]
            if isinstance(sub, _Rule):
                raise SceneError(key, value, f"{'.'.join(tokens[: depth + 1])} is a value, not a table")
            if tok not in container:
                container[tok] = {} if isinstance(sub, dict) else []
            container, schema = container[tok], sub
            if isinstance(schema, dict) and not isinstance(container, dict):
                raise SceneError(key, value, f"{'.'.join(tokens[: depth + 1])} is not a table")
        else:  # array of tables
            n = len(container) if isinstance(container, list) else 0
            if not tok.isdigit() or int(tok) >= n:
                raise SceneError(
                    key,
                    value,
                    f"{where} is an array of {n} table(s): use {where}.N.key with N in 0..{n - 1}",
                )
            i = int(tok)
            if last:
                container[i] = value
                return
            container, schema = container[i], schema[0]
            if not isinstance(container, dict):
                raise SceneError(key, value, f"{where}.{i} is not a table")
