"""The output contract, declared once: names, types and meanings of the arrays and field data
that a light field (and a sky image made from it) carries.

Writers and readers go through this module instead of spelling the names themselves:

- point arrays: the :class:`PointArray` constants (:data:`J`, :data:`EMISSIVITY`, ...), whose
  :meth:`~PointArray.name` gives the array's name for a band;
- field data: :class:`LightFieldData` and :class:`SkyImageData`, one attribute per field. The
  metadata of their dataclass fields *are* the table (:func:`field_specs`: name pattern, type,
  meaning); :meth:`~ContractData.to_field_data` makes the flat ``{name: value}`` mapping that
  the VTK layer stores, :meth:`~ContractData.from_field_data` reads it back with the declared
  types.

Types in the flat mapping (what :mod:`nebula_rt.filters.image_data` turns into VTK arrays):
``float64`` fields are Python floats (a one-value ``vtkDoubleArray``), ``int64`` Python ints
(``Int64``), ``uint64`` NumPy ``uint64`` scalars (XML type ``UInt64``: the seed's whole range
[0, 2^64)), ``str`` strings (``vtkStringArray``), ``names`` a comma-separated string of the band
names, and array fields 1-D ``float64`` arrays (one value per band, or a vector). A field whose
name holds ``{band}`` is one field per band (``terminated_fraction_<band>``), its attribute an
array over the bands; ``{tally}`` runs over :data:`nebula_rt.transport.TALLY_NAMES`
(``emitted_<band>``, ``packets_absorbed_<band>``, ...).

This module imports no VTK: the library writes and reads the contract, the VTK layer only
stores it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Optional

import numpy as np

from ..errors import SceneError
from ..transport.plan import TALLY_NAMES

__all__ = [
    "DENSITY", "EMISSIVITY", "J", "REL_ERROR", "RGBA", "RGB_LINEAR", "LIGHT_FIELD_ARRAYS",
    "SKY_INTENSITY", "SKY_SCATTERED", "SKY_RELATIVE", "SKY_RGB", "SKY_IMAGE_ARRAYS",
    "SKY_SCATTERED_ERROR", "SKY_Q", "SKY_U", "SKY_Q_ERROR", "SKY_U_ERROR", "SKY_V", "SKY_V_ERROR", "PEEL_SKY_ARRAYS",
    "POLARIZATION_VECTOR", "POLARIZATION_DEGREE", "POLARIZATION_DEGREE_ERROR", "POLARIZATION_ANGLE",
    "POLARIZATION_ARRAYS",
    "STAR_ARRAYS", "STAR_LUMINOSITY", "STAR_RGB",
    "FieldSpec", "LightFieldData", "PointArray", "SkyImageData", "field_specs",
]


# --------------------------------------------------------------------------- point arrays


@dataclass(frozen=True)
class PointArray:
    """One point-data array of the contract.

    Attributes
    ----------
    key : str
        Its name; ``{band}`` stands for a band's name (one array per band).
    dtype : str
        NumPy dtype of its values.
    components : int
        Values per point.
    meaning : str
        What it holds, with units.
    """

    key: str
    dtype: str
    components: int
    meaning: str

    def name(self, band: Optional[str] = None) -> str:
        """The array's name (for ``band`` when it is one array per band)."""
        if ("{band}" in self.key) != (band is not None):
            raise ValueError(f"point array {self.key!r}: band {band!r}")
        return self.key.format(band=band)


DENSITY = PointArray("density", "float32", 1, "dust density (dimensionless; x tau x extinction = "
                                              "extinction per box unit)")
J = PointArray("J_{band}", "float32", 1, "mean intensity: luminosity per box-unit area per steradian")
EMISSIVITY = PointArray("emissivity_{band}", "float32", 1,
                        "scattered emissivity albedo x sigma x J: luminosity per box-unit volume per steradian")
REL_ERROR = PointArray("rel_error_{band}", "float32", 1, "batch-means relative standard error of J")
RGBA = PointArray("rgba", "uint8", 4, "sRGB colour of the emissivity and alpha = opacity of one voxel "
                                      "in the reference band (multi-band runs and Nebula Colour)")
RGB_LINEAR = PointArray("rgb_linear", "float32", 3, "exposed linear sRGB before the transfer curve "
                                                    "(Nebula Colour)")
#: the arrays of a light field, in the order they are written
LIGHT_FIELD_ARRAYS = (DENSITY, J, EMISSIVITY, REL_ERROR, RGBA, RGB_LINEAR)

STAR_RGB = PointArray("star_rgb", "uint8", 3, "sRGB of a star's own light at full brightness "
                                              "(the Stars output of Nebula Light Field: one point per star)")
STAR_LUMINOSITY = PointArray("luminosity", "float32", 1, "a star's luminosity (scene units)")
#: the point arrays of the stars (one vertex per star at its place in the light field)
STAR_ARRAYS = (STAR_RGB, STAR_LUMINOSITY)

SKY_INTENSITY = PointArray("I_{band}", "float32", 1, "sky intensity (scattered light and the stars): "
                                                     "luminosity per box-unit area per steradian")
SKY_SCATTERED = PointArray("scattered_{band}", "float32", 1, "the scattered light alone, same unit")
SKY_RELATIVE = PointArray("relative_{band}", "float32", 1, "surface brightness relative to the stars, "
                                                           "I / (L_band / 4 pi), per box-unit^2 of sky")
SKY_RGB = PointArray("rgb", "uint8", 3, "sRGB of the sky image")
#: the arrays of a sky image (Nebula Sky Image)
SKY_IMAGE_ARRAYS = (SKY_INTENSITY, SKY_SCATTERED, SKY_RELATIVE, SKY_RGB)
SKY_SCATTERED_ERROR = PointArray("scattered_error_{band}", "float32", 1,
                                 "peel-off: the batch-means standard error of scattered_{band}")
SKY_Q = PointArray("Q_{band}", "float32", 1, "peel-off of a polarized scene: Stokes Q of the scattered light, "
                   "the unit of scattered_; IAU convention with the image's up axis as north (east to its left)")
SKY_U = PointArray("U_{band}", "float32", 1, "peel-off of a polarized scene: Stokes U, as Q_")
SKY_Q_ERROR = PointArray("Q_error_{band}", "float32", 1, "the standard error of Q_{band}")
SKY_U_ERROR = PointArray("U_error_{band}", "float32", 1, "the standard error of U_{band}")
SKY_V = PointArray("V_{band}", "float32", 1, "peel-off of a scene whose grains make circular polarization "
                   "(bands.polarization = \"mie\"): Stokes V, as Q_; V > 0 for the electric vector "
                   "turning counterclockwise (north through east) as the observer sees it (IAU 1974)")
SKY_V_ERROR = PointArray("V_error_{band}", "float32", 1, "the standard error of V_{band}")
#: the arrays a peel-off sky image adds (its errors; a polarized scene's Stokes Q and U, and V
#: where the grains give it)
PEEL_SKY_ARRAYS = (SKY_SCATTERED_ERROR, SKY_Q, SKY_U, SKY_Q_ERROR, SKY_U_ERROR, SKY_V, SKY_V_ERROR)
#: a polarization vector field of a sky image (Nebula Polarization Vectors: cell data of one line
#: segment per block)
POLARIZATION_VECTOR = PointArray("polarization", "float32", 3, "P times the unit vector along the polarization "
                                 "angle in the image plane (north = +y, east = -x); a headless glyph's direction")
POLARIZATION_DEGREE = PointArray("P", "float32", 1, "degree of linear polarization of the block's scattered light")
POLARIZATION_DEGREE_ERROR = PointArray("P_error", "float32", 1, "its first-order standard error")
POLARIZATION_ANGLE = PointArray("angle", "float32", 1, "polarization angle, degrees from north (+y) through "
                                "east (-x), in [0, 180)")
POLARIZATION_ARRAYS = (POLARIZATION_VECTOR, POLARIZATION_DEGREE, POLARIZATION_DEGREE_ERROR, POLARIZATION_ANGLE)
SKY_SURFACE_BRIGHTNESS = PointArray("sb_{band}", "float32", 1, "calibrated surface brightness (scattered light "
                                    "and the stars, PSF-convolved), MJy/sr, band-averaged per unit frequency")
SKY_MAG = PointArray("mag_{band}", "float32", 1, "AB surface brightness through a passband (B, V, R: Bessell; "
                     "g, r, i: SDSS), mag/arcsec^2; NaN without light")
SKY_SB_Q = PointArray("sb_Q_{band}", "float32", 1, "calibrated Stokes Q of the scattered light (PSF-convolved), "
                      "MJy/sr, IAU convention on the sky (celestial north)")
SKY_SB_U = PointArray("sb_U_{band}", "float32", 1, "calibrated Stokes U, as sb_Q_")
SKY_SB_V = PointArray("sb_V_{band}", "float32", 1, "calibrated Stokes V (Mie grains), as sb_Q_")
#: the arrays a calibrated sky image adds (Nebula Sky Image with Units MJy/sr; per band, per
#: passband; a polarized peel-off's Stokes)
CALIBRATED_SKY_ARRAYS = (SKY_SURFACE_BRIGHTNESS, SKY_MAG, SKY_SB_Q, SKY_SB_U, SKY_SB_V)


# --------------------------------------------------------------------------- field data

_DTYPES = ("float64", "int64", "uint64", "str", "names")


@dataclass(frozen=True)
class FieldSpec:
    """One field-data entry of the contract (the metadata of a :class:`ContractData` field).

    Attributes
    ----------
    key : str
        Its name in the file: ``{band}`` / ``{tally}`` stand for each band's / tally's name.
    dtype : {"float64", "int64", "uint64", "str", "names"}
        The stored type (``names``: the band names, comma-separated in one string).
    array : bool
        A 1-D ``float64`` array (per band, or a vector) instead of one value.
    meaning : str
    optional : bool
        Absent from some outputs (a run without a density file has no ``dust_file_sha256``).
    """

    key: str
    dtype: str
    array: bool
    meaning: str
    optional: bool = False

    def keys(self, bands) -> list[str]:
        """The names this entry stands for, for these band names."""
        if "{tally}" in self.key:
            return [self.key.format(tally=t, band=b) for b in bands for t in TALLY_NAMES]
        if "{band}" in self.key:
            return [self.key.format(band=b) for b in bands]
        return [self.key]

    @property
    def per_band(self) -> bool:
        return "{band}" in self.key


def _field(dtype: str, meaning: str, *, key: Optional[str] = None, array: bool = False, optional: bool = False):
    """A dataclass field carrying its :class:`FieldSpec` (``key`` None: the attribute's name)."""
    assert dtype in _DTYPES, dtype
    return dataclasses.field(default=None, metadata={"contract": (key, dtype, array, meaning, optional)})


def field_specs(cls) -> dict[str, FieldSpec]:
    """The table of a :class:`ContractData` subclass: attribute name -> :class:`FieldSpec`."""
    out = {}
    for f in dataclasses.fields(cls):
        key, dtype, array, meaning, optional = f.metadata["contract"]
        out[f.name] = FieldSpec(key or f.name, dtype, array, meaning, optional)
    return out


def _scalar(value: Any):
    """One stored value: a Python scalar, or the single element of a 1-value array."""
    if isinstance(value, np.ndarray):
        if value.size != 1:
            raise ValueError(f"expected one value, found {value.size}")
        return value.reshape(-1)[0]
    return value


def _encode(spec: FieldSpec, value: Any):
    if spec.dtype == "names":
        return [str(v) for v in value]  # a string array, one value per band
    if spec.dtype == "str":
        return str(value)
    if spec.array:
        return np.array(value, dtype=np.float64).reshape(-1)
    if spec.dtype == "float64":
        return float(value)
    iv = int(value)
    if spec.dtype == "uint64":
        if not 0 <= iv < 2**64:
            raise OverflowError(f"field data {spec.key!r} = {iv} does not fit in uint64")
        return np.uint64(iv)
    if not -(2**63) <= iv < 2**63:
        raise OverflowError(f"field data {spec.key!r} = {iv} does not fit in int64")
    return iv


def _decode(spec: FieldSpec, value: Any):
    if spec.dtype == "names":
        if isinstance(value, (list, tuple)):
            return tuple(str(v) for v in value)
        # one band (a one-value string array), or a file of NebulaRT <= 0.1: names joined by ","
        return tuple(str(_scalar(value)).split(","))
    if spec.dtype == "str":
        return str(_scalar(value))
    if spec.array:
        return np.atleast_1d(np.asarray(value, dtype=np.float64)).reshape(-1)
    v = _scalar(value)
    return float(v) if spec.dtype == "float64" else int(v)


@dataclass
class ContractData:
    """Field data of one kind of output, one attribute per field (see the module notes).

    Every attribute defaults to None (not known): a reader asks for what it needs
    (``need``), a writer must set every field that is not optional.
    """

    #: what the input must come from, for the message of a missing field
    SOURCE: ClassVar[str] = ""

    def to_field_data(self, complete: bool = True) -> dict[str, object]:
        """The flat field data ``{name: value}``, typed as the table declares.

        Parameters
        ----------
        complete : bool
            Every field that is not optional must be set (the whole contract); False: only the
            fields that are set (a filter adding to its input's field data).

        Raises
        ------
        ValueError
            ``complete`` and a field is not set.
        """
        specs = field_specs(type(self))
        missing = [s.key for n, s in specs.items() if getattr(self, n) is None and not s.optional]
        if complete and missing:
            raise ValueError(f"{type(self).__name__}: no value for {', '.join(missing)}")
        bands = self.band_names
        out: dict[str, object] = {}
        for name, spec in specs.items():
            value = getattr(self, name)
            if value is None:
                continue
            if not spec.per_band:
                out[spec.key] = _encode(spec, value)
                continue
            if bands is None:
                raise ValueError(f"{type(self).__name__}: {spec.key} needs band_names")
            flat = np.asarray(value).reshape(-1)
            keys = spec.keys(bands)
            if flat.size != len(keys):
                raise ValueError(f"{type(self).__name__}.{name}: {flat.size} values for {len(keys)} fields")
            out.update((k, _encode(spec, v)) for k, v in zip(keys, flat.tolist()))
        return out

    @classmethod
    def from_field_data(cls, fd: Mapping, need=()) -> "ContractData":
        """Read the fields of the contract from a field-data mapping (other entries are ignored).

        Parameters
        ----------
        fd : mapping
            As :func:`nebula_rt.filters.image_data.field_data_dict` or :meth:`to_field_data`
            give it.
        need : iterable of str
            Attributes that must be present.

        Raises
        ------
        SceneError
            (parameter ``input``) a needed field is absent: the input does not come from
            :attr:`SOURCE`.
        """
        specs = field_specs(cls)
        unknown = [n for n in need if n not in specs]
        if unknown:
            raise ValueError(f"{cls.__name__} has no field {', '.join(unknown)}")
        values: dict[str, object] = {}
        bands = _decode(specs["band_names"], fd["band_names"]) if "band_names" in fd else None
        for name, spec in specs.items():
            if not spec.per_band:
                if spec.key in fd:
                    values[name] = _decode(spec, fd[spec.key])
                continue
            if bands is None:
                continue
            keys = spec.keys(bands)
            if all(k in fd for k in keys):
                flat = [_decode(spec, fd[k]) for k in keys]
                arr = np.array(flat, dtype=np.float64 if spec.dtype == "float64" else np.int64)
                values[name] = arr.reshape(len(bands), -1) if "{tally}" in spec.key else arr
        absent = [specs[n].key.replace("{band}", "<band>").replace("{tally}", "<tally>")
                  for n in need if n not in values]
        if absent:
            raise SceneError("input", "field data", f"must come from {cls.SOURCE} (missing {', '.join(absent)})")
        ref = values.get("reference_band")
        if ref is not None and bands is not None and not 0 <= int(ref) < len(bands):
            # a crafted or foreign file: the index picks a band's arrays further down
            raise SceneError("input", f"field data reference_band = {int(ref)}",
                             f"must be a band index in [0, {len(bands) - 1}] (the input's {len(bands)} bands; "
                             f"field data of {cls.SOURCE})")
        return cls(**values)


@dataclass
class LightFieldData(ContractData):
    """The field data of a light field (``nebula-rt render``'s ``.vti``, Nebula Light Field,
    and Nebula Colour, which adds ``exposure``). Arrays over bands are in band order."""

    SOURCE: ClassVar[str] = "Nebula Light Field"

    # -- the bands
    band_names: Optional[tuple] = _field("names", "band names, in band order")
    band_wavelength_nm: Optional[np.ndarray] = _field("float64", "band centres (nm)", array=True)
    band_luminosity: Optional[np.ndarray] = _field("float64", "the stars' total luminosity per band", array=True)
    band_extinction: Optional[np.ndarray] = _field("float64", "extinction relative to the reference band",
                                                   array=True)
    band_albedo: Optional[np.ndarray] = _field("float64", "single-scattering albedo", array=True)
    band_g: Optional[np.ndarray] = _field("float64", "Henyey-Greenstein asymmetry g", array=True)
    reference_band: Optional[int] = _field("int64", "index of the reference band (extinction nearest 1)")
    tau: Optional[float] = _field("float64", "optical depth across one box edge at density 1, reference band")
    # -- the transport, per band
    energy: Optional[np.ndarray] = _field(
        "float64", "energies (n_bands, 4): emitted = absorbed + escaped + terminated bit for bit",
        key="{tally}_{band}")
    packets: Optional[np.ndarray] = _field("int64", "packet counts (n_bands, 4) behind the energies "
                                           "(analog transport)", key="packets_{tally}_{band}", optional=True)
    biasing_energy: Optional[np.ndarray] = _field(
        "float64", "biased transport: energy its roulette and path-length biasing removed (negative: "
        "added), zero in expectation; emitted = absorbed + escaped + terminated + biasing",
        key="biasing_{band}", optional=True)
    absorbed_fraction: Optional[np.ndarray] = _field(
        "float64", "absorbed packets / emitted packets, per band in band order", array=True)
    escaped_fraction: Optional[np.ndarray] = _field(
        "float64", "escaped packets / emitted packets, per band in band order", array=True)
    terminated_fraction: Optional[np.ndarray] = _field(
        "float64", "fraction of packets stopped at transport.max_scatterings", key="terminated_fraction_{band}")
    terminated_bias: Optional[np.ndarray] = _field(
        "float64", "bound on the relative bias of J those packets leave, f / (A + f)", key="terminated_bias_{band}")
    # -- the heavy-tail diagnostic of J (weighted packets with the track-length estimator;
    #    nebula_rt.transport.tails): per band, per class of optical depth from the stars, band-major
    j_tail_classes: Optional[str] = _field("str", "J's depth classes of the j_tail_ arrays, comma-separated",
                                           optional=True)
    j_tail_vov: Optional[np.ndarray] = _field(
        "float64", "variance of the variance of J per band and depth class (n_bands x classes, band-major; "
        "NaN: the class has no cells)", array=True, optional=True)
    j_tail_largest_share: Optional[np.ndarray] = _field(
        "float64", "the largest packet's share of J per band and depth class (as j_tail_vov)", array=True,
        optional=True)
    j_tail_index: Optional[np.ndarray] = _field(
        "float64", "Hill index of the largest packets' contributions to J (as j_tail_vov)", array=True,
        optional=True)
    j_tail_reliable: Optional[np.ndarray] = _field(
        "float64", "1 where J's error passed the heavy-tail checks, 0 where it did not (as j_tail_vov)",
        array=True, optional=True)
    # -- the run
    photons: Optional[int] = _field("int64", "packets traced per band")
    photons_budget: Optional[int] = _field("int64", "packet budget per band (= photons unless error-targeted)")
    achieved_error: Optional[float] = _field("float64", "lit-region relative error reached (NaN: not measured)")
    seed: Optional[int] = _field("uint64", "transport.seed (the scene's [0, 2^53]; files may hold any uint64)")
    batches: Optional[int] = _field("int64", "batches per band (the unit of the error estimate; the "
                                             "packets per band when it was by packets)")
    transport_ranks: Optional[int] = _field("int64", "processes that traced together")
    estimator: Optional[str] = _field("str", "transport.estimator")
    transport_method: Optional[str] = _field("str", "transport.method", optional=True)
    error_estimate: Optional[str] = _field("str", "how the error was estimated: batches or packets "
                                                  "(transport.error_estimate)", optional=True)
    device: Optional[str] = _field("str", "the compute device")
    exposure: Optional[float] = _field("float64", "exposure of rgba (NaN: no colour stage ran)")
    opacity_scale: Optional[float] = _field(
        "float64", "factor on the reference band's optical depth in rgba's alpha (colour.opacity_scale, or "
        "the one 'auto' chose from the data; NaN: no colour stage ran)")
    colour_temperature: Optional[float] = _field("float64", "temperature (K) of the most luminous star "
                                                            "(0: flat or measured spectrum)")
    device_memory_peak_bytes: Optional[int] = _field("int64", "peak device memory of the run (bytes)",
                                                     optional=True)
    scene: Optional[str] = _field("str", "the scene as TOML text; reproduces the run")
    dust_file_sha256: Optional[str] = _field("str", "SHA-256 of the density file the run read", optional=True)


@dataclass
class DensityData(ContractData):
    """The field data of a dust density (Nebula Dust Density): the stars it was made with, so
    that a light field downstream lights it with the same stars (entered once)."""

    SOURCE: ClassVar[str] = "Nebula Dust Density"
    band_names: ClassVar[None] = None  # no field of a density is per band

    stars: Optional[np.ndarray] = _field(
        "float64", "the stars, 6 numbers each: x, y, z (box units), luminosity, temperature (K, 0 = flat "
        "spectrum), bump radius (box units)", array=True)


@dataclass
class SkyImageData(ContractData):
    """The field data of a sky image (Nebula Sky Image)."""

    SOURCE: ClassVar[str] = "Nebula Sky Image"

    band_names: Optional[tuple] = _field("names", "band names, in band order")
    band_luminosity: Optional[np.ndarray] = _field("float64", "the stars' total luminosity per band", array=True)
    view_direction: Optional[np.ndarray] = _field("float64", "unit vector from the observer into the box",
                                                  array=True)
    view_up: Optional[np.ndarray] = _field("float64", "the image's up direction (unit vector)", array=True)
    pixel_size: Optional[float] = _field("float64", "pixel edge (box units)")
    exposure: Optional[float] = _field("float64", "exposure of rgb")
    tau_star: Optional[np.ndarray] = _field("float64", "optical depth from the first star to the observer",
                                            key="tau_star_{band}", optional=True)
    sky_units: Optional[str] = _field("str", "units of the calibrated arrays (\"MJy/sr\"; absent: box units only)",
                                      optional=True)
    wcs_header: Optional[str] = _field("str", "the celestial WCS as FITS header cards (calibrated images)",
                                       optional=True)
    pixel_scale_arcsec: Optional[float] = _field("float64", "pixel side on the sky, arcsec (calibrated images)",
                                                 optional=True)
    psf_fwhm_arcsec: Optional[float] = _field("float64", "FWHM of the Gaussian PSF, arcsec (calibrated images)",
                                              optional=True)
    passband_names: Optional[str] = _field("str", "the passbands of the mag_ arrays, comma-separated "
                                           "(calibrated images)", optional=True)
    mag_system: Optional[str] = _field("str", "magnitude system of the mag_ arrays, AB or Vega (calibrated images)",
                                       optional=True)
    sky_method: Optional[str] = _field("str", "how the scattered light was made: ray-march or peel-off",
                                       optional=True)
    polconv: Optional[str] = _field("str", "the convention of the Q_ and U_ arrays (IAU; absent: unpolarized)",
                                    optional=True)
