"""The blind proof of the discrepancy engine at full size (= ``compasscal prove`` with these defaults).

Random production units (physics.sensor.random_unit) on the characterize plan
(procedures.calibrate.characterize_plan, about 10 minutes at 20 Hz), I in 40-70 deg, base tilt up to
0.1 deg, a warm-up of 0-4 C, noise 1-5 LSB white or AR(1) with phi 0.3-0.9, quantised. Per catalogue
effect ``--n`` recordings with the effect concealed at a non-centrality spread log-uniformly over 3-300
(physics/prove.py defines it), ``--nulls`` recordings without, ``--n // 2`` pairs of effects. The
analyser sees only each noisy recording. Prints detection against effect size per effect, false
alarms, the confusion matrix, naming, parameter recovery with interval coverage, held-out improvement
against the true model and seconds per analysis, each next to the issue's target.

    python benchmarks/discrepancy.py [--n 40] [--nulls 300] [--seed 1] [--workers 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from physics.prove import format_report, run_proof
from procedures.calibrate import characterize_plan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40, help="recordings per effect")
    ap.add_argument("--nulls", type=int, default=300, help="null recordings (the false-alarm target needs >= 300)")
    ap.add_argument("--pairs", type=int, default=None, help="pairs of effects (default n // 2)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=None, help="write the score and every case here")
    args = ap.parse_args()
    t0 = time.perf_counter()

    def progress(done: int, total: int, kind: str) -> None:
        rate = (time.perf_counter() - t0) / done
        print(f"\r{done}/{total} {kind:<45} ~{rate * (total - done) / 60:.0f} min left", end="", file=sys.stderr, flush=True)

    out = run_proof(args.n, args.seed, args.workers, progress, plan=characterize_plan(), nulls=args.nulls,
                    pairs=args.pairs)
    print(file=sys.stderr)
    cfg = out["config"]
    print(f"{len(out['cases'])} recordings ({args.n} per effect, {cfg['nulls']} nulls, {cfg['pairs']} pairs), seed "
          f"{args.seed}, {cfg['wall_s'] / 60:.1f} min on {args.workers} workers")
    print()
    print(format_report(out["score"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
