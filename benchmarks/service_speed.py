"""The service's speed on SQLite and PostgreSQL, and the targets of issue 13 (stations as workers).

Parts (all by default; ``--only PART`` runs one), each printed as a table, then every target with
ok or MISSED:

- ``insert``: samples inserted per second through store.insert_samples (one commit per acquisition of
  8 units x 60 rows, and commits of 4800 rows), SQLite and PostgreSQL. Target > 50,000.
- ``history``: ``GET /devices/{serial}/calibrations`` with 10,000 calibrations over 200 devices,
  50 concurrent keep-alive clients on loopback (5 load processes x 10 threads, all starting at
  once), p50 and p99; then under the same load and process count ``GET /health`` (the stack's floor),
  in alternating rounds. SQLite: one ``compasscal serve`` process (target p99 < 50 ms, as before).
  PostgreSQL: 1, 2 and 4 API processes (``serve --no-station-worker``, ``serve --workers 2``, ``4``).
  Target: p99 history / p99 health <= 1.5 at each count. Also shown: the same with each client's
  first request left out ("steady": its connection's set-up while 50 clients start at once) and
  those first requests alone, since they make most of the history's tail.
- ``overhead``: one simulated calibration (time scale 20, 60 samples per pose) directly
  (``compasscal calibrate``'s path) and through the REST API on SQLite. ``--skip-overhead`` leaves it out.
- ``stations``: K = 1, 2 and 8 simulated stations (``sim_station(reference_config(seed=i,
  time_scale=20))``, threads of this process) calibrating at once on one PostgreSQL, one API process
  (``serve --no-station-worker``) and one ``compasscal worker --station NAME --no-analyses`` process
  per station; one ``calibrate`` run (20 samples per pose, 18 poses) per station, all posted at once.
  Reported: runs completed (a failed run is listed with its reason), wall time (first run created
  to last run finished, the database's clock), samples stored per second (their samples_count over
  the wall time), the table seconds (simulated: they inflate when the machine cannot keep up), the
  machine's CPU use and the CPU seconds of the simulated stations and of the workers, "overloaded"
  when the machine is, and each unit's accuracy: the stored calibration's heading error
  (``GET /runs/{id}`` -> result.units["0"].heading_error_deg: "full" level, "tilted_full" up to
  +-60 deg). Every station carries the same reference unit (the seed changes only the noise), so
  medians across stations compare; a unit's error moves from run to run with its noise draws,
  so after the largest K its stations calibrate once more one at a time, the baseline. Shown: the
  median against K=1 (a single run) and against that baseline. Targets: every run completed;
  median(K) / median(one at a time) <= 1.5 for K = 2 and 8 (accuracy unchanged).
- ``notify``: latency from a worker's event to a server-sent-events client through PostgreSQL's
  LISTEN/NOTIFY: one API process (``serve --no-station-worker``), a ``running`` run made directly in
  the database, ``GET /runs/{id}/events`` streamed by an httpx client thread, and a separate process
  (as a worker) publishing 300 ``progress`` events with ``service.runtime.publish`` + commit, each its
  own transaction, 20 ms apart, each carrying ``time.time()``; then the run's ``completed`` state,
  which ends the stream. Receipt time minus that: p50, p99, max. Target p99 < 100 ms.

Databases: PostgreSQL is the machine's server at 127.0.0.1:5432 (user postgres), database
``compasscal_bench`` (created through the ``postgres`` database when missing; its schema public is
dropped and made again before each part), never the tests' ``test``. SQLite is a temporary file.
Every process the benchmark starts has a process group of its own and is stopped at the end of its
part, also on errors, Ctrl-C and SIGTERM.

Run (on a quiet machine: the figures are latencies on 2 shared cores):

    .venv/bin/python benchmarks/service_speed.py [--skip-overhead] [--only insert|history|overhead|stations|notify]
    .venv/bin/python benchmarks/service_speed.py --quick      # a fast check (~1.5 min): 24,000 rows per
                                                        # insert figure, 1,000 requests per latency
                                                        # figure, K in (1, 2), 100 events

The full run sends 3,000 requests per latency figure and takes a few minutes more (K = 8 most).
"""

from __future__ import annotations

import argparse
import asyncio
import http.client
import json
import multiprocessing as mp
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from physics.fit import fit  # noqa: E402
from physics.recording import Recording  # noqa: E402
from physics.sensor import reference_unit  # noqa: E402
from physics.simulate import World, simulate_recording  # noqa: E402
from procedures.calibrate import CalibrateParams, calibration_poses  # noqa: E402

#: The benchmark's own PostgreSQL database (never the tests' ``test``).
BENCH_DB = "compasscal_bench"
PG_URL = f"postgresql://postgres@127.0.0.1:5432/{BENCH_DB}"
TIME_SCALE = 20
ACTIVE = ("queued", "running", "paused")

#: Every process this benchmark started (each the leader of its own process group).
CHILDREN: list[subprocess.Popen[bytes]] = []
#: (measure, value, target, verdict) of every target, printed at the end.
TARGETS: list[tuple[str, str, str, str]] = []


# ----------------------------------------------------------------------------------- databases

def _pg_up() -> bool:
    import psycopg
    try:
        psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=postgres", connect_timeout=3).close()
        return True
    except psycopg.OperationalError:
        return False


def bench_postgres() -> str:
    """The benchmark's database, emptied: ``compasscal_bench`` created when missing (through the
    ``postgres`` database), its schema public dropped and made again. Starts the machine's
    PostgreSQL when it is not running (as the tests' set-up does)."""
    import psycopg
    if not _pg_up():
        clusters = sorted(p.name for p in Path("/etc/postgresql").iterdir()) if Path("/etc/postgresql").exists() else []
        if clusters:
            subprocess.run(["pg_ctlcluster", "--skip-systemctl-redirect", clusters[-1], "main", "start"], check=False,
                           capture_output=True, timeout=60)
    if not _pg_up():
        raise RuntimeError("PostgreSQL at 127.0.0.1:5432 is not running and could not be started")
    with psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=postgres", autocommit=True) as conn:
        if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (BENCH_DB,)).fetchone() is None:
            conn.execute(f"CREATE DATABASE {BENCH_DB}")
    with psycopg.connect(f"host=127.0.0.1 port=5432 user=postgres dbname={BENCH_DB}", autocommit=True) as conn:
        conn.execute("DROP SCHEMA IF EXISTS public CASCADE")
        conn.execute("CREATE SCHEMA public")
    return PG_URL


def fresh(kind: str, tmp: Path) -> str:
    """An empty database of ``kind``: a new SQLite file each call, or the benchmark's PostgreSQL
    database emptied."""
    if kind == "postgresql":
        return bench_postgres()
    where = tmp / f"bench-{time.time_ns()}"
    where.mkdir()
    return f"sqlite:///{where / 'compasscal.db'}"


def keys(url: str) -> dict[str, str]:
    """One API key per role, made directly in the database."""
    from service.auth import create_key
    from service.db import make_engine, sessions, upgrade
    engine = make_engine(url)
    upgrade(engine)
    with sessions(engine)() as s:
        out = {role: create_key(s, f"bench-{role}", role) for role in ("viewer", "operator", "admin")}
    engine.dispose()
    return out


# ----------------------------------------------------------------------------------- processes

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args: list[str], url: str, log: Path) -> subprocess.Popen[bytes]:
    """``python -m service.cli ARGS`` on ``url``, in a process group of its own (so that stopping it
    also stops the API processes ``serve --workers N`` spawns), output to ``log``."""
    env = {**os.environ, "COMPASSCAL_DATABASE_URL": url}
    with log.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
    CHILDREN.append(proc)
    return proc


def stop(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the process's group, SIGKILL after 10 s."""
    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(wait)
            try:  # the leader is gone; its group (uvicorn's spawned processes) too?
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.5)
        except subprocess.TimeoutExpired:
            continue
    if proc in CHILDREN:
        CHILDREN.remove(proc)


def stop_all() -> None:
    for proc in list(CHILDREN):
        stop(proc)


def tail(log: Path, n: int = 2000) -> str:
    try:
        return log.read_text(errors="replace")[-n:]
    except OSError:
        return ""


def serve(url: str, log: Path, workers: int = 1, station_worker: bool | None = None) -> tuple[subprocess.Popen[bytes], int]:
    """``compasscal serve`` on a free port; returns once every one of its ``workers`` API processes
    has started (uvicorn's "Application startup complete" per process) and /health answers."""
    import httpx
    port = free_port()
    args = ["serve", "--port", str(port)]
    if workers > 1:
        args += ["--workers", str(workers)]
    elif station_worker is False:
        args.append("--no-station-worker")
    proc = start(args, url, log)
    deadline = time.monotonic() + 120
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"compasscal {' '.join(args)} exited:\n{tail(log)}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"compasscal {' '.join(args)} did not start in 120 s:\n{tail(log)}")
        if tail(log, 1_000_000).count("Application startup complete") >= workers:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                    return proc, port
            except httpx.HTTPError:
                pass
        time.sleep(0.2)


def cpu_ticks(pid: int) -> int:
    """utime + stime of one process, in clock ticks (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, IndexError, ValueError):
        return 0


def machine_ticks() -> tuple[int, int]:
    """(busy, total) clock ticks of all CPUs since boot."""
    v = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = v[3] + v[4]  # idle + iowait
    return sum(v) - idle, sum(v)


# ------------------------------------------------------------------------------------- inserts

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


def part_insert(tmp: Path, quick: bool) -> None:
    total = 24_000 if quick else 120_000
    rows = []
    for kind in ("sqlite", "postgresql"):
        for chunk, what in ((480, "one commit per acquisition of 8 units x 60"), (4800, "commits of 4800 rows (an upload)")):
            rate = insert_rate(fresh(kind, tmp), total=total, chunk=chunk)
            verdict = "ok" if rate > 50_000 else "MISSED"
            rows.append((kind, what, f"{rate:,.0f}", "> 50,000", verdict))
            TARGETS.append((f"samples inserted per second, {kind}, {what}", f"{rate:,.0f}", "> 50,000", verdict))
    table("Samples inserted per second", ("database", "how", "rows/s", "target", "verdict"), rows)


# ------------------------------------------------------------------------------------- history

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


def _client_process(port: int, key: str, paths: list[str], threads: int, per: int, seed: int, out: "mp.Queue[Any]") -> None:
    """One load-generator process: ``threads`` keep-alive clients, each sending ``per`` requests in turn."""
    times: list[tuple[int, float]] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(i: int) -> None:
        rnd = random.Random(seed * 1000 + i)
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
        local = []
        try:
            for j in range(per):
                t0 = time.perf_counter()
                conn.request("GET", rnd.choice(paths), headers={"X-API-Key": key})
                r = conn.getresponse()
                body = r.read()
                local.append((j, time.perf_counter() - t0))
                if r.status != 200:
                    raise RuntimeError(f"HTTP {r.status}: {body[:200]!r}")
        except Exception as e:  # noqa: BLE001 - reported to the parent
            with lock:
                errors.append(repr(e))
        with lock:
            times.extend(local)
    th = [threading.Thread(target=client, args=(i,)) for i in range(threads)]
    for t in th:
        t.start()
    for t in th:
        t.join()
    out.put((times, errors))


def query_load(port: int, key: str, paths: list[str], clients: int = 50, per_client: int = 60, processes: int = 5
               ) -> list[tuple[int, float]]:
    """Latencies of GETs of ``paths`` (chosen at random) from ``clients`` concurrent keep-alive clients,
    spread over several processes so that the load generator's own GIL does not queue the requests;
    as (the request's number on its client's connection, seconds)."""
    q: "mp.Queue[Any]" = mp.Queue()
    procs = [mp.Process(target=_client_process, args=(port, key, paths, clients // processes, per_client, i, q), daemon=True)
             for i in range(processes)]
    for p in procs:
        p.start()
    times: list[tuple[int, float]] = []
    errors: list[str] = []
    try:
        for _ in procs:
            t, e = q.get(timeout=900)
            times += t
            errors += e
    finally:
        for p in procs:
            p.join(10)
            if p.is_alive():
                p.kill()
    if errors:
        raise RuntimeError(f"{len(errors)} load clients failed, e.g. {errors[0]}")
    return times


def pct(t: list[float], q: float) -> float:
    """The q-quantile of sorted seconds, in ms."""
    return 1e3 * t[min(len(t) - 1, int(q * len(t)))]


def part_history(tmp: Path, quick: bool) -> None:
    rounds, per_client = (1, 20) if quick else (3, 20)  # 1,000 or 3,000 requests of each
    rows = []
    for kind, counts in (("sqlite", (1,)), ("postgresql", (1, 2, 4))):
        url = fresh(kind, tmp)
        serials, key = populate(url)
        paths = [f"/devices/{sn}/calibrations" for sn in serials]
        for n in counts:
            log = tmp / f"serve-{kind}-{n}.log"
            proc, port = serve(url, log, workers=n, station_worker=None if kind == "sqlite" else False)
            try:
                query_load(port, key, paths, per_client=2)  # warm-up: connections, pools, compiled queries
                t, floor = [], []
                for _ in range(rounds):  # alternated, so that a disturbance of the machine falls on both
                    t += query_load(port, key, paths, per_client=per_client)
                    floor += query_load(port, key, ["/health"], per_client=per_client)
            finally:
                stop(proc)
            # apart: each client's first request (its connection's set-up, the 50 clients starting at
            # the same instant), so that the steady state's tail shows too
            first = sorted(d for j, d in t if j == 0)
            t_on, f_on = sorted(d for j, d in t if j > 0), sorted(d for j, d in floor if j > 0)
            t, floor = sorted(d for _, d in t), sorted(d for _, d in floor)
            h50, h99, f50, f99 = pct(t, .5), pct(t, .99), pct(floor, .5), pct(floor, .99)
            ratio, steady = h99 / f99, pct(t_on, .99) / pct(f_on, .99)
            rows.append((kind, str(n), f"{h50:.1f}", f"{h99:.1f}", f"{f50:.1f}", f"{f99:.1f}", f"{ratio:.2f}",
                         "ok" if ratio <= 1.5 else "MISSED", f"{pct(t_on, .99):.1f}", f"{pct(f_on, .99):.1f}", f"{steady:.2f}",
                         f"{pct(first, .5):.0f} / {1e3 * first[-1]:.0f}", "ok" if h99 < 50 else "MISSED", str(len(t))))
            TARGETS.append((f"history p99 / health p99, {kind}, {n} API process(es)", f"{ratio:.2f}", "<= 1.5",
                            "ok" if ratio <= 1.5 else "MISSED"))
            TARGETS.append((f"steady history p99 / health p99, {kind}, {n} API process(es)", f"{steady:.2f}", "<= 1.5",
                            "ok" if steady <= 1.5 else "MISSED"))
            if kind == "sqlite":
                TARGETS.append((f"history p99, {kind}, one process", f"{h99:.0f} ms", "< 50 ms", "ok" if h99 < 50 else "MISSED"))
            TARGETS.append((f"steady history p99, {kind}, {n} API process(es)", f"{pct(t_on, .99):.0f} ms", "< 50 ms",
                            "ok" if pct(t_on, .99) < 50 else "MISSED"))
    table("GET /devices/{serial}/calibrations (10,000 stored) vs GET /health under the same load: 50 concurrent "
          "keep-alive clients, all starting at once (ms)",
          ("database", "API procs", "hist p50", "hist p99", "health p50", "health p99", "p99 ratio", "ratio<=1.5",
           "steady hist p99", "steady health p99", "steady ratio", "1st req hist med/max", "hist p99<50", "requests"), rows)
    print("  API processes: SQLite `compasscal serve` (drives the stations too); PostgreSQL 1: `serve --no-station-worker`, "
          "2 and 4: `serve --workers N`\n"
          "  steady: each client's first request left out (its connection's set-up while all 50 clients start at once); "
          "1st req: those first requests of the history")


# ------------------------------------------------------------------------------------ overhead

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


def part_overhead(tmp: Path, quick: bool) -> None:
    direct, via_api = overhead()
    table("A calibration at time scale 20 (60 samples per pose)", ("path", "wall s", "overhead"),
          [("direct (compasscal calibrate's path)", f"{direct:.2f}", ""),
           ("through the REST API (SQLite, one process)", f"{via_api:.2f}",
            f"{via_api - direct:+.2f} s ({100 * (via_api / direct - 1):+.0f} %)")])


# ------------------------------------------------------------------------------------ stations

class Api:
    """HTTP to one API process with a key per role."""

    def __init__(self, port: int, keys: dict[str, str]) -> None:
        import httpx
        self.base, self.keys, self.httpx = f"http://127.0.0.1:{port}", keys, httpx

    def call(self, method: str, path: str, role: str = "admin", **kw: Any) -> Any:
        return self.httpx.request(method, self.base + path, headers={"X-API-Key": self.keys[role]}, timeout=30, **kw)


def _when(s: str | None) -> datetime | None:
    return datetime.fromisoformat(s.replace("Z", "+00:00")) if s else None


def stations_round(api: Api, url: str, tmp: Path, k: int, timeout: float, one_at_a_time: bool = False) -> dict[str, Any]:
    """K simulated stations, a worker each, one calibration each started at once; what happened.
    ``one_at_a_time``: then one more calibration on each station in turn (the baseline of accuracy)."""
    from conftest import sim_station
    from drivers.sim.config import reference_config

    workers: list[subprocess.Popen[bytes]] = []
    names = [f"bench-k{k}-s{i}" for i in range(k)]
    try:
        with ExitStack() as stack:
            infos = [stack.enter_context(sim_station(reference_config(seed=i, time_scale=TIME_SCALE))) for i in range(k)]
            for name, info in zip(names, infos):
                r = api.call("POST", "/stations", json={"name": name, "modbus": info["modbus"], "time_scale": TIME_SCALE,
                                                        "compasses": [c["url"] for c in info["compasses"]]})
                if r.status_code != 201:
                    raise RuntimeError(f"POST /stations {name}: {r.status_code} {r.text}")
                workers.append(start(["worker", "--station", name, "--no-analyses"], url, tmp / f"worker-{name}.log"))
            deadline = time.monotonic() + 90
            while not all(api.call("GET", f"/stations/{n}", "viewer").json().get("worker_alive") for n in names):
                for n, w in zip(names, workers):
                    if w.poll() is not None:
                        raise RuntimeError(f"the worker of {n} exited:\n{tail(tmp / f'worker-{n}.log')}")
                if time.monotonic() > deadline:
                    raise RuntimeError("the workers did not beat within 90 s")
                time.sleep(0.2)
            time.sleep(1.0)  # let the workers settle after their first beat

            pids = {"workers": [w.pid for w in workers]}
            before = {g: sum(cpu_ticks(p) for p in ps) for g, ps in pids.items()}
            busy0, total0 = machine_ticks()
            me0 = time.process_time()
            t0 = time.monotonic()

            def post(i: int) -> Any:
                return api.call("POST", "/runs", "operator", json={
                    "station": names[i], "procedure": "calibrate", "parameters": {"samples": 20},
                    # every simulated station carries the same reference unit under its own serial:
                    # certify the typed serial rather than prompt for the mismatch
                    "serials": {"0": f"BENCH-K{k}-{i}"}, "serial_policy": "trust-typed"})
            with ThreadPoolExecutor(k) as ex:
                answers = list(ex.map(post, range(k)))
            ids = []
            for n, r in zip(names, answers):
                if r.status_code != 202:
                    raise RuntimeError(f"POST /runs on {n}: {r.status_code} {r.text}")
                ids.append(r.json()["id"])
            runs: dict[int, dict[str, Any]] = {}
            seen_end: dict[int, float] = {}
            while len(seen_end) < k and time.monotonic() - t0 < timeout:
                for rid in ids:
                    if rid in seen_end:
                        continue
                    try:
                        j = api.call("GET", f"/runs/{rid}", "viewer").json()
                    except Exception:  # noqa: BLE001 - a slow answer under load: ask again
                        continue
                    runs[rid] = j
                    if j["status"] not in ACTIVE:
                        seen_end[rid] = time.monotonic() - t0
                time.sleep(0.1)
            polled_wall = max(seen_end.values()) if seen_end else float("nan")
            busy1, total1 = machine_ticks()
            me = time.process_time() - me0
            after = {g: sum(cpu_ticks(p) for p in ps) for g, ps in pids.items()}
            for rid in ids:  # the final view (and the unfinished ones as they stand)
                runs[rid] = api.call("GET", f"/runs/{rid}", "viewer").json()
            # the baseline: the same stations, one run at a time (each unit's noise draws differ from
            # run to run, so the concurrent runs are compared with as many runs alone)
            alone: list[dict[str, Any]] = []
            for i in range(k if one_at_a_time else 0):
                r = post(i)
                if r.status_code != 202:  # e.g. its station in fault after a failed run
                    alone.append({"id": None, "status": f"not started (HTTP {r.status_code})", "reason": r.text})
                    continue
                rid, t1 = r.json()["id"], time.monotonic()
                while True:
                    j = api.call("GET", f"/runs/{rid}", "viewer").json()
                    if j["status"] not in ACTIVE or time.monotonic() - t1 > timeout:
                        break
                    time.sleep(0.1)
                alone.append(j)
    finally:
        for w in workers:
            stop(w)
    hz = os.sysconf("SC_CLK_TCK")
    created = [_when(runs[r]["created_at"]) for r in ids]
    finished = [_when(runs[r]["finished_at"]) for r in ids]
    wall = ((max(f for f in finished) - min(c for c in created)).total_seconds()
            if all(finished) and all(created) else polled_wall)
    return {"k": k, "names": names, "runs": [runs[r] for r in ids], "wall": wall, "polled_wall": polled_wall,
            "timed_out": len(seen_end) < k, "timeout": timeout, "alone": alone,
            "cpu_busy": (busy1 - busy0) / max(1, total1 - total0),
            "cpu_workers_s": (after["workers"] - before["workers"]) / hz, "cpu_sims_s": me}


def _heading(run: dict[str, Any], key: str = "full") -> float | None:
    unit = ((run.get("result") or {}).get("units") or {}).get("0") or {}
    he = unit.get("heading_error_deg") or {}
    v = he.get(key)
    return float(v) if isinstance(v, (int, float)) else None


def _errors(runs: list[dict[str, Any]], key: str = "full") -> list[float]:
    return [e for e in (_heading(r, key) for r in runs if r["status"] == "completed") if e is not None]


def _median(v: list[float]) -> float:
    return statistics.median(v) if v else float("nan")


def _f(x: float, fmt: str = ".4f") -> str:
    return format(x, fmt) if x == x else "-"


def part_stations(tmp: Path, quick: bool) -> None:
    ks = (1, 2) if quick else (1, 2, 8)
    url = fresh("postgresql", tmp)
    k_ = keys(url)
    log = tmp / "serve-stations.log"
    proc, port = serve(url, log, station_worker=False)
    api = Api(port, k_)
    rounds = []
    try:
        for k in ks:
            rounds.append(stations_round(api, url, tmp, k, timeout=120 + 60 * k, one_at_a_time=k == ks[-1]))
            time.sleep(1.0)
    finally:
        stop(proc)

    # accuracy baselines: K=1 (one run: its error varies from run to run with the noise draws) and
    # the largest K's stations run again one at a time (as many runs as the largest K)
    alone = rounds[-1]["alone"]
    base1 = _median(_errors(rounds[0]["runs"]))
    base_alone = _median(_errors(alone))
    base_wall = rounds[0]["wall"]
    tables1 = [r["table_seconds"] for r in rounds[0]["runs"] if r.get("table_seconds")]
    base_table = statistics.mean(tables1) if tables1 else float("nan")
    rows, notes = [], []
    for rd in rounds:
        k, runs = rd["k"], rd["runs"]
        done = [r for r in runs if r["status"] == "completed"]
        samples = sum(r.get("samples_count") or 0 for r in runs)
        tables = [r["table_seconds"] for r in runs if r.get("table_seconds")]
        errs, tilted = _errors(runs), _errors(runs, "tilted_full")
        med = _median(errs)
        vs1, vs_alone = med / base1, med / base_alone
        table_mean = statistics.mean(tables) if tables else float("nan")
        slowdown, inflation = rd["wall"] / base_wall, table_mean / base_table
        overloaded = k > 1 and (rd["cpu_busy"] > 0.9 or inflation > 1.25 or slowdown > 1.5)
        rows.append((str(k), f"{len(done)}/{k}", _f(rd["wall"], ".1f"), _f(samples / rd["wall"], ".0f"),
                     _f(table_mean, ".1f"), f"{100 * rd['cpu_busy']:.0f} %", f"{rd['cpu_sims_s']:.1f} / {rd['cpu_workers_s']:.1f}",
                     _f(med), _f(_median(tilted)), _f(vs1, ".2f") if k > 1 else "", _f(vs_alone, ".2f"),
                     "YES" if overloaded else "no"))
        for name, r in zip(rd["names"], runs):
            if r["status"] != "completed":
                notes.append(f"K={k}: run {r['id']} on {name} {r['status']}: {r.get('reason')}")
            else:
                unit = ((r.get("result") or {}).get("units") or {}).get("0") or {}
                if "error" in unit or unit.get("verdict") not in ("PASS", "MARGINAL"):
                    notes.append(f"K={k}: run {r['id']} on {name} completed, unit 0: verdict {unit.get('verdict')} "
                                 f"{unit.get('reasons') or unit.get('error') or ''}")
        if rd["timed_out"]:
            notes.append(f"K={k}: not every run ended within {rd['timeout']:.0f} s")
        if overloaded:
            notes.append(f"K={k}: the machine is OVERLOADED ({os.cpu_count()} CPUs {100 * rd['cpu_busy']:.0f} % busy; wall "
                         f"{slowdown:.2f}x and table seconds {inflation:.2f}x those of one station alone); the simulated "
                         f"stations (threads of this process) used {rd['cpu_sims_s']:.1f} CPU s, the workers "
                         f"{rd['cpu_workers_s']:.1f} CPU s, PostgreSQL and the API the rest")
        notes.append(f"K={k}: level heading error per station (deg): {', '.join(f'{e:.4f}' for e in errs) or '-'}")
        TARGETS.append((f"{k} station(s) at once: runs completed", f"{len(done)}/{k}", f"{k}/{k}",
                        "ok" if len(done) == k else "MISSED"))
        if k > 1:
            TARGETS.append((f"{k} stations at once: median level heading error / the same of {len(alone)} runs one at a time",
                            _f(vs_alone, ".2f"), "<= 1.5", "ok" if vs_alone <= 1.5 else "MISSED"))
    if alone:
        done = [r for r in alone if r["status"] == "completed"]
        walls = [(_when(r["finished_at"]) - _when(r["created_at"])).total_seconds() for r in done
                 if r.get("finished_at") and r.get("created_at")]
        tables = [r["table_seconds"] for r in done if r.get("table_seconds")]
        rows.append((f"{len(alone)} runs one at a time", f"{len(done)}/{len(alone)}", f"{statistics.mean(walls):.1f} each" if walls else "-",
                     _f(sum(r.get("samples_count") or 0 for r in done) / sum(walls), ".0f") if walls else "-",
                     _f(statistics.mean(tables), ".1f") if tables else "-", "", "", _f(base_alone),
                     _f(_median(_errors(alone, "tilted_full"))), _f(base_alone / base1, ".2f"), "1.00", ""))
        notes.append(f"one at a time (the K={rounds[-1]['k']} stations again, each run alone): level heading error per "
                     f"station (deg): {', '.join(f'{e:.4f}' for e in _errors(alone)) or '-'}")
        for name, r in zip(rounds[-1]["names"], alone):
            if r["status"] != "completed":
                notes.append(f"one at a time: run {r['id']} on {name} {r['status']}: {r.get('reason')}")
    notes.append("the reference for accuracy is the runs one at a time: the K=1 figure is a single run, and a unit's "
                 "error moves from run to run with the noise draws (the spread across stations above shows by how much)")
    table(f"Stations calibrating at once on one PostgreSQL (calibrate, 20 samples x 18 poses, time scale {TIME_SCALE}; "
          f"one API process, one worker per station; errors in deg, the stored calibration's heading_error_deg)",
          ("K", "completed", "wall s", "samples/s", "table s", "CPU busy", "CPU s sims/workers", "level err med",
           "+-60 err med", "err / K=1", "err / alone", "overloaded"), rows)
    notes.append("CPU busy: the whole machine's (anything else running counts); CPU s: this process's (the "
                 "simulated stations) and the workers' during the runs at once")
    for n in notes:
        print("  " + n)


# -------------------------------------------------------------------------------------- notify

def _publisher(url: str, run_id: int, n: int, interval: float, ready: Any) -> None:
    """A separate process, as a worker: ``n`` progress events, each in its own transaction, then the
    run's end."""
    from sqlalchemy import text

    from service.db import make_engine, sessions
    from service.runtime import publish
    engine = make_engine(url)
    S = sessions(engine)
    with S() as s:
        s.execute(text("SELECT 1"))  # connected before the first event
    ready.set()
    for i in range(n):
        with S() as s:
            publish(s, run_id, "progress", {"sent": time.time(), "i": i, "n": n})
            s.commit()
        time.sleep(interval)
    with S() as s:
        publish(s, run_id, "state", {"state": "completed", "reason": None})
        s.commit()
    engine.dispose()


def part_notify(tmp: Path, quick: bool) -> None:
    import httpx

    from service.db import Run, make_engine, sessions
    from service.runtime import publish

    n = 100 if quick else 300
    url = fresh("postgresql", tmp)
    k_ = keys(url)
    engine = make_engine(url)
    with sessions(engine)() as s:
        run = Run(procedure="calibrate", procedure_version="bench", parameters={}, operator="bench",
                  software_version="bench", status="running", prompts={})
        s.add(run)
        s.flush()
        publish(s, run.id, "state", {"state": "running", "reason": None})
        s.commit()
        run_id = run.id
    engine.dispose()
    proc, port = serve(url, tmp / "serve-notify.log", station_worker=False)
    lat: list[float] = []
    other: list[str] = []
    opened = threading.Event()
    failure: list[BaseException] = []

    def client() -> None:
        try:
            with httpx.stream("GET", f"http://127.0.0.1:{port}/runs/{run_id}/events",
                              headers={"X-API-Key": k_["viewer"]}, timeout=httpx.Timeout(30, read=60)) as r:
                kind = ""
                for line in r.iter_lines():
                    now = time.time()
                    if line.startswith("event: "):
                        kind = line[7:]
                    elif line.startswith("data: "):
                        data = json.loads(line[6:])
                        if kind == "progress":
                            lat.append(now - data["sent"])
                        else:
                            other.append(f"{kind} {data}")
                            opened.set()
        except BaseException as e:  # noqa: BLE001 - reported below
            failure.append(e)
            opened.set()

    ctx = mp.get_context("spawn")
    ready = ctx.Event()
    pub = ctx.Process(target=_publisher, args=(url, run_id, n, 0.02, ready), daemon=True)
    th = threading.Thread(target=client, daemon=True)
    try:
        th.start()
        if not opened.wait(30) or failure:
            raise RuntimeError(f"the event stream did not open: {failure}")
        pub.start()
        ready.wait(60)
        pub.join(n * 0.2 + 60)
        th.join(30)
    finally:
        if pub.is_alive():
            pub.kill()
        stop(proc)
    if failure:
        raise RuntimeError(f"the event stream failed: {failure[0]!r}")
    ended = any(o.startswith("state") and "completed" in o for o in other)
    if not lat:
        raise RuntimeError("no progress event reached the client")
    t = sorted(lat)
    p50, p99, mx = pct(t, .5), pct(t, .99), 1e3 * t[-1]
    verdict = "ok" if p99 < 100 and len(t) == n else "MISSED"
    table(f"A worker's event to a server-sent-events client through NOTIFY (PostgreSQL, one API process, "
          f"{n} events 20 ms apart)", ("received", "p50 ms", "p99 ms", "max ms", "target", "verdict", "stream ended"),
          [(f"{len(t)}/{n}", f"{p50:.1f}", f"{p99:.1f}", f"{mx:.1f}", "p99 < 100 ms", verdict,
            "yes" if ended else "NO")])
    TARGETS.append(("event to SSE client through NOTIFY, p99", f"{p99:.1f} ms", "< 100 ms", verdict))


# --------------------------------------------------------------------------------------- print

def table(title: str, head: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
    w = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(head)]
    print(f"\n{title}", flush=True)
    print("| " + " | ".join(h.ljust(w[i]) for i, h in enumerate(head)) + " |")
    print("|" + "|".join("-" * (x + 2) for x in w) + "|")
    for r in rows:
        print("| " + " | ".join(c.ljust(w[i]) for i, c in enumerate(r)) + " |", flush=True)


PARTS = {"insert": part_insert, "history": part_history, "overhead": part_overhead, "stations": part_stations,
         "notify": part_notify}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-overhead", action="store_true", help="Leave out the calibration-overhead part.")
    ap.add_argument("--quick", action="store_true", help="A fast check: fewer rows and queries, K in (1, 2), 100 events.")
    ap.add_argument("--only", choices=sorted(PARTS), help="Run one part.")
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so that the finally below runs
    parts = [args.only] if args.only else [p for p in PARTS if not (p == "overhead" and args.skip_overhead)]
    print(f"benchmarks/service_speed.py{' --quick' if args.quick else ''}: {', '.join(parts)}; {os.cpu_count()} CPUs; "
          f"PostgreSQL database {BENCH_DB}", flush=True)
    failed = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for p in parts:
                t0 = time.monotonic()
                try:
                    PARTS[p](Path(tmp), args.quick)
                except Exception as e:  # noqa: BLE001 - the other parts still run
                    failed.append(p)
                    print(f"\n{p}: FAILED: {type(e).__name__}: {e}", flush=True)
                finally:
                    stop_all()
                print(f"  ({p}: {time.monotonic() - t0:.0f} s)", flush=True)
    finally:
        stop_all()
    if TARGETS:
        table("Targets", ("measure", "value", "target", "verdict"), TARGETS)
    if failed:
        print(f"\nparts that failed: {', '.join(failed)}")
        sys.exit(1)


if __name__ == "__main__":
    main()
