"""Accuracy and cost of every calibration method on the same simulated recordings.

For the paper's reference unit and for N random production units (3 LSB magnetometer noise, base
tilt up to 0.1 deg, I in 40-70 deg), each method calibrates from the same recording and is scored
against the true unit: max and RMS heading error over a level turn, max over pitch and roll up to
+-60 deg, table positions and seconds (30 deg/s, 60 deg/s^2, 0.3 s settle, 20 Hz), fit time.
Peak-picking is also given a fine 5-deg recording, since on coarse sweeps it cannot work at all.

    python benchmarks/accuracy.py [--units 50] [--seed 1]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from physics.calibration import truth_summary
from physics.errorsep import InsufficientData
from physics.fit import METHODS, fit
from physics.sensor import Unit, random_unit, reference_unit
from physics.simulate import World, plan_cost, simulate_recording
from physics.table import TableGeometry
from procedures.calibrate import CalibrateParams, calibration_poses

TARGET_LEVEL, TARGET_TILTED, TARGET_TABLE_S = 0.02, 0.05, 120.0
RECORDINGS = {"default": CalibrateParams(), "fine 5 deg": CalibrateParams(z_step_deg=5.0, tilt_step_deg=5.0, samples=10)}


def runs() -> list[tuple[str, str]]:
    """(method, recording) pairs to score."""
    return [(m, "default") for m in METHODS] + [("peak-picking", "fine 5 deg")]


def score(units: list[tuple[Unit, World]], seed: int) -> dict[tuple[str, str], dict[str, list[float]]]:
    """Heading-error figures per (method, recording) over all units."""
    out: dict[tuple[str, str], dict[str, list[float]]] = {r: {} for r in runs()}
    for n, (unit, world) in enumerate(units):
        recs = {name: simulate_recording(unit, calibration_poses(p), world, rng=np.random.default_rng(seed + n))
                for name, p in RECORDINGS.items()}
        for method, rec_name in runs():
            t0 = time.perf_counter()
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    cal = fit(recs[rec_name], method, bootstrap=0)
            except (InsufficientData, ValueError):
                figures = {"level_max": np.nan, "level_rms": np.nan, "tilted_max": np.nan, "tilted_rms": np.nan}
            else:
                figures = truth_summary(cal, unit, world)
            figures["fit_s"] = time.perf_counter() - t0
            for k, v in figures.items():
                out[(method, rec_name)].setdefault(k, []).append(v)
    return out


def table(title: str, results: dict[tuple[str, str], dict[str, list[float]]], many: bool) -> str:
    """The printed table; with many units, median and worst case of each figure."""
    head = f"{'method':<17}{'recording':<12}{'poses':>6}{'table s':>9}"
    if many:
        head += f"{'level max med/worst':>22}{'level rms med':>15}{'+-60 max med/worst':>22}{'fit s':>8}"
    else:
        head += f"{'level max':>11}{'level rms':>11}{'+-60 max':>10}{'fit s':>8}"
    lines = [title, head, "-" * len(head)]
    for (method, rec_name), r in results.items():
        cost = plan_cost(calibration_poses(RECORDINGS[rec_name]))
        lm, lr, tm = (np.array(r[k]) for k in ("level_max", "level_rms", "tilted_max"))
        row = f"{method:<17}{rec_name:<12}{cost.positions:>6}{cost.total_s:>9.1f}"
        if many:
            row += f"{np.nanmedian(lm):>12.4f} /{np.nanmax(lm):>8.4f}{np.nanmedian(lr):>15.4f}"
            row += f"{np.nanmedian(tm):>12.4f} /{np.nanmax(tm):>8.4f}{np.mean(r['fit_s']):>8.2f}"
            failed = int(np.isnan(lm).sum())
            if failed:
                row += f"  ({failed} refused)"
        else:
            row += f"{lm[0]:>11.4f}{lr[0]:>11.4f}{tm[0]:>10.4f}{r['fit_s'][0]:>8.2f}"
        lines.append(row)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    ref = [(reference_unit(3.0, 4.0), World(55.0, 23.0, TableGeometry(base_tilt_deg=(0.05, -0.03))))]
    randoms = [(random_unit(rng, mag_noise_lsb=3.0),
                World(rng.uniform(40, 70), rng.uniform(0, 360), TableGeometry(base_tilt_deg=tuple(rng.uniform(-0.1, 0.1, 2)))))
               for _ in range(args.units)]
    r_ref = score(ref, args.seed)
    print(table("Reference unit (Gao et al. 2017, Tables 1-2), 3 LSB noise; heading errors in deg", r_ref, many=False))
    print()
    r_rand = score(randoms, args.seed + 1000)
    print(table(f"{args.units} random production units, 3 LSB noise; heading errors in deg", r_rand, many=True))
    print()
    ours = r_rand[("joint", "default")]
    cost = plan_cost(calibration_poses(RECORDINGS["default"]))
    ok_ref = r_ref[("joint", "default")]
    print(f"target (joint): level max <= {TARGET_LEVEL} deg, +-60 max <= {TARGET_TILTED} deg, table time <= {TARGET_TABLE_S:.0f} s")
    print(f"  reference unit: level {ok_ref['level_max'][0]:.4f}, +-60 {ok_ref['tilted_max'][0]:.4f}, table {cost.total_s:.1f} s")
    within = np.mean((np.array(ours["level_max"]) <= TARGET_LEVEL) & (np.array(ours["tilted_max"]) <= TARGET_TILTED))
    print(f"  random units meeting both: {100 * within:.0f} %; the paper measured 0.22 deg level and 0.4 deg at +-60 deg")


if __name__ == "__main__":
    main()
