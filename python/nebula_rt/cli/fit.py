"""Command line of the user's observations: ``nebula-rt compare --table`` and ``nebula-rt fit``.

``nebula-rt compare SCENE --table obs.ecsv [--table more.csv]`` traces the scene once and
writes the residuals and chi^2 of every table (JSON on stdout, ``--json``) and the plot of
model, data and residuals side by side (``--png``). ``nebula-rt fit SCENE --table ... --free
albedo --free g --free tau=0.3:10:log`` finds the parameters that match best, with their
uncertainties, and writes the best-fit scene (``--scene-out``), the comparison plot and JSON.
Progress, cancel and exit statuses as for ``nebula-rt render``.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from ..errors import SceneError
from ..scene import sky_schema
from .arguments import file_name


def add_table_options(p) -> None:
    """The options that say how to read the tables (shared by compare and fit)."""
    p.add_argument("--table", action="append", type=file_name, default=[], metavar="PATH",
                   help="the user's observations: a .csv or .ecsv table of Delta(B-V) versus offset (columns offset, "
                        "delta_bv, delta_bv_err) or of the nebula/star ratio versus wavelength (wavelength, ratio, "
                        "ratio_err); repeatable (docs/observations.md)")
    p.add_argument("--distance", default=None, help="distance to the nebula, e.g. '430 pc' (for offsets in arcsec)")
    p.add_argument("--box-length", default=None,
                   help="physical length of one box edge, e.g. '0.5 pc' (default grid.length grid.unit)")
    p.add_argument("--normalisation", default="free", choices=["free", "absolute"],
                   help="ratio tables: 'free' (relative ratios: the model is scaled to them per annulus) or "
                        "'absolute' (nebula flux in the annulus / star flux)")
    p.add_argument("--annulus", default="0,0.5",
                   help="ratio tables without offset columns: the annulus lo,hi (box units, default 0,0.5)")
    p.add_argument("--stokes", type=file_name, default=None, metavar="FITS",
                   help="observed Stokes images (I, Q, U; IAU): their tangential degree of polarization in "
                        "annuli about the star becomes a polarization table (docs/observations.md); with "
                        "--stokes-hdus, --stokes-wavelength, --stokes-annuli and --stokes-error")
    p.add_argument("--stokes-hdus", default=None, metavar="I,Q,U",
                   help="the HDUs of I, Q and U, by name or number (e.g. SB_G,Q_G,U_G, as nebula-rt sky writes them)")
    p.add_argument("--stokes-wavelength", type=float, default=None, metavar="NM", help="the observation's wavelength, nm")
    p.add_argument("--stokes-annuli", default=None, metavar="A,B,C,...", help="annulus edges, arcsec from the star")
    p.add_argument("--stokes-error", action="append", default=[], metavar="HDU|X%%|VALUE UNIT",
                   help="1-sigma error terms of I, Q and U (added in quadrature), as --image-error; repeatable")
    p.add_argument("--stokes-mask", type=float, default=0.0, metavar="ARCSEC",
                   help="leave out the pixels within this distance of a star (its unpolarized light)")


def _quantity(option: str, text):
    import astropy.units as u
    import numpy as np

    from ..scene.units import LENGTH_RANGE_M, LENGTH_RANGE_TEXT

    if text is None:
        return None
    try:
        q = u.Quantity(text)
    except (TypeError, ValueError):
        raise SceneError(option, text, "must be a length with its unit, e.g. '430 pc' or '0.5 pc'") from None
    allowed = f"must be a positive length with its unit, e.g. '430 pc' or '0.5 pc', {LENGTH_RANGE_TEXT}"
    if not q.unit.is_equivalent(u.m) or not (math.isfinite(q.value) and q.value > 0):
        raise SceneError(option, text, allowed)
    # the offsets in angles go through box / distance: a length beyond float64's squares is refused
    # here, by its option, not as an offset of no width later
    with np.errstate(over="ignore", under="ignore"):  # beyond float64: inf or 0, refused below
        metres = float(q.to_value(u.m))
    if not LENGTH_RANGE_M[0] <= metres <= LENGTH_RANGE_M[1]:
        raise SceneError(option, text, allowed)
    return q


def _box_length(args, scene):
    import astropy.units as u

    if args.box_length is not None:
        return _quantity("--box-length", args.box_length)
    from ..scene.units import length_metres

    try:  # the scene's box edge: a number in grid.unit, or a quantity such as "0.5 pc"
        return length_metres(scene.grid.length, scene.grid.unit) * u.m
    except (ValueError, TypeError, AttributeError):
        return None


def read_tables(args, scene) -> list:
    """The ``--table`` files, validated (SceneError before any tracing)."""
    from ..observe.observed_tables import OffsetScale, read_table

    try:
        annulus = tuple(float(x) for x in args.annulus.split(","))
        assert len(annulus) == 2 and all(math.isfinite(a) for a in annulus) and 0 <= annulus[0] < annulus[1]
    except (ValueError, AssertionError):
        raise SceneError("--annulus", args.annulus, "must be lo,hi with 0 <= lo < hi (box units)") from None
    scale = OffsetScale(box_length=_box_length(args, scene), distance=_quantity("--distance", args.distance))
    tables = [read_table(p, scale=scale, normalisation=args.normalisation, annulus=annulus, option="--table")
              for p in args.table]
    if getattr(args, "stokes", None):
        tables.append(_stokes_table(args, scene))
    return tables


#: the options that describe ``--stokes`` and their defaults (given without it: refused, not ignored)
STOKES_OPTIONS = {"--stokes-hdus": ("stokes_hdus", None), "--stokes-wavelength": ("stokes_wavelength", None),
                  "--stokes-annuli": ("stokes_annuli", None), "--stokes-error": ("stokes_error", []),
                  "--stokes-mask": ("stokes_mask", 0.0)}


def check_stokes_options(args) -> None:
    """An option of :data:`STOKES_OPTIONS` given without ``--stokes`` is refused by name (it
    would act on nothing)."""
    if getattr(args, "stokes", None):
        return
    for option, (dest, default) in STOKES_OPTIONS.items():
        value = getattr(args, dest, default)
        if value != default:  # (NaN too: it equals nothing)
            raise SceneError(option, value if not isinstance(value, list) else value[0],
                             "describes observed Stokes images: give them with --stokes FITS")


def _stokes_table(args, scene):
    """``--stokes``: the observed Stokes images as a polarization table (nebula_rt.observe.observed_stokes)."""
    from ..input_files import check_input_file
    from ..observe.observed_stokes import stokes_table

    check_input_file("--stokes", args.stokes, "a readable FITS file")  # (the file first: its option named)
    hdus = (args.stokes_hdus or "").split(",")
    if len(hdus) != 3 or not all(h.strip() for h in hdus):
        raise SceneError("--stokes-hdus", args.stokes_hdus, "must name the HDUs of I, Q and U: I,Q,U (names or numbers)")
    hdus = [int(h) if h.strip().isdigit() else h.strip() for h in hdus]
    if args.stokes_wavelength is None:
        raise SceneError("--stokes-wavelength", None, "must give the observation's wavelength in nm with --stokes")
    try:
        edges = [float(x) for x in (args.stokes_annuli or "").split(",")]
    except ValueError:
        raise SceneError("--stokes-annuli", args.stokes_annuli, "must be annulus edges in arcsec, a,b,c,...") from None
    if not args.stokes_error:
        raise SceneError("--stokes-error", [], "must give the errors of I, Q and U (an HDU, X% or a surface brightness)")
    if not (math.isfinite(args.stokes_mask) and args.stokes_mask >= 0):
        raise SceneError("--stokes-mask", args.stokes_mask, "must be a radius in arcsec >= 0")
    return stokes_table(scene, args.stokes, intensity=hdus[0], q=hdus[1], u=hdus[2], errors=args.stokes_error,
                        wavelength_nm=args.stokes_wavelength, annuli_arcsec=edges, mask_arcsec=args.stokes_mask,
                        option="--stokes")


def _outputs(args, scene, inputs):
    from ..pipeline.outputs import Output, check_outputs

    outs = [Output("--png", Path(args.png), ".png", 4 << 20)]
    if getattr(args, "json", None):
        outs.append(Output("--json", Path(args.json), ".json", 1 << 20))
    if getattr(args, "scene_out", None):
        outs.append(Output("--scene-out", Path(args.scene_out), ".toml", 1 << 20))
    check_outputs(outs, inputs + [("--table", Path(t)) for t in args.table]
                  + ([("--stokes", Path(args.stokes))] if getattr(args, "stokes", None) else []))


def compare_tables_command(args, ranks, scene, direction, backend_of, inputs, print_summary) -> int:
    """``nebula-rt compare --table``: one trace, residuals and chi^2 of every table, the plot.
    ``ranks``: the command's steps on the ranks (:class:`nebula_rt.cli.failures.Ranks`, with
    its cancel); ``backend_of()`` makes the backend (after the tables are checked); ``inputs``
    are the files no output may replace; ``print_summary`` prints the JSON summary
    (nebula_rt.cli's)."""
    from ..observe import comparison, published
    from ..transport import resources
    from ..pipeline.outputs import Publication

    cancel = ranks.cancel
    with ranks.start():
        tables = read_tables(args, scene)
        comparison.check_tables_against_scene(scene, tables, direction=direction, size=args.size, option="--table")
        backend = backend_of()
        resources.check(scene, backend, peel_pixels=args.size * args.size, peel_option="--size",
                        peel_value=args.size)
        _outputs(args, scene, inputs)
        cancel.check("start-up")
    with ranks.trace():
        comp = comparison.compare(scene, tables, direction=direction, size=args.size, reference=args.reference,
                                  backend=backend, cancel=cancel, comm=ranks.comm)
        cancel.check("run")
    dust = published.beside(scene)
    summary = {"scene": str(args.scene), "png": str(args.png), "photons_per_band": comp.rings.photons,
               **comp.to_dict(), "dust_optics": dust.to_dict()}

    def publish():
        with Publication() as pub:
            comparison.plot(comp, pub.stage(args.png),
                            title=f"{Path(args.scene).stem} against {len(tables)} table(s): chi2 = {comp.chi2:.2f} "
                                  f"for {comp.dof} dof ({comp.rings.photons:,} packets per band)", dust=dust)
            if args.json:
                pub.stage(args.json).write_text(json.dumps(summary, indent=2) + "\n")
            cancel.check("run")
            pub.publish()
        print_summary(summary)

    ranks.publish(publish)
    return 0


def fit_command(args, ranks, scene, direction, backend_of, inputs, print_summary) -> int:
    """``nebula-rt fit`` (arguments as :func:`compare_tables_command`'s). Under mpiexec the
    ranks share every trace and take the same steps (:meth:`nebula_rt.observe.fit.FitRequest.run`)."""
    from ..observe import comparison, fit, fit_parameters, published
    from ..transport import resources
    from ..pipeline.outputs import Publication

    cancel = ranks.cancel
    with ranks.start():
        check_stokes_options(args)
        tables = read_tables(args, scene)
        free = [fit_parameters.parse_free(s, scene, direction) for s in args.free]
        if not free:
            raise SceneError("--free", [], "name at least one parameter to fit, e.g. --free albedo --free tau")
        comparison.check_tables_against_scene(scene, tables, direction=direction, size=args.size, option="--table")
        request = fit.FitRequest(scene, tables, free, direction=direction, size=args.size, reference=args.reference,
                                 uncertainty=args.uncertainty, grid=args.grid, starts=args.starts)
        request.parameters()  # every option and bound, before the device is opened
        backend = backend_of()
        resources.check(scene, backend, peel_pixels=args.size * args.size, peel_option="--size",
                        peel_value=args.size)
        _outputs(args, scene, inputs)
        cancel.check("start-up")
    bar = None
    with ranks.trace():
        try:
            from tqdm import tqdm

            def progress(done, total, best):
                nonlocal bar
                if bar is None:  # from the first trace on (a refusal on the way has no empty bar)
                    bar = tqdm(total=1, unit="trace", desc="fitting", disable=args.quiet or not ranks.lead,
                               file=sys.stderr)
                bar.total = total
                bar.n = done
                bar.set_postfix_str(f"best chi2 {best:.2f}", refresh=False)
                bar.refresh()

            res = request.run(backend=backend, progress=progress, cancel=cancel, comm=ranks.comm)
        finally:
            if bar is not None:
                bar.close()
        cancel.check("run")
    dust = published.beside(res.scene)  # (the best fit's dust beside the published)
    summary = {"scene": str(args.scene), "png": str(args.png), **res.to_dict(), "dust_optics": dust.to_dict()}

    def publish():
        with Publication() as pub:
            comparison.plot(res.comparison, pub.stage(args.png),
                            title=f"best fit of {Path(args.scene).stem}: " + ", ".join(
                                f"{p.name} = {v:.4g}" for p, v in zip(res.parameters, res.best)) +
                                  f"; chi2 = {res.chi2:.2f} for {res.dof} dof", dust=dust)
            if args.json:
                pub.stage(args.json).write_text(json.dumps(summary, indent=2) + "\n")
            if args.scene_out:
                pub.stage(args.scene_out).write_text(res.scene.to_toml())
            cancel.check("run")
            pub.publish()
        if not args.quiet:
            print(res.summary(), file=sys.stderr, flush=True)
        print_summary(summary)

    ranks.publish(publish)
    return 0


def add_fit_parser(sub, func, sizes, parents=()) -> None:
    """The ``fit`` subcommand's options; ``func(args, cancel)`` runs it, ``sizes`` = (min, max)
    pixels per side of the image; ``parents``: the options it shares with the other commands
    (scene overrides, packets, device, direction, reference; ``--photons`` counts the packets of
    every trial, and a target error or quality preset is refused: a fit's trials trace a fixed
    number of packets)."""
    f = sub.add_parser("fit", parents=list(parents),
                       help="fit the dust (albedo, g, tau, the star's depth, any scene key) to observations")
    f.add_argument("scene", type=file_name, help="scene file (TOML): the model, and the start")
    add_table_options(f)
    f.add_argument("--free", action="append", default=[], metavar="NAME[=LO:HI[:log]]",
                   help="a parameter to fit: albedo, g, albedo_slope, g_slope, albedo.BAND, g.BAND, tau, depth or a "
                        "scene key (with bounds); repeatable")
    f.add_argument("--uncertainty", default="profile", choices=["profile", "mcmc", "none"],
                   help="profile likelihood (default), MCMC (emcee), or none")
    f.add_argument("--grid", type=int, default=None, help="starting grid points per parameter (default 3 for <= 3)")
    f.add_argument("--starts", type=int, default=None,
                   help="Nelder-Mead runs from the grid's best points and the start, at most as many as there are "
                        "(default 2, or 1 without a grid)")
    f.add_argument("--png", type=file_name, default="fit.png",
                   help="plot of the best fit against the tables (default fit.png)")
    f.add_argument("--json", type=file_name, default=None, help="also write the result as JSON")
    f.add_argument("--scene-out", type=file_name, default=None, help="write the best-fit scene (TOML)")
    f.add_argument("--size", type=int, default=sky_schema.COMPARISON_SIZE,
                   help=f"peel-off image pixels per side ({sizes[0]}-{sizes[1]})")
    f.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary on stderr")
    f.set_defaults(func=func)
