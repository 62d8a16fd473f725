#!/usr/bin/env python
"""Speed versus accuracy: error against a known answer versus time, in one command.

    python benchmarks/trade_study.py [--backend cuda|opencl] [--device SEL] [--max-photons 1e8]
                                     [--out benchmarks/results/trade-study-<device>.json]
    python benchmarks/trade_study.py --plot RESULT.json      # -> docs/trade_study.{png,md}
    python benchmarks/trade_study.py --presets [--out F]     # the quality presets, measured

Scenes with known answers:
  absorber  uniform dust, tau 3 across the box, albedo 0, one band, star at the centre: the
            analytic J = L exp(-kappa r) / (16 pi^2 r^2), averaged over each voxel by
            Gauss-Legendre quadrature (nebula_rt.transport.analytic);
  thesis    the thesis nebula (turbulence, 3 bands, albedo = g = 0.6, tau 128) against a
            reference run with 10x the largest photon count and another seed, regenerated
            here (its own variance is subtracted from the measured squared error).

Axes: photons per band 1e4 .. --max-photons (x10 steps); estimator: track-length and the
collision filter at radii 0.02 and 0.04 box units; transport method: analog, and biased
(weighted packets, track-length); grid 32^3, 64^3, 128^3 (at 1e6 photons).
Error: brightness-weighted (sigma J) RMS over the lit region (nebula_rt.transport.lit_region,
from the known answer) of the relative error of J in each band, the largest over the bands; beside it the error the run
reports (batch means over the same voxels; it does not see the filter's bias). Time: wall
time of the transport (kernels + finishing), median of 3 (1 for the largest runs), after a
warm-up. Precision: the transport has one precision (float32 geometry, 64-bit fixed-point
tallies; docs/physics.md gives its error, far below the Monte Carlo error), so it is not an
axis here.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: (estimator, filter radius, transport method)
CONFIGS = [("track-length", 0.0, "analog"), ("collision-filter", 0.02, "analog"),
           ("collision-filter", 0.04, "analog"), ("track-length", 0.0, "biased")]


def absorber_scene(n, photons, backend, device):
    from nebula_rt.scene import Scene

    return Scene.from_dict({
        "grid": {"shape": [n, n, n]},
        "dust": {"model": "uniform", "density": 1.0, "floor": 0.0, "tau": 3.0},
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0}],
        "bands": {"list": [{"name": "V", "wavelength": 550.0, "extinction": 1.0, "albedo": 0.0, "g": 0.0}]},
        "transport": {"photons": int(photons), "backend": backend, "device": device},
    })


def thesis_scene(n, photons, backend, device):
    from nebula_rt.scene import Scene

    return Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        [f"grid.shape=[{n},{n},{n}]", f"transport.photons={int(photons)}",
         f'transport.backend="{backend}"', f'transport.device="{device}"'])


def run(scene, backend, estimator, radius, seed, repeats, method="analog"):
    """(J, reported error, sigma, median wall s, median kernel s) of one configuration."""
    from nebula_rt.pipeline import compute_light
    from nebula_rt.transport.estimate import lit_region_error

    from nebula_rt.pipeline import Pipeline

    over = [f'transport.estimator="{estimator}"', f"transport.seed={seed}", f'transport.method="{method}"']
    if radius:
        over.append(f"transport.filter_radius={radius}")
    scene = scene.with_overrides(over)
    rho = Pipeline(backend).density(scene)
    walls, kernels = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res, J, rel = compute_light(scene, rho, backend)
        walls.append(time.perf_counter() - t0)
        kernels.append(res.timings["kernel_s"])
    sigma = res.sigma_scale[:, None, None, None] * rho.astype(np.float64)[None]
    return J, rel, sigma, statistics.median(walls), statistics.median(kernels), lit_region_error(J, rel, sigma)


def rms_error(J, truth, sigma, mask, ref_rel=None):
    """Largest over the bands of the brightness-weighted (sigma J of the known answer) RMS
    relative error over the mask, the reference's own variance subtracted when ``ref_rel`` is
    given -- the measure ``lit_region_error`` reports."""
    worst = 0.0
    for b in range(J.shape[0]):
        m = mask[b]
        w = (truth[b] * sigma[b])[m]
        d2 = np.sum(w * (J[b][m] / truth[b][m] - 1.0) ** 2) / np.sum(w)
        if ref_rel is not None:
            d2 = max(d2 - np.sum(w * ref_rel[b][m] ** 2) / np.sum(w), 0.0)
        worst = max(worst, float(np.sqrt(d2)))
    return worst


def study(args) -> dict:
    from nebula_rt.transport.analytic import voxel_average_point_source, voxel_centres
    from nebula_rt.backends import get_backend
    from nebula_rt.transport.estimate import lit_region

    backend = get_backend(args.backend, args.device)
    photon_list = [int(10**k) for k in range(4, int(round(np.log10(args.max_photons))) + 1)]
    rows = []
    for n in args.grids:
        for name, make in (("absorber", absorber_scene), ("thesis", thesis_scene)):
            photons_here = photon_list if n == args.base_grid else [1_000_000]
            # warm-up (compile) on this grid
            run(make(n, 1000, args.backend, args.device), backend, "track-length", 0.0, 1, 1)
            run(make(n, 1000, args.backend, args.device), backend, "collision-filter", 0.02, 1, 1)
            run(make(n, 1000, args.backend, args.device), backend, "track-length", 0.0, 1, 1, "biased")
            if name == "absorber":
                shape = (n, n, n)
                X, Y, Z = voxel_centres(shape)
                r = np.sqrt((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2)
                far = r > 1.5 / n  # the source's own voxels are not integrable by quadrature
                truth = np.zeros((1,) + shape)
                truth[0][far] = voxel_average_point_source(shape, (0.5, 0.5, 0.5), 3.0, 1.0, far)
                sigma = np.full((1,) + shape, 3.0)
                mask = lit_region(truth, sigma) & far[None]
                ref_rel = None
                ref_info = "analytic"
            else:
                ref_photons = 10 * max(photons_here)
                t0 = time.perf_counter()
                truth, ref_rel, sigma, _, _, ref_err = run(make(n, ref_photons, args.backend, args.device),
                                                           backend, "track-length", 0.0, 987654321, 1)
                mask = lit_region(truth, sigma) & (truth > 0)
                ref_info = f"track-length, {ref_photons} photons, seed 987654321, error {ref_err:.2e}, {time.perf_counter() - t0:.1f} s"
            print(f"== {name} {n}^3 (reference: {ref_info}; lit voxels {int(mask.sum())})", flush=True)
            for photons in photons_here:
                for estimator, radius, method in CONFIGS:
                    repeats = 1 if photons >= args.max_photons / 10 else 3
                    J, rel, _, wall, kernel, reported = run(make(n, photons, args.backend, args.device), backend,
                                                            estimator, radius, 1, repeats, method)
                    err = rms_error(J, truth, sigma, mask, ref_rel)
                    row = {"scene": name, "grid": n, "photons": photons, "estimator": estimator,
                           "filter_radius": radius, "method": method, "wall_s": round(wall, 5),
                           "kernel_s": round(kernel, 5), "true_error": err, "reported_error": reported,
                           "reference": ref_info}
                    rows.append(row)
                    print(f"  {photons:>11,d} {estimator:16s} r={radius:<5} {method:6s} wall {wall * 1e3:9.1f} ms  "
                          f"error {err:.4f}  reported {reported:.4f}", flush=True)
    return _result("trade_study", backend, rows)


def presets(args) -> dict:
    """Each quality preset on the thesis nebula: photons used, reported and true error, time."""
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline, compute_light
    from nebula_rt.scene import QUALITY_PRESETS
    from nebula_rt.transport.estimate import lit_region

    backend = get_backend(args.backend, args.device)
    rows = []
    for n, names, ref_photons in ((64, ("preview", "balanced", "reference"), 1_000_000_000),
                                  (128, ("preview", "balanced"), 1_000_000_000)):
        base = thesis_scene(n, 1000, args.backend, args.device)
        truth, ref_rel, sigma, _, _, ref_err = run(base.with_overrides([f"transport.photons={ref_photons}"]),
                                                   backend, "track-length", 0.0, 987654321, 1)
        mask = lit_region(truth, sigma) & (truth > 0)
        rho = Pipeline(backend).density(base)
        for name, method in [(q, m) for m in ("analog", "biased") for q in names]:
            scene = base.with_overrides([f'transport.quality="{name}"', f'transport.method="{method}"'])
            compute_light(scene.with_overrides(['transport.quality=""', "transport.photons=10000"]), rho, backend)
            t0 = time.perf_counter()
            res, J, rel = compute_light(scene, rho, backend)
            wall = time.perf_counter() - t0
            err = rms_error(J, truth, sigma, mask, ref_rel)
            row = {"grid": n, "quality": name, "method": method, "target_error": QUALITY_PRESETS[name]["target_error"],
                   "budget": QUALITY_PRESETS[name]["photons"], "photons_used": int(res.photons),
                   "reported_error": res.achieved_error, "true_error": err, "wall_s": round(wall, 4),
                   "reference": f"{ref_photons} photons, error {ref_err:.2e}"}
            rows.append(row)
            print(f"{n}^3 {name:9s} {method:6s} target {row['target_error']:.2f}: {row['photons_used']:>11,d} photons, "
                  f"reported {row['reported_error']:.4f}, true {err:.4f}, {wall * 1e3:8.1f} ms", flush=True)
    return _result("quality_presets", backend, rows)


def _result(name: str, backend, rows) -> dict:
    return {"benchmark": name, "device": backend.device_name,
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "command": " ".join(["benchmarks/trade_study.py"] + sys.argv[1:]), "rows": rows}


def label(row) -> str:
    est = "track-length" if row["estimator"] == "track-length" else f"collision filter r={row['filter_radius']}"
    return est + (", biased" if row.get("method") == "biased" else "")


def plot(result: dict, png: Path, md: Path) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    base = max(set(r["grid"] for r in rows), key=lambda g: sum(1 for r in rows if r["grid"] == g))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    for ax, scene in zip(axes, ("absorber", "thesis")):
        for lab in dict.fromkeys(label(r) for r in rows):
            sel = sorted((r for r in rows if r["scene"] == scene and r["grid"] == base and label(r) == lab),
                         key=lambda r: r["photons"])
            if not sel:
                continue
            line, = ax.loglog([r["wall_s"] for r in sel], [r["true_error"] for r in sel], "o-", label=lab)
            if lab == "track-length":  # analog
                ax.loglog([r["wall_s"] for r in sel], [r["reported_error"] for r in sel], "x--",
                          color=line.get_color(), label="track-length, reported")
            for r in sel:
                ax.annotate(f"{r['photons']:.0e}".replace("+0", ""), (r["wall_s"], r["true_error"]),
                            fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel("transport wall time (s)")
        ax.set_ylabel("relative error of J (weighted RMS, lit region)")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(f"{scene} {base}^3" + (" (analytic J)" if scene == "absorber" else " (vs 10x reference)"))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Speed vs accuracy, {result['device']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    lines = [f"# Speed versus accuracy", "",
             f"`{result['command']}` on {result['device']}, {result['date'][:10]}.", "",
             "Error: RMS relative error of J over the lit region (the largest over the bands) against the "
             "known answer; reported: the run's own batch-means error over its lit region (it cannot see "
             "the collision filter's smoothing bias). Time: transport wall time (kernels + finishing).", "",
             f"![speed vs accuracy]({png.name})", "",
             "| scene | grid | photons/band | estimator | wall (ms) | error | reported |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['grid']}^3 | {r['photons']:.0e} | {label(r)} | {r['wall_s'] * 1e3:.1f} | "
                     f"{r['true_error']:.4f} | {r['reported_error']:.4f} |")
    md.write_text("\n".join(lines) + "\n")


def _save(result: dict, out, stem: str) -> None:
    """Write a result as JSON to ``out`` (default benchmarks/results/<stem>-<date>.json)."""
    out = Path(out) if out else ROOT / "benchmarks" / "results" / f"{stem}-{_dt.date.today()}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"saved {out}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="")
    ap.add_argument("--max-photons", type=float, default=1e8)
    ap.add_argument("--grids", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--base-grid", type=int, default=64, help="grid of the photon sweep")
    ap.add_argument("--out", default=None)
    ap.add_argument("--plot", default=None, help="plot a saved result into docs/ instead of running")
    ap.add_argument("--presets", action="store_true", help="measure the quality presets instead")
    args = ap.parse_args(argv)
    if args.presets:
        _save(presets(args), args.out, "quality-presets")
        return 0
    if args.plot:
        plot(json.loads(Path(args.plot).read_text()), ROOT / "docs" / "trade_study.png", ROOT / "docs" / "trade_study.md")
        print("wrote docs/trade_study.png and docs/trade_study.md")
        return 0
    _save(study(args), args.out, "trade-study")
    return 0


if __name__ == "__main__":
    sys.exit(main())
