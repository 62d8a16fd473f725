"""Command line: ``nebula-rt render SCENE.toml -o out.vti --png out.png``.

Every scene key can be overridden with ``--set dotted.key=value`` (repeatable), e.g.
``--set grid.shape=[128,128,128] --set transport.photons=2.1e6``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

from .errors import BackendUnavailableError, CancelledError, NebulaError, SceneError


def _scene_from_args(args):
    """The scene file with the command line's overrides applied."""
    from .scene import Scene

    scene = Scene.load(args.scene)
    if args.set:
        scene = scene.with_overrides(args.set)
    if args.backend:
        scene = scene.with_overrides([f"transport.backend={args.backend}"])
    if args.device is not None:
        scene = scene.with_overrides([f'transport.device="{args.device}"'])
    if args.photons is not None:
        scene = scene.with_overrides([f"transport.photons={args.photons}"])
    if args.target_error is not None:
        scene = scene.with_overrides([f"transport.target_error={args.target_error}"])
    if args.quality is not None:
        scene = scene.with_overrides([f'transport.quality="{args.quality}"'])
    return scene


def _render(args) -> int:
    from .pipeline import Pipeline

    scene = _scene_from_args(args)
    out = Path(args.output)
    if out.suffix.lower() != ".vti":
        raise SceneError("--output", str(out), "must end in .vti")
    if not out.parent.exists():
        raise SceneError("--output", str(out), f"folder {out.parent} does not exist")
    if args.png and not Path(args.png).parent.exists():
        raise SceneError("--png", str(args.png), f"folder {Path(args.png).parent} does not exist")

    interrupted = {"flag": False}

    def on_sigint(signum, frame):  # cancel cleanly between batches; a second Ctrl-C kills
        if interrupted["flag"]:
            raise KeyboardInterrupt
        interrupted["flag"] = True
        print("\ncancelling after the current batch (Ctrl-C again to abort now)", file=sys.stderr)

    old = signal.signal(signal.SIGINT, on_sigint)
    bar = None
    try:
        from tqdm import tqdm

        bar = tqdm(total=scene.transport.effective()[0], unit="pkt", unit_scale=True, desc="tracing",
                   disable=args.quiet, file=sys.stderr)

        def progress(done, total):
            bar.n = done
            bar.refresh()

        t0 = time.perf_counter()
        light = Pipeline().run(scene, progress=progress, cancel=lambda: interrupted["flag"])
    finally:
        if bar is not None:
            bar.close()
        signal.signal(signal.SIGINT, old)

    from .io_vti import write_vti

    write_vti(out, light.point_arrays(), light.field_data(), light.spacing, light.origin)
    if args.png:
        import numpy as np

        from .pipeline import colour_rgba
        from .render import render_rgba_png

        rgba = light.rgba
        if rgba is None:  # one band: no colour stage ran; the PNG asks for one (star's colour)
            rho = light.density.astype(np.float64)
            rgba, _ = colour_rgba(scene, light.bands, rho, light.emissivity.astype(np.float64), light.transport)
        render_rgba_png(args.png, rgba, light.spacing, light.origin)
    elapsed = time.perf_counter() - t0
    tr = light.transport
    summary = {
        "output": str(out),
        "png": args.png,
        "device": tr.device,
        "grid": list(light.density.shape),
        "bands": [b.name for b in light.bands],
        "photons_per_band": tr.photons,
        "achieved_error": None if tr.achieved_error != tr.achieved_error else round(tr.achieved_error, 5),
        "wall_s": round(elapsed, 3),
        "timings_s": {k: round(v, 3) for k, v in light.timings.items()},
        "peak_device_mib": round(light.memory.get("device_peak_bytes", 0) / 2**20, 1),
        "peak_host_rss_mib": round(light.memory.get("host_peak_rss_bytes", 0) / 2**20, 1),
        "escaped_fraction": {b.name: float(tr.counts[i, 2] / tr.photons) for i, b in enumerate(light.bands)},
        # packets stopped at transport.max_scatterings: their light is missing from J
        "terminated_fraction": {b.name: float(f) for b, f in zip(light.bands, tr.terminated_fraction)},
    }
    if not args.quiet:
        print(json.dumps(summary, indent=2))
    return 0


def _compare(args) -> int:
    """Trace a scene and measure its colours as an observer would, beside observed values."""
    import numpy as np

    from . import observe

    scene = _scene_from_args(args)
    try:
        direction = tuple(float(x) for x in args.direction.split(","))
        assert len(direction) == 3 and any(direction)
    except (ValueError, AssertionError):
        raise SceneError("--direction", args.direction, "must be three numbers x,y,z, not all 0") from None
    png = Path(args.png)
    if not png.parent.exists():
        raise SceneError("--png", str(png), f"folder {png.parent} does not exist")
    prof, res = observe.observe_scene(scene, direction=direction, size=args.size, reference=args.reference)
    observe.plot(prof, png, title=f"{Path(args.scene).stem}: {len(res.band_luminosity)} bands, "
                                  f"{res.photons:,} packets per band, peel-off image, "
                                  f"against the {observe.REFERENCE_LABELS[prof.reference]}")

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
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    return 0


def _devices(args) -> int:
    from .backends.opencl import list_devices

    found = list_devices()
    if not found:
        print("no OpenCL devices found")
        return 1
    for p, d, name, gpu in found:
        print(f"opencl {p}:{d}  {name}  ({'GPU' if gpu else 'CPU/other'})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="nebula-rt", description="Radiative transfer in reflection nebulae")
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="trace a scene and write a .vti (and optionally a PNG)")
    r.add_argument("scene", help="scene file (TOML)")
    r.add_argument("-o", "--output", default="nebula.vti", help="output .vti file (default nebula.vti)")
    r.add_argument("--png", default=None, help="also write a volume rendering of rgba to this PNG")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key, e.g. transport.photons=1e6 (repeatable)")
    r.add_argument("--photons", default=None, help="shorthand for --set transport.photons=N")
    r.add_argument("--target-error", default=None,
                   help="trace until the lit region's relative error is at most this (photons = budget)")
    r.add_argument("--quality", default=None, choices=["preview", "balanced", "reference"],
                   help="quality preset: a target error with a photon budget (overrides --photons)")
    r.add_argument("--backend", default=None, choices=["auto", "opencl", "cuda"])
    r.add_argument("--device", default=None, help="device selector (name substring or P:D)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    r.set_defaults(func=_render)
    c = sub.add_parser("compare", help="a scene's colours (Delta(B-V), nebula/star ratio) against observed nebulae")
    c.add_argument("scene", help="scene file (TOML)")
    c.add_argument("--png", default="compare.png", help="plot (default compare.png)")
    c.add_argument("--json", default=None, help="also write the measured profiles as JSON")
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a scene key")
    c.add_argument("--photons", default=None, help="shorthand for --set transport.photons=N")
    c.add_argument("--target-error", default=None, help="trace until this lit-region error")
    c.add_argument("--quality", default=None, choices=["preview", "balanced", "reference"])
    c.add_argument("--backend", default=None, choices=["auto", "opencl", "cuda"])
    c.add_argument("--device", default=None, help="device selector (name substring or P:D)")
    c.add_argument("--direction", default="0,0,-1", help="viewing direction x,y,z (default 0,0,-1)")
    c.add_argument("--size", type=int, default=128, help="sky image pixels per side")
    c.add_argument("--reference", default="observed", choices=["observed", "intrinsic"],
                   help="star colour to measure against: as seen through its dust (default) or intrinsic")
    c.set_defaults(func=_compare)
    d = sub.add_parser("devices", help="list compute devices")
    d.set_defaults(func=_devices)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except SceneError as exc:
        print(f"nebula-rt: invalid scene: {exc}", file=sys.stderr)
        return 2
    except BackendUnavailableError as exc:
        print(f"nebula-rt: {exc}", file=sys.stderr)
        return 3
    except CancelledError as exc:
        print(f"nebula-rt: {exc}; nothing written", file=sys.stderr)
        return 130
    except NebulaError as exc:
        print(f"nebula-rt: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
