"""Stations as workers on PostgreSQL (issue 13): an API process and a station worker as separate
processes sharing one database. kill -9 of the API mid-run: the run carries on in its worker and a
new API process streams it on from Last-Event-ID. kill -9 of the worker mid-run: within a few
heartbeats the run is failed, "worker lost", with its samples kept and the station in fault; a
restarted worker stops the axes first, and the station's reset goes through it."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from conftest import free_port, fresh_database, parse_sse, sim_station, wait_healthy
from drivers.sim.config import parse_config, reference_config

ROOT = Path(__file__).resolve().parent.parent


def _start(args: list[str], url: str, log: Path) -> subprocess.Popen[bytes]:
    env = {**os.environ, "COMPASSCAL_DATABASE_URL": url}
    with log.open("wb") as out:  # the child keeps its own copy of the descriptor
        # a session of its own: kill -9 then takes the process and every process it started
        # (`serve --workers N` runs its API processes as children)
        return subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


class Client:
    """HTTP to one API process, with a key per role."""

    def __init__(self, port: int, keys: dict[str, str]) -> None:
        self.base, self.keys = f"http://127.0.0.1:{port}", keys

    def call(self, method: str, path: str, role: str = "admin", **kw: Any) -> httpx.Response:
        return httpx.request(method, self.base + path, headers={"X-API-Key": self.keys[role]}, timeout=30, **kw)

    def station(self, info: dict[str, Any], name: str) -> None:
        """Register simulated station ``info`` (conftest.sim_station) as ``name``."""
        r = self.call("POST", "/stations", json={"name": name, "modbus": info["modbus"], "time_scale": 20,
                                                 "compasses": [x["url"] for x in info["compasses"]]})
        assert r.status_code == 201, r.text

    def run(self, run_id: int) -> dict[str, Any]:
        return self.call("GET", f"/runs/{run_id}", "viewer").json()

    def wait(self, run_id: int, until: Any, timeout: float = 60.0) -> dict[str, Any]:
        deadline, j = time.monotonic() + timeout, {"status": "unknown", "reason": "no answer yet"}
        while True:
            try:
                j = self.run(run_id)
                if until(j):
                    return j
            except (httpx.HTTPError, ValueError):  # the API or its database restarting
                pass
            assert time.monotonic() < deadline, f"run {run_id}: {j['status']} ({j['reason']}) after {timeout} s"
            time.sleep(0.1)

    def events(self, run_id: int, last: int | None = None) -> list[tuple[int, str, dict[str, Any]]]:
        headers = {"X-API-Key": self.keys["viewer"], **({"Last-Event-ID": str(last)} if last is not None else {})}
        with httpx.stream("GET", f"{self.base}/runs/{run_id}/events", headers=headers, timeout=120) as r:
            return parse_sse(r.iter_lines())


def _api(url: str, tmp: Path, name: str, *options: str) -> tuple[subprocess.Popen[bytes], int]:
    """`compasscal serve` (default: one process, no station worker) once it answers; it and its port."""
    port = free_port()
    proc = _start(["serve", "--port", str(port), *(options or ("--no-station-worker",))], url, tmp / f"{name}.log")
    wait_healthy(port, proc, tmp / f"{name}.log")
    return proc, port


def _keys(url: str) -> dict[str, str]:
    from service.auth import create_key
    from service.db import make_engine, sessions

    engine = make_engine(url)
    with sessions(engine)() as s:
        keys = {role: create_key(s, f"{role}-user", role) for role in ("viewer", "operator", "admin")}
    engine.dispose()
    return keys


def _restart_postgres(down_s: float) -> None:
    """Stop the machine's PostgreSQL (fast: every connection is cut), wait, start it again."""
    cluster = sorted(p.name for p in Path("/etc/postgresql").iterdir())[-1]
    ctl = ["pg_ctlcluster", "--skip-systemctl-redirect", cluster, "main"]
    subprocess.run([*ctl, "stop", "-m", "fast"], check=True, capture_output=True, timeout=60)
    time.sleep(down_s)
    subprocess.run([*ctl, "start"], check=True, capture_output=True, timeout=60)


def _kill(proc: subprocess.Popen[bytes]) -> None:
    """kill -9 of the process and of every process it started."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(10)


def test_runs_survive_an_api_kill_and_a_lost_worker_is_reported(tmp_path: Path):
    url = fresh_database("postgresql", tmp_path)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        api1, port1 = _api(url, tmp_path, "api1")
        procs.append(api1)
        keys = _keys(url)
        c1 = Client(port1, keys)
        with sim_station(reference_config(seed=4, time_scale=20)) as info:
            c1.station(info, "lab-1")
            worker = _start(["worker", "--station", "lab-1"], url, tmp_path / "worker1.log")
            procs.append(worker)
            body = {"station": "lab-1", "procedure": "calibrate", "parameters": {"samples": 20}}

            # 1. kill -9 of the API mid-run: the run carries on; a new API process streams it on
            rid = c1.call("POST", "/runs", "operator", json=body).json()["id"]
            j = c1.wait(rid, lambda j: j["samples_count"] > 0)
            assert j["status"] == "running" and c1.call("GET", "/stations/lab-1", "viewer").json()["worker_alive"]
            _kill(api1)
            api2, port2 = _api(url, tmp_path, "api2")
            procs.append(api2)
            c2 = Client(port2, keys)
            first = c2.events(rid)
            assert first[-1][1:] == ("state", {"state": "completed", "reason": None}), first[-3:]
            assert [i for i, _, _ in first] == sorted(i for i, _, _ in first)
            assert c2.events(rid, last=first[-3][0]) == first[-2:]  # Last-Event-ID resumes there
            done = c2.run(rid)
            assert done["samples_count"] == 18 * 20 and done["result"]["units"]["0"]["verdict"] in ("PASS", "MARGINAL")

            # 2. kill -9 of the worker mid-run: failed "worker lost", samples kept, station in fault
            rid2 = c2.call("POST", "/runs", "operator", json=body).json()["id"]
            c2.wait(rid2, lambda j: j["samples_count"] > 0)
            t0 = time.monotonic()
            _kill(worker)
            lost = c2.wait(rid2, lambda j: j["status"] not in ("queued", "running", "paused"), timeout=30)
            assert lost["status"] == "failed" and "worker lost" in lost["reason"], lost
            assert time.monotonic() - t0 < 15  # a few heartbeats
            assert lost["samples_count"] > 0
            assert c2.call("GET", f"/runs/{rid2}/samples", "viewer").status_code == 200
            st = c2.call("GET", "/stations/lab-1", "viewer").json()
            assert st["state"] == "fault" and "worker lost" in st["fault"] and st["run_id"] is None
            assert c2.call("POST", "/runs", "operator", json=body).status_code == 409

            # a restarted worker stops the axes, then the station's reset goes through it
            worker2 = _start(["worker", "--station", "lab-1"], url, tmp_path / "worker2.log")
            procs.append(worker2)
            deadline = time.monotonic() + 30
            while True:
                r = c2.call("POST", "/stations/lab-1/reset", "operator")
                if r.status_code == 200 or time.monotonic() > deadline:
                    break
                time.sleep(0.5)
            assert r.status_code == 200 and r.json()["state"] == "idle", r.text
            table = info["station"].table
            assert all(ax.mode not in ("move", "jog") for ax in table.axes.values())  # nothing left turning
            rid3 = c2.call("POST", "/runs", "operator", json={**body, "procedure": "rotate_z",
                                                              "parameters": {"samples": 10, "step_deg": 90}}).json()["id"]
            assert c2.wait(rid3, lambda j: j["status"] in ("completed", "failed", "aborted"))["status"] == "completed"
    finally:
        for p in procs:
            _kill(p)


def test_the_production_line_topology_two_api_processes_two_stations_two_workers(tmp_path: Path):
    """The README's topology without Docker: PostgreSQL, `serve --workers 2`, two simulated stations
    with a worker each; two calibrations at once while the unit's history is queried."""
    url = fresh_database("postgresql", tmp_path)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        api, port = _api(url, tmp_path, "api", "--workers", "2")
        procs.append(api)
        keys = _keys(url)
        c = Client(port, keys)
        def unit(seed: int, serial: str) -> Any:  # the serial the simulated compass reports is the one typed
            d = reference_config(seed=seed, time_scale=20).model_dump()
            d["unit"][0]["serial"] = serial
            return parse_config(d)
        with sim_station(unit(5, "LINE1-UNIT")) as a, sim_station(unit(6, "LINE2-UNIT")) as b:
            runs = []
            for name, info in (("line-1", a), ("line-2", b)):
                r = c.call("PUT", f"/stations/{name}", json={"modbus": info["modbus"], "time_scale": 20,
                                                               "compasses": [x["url"] for x in info["compasses"]]})
                assert r.status_code == 200, r.text
                procs.append(_start(["worker", "--station", name], url, tmp_path / f"{name}.log"))
            for name, serial in (("line-1", "LINE1-UNIT"), ("line-2", "LINE2-UNIT")):
                r = c.call("POST", "/runs", "operator", json={"station": name, "parameters": {"samples": 20},
                                                              "serials": {"0": serial}})
                assert r.status_code == 202, r.text
                runs.append(r.json()["id"])
            answered = 0
            while any(c.run(r)["status"] in ("queued", "running", "paused") for r in runs):
                for serial in ("LINE1-UNIT", "LINE2-UNIT"):  # history queries, through either API process
                    h = c.call("GET", f"/devices/{serial}/calibrations", "viewer")
                    assert h.status_code in (200, 404)
                    answered += 1
                time.sleep(0.2)
            assert answered > 10
            for r, serial in zip(runs, ("LINE1-UNIT", "LINE2-UNIT")):
                j = c.run(r)
                assert j["status"] == "completed", j["reason"]
                assert j["result"]["units"]["0"]["verdict"] in ("PASS", "MARGINAL")
                hist = c.call("GET", f"/devices/{serial}/calibrations", "viewer").json()
                assert [h["run_id"] for h in hist] == [r]
            # each station's run was driven by its own worker (the stations' rows name them)
            stations = c.call("GET", "/stations", "viewer").json()
            assert len({s["worker"] for s in stations}) == 2 and all(s["worker_alive"] for s in stations)
    finally:
        for p in procs:
            _kill(p)


@pytest.mark.serial  # it stops the machine's PostgreSQL: nothing else may run meanwhile
def test_a_postgresql_restart_mid_run_loses_nothing(tmp_path: Path):
    """PostgreSQL stopped for a few seconds mid-calibration: the worker keeps the samples and events
    it could not write and writes them once the database is back, the API reconnects, the run
    completes with every sample stored and its events in order; the queue works on after it."""
    url = fresh_database("postgresql", tmp_path)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        api, port = _api(url, tmp_path, "api")
        procs.append(api)
        c = Client(port, _keys(url))
        with sim_station(reference_config(seed=6, time_scale=20)) as info:
            c.station(info, "lab-pg")
            procs.append(_start(["worker", "--station", "lab-pg"], url, tmp_path / "worker.log"))
            body = {"station": "lab-pg", "procedure": "calibrate", "parameters": {"samples": 20}}
            rid = c.call("POST", "/runs", "operator", json=body).json()["id"]
            c.wait(rid, lambda j: j["samples_count"] > 0)
            _restart_postgres(down_s=4.0)
            done = c.wait(rid, lambda j: j["status"] not in ("queued", "running", "paused"), timeout=120)
            log = (tmp_path / "worker.log").read_text()
            assert done["status"] == "completed", (done, log[-3000:])
            assert done["samples_count"] == 18 * 20 == done["result"]["samples"], done
            assert done["result"]["units"]["0"]["verdict"] in ("PASS", "MARGINAL")
            events = c.events(rid)
            ids = [i for i, _, _ in events]
            assert ids == sorted(ids) and events[-1][1:] == ("state", {"state": "completed", "reason": None})
            counts = [d["count"] for _, kind, d in events if kind == "samples"]
            assert counts == sorted(counts) and counts[-1] == 18 * 20  # every acquisition's event arrived, in order
            # the queue, the API and the worker all work on
            rid2 = c.call("POST", "/runs", "operator", json={**body, "procedure": "rotate_z",
                                                              "parameters": {"samples": 10, "step_deg": 90}}).json()["id"]
            assert c.wait(rid2, lambda j: j["status"] in ("completed", "failed", "aborted"), timeout=60)["status"] == "completed"
    finally:
        for p in procs:
            _kill(p)


def test_a_station_never_has_two_workers(tmp_path: Path):
    """A second `compasscal worker` of a station that has a live worker, or a single-process
    `compasscal serve` that would drive every station from its own process, is refused naming the
    station and its worker; the first worker carries on."""
    url = fresh_database("postgresql", tmp_path)
    from service.db import Station, make_engine, sessions, upgrade

    engine = make_engine(url)
    upgrade(engine)
    with sessions(engine)() as s:
        s.add(Station(name="lab-w", modbus="tcp://127.0.0.1:9", compasses=["tcp://127.0.0.1:9"], time_scale=1.0))
        s.commit()
    first = _start(["worker", "--station", "lab-w"], url, tmp_path / "first.log")
    try:
        deadline = time.monotonic() + 30
        while True:
            with sessions(engine)() as s:
                row = s.query(Station).filter_by(name="lab-w").one()
                if row.heartbeat_at is not None:
                    break
            assert first.poll() is None and time.monotonic() < deadline, (tmp_path / "first.log").read_text()
            time.sleep(0.2)
        env = {**os.environ, "COMPASSCAL_DATABASE_URL": url}
        # both at once: each first waits a few heartbeats in case the live worker is a dying one
        tries = {tuple(args): subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env,
                                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                 for args in (["worker", "--station", "lab-w"], ["serve", "--port", str(free_port())])}
        for args, proc in tries.items():
            out, _ = proc.communicate(timeout=90)
            said = " ".join(out.split())
            assert proc.returncode == 2 and "station lab-w by" in said and "stop it first" in said, (args, said)
        assert first.poll() is None
    finally:
        _kill(first)
        engine.dispose()


def _batch(c: Client, bid: int, until: Any, timeout: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        b = c.call("GET", f"/batches/{bid}", "viewer").json()
        if until(b):
            return b
        assert time.monotonic() < deadline, b
        time.sleep(0.1)


@contextmanager
def _station_with_worker(tmp_path: Path, seed: int) -> Iterator[tuple[Client, dict[str, Any], str, list[subprocess.Popen[bytes]]]]:
    """An API process and station lab-1 (simulated, time scale 20) with its worker, on a fresh PostgreSQL
    database: the client, the simulator, the database URL and the processes (the worker last; every one
    killed at the end, woken first if stopped)."""
    url = fresh_database("postgresql", tmp_path)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        api, port = _api(url, tmp_path, "api")
        procs.append(api)
        c = Client(port, _keys(url))
        with sim_station(reference_config(seed=seed, time_scale=20)) as info:
            c.station(info, "lab-1")
            procs.append(_start(["worker", "--station", "lab-1"], url, tmp_path / "worker1.log"))
            yield c, info, url, procs
    finally:
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
            _kill(p)


def test_a_batch_ends_with_its_worker_killed_or_stopped_and_frees_the_station(tmp_path: Path):
    """kill -9 of a station's worker mid-batch left the batch "running" for good and every later run on the
    station refused ("busy with batch 1"), whatever was reset or restarted; SIGTERM while a unit waited to be
    mounted left the worker holding the prompt for its 15 minutes, then running the rest of the batch.
    Now a lost worker's batch ends failed, every unit it did not judge named in its summary, the station
    freed; a stopped worker aborts the unit not yet mounted, runs no further unit and exits."""
    with _station_with_worker(tmp_path, seed=5) as (c, info, url, procs):
        worker = procs[-1]
        body = {"station": "lab-1", "serials": ["SN-1", "SN-2", "SN-3"], "parameters": {"samples": 20},
                "serial_policy": "trust-typed"}

        # kill -9 while the first unit is measured
        bid = c.call("POST", "/batches", "operator", json=body).json()["id"]
        b = _batch(c, bid, lambda b: b["prompt"] is not None)
        assert c.call("POST", f"/runs/{b['prompt']['run_id']}/prompts/mount", "operator",
                      json={"answer": "done"}).status_code == 200
        first = c.wait(b["prompt"]["run_id"], lambda j: j["samples_count"] >= 3 * 20)  # past a checkpoint or two
        _kill(worker)
        b = _batch(c, bid, lambda b: b["status"] != "running", timeout=30)
        lost = c.run(first["id"])
        assert lost["status"] == "failed" and "worker lost" in lost["reason"] and lost["samples_count"] > 0, (b, lost)
        assert b["status"] == "failed" and b["summary"]["SN-1"] == f"failed: {lost['reason']}", b
        # the unit it measured is named although its worker never ended the run: by the serial it reported
        reported = info["station"].compasses[0].device.serial
        assert lost["result"]["identities"]["0"]["identified_serial"] == reported != "SN-1", lost["result"]
        assert b["units"][0]["identified_serial"] == reported, b["units"][0]
        assert first["id"] in [r["id"] for r in c.call("GET", f"/runs?serial={reported}", "viewer").json()]
        # its page says why once (the status cell and the summary's line in the verdict cell said it twice)
        page = c.call("GET", f"/ui/batches/{bid}", "viewer")
        assert page.status_code == 200 and "text/html" in page.headers["content-type"], page.text[:300]
        row = re.search(r'<tr data-serial="SN-1">(.*?)</tr>', page.text, re.S).group(1)
        assert row.count("worker lost") == 1, row
        row3 = re.search(r'<tr data-serial="SN-3">(.*?)</tr>', page.text, re.S).group(1)
        assert "not run: station lab-1&#39;s worker stopped beating" in row3, row3
        assert b["summary"]["SN-2"] == b["summary"]["SN-3"] == "not run: station lab-1's worker stopped beating", b
        assert c.call("GET", "/stations/lab-1", "viewer").json()["batch_id"] is None
        listed = c.call("GET", "/batches", "viewer").json()
        assert listed[0]["id"] == bid and listed[0]["summary"] == b["summary"]

        # a new worker; the station reset (the table stopped mid-run) takes runs again
        worker = _start(["worker", "--station", "lab-1"], url, tmp_path / "worker2.log")
        procs.append(worker)
        deadline = time.monotonic() + 30
        while (r := c.call("POST", "/stations/lab-1/reset", "operator")).status_code != 200:
            assert time.monotonic() < deadline, r.text
            time.sleep(0.5)

        # the lost unit resumed on its own: it stays the batch's, whose summary says how it came out
        r = c.call("POST", "/runs", "operator", json={"station": "lab-1", "resume": first["id"]})
        assert r.status_code == 202, r.text
        resumed = c.wait(r.json()["id"], lambda j: j["status"] in ("completed", "failed", "aborted"), timeout=90)
        assert resumed["status"] == "completed" and resumed["batch_id"] == bid, resumed
        b = c.call("GET", f"/batches/{bid}", "viewer").json()
        verdict = resumed["result"]["units"]["0"]["verdict"]
        assert b["summary"]["SN-1"] == f"{verdict} (resumed as run {resumed['id']})", b["summary"]
        assert b["units"][0]["run_id"] == resumed["id"] and b["units"][0]["calibration_id"], b["units"][0]
        assert b["status"] == "failed" and b["summary"]["SN-2"].startswith("not run"), b  # the rest as they were
        # the batches' list counts the resumed unit by its verdict (it counted "PASS (resumed as run N)" as "other")
        page = c.call("GET", "/ui/batches", "viewer").text
        row = re.search(rf'<tr data-batch="{bid}">(.*?)</tr>', page, re.S).group(1)
        assert f'<td class="verdict-{verdict.lower()}">1</td>' in row, row

        # SIGTERM while the next batch's first unit waits to be mounted: the worker exits at once
        bid2 = c.call("POST", "/batches", "operator", json={**body, "serials": ["SN-4", "SN-5"]}).json()["id"]
        b = _batch(c, bid2, lambda b: b["prompt"] is not None)
        t0 = time.monotonic()
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(30) == 0
        assert time.monotonic() - t0 < 15
        b = _batch(c, bid2, lambda b: b["status"] != "running", timeout=5)
        stopped = c.run(b["prompt"]["run_id"] if b["prompt"] else b["units"][0]["run_id"])
        assert stopped["status"] == "aborted" and "not yet mounted" in stopped["reason"], stopped
        assert b["status"] == "failed" and b["summary"]["SN-4"] == f"aborted: {stopped['reason']}", b
        assert b["summary"]["SN-5"].startswith("not run: the station's worker was stopped"), b
        assert c.call("GET", "/stations/lab-1", "viewer").json()["batch_id"] is None



def test_a_worker_stopped_while_its_run_stands_paused_aborts_it_and_exits(tmp_path: Path):
    """SIGTERM to a worker whose run stood paused: it waited, silent, until someone resumed the run (a
    service manager then kills it, and the run ends "worker lost"). The paused run is now aborted with a
    reason that says how to resume it, and the worker exits."""
    with _station_with_worker(tmp_path, seed=8) as (c, info, url, procs):
        worker = procs[-1]
        r = c.call("POST", "/runs", "operator", json={"station": "lab-1", "procedure": "rotate_z",
                                                       "parameters": {"samples": 40, "step_deg": 20}})
        rid = r.json()["id"]
        c.wait(rid, lambda j: j["status"] == "running")
        assert c.call("PUT", f"/runs/{rid}/state", "operator", json={"state": "paused"}).status_code == 202
        c.wait(rid, lambda j: j["status"] == "paused")
        t0 = time.monotonic()
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(30) == 0
        assert time.monotonic() - t0 < 20
        j = c.wait(rid, lambda j: j["status"] in ("aborted", "failed", "completed"), timeout=10)
        assert j["status"] == "aborted" and "stood paused" in j["reason"] and f'"resume": {rid}' in j["reason"], j
        assert j["samples_count"] > 0, j

def test_a_worker_that_wakes_from_a_freeze_leaves_what_was_ended_without_it(tmp_path: Path):
    """A worker frozen (SIGSTOP: a PC that hangs, a debugger) is taken for lost: its run failed, its batch
    ended, the station in fault. Woken, it drove the table through the rest of the plan, adding samples and
    events to the failed run, and rewrote the batch's summary; and an answer to a prompt of the frozen run
    got 200 although no worker ever took it. Now the answer gets 409, and the woken worker stops its axes
    at once, keeps no further sample and leaves the run and the batch as they were ended."""
    with _station_with_worker(tmp_path, seed=6) as (c, info, _, procs):
        worker = procs[-1]

        # frozen while a batch's unit waits to be mounted: the answer is refused once the run has ended
        bid = c.call("POST", "/batches", "operator", json={"station": "lab-1", "serials": ["SN-1", "SN-2"],
                                                            "parameters": {"samples": 20}}).json()["id"]
        b = _batch(c, bid, lambda b: b["prompt"] is not None)
        os.killpg(worker.pid, signal.SIGSTOP)
        r = c.call("POST", f"/runs/{b['prompt']['run_id']}/prompts/mount", "operator", json={"answer": "done"})
        assert r.status_code == 409 and "before its worker took the answer" in r.text, r.text
        ended = _batch(c, bid, lambda b: b["status"] != "running", timeout=30)
        assert ended["status"] == "failed" and "worker lost" in ended["summary"]["SN-1"], ended
        os.killpg(worker.pid, signal.SIGCONT)
        time.sleep(3)  # many of the woken worker's command polls
        assert c.call("GET", f"/batches/{bid}", "viewer").json()["summary"] == ended["summary"]
        assert c.run(b["prompt"]["run_id"])["samples_count"] == 0

        # frozen while a run measures: woken, it stops, and the failed run keeps what it had
        while (r := c.call("POST", "/stations/lab-1/reset", "operator")).status_code != 200:
            time.sleep(0.5)
        rid = c.call("POST", "/runs", "operator", json={"station": "lab-1", "procedure": "calibrate",
                                                         "parameters": {"samples": 20}}).json()["id"]
        c.wait(rid, lambda j: j["samples_count"] > 0)
        os.killpg(worker.pid, signal.SIGSTOP)
        lost = c.wait(rid, lambda j: j["status"] == "failed", timeout=30)
        kept, events = lost["samples_count"], c.events(rid)
        assert "worker lost" in lost["reason"] and 0 < kept < 18 * 20, lost
        os.killpg(worker.pid, signal.SIGCONT)
        time.sleep(3)
        now = c.run(rid)
        assert (now["status"], now["reason"], now["samples_count"]) == ("failed", lost["reason"], kept), now
        later = [e for e in c.events(rid) if e[0] > events[-1][0]]
        assert [k for _, k, _ in later] in ([], ["step"]), later  # at most the worker's word that it stopped
        assert all("ended meanwhile" in d["warning"] for _, _, d in later), later
        assert all(ax.mode not in ("move", "jog") for ax in info["station"].table.axes.values())
        assert c.call("GET", "/stations/lab-1", "viewer").json()["state"] == "fault"


def test_a_batch_no_worker_has_taken_is_aborted_at_once(tmp_path: Path):
    """A batch queued on a station whose worker is down could not be aborted: it stayed "aborting", a second
    abort was refused, and every run or batch on that station was "busy with batch N" until a worker came.
    Its job is now cancelled and it ends at once, as an unstarted run does."""
    url = fresh_database("postgresql", tmp_path)
    api, port = _api(url, tmp_path, "api")
    try:
        c = Client(port, _keys(url))
        c.station({"modbus": "tcp://127.0.0.1:1", "compasses": [{"url": "socket://127.0.0.1:2"}]}, "lab-9")
        r = c.call("POST", "/batches", "operator", json={"station": "lab-9", "serials": ["SN-1", "SN-2"]})
        assert r.status_code == 202, r.text
        bid = r.json()["id"]
        r = c.call("PUT", f"/batches/{bid}/state", "operator", json={"state": "aborted"})
        assert r.status_code == 202 and r.json()["status"] == "aborted", r.text
        b = c.call("GET", f"/batches/{bid}", "viewer").json()
        assert b["status"] == "aborted", b
        assert all(v.startswith("not run: the batch was aborted before") for v in b["summary"].values()), b["summary"]
        assert [u["status"] for u in b["units"]] == ["not run", "not run"] and b["tally"]["pending"] == 0, b["units"]
        # the station is free again: a run can be queued on it (and aborted the same way)
        r = c.call("POST", "/runs", "operator", json={"station": "lab-9", "procedure": "calibrate"})
        assert r.status_code == 202, r.text
        assert c.call("PUT", f"/runs/{r.json()['id']}/state", "operator", json={"state": "aborted"}).status_code == 202
        # a reset no worker takes in time is cancelled, not left to run whenever a worker comes (unasked)
        r = c.call("POST", "/stations/lab-9/reset", "operator")
        assert r.status_code == 503 and "so it was cancelled" in r.text, r.text
        import psycopg

        with psycopg.connect(url.replace("postgresql+psycopg://", "postgresql://")) as conn:
            left = conn.execute("select count(*) from procrastinate_jobs where task_name = 'compasscal.reset' "
                                "and status = 'todo'").fetchone()[0]
        assert left == 0
    finally:
        _kill(api)


def test_a_resumed_unit_settles_its_batch():
    """A batch that failed because its worker was lost mid-unit stayed "failed" beside "1 pass" once that
    unit was resumed and passed. Resumed, the unit's line says how it came out, and a batch whose units
    have all run, some calibrated, is completed; with units never run it stays failed."""
    from service.db import Batch
    from service.runtime import settle_resumed_unit

    lone = Batch(serials=["SN-1"], status="failed", summary={"SN-1": "failed: worker lost"})
    settle_resumed_unit(lone, "SN-1", "PASS (resumed as run 19)")
    assert lone.status == "completed" and lone.summary == {"SN-1": "PASS (resumed as run 19)"}
    rest = Batch(serials=["SN-1", "SN-2"], status="failed",
                 summary={"SN-1": "failed: worker lost", "SN-2": "not run: station lab-1's worker stopped beating"})
    settle_resumed_unit(rest, "SN-1", "MARGINAL (resumed as run 20)")
    assert rest.status == "failed" and rest.summary["SN-1"] == "MARGINAL (resumed as run 20)"
    again = Batch(serials=["SN-1"], status="failed", summary={"SN-1": "failed: worker lost"})
    settle_resumed_unit(again, "SN-1", "failed: compass timeout (resumed as run 21)")
    assert again.status == "failed"
    aborted = Batch(serials=["SN-1"], status="aborted", summary={"SN-1": "aborted: stop"})
    settle_resumed_unit(aborted, "SN-1", "PASS (resumed as run 22)")
    assert aborted.status == "aborted"
