"""The discrepancy analysis of every real recording in ``data/real`` (or the files given), timed.

Each file is read as ``compasscal analyze`` reads it and analysed with the default 200 null simulations,
one at a time in this process. Prints, per file: the model (table angles or attitude-free), the samples
analysed, the seconds the analysis took, the verdict, the residual before and after (its largest column:
an axis with table angles, the magnitude or the dip without), the held-out improvement and the first finding, next to the issue's target of
30 s per analysis.

    python benchmarks/real.py [FILE ...] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from physics.discrepancy import analyze
from service.imports import read_recording_file

REAL = Path(__file__).resolve().parent.parent / "data" / "real"
TARGET_S = 30.0


def _first(findings: list[dict]) -> str:
    """The first finding in a few words: effect, frame and form, segments."""
    if not findings:
        return "-"
    f = findings[0]
    m = f.get("model") or {}
    where = ", ".join(f"{s:.0f}-{e:.0f} s" for s, e in m.get("segments") or [])
    what = " ".join(str(x) for x in (f["effect"], m.get("frame"), m.get("form"), m.get("against")) if x)
    return what + (f" [{where}]" if where else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path, help="recordings (default: every file in data/real but its README)")
    ap.add_argument("--seed", type=int, default=None, help="seed of the null simulations (default: the analyser's own)")
    args = ap.parse_args()
    files = args.files or sorted(p for p in REAL.iterdir() if p.suffix.lower() in (".csv", ".mat", ".hdf5", ".h5"))
    print("| file | model | samples | seconds | verdict | residual rms, largest column (LSB) | held-out better | first finding |")
    print("|---|---|---|---|---|---|---|---|")
    worst = 0.0
    for path in files:
        rec = read_recording_file(path)
        t0 = time.perf_counter()
        r = analyze(rec, seed=args.seed).result
        dt = time.perf_counter() - t0
        worst = max(worst, dt)
        before, after = (max(v for v in r[k] if v is not None) for k in ("residual_rms_before_lsb", "residual_rms_after_lsb"))
        held = (r.get("heldout") or {}).get("improvement_pct")
        print(f"| {path.name} | {r['model']} | {r['samples']} | {dt:.1f} | {r['verdict']} | {before:.1f} -> {after:.1f} | "
              + (f"{held:.1f} %" if held is not None else "-") + f" | {_first(r['findings'])} |")
    print(f"\nslowest analysis {worst:.1f} s (target <= {TARGET_S:.0f} s per analysis): "
          + ("ok" if worst <= TARGET_S else "MISSED"))


if __name__ == "__main__":
    main()
