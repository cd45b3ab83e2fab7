"""The calibration procedure end to end against the simulated station, over the real protocols.

Per configuration: table seconds (simulated) and wall seconds per calibration run, and the heading
error achieved, scored against the simulator's true units (max level, max over pitch and roll up to
+-60 deg; the worst unit of the fixture). Beside it, the paper's method as published (peak-picking on
5-degree sweeps). Realistic station: 30 deg/s, 60 deg/s^2, drive settle, 20 Hz, 3 LSB noise, base tilt
0.05/-0.03 deg.

Targets (issue 4): <= 0.02 deg level and <= 0.05 deg at +-60 deg within 2 minutes of table time,
whatever the number of units; under 20 s of wall time at time scale 20. Issue 14: the table time
within 5 % of the plan's nominal seconds at any time scale ("vs plan"); 8 units at time scale 20 run
once with the simulator in this process (as `compasscal demo`) and once in its own (as `compasscal sim`
beside `compasscal calibrate`).

Load and time scale (issue 14): the same plan idle at time scale 2, idle at 20 and at 20 with every
core taken by a busy loop, over several seeds: table time within 5 % of the idle time-scale-2 figure,
and the level error's spread the same in every condition.
Run: .venv/bin/python benchmarks/procedure.py [--quick]   (--quick skips time scales 1 and 2)
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.sim.config import StationConfig, parse_config, reference_config  # noqa: E402
from drivers.sim.station import SimStation  # noqa: E402
from drivers.station import open_station  # noqa: E402
from physics.calibration import truth_summary  # noqa: E402
from physics.sensor import angles_to_Mo  # noqa: E402
from physics.simulate import truth_from_json  # noqa: E402
from drivers import Station, keep_drivers_responsive  # noqa: E402
from physics.table import Motion  # noqa: E402
from procedures.calibrate import PROCEDURES  # noqa: E402
from procedures.engine import run_procedure  # noqa: E402
from procedures.steps import step_seconds  # noqa: E402


def fixture(units: int, time_scale: float, seed: int = 1) -> StationConfig:
    """The reference unit in slot 0 and production-like units (reference-like sensitivities, other
    misalignments and biases) in the other slots."""
    cfg = reference_config(seed=seed, time_scale=time_scale).model_dump()
    rng = np.random.default_rng(seed)
    for i in range(1, units):
        angles = np.eye(3) * 0 + np.array([[0, 90, 90], [90, 0, 90], [90, 90, 0]]) + rng.uniform(-2.5, 2.5, (3, 3))
        cfg["unit"].append({"serial": f"SN-{i:04d}", "mag_M_o": angles_to_Mo(angles).tolist(),
                            "mag_k": rng.uniform(3000, 3400, 3).tolist(), "mag_bias": rng.uniform(-600, 600, 3).tolist(),
                            "mag_noise_lsb": 3.0, "acc_noise_lsb": 4.0, "transport": "tcp" if i % 2 else "pty"})
    return parse_config(cfg)


async def one(cfg: StationConfig, params: dict) -> dict[str, float]:
    """One calibration run with the simulated station in this process (as `compasscal demo` has it)."""
    async with SimStation(cfg, control_port=None) as st:
        return await _calibrate(st.describe(), st.truth(), cfg.world.time_scale, params)


async def apart(units: int, scale: float, params: dict) -> dict[str, float]:
    """One calibration run with the simulated station in a process of its own (as `compasscal sim` beside
    `compasscal calibrate`)."""
    proc = subprocess.Popen([sys.executable, __file__, "--serve-sim", str(units), str(scale)], stdout=subprocess.PIPE, text=True)
    try:
        line = await asyncio.to_thread(proc.stdout.readline)  # type: ignore[union-attr]
        served = json.loads(line)
        return await _calibrate(served["station"], served["truth"], scale, params)
    finally:
        proc.kill()
        proc.wait()


async def _calibrate(station_urls: dict, truth: list, scale: float, params: dict) -> dict[str, float]:
    async with open_station(station_urls["modbus"], [c["url"] for c in station_urls["compasses"]], time_scale=scale) as station:
        t0 = time.monotonic()
        result, serials, _ = await run_procedure(station, "calibrate", params)
        wall = time.monotonic() - t0
    if result.outcome is None:
        raise RuntimeError(f"run {result.state.value}: {result.reason}")
    level, tilted = [], []
    for slot, r in result.outcome.results.items():
        unit, world = truth_from_json(truth[slot])
        s = truth_summary(r["calibration"], unit, world)
        level.append(s["level_max"])
        tilted.append(s["tilted_max"])
    return {"table_s": result.table_seconds, "wall_s": wall, "level": max(level), "tilted": max(tilted)}


def serve_sim(units: int, scale: float) -> None:
    """The simulated station of :func:`fixture` until killed; first prints its URLs and truth (JSON)."""
    async def serve() -> None:
        async with SimStation(fixture(units, scale), control_port=None) as st:
            print(json.dumps({"station": st.describe(), "truth": st.truth()}), flush=True)
            await asyncio.Event().wait()
    asyncio.run(serve())


def plan_seconds(params: dict) -> float:
    """The plan's nominal table seconds on the fixture's station (30 deg/s, 60 deg/s^2, the servo's
    settling, 20 Hz), from home: the engine's `step_seconds`, as a run's ``plan_seconds`` says."""
    proc = PROCEDURES["calibrate"]
    plan = proc.plan(proc.validate(params))
    return sum(step_seconds(plan, Motion(30.0, 60.0, Station.settle_s, 20.0)))


@contextmanager
def busy(processes: int):
    """``processes`` busy loops beside the run: a machine whose cores are taken by other work."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(processes)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def load_and_scale(seeds: list[int], slow: bool) -> None:
    """The reference unit on the same plan idle and loaded at time scale 20 (and idle at 2 unless
    --quick): table time and level heading error per condition over several simulator seeds (one
    seed's error is one noise realisation; which samples a pose gets shifts with timing, so compare
    the spreads, not one run with another)."""
    conditions = [("idle", 20.0, 0), (f"loaded ({os.cpu_count()} busy processes)", 20.0, os.cpu_count() or 2)]
    if slow:
        conditions.insert(0, ("idle", 2.0, 0))
    print(f"\nLoad and time scale: the reference unit, default plan, seeds {seeds[0]}-{seeds[-1]}")
    print(f"{'machine':<28} {'scale':>5} {'table s median (range)':>24} {'level median (range)':>26}")
    base = None
    for name, scale, procs in conditions:
        table, level = [], []
        with busy(procs):
            for seed in seeds:
                r = asyncio.run(one(fixture(1, scale, seed=seed), {}))
                table.append(r["table_s"])
                level.append(r["level"])
        med = float(np.median(table))
        base = base or med
        verdict = "meets target" if med <= 1.05 * base else "misses target"
        print(f"{name:<28} {scale:>5g} {med:>8.1f} ({min(table):.1f}-{max(table):.1f}) {100 * (med / base - 1):+5.1f} %"
              f" {np.median(level):>10.4f} ({min(level):.4f}-{max(level):.4f})  {verdict}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the runs at time scale 1 (they take 2 minutes each)")
    ap.add_argument("--load-seeds", type=int, default=4, help="simulator seeds of each load and time-scale condition")
    ap.add_argument("--serve-sim", nargs=2, type=float, metavar=("UNITS", "SCALE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve_sim:
        serve_sim(int(args.serve_sim[0]), args.serve_sim[1])
        return
    keep_drivers_responsive()  # as every command-line entry point
    published = {"method": "peak-picking", "z_step_deg": 5.0, "tilt_step_deg": 5.0, "samples": 10}
    default = "joint (default plan)"
    runs = [(default, {}, 1, 20.0, False), (default, {}, 8, 20.0, False), (default, {}, 8, 20.0, True),
            ("paper as published: peak-picking, 5 deg", published, 1, 20.0, False)]
    if not args.quick:
        runs[:0] = [(default, {}, 1, 1.0, False), (default, {}, 8, 1.0, False)]
    print(f"{'procedure':<42} {'units':>5} {'scale':>5} {'simulator':>12} {'table s':>8} {'vs plan':>8} {'wall s':>7} "
          f"{'level max':>10} {'+-60 max':>9}  verdict")
    for name, params, units, scale, separate in runs:
        r = asyncio.run(apart(units, scale, params) if separate else one(fixture(units, scale), params))
        plan = plan_seconds(params)
        # table time within 5 % of the plan's nominal seconds whatever the time scale (issue 14); the wall
        # time under 20 s at time scale 20 (issue 4)
        ok = (r["level"] <= 0.02 and r["tilted"] <= 0.05 and r["table_s"] <= 1.05 * plan
              and (scale == 1 or r["wall_s"] < 20))
        print(f"{name:<42} {units:>5} {scale:>5g} {'own process' if separate else 'in process':>12} {r['table_s']:>8.1f} "
              f"{100 * (r['table_s'] / plan - 1):>+7.1f}% {r['wall_s']:>7.1f} {r['level']:>10.4f} {r['tilted']:>9.4f}  "
              f"{'meets target' if ok else 'misses target'}")
    load_and_scale(list(range(1, args.load_seeds + 1)), slow=not args.quick)
    # the simulator alone, as the blind proof's generator uses it: a 10-minute plan in under a second
    from physics.effects import Hysteresis, StageHardIron
    from physics.sensor import random_unit
    from physics.simulate import Motion, Noise, World, simulate_timeline
    from procedures.calibrate import characterize_plan

    t0 = time.perf_counter()
    simulate_timeline(random_unit(np.random.default_rng(1)), characterize_plan(), World(), Motion(),
                      [StageHardIron("outer", [0.01, 0.0, 0.02]), Hysteresis([0.002, 0.001, 0.0])], Noise(3.0, 0.7),
                      np.random.default_rng(0))
    dt = time.perf_counter() - t0
    print(f"\nsimulate_timeline, the characterize plan (about 10 min at 20 Hz): {dt:.2f} s wall (target < 1 s)  "
          f"{'meets target' if dt < 1.0 else 'misses target'}")


if __name__ == "__main__":
    main()
