#!/usr/bin/env python
"""Where a kernel's instructions and stalls go, from Nsight Compute's source page as CSV.

    ncu --import REPORT.ncu-rep --page source --csv --print-source sass > sass.csv
    python benchmarks/ncu_source_summary.py sass.csv [--top 40] [--out summary.json]

Prints the SASS instructions with the most warp-level executions and stall samples, the lanes
active per execution (thread-level over warp-level instructions), and the totals per opcode
family (the first word of the SASS text, e.g. IMAD, FFMA, ATOM, LDG), so that the kernel's time
can be told apart: the voxel step, the random numbers (64-bit multiplies: IMAD.HI, IMAD.WIDE),
the deposits (RED/ATOM), the density loads (LDG). It also splits the instructions by the lanes
active when they run (0-2, 2-8, 8-24, 24-32): code that one or two lanes of a warp run while
the others wait (a packet's interaction, its random-number block) is told apart from the walk
that all packets in flight take.
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import sys


def _num(x) -> float:
    try:
        return float(str(x).replace(",", ""))
    except ValueError:
        return 0.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv")
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    with open(args.csv, newline="") as f:
        lines = [ln for ln in f if ln.strip() and not ln.startswith("==")]
    # ncu heads the table with the kernel's name ("Kernel Name","trace_photons"): the header row
    # is the first that names the columns
    start = next((i for i, ln in enumerate(lines) if ln.startswith(('"Address"', '"#"'))), 0)
    rows = list(csv.DictReader(lines[start:]))
    if not rows:
        print("no rows")
        return 1
    cols = list(rows[0])
    print("columns:", len(cols))

    def col(*names):
        for n in names:
            for c in cols:
                if c.lower() == n.lower():
                    return c
        for n in names:
            for c in cols:
                if n.lower() in c.lower():
                    return c
        return None

    src, inst, thr = col("Source"), col("Instructions Executed", "inst_executed"), col("Thread Instructions Executed")
    stall = col("Warp Stall Sampling (All Samples)", "Warp Stall Sampling")
    addr = col("Address", "#")
    total_i = sum(_num(r.get(inst)) for r in rows) if inst else 0.0
    total_s = sum(_num(r.get(stall)) for r in rows) if stall else 0.0
    fam = collections.defaultdict(lambda: [0.0, 0.0, 0.0])
    for r in rows:
        op = (r.get(src) or "").strip().split()
        name = op[0] if op else "?"
        if name.startswith("@") and len(op) > 1:
            name = op[1]
        name = name.split(".")[0]
        fam[name][0] += _num(r.get(inst))
        fam[name][1] += _num(r.get(thr))
        fam[name][2] += _num(r.get(stall))
    print(f"\ntotal warp instructions {total_i:,.0f}, stall samples {total_s:,.0f}")
    print("\nopcode family: share of warp instructions, lanes per instruction, share of stall samples")
    for name, (i, t, s) in sorted(fam.items(), key=lambda kv: -kv[1][0])[:30]:
        print(f"  {name:<10} {i / max(total_i, 1):7.2%}  {t / max(i, 1):6.2f}  {s / max(total_s, 1):7.2%}")
    if inst and thr:
        print("\nby lanes active: instructions, share of warp instructions, lanes, share of stall samples")
        bins = ((0, 2), (2, 8), (8, 24), (24, 33))
        for lo, hi in bins:
            sel = [r for r in rows if _num(r.get(inst)) > 0 and lo <= _num(r.get(thr)) / _num(r.get(inst)) < hi]
            i = sum(_num(r.get(inst)) for r in sel)
            t = sum(_num(r.get(thr)) for r in sel)
            s_ = sum(_num(r.get(stall)) for r in sel) if stall else 0.0
            print(f"  {lo:2d}-{hi - 1 if hi == 33 else hi:<2d} lanes  {len(sel):5d}  {i / max(total_i, 1):7.2%}"
                  f"  {t / max(i, 1):6.2f}  {s_ / max(total_s, 1):7.2%}")
    for key, label in ((inst, "warp instructions"), (stall, "stall samples")):
        if not key:
            continue
        print(f"\ntop {args.top} by {label}:")
        for r in sorted(rows, key=lambda r: -_num(r.get(key)))[:args.top]:
            i = _num(r.get(inst))
            print(f"  {r.get(addr, '')!s:>8}  {_num(r.get(key)):14,.0f}  lanes {(_num(r.get(thr)) / i) if i else 0:5.1f}"
                  f"  {(r.get(src) or '').strip()[:90]}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"columns": cols, "total_inst": total_i, "total_stall": total_s,
                       "families": {k: {"inst": v[0], "thread_inst": v[1], "stall": v[2]} for k, v in fam.items()}},
                      f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
