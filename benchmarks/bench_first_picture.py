#!/usr/bin/env python
"""The first picture in ParaView: Nebula Dust Density and Nebula Light Field at their defaults.

    python benchmarks/bench_first_picture.py [--repeats 3] [--device NAME] [--out FILE.json]

What a user meets on the first Apply: each repetition is a fresh ``pvpython`` (environment of
scripts/pv-env.sh, on the X display of $DISPLAY or a private Xvfb) that loads the plugin,
makes the density and the light field with every property at its default (the thesis's
nebula: 64^3, Tau 128, a 20000 K star, 3 bands x 2.1M packets) and shows the light field as
Apply does, then renders. Times, from the script's start (its imports excluded):

  density_s   the dust density source's update;
  light_s     the light field's update (the device's start-up, the kernels' build or their
              cache, the trace, the finishing, the colour);
  picture_s   the first render after Show (the display's set-up and the volume's upload);
  total_s     all three: from Apply to the picture.

The device is PoCL unless ``--device`` names another. Prints a table and writes the JSON
(default benchmarks/results/first_picture.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = r'''
import json, sys, time
t0 = time.perf_counter()
from paraview import simple
from nebula_rt_paraview.view import load_plugin
load_plugin()
device = sys.argv[1]
t1 = time.perf_counter()
dust = simple.NebulaDustDensity(Device=device)
dust.UpdatePipeline()
t2 = time.perf_counter()
light = simple.NebulaLightField(dust, Device=device)
light.UpdatePipeline()
t3 = time.perf_counter()
view = simple.CreateView("RenderView")
view.ViewSize = [1000, 800]
simple.Show(light, view)
simple.Render(view)
t4 = time.perf_counter()
alg = light.GetClientSideObject()
print("RESULT " + json.dumps({"setup_s": t1 - t0, "density_s": t2 - t1, "light_s": t3 - t2, "picture_s": t4 - t3,
                              "total_s": t4 - t1, "error": alg.last_error,
                              "points": int(light.GetDataInformation().GetNumberOfPoints())}))
'''


def pv_environment() -> dict:
    proc = subprocess.run(["bash", "-c", 'source "$1" >/dev/null && env -0', "pv-env", str(REPO / "scripts" / "pv-env.sh")],
                          capture_output=True, check=True)
    return dict(item.split("=", 1) for item in proc.stdout.decode().split("\0") if "=" in item)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="Portable Computing Language")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "first_picture.json"))
    args = ap.parse_args()
    env = pv_environment()
    xvfb = None
    if not os.environ.get("DISPLAY"):
        display = f":{200 + os.getpid() % 100}"
        xvfb = subprocess.Popen(["Xvfb", display, "-screen", "0", "1280x1024x24", "-nolisten", "tcp", "-noreset"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(1.0)
        env["DISPLAY"] = display
    else:
        env["DISPLAY"] = os.environ["DISPLAY"]
    runs = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            script = Path(tmp) / "first_picture.py"
            script.write_text(CHILD)
            for i in range(args.repeats):
                proc = subprocess.run(["pvpython", str(script), args.device], env=env, capture_output=True,
                                      text=True, timeout=600)
                line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                if not line:
                    print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
                    return 1
                r = json.loads(line[0][7:])
                runs.append(r)
                print(f"run {i + 1}: density {r['density_s']:.2f} s, light field {r['light_s']:.2f} s, "
                      f"first render {r['picture_s']:.2f} s, total {r['total_s']:.2f} s (error: {r['error']})")
    finally:
        if xvfb is not None:
            xvfb.terminate()
            xvfb.wait()
    med = sorted(r["total_s"] for r in runs)[len(runs) // 2]
    print(f"median from Apply to picture: {med:.2f} s over {len(runs)} runs")
    out = {"benchmark": "first_picture", "device": args.device, "host": platform.node(),
           "cpus": os.cpu_count(), "pvpython": shutil.which("pvpython"), "runs": runs, "median_total_s": med}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
