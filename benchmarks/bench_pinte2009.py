#!/usr/bin/env python
"""The Pinte et al. (2009, A&A 498, 967) polarization benchmark at tau = 1e6: NebulaRT's degree
of linear polarization along six cuts through the 1-micron images against the benchmark codes'
(SKIRT, Pinball, MCMax, MCFOST; digitized, benchmarks/data/pinte2009/published_cuts_tau1e6.csv).

The disk, star and grains are the benchmark's (benchmarks/pinte2009.py): the density on an
octree, the grains' tabulated matrix (``bands.polarization = "matrix"``), weighted packets
(forced scattering: the tenuous layers above the disk scatter some of every packet's light, as
the benchmark codes' images need) steered by the stars' windows, peel-off images of I, Q and U
at inclinations 69.5 and 87.1 degrees, 251 pixels over 900 AU.

Along each cut, P of the summed I, Q and U in bins of the cut (``--bin`` AU) and of the image
row (or column) on it and its two neighbours (the published cuts' lines in the figure are 3
pixels wide), by the modified asymptotic estimator (``--debias mas``, the default: the raw
sqrt(Q^2 + U^2) / I is biased high where it is within a few of its errors; ``none``: the raw
ratio), with its batch-means error (first order, from the peel-off errors), against the
published consensus averaged over the same bins, where every published point of the bin has at
least two codes and |x| <= 380 AU (the disk's edge at 400 AU makes narrow spikes). Reported per
cut: the differences' median and 90th percentile, the share within max(0.05, the codes' spread)
(or twice the stated error), the rms of the differences over the stated errors (about 1 where
they agree within NebulaRT's noise), and the same against the image mirrored about the disk's
major axis (which side of the disk is up in the figure is read from it, not stated).
``--from-images`` compares saved images again (another bin width) without tracing, and combines the
images of runs with other seeds (``--seed``), so a count of packets no single command can trace
within a time limit is reached in parts.

    python benchmarks/bench_pinte2009.py --backend cuda --photons 1e8 --out pinte.json
    python benchmarks/bench_pinte2009.py --backend opencl --device Portable --photons 3e5 --fraction 0.1
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pinte2009 as pinte  # noqa: E402
from provenance import provenance  # noqa: E402  (benchmarks/provenance.py)

from nebula_rt.backends import get_backend  # noqa: E402
from nebula_rt.errors import NebulaWarning  # noqa: E402
from nebula_rt.optics.bands import Band  # noqa: E402
from nebula_rt.observe.polarimetry import DEBIAS, polarization_maps  # noqa: E402
from nebula_rt.optics.mueller_table import read_matrix  # noqa: E402
from nebula_rt.optics.polarization import Polarization  # noqa: E402
from nebula_rt.scene import Star  # noqa: E402
from nebula_rt.transport import trace  # noqa: E402

BIN_AU = 5.0
EDGE_AU = 380.0
#: the agreement asked of a point: within the codes' own spread, and at least this
TOLERANCE = 0.05


def cut_profile(img, err, axis: str, offset_au: float, flip: bool = False, bin_au: float = BIN_AU,
                debias: str = "mas"):
    """(bin edges AU, P, P error) along a cut: I, Q, U (each (W, H)) summed over the cut's row
    (column) and its neighbours and over ``bin_au`` bins of x, P by ``debias``
    (:func:`~nebula_rt.observe.polarimetry.polarization_maps`: "mas" removes the Ricean bias of
    the raw ratio in the noisy bins); ``flip`` mirrors the image about the major axis first
    (y -> -y)."""
    i, q, u = (a[:, ::-1] if flip else a for a in img)
    ei, eq, eu = (a[:, ::-1] if flip else a for a in err)
    w = i.shape[0]
    pix = pinte.BOX_AU / w
    k = int(np.floor(offset_au / pix + w / 2))
    lines = slice(max(k - 1, 0), k + 2)
    if axis == "y":  # a row: x along the image's first axis
        parts = [a[:, lines].sum(axis=1) for a in (i, q, u)]
        var = [(a[:, lines] ** 2).sum(axis=1) for a in (ei, eq, eu)]
    else:
        parts = [a[lines, :].sum(axis=0) for a in (i, q, u)]
        var = [(a[lines, :] ** 2).sum(axis=0) for a in (ei, eq, eu)]
    x = (np.arange(w) + 0.5 - w / 2) * pix
    edges = np.arange(-450.0, 450.0 + bin_au / 2, bin_au)
    which = np.digitize(x, edges) - 1
    nb = len(edges) - 1
    si, sq, su = (np.bincount(which, a, nb) for a in parts)
    vi, vq, vu = (np.bincount(which, a, nb) for a in var)
    p, perr, _, _ = polarization_maps(si, sq, su, np.sqrt(vi), np.sqrt(vq), np.sqrt(vu), debias=debias)
    return edges, p, perr


def combined_images(paths):
    """(I, Q, U), (their errors) of the images saved by runs of other seeds (``--images``):
    each run's images are means over its packets, so they combine as a mean weighted by the
    runs' packets, their independent errors in quadrature with the same weights. Several
    files must each say how many packets they hold; the same seed twice is refused (the same
    packets are not independent)."""
    runs = [np.load(p) for p in paths]
    if len(runs) == 1:
        f = runs[0]
        return (f["i"], f["q"], f["u"]), (f["ei"], f["eq"], f["eu"])
    if any("photons" not in f for f in runs):
        raise SystemExit("--from-images: combining runs needs images saved with their packet counts "
                         "(bench_pinte2009.py --images, from this version on)")
    seeds = [int(f["seed"]) for f in runs]
    if len(set(seeds)) < len(seeds):
        raise SystemExit(f"--from-images: the runs' seeds {seeds} repeat; runs of one seed hold the same packets")
    w = np.array([float(f["photons"]) for f in runs])
    w = w / w.sum()
    img = tuple(sum(wk * f[k] for wk, f in zip(w, runs)) for k in ("i", "q", "u"))
    err = tuple(np.sqrt(sum((wk * f[k]) ** 2 for wk, f in zip(w, runs))) for k in ("ei", "eq", "eu"))
    return img, err


def compare(edges, p, perr, published):
    """Agreement with the published consensus averaged over the same bins (those whose
    published points all have at least two codes and lie within EDGE_AU): the z-scores'
    spread (the differences against NebulaRT's stated errors: about 1 where they agree within
    the noise), the differences' median and 90th percentile, and the share within the
    tolerance (max(TOLERANCE, the codes' spread)) or within twice the error."""
    px, cons, spread = published["x_au"], published["consensus"], published["spread"]
    which = np.digitize(px, edges) - 1
    rows = []
    for b in range(len(edges) - 1):
        sel = which == b
        if not sel.any() or not np.isfinite(cons[sel]).all() or np.abs(px[sel]).max() > EDGE_AU:
            continue
        if not np.isfinite(p[b]):
            continue
        rows.append((p[b], perr[b], cons[sel].mean(), np.nanmax(np.nan_to_num(spread[sel], nan=0.0))))
    if not rows:
        return {"bins": 0}
    ours, err, pub, spr = (np.array(c) for c in zip(*rows))
    d = np.abs(ours - pub)
    tol = np.maximum(TOLERANCE, spr)
    return {"bins": len(rows), "median_abs_diff": float(np.median(d)), "p90_abs_diff": float(np.percentile(d, 90)),
            "within_tolerance": float(np.mean(d <= tol)),
            "within_tolerance_or_2_errors": float(np.mean(d <= np.maximum(tol, 2 * err))),
            "z_rms": float(np.sqrt(np.mean(((ours - pub) / np.hypot(err, 0.005)) ** 2))),
            "median_error": float(np.median(err))}


def run(backend, tree, tau, inclination, photons, seed, method, importance, max_scatterings):
    m = read_matrix(pinte.MATRIX)
    band = Band(name="J", wavelength=1000.0, extinction=1.0, albedo=pinte.ALBEDO, g=m.g)
    star = Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        t0 = time.perf_counter()
        res = trace(tree, [band], [star], tau=tau, photons=photons, seed=seed, backend=backend,
                    peel=pinte.camera(inclination), polarization=Polarization("matrix", matrix=m),
                    light_field=False, method=method, importance=importance, max_scatterings=max_scatterings)
        wall = time.perf_counter() - t0
    img = (res.peel_image[0], res.peel_stokes[0, 0], res.peel_stokes[0, 1])
    err = (res.peel_error[0], res.peel_stokes_error[0, 0], res.peel_stokes_error[0, 1])
    return res, img, err, wall


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--device", default="")
    ap.add_argument("--photons", type=float, default=1e6)
    ap.add_argument("--tau", type=float, default=1e6, help="midplane optical depth from R_in to R_out")
    ap.add_argument("--fraction", type=float, default=0.1, help="the octree's cell edge / distance from the star")
    ap.add_argument("--height", type=float, default=0.5, help="the octree's cell edge / the disk's scale height")
    ap.add_argument("--method", default="biased")
    ap.add_argument("--importance", default="stars")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-scatterings", type=int, default=1000)
    ap.add_argument("--inclinations", default="69.5,87.1")
    ap.add_argument("--out", default="")
    ap.add_argument("--images", default="", help="save I, Q, U and their errors per inclination (.npz)")
    ap.add_argument("--plot", default="", help="a PNG of the cuts against the published ones")
    ap.add_argument("--bin", type=float, default=BIN_AU, help="bin width along the cuts, AU")
    ap.add_argument("--debias", default="mas", choices=DEBIAS,
                    help="P of each bin: the modified asymptotic estimator (mas) or the raw ratio (none)")
    ap.add_argument("--from-images", default="",
                    help="compare the images earlier runs saved (--images) instead of tracing: one prefix, or "
                         "several (comma-separated) of runs with other seeds, combined")
    args = ap.parse_args(argv)
    backend = get_backend(args.backend, args.device)
    tree, tau, discretised = None, pinte.tau_per_box(args.tau), None
    if not args.from_images:
        t0 = time.perf_counter()
        tree, tau = pinte.build_tree(args.tau, fraction=args.fraction, height=args.height)
        build_s = time.perf_counter() - t0
        discretised = pinte.midplane_tau_of(tree, tau)
        print(f"octree: {tree.n_leaves:,} leaves, depth {tree.depth()}, built in {build_s:.1f} s; tau per box "
              f"{tau:.6g}; midplane tau through the leaves {discretised:.4g} (defined: {args.tau:g})")
    published, positions = pinte.read_cuts()
    out = {"benchmark": "bench_pinte2009", "date": time.strftime("%Y-%m-%d %H:%M:%S"), "device": backend.device_name,
           "command": " ".join(sys.argv), **provenance(),
           "host": platform.node(), "photons": int(args.photons), "midplane_tau": args.tau, "fraction": args.fraction,
           "height": args.height, "midplane_tau_of_the_leaves": discretised,
           "leaves": None if tree is None else tree.n_leaves, "depth": None if tree is None else tree.depth(), "method": args.method, "importance": args.importance,
           "seed": args.seed, "max_scatterings": args.max_scatterings, "bin_au": args.bin, "debias": args.debias,
           "from_images": args.from_images, "inclinations": {}, "cuts": {}}
    curves = {}
    for inc in (float(v) for v in args.inclinations.split(",")):
        if args.from_images:
            img, err = combined_images([f"{prefix}-{inc}.npz" for prefix in args.from_images.split(",")])
        else:
            res, img, err, wall = run(backend, tree, tau, inc, int(args.photons), args.seed, args.method,
                                      args.importance, args.max_scatterings)
            kernel = res.timings.get("kernel_s", float("nan"))
            print(f"i = {inc} deg: {wall:.1f} s ({kernel:.1f} s kernel), method {res.method}")
            out["inclinations"][str(inc)] = {"wall_s": wall, "kernel_s": kernel, "method": res.method,
                                             "counts": [str(c) for c in res.counts[0]]}
        if args.images and not args.from_images:
            np.savez_compressed(f"{args.images}-{inc}.npz", i=img[0], q=img[1], u=img[2], ei=err[0], eq=err[1], eu=err[2],
                                photons=int(args.photons), seed=args.seed)
        for k, (axis, off, kinc) in positions.items():
            if abs(kinc - inc) > 0.05:
                continue
            row = {}
            for name, flip in (("as_is", False), ("mirrored", True)):
                edges, p, perr = cut_profile(img, err, axis, off, flip, args.bin, args.debias)
                row[name] = compare(edges, p, perr, published[k])
                curves[(k, name)] = (0.5 * (edges[1:] + edges[:-1]), p, perr)
            out["cuts"][str(k)] = {"axis": axis, "offset_au": off, "inclination": inc, **row}
            a, b = row["as_is"], row["mirrored"]
            print(f"  cut {k} ({axis} {off:+g} AU, {a['bins']} bins of {args.bin:g} AU): |dP| median "
                  f"{a['median_abs_diff']:.3f} p90 {a['p90_abs_diff']:.3f}, within tolerance {a['within_tolerance']:.2f} "
                  f"(or 2 errors {a['within_tolerance_or_2_errors']:.2f}), z rms {a['z_rms']:.2f}, P error "
                  f"{a['median_error']:.3f}; mirrored: median {b['median_abs_diff']:.3f}, z rms {b['z_rms']:.2f}")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(2, 3, figsize=(15, 7), sharey=True)
        for a, k in zip(axes.ravel(), sorted(int(c) for c in out["cuts"])):
            c = published[k]
            a.fill_between(c["x_au"], c["consensus"] - np.maximum(TOLERANCE, np.nan_to_num(c["spread"])),
                           c["consensus"] + np.maximum(TOLERANCE, np.nan_to_num(c["spread"])), color="r", alpha=0.15)
            a.plot(c["x_au"], c["consensus"], "r-", lw=1, label="benchmark codes (median)")
            for name, style in (("as_is", "k-"), ("mirrored", "b:")):
                if (k, name) in curves:
                    x, p, perr = curves[(k, name)]
                    a.plot(x, p, style, lw=0.9, label=f"NebulaRT ({name.replace('_', ' ')})")
            info = out["cuts"][str(k)]
            a.set_title(f"cut {k}: i = {info['inclination']}, {info['axis']} = {info['offset_au']:+g} AU")
            a.set_xlim(-450, 450)
            a.set_ylim(0, 1)
        axes[0, 0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=80)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
