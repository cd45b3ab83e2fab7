"""The service's speed on SQLite and PostgreSQL.

- samples inserted per second (the engine's path: one bulk insert per acquisition of 60 rows x units);
  target above 50,000 on both databases;
- GET /devices/{serial}/calibrations with 10,000 calibrations stored, 50 concurrent clients on loopback
  against `compasscal serve` (p50, p99); target p99 under 50 ms;
- the overhead the service adds to a simulated calibration, against `compasscal calibrate`'s path
  (time scale 20, the same station).

Run: .venv/bin/python benchmarks/service.py [--skip-overhead]
"""

from __future__ import annotations

import argparse
import asyncio
import http.client
import multiprocessing as mp
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from conftest import fresh_database  # noqa: E402
from physics.fit import fit  # noqa: E402
from physics.recording import Recording  # noqa: E402
from physics.sensor import reference_unit  # noqa: E402
from physics.simulate import World, simulate_recording  # noqa: E402
from procedures.calibrate import CalibrateParams, calibration_poses  # noqa: E402


def fresh(kind: str, tmp: Path) -> str:
    """An empty database of ``kind`` (a new SQLite file each call; the PostgreSQL test database emptied)."""
    where = tmp / f"bench-{time.time_ns()}"
    where.mkdir()
    return fresh_database(kind, where)


def insert_rate(url: str, total: int = 120_000, chunk: int = 480) -> float:
    """Rows per second through store.insert_samples, one commit per acquisition-sized chunk."""
    from service.db import Run, make_engine, sessions, upgrade
    from service.store import insert_samples
    engine = make_engine(url)
    upgrade(engine)
    S = sessions(engine)
    n = chunk
    rng = np.random.default_rng(0)
    rec = Recording.from_arrays(t=np.arange(n) / 20.0, step=["rotate_z"] * n, psi_t=np.zeros(n), theta_t=np.zeros(n),
                                phi_t=np.zeros(n), mag=rng.normal(0, 3000, (n, 3)), acc=rng.normal(0, 16384, (n, 3)),
                                temp_c=np.full(n, 23.0))
    with S() as s:
        run = Run(procedure="bench", procedure_version="1", parameters={}, operator="bench", software_version="bench")
        s.add(run)
        s.commit()
        run_id = run.id
    t0 = time.perf_counter()
    done = 0
    while done < total:
        with S() as s:
            insert_samples(s, run_id, 0, rec)
            s.commit()
        done += n
    rate = done / (time.perf_counter() - t0)
    engine.dispose()
    return rate


def populate(url: str, calibrations: int = 10_000, devices: int = 200) -> tuple[list[str], str]:
    """10,000 calibrations over 200 devices; returns the serials and a viewer key."""
    from sqlalchemy import insert

    from service.auth import create_key
    from service.db import Calibration, Device, Run, make_engine, sessions, upgrade
    from service.store import figures
    engine = make_engine(url)
    upgrade(engine)
    rec = simulate_recording(reference_unit(3.0, 4.0), calibration_poses(CalibrateParams(samples=10)), World(),
                             rng=np.random.default_rng(1))
    cal = fit(rec, "joint").to_json()
    fig = figures(cal)
    serials = [f"SN-{i:05d}" for i in range(devices)]
    with sessions(engine)() as s:
        key = create_key(s, "bench", "viewer")
        s.execute(insert(Device), [{"serial": sn, "model": "XDC-3"} for sn in serials])
        run = Run(procedure="calibrate", procedure_version="2", parameters={}, operator="bench", software_version="bench")
        s.add(run)
        s.flush()
        ids = dict(s.query(Device.serial, Device.id).all())
        per = calibrations // devices
        rows = [{"device_id": ids[sn], "run_id": run.id, "slot": 0, "status": "superseded" if j < per - 1 else "current",
                 "verdict": "PASS", "reasons": [], "method": "joint", "data": cal, "figures": fig} for sn in serials for j in range(per)]
        for i in range(0, len(rows), 1000):
            s.execute(insert(Calibration), rows[i:i + 1000])
        s.commit()
    engine.dispose()
    return serials, key


def _client_process(port: int, key: str, paths: list[str], threads: int, per: int, seed: int, out: "mp.Queue[list[float]]") -> None:
    """One load-generator process: ``threads`` keep-alive clients, each sending ``per`` requests in turn."""
    times: list[float] = []
    lock = threading.Lock()

    def client(i: int) -> None:
        rnd = random.Random(seed * 1000 + i)
        conn = http.client.HTTPConnection("127.0.0.1", port)
        local = []
        for _ in range(per):
            t0 = time.perf_counter()
            conn.request("GET", rnd.choice(paths), headers={"X-API-Key": key})
            r = conn.getresponse()
            body = r.read()
            local.append(time.perf_counter() - t0)
            assert r.status == 200, body[:200]
        with lock:
            times.extend(local)
    th = [threading.Thread(target=client, args=(i,)) for i in range(threads)]
    for t in th:
        t.start()
    for t in th:
        t.join()
    out.put(times)


def query_load(port: int, key: str, paths: list[str], clients: int = 50, per_client: int = 60, processes: int = 5) -> list[float]:
    """Latencies of GETs of ``paths`` (chosen at random) from ``clients`` concurrent keep-alive clients,
    spread over several processes so that the load generator's own GIL does not queue the requests."""
    q: "mp.Queue[list[float]]" = mp.Queue()
    procs = [mp.Process(target=_client_process, args=(port, key, paths, clients // processes, per_client, i, q))
             for i in range(processes)]
    for p in procs:
        p.start()
    times = [t for _ in procs for t in q.get()]
    for p in procs:
        p.join()
    return sorted(times)


def serve(url: str, port: int) -> subprocess.Popen:
    env = {**os.environ, "COMPASSCAL_DATABASE_URL": url}
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import httpx
    for _ in range(200):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=0.5).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("the service did not start")


def overhead() -> tuple[float, float]:
    """Wall seconds of one calibration at time scale 20: direct (the CLI's path) and through the REST API."""
    from fastapi.testclient import TestClient

    from conftest import sim_station
    from drivers.sim.config import reference_config
    from drivers.station import open_station
    from procedures.engine import run_procedure
    from service.app import create_app
    from service.auth import create_key

    params = {"samples": 60}
    with sim_station(reference_config(seed=1, time_scale=20)) as info:
        async def direct() -> float:
            async with open_station(info["modbus"], [c["url"] for c in info["compasses"]], time_scale=20) as st:
                t0 = time.perf_counter()
                result, _, _ = await run_procedure(st, "calibrate", params)
                assert result.state.value == "completed", result.reason
                return time.perf_counter() - t0
        t_direct = asyncio.run(direct())
    with tempfile.TemporaryDirectory() as tmp, sim_station(reference_config(seed=1, time_scale=20)) as info:
        app = create_app(f"sqlite:///{tmp}/o.db")
        with TestClient(app) as client:
            with app.state.sessions() as s:
                h = {"X-API-Key": create_key(s, "bench", "admin")}
            client.post("/stations", headers=h, json={"name": "s", "modbus": info["modbus"],
                                                      "compasses": [c["url"] for c in info["compasses"]], "time_scale": 20})
            t0 = time.perf_counter()
            run = client.post("/runs", headers=h, json={"station": "s", "procedure": "calibrate", "parameters": params}).json()
            while client.get(f"/runs/{run['id']}", headers=h).json()["status"] in ("queued", "running"):
                time.sleep(0.05)
            t_api = time.perf_counter() - t0
    return t_direct, t_api


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-overhead", action="store_true")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("sqlite", "postgresql"):
            for chunk, what in ((480, "one commit per acquisition of 8 units x 60"), (4800, "commits of 4800 rows (an upload)")):
                rate = insert_rate(fresh(kind, Path(tmp)), chunk=chunk)
                rows.append((f"samples inserted per second, {kind}, {what}", f"{rate:,.0f}", "> 50,000",
                             "ok" if rate > 50_000 else "MISSED"))
        for kind, port in (("sqlite", 18765), ("postgresql", 18766)):
            url = fresh(kind, Path(tmp))
            serials, key = populate(url)
            proc = serve(url, port)
            try:
                t = query_load(port, key, [f"/devices/{sn}/calibrations" for sn in serials])
                floor = query_load(port, key, ["/health"])
            finally:
                proc.terminate()
                proc.wait(10)
            p50, p99 = 1e3 * t[len(t) // 2], 1e3 * t[int(0.99 * len(t))]
            rows.append((f"GET /devices/{{serial}}/calibrations, 10k stored, 50 clients ({kind}) p50", f"{p50:.1f} ms", "", ""))
            rows.append((f"GET /devices/{{serial}}/calibrations, 10k stored, 50 clients ({kind}) p99", f"{p99:.1f} ms",
                         "< 50 ms", "ok" if p99 < 50 else "MISSED"))
            rows.append((f"  the stack's floor: GET /health, same load ({kind}) p50 / p99",
                         f"{1e3 * floor[len(floor) // 2]:.0f} / {1e3 * floor[int(0.99 * len(floor))]:.0f} ms", "", ""))
    if not args.skip_overhead:
        direct, via_api = overhead()
        rows.append(("calibration at time scale 20, direct (compasscal calibrate's path)", f"{direct:.2f} s", "", ""))
        rows.append(("the same through the REST API (SQLite)", f"{via_api:.2f} s", "",
                     f"overhead {via_api - direct:+.2f} s ({100 * (via_api / direct - 1):+.0f} %)"))
    w = max(len(r[0]) for r in rows)
    print(f"{'measure':<{w}}  {'value':>12}  {'target':>9}  verdict")
    for name, value, target, verdict in rows:
        print(f"{name:<{w}}  {value:>12}  {target:>9}  {verdict}")


if __name__ == "__main__":
    main()
