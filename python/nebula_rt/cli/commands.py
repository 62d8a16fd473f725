"""Command line: ``nebula-rt render SCENE.toml -o out.vti --png out.png``.

Every scene key can be overridden with ``--set dotted.key=value`` (repeatable), e.g.
``--set grid.shape=[128,128,128] --set transport.photons=2.1e6``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from ..errors import CancelledError, OutputError, SceneError
from .. import scene as _scene
from ..scene import sky_schema
from .. import interrupts
from ..interrupts import SignalCancel
from .arguments import file_name
from .failures import RanksFailed, Ranks, abort_the_other_ranks, describe, error, quiet_rank, say

#: pixels per side of the sky image of ``nebula-rt compare``


def _toml_string(text: str) -> str:
    """``text`` as a TOML basic string, every quote, backslash and control character escaped:
    spliced between quotes as it was, ``--device 'a"b'`` was not TOML and reached the scene as
    the raw text with the quotes around it."""
    return '"' + "".join(c if c >= " " and c not in '"\\\x7f' else f"\\u{ord(c):04x}" for c in text) + '"'


def _scene_from_args(args):
    """The scene file with the command line's overrides applied."""
    from ..scene.model import Scene

    scene = Scene.load(args.scene)
    args.scene_used = scene  # a later error on a converted value names the physical key (units.attribute)
    for item in args.set:
        # an override without a key ("", "=1") has nothing the scene's message could name
        if "=" not in item or not item.partition("=")[0].strip():
            raise SceneError("--set", item, "must be KEY=VALUE with a dotted scene key, e.g. transport.photons=1e6")
    if args.set:
        scene = scene.with_overrides(args.set)
    if args.backend:
        scene = scene.with_overrides([f"transport.backend={args.backend}"])
    if args.device is not None:
        scene = scene.with_overrides([f"transport.device={_toml_string(args.device)}"])
    if args.photons is not None:
        scene = scene.with_overrides([f"transport.photons={args.photons}"])
    if args.target_error is not None:
        scene = scene.with_overrides([f"transport.target_error={args.target_error}"])
    if args.quality is not None:
        scene = scene.with_overrides([f'transport.quality="{args.quality}"'])
    if getattr(args, "stretch", None) is not None:
        scene = scene.with_overrides([f'colour.stretch="{args.stretch}"'])
    args.scene_used = scene
    if scene.dust.model == "file":  # the density file's kind, header and size, before any work
        from ..density import check_density_file

        check_density_file(scene.dust_file_path(), scene.dust.array, tuple(scene.grid.shape))
    return scene


#: upper bound of a PNG volume rendering (800 x 800 RGBA plus headers), for the free-space check
PNG_BYTES = 800 * 800 * 4 + 65536


def _vti_bytes(scene) -> int:
    """Upper bound of the ``.vti`` a scene writes (uncompressed arrays plus headers)."""
    import math

    nvox = math.prod(scene.grid.shape)
    nb = len(scene.bands.resolve())
    return nvox * (4 + 12 * nb + (4 if nb > 1 else 0)) + (64 << 10)


def _tree_bytes(scene) -> int:
    """Upper bound of the ``--tree`` .htg: a leaf per byte of the density file at most (each
    leaf takes more than a byte there) or 8^tree_depth for ``dust.octree``, times its arrays (float32 J, error and emissivity per
    band, the density) and the tree's own bits, plus headers."""
    nb = len(scene.bands.resolve())
    if scene.dust.model != "file":  # dust.octree: 8^tree_depth leaves at most (int32 node indices)
        leaves = min(8 ** int(scene.dust.tree_depth), 2**31 // 8 * 7)
    else:
        path = scene.dust_file_path()
        leaves = path.stat().st_size if path.is_file() else 0  # (a missing file is refused as an input)
    return leaves * (4 + 12 * nb + 2) + (64 << 10)


def _require_io(option: str, path, png: bool = False) -> None:
    """The VTK layer's writers (the ``io`` extra: VTK, pyvista) must import before a trace
    whose output needs them."""
    import importlib

    try:
        importlib.import_module("nebula_rt.filters.render" if png else "nebula_rt.filters.vti")
    except ImportError as exc:
        missing = (exc.name or "vtk").split(".")[0]
        raise OutputError(option, path, f"writing it needs {missing}: pip install 'nebula-rt[io]'") from None


def _inputs(args, scene) -> list[tuple[str, Path]]:
    """The files a run reads, which no output may replace."""
    inputs = [("scene", Path(args.scene))]
    if scene.dust.model == "file":
        inputs.append(("dust.file", scene.dust_file_path()))
    return inputs


def _backend_for(scene, comm=None):
    """The scene's backend (:func:`nebula_rt.transport.request.scene_backend`), its kernels
    built (an unusable device is reported before any work)."""
    from ..transport.request import scene_backend

    backend = scene_backend(scene, comm)
    check = getattr(backend, "check_build", None)
    if check is not None:
        check()
    return backend


class _Progress:
    """The trace's progress bar on stderr, shown from the first packets traced on: a run
    refused on the way (a density file's values, dust.tau against the density) says so in
    its one line, without an empty bar before it."""

    def __init__(self, scene, quiet: bool):
        self.total, self.quiet, self.bar = scene.transport.effective()[0], quiet, None

    def __call__(self, done, total) -> None:
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, unit="pkt", unit_scale=True, desc="tracing", disable=self.quiet,
                            file=sys.stderr)
        self.bar.n = done
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _print_summary(summary: dict) -> None:
    """Print the run's summary; a closed or broken stdout loses only the summary (the outputs
    are already published)."""
    if sys.stdout is None:
        return
    try:
        print(json.dumps(summary, indent=2), flush=True)
    except (OSError, ValueError):
        try:  # keep the interpreter's own flush at exit quiet too
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass


# One function though long (about 90 lines): the render command's steps in the order they
# happen (inputs, outputs checked, memory, trace, write, picture, publish), each followed by
# its cancel point, which a reader should see together.
def _render(args, cancel) -> int:
    from ..pipeline.outputs import Output, Publication, check_outputs
    from ..pipeline.stages import Pipeline
    from ..transport import resources

    # under mpiexec: every rank traces a share and holds the whole result; rank 0 writes it.
    # The ranks agree on how each step ended (cli.failures): one message, one exit status.
    ranks = Ranks(args, cancel)
    comm, lead = ranks.comm, ranks.lead
    with ranks.start():  # the start-up, whatever fails on whichever rank
        scene = _scene_from_args(args)
        out = Path(args.output)
        outputs = [Output("--output", out, ".vti", _vti_bytes(scene))]
        _require_io("--output", out)
        if args.png:
            outputs.append(Output("--png", Path(args.png), ".png", PNG_BYTES))
            _require_io("--png", args.png, png=True)
        if args.tree:
            from ..density.generate import traced_on_tree

            if not traced_on_tree(scene):
                raise SceneError("--tree", args.tree, "needs an adaptive density (dust.file .htg, .vthb or .vtp, or "
                                                      "dust.octree = true): the light of a uniform grid is the .vti")
            outputs.append(Output("--tree", Path(args.tree), ".htg", _tree_bytes(scene)))
            _require_io("--tree", args.tree)
        backend = _backend_for(scene, comm)
        resources.check(scene, backend)  # memory first: an impossible run is refused as such
        check_outputs(outputs, _inputs(args, scene))
        pipe = Pipeline(backend, comm=comm)
        cancel.check("start-up")

    t0 = time.perf_counter()
    progress = _Progress(scene, args.quiet or not lead)
    # the trace: the ranks decide a cancel together; any other failure is one rank's own
    with ranks.trace():
        try:
            light = pipe.run(scene, progress=progress, cancel=cancel)
        finally:
            progress.close()
        cancel.check("run")  # a cancel after the last launch publishes nothing either

    def publish():
        from ..filters.vti import write_vti

        with Publication() as pub:
            write_vti(pub.stage(out), light.point_arrays(), light.field_data(), light.spacing, light.origin)
            cancel.check("run")
            if args.tree:
                from ..filters.tree_light import write_tree_light

                write_tree_light(pub.stage(args.tree), pipe.density(scene), light)
                cancel.check("run")
            if args.png:
                import numpy as np

                from ..pipeline.rgba import colour_rgba, scene_opacity_factor
                from ..filters.render import render_rgba_png

                rgba = light.rgba
                if rgba is None:  # one band: no colour stage ran; the PNG asks for one (star's colour)
                    rho = light.density.astype(np.float64)
                    rgba, _ = colour_rgba(scene, light.bands, rho, light.emissivity.astype(np.float64),
                                          light.transport, scene_opacity_factor(scene, light.bands, light.density))
                render_rgba_png(pub.stage(args.png), rgba, light.spacing, light.origin)
                cancel.check("run")
            pub.publish()  # both outputs or neither

    ranks.publish(publish)  # the other ranks wait for rank 0's outcome
    if not lead:
        return 0
    elapsed = time.perf_counter() - t0
    tr = light.transport
    summary = {
        "output": str(out),
        "png": args.png,
        "device": tr.device,
        "grid": list(light.density.shape),
        "bands": [b.name for b in light.bands],
        "photons_per_band": tr.photons,
        "batches": tr.batches,
        "error_estimate": tr.error_estimate,  # "packets": batches of one packet
        "achieved_error": None if tr.achieved_error != tr.achieved_error else round(tr.achieved_error, 5),
        "wall_s": round(elapsed, 3),
        "timings_s": {k: round(v, 3) for k, v in light.timings.items()},
        "peak_device_mib": round(light.memory.get("device_peak_bytes", 0) / 2**20, 1),
        "peak_host_rss_mib": round(light.memory.get("host_peak_rss_bytes", 0) / 2**20, 1),
        "escaped_fraction": {b.name: float(tr.counts[i, 2] / tr.counts[i, 0]) for i, b in enumerate(light.bands)},
        # packets stopped at transport.max_scatterings: their light is missing from J
        "terminated_fraction": {b.name: float(f) for b, f in zip(light.bands, tr.terminated_fraction)},
    }
    if not args.quiet:
        _print_summary(summary)
    return 0


def parse_direction(text: str) -> tuple:
    """``--direction x,y,z`` -> a tuple of 3 floats by the rule of ``sky.direction`` (a length
    that normalises in float64: :data:`nebula_rt.scene.sky_schema.DIRECTION_ALLOWED`);
    SceneError naming ``--direction`` otherwise."""
    try:
        direction = tuple(float(x) for x in text.split(","))
    except ValueError:
        direction = None
    if direction is None or not sky_schema.valid_direction(direction):
        raise SceneError("--direction", text, sky_schema.DIRECTION_ALLOWED)
    return direction


def _size_range() -> tuple:
    """``--size``'s range: the declared ``sky.size`` (the filter's and the panel's too)."""
    p = sky_schema.declaration("sky.size")
    return int(p.lo), int(p.hi)


def check_size(size: int) -> None:
    """``--size``: pixels per side of a sky image."""
    lo, hi = _size_range()
    if not lo <= size <= hi:
        raise SceneError("--size", size, f"must be an integer in [{lo}, {hi}] (pixels per side)")


def _compare(args, cancel) -> int:
    """Trace a scene and measure its colours as an observer would, beside observed values.
    Under mpiexec the ranks share the trace and rank 0 writes (:class:`~nebula_rt.cli.failures.Ranks`)."""

    import numpy as np

    from ..observe import colours as observe
    from ..transport import resources
    from ..pipeline.outputs import Output, Publication, check_outputs

    ranks = Ranks(args, cancel)
    with ranks.start():
        scene = _scene_from_args(args)
        direction = parse_direction(args.direction)
        check_size(args.size)
        from .fit import check_stokes_options
        from .image import check_image_options, compare_image_command

        check_image_options(args)
        check_stokes_options(args)
    if args.image:  # the user's observed image (nebula_rt.cli.image)
        return compare_image_command(args, ranks, scene, direction, lambda: _backend_for(scene, ranks.comm),
                                     _inputs(args, scene), _print_summary)
    if args.table or args.stokes:  # the user's own observations (nebula_rt.cli.fit)
        from .fit import compare_tables_command

        return compare_tables_command(args, ranks, scene, direction, lambda: _backend_for(scene, ranks.comm),
                                      _inputs(args, scene), _print_summary)
    with ranks.start():
        wl = sorted(b.wavelength for b in scene.bands.resolve())
        if len(wl) < 2 or wl[0] > 480.0 or wl[-1] < 520.0:
            raise SceneError("bands", [round(w, 1) for w in wl],
                             "nebula-rt compare measures B-V: it needs at least 2 bands, one at or "
                             "below 480 nm and one at or above 520 nm (e.g. bands.preset = 'spectral-8')")
        png = Path(args.png)
        outputs = [Output("--png", png, ".png", 4 << 20)]
        if args.json:
            outputs.append(Output("--json", Path(args.json), ".json", 1 << 20))
        backend = _backend_for(scene, ranks.comm)
        resources.check(scene, backend, peel_pixels=args.size * args.size, peel_option="--size",
                        peel_value=args.size)
        check_outputs(outputs, _inputs(args, scene))
        cancel.check("start-up")
    with ranks.trace():
        prof, res = observe.observe_scene(scene, direction=direction, size=args.size, backend=backend,
                                          reference=args.reference, cancel=cancel, comm=ranks.comm)
        cancel.check("run")

    def mags(values):
        return [None if not np.isfinite(x) else round(float(x), 4) for x in values]

    summary = {
        "scene": str(args.scene), "png": str(png),
        "reference": prof.reference,
        "star_tau": [round(float(x), 4) for x in prof.star_tau],
        "star_ebv_mag": round(float(prof.star_ebv), 4),
        "offset": [round(float(x), 4) for x in prof.offset],
        "delta_bv_mag": mags(prof.delta_bv),
        "delta_bv_err_mag": mags(prof.delta_bv_err),
        "delta_bv_intrinsic_mag": mags(prof.delta_bv_intrinsic),
        "batches": prof.batches,
        "wavelength_nm": [float(x) for x in prof.wavelength_nm],
        "ratio_rel_550nm": [mags(row) for row in prof.ratio],
        "ratio_err": [mags(row) for row in prof.ratio_err],
        "observed_mean_delta_bv_mag": observe.observations()["mean_delta_bv"]["value"],
        "single_scattering_delta_bv_mag": observe.observations()["single_scattering_delta_bv"]["range"],
    }

    def publish():
        with Publication() as pub:  # the plot and the JSON, both or neither
            observe.plot(prof, pub.stage(png), title=f"{Path(args.scene).stem}: {len(res.band_luminosity)} bands, "
                                                     f"{res.photons:,} packets per band, peel-off image, "
                                                     f"against the {observe.REFERENCE_LABELS[prof.reference]}")
            if args.json:
                pub.stage(args.json).write_text(json.dumps(summary, indent=2) + "\n")
            cancel.check("run")
            pub.publish()
        _print_summary(summary)

    ranks.publish(publish)
    return 0


def _fit(args, cancel) -> int:
    """Fit the scene's dust to the user's tables (nebula_rt.cli.fit); under mpiexec the ranks
    share every trace and rank 0 writes."""
    from .fit import fit_command

    ranks = Ranks(args, cancel)
    with ranks.start():
        scene = _scene_from_args(args)
        direction = parse_direction(args.direction)
        check_size(args.size)
    return fit_command(args, ranks, scene, direction, lambda: _backend_for(scene, ranks.comm),
                       _inputs(args, scene), _print_summary)


def _devices(args, cancel) -> int:
    from ..backends.opencl import POCL_PLATFORM, list_devices, pocl_cache_refusal, probe_device

    found = list_devices()
    # PoCL lists no device at all when it cannot make its kernel cache folder
    refusal = pocl_cache_refusal()
    if not found:
        if refusal is not None:
            raise refusal
        print("no OpenCL devices found")
        return 1
    for p, d, name, gpu in found:
        problem = probe_device(f"{p}:{d}")
        state = "usable" if problem is None else f"NOT usable: {problem}"
        print(f"opencl {p}:{d}  {name}  ({'GPU' if gpu else 'CPU/other'}; {state})", flush=True)
    if refusal is not None:
        print(f"opencl {POCL_PLATFORM}  (NOT usable: {refusal})", flush=True)
    return 0


def _with_vectors(rgb8, cal, scene):
    """The picture with the reference band's polarization vectors, one per block of about a
    24th of the image, where P is at least 3 of its errors (nebula_rt.observe.polarimetry)."""
    from ..observe.polarimetry import overlay_vectors, vector_field
    from ..optics.bands import reference_band_index

    b = reference_band_index(scene.bands.resolve())
    step = max(2, rgb8.shape[0] // 24)
    err = cal.stokes_error
    centres, p, _, chi, keep = vector_field(cal.scattered[b], cal.stokes[b, 0], cal.stokes[b, 1],
                                         None if cal.scattered_error is None else cal.scattered_error[b],
                                         None if err is None else err[b, 0], None if err is None else err[b, 1],
                                         step=step)
    return overlay_vectors(rgb8, centres, p, chi, keep, length=2.0 * step)


def _sky(args, cancel) -> int:
    """A calibrated sky image of a scene (nebula_rt.observe.calibrate): FITS in MJy/sr and mag/arcsec^2
    with a celestial WCS, and a true-colour PNG. Under mpiexec the ranks share the trace and
    rank 0 writes."""
    import numpy as np

    from ..observe import calibrate
    from ..transport import resources
    from ..pipeline.outputs import Output, Publication, check_outputs

    ranks = Ranks(args, cancel)
    with ranks.start():
        scene = _scene_from_args(args)
        direction = parse_direction(args.direction)
        check_size(args.size)
        calibrate.check_scene(scene)
        npix = args.size * args.size
        nb = len(scene.bands.resolve())
        polarized = scene.bands.polarization != "none"
        if polarized and args.method != "peel-off":
            raise SceneError("--method", args.method, f"must be 'peel-off' with bands.polarization = "
                             f"'{scene.bands.polarization}' (the ray march has no Stokes Q and U)")
        if args.vectors and not polarized:
            raise SceneError("--vectors", True, "needs a scene with bands.polarization (it has none)")
        outputs = [Output("--fits", Path(args.fits), ".fits",
                          (nb * (3 if polarized else 1) + len(calibrate.PASSBANDS)) * npix * 4 + (256 << 10))]
        if args.png:
            outputs.append(Output("--png", Path(args.png), ".png", npix * 4 + 65536))
        if args.json:
            outputs.append(Output("--json", Path(args.json), ".json", 1 << 20))
        backend = _backend_for(scene, ranks.comm)
        resources.check(scene, backend, peel_pixels=npix if args.method == "peel-off" else 0,
                        peel_option="--size", peel_value=args.size)
        check_outputs(outputs, _inputs(args, scene))
        cancel.check("start-up")
        cam = calibrate.camera_for(scene, direction, args.size)
    progress = _Progress(scene, args.quiet or not ranks.lead)
    with ranks.trace():
        try:
            if args.method == "peel-off":
                cal, res = calibrate.peel_off_sky(scene, cam, backend, progress=progress, cancel=cancel,
                                                  comm=ranks.comm)
            else:
                from ..pipeline.stages import Pipeline

                light = Pipeline(backend, comm=ranks.comm).run(scene, progress=progress, cancel=cancel, colour=False)
                res = light.transport
                cal = calibrate.ray_march_sky(light, cam)
        finally:
            progress.close()
        cancel.check("run")
    summary = {
        "scene": str(args.scene), "fits": str(args.fits), "png": args.png, "method": cal.method,
        "photons_per_band": int(res.photons), "pixel_scale_arcsec": round(cal.pixel_scale_arcsec, 6),
        "psf_fwhm_arcsec": cal.psf_fwhm_arcsec, "bands": cal.band_names,
        "total_flux_jy": {n: float(f) for n, f in zip(cal.band_names, cal.total_flux_jy())},
        "star_flux_jy": [{n: float(f) for n, f in zip(cal.band_names, row)} for row in cal.star_flux_jy],
        "star_mag_ab": [{n: round(float(m), 4) for n, m in zip(cal.passbands, row)} for row in cal.star_mag],
        "faintest_lit_mag_arcsec2": {n: None if not (cal.mag[x] == cal.mag[x]).any() else
                                     round(float(np.nanmax(cal.mag[x])), 3) for x, n in enumerate(cal.passbands)},
    }
    if cal.stokes is not None:  # the whole image's polarization per band (its scattered light)
        from ..observe.polarimetry import polarization_maps

        p, _, chi, _ = polarization_maps(cal.scattered.sum(axis=(1, 2)), cal.stokes[:, 0].sum(axis=(1, 2)),
                                         cal.stokes[:, 1].sum(axis=(1, 2)))
        summary["net_polarization"] = {n: {"p": float(p[b]), "angle_deg_east_of_north": float(chi[b])}
                                       for b, n in enumerate(cal.band_names)}
        if cal.stokes.shape[1] > 2:  # Mie grains: the net circular polarization V / I too
            v = cal.stokes[:, 2].sum(axis=(1, 2)) / cal.scattered.sum(axis=(1, 2))
            for b, n in enumerate(cal.band_names):
                summary["net_polarization"][n]["v_over_i"] = float(v[b])

    def publish():
        with Publication() as pub:  # the FITS, the PNG and the JSON: all or none
            calibrate.write_fits(pub.stage(args.fits), cal, scene)
            if args.png:
                rgb8, exposure = calibrate.picture(cal, scene, scene.colour.exposure)
                if args.vectors:
                    rgb8 = _with_vectors(rgb8, cal, scene)
                calibrate.write_png(pub.stage(args.png), rgb8)
                summary["exposure"] = exposure
            if args.json:
                pub.stage(args.json).write_text(json.dumps(summary, indent=2) + "\n")
            cancel.check("run")
            pub.publish()
        if not args.quiet:
            _print_summary(summary)

    ranks.publish(publish)
    return 0


def _choices(key: str) -> list:
    """The non-empty choices of a scene key, from the scene schema (its flags take those)."""
    return [c for c in _scene.declaration(key).choices if c]


def _run_options() -> argparse.ArgumentParser:
    """The options of every command that traces (an argparse parent): scene overrides, the
    packets and the device."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key, e.g. transport.photons=1e6 (repeatable)")
    p.add_argument("--photons", default=None, help="shorthand for --set transport.photons=N")
    p.add_argument("--target-error", default=None,
                   help="trace until the lit region's relative error is at most this (photons = budget)")
    p.add_argument("--quality", default=None, choices=_choices("transport.quality"),
                   help="quality preset: a target error with a photon budget (overrides --photons)")
    p.add_argument("--backend", default=None, choices=_choices("transport.backend"),
                   help=_scene.declaration("transport.backend").doc)
    p.add_argument("--device", default=None, help="device selector (name substring or P:D)")
    return p


def _view_options() -> argparse.ArgumentParser:
    """The options of the commands that look at the scene from a direction (an argparse parent)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--direction", default="0,0,-1", help="viewing direction x,y,z (default 0,0,-1)")
    return p


def _reference_options() -> argparse.ArgumentParser:
    """The star colour the comparisons measure against (an argparse parent)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--reference", default="observed", choices=["observed", "intrinsic"],
                   help="star colour to measure against: as seen through its dust (default) or intrinsic")
    return p


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="nebula-rt", description="Radiative transfer in reflection nebulae")
    sub = ap.add_subparsers(dest="command", required=True)
    run, view, reference = _run_options(), _view_options(), _reference_options()
    r = sub.add_parser("render", parents=[run], help="trace a scene and write a .vti (and optionally a PNG)")
    r.add_argument("scene", type=file_name, help="scene file (TOML)")
    r.add_argument("-o", "--output", type=file_name, default="nebula.vti", help="output .vti file (default nebula.vti)")
    r.add_argument("--png", type=file_name, default=None, help="also write a volume rendering of rgba to this PNG")
    r.add_argument("--tree", type=file_name, default=None,
                   help="an adaptive dust.file only: also write the light per leaf (J, rel_error, emissivity, density) "
                        "as cell data of a vtkHyperTreeGrid to this .htg")
    r.add_argument("--stretch", default=None, choices=_choices("colour.stretch"),
                   help="shorthand for --set colour.stretch=S: " + _scene.declaration("colour.stretch").doc)
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    r.set_defaults(func=_render)
    k = sub.add_parser("sky", parents=[run, view],
                       help="a calibrated sky image: FITS (MJy/sr, mag/arcsec^2, celestial WCS) and PNG")
    k.add_argument("scene", type=file_name, help="scene file (TOML) with [observer] distance and stars in L_sun or M_V")
    k.add_argument("--fits", type=file_name, required=True, help="output FITS file")
    k.add_argument("--png", type=file_name, default=None, help="also write the true-colour picture to this PNG")
    k.add_argument("--json", type=file_name, default=None, help="also write the summary (fluxes, magnitudes) as JSON")
    k.add_argument("--method", default="peel-off", choices=["peel-off", "ray-march"],
                   help="peel-off during the transport (the phase function; default) or the ray march of the "
                        "light field's emissivity (isotropic per voxel)")
    k.add_argument("--size", type=int, default=sky_schema.default("sky.size")[0],
                   help="pixels per side ({}-{})".format(*_size_range()))
    k.add_argument("--stretch", default=None, choices=_choices("colour.stretch"),
                   help="the picture's tone curve (shorthand for --set colour.stretch=S)")
    k.add_argument("--vectors", action="store_true",
                   help="a polarized scene (bands.polarization): draw the reference band's polarization "
                        "vectors over the picture (length P, angle east of north; where P >= 3 errors)")
    k.add_argument("-q", "--quiet", action="store_true", help="no summary")
    k.set_defaults(func=_sky)
    c = sub.add_parser("compare", parents=[run, view, reference],
                       help="a scene's colours (Delta(B-V), nebula/star ratio) against observed nebulae, "
                            "the user's tables (--table) or FITS image (--image)")
    c.add_argument("scene", type=file_name, help="scene file (TOML)")
    c.add_argument("--png", type=file_name, default="compare.png", help="plot (default compare.png)")
    c.add_argument("--json", type=file_name, default=None, help="also write the measured profiles as JSON")
    c.add_argument("--size", type=int, default=sky_schema.COMPARISON_SIZE,
                   help="sky image pixels per side ({}-{})".format(*_size_range()))
    from .fit import add_fit_parser, add_table_options

    add_table_options(c)
    from .image import add_image_options

    add_image_options(c)
    c.set_defaults(func=_compare)
    add_fit_parser(sub, _fit, _size_range(), parents=[run, view, reference])
    d = sub.add_parser("devices", help="list compute devices")
    d.set_defaults(func=_devices)
    return ap


def main(argv=None) -> int:
    """Run the command line; returns the exit status.

    0 done; 1 a run that failed (an output that could not be written, an internal error); 2
    bad input (a scene value, an option, an output path, more memory than there is: nothing
    was written); 3 the backend or device cannot be used; 130 / 143 / 129 / 131 cancelled by
    SIGINT / SIGTERM / SIGHUP / SIGQUIT (nothing was written). Under mpiexec the ranks of a
    render agree on the failure (:mod:`~nebula_rt.cli.failures`): rank 0 alone prints it and
    every rank exits with its status.
    """
    import warnings

    from ..errors import NebulaWarning

    def show(message, category, filename, lineno, file=None, line=None):
        # NebulaRT's warnings are for the user: one line, no source location
        if issubclass(category, NebulaWarning):
            if not quiet_rank():  # the ranks' results, and so their warnings, are the same
                say(f"warning: {message}")
        else:
            _show_default(message, category, filename, lineno, file, line)

    _show_default = warnings.showwarning
    warnings.showwarning = show
    try:
        return _main(argv)
    finally:
        warnings.showwarning = _show_default


def _main(argv) -> int:
    from ..backends.parallel import launched_by_mpi

    # the ranks of an MPI job cancel together, by their polls (no watchdog: interrupts)
    cancel = SignalCancel(watchdog=not launched_by_mpi(), ends_process=interrupts.is_command())
    with cancel:
        args = None
        try:
            args = build_parser().parse_args(argv)
            # under mpiexec rank 0 alone says that a signal is cancelling the run
            cancel.quiet = bool(getattr(args, "quiet", False)) or quiet_rank()
            return args.func(args, cancel)
        except RanksFailed as exc:  # every rank of a distributed run raised it together
            if not quiet_rank():
                say(exc.failure.message, exc.rank if exc.rank else None, exc.size)
            return exc.status
        except (Exception, KeyboardInterrupt) as exc:
            failure = describe(exc, args, cancel)
            if failure is None:  # NEBULA_RT_DEBUG: the traceback of an internal error
                raise
            error(failure.message)
            if not isinstance(exc, CancelledError):
                # every rank of a distributed run raises a CancelledError together: no need to
                # abort the others
                abort_the_other_ranks(failure.status)
            return failure.status


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose usage, help and errors only rank 0 of an MPI job prints:
    every rank parses the same arguments and exits alike."""

    def _print_message(self, message, file=None):
        if not quiet_rank():
            super()._print_message(message, file)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
