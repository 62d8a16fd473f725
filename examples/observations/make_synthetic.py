#!/usr/bin/env python
"""Make the synthetic observation of the worked example (docs/observations.md).

The NGC 7023-like scene (examples/scenes/ngc7023-like.toml) on a 24^3 grid with albedo 0.6, g 0.5 in
every band and tau 15 is traced with 400,000 packets per band (seed 99) and observed along -z:
Delta(B-V) in 5 annuli of projected offset (error 0.05 mag) and the absolute nebula/star ratio at
4 wavelengths in 3 annuli (error 8 %), plus Gaussian noise of those errors (noise seed 7). The
tables are written as ECSV with units, their meta saying how they were made:

    python examples/observations/make_synthetic.py
"""

from pathlib import Path

import numpy as np

from nebula_rt.observe import comparison
from nebula_rt.observe.observed_tables import ObservedTable, _annuli_from_offsets, write_table
from nebula_rt.scene import Scene

HERE = Path(__file__).resolve().parent
TRUTH = {"bands.albedo": 0.6, "bands.g": 0.5, "dust.tau": 15.0}
OVERRIDES = ["grid.shape=[24,24,24]", "transport.photons=400000", "transport.seed=99"]


def main():
    scene = Scene.load(HERE.parent / "scenes" / "ngc7023-like.toml").with_overrides(
        OVERRIDES + [f"{k}={v}" for k, v in TRUTH.items()])
    offs = np.array([0.06, 0.14, 0.22, 0.30, 0.38])
    col = ObservedTable("colour", "colour", offs, np.zeros(5), np.full(5, 0.05), *_annuli_from_offsets(offs, "offset"))
    wl = np.array([420.0, 500.0, 600.0, 720.0])
    ann = [(0.02, 0.12), (0.12, 0.25), (0.25, 0.4)]
    x = np.tile(wl, len(ann))
    lo, hi = np.repeat([a[0] for a in ann], len(wl)), np.repeat([a[1] for a in ann], len(wl))
    rat = ObservedTable("ratio", "ratio", x, np.ones_like(x), np.ones_like(x), lo, hi, normalisation="absolute")
    comp = comparison.compare(scene, [col, rat], size=64)
    rng = np.random.default_rng(7)
    col.value = comp.results[0].model + col.error * rng.standard_normal(len(offs))
    rat.error = 0.08 * comp.results[1].model
    rat.value = comp.results[1].model + rat.error * rng.standard_normal(len(x))
    meta = {"source": "synthetic: made by NebulaRT (examples/observations/make_synthetic.py), not observed",
            "scene": "examples/scenes/ngc7023-like.toml with " + ", ".join(OVERRIDES),
            "truth": TRUTH, "direction": [0.0, 0.0, -1.0], "reference": "observed",
            "noise": "Gaussian, the errors of the table, numpy default_rng(7)"}
    write_table(col, HERE / "synthetic-colour.ecsv", meta={**meta, "quantity": "Delta(B-V) nebula - star as seen"})
    write_table(rat, HERE / "synthetic-ratio.ecsv",
                meta={**meta, "quantity": "nebula flux in the annulus / star flux as seen"})
    print("wrote", HERE / "synthetic-colour.ecsv", HERE / "synthetic-ratio.ecsv")


if __name__ == "__main__":
    main()
