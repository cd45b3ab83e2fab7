"""Two departures that overlap in time (issue 12): a magnet on the unit for one stretch (an offset fixed in
the sensor frame) and steel set down by the table for another that overlaps it (an offset fixed in the lab
frame), on the ordinary calibration plan with 3 LSB noise. A case succeeds when the analyser reports
exactly two discovered findings, one in each true frame, each with one window whose edges are within 5 %
of the run of the true window's. Prints one row per case and the share.

    python benchmarks/overlapping.py [--cases 12] [--seed 20]
"""

from __future__ import annotations

import argparse

import numpy as np

from physics.discrepancy import analyze
from physics.recording import Recording
from physics.sensor import random_unit
from physics.simulate import Noise, World, simulate_timeline
from physics.table import platform_attitude
from procedures.calibrate import calibration_poses

WORLD = World(inclination_deg=60.0, declination_deg=100.0, warmup_c=4.0, warmup_tau_s=60.0)


def _case(seed: int) -> tuple[Recording, dict[str, tuple[float, float]]]:
    """A recording with both departures, and each true window (as fractions of the run) by frame."""
    rng = np.random.default_rng(seed)
    unit = random_unit(rng)
    rec, _ = simulate_timeline(unit, calibration_poses(), WORLD, noise=Noise(3.0, 0.0, True), rng=rng)
    a0 = rng.uniform(0.05, 0.35)
    a1 = a0 + rng.uniform(0.25, 0.4)
    b0 = rng.uniform(a0 + 0.1, a1 - 0.05)
    b1 = min(b0 + rng.uniform(0.25, 0.45), 0.97)
    d_sensor = rng.normal(size=3)
    d_sensor *= rng.uniform(20, 60) / np.linalg.norm(d_sensor)  # counts
    d_lab = rng.normal(size=3)
    d_lab *= rng.uniform(0.01, 0.03) / np.linalg.norm(d_lab)  # of the field
    span = rec.t[-1] - rec.t[0]

    def inside(a: float, b: float) -> np.ndarray:
        return (rec.t >= rec.t[0] + a * span) & (rec.t < rec.t[0] + b * span)
    C = platform_attitude(rec.psi_t, rec.theta_t, rec.phi_t)
    lab_counts = np.einsum("nji,j->ni", C, d_lab) @ (unit.mag.k[:, None] * unit.mag.M_o).T
    mag = rec.mag + np.outer(inside(a0, a1), d_sensor) + lab_counts * inside(b0, b1)[:, None]
    out = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, mag, rec.acc, rec.temp_c, rec.meta)
    return out, {"sensor": (a0, a1), "lab": (b0, b1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=12)
    ap.add_argument("--seed", type=int, default=20, help="seed of the first case (then +1 per case)")
    args = ap.parse_args()
    ok = 0
    print(f"{'seed':>5} {'ok':>3}  findings (frame [window s])")
    for seed in range(args.seed, args.seed + args.cases):
        rec, truth = _case(seed)
        r = analyze(rec, null_sims=60).result
        got = [(f["model"]["frame"], f["model"]["segments"]) for f in r["findings"] if f["effect"] == "discovered"]
        span = rec.t[-1] - rec.t[0]

        def found(frame: str, a: float, b: float) -> bool:
            return any(fr == frame and len(sg) == 1 and abs(sg[0][0] - (rec.t[0] + a * span)) < 0.05 * span
                       and abs(sg[0][1] - (rec.t[0] + b * span)) < 0.05 * span for fr, sg in got)
        good = len(got) == 2 and all(found(frame, a, b) for frame, (a, b) in truth.items())
        ok += good
        said = ", ".join(f"{fr} {[[round(x, 1) for x in s] for s in sg]}" for fr, sg in got)
        print(f"{seed:>5} {'yes' if good else 'no':>3}  {said}")
    print(f"both windows in their frames, nothing invented: {ok}/{args.cases} = {100 * ok / args.cases:.0f} %")


if __name__ == "__main__":
    main()
