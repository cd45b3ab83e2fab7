"""The blind proof of discovery without table angles (issue 12): hand-held recordings (proof/handheld.py)
with an out-of-catalogue departure concealed, analysed by the attitude-free model
(= ``compasscal prove --n 0 --nulls 0 --handheld-n N --handheld-nulls M``).

Per kind (an offset present for a while in the sensor frame or in the lab frame, one switched on twice,
the sensitivity following the temperature) ``--n`` recordings at a non-centrality spread log-uniformly
over 3-300, and ``--nulls`` recordings without. Each case is judged as the table proof's open-world cases
are (proof.score.judge_model): a finding in the true frame whose windows (or, since the nominal model
takes the constant, their complement) match each true window with both edges within 5 % of the run, or
modelled against the true input, and the residual after within 1.3x the noise floor. The table proof's
third criterion, the level heading error, needs a heading reference, which a hand-held recording lacks.

    python benchmarks/handheld.py [--n 20] [--nulls 100] [--seed 1] [--workers 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json

from proof.runner import run_handheld_proof
from proof.score import format_handheld_report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20, help="recordings per kind")
    ap.add_argument("--nulls", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=None, help="write the score and every case here")
    args = ap.parse_args()
    out = run_handheld_proof(args.n, args.nulls, args.seed, args.workers)
    print(f"seed {args.seed}, {len(out['cases'])} recordings in {out['config']['wall_s']:.0f} s")
    print(format_handheld_report(out["score"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
