"""The scene's tables as declarations: one dataclass per TOML table, one field (a
:class:`~nebula_rt.scene.schema.Param`) per key, with its range, choices, unit and panel group.

The keys are public API (docs/design.md, "Scene file contract"); positions and lengths are in
box units (the box is [0, 1]^3), physical quantities convert to them when the scene is built
(:mod:`nebula_rt.scene.units`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple, Union

from ..errors import SceneError
from ..limits import INT32_MAX, MAX_OFFSET, MAX_PHOTONS, MAX_TREE_DEPTH, PARTICLE_COORDINATE_MAX, TEMPERATURE_RANGE
from ..optics.bands import ALBEDO_RANGE, G_RANGE, PRESETS, Band, resolve_bands
from ..optics import mie
from ..optics.polarization import DEFAULT_PEAK as DEFAULT_PEAK_POLARIZATION, KINDS as POLARIZATION_KINDS
from . import schema, units, values
from .schema import document, param


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
#: magnitude systems of calibrated sky images (their offsets: nebula_rt.scene.units.ab_minus_vega)
MAG_SYSTEMS = ("AB", "Vega", "Vega-Blanton2007")
#: The widest PSF (arcsec): 180 deg, the widest angle on the sky. Wider ones are no blur but a
#: number: 1e308 arcsec spread every star and pixel over 1e305 pixels, an image of zeros.
MAX_PSF_FWHM = 180.0 * 3600.0
#: The smallest error a run can target: the error falls as c / sqrt(packets), c the relative
#: scatter of one packet's tally, of order 1 or more in the lit region (most packets miss most
#: voxels), so the largest budget, MAX_PHOTONS packets per band, reaches about 1 / sqrt(2**53) =
#: 1.05e-8. A smaller target is never reached; 1e-300 overflowed the run's prediction of when it
#: would be, (error / target)^2, after tracing.
MIN_TARGET_ERROR = 1e-8
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


def _known_spectral_type(v: str) -> bool:
    return units.parse_spectral_type(v) is not None


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
        note="int32 on the device",
        doc="Voxels along x, y, z (non-cubic allowed). The grid spans the box [0, 1]^3 whatever its "
            "shape, so voxels need not be cubes; memory and trace time grow with the number of voxels "
            "(the thesis used 128^3)")
    length: Union[float, str] = param(
        1.0, type="float or str", lo=0.0, lo_open=True, label="Box Length", group=G_UNITS, advanced=True,
        convert=values.to_length, check=units.valid_length, allowed=units.length_allowed("a finite length > 0"),
        doc="Physical length of one box edge: a number in `unit`, or a quantity with its own unit "
            "(\"3 pc\", \"2e5 AU\"; astropy.units). The transport works in box units; the length "
            "converts the physical dust keys to dust.tau and scales calibrated sky images")
    unit: str = param("pc", type="str", group=G_UNITS, advanced=True,
                      check=units.is_length_unit, allowed=f"must be a length unit: {units.LENGTH_UNITS_TEXT}",
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
        float32=True,
        doc="\"uniform\": the density everywhere (dimensionless; `tau` is the optical depth across the "
            "box at density 1)")
    file: str = param(
        "", type="str", group=G_DUST,
        doc="\"file\": a .npy array in (x, y, z) order or a .vti image on grid.shape, or an adaptive "
            "density: a hyper tree grid (.htg), an overlapping AMR hierarchy (.vthb), either in a VTKHDF file "
            "(.vtkhdf, .hdf) where the VTK in use reads it, or an SPH particle snapshot (.vtp, deposited on an "
            "octree), traced leaf by leaf (docs/adaptive_grids.md); a "
            "relative path is relative to the scene file's folder")
    array: str = param("density", type="str", group=G_DUST,
                       doc="\"file\" with .vti: the name of the point-data array to read; with .htg, "
                           ".vthb or VTKHDF: the cell-data array")
    particle_mass: str = param(
        "mass", type="str", label="Particle Mass", group=G_DUST, advanced=True,
        doc="\"file\" with a .vtp particle snapshot (SPH: points with per-particle arrays): the point-data "
            "array of the masses; the density is mass per box volume (box edge 1), in the masses' unit")
    particle_smoothing: str = param(
        "smoothing_length", type="str", label="Particle Smoothing", group=G_DUST, advanced=True,
        doc="\"file\" with a .vtp particle snapshot: the point-data array of the smoothing lengths h, in "
            "grid.unit as the positions (the cubic spline kernel reaches r < h; Gadget-2's convention)")
    particle_origin: Vec3 = param(
        (0.0, 0.0, 0.0), type="tuple of 3 float", lo=-PARTICLE_COORDINATE_MAX, hi=PARTICLE_COORDINATE_MAX,
        unit="grid.unit", group=G_DUST, advanced=True,
        doc="\"file\" with a .vtp particle snapshot: the box's low corner in the snapshot's coordinates "
            "(grid.unit); the box is a cube of edge grid.length, and a particle outside it is refused")
    leaf_particles: int = param(
        8, type="int", lo=1, hi=INT32_MAX, label="Leaf Particles", group=G_DUST, advanced=True,
        doc="\"file\" with a .vtp particle snapshot: a cell of the octree the particles are deposited on is "
            "split while it holds more particles than this (down to tree_depth)")
    tree_depth: int = param(
        8, type="int", lo=0, hi=MAX_TREE_DEPTH, label="Tree Depth", group=G_DUST, advanced=True,
        doc="An octree's levels of refinement at most (2^tree_depth cells per box edge where the dust "
            "needs them): a .vtp particle snapshot's, or the procedural density's with `octree`")
    octree: bool = param(
        False, type="bool", group=G_DUST, advanced=True,
        doc="\"turbulence\" or \"uniform\": make the density on an adaptive octree refined where the dust "
            "needs it (`cell_tau`, `cell_tau_spread`, down to `tree_depth`) and trace it leaf by leaf, instead "
            "of on grid.shape; grid.shape stays the light field's output grid (docs/adaptive_grids.md). With a "
            ".vtp particle snapshot: split its cells by the particles' optical depth (`cell_tau`) as well as "
            "by their count")
    cell_tau: float = param(
        0.1, type="float", lo=0.0, lo_open=True, group=G_DUST, advanced=True,
        doc="`octree`: a cell is split while its optical depth across one edge (reference band) exceeds "
            "this (SKIRT's maximum optical depth per cell)")
    cell_tau_spread: float = param(
        0.02, type="float", lo=0.0, group=G_DUST, advanced=True,
        doc="`octree`: a cell is also split while its 8 octants' optical depths across its edge spread "
            "(max - min) by more than this (0: wherever the density varies)")
    scale: float = param(
        0.15, type="float", lo=0.0, group=G_DUST,
        float32=True,
        doc="\"turbulence\": amplitude of the noise (the thesis's densityScale, 0.15)")
    offset: Vec3 = param(
        (0.5, 0.5, 0.5), type="tuple of 3 float", lo=-MAX_OFFSET, hi=MAX_OFFSET, unit="box units", group=G_DUST,
        note="box units; beyond, the float32 turbulence loses its structure: docs/physics.md",
        doc="\"turbulence\": offset into the noise; a different offset gives a different nebula")
    floor: float = param(
        1e-4, type="float", lo=0.0, group=G_DUST, advanced=True,
        float32=True,
        doc="Minimum density everywhere (the thesis's clamp; keeps the medium from being empty)")
    tau: float = param(
        128.0, type="float", lo=0.0, label="Tau", group=G_DUST,
        float32=True,
        doc="Optical depth across one box edge at density 1 in the reference band: the extinction "
            "per box edge is tau x extinction_b x density (the thesis's 128^3 nebula: 128, i.e. "
            "extinction = density per voxel). Set by hydrogen_density, mass_density or "
            "visual_extinction where one of them is given")
    hydrogen_density: Optional[float] = param(
        None, type="float or None", lo=0.0, unit="cm^-3", label="Hydrogen Density", group=G_UNITS, advanced=True,
        what="a number of H nuclei per cm^3", note="finite",
        doc="H nuclei per cm^3 at density 1: sets tau = n_H x C_ext per H in the reference band "
            "(Draine 2003 dust of the band preset) x the box edge (grid.length) in cm")
    mass_density: Optional[float] = param(
        None, type="float or None", lo=0.0, unit="g cm^-3", label="Dust Mass Density", group=G_UNITS,
        advanced=True,
        what="a dust mass density in g cm^-3", note="finite",
        doc="Grams of dust per cm^3 at density 1: sets tau through the dust model's dust mass per "
            "H nucleon (1.870e-26 g for R_V = 3.1, Draine's table) as hydrogen_density does")
    visual_extinction: Optional[float] = param(
        None, type="float or None", lo=0.0, unit="mag", label="Visual Extinction", group=G_UNITS, advanced=True,
        what="an A_V in mag", note="finite",
        doc="A_V across one box edge at density 1: sets tau = A_V / 1.0857 x C_ext(reference band) "
            "/ C_ext(V) of the dust model")


@document
@dataclass
class Star:
    """A point source, one TOML ``[[stars]]`` table."""

    position: Vec3 = param(
        (0.5, 0.5, 0.5), type="tuple of 3 float", lo=0.0, hi=1.0, unit="box units", group=G_STARS,
        what="a list of 3 finite numbers", note="box units",
        doc="Where the star is, inside [0, 1]^3")
    luminosity: float = param(
        1.0, type="float", lo=0.0, lo_open=True, unit="scene units", group=G_STARS,
        float32=True,
        doc="Total luminosity over all bands; set (in L_sun inside the bands' range) by "
            "luminosity_lsun or absolute_magnitude where one is given")
    temperature: Optional[float] = param(
        20000.0, type="float or None", lo=TEMPERATURE_RANGE[0], hi=TEMPERATURE_RANGE[1], unit="K", group=G_STARS,
        note="K; 0 = flat spectrum", off=True,
        doc="Effective temperature: a blackbody spectrum splits the luminosity over the bands and "
            "colours the star (the thesis's star: 20000 K); 0 (None in Python) gives every band an "
            "equal share, a flat spectrum")
    bump_radius: float = param(
        0.01, type="float", lo=0.0, hi=1.0, unit="box units", group=G_STARS,
        hi_open=True, float32=True, note="box units; float32",
        doc="Half-size of the thesis's cubic dust bump around the star (0 = none; the thesis used "
            "0.01); used where the density is made, not by the light field of a given density")
    spectrum: Optional[Tuple[Tuple[float, float], ...]] = param(
        None, type="tuple of (wavelength nm, relative power) pairs, or None", group=G_STARS,
        convert=values.to_spectrum, check=values.valid_spectrum,
        allowed="must be a list of at least 2 [wavelength nm, relative power] pairs, wavelengths "
                "increasing in (0, 1e5], powers finite, >= 0 and not all 0 (or omitted)",
        doc="A measured spectrum (at least 2 pairs, wavelengths increasing): it replaces the "
            "blackbody of `temperature` for the split over the bands and for the colour")
    luminosity_lsun: Optional[float] = param(
        None, type="float or None", lo=0.0, lo_open=True, unit="L_sun", group=G_STARS,
        what="a bolometric luminosity in L_sun",
        doc="Bolometric luminosity in nominal solar luminosities (3.828e26 W): sets `luminosity` "
            "to the part of the blackbody of `temperature` inside the bands' range, in L_sun")
    absolute_magnitude: Optional[float] = param(
        None, type="float or None", unit="mag", group=G_STARS,
        what="an absolute magnitude M_V in mag", note="AB, Bessell V; finite",
        doc="Absolute magnitude M_V (AB, Bessell V): sets `luminosity` as luminosity_lsun does, "
            "from the blackbody of `temperature` with that magnitude at 10 pc")
    spectral_type: Optional[str] = param(
        None, type="str or None", group=G_STARS,
        check=_known_spectral_type, allowed="must be " + units.SPECTRAL_TYPE_FORM + " (or omitted)",
        doc="MK spectral type and luminosity class (\"B2V\", \"B2.5 IV\", \"K0III\"; O1-M10): sets "
            "`temperature` by `spectral_calibration`")
    spectral_calibration: str = param(
        "auto", type="str", choices=units.SPECTRAL_CALIBRATIONS, group=G_STARS,
        doc="How `spectral_type` sets `temperature`: pecaut-mamajek-2013 (the mean dwarf sequence of "
            "Pecaut & Mamajek 2013, ApJS 208, 9: class V, O3V-M9.5V), de-jager-1987 (de Jager & "
            "Nieuwenhuijzen 1987, A&A 177, 217: every class, O1-M10), or auto (the first for a dwarf "
            "inside its range, else the second)")

    def spectral_source(self):
        """What sets the star's spectrum: the measured pairs, else the temperature (K), else
        None (flat); see :func:`nebula_rt.optics.colour_convert.star_spectrum`."""
        return self.spectrum if self.spectrum else (self.temperature or None)


@document
@dataclass
class BandsConfig:
    """Band selection, TOML table ``[bands]``."""

    preset: Optional[str] = param(
        "thesis-rgb", type="str or None", choices=tuple(sorted(PRESETS)), label="Band Preset", group=G_OPTICS,
        doc="The wavelength bands traced, a preset of nebula_rt.optics.bands.PRESETS (thesis-rgb: R 677, "
            "G 550, B 439 nm with the thesis's extinction factors 0.748 / 1 / 1.324); None whenever "
            "`list` is given")
    albedo: Optional[float] = param(
        None, type="float or None", lo=ALBEDO_RANGE[0], hi=ALBEDO_RANGE[1], group=G_OPTICS,
        doc="If given, the single-scattering albedo of the dust in every band (else each band's own)")
    g: Optional[float] = param(
        None, type="float or None", lo=G_RANGE[0], hi=G_RANGE[1], label="G", group=G_OPTICS,
        doc="If given, the Henyey-Greenstein asymmetry parameter of every band (else each band's own)")
    polarization: str = param(
        "none", type="str", choices=POLARIZATION_KINDS, group=G_OPTICS,
        doc="Polarized scattering: none (intensity alone), rayleigh (dipole scattering: phase "
            "function 3 (1 + cos^2) / (16 pi), polarization sin^2 / (1 + cos^2) of the scattering "
            "angle; the bands' g plays no part), white (each band's Henyey-Greenstein phase function "
            "with White's 1979 approximation of the linear polarization, peak_polarization at 90 "
            "degrees), mie (spherical grains, grain_*: their Mie matrix per band, and the bands' "
            "albedo, g and extinction are the grains') or matrix (a tabulated matrix, grain_matrix). "
            "Packets then carry Stokes I, Q, U (and V: mie, matrix), and peel-off images gain Q and U "
            "(and V) (docs/physics.md)")
    peak_polarization: Union[float, Tuple[float, ...]] = param(
        DEFAULT_PEAK_POLARIZATION, type="float or list of float", lo=0.0, hi=1.0, label="Peak Polarization",
        group=G_OPTICS, advanced=True,
        doc="polarization = \"white\": the linear polarization of unpolarized light scattered through "
            "90 degrees (White's p_l), one number for every band or a list of one per band")
    grain_material: str = param(
        "astronomical-silicate", type="str", choices=tuple(mie.MATERIALS), label="Grain Material", group=G_OPTICS,
        advanced=True,
        doc="polarization = \"mie\": the grains' material, whose optical constants give the refractive "
            "index at each band's wavelength (astronomical-silicate: Draine 2003); unused where "
            "grain_n and grain_k are given")
    grain_n: Optional[Union[float, Tuple[float, ...]]] = param(
        None, type="float or list of float or None", lo=mie.N_RANGE[0], hi=mie.N_RANGE[1], label="Grain N",
        group=G_OPTICS, advanced=True,
        doc="polarization = \"mie\": the real part n of the grains' refractive index n + i k, one number "
            "or one per band (with grain_k; else the material's)")
    grain_k: Optional[Union[float, Tuple[float, ...]]] = param(
        None, type="float or list of float or None", lo=mie.K_RANGE[0], hi=mie.K_RANGE[1], label="Grain K",
        group=G_OPTICS, advanced=True,
        doc="polarization = \"mie\": the imaginary part k of the grains' refractive index (>= 0: "
            "absorbing), one number or one per band (with grain_n)")
    grain_radius_min: float = param(
        mie.DEFAULT_RADIUS_MIN_UM, type="float", lo=mie.RADIUS_RANGE_UM[0], hi=mie.RADIUS_RANGE_UM[1],
        unit="micron", label="Grain Radius Min", group=G_OPTICS, advanced=True,
        doc="polarization = \"mie\": the smallest grain radius (Mathis, Rumpl & Nordsieck 1977: 0.005)")
    grain_radius_max: float = param(
        mie.DEFAULT_RADIUS_MAX_UM, type="float", lo=mie.RADIUS_RANGE_UM[0], hi=mie.RADIUS_RANGE_UM[1],
        unit="micron", label="Grain Radius Max", group=G_OPTICS, advanced=True,
        doc="polarization = \"mie\": the largest grain radius (MRN: 0.25); equal to grain_radius_min "
            "for grains of one size")
    grain_size_slope: float = param(
        mie.DEFAULT_SIZE_SLOPE, type="float", lo=mie.SIZE_SLOPE_RANGE[0], hi=mie.SIZE_SLOPE_RANGE[1],
        label="Grain Size Slope", group=G_OPTICS, advanced=True,
        doc="polarization = \"mie\": q of the size distribution n(a) ~ a^-q between the radii (MRN: 3.5)")
    grain_matrix: str = param(
        "", type="str", label="Grain Matrix", group=G_OPTICS, advanced=True,
        doc="polarization = \"matrix\": a text table of the dust's scattering matrix, rows 'theta S11 "
            "S12 S33 S34' (theta in degrees from 0 to 180; Bohren & Huffman's signs), used in every band: "
            "its phase function gives g, the bands give albedo and extinction "
            "(nebula_rt.optics.mueller_table); a relative path is relative to the scene file's folder")
    list: Optional[List[Dict[str, Any]]] = param(
        None, type="list of dict or None", group=G_OPTICS,
        doc="Explicit bands, [[bands.list]] tables with keys name, wavelength (nm), extinction "
            "(relative to the reference band), albedo and g (polarization = \"mie\": name and wavelength "
            "alone, the grains giving the rest, the band nearest 550 nm the reference; \"matrix\": no g, "
            "the table's)")

    def __post_init__(self) -> None:
        if self.list is not None:
            self.preset = None
        # the folder a relative grain_matrix is read from (the scene's base_dir; Scene sets it)
        self._base_dir = None

    def grain_matrix_path(self) -> Path:
        """``grain_matrix`` as a path, resolved against the scene file's folder if relative."""
        if not self.grain_matrix:
            from ..optics.mueller_table import MATRIX_FILE

            raise SceneError("bands.grain_matrix", self.grain_matrix,
                             f"must name {MATRIX_FILE} (the dust's scattering matrix) with bands.polarization = 'matrix'")
        return values.scene_relative_path(self.grain_matrix, self._base_dir)

    def mueller_table(self):
        """The :class:`~nebula_rt.optics.mueller_table.MuellerTable` of ``grain_matrix``
        (``polarization = "matrix"``), read from the file at each call (its kernel table is
        made once per content)."""
        from ..optics.mueller_table import read_matrix

        return read_matrix(self.grain_matrix_path())

    def resolve(self) -> List[Band]:
        """Return the validated bands (see :func:`nebula_rt.optics.bands.resolve_bands`); with
        ``polarization = "mie"`` their albedo, g and extinction are the grains'
        (:func:`nebula_rt.optics.mie.mie_bands`), with ``"matrix"`` their g the table's."""
        grains = self.polarization == "mie"
        if self.polarization == "matrix":
            return resolve_bands(self.preset, self.list, self.albedo, None, phase_g=self.mueller_table().g)
        bands = resolve_bands(self.preset, self.list, self.albedo, self.g, grain_optics=grains and self.list is not None)
        if grains:
            from ..optics.polarization import grains_of

            ref = None  # a preset's own reference band; explicit bands': the one nearest 550 nm
            if self.list is not None:
                ref = min(range(len(bands)), key=lambda i: abs(bands[i].wavelength - mie.REFERENCE_WAVELENGTH_NM))
            return mie.mie_bands(bands, grains_of(self), reference=ref)
        return bands


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
        "auto", type="str", choices=METHODS, group=G_TRANSPORT,
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
        0.02, type="float", lo=0.0, lo_open=True, hi=math.sqrt(3.0), unit="box units", label="Filter Radius",
        group=G_TRANSPORT, note="box units; at most the box's diagonal",
        doc="Radius of the collision filter (collision-filter only); at most the box's diagonal, sqrt(3): "
            "a wider filter reaches the whole box from every voxel")
    max_scatterings: int = param(
        1000, type="int", lo=0, hi=INT32_MAX, label="Max Scatterings", group=G_TRANSPORT, advanced=True,
        note="int32 on the device",
        doc="A packet is terminated (and tallied as such) after this many scatterings")
    seed: int = param(
        1, type="int", lo=0, hi=MAX_SEED, group=G_TRANSPORT, advanced=True,
        note="exact as a double: ParaView's panel, pvpython",
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
        note="0 = automatic",
        doc="Packets per band in one batch, the unit of the Monte Carlo error estimate (0 = automatic: "
            "at least 16 batches); progress and cancelling happen between kernel launches")
    target_error: float = param(
        0.0, type="float", lo=MIN_TARGET_ERROR, hi=1.0, label="Target Error", group=G_QUALITY,
        hi_open=True, off=True,
        doc=f"0: trace `photons` packets. In [{MIN_TARGET_ERROR:g}, 1): trace until the relative error in the "
            "lit region (RMS over the lit voxels, 1 sigma) is at most this, `photons` being the budget (a "
            "smaller target is beyond any budget: about 1 / sqrt(2**53))")
    time_limit: float = param(
        0.0, type="float", lo=0.0, unit="s", label="Time Limit", group=G_QUALITY, advanced=True,
        note="seconds; 0 = none",
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
        float32=True, note="the colours are float32",
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
        note="the asinh softening Q",
        doc="The asinh stretch's softening Q: how far the faint light is lifted (about Q / asinh(Q) "
            "times the linear exposure)")


@document
@dataclass
class Observer:
    """Where the scene lies on the sky, for calibrated sky images, TOML table ``[observer]``."""

    distance: Optional[Union[float, str]] = param(
        None, type="float or str or None", lo=0.0, lo_open=True, unit="pc", group=G_OBSERVER,
        convert=values.to_opt_length, check=units.valid_distance,
        allowed=units.length_allowed("a distance > 0", "pc") + " (or omitted)",
        doc="Distance from the observer to the box centre: a quantity (\"140 pc\") or a number in "
            "pc; sets the image's angular scale and the stars' flux")
    ra: float = param(0.0, type="float", lo=0.0, hi=360.0, hi_open=True, unit="deg", label="RA", group=G_OBSERVER,
                      what="a right ascension in degrees",
                      doc="Right ascension (ICRS) of the box centre, the sky image's reference point")
    dec: float = param(0.0, type="float", lo=-90.0, hi=90.0, unit="deg", label="Dec", group=G_OBSERVER,
                       what="a declination in degrees",
                       doc="Declination (ICRS) of the box centre")
    position_angle: float = param(
        0.0, type="float", lo=-360.0, hi=360.0, unit="deg", label="Position Angle", group=G_OBSERVER,
        what="an angle in degrees", note="east of north",
        doc="Position angle of the image's up axis, from north through east (0: up is north and "
            "east is left)")
    psf_fwhm: float = param(
        0.0, type="float", lo=0.0, hi=MAX_PSF_FWHM, unit="arcsec", label="PSF FWHM", group=G_OBSERVER,
        what="a FWHM in arcsec", note="180 deg at most, no angle on the sky is wider; 0 = no PSF",
        doc="FWHM of the Gaussian point-spread function the calibrated image is convolved with "
            "(0: none; a star then fills the pixel it falls in)")
    magnitude_system: str = param(
        "AB", type="str", choices=MAG_SYSTEMS, label="Magnitude System", group=G_OBSERVER,
        doc="Zero point of the calibrated images' magnitudes: AB (3631 Jy); Vega (0 mag for Vega: AB "
            "minus Vega's AB magnitude through the passband, from its CALSPEC spectrum alpha_lyr_stis_011, "
            "Bohlin et al. 2020, AJ 160, 21); or Vega-Blanton2007 (AB minus the offsets of Blanton & Roweis "
            "2007, AJ 133, 734, Table 1, which differ by up to 0.03 mag)")


#: The scene file's tables with their dataclasses, in the file's order: the schema
#: (:mod:`nebula_rt.scene.schema`). A star's keys are ``stars.<field>`` (the same for every star).
SECTIONS = (("grid", Grid), ("dust", Dust), ("stars", Star), ("bands", BandsConfig), ("transport", Transport),
            ("colour", Colour), ("observer", Observer))


#: the scene keys' lookups: parameters() (key, declaration, default) in the file's order,
#: declaration(key), default(key)
parameters, declaration, default = (getattr(schema.Declarations(SECTIONS), n)
                                    for n in ("parameters", "declaration", "default"))
