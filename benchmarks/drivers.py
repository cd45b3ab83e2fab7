"""Driver speed on loopback: Modbus status poll round trip, a 90 deg move with its settle detection,
compass sentences parsed per second, and compass samples delivered per second over a pty and TCP;
and the status read of three axes while two threads of the same process compute (as a fit does
beside a run), at Python's default thread switch interval and at the drivers' (1 ms).

Targets (issue 3): a poll under 2 ms median; parsing above 100,000 sentences per second. Beside
CPU-bound threads, the worst status read well inside the driver's 0.4 s timeout.
Run: .venv/bin/python benchmarks/drivers.py
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers import SWITCH_INTERVAL_S  # noqa: E402
from drivers.compass import Compass, SentenceParser  # noqa: E402
from drivers.protocol import sentence  # noqa: E402
from drivers.sim.clock import SimClock  # noqa: E402
from drivers.sim.compass import CompassSim  # noqa: E402
from drivers.sim.turntable import TableSim  # noqa: E402
from drivers.turntable import Turntable, trapezoid_time  # noqa: E402


async def modbus(framer: str) -> dict[str, float]:
    """Median poll round trip and a 90 deg move at 30 deg/s, 60 deg/s^2 (time scale 1)."""
    clock = SimClock(1.0)
    sim = TableSim(clock, homed=True, enabled=True)
    await sim.start(0, framer=framer)
    table = Turntable(sim.url())
    try:
        await table.connect()
        axis = table.axes["z"]
        for _ in range(20):
            await axis.status()
        rtt = []
        for _ in range(500):
            t0 = time.perf_counter()
            await axis.status()
            rtt.append(time.perf_counter() - t0)
        t0, s0 = time.perf_counter(), clock.now()
        await table.move_to(90.0, 0.0, 0.0, speed_dps=30, accel_dps2=60)
        wall, sim_s = time.perf_counter() - t0, clock.now() - s0
    finally:
        await table.close()
        await sim.stop()
    rtt.sort()
    return {"poll_median_ms": 1e3 * statistics.median(rtt), "poll_p99_ms": 1e3 * rtt[int(0.99 * len(rtt))],
            "move_wall_s": wall, "move_sim_s": sim_s, "profile_s": trapezoid_time(90.0, 30.0, 60.0)}


def parse_rate(n: int = 200_000) -> float:
    """RAW sentences parsed per second (CPU time), fed in 4 KiB chunks."""
    data = b"".join(sentence("RAW", i % 65536, 2154 + i % 7, -180, 2918, 12, -7, 16388, 231, 0) for i in range(n))
    chunks = [data[i:i + 4096] for i in range(0, len(data), 4096)]
    parser = SentenceParser()
    t0 = time.process_time()
    count = sum(len(parser.feed(c)) for c in chunks)
    dt = time.process_time() - t0
    assert count == n and parser.stats.samples == n, (count, parser.stats.as_dict())
    return n / dt


async def stream_rate(transport: str, rate_hz: int = 100, time_scale: float = 20.0, seconds: float = 2.0) -> tuple[float, int]:
    """Samples per wall second delivered by the driver from a simulated compass, and any lost."""
    clock = SimClock(time_scale)
    sim = CompassSim(lambda t: ([2154, 180, 2918], [0, 0, 16384], 23.0), clock, serial="BENCH")
    url = await sim.start(transport)
    try:
        async with Compass(url) as c:
            await c.set_rate(rate_hz)
            await c.read(10, timeout=2.0)
            n = int(rate_hz * time_scale * seconds)
            t0 = time.perf_counter()
            got = await c.read(n, timeout=seconds * 3)
            return len(got) / (time.perf_counter() - t0), c.stats.dropped_samples
    finally:
        await sim.stop()


def beside_busy_threads(interval_s: float, reads: int = 300) -> tuple[float, float]:
    """Median and worst wall time (ms) of a three-axis status read from a simulated table served by
    another thread's event loop, while two more threads run Python code, at thread switch interval
    ``interval_s``."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    stop = threading.Event()
    ready = threading.Event()
    url: list[str] = []

    def serve() -> None:
        async def main() -> None:
            sim = TableSim(SimClock(1.0), homed=True, enabled=True)
            await sim.start(0)
            url.append(sim.url())
            ready.set()
            while not stop.is_set():
                await asyncio.sleep(0.05)
            await sim.stop()
        asyncio.run(main())

    def compute() -> None:
        x = 0
        while not stop.is_set():
            for i in range(1000):
                x += i * i

    async def probe() -> list[float]:
        table = Turntable(url[0])
        await table.connect()
        out = []
        try:
            for _ in range(reads):
                t0 = time.perf_counter()
                await table.status_all()
                out.append(time.perf_counter() - t0)
                await asyncio.sleep(0.002)
        finally:
            await table.close()
        return out

    threads = [threading.Thread(target=serve, daemon=True)] + [threading.Thread(target=compute, daemon=True) for _ in range(2)]
    threads[0].start()
    ready.wait(10)
    for t in threads[1:]:
        t.start()
    try:
        lat = asyncio.run(probe())
    finally:
        stop.set()
        for t in threads:
            t.join(5)
        sys.setswitchinterval(before)
    return 1e3 * statistics.median(lat), 1e3 * max(lat)


def main() -> None:
    rows = []
    for framer in ("tcp", "rtu"):
        m = asyncio.run(modbus(framer))
        rows.append((f"Modbus {framer.upper()} status poll, median", f"{m['poll_median_ms']:.2f} ms", "< 2 ms",
                     "ok" if m["poll_median_ms"] < 2 else "MISSED"))
        rows.append((f"Modbus {framer.upper()} status poll, 99th percentile", f"{m['poll_p99_ms']:.2f} ms", "", ""))
        rows.append((f"90 deg move incl. settle detection ({framer})", f"{m['move_wall_s']:.2f} s wall",
                     f"profile {m['profile_s']:.2f} s", f"+{m['move_sim_s'] - m['profile_s']:.2f} s settle"))
    rate = parse_rate()
    rows.append(("compass RAW sentences parsed per CPU second", f"{rate:,.0f}", "> 100,000", "ok" if rate > 100_000 else "MISSED"))
    for transport in ("pty", "tcp"):
        r, lost = asyncio.run(stream_rate(transport))
        rows.append((f"compass samples delivered per second ({transport}, 100 Hz x20)", f"{r:,.0f}", "", f"{lost} lost"))
    for interval in (0.005, SWITCH_INTERVAL_S):
        med, worst = beside_busy_threads(interval)
        rows.append((f"3-axis status read beside 2 busy threads, switch {interval * 1e3:g} ms", f"{med:.0f} / {worst:.0f} ms",
                     "worst < 400 ms", "ok" if worst < 400 else "MISSED"))
    w = max(len(r[0]) for r in rows)
    print(f"{'measure':<{w}}  {'value':>16}  {'target':>16}  verdict")
    for name, value, target, verdict in rows:
        print(f"{name:<{w}}  {value:>16}  {target:>16}  {verdict}")


if __name__ == "__main__":
    main()
