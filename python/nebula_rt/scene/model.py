"""The scene: one TOML scene file, parsed, checked and converted to box units (see
:mod:`nebula_rt.scene.sections` for the tables and their keys). Never imports VTK."""

from __future__ import annotations

import copy
import math
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union


from .. import limits
from ..errors import SceneError
from ..input_files import MAX_SCENE_BYTES, read_input_text
from . import units, values
from .sections import BandsConfig, Colour, Dust, Grid, Observer, Star, Transport
from .rules import BANDS_RULES, BAND_ENTRY_RULES, COLOUR_RULES, DUST_RULES, GRID_RULES, OBSERVER_RULES, STAR_RULES, TRANSPORT_RULES, _SCHEMA, _TABLE_NAMES, _check_dataclass, _check_star_spectra, _parse_array, _parse_table
from .overrides import _NUMERIC_ARRAY, _apply_override, _drop_derived, _parse_toml, _parse_value


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

    def __setattr__(self, name, value):
        super().__setattr__(name, value)
        # bands.grain_matrix, like dust.file, is relative to the scene file's folder
        if name in ("base_dir", "bands") and isinstance(getattr(self, "bands", None), BandsConfig):
            self.bands._base_dir = getattr(self, "base_dir", None)

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
        for s in stars:  # a temperature of 0 is the flat spectrum, None in Python
            if s.temperature == 0:
                s.temperature = None

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
        # a regular file of at most MAX_SCENE_BYTES (a FIFO or /dev/zero would never end the
        # read), UTF-8 with or without a byte-order mark
        text = read_input_text("scene file", path, "an existing UTF-8 TOML file", MAX_SCENE_BYTES)
        return cls.from_dict(_parse_toml(text, str(path)), base_dir=path.absolute().parent)

    # -- serialisation ------------------------------------------------------

    def to_dict(self) -> Dict[str, Any]:
        """The scene as a TOML-shaped dict (None values omitted but a star's temperature, 0 for
        a flat spectrum; tuples as lists)."""

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
            # a flat spectrum is written as temperature 0: omitted, it would read as the default
            "stars": [dict(table(s), **({"temperature": 0.0} if s.temperature is None else {})) for s in self.stars],
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
            raise SceneError("dust.file", self.dust.file, "must name a .npy, .vti, .htg, .vthb or .vtp file")
        return values.scene_relative_path(self.dust.file, self.base_dir)

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
                    "dust.file", self.dust.file, "must name a .npy, .vti, .htg, .vthb or .vtp file when dust.model = 'file'"
                )
            if self.dust.file.lower().endswith((".vti", ".htg", ".vthb")) and not self.dust.array:
                raise SceneError(
                    "dust.array", self.dust.array, "must name the density array of the .vti, .htg or .vthb file"
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
        self._check_polarization(bands)
        self._apply_units()
        _check_dataclass("transport", self.transport, TRANSPORT_RULES)
        _check_dataclass("colour", self.colour, COLOUR_RULES)
        if not isinstance(self.observer, Observer):
            raise SceneError("observer", self.observer, "must be an Observer")
        _check_dataclass("observer", self.observer, OBSERVER_RULES)
        self._check_batches()
        _check_star_spectra(self.stars, bands)

    def _check_polarization(self, bands) -> None:
        """bands.peak_polarization holds one value per band where it is a list; a scene that
        scatters by its own phase function (Rayleigh's, Mie's, a table's) gives no bands.g, nor
        bands.albedo where the grains give it; bands.grain_matrix only with 'matrix'; the grains'
        keys are given only for Mie scattering, whose
        grains convert dust.mass_density (with a material's bulk density) and
        dust.visual_extinction, not dust.hydrogen_density (they give no dust-to-gas ratio)."""
        from ..optics import mie
        from ..optics.polarization import DEFAULT_PEAK, OWN_OPTICS, OWN_PHASE_FUNCTION, polarization_of

        pol = polarization_of(self)
        pol.peaks(len(bands))
        if pol.kind != "white" and self.bands.peak_polarization != DEFAULT_PEAK:
            raise SceneError("bands.peak_polarization", self.bands.peak_polarization, "is used only with "
                             f"bands.polarization = 'white' (here '{pol.kind}'): omit it")
        if pol.kind in OWN_PHASE_FUNCTION and self.bands.g is not None:
            raise SceneError("bands.g", self.bands.g, f"must be omitted with bands.polarization = '{pol.kind}' "
                             "(that phase function has no asymmetry parameter)")
        if pol.kind in OWN_OPTICS:
            if self.bands.albedo is not None:
                raise SceneError("bands.albedo", self.bands.albedo, f"must be omitted with bands.polarization = "
                                 f"'{pol.kind}' (the grains' albedo is Mie theory's)")
            key = units.physical_dust_key(self.dust)
            if key == "hydrogen_density":
                raise SceneError("dust.hydrogen_density", self.dust.hydrogen_density, "is not taken with Mie grains "
                                 "(they give no dust-to-gas ratio): give dust.mass_density, dust.visual_extinction "
                                 "or dust.tau")
            if key == "mass_density" and self.bands.grain_n is not None:
                raise SceneError("dust.mass_density", self.dust.mass_density, "needs the grains' bulk density, which "
                                 "bands.grain_material gives and bands.grain_n / grain_k do not: give "
                                 "dust.visual_extinction or dust.tau")
            pol.grains.refractive_index([b.wavelength for b in bands])  # one value per band
            return
        if pol.kind != "matrix" and self.bands.grain_matrix:
            raise SceneError("bands.grain_matrix", self.bands.grain_matrix, "is used only with bands.polarization = "
                             f"'matrix' (here '{pol.kind}'): omit it")
        defaults = mie.Grains()
        for key, default in (("material", defaults.material), ("n", None), ("k", None),
                             ("radius_min", defaults.radius_min), ("radius_max", defaults.radius_max),
                             ("size_slope", defaults.size_slope)):
            value = getattr(self.bands, f"grain_{key}")
            if value != default:
                raise SceneError(f"bands.grain_{key}", value, "is used only with bands.polarization = 'mie' "
                                 f"(here '{pol.kind}'): omit it")

    def _apply_units(self, given_tau: Optional[float] = None, given_luminosity: Optional[Mapping[int, float]] = None,
                     given_temperature: Optional[Mapping[int, float]] = None) -> None:
        """Set ``dust.tau``, the stars' ``temperature`` and ``luminosity`` from the physical keys
        that are given (:mod:`nebula_rt.scene.units`); ``given_*``: the values the scene table gave for
        them too, which must then be the converted ones (bit for bit: a scene written by
        :meth:`to_toml` holds both)."""
        for i, s in enumerate(self.stars):
            if s.spectral_type is None:
                continue
            calibration = units.spectral_calibration_of(s.spectral_type, s.spectral_calibration)
            try:
                temperature = units.temperature_from_spectral_type(s.spectral_type, calibration)
            except ValueError as exc:
                raise SceneError(f"stars[{i}].spectral_type", s.spectral_type,
                                 f"is not a type of stars[{i}].spectral_calibration = {calibration!r} ({exc}); "
                                 "'de-jager-1987' holds every luminosity class") from None
            if given_temperature and i in given_temperature and given_temperature[i] != temperature:
                raise SceneError(f"stars[{i}].temperature", given_temperature[i],
                                 f"is set by stars[{i}].spectral_type = {s.spectral_type!r}, which gives "
                                 f"{temperature!r} K ({calibration}): give one of them")
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
                allowed = STAR_RULES["luminosity"].allowed
                if k == "absolute_magnitude":  # the range in the key's own unit
                    m_lo, m_hi = units.absolute_magnitude_range(
                        s.temperature, bands, (limits.FLOAT32_TINY, limits.FLOAT32_MAX))  # stars.luminosity: float32
                    allowed += f": M_V in [{m_lo:.6g}, {m_hi:.6g}] for {s.temperature:g} K and these bands"
                raise SceneError(f"stars[{i}].{k}", getattr(s, k),
                                 f"gives a luminosity of {lum:.6g} L_sun inside the bands (bolometric {lbol:.6g} "
                                 f"L_sun), which " + allowed)
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
