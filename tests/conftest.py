"""Shared fixtures: the service on SQLite and on the machine's PostgreSQL, API keys per role, a fake
engine that answers procedure steps with the forward model, and a simulated station running in its
own thread (as a separate station would)."""

from __future__ import annotations

import asyncio
import gc
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers import keep_drivers_responsive
from physics.recording import Recording
from physics.simulate import World
from procedures.calibrate import PROCEDURES
from procedures.steps import Acquire, Move, Outcome, Scan, Step, drive

# the tests host simulated stations in their own process, beside the service and its fits, as
# `compasscal demo` does: the drivers' timeouts need the short switch interval the CLI sets
keep_drivers_responsive()

#: The machine's test database. Under pytest-xdist each worker gets a database of its own
#: (test_gw0, test_gw1, ...: created on first use), because a test empties the one it uses.
PG_DB = "test" if not os.environ.get("PYTEST_XDIST_WORKER") else f"test_{os.environ['PYTEST_XDIST_WORKER']}"
PG_URL = f"postgresql://postgres@127.0.0.1:5432/{PG_DB}"


def _pg_up() -> bool:
    import psycopg
    try:
        psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=test", connect_timeout=3).close()
        return True
    except psycopg.OperationalError:
        return False


def _ensure_worker_database() -> None:
    import psycopg
    if PG_DB == "test":
        return
    with psycopg.connect("host=127.0.0.1 port=5432 user=postgres dbname=test", autocommit=True) as conn:
        if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (PG_DB,)).fetchone() is None:
            conn.execute(f'CREATE DATABASE "{PG_DB}"')


def ensure_postgres() -> str:
    """The test database's URL (this xdist worker's own), starting the machine's PostgreSQL when it is
    not running."""
    if not _pg_up():
        clusters = sorted(p.name for p in Path("/etc/postgresql").iterdir()) if Path("/etc/postgresql").exists() else []
        if clusters and shutil.which("pg_ctlcluster"):
            subprocess.run(["pg_ctlcluster", "--skip-systemctl-redirect", clusters[-1], "main", "start"], check=False,
                           capture_output=True, timeout=60)
    if not _pg_up():
        raise RuntimeError("PostgreSQL at 127.0.0.1:5432 (database test) is not running and could not be started")
    _ensure_worker_database()
    return PG_URL


def fresh_database(kind: str, tmp_path: Path) -> str:
    """An empty database of ``kind`` (sqlite: a new file; postgresql: this worker's test database emptied)."""
    if kind == "sqlite":
        return f"sqlite:///{tmp_path / 'compasscal.db'}"
    url = ensure_postgres()
    from sqlalchemy import create_engine, text
    eng = create_engine(url.replace("postgresql://", "postgresql+psycopg://"))
    with eng.begin() as conn:
        conn.execute(text("DROP SCHEMA IF EXISTS public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    eng.dispose()
    return url


@pytest.fixture(autouse=True)
def _no_full_collection_mid_test() -> None:
    """Collect the earlier tests' garbage now and freeze what survives, so that no full collection
    over it runs during the test. One process hosts hundreds of tests' leftovers (~480 000 objects);
    a collection over them stopped every thread for 0.3-0.8 s (measured under three processes on two
    cores), the simulated devices and the drivers alike, and the drivers' Modbus timeout is 0.4 s. A
    collection after the freeze walks only what the test itself made (the command line freezes its imports
    at startup, ``drivers.keep_drivers_responsive``)."""
    gc.collect()
    gc.freeze()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """Each test using it runs once on SQLite and once on PostgreSQL."""
    return fresh_database(request.param, tmp_path)


class Api:
    """A TestClient with one key per role: ``api.get(path, role="viewer")``."""

    def __init__(self, client: Any, keys: dict[str, str]) -> None:
        self.client, self.keys = client, keys

    def __getattr__(self, method: str) -> Any:
        def call(path: str, role: str | None = "admin", **kw: Any) -> Any:
            headers = dict(kw.pop("headers", {}) or {})
            if role:
                headers["X-API-Key"] = self.keys[role]
            return getattr(self.client, method)(path, headers=headers, **kw)
        return call


@pytest.fixture
def api(db_url: str) -> Iterator[Api]:
    """The service on a fresh database, with an admin, an operator and a viewer key."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.auth import create_key

    app = create_app(db_url)
    with TestClient(app) as client:
        with app.state.sessions() as session:
            keys = {role: create_key(session, f"{role}-user", role) for role in ("viewer", "operator", "admin")}
        yield Api(client, keys)


class FakeEngine:
    """Answers procedure steps like a station, with the physics forward model: Move remembers the
    angles, Acquire samples there, Scan turns the axis at constant speed sampling at 20 Hz, each sample
    with its angle (no I/O, no hardware)."""

    def __init__(self, units: list, world: World = World(), seed: int = 0) -> None:
        self.units, self.world = units, world
        self.rng = np.random.default_rng(seed)
        self.angles = (0.0, 0.0, 0.0)
        self.steps: list[Step] = []
        self.t = 0.0

    def _record(self, step: str, a: np.ndarray) -> dict[int, Recording]:
        n = len(a)
        h_b, f_b = self.world.body_vectors(a[:, 0], a[:, 1], a[:, 2])
        out = {slot: Recording.from_arrays(
            t=self.t + np.arange(n) / 20.0, step=[step] * n, psi_t=a[:, 0], theta_t=a[:, 1], phi_t=a[:, 2],
            mag=u.mag.measure(h_b, self.rng), acc=u.acc.measure(f_b, self.rng), meta={"serial": u.serial})
            for slot, u in enumerate(self.units)}
        self.t += n / 20.0 + 1.0  # the move to the next pose
        return out

    def __call__(self, step: Step) -> object:
        self.steps.append(step)
        if isinstance(step, Move):
            self.angles = (step.psi, step.theta, step.phi)
        if isinstance(step, Acquire):
            return self._record(step.step, np.tile(self.angles, (step.samples, 1)))
        if isinstance(step, Scan):
            n = int(abs(step.stop_deg - step.start_deg) / step.speed_dps * 20.0) + 1
            a = np.tile(step.start_angles, (n, 1))
            a[:, step.index] = np.linspace(step.start_deg, step.stop_deg, n)
            self.angles = step.stop_angles
            return self._record(step.step, a)
        return None

    def run(self, name: str, params: dict | None = None) -> Outcome:
        proc = PROCEDURES[name]
        return drive(proc.run(proc.validate(params)), self)

    def kinds(self) -> list[str]:
        return [type(s).__name__ for s in self.steps]


@contextmanager
def sim_station(cfg: Any) -> Iterator[dict[str, Any]]:
    """A SimStation in its own thread and event loop; yields its description plus ``truth`` and ``station``."""
    from drivers.sim.station import SimStation

    info: dict[str, Any] = {}
    started = threading.Event()
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()

    async def main() -> None:
        async with SimStation(cfg) as st:
            info.update(st.describe(), truth=st.truth(), station=st)
            started.set()
            await stop.wait()

    def serve() -> None:
        try:
            loop.run_until_complete(main())
        except BaseException as e:  # noqa: BLE001 - reported to the test
            info["error"] = e
            started.set()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    started.wait(30)
    if "error" in info:
        raise info["error"]
    # The simulated controllers answer from a thread of this process, which shares two cores with the
    # service, its fits and two other pytest processes: allow them the answer time of a slow gateway
    # (1 s instead of 0.3 s), as a station would on such a line (a silent axis still fails the run).
    info["modbus"] += "?timeout=1"
    info["loop"] = loop
    try:
        yield info
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(10)


def parse_sse(lines: Any) -> list[tuple[int, str, dict[str, Any]]]:
    """Server-sent events as (id, event, data) from a stream's lines (id -1 where none was sent)."""
    import json

    events, ident, kind = [], -1, ""
    for line in lines:
        if line.startswith("id: "):
            ident = int(line[4:])
        elif line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: "):
            events.append((ident, kind, json.loads(line[6:])))
    return events


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_healthy(port: int, proc: subprocess.Popen, log: Path, timeout: float = 60.0) -> None:
    """Until the service ``proc`` started answers ``GET /health`` on ``port``; fails with its log if
    it exits or does not answer within ``timeout`` s."""
    import httpx

    deadline = time.monotonic() + timeout
    while True:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        assert proc.poll() is None, log.read_text()
        assert time.monotonic() < deadline, f"the service did not answer in {timeout:g} s: {log.read_text()[-2000:]}"
        time.sleep(0.2)
