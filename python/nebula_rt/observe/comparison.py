"""A run held against the user's observations: residuals and chi^2 with both errors.

:func:`trace_rings` traces a scene with a peel-off image centred on its most luminous star and
sums the scattered light, per band and per batch, over rings of projected offset: the union of
every annulus edge of the tables, so that each table's annulus is a sum of whole rings and all
tables share one trace. :func:`model_values` turns the ring sums into each table's statistic
(Delta(B-V) of an annulus; the nebula/star ratio at a wavelength, interpolated between band
centres with the hat functions of the colour conversion) and its Monte Carlo error: each
statistic is linearised in the ring sums and the batch-means standard error taken of that
linear combination's batch values (as :mod:`nebula_rt.observe` does).

chi^2 = sum_i (d_i - m_i)^2 / (sigma_d,i^2 + sigma_m,i^2). The observation's noise and the
run's Monte Carlo noise are independent of each other (the photons of the telescope know
nothing of the packets' random numbers), so the variance of d - m is the sum of the two
variances: the errors add in quadrature. Without the run's own error a short run would be held
to the data's errors alone, and its noise read as a misfit. The model errors of different rows
are correlated (one packet peels off into many rings and every band); chi^2 uses the diagonal,
the usual approximation, which is exact when the model error is small beside the data's, as it
should be in a fit (:func:`nebula_rt.observe.fit.fit_observations` reports the ratio).
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from ..optics.colour_convert import hat_basis
from ..density.generate import scene_density
from ..errors import SceneError
from ..scene import units
from .colours import (
    REFERENCE_LABELS, _check_reference, _labels, _offsets, passband_weights, star_reddening)
from .observed_tables import ObservedTable, finite_or_none
from ..pipeline.outputs import Publication
from ..pipeline.rgba import _dominant_source
from .sky import Camera
from ..scene.sky_schema import COMPARISON_SIZE
from ..transport.estimate import batch_standard_error
from ..transport.line_of_sight import density_column
from ..transport.request import TransportRequest, scene_backend

#: Sky image pixels per side of the comparison's peel-off image (over 2 x the largest offset).
DEFAULT_SIZE = COMPARISON_SIZE


@dataclass
class RingSums:
    """Scattered light in rings of projected offset about the star, per band and batch.

    Attributes
    ----------
    edges : ndarray (n_rings + 1,)
        Ring edges, box units.
    sums : ndarray (n_bands, n_rings)
        Summed peel-off intensity of the pixels of each ring (luminosity per box-unit area per sr).
    batches : ndarray (M, n_bands, n_rings)
        The same per batch (they add up to ``sums``).
    band_luminosity : ndarray (n_bands,)
        Stars' luminosity per band.
    wavelength_nm : ndarray (n_bands,)
    pixel_area : float
        Area of one pixel, box units^2.
    star_tau : ndarray (n_bands,)
        Optical depth from the star to the box's edge towards the observer.
    source : object
        The star's spectrum (temperature, pairs or None) for the passband weights.
    photons : int
        Packets per band.
    rv : str
        R_V of the dust's extinction law (Draine 2003), for the star's transmission beyond the
        bands (:func:`nebula_rt.observe.colours.star_transmission`).
    pixels : ndarray (n_rings,) or None
        Pixels of each ring whose central ray crosses the box (:func:`ring_pixels`): a ring
        without any holds no light of the model but what pixelisation carries in. None: not
        counted (ring sums made elsewhere).
    tangential, tangential_batches : ndarray (n_bands, n_rings), (M, n_bands, n_rings) or None
        A polarized scene's (``trace_rings(stokes=True)``): the tangential Stokes
        Q cos 2psi + U sin 2psi of the ring's pixels summed (psi each pixel's position angle
        about the star in the image's frame), in the units of ``sums``, and per batch.
    """

    edges: np.ndarray
    sums: np.ndarray
    batches: np.ndarray
    band_luminosity: np.ndarray
    wavelength_nm: np.ndarray
    pixel_area: float
    star_tau: np.ndarray
    source: object
    photons: int = 0
    pixels: Optional[np.ndarray] = None
    rv: str = units.DEFAULT_RV
    tangential: Optional[np.ndarray] = None
    tangential_batches: Optional[np.ndarray] = None


def ring_edges(tables: Sequence[ObservedTable]) -> np.ndarray:
    """Sorted distinct annulus edges of all tables (box units), rounded to 1e-12 so that one edge
    computed two ways (0.1 and (0.05 + 0.15) / 2) is one edge, not a ring of no width. Python's
    round, as :func:`_rings_of` rounds an annulus's edges: the same edge either way, and no
    overflow (numpy's rounding multiplies by 1e12, which made an edge of 1e308 infinite)."""
    e = np.concatenate([np.concatenate([t.lo, t.hi]) for t in tables])
    return np.unique(np.array([round(float(x), 12) for x in e], np.float64))


def box_reach(star_position, direction) -> float:
    """How far the box reaches from the star on the sky (box units): the largest distance of
    its projection, seen along ``direction``, from the star's. The projection of the box is
    the convex hull of its corners', so the farthest point is a corner; the scattered light of
    the model lies within this distance of the star, and an annulus beyond it compares
    nothing."""
    d = np.asarray(direction, np.float64) / math.hypot(*direction)
    rel = np.array(list(itertools.product((0.0, 1.0), repeat=3))) - np.asarray(star_position, np.float64)
    return float(np.linalg.norm(rel - (rel @ d)[:, None] * d, axis=1).max())


def _camera(star_position, direction, size, edges):
    # the outermost ring whole inside the image, but no farther than the box reaches: pixels
    # beyond it hold no light, and an annulus out to 1e308 would make the pixels as large
    # (or the field infinite)
    outer = min(float(edges[-1]), box_reach(star_position, direction))
    return Camera(direction=tuple(direction), size=(size, size), extent=2.0 * outer * 1.02,
                  center=tuple(star_position))


def _on_box(cam) -> np.ndarray:
    """(W, H) True for the pixels whose central ray (along the camera's direction) crosses the
    box [0, 1]^3: the slab test, axis by axis."""
    d, u, v = cam.basis()
    w, h = cam.size
    P, Q = np.meshgrid(np.arange(w), np.arange(h), indexing="ij")
    c = cam.origin()[None, None, :] + cam.pixel_size * (P[..., None] * u + Q[..., None] * v)
    t_lo, t_hi = np.full((w, h), -np.inf), np.full((w, h), np.inf)
    inside = np.ones((w, h), bool)
    for a in range(3):
        if d[a] == 0.0:
            inside &= (c[..., a] >= 0.0) & (c[..., a] <= 1.0)
        else:
            t0, t1 = -c[..., a] / d[a], (1.0 - c[..., a]) / d[a]
            t_lo, t_hi = np.maximum(t_lo, np.minimum(t0, t1)), np.minimum(t_hi, np.maximum(t0, t1))
    return inside & (t_lo <= t_hi)


def ring_pixels(star_position, direction, size, edges):
    """The comparison's camera for ``edges`` (box units) about the star, each pixel's ring
    (-1: none) and the pixels per ring whose central ray crosses the box (n_rings,); the
    arrays are read-only (kept for the next call with the same arguments: a fit's trials
    share them while the star's depth is not free, and they took 3 ms of a 40 ms trial)."""
    return _ring_pixels(tuple(float(x) for x in star_position), tuple(float(x) for x in direction), int(size),
                        tuple(float(x) for x in np.asarray(edges, np.float64)))


@functools.lru_cache(maxsize=8)
def _ring_pixels(star_position, direction, size, edges):
    e = np.asarray(edges, np.float64)
    cam = _camera(star_position, direction, size, e)
    _, u, v = cam.basis()
    labels = _labels(_offsets(cam.origin(), cam.pixel_size, u, v, cam.size, star_position, direction), e)
    seen = labels[(labels >= 0) & _on_box(cam)]
    pixels = np.bincount(seen, minlength=len(e) - 1)[:len(e) - 1]
    labels.flags.writeable = pixels.flags.writeable = False
    return cam, labels, pixels


def _position_angles(cam, star_position) -> np.ndarray:
    """(W, H) position angle psi of every pixel centre about the star's projection, from the
    image's u axis towards its v axis (radians): the frame in which a pattern tangential about
    the star has Q = P I cos 2psi, U = P I sin 2psi."""
    _, u, v = cam.basis()
    w, h = cam.size
    P, Q = np.meshgrid(np.arange(w), np.arange(h), indexing="ij")
    rel = cam.origin()[None, None, :] + cam.pixel_size * (P[..., None] * u + Q[..., None] * v) \
        - np.asarray(star_position, np.float64)
    return np.arctan2(rel @ v, rel @ u)


def trace_rings(scene, edges, *, direction=(0.0, 0.0, -1.0), size: int = DEFAULT_SIZE, backend=None,
                progress=None, cancel=None, density=None, comm=None, stokes: bool = False) -> RingSums:
    """Trace ``scene`` with a peel-off image along ``direction`` centred on its most luminous
    star and sum it over the rings between consecutive ``edges`` (box units).

    ``density`` (nx, ny, nz) skips making the density (a fit reuses it while no dust key
    changes). The scene's error target and time limit apply (a fit refuses both: its trials
    trace a fixed number of packets with one seed). ``comm``: the ranks that share the trace
    (:mod:`nebula_rt.backends.parallel`); every rank gets the same sums. ``stokes``: also the
    rings' tangential Stokes (a polarized scene: ``RingSums.tangential``), from every pixel's
    batch sums (each pixel its own group), so that each pixel's Q and U turn by its own angle.
    """

    backend = backend or scene_backend(scene)
    bands = scene.bands.resolve()
    wl = np.array([b.wavelength for b in bands])
    star = max(scene.stars, key=lambda s: s.luminosity)
    e = np.asarray(edges, np.float64)
    cam, labels, pixels = ring_pixels(star.position, direction, size, e)
    rho = scene_density(scene, backend) if density is None else density  # a grid or an octree
    # only the peel-off image's ring sums are used: no J
    if stokes and scene.bands.polarization == "none":
        raise SceneError("bands.polarization", "none", "must be 'rayleigh' or 'white' to compare the degree of "
                                                       "polarization (the scene traces intensity alone)")
    nr = len(e) - 1
    bins = labels if not stokes else np.arange(labels.size, dtype=np.int64).reshape(labels.shape)
    res = TransportRequest.from_scene(scene, peel=cam, peel_bins=bins, light_field=False).trace(
        rho, backend, progress=progress, cancel=cancel, comm=comm)
    tau_star = np.array([scene.dust.tau * b.extinction for b in bands]) * density_column(
        rho, star.position, -np.asarray(direction, float))
    xb = np.asarray(res.peel_bin_batches, np.float64)
    tb = None
    if stokes:  # every pixel's batch sums: the rings' intensity, and their tangential Stokes
        flat = labels.reshape(-1)
        ring = np.zeros((flat.size, nr))
        ring[np.flatnonzero(flat >= 0), flat[flat >= 0]] = 1.0
        psi = _position_angles(cam, star.position).reshape(-1)
        qu = np.asarray(res.peel_stokes_bin_batches, np.float64)  # (M, n_bands, 2, pixels)
        xb = xb[..., :flat.size] @ ring
        tb = (qu[:, :, 0, :flat.size] * np.cos(2 * psi) + qu[:, :, 1, :flat.size] * np.sin(2 * psi)) @ ring
    if xb.shape[2] < nr:  # the outermost rings hold no pixel centre (finer than a pixel)
        xb = np.concatenate([xb, np.zeros(xb.shape[:2] + (nr - xb.shape[2],))], axis=2)
    return RingSums(edges=e, sums=xb.sum(axis=0), batches=xb, band_luminosity=np.asarray(res.band_luminosity,
                    np.float64), wavelength_nm=wl, pixel_area=cam.pixel_size ** 2, star_tau=tau_star,
                    source=_dominant_source(scene.stars), photons=int(res.photons), pixels=pixels,
                    rv=units.dust_model(scene.bands)[0], tangential=None if tb is None else tb.sum(axis=0),
                    tangential_batches=tb)


def _rings_of(edges, lo, hi) -> np.ndarray:
    """(n_rings,) 0/1 weights of the rings that make up the annulus [lo, hi)."""
    i0 = int(np.searchsorted(edges, round(float(lo), 12)))
    i1 = int(np.searchsorted(edges, round(float(hi), 12)))
    w = np.zeros(len(edges) - 1)
    w[i0:i1] = 1.0
    return w


def _batch_error(y) -> np.ndarray:
    """Batch-means standard error of the total of per-batch values y (M, ...)."""

    m = y.shape[0]
    mean = y.mean(axis=0)
    return batch_standard_error(y.sum(axis=0), ((y - mean) ** 2).sum(axis=0), m)


def model_values(rings: RingSums, table: ObservedTable, reference: str = "observed"):
    """The model's value of every row of ``table`` and its Monte Carlo error (1 sigma).

    Colour rows: Delta(B-V) of the annulus against ``reference`` (the star as seen through the
    dust in front of it, or its intrinsic light). Polarization rows: the tangential degree of
    polarization of the annulus's light, sum T / sum I at the row's wavelength (linear between
    band centres; ``reference`` plays no part). Ratio rows: nebula flux in the annulus over
    the star's flux (as seen, or intrinsic), at the row's wavelength: sum over the annulus of
    the intensity times the pixel area (luminosity per sr towards the observer) over the
    star's L_b exp(-tau_b) / (4 pi), linear between band centres. Returns (model, error).
    """
    _check_reference(reference)
    wl = rings.wavelength_nm
    L = rings.band_luminosity
    W = np.stack([_rings_of(rings.edges, lo, hi) for lo, hi in zip(table.lo, table.hi)])  # (n, n_rings)
    S = rings.sums @ W.T  # (n_bands, n)
    X = np.einsum("mbr,nr->mbn", rings.batches, W)  # (M, n_bands, n)
    if table.kind == "colour":
        wb = passband_weights(wl, rings.source, "B")
        wv = passband_weights(wl, rings.source, "V")
        r = S / L[:, None]
        fb, fv = wb @ r, wv @ r
        ebv = star_reddening(rings.star_tau, wl, rings.source, rings.rv) if reference == "observed" else 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            model = np.where((fb > 0) & (fv > 0), -2.5 * np.log10(fb / fv), np.nan) - ebv
            # d Delta = -2.5 / ln 10 (sum_b wB_b dS_b / (L_b FB) - sum_b wV_b dS_b / (L_b FV))
            c = -2.5 / math.log(10.0) * (wb[:, None] / fb[None] - wv[:, None] / fv[None]) / L[:, None]
        y = np.einsum("bn,mbn->mn", np.nan_to_num(c), X)
        err = np.where(np.isfinite(model), _batch_error(y), np.nan)
        return model, err

    if table.kind == "polarization":
        if rings.tangential is None:
            raise SceneError("tables", table.path, "a polarization table needs the rings' Stokes sums "
                                                   "(trace_rings(..., stokes=True) of a polarized scene)")
        # P_t = sum_b h_b T_b / sum_b h_b S_b at the row's wavelength (linear between band
        # centres), linearised per batch: dP = (h . dT - P h . dS) / (h . S)
        h = hat_basis(wl, table.wavelength)  # (n_bands, n)
        T = rings.tangential @ W.T
        XT = np.einsum("mbr,nr->mbn", rings.tangential_batches, W)
        num, den = (h * T).sum(axis=0), (h * S).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            model = np.where(den > 0, num / den, np.nan)
            y = (np.einsum("bn,mbn->mn", h, XT) - np.nan_to_num(model) * np.einsum("bn,mbn->mn", h, X)) / den
        return model, np.where(np.isfinite(model), _batch_error(np.nan_to_num(y)), np.nan)
    seen = np.exp(-rings.star_tau) if reference == "observed" else np.ones(len(wl))
    h = hat_basis(wl, table.x)  # (n_bands, n)
    c = 4.0 * math.pi * rings.pixel_area * h / (L * seen)[:, None]
    model = (c * S).sum(axis=0)
    y = np.einsum("bn,mbn->mn", c, X)
    return model, _batch_error(y)


@dataclass
class TableResult:
    """One table against the model.

    ``raw_model_err`` is the Monte Carlo error before any free scale (what ``model_errors`` of
    :func:`compare_tables` takes).

    Attributes
    ----------
    table : ObservedTable
    model, model_err : ndarray (n,)
        The model's value per row (scaled by ``scale`` for a free-normalised ratio table) and its
        Monte Carlo error.
    residual : ndarray (n,)
        data - model.
    pull : ndarray (n,)
        residual / sqrt(error^2 + model_err^2).
    chi2 : float
    dof : int
        Rows less the fitted scale factors (one per annulus of a free-normalised ratio table).
    scale : ndarray or None
        The fitted factor per annulus (free normalisation).
    """

    table: ObservedTable
    model: np.ndarray
    model_err: np.ndarray
    residual: np.ndarray
    pull: np.ndarray
    chi2: float
    dof: int
    scale: Optional[np.ndarray] = None
    raw_model_err: Optional[np.ndarray] = None

    def to_dict(self) -> dict:
        t = self.table

        def lst(a):
            return [finite_or_none(x) for x in a]

        d = {"table": t.path, "kind": t.kind, "x": lst(t.x), "x_unit": "nm" if t.kind == "ratio" else "box units",
             "offset_lo": lst(t.lo), "offset_hi": lst(t.hi), "data": lst(t.value), "data_err": lst(t.error),
             "model": lst(self.model), "model_err": lst(self.model_err), "residual": lst(self.residual),
             "pull": lst(self.pull), "chi2": finite_or_none(self.chi2), "dof": self.dof}
        if t.kind == "ratio":
            d["normalisation"] = t.normalisation
        if t.kind == "polarization":
            d["wavelength_nm"] = lst(t.wavelength)
        if self.scale is not None:
            d["scale"] = lst(self.scale)
        return d


@dataclass
class Comparison:
    """A run against one or more tables."""

    results: list = field(default_factory=list)
    reference: str = "observed"
    rings: Optional[RingSums] = None

    @property
    def chi2(self) -> float:
        return float(sum(r.chi2 for r in self.results))

    @property
    def dof(self) -> int:
        return int(sum(r.dof for r in self.results))

    @property
    def n(self) -> int:
        return int(sum(len(r.table) for r in self.results))

    def model_error_ratio(self) -> float:
        """Largest model/data error ratio over all rows: the diagonal chi^2 (and a fit) wants it small."""
        return float(max(np.nanmax(r.model_err / r.table.error) for r in self.results))

    def to_dict(self) -> dict:
        from scipy.stats import chi2 as chi2_dist

        # no p-value without a chi^2 (a row the model gives no colour, NaN) or without a degree of freedom
        p = finite_or_none(chi2_dist.sf(self.chi2, self.dof)) if self.dof > 0 and math.isfinite(self.chi2) else None
        return {"reference": self.reference, "chi2": finite_or_none(self.chi2), "dof": self.dof,
                "reduced_chi2": finite_or_none(self.chi2 / self.dof) if self.dof > 0 else None, "p_value": p,
                "max_model_to_data_error": finite_or_none(self.model_error_ratio()),
                "tables": [r.to_dict() for r in self.results]}


def compare_tables(rings: RingSums, tables: Sequence[ObservedTable], reference: str = "observed",
                   model_errors: Optional[Sequence[np.ndarray]] = None) -> Comparison:
    """Residuals and chi^2 of ``tables`` against the ring sums of one run (see the module doc).

    ``model_errors`` (one array per table, before any free scale) replaces the run's own Monte
    Carlo errors: a fit holds them fixed while it moves the parameters (see
    :mod:`nebula_rt.observe.fit`).

    A free-normalised ratio table's model is scaled per annulus by s = sum(d m / v) / sum(m^2 / v)
    with v = sigma_d^2 + (s sigma_m)^2 (the weighted least-squares factor, iterated twice from
    v = sigma_d^2), and its degrees of freedom are the rows less one per annulus.
    """
    out = Comparison(reference=reference, rings=rings)
    if not tables:
        raise SceneError("tables", [], "give at least one table of observations")
    for j, t in enumerate(tables):
        if rings.pixels is not None:
            _check_rows_have_pixels(rings.edges, rings.pixels, t)
        model, merr = model_values(rings, t, reference)
        if model_errors is not None:
            merr = np.asarray(model_errors[j], np.float64)
        scale = None
        raw_err = merr
        dof = len(t)
        if t.kind == "ratio" and t.normalisation == "free":
            idx = t.annulus_index()
            scale = np.ones(idx.max() + 1)
            for k in range(len(scale)):
                rows = idx == k
                s = 1.0
                for it in range(3):
                    v = t.error[rows] ** 2 + (s * merr[rows]) ** 2 * (it > 0)
                    den = np.sum(model[rows] ** 2 / v)
                    s = float(np.sum(t.value[rows] * model[rows] / v) / den) if den > 0 else np.nan
                scale[k] = s
            model, merr = model * scale[idx], merr * np.abs(scale[idx])
            dof -= len(scale)
        res = t.value - model
        pull = res / np.sqrt(t.error ** 2 + merr ** 2)
        chi2 = float(np.sum(pull ** 2)) if np.all(np.isfinite(pull)) else math.inf
        out.results.append(TableResult(table=t, model=model, model_err=merr, residual=res, pull=pull, chi2=chi2,
                                       dof=dof, scale=scale, raw_model_err=raw_err))
    return out


def _check_rows_have_pixels(edges, pixels, t: ObservedTable, option: str = "table") -> None:
    """Every row of ``t`` must sum at least one pixel that sees the box (``pixels`` per ring
    between ``edges``, :func:`ring_pixels`): a row of no pixel would be compared with nothing
    (a colour of NaN, a ratio of 0)."""
    for i, (lo, hi) in enumerate(zip(t.lo, t.hi)):
        if not _rings_of(edges, lo, hi) @ pixels > 0:
            raise SceneError(f"{option} {t.path!r}, row {i + 1}", [float(lo), float(hi)],
                             "the annulus holds no pixel centre of the model image on the box, so it would be "
                             "compared with nothing: widen it, or give the image more pixels (--size)")


def compare(scene, tables: Sequence[ObservedTable], *, direction=(0.0, 0.0, -1.0), size: int = DEFAULT_SIZE,
            reference: str = "observed", backend=None, progress=None, cancel=None, comm=None) -> Comparison:
    """Trace ``scene`` once and hold it against ``tables`` (:func:`compare_tables`); the tables
    are checked against the scene and the model image first
    (:func:`check_tables_against_scene`: no row compared with nothing)."""
    _check_reference(reference)
    check_tables_against_scene(scene, tables, direction=direction, size=size)
    rings = trace_rings(scene, ring_edges(tables), direction=direction, size=size, backend=backend,
                        progress=progress, cancel=cancel, comm=comm, stokes=needs_stokes(tables))
    return compare_tables(rings, tables, reference)


def needs_stokes(tables) -> bool:
    """Whether any table compares the degree of polarization (the trace then keeps every
    pixel's Stokes batch sums)."""
    return any(t.kind == "polarization" for t in tables)


def check_tables_against_scene(scene, tables: Sequence[ObservedTable], direction=None, size: int = DEFAULT_SIZE,
                               option: str = "table") -> None:
    """What the scene must have for the tables: bands that cover each ratio table's wavelengths
    (no extrapolation) and, for colours, the B and V passbands; at least one table.

    With ``direction``, the model image too (``size`` pixels per side, about the most luminous
    star): every row's annulus must start inside the box's reach on the sky
    (:func:`box_reach`) and hold a pixel centre that sees the box, or it would be compared with
    nothing. Refusals name ``option`` (``--table`` on the command line), the file and the row.
    """

    if not tables:
        raise SceneError("tables", [], "give at least one table of observations")
    wl = sorted(b.wavelength for b in scene.bands.resolve())
    for t in tables:
        where = f"{option} {t.path!r}"
        if t.kind == "polarization":
            if scene.bands.polarization == "none":
                raise SceneError("bands.polarization", "none", f"{where} holds the degree of polarization: the scene "
                                 "needs bands.polarization = 'rayleigh' or 'white'")
            out = (t.wavelength < wl[0] - 1e-9) | (t.wavelength > wl[-1] + 1e-9)
            if out.any():
                i = int(np.flatnonzero(out)[0])
                raise SceneError(f"{where}, column 'wavelength', row {i + 1}", float(t.wavelength[i]),
                                 f"must lie within the scene's bands, {wl[0]:g} to {wl[-1]:g} nm (the model is "
                                 "interpolated between band centres, not extrapolated)")
        elif t.kind == "ratio":
            out = (t.x < wl[0] - 1e-9) | (t.x > wl[-1] + 1e-9)
            if out.any():
                i = int(np.flatnonzero(out)[0])
                raise SceneError(f"{where}, column 'wavelength', row {i + 1}", float(t.x[i]),
                                 f"must lie within the scene's bands, {wl[0]:g} to {wl[-1]:g} nm (the model is "
                                 "interpolated between band centres, not extrapolated); choose other bands "
                                 "(e.g. bands.preset = 'spectral-8')")
        elif len(wl) < 2 or wl[0] > 480.0 or wl[-1] < 520.0:
            raise SceneError("bands", [round(w, 1) for w in wl],
                             f"{where} holds Delta(B-V): the scene needs at least 2 bands, one at or below 480 nm "
                             "and one at or above 520 nm (e.g. bands.preset = 'spectral-8')")
    if direction is not None:
        _check_tables_in_image(scene, tables, direction, size, option)


def _check_tables_in_image(scene, tables, direction, size: int, option: str) -> None:
    """Every row's annulus inside the box's reach and on a pixel that sees the box
    (:func:`check_tables_against_scene`)."""
    star = max(scene.stars, key=lambda s: s.luminosity)
    reach = box_reach(star.position, direction)
    view = ",".join(f"{x:g}" for x in direction)
    for t in tables:
        beyond = t.lo >= reach
        if beyond.any():
            i = int(np.flatnonzero(beyond)[0])
            raise SceneError(f"{option} {t.path!r}, row {i + 1}", [float(t.lo[i]), float(t.hi[i])],
                             f"the annulus lies outside the model image: seen along {view}, the box reaches "
                             f"{reach:.4g} box units from the star (the most luminous), so an annulus must start "
                             f"below {reach:.4g} (offset_lo, box units)")
    edges = ring_edges(tables)
    _, _, pixels = ring_pixels(star.position, direction, size, edges)
    for t in tables:
        _check_rows_have_pixels(edges, pixels, t, option)


def plot(comp: Comparison, path, title: str = "", dust=None) -> None:
    """Model, data and residuals side by side, one row per table: left the data (1-sigma
    errors) with the model (its Monte Carlo error as a band), right the residuals in units of
    the combined error; with ``dust`` (:class:`nebula_rt.observe.published.DustBeside`) a last
    row of the scene's band albedo and g beside the published values of real nebulae. Written as
    a PNG through a temporary file."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(comp.results)
    rows = n + (dust is not None)
    fig, axes = plt.subplots(rows, 2, figsize=(11, 3.6 * rows), squeeze=False)
    if dust is not None:
        from .published import plot_beside

        plot_beside(axes[n], dust)
    ref = REFERENCE_LABELS[comp.reference]
    for (a1, a2), r in zip(axes, comp.results):
        t = r.table
        order = np.argsort(t.x)
        x = t.x[order]
        if t.kind == "colour":
            xlabel, ylabel = "projected offset from the star (box units)", f"Delta(B-V) nebula - {ref} (mag)"
        elif t.kind == "polarization":
            xlabel, ylabel = "projected offset from the star (box units)", "degree of polarization (tangential)"
        else:
            xlabel = "wavelength (nm)"
            ylabel = "nebula / star flux" + (" (model scaled per annulus)" if t.normalisation == "free" else "")
        a1.errorbar(x, t.value[order], yerr=t.error[order], fmt="o", color="C3", capsize=3, label="data (1 sigma)")
        m, me = r.model[order], r.model_err[order]
        a1.plot(x, m, "-", color="C0", label="model")
        a1.fill_between(x, m - me, m + me, color="C0", alpha=0.25, label="model Monte Carlo error")
        a1.set_xlabel(xlabel)
        a1.set_ylabel(ylabel)
        a1.set_title(f"{t.path}: chi2 = {r.chi2:.2f} for {r.dof} dof", fontsize=9)
        a1.legend(fontsize=7)
        a1.grid(alpha=0.3)
        a2.axhline(0.0, color="k", lw=0.8)
        a2.axhspan(-1, 1, color="C2", alpha=0.15, label="+-1 combined sigma")
        a2.plot(x, r.pull[order], "o-", color="C3", label="(data - model) / sqrt(sigma_d^2 + sigma_m^2)")
        a2.set_xlabel(xlabel)
        a2.set_ylabel("residual / combined error")
        a2.legend(fontsize=7)
        a2.grid(alpha=0.3)
    fig.suptitle(title or f"chi2 = {comp.chi2:.2f} for {comp.dof} degrees of freedom", fontsize=10)
    fig.tight_layout()

    try:
        with Publication() as pub:
            fig.savefig(pub.stage(path), dpi=100)
            pub.publish()
    finally:
        plt.close(fig)
