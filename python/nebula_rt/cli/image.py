"""Command line of an observed image: ``nebula-rt compare SCENE --image obs.fits``.

The scene's calibrated peel-off image (:mod:`nebula_rt.observe.calibrate`, as ``nebula-rt sky`` makes
it) in one band or passband, against the user's FITS image reprojected onto it
(:mod:`nebula_rt.observe.image_compare`): the plot of model, data and residuals side by side
(``--png``), the summary with chi^2 (JSON on stdout, ``--json``) and, with ``--fits``, the
images of the comparison on the model's WCS. The image, its errors and its overlap with the
model image are checked before anything is traced.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import SceneError
from .arguments import file_name


def add_image_options(p) -> None:
    """The options of ``compare --image``."""
    from ..observe.image_compare import REPROJECT_MODES

    p.add_argument("--image", type=file_name, default=None, metavar="FITS",
                   help="the user's observed image: FITS with a celestial WCS, in MJy/sr or another surface brightness "
                        "per unit frequency (docs/observations.md)")
    p.add_argument("--image-hdu", default=None, help="the image's HDU, by name or number (default: the first image)")
    p.add_argument("--image-band", default=None,
                   help="the model image to compare: a scene band or a passband (bessell-B, bessell-V, bessell-R, "
                        "sdss2010-g, sdss2010-r, sdss2010-i); default the header's BAND or FILTER")
    p.add_argument("--image-unit", default=None, help="the image's unit where its header has no BUNIT, e.g. 'MJy/sr'")
    p.add_argument("--image-error", action="append", default=[], metavar="HDU|X%|VALUE UNIT",
                   help="the image's 1-sigma error: an error HDU (e.g. ERR), a relative error ('5%%') or a surface "
                        "brightness ('0.2 MJy/sr'); repeatable, added in quadrature")
    p.add_argument("--reproject", default="exact", choices=list(REPROJECT_MODES),
                   help="exact: flux-conserving area means (default); interp: bilinear at the model pixels' centres")
    p.add_argument("--mask-stars", type=float, default=0.0, metavar="ARCSEC",
                   help="leave out the pixels within this radius of each star (default 0)")
    p.add_argument("--fits", type=file_name, default=None,
                   help="with --image: also write model, data, errors, residual and pull as FITS on the model's WCS")


def check_image_options(args) -> None:
    """The image's options without ``--image``: refused rather than ignored."""
    given = [opt for opt, val in (("--image-hdu", args.image_hdu), ("--image-band", args.image_band),
                                  ("--image-unit", args.image_unit), ("--image-error", args.image_error),
                                  ("--mask-stars", args.mask_stars), ("--fits", args.fits)) if val]
    if args.image is None and given:
        raise SceneError(given[0], getattr(args, given[0][2:].replace("-", "_")),
                         "applies to an observed image: give it with --image obs.fits")


def compare_image_command(args, ranks, scene, direction, backend_of, inputs, print_summary) -> int:
    """``nebula-rt compare --image``: arguments as :func:`nebula_rt.cli.fit.compare_tables_command`'s."""
    from ..observe import calibrate, image_compare as ic
    from ..transport import resources
    from ..pipeline.outputs import Output, Publication, check_outputs

    cancel = ranks.cancel
    with ranks.start():
        if args.table or args.stokes:
            raise SceneError("--image", args.image, "compare an image or tables (--table, --stokes), not both in one run")
        if not (math.isfinite(args.mask_stars) and args.mask_stars >= 0):
            raise SceneError("--mask-stars", args.mask_stars, "must be a radius in arcsec >= 0")
        calibrate.check_scene(scene)
        obs = ic.read_image(args.image, args.image_hdu, unit=args.image_unit, errors=args.image_error,
                             option="--image")
        # the band, the overlap, the reprojection and the star mask: refused here, where the
        # ranks of an MPI job agree on it (in the trace, each rank told it and aborted the job)
        prepared = ic.prepare_observed_image(scene, obs, band=args.image_band, direction=direction, size=args.size,
                                             mode=args.reproject, mask_stars_arcsec=args.mask_stars)
        npix = args.size * args.size
        outs = [Output("--png", Path(args.png), ".png", 4 << 20)]
        if args.json:
            outs.append(Output("--json", Path(args.json), ".json", 1 << 20))
        if args.fits:
            outs.append(Output("--fits", Path(args.fits), ".fits", 7 * npix * 4 + (64 << 10)))
        check_outputs(outs, inputs + [("--image", Path(args.image))])
        backend = backend_of()
        resources.check(scene, backend, peel_pixels=npix, peel_option="--size", peel_value=args.size)
        cancel.check("start-up")
    with ranks.trace():
        res = ic.compare_observed_image(scene, obs, band=prepared.kind[2], direction=direction, size=args.size,
                                        mode=args.reproject, mask_stars_arcsec=args.mask_stars, backend=backend,
                                        cancel=cancel, comm=ranks.comm, prepared=prepared)
        cancel.check("run")
    c = res.comparison
    summary = {"scene": str(args.scene), "png": str(args.png), **res.to_dict()}

    def publish():
        with Publication() as pub:
            ic.plot(res, pub.stage(args.png),
                    title=f"{Path(args.scene).stem} ({res.model.band}) against {Path(args.image).name}: chi2 = "
                          f"{c.chi2:.1f} for {c.n} pixels ({res.model.photons:,} packets per band)")
            if args.json:
                pub.stage(args.json).write_text(json.dumps(summary, indent=2) + "\n")
            if args.fits:
                ic.write_fits(pub.stage(args.fits), res)
            cancel.check("run")
            pub.publish()
        print_summary(summary)

    ranks.publish(publish)
    return 0
