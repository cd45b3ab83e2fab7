"""Stations, runs and batches through the REST API, against a simulated station over the real
protocols, on SQLite and on PostgreSQL (the ``api`` fixture): auth, validation, calibration runs and
their history, pause/resume/abort, server-sent events, a fault mid-run and the station's reset,
and a batch answered prompt by prompt."""

from __future__ import annotations

import json
import re
import time
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select

from conftest import Api, parse_sse, sim_station
from drivers.sim.config import parse_fault, reference_config
from physics.recording import parse_recording
from service.db import AuditLog

FINAL = ("completed", "failed", "aborted")


def make_station(api: Api, info: dict[str, Any], name: str = "lab-1") -> dict[str, Any]:
    r = api.post("/stations", json={"name": name, "modbus": info["modbus"],
                                    "compasses": [c["url"] for c in info["compasses"]], "time_scale": 20})
    assert r.status_code == 201, r.text
    return r.json()


def mount(info: dict[str, Any], serial: str, slot: int = 0) -> None:
    """Put another unit in a simulated station's slot: its compass reports ``serial`` from now on."""
    info["station"].compasses[slot].device.serial = serial


def wait_run(api: Api, run_id: int, until: tuple[str, ...] = FINAL, timeout: float = 40.0) -> dict[str, Any]:
    """Poll the run until its status is one of ``until``."""
    deadline = time.monotonic() + timeout
    while True:
        j = api.get(f"/runs/{run_id}", role="viewer").json()
        if j["status"] in until:
            return j
        assert time.monotonic() < deadline, f"run {run_id} still {j['status']} after {timeout} s"
        time.sleep(0.05)


def read_events(api: Api, run_id: int, last: int | None = None) -> list[tuple[str, dict[str, Any]]]:
    """The run's server-sent events until the stream closes (after event ``last``, if given)."""
    return [(k, d) for _, k, d in _stream(api, run_id, last)]


def read_event_ids(api: Api, run_id: int) -> list[int]:
    return [i for i, _, _ in _stream(api, run_id, None)]


def _stream(api: Api, run_id: int, last: int | None) -> list[tuple[int, str, dict[str, Any]]]:
    headers = {"X-API-Key": api.keys["viewer"], **({"Last-Event-ID": str(last)} if last is not None else {})}
    with api.client.stream("GET", f"/runs/{run_id}/events", headers=headers) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        return parse_sse(r.iter_lines())


def audited(api: Api, action: str) -> list[AuditLog]:
    with api.client.app.state.sessions() as s:
        return list(s.scalars(select(AuditLog).where(AuditLog.action == action)))


def test_stations_need_admin_and_requests_are_validated(api: Api):
    body = {"name": "lab-1", "modbus": "tcp://127.0.0.1:1502", "compasses": ["socket://127.0.0.1:4001"]}
    assert api.post("/stations", role=None, json=body).status_code == 401
    assert api.post("/stations", role="viewer", json=body).status_code == 403
    assert api.post("/stations", role="operator", json=body).status_code == 403
    r = api.post("/stations", json=body)
    assert r.status_code == 201 and r.json()["state"] == "idle" and r.json()["time_scale"] == 1.0
    assert api.post("/stations", json=body).status_code == 409
    assert [a.owner for a in audited(api, "station.create")] == ["admin-user"]
    bad = api.post("/stations", json={**body, "name": "lab-2", "modbus": "ftp://x"})
    assert bad.status_code == 422 and bad.json()["detail"][0]["field"] == "body.modbus"
    assert api.get("/stations", role=None).status_code == 401
    assert [s["name"] for s in api.get("/stations", role="viewer").json()] == ["lab-1"]
    assert api.get("/stations/nope", role="viewer").status_code == 404

    # runs: unknown station and run 404; unknown procedure and bad parameters 422 naming the field
    run = {"station": "lab-1", "procedure": "calibrate", "parameters": {"samples": 20}}
    assert api.post("/runs", role="viewer", json=run).status_code == 403
    assert api.post("/runs", role="operator", json={**run, "station": "nope"}).status_code == 404
    r = api.post("/runs", role="operator", json={**run, "procedure": "dance"})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.procedure" and "calibrate" in r.json()["detail"][0]["problem"]
    r = api.post("/runs", role="operator", json={**run, "parameters": {"samples": 0}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.parameters.samples"
    # a batch's unit outside a batch (its serial would go unchecked); more slots than a station can have
    # (200 000 serials held the service for minutes: a quadratic check on the event loop)
    r = api.post("/runs", role="operator", json={**run, "procedure": "batch_calibrate", "parameters": {"serial": "Q1"}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.procedure" and "POST /batches" in r.text
    # a misspelt filter is named, not ignored (every run came back as if it were the unit's)
    r = api.get("/runs?serail=SN-1&limit=5", role="viewer")
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "query.serail" and "serial" in r.text, r.text
    assert api.get("/runs?serial=SN-1&limit=5", role="viewer").status_code == 200
    r = api.post("/runs", role="operator", json={**run, "serials": {"0": "SN-2", "00": "SN-1"}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.serials.00" and "twice" in r.text, r.text
    r = api.post("/runs", role="operator", json={**run, "serials": {str(i): f"S{i}" for i in range(20000)}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.serials", r.text
    from physics.calibration import Calibration, json_safe
    from physics.sensor import LinearSensor
    cal = json_safe(Calibration(method="joint", mag=LinearSensor.from_matrix(1000.0 * np.eye(3), np.zeros(3))).to_json())
    r = api.post("/runs", role="operator", json={**run, "procedure": "evaluate", "parameters": {"calibrations": {"5": cal}}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.parameters.calibrations.5", r.text
    # a batch mounts one unit in slot 0: a station of two slots would certify the other slot's unit too
    two = {**body, "name": "lab-2", "modbus": "tcp://127.0.0.1:1503", "compasses": ["socket://127.0.0.1:4002", "socket://127.0.0.1:4003"]}
    # one table or compass belongs to one station; a URL no driver opens, or one compass for two slots: 422
    shared = api.post("/stations", json={**two, "modbus": body["modbus"]})
    assert shared.status_code == 409 and "already has table" in shared.text
    assert api.post("/stations", json={**two, "compasses": ["socket://127.0.0.1:4001"]}).status_code == 409
    # however a URL spells it: the host's name, the framing or a timeout do not make another device (a probe's
    # station on "tcp://...?timeout=0.8" and "socket://localhost:..." moved the first one's table mid-run)
    port = body["modbus"].rsplit(":", 1)[1]
    for modbus in (f"tcp://localhost:{port}?timeout=0.8", f"rtu+tcp://127.0.0.1:{port}"):
        r = api.post("/stations", json={**two, "modbus": modbus})
        assert r.status_code == 409 and "already has table" in r.text and f"(as {body['modbus']})" in r.text, r.text
    # a URL the CLI refuses, the API refuses too (it took them; the first run then put the station in fault)
    for modbus, words in (("tcp://127.0.0.1", "no port"), ("127.0.0.1:1503", "give tcp://127.0.0.1:1503")):
        r = api.post("/stations", json={**two, "modbus": modbus})
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.modbus" and words in r.text, r.text
    r = api.post("/stations", json={**two, "compasses": ["socket://localhost:4001"]})
    assert r.status_code == 409 and "already has compass" in r.text, r.text
    # a station stored before a URL without its port was refused does not make every check fail (500)
    from service.db import Station

    with api.client.app.state.sessions() as s:
        s.add(Station(name="old-1", modbus="tcp://10.9.9.9", compasses=["socket://10.9.9.9:4009"], time_scale=1.0,
                      state="idle", serial_policy="prompt"))
        s.commit()
    r = api.post("/stations", json={**two, "name": "lab-3", "modbus": "tcp://127.0.0.1:1509",
                                    "compasses": ["socket://127.0.0.1:4019"]})
    assert r.status_code == 201, r.text
    r = api.post("/stations", json={**two, "compasses": ["socket://127.0.0.1:4002", "socket://LOCALHOST:4002"]})
    assert r.status_code == 422 and "two slots" in r.text, r.text
    for compasses, words in ((["ftp://x"], "protocol 'ftp' not known"), (["/dev/ttyS7", "/dev/ttyS7"], "two slots")):
        r = api.post("/stations", json={**two, "compasses": compasses})
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.compasses" and words in r.text, r.text
    assert api.post("/stations", json=two).status_code == 201
    r = api.post("/batches", role="operator", json={"station": "lab-2", "serials": ["SN-1", "SN-2"]})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.station" and "2 compass slots" in r.text
    r = api.post("/runs", role="operator", json={**run, "parameters": {"z_step": 10}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.parameters.z_step"
    # a field no body knows is an error, not silently the default (a misspelt serial policy left the
    # station's as it was; "serial" for "serials" started a run with none typed); true is no number;
    # "nan" is no number, not a number out of range
    for path, method, extra, field in (("/stations/lab-1", "put", {k: v for k, v in body.items() if k != "name"} | {"serial_polcy": "refuse"},
                                        "body.serial_polcy"),
                                       ("/runs", "post", {**run, "serial": {"0": "SN-1"}}, "body.serial"),
                                       ("/batches", "post", {"station": "lab-1", "serials": ["A"], "extra": 1}, "body.extra"),
                                       ("/runs", "post", {**run, "parameters": {"samples": True}}, "body.parameters.samples"),
                                       ("/runs", "post", {**run, "parameters": {"z_step_deg": "nan"}}, "body.parameters.z_step_deg")):
        r = getattr(api, method)(path, role="admin" if method == "put" else "operator", json=extra)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == field, (path, r.text)
    assert "not the string 'nan'" in r.text
    # parameters no station could run are refused before the station is claimed (they were accepted,
    # then failed on the table with a Python error, or turned it round twice), a batch's too; "60" is no
    # number; a plan of days is refused whole
    for path, extra, field, words in (
            ("/runs", {**run, "parameters": {"tilt_step_deg": 1e-300}}, "body.parameters.tilt_step_deg", "greater than or equal to 1"),
            ("/runs", {**run, "parameters": {"sweep_psi_deg": 1e308}}, "body.parameters.sweep_psi_deg", "less than or equal to 360"),
            ("/runs", {**run, "parameters": {"sweep_psi_deg": -720.5}}, "body.parameters.sweep_psi_deg", "-360"),
            ("/runs", {**run, "parameters": {"samples": "60"}}, "body.parameters.samples", "not the string '60'"),
            ("/runs", {**run, "parameters": {"z_step_deg": 1, "tilt_step_deg": 1, "samples": 10000}}, "body.parameters",
             "h of table time"),
            ("/batches", {"station": "lab-1", "serials": ["SN-1"], "parameters": {"z_step_deg": 0.001}},
             "body.parameters.z_step_deg", "greater than or equal to 1")):
        r = api.post(path, role="operator", json=extra)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == field and words in r.text, (extra, r.text)
    assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
    # what parameters each procedure takes, with the ranges refused above, for a script to read first
    procs = {p["name"]: p for p in api.get("/procedures", role="viewer").json()}
    assert set(procs) >= {"calibrate", "rotate_z", "sweep", "evaluate", "characterize", "batch_calibrate"}
    z_step = procs["calibrate"]["parameters"]["properties"]["z_step_deg"]
    assert (z_step["default"], z_step["minimum"], z_step["maximum"]) == (45.0, 1.0, 120.0)
    assert procs["calibrate"]["parameters"]["properties"]["sweep_psi_deg"]["minimum"] == -360.0
    assert api.get("/procedures", role=None).status_code == 401
    assert api.get("/stations/lab-1", role="viewer").json()["serial_policy"] == "prompt"
    # the body a station was made with may be PUT again (its name the path's); another name is refused
    assert api.put("/stations/lab-1", json=body).status_code == 200
    r = api.put("/stations/lab-1", json={**body, "name": "lab-9"})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.name" and "keeps its name" in r.text, r.text
    r = api.post("/runs", role="operator", json={**run, "serials": {"3": "SN-1"}})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.serials.3"
    assert api.post("/runs", role="operator", json={"procedure": "calibrate"}).json()["detail"][0]["field"] == "body.station"
    for path in ("/runs/999", "/runs/999/events", "/runs/999/samples", "/batches/999"):
        assert api.get(path, role="viewer").status_code == 404, path
    assert api.put("/runs/999/state", role="operator", json={"state": "paused"}).status_code == 404
    assert api.post("/runs/999/prompts/mount", role="operator", json={"answer": "ok"}).status_code == 404
    r = api.post("/runs/999/prompts/mount", role="operator", json={})  # an empty body is no answer
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.answer", r.text
    assert api.put("/runs/999/state", role="operator", json={"state": "dancing"}).status_code == 422
    assert api.post("/batches", role="operator", json={"station": "nope", "serials": ["A"]}).status_code == 404
    r = api.post("/batches", role="operator", json={"station": "lab-1", "serials": ["A", "A"]})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.serials"
    assert api.get("/runs", role="viewer").json() == []


def test_an_unreachable_station_fails_the_run_and_stays_in_fault(api: Api):
    api.post("/stations", json={"name": "dead", "modbus": "tcp://127.0.0.1:9", "compasses": ["socket://127.0.0.1:9"]})
    r = api.post("/runs", role="operator", json={"station": "dead", "parameters": {"samples": 5}})
    assert r.status_code == 202
    j = wait_run(api, r.json()["id"])
    assert j["status"] == "failed" and "could not open station dead" in j["reason"]
    st = api.get("/stations/dead", role="viewer").json()
    assert st["state"] == "fault" and "could not open" in st["fault"]
    r = api.post("/runs", role="operator", json={"station": "dead"})
    assert r.status_code == 409 and "fault" in r.json()["detail"]
    r = api.post("/stations/dead/reset", role="operator")
    assert r.status_code == 503 and api.get("/stations/dead", role="viewer").json()["state"] == "fault"
    assert api.get("/health", role=None).json()["status"] == "ok"  # the service is fine


def test_calibration_runs_store_history_and_stream_events(api: Api):
    with sim_station(reference_config(seed=1, time_scale=20)) as info:
        make_station(api, info)
        body = {"station": "lab-1", "procedure": "calibrate", "parameters": {"samples": 20}}
        r = api.post("/runs", role="operator", json=body)
        assert r.status_code == 202, r.text
        first = r.json()
        assert first["status"] == "queued" and first["station"] == "lab-1" and first["procedure"] == "calibrate"
        assert first["parameters"]["samples"] == 20 and first["operator"] == "operator-user"
        busy = api.post("/runs", role="operator", json=body)
        assert busy.status_code == 409 and f"run {first['id']}" in busy.json()["detail"]
        station = api.get("/stations/lab-1", role="viewer").json()
        assert station["state"] == "running" and station["run_id"] == first["id"] and station["run"]["id"] == first["id"]

        done = wait_run(api, first["id"])
        assert done["status"] == "completed", done["reason"]
        assert done["serials"] == {"0": "GAO2017-REF"}  # the compass's own serial number
        assert done["station_snapshot"]["modbus"] == info["modbus"] and done["station_snapshot"]["time_scale"] == 20
        assert done["procedure_version"] and done["software_version"] and done["started_at"] and done["finished_at"]
        assert done["samples_count"] == 18 * 20 and done["table_seconds"] > 0
        unit = done["result"]["units"]["0"]
        assert unit["serial"] == "GAO2017-REF" and unit["verdict"] in ("PASS", "MARGINAL")
        cal = api.get("/devices/GAO2017-REF/calibrations/current", role="viewer").json()
        assert cal["run_id"] == first["id"] and cal["status"] == "current" and cal["verdict"] in ("PASS", "MARGINAL")
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        illegal = api.put(f"/runs/{first['id']}/state", role="operator", json={"state": "paused"})
        assert illegal.status_code == 409 and "completed -> paused" in illegal.json()["detail"]

        # the samples as a RECORDING.md CSV
        r = api.get(f"/runs/{first['id']}/samples", role="viewer")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
        rec = parse_recording(r.text)
        assert len(rec) == 18 * 20 and rec.serial == "GAO2017-REF" and rec.meta["run_id"] == str(first["id"])
        assert api.get(f"/runs/{first['id']}/samples?slot=1", role="viewer").status_code == 404

        # a second run supersedes the first; its events stream live until it ends
        r = api.post("/runs", role="operator", json=body)
        assert r.status_code == 202, r.text
        second = r.json()["id"]
        events = read_events(api, second)
        kinds = [k for k, _ in events]
        assert {"state", "step", "progress", "samples", "result"} <= set(kinds)
        progress = [d["percent"] for k, d in events if k == "progress"]
        assert progress == sorted(progress) and progress[-1] == 100.0
        assert events[-1] == ("state", {"state": "completed", "reason": None})
        assert [d["state"] for k, d in events if k == "state"] == ["queued", "running", "completed"]
        assert api.get(f"/runs/{second}", role="viewer").json()["status"] == "completed"
        history = api.get("/devices/GAO2017-REF/calibrations", role="viewer").json()
        assert [(h["run_id"], h["status"]) for h in history] == [(second, "current"), (first["id"], "superseded")]

        # a finished run's history replays from the database, whole, to any process; Last-Event-ID resumes
        replay = read_events(api, first["id"])
        assert replay[0] == ("state", {"state": "queued", "reason": None}) and replay[-1] == events[-1]
        assert {"step", "progress", "samples", "result"} <= {k for k, _ in replay}
        ids = read_event_ids(api, second)
        assert ids == sorted(ids) and len(ids) == len(events)
        tail = read_events(api, second, last=ids[-3])
        assert tail == events[-2:]
        assert read_events(api, second, last=10**25) == []  # beyond any id (SQLite overflowed: a 500 in the stream)

        # listing: newest first, filters, pagination
        runs = api.get("/runs", role="viewer").json()
        assert [x["id"] for x in runs] == [second, first["id"]]
        assert [x["id"] for x in api.get("/runs?limit=1&offset=1", role="viewer").json()] == [first["id"]]
        assert len(api.get("/runs?serial=GAO2017-REF&status=completed&station=lab-1&procedure=calibrate", role="viewer").json()) == 2
        assert api.get("/runs?serial=GAO2017", role="viewer").json() == []
        # a station no run can have is a mistake, named (it listed nothing, as if the station had made no run)
        r = api.get("/runs?station=other", role="viewer")
        assert r.status_code == 422 and r.json()["detail"][0] == {"field": "query.station",
                                                                  "problem": "no station 'other'; known: lab-1"}, r.text
        assert [a.owner for a in audited(api, "run.start")] == ["operator-user"] * 2


def test_pause_resume_and_abort_keep_the_samples(api: Api):
    with sim_station(reference_config(seed=5, time_scale=20)) as info:
        make_station(api, info)
        r = api.post("/runs", role="operator", json={"station": "lab-1", "procedure": "rotate_z",
                                                      "parameters": {"samples": 40, "step_deg": 20}})
        rid = r.json()["id"]
        wait_run(api, rid, ("running",))
        r = api.put(f"/runs/{rid}/state", role="operator", json={"state": "paused", "reason": "coffee"})
        assert r.status_code == 202 and r.json()["requested"] == "paused"
        paused = wait_run(api, rid, ("paused",) + FINAL)
        assert paused["status"] == "paused"
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "paused"
        r = api.put(f"/runs/{rid}/state", role="operator", json={"state": "paused"})
        assert r.status_code == 409 and "paused -> paused" in r.json()["detail"]
        assert api.put(f"/runs/{rid}/state", role="viewer", json={"state": "running"}).status_code == 403
        n = api.get(f"/runs/{rid}", role="viewer").json()["samples_count"]
        time.sleep(0.3)
        assert api.get(f"/runs/{rid}", role="viewer").json()["samples_count"] == n  # held still
        assert api.put(f"/runs/{rid}/state", role="operator", json={"state": "running"}).status_code == 202
        wait_run(api, rid, ("running",) + FINAL)
        r = api.put(f"/runs/{rid}/state", role="operator", json={"state": "aborted", "reason": "wrong unit"})
        assert r.status_code == 202
        j = wait_run(api, rid)
        assert j["status"] == "aborted" and j["reason"] == "wrong unit"
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        rec = parse_recording(api.get(f"/runs/{rid}/samples", role="viewer").text)
        assert 0 < len(rec) < 18 * 40 and len(rec) % 40 == 0
        states = [d["state"] for k, d in read_events(api, rid) if k == "state"]
        assert states == ["queued", "running", "paused", "running", "aborted"]
        assert [a.detail["state"] for a in audited(api, "run.state")] == ["paused", "running", "aborted"]


def _run_with_fault(api: Api, info: dict[str, Any], fault: dict[str, Any]) -> dict[str, Any]:
    """Register simulated station ``info`` as lab-1, inject ``fault`` (the [[fault]] keys) and run a calibration
    to its end: the run as GET /runs/{id} gives it."""
    make_station(api, info)
    info["loop"].call_soon_threadsafe(info["station"].inject, parse_fault(fault))
    r = api.post("/runs", role="operator", json={"station": "lab-1", "parameters": {"samples": 20}})
    return wait_run(api, r.json()["id"])


def test_an_axis_fault_mid_run_fails_it_and_the_station_until_reset(api: Api):
    with sim_station(reference_config(seed=3, time_scale=20)) as info:
        j = _run_with_fault(api, info, {"kind": "axis_alarm", "axis": "y", "code": 48, "at_angle_deg": 100})
        assert j["status"] == "failed" and "overload" in j["reason"] and "axis y" in j["reason"]
        assert j["samples_count"] == 9 * 20  # the level turn and the first sweep pose
        # an ended run has no time left (its last progress event still counted some)
        assert j["progress"]["left_s"] == j["progress"]["left_wall_s"] == 0.0, j["progress"]
        assert j["progress"]["samples"] == j["samples_count"], j["progress"]  # the samples kept, not a pose's before
        # its page draws what it kept and links the samples (it showed neither), its step line the last step
        page = api.get(f"/ui/runs/{j['id']}", role="viewer").text
        assert f'href="/runs/{j["id"]}/samples?slot=0"' in page and "180 kept" in page and 'class="samples-plot"' in page
        assert '<span class="label">last step</span>' in page
        st = api.get("/stations/lab-1", role="viewer").json()
        assert st["state"] == "fault" and "overload" in st["fault"] and st["run_id"] is None
        assert api.post("/runs", role="operator", json={"station": "lab-1"}).status_code == 409
        assert api.post("/stations/lab-1/reset", role="viewer").status_code == 403
        r = api.post("/stations/lab-1/reset", role="operator")
        assert r.status_code == 200, r.text
        assert r.json()["state"] == "idle" and r.json()["reset_axes"] == ["y"]
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        assert [a.owner for a in audited(api, "station.reset")] == ["operator-user"]


def test_a_compass_that_stops_talking_puts_the_station_in_fault_until_it_answers(api: Api):
    """A compass silent mid-run failed the run but left the station "idle" (the next run failed at its
    identification), and a reset said "idle" with the compass still silent."""
    with sim_station(reference_config(seed=3, time_scale=20)) as info:
        j = _run_with_fault(api, info, {"kind": "compass_silent", "slot": 0, "at_s": 20.0})
        assert j["status"] == "failed" and "Compass" in j["reason"] and j["samples_count"] > 0, j["reason"]
        assert j["progress"]["samples"] == j["samples_count"], j["progress"]  # the samples kept, not a pose's before
        st = api.get("/stations/lab-1", role="viewer").json()
        assert st["state"] == "fault" and st["run_id"] is None, st
        # the fault says what to do before a reset (it said what went wrong only)
        assert "to clear it: check the compass's cable and power" in st["fault"], st["fault"]
        r = api.post("/stations/lab-1/reset", role="operator")
        assert r.status_code == 503 and "compass slot 0 does not answer" in r.text and "cable" in r.text, r.text
        # the silent compasses by slot beside the sentence, as a script reads them (the sentence only before)
        assert list(r.json()["silent_compasses"]) == ["0"] and r.json()["still_faulted"] == {}, r.json()
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "fault"
        info["loop"].call_soon_threadsafe(info["station"].clear_faults)
        r = api.post("/stations/lab-1/reset", role="operator")
        assert r.status_code == 200 and r.json()["state"] == "idle" and r.json()["silent_compasses"] == {}, r.text


def test_a_compass_that_resets_itself_mid_run_is_said_in_the_run(api: Api):
    """A compass that reset itself mid-run had its settings applied again by its driver and the run went on
    to PASS: only the worker's log said so. The run's events now carry a warning naming the slot and step."""
    with sim_station(reference_config(seed=3, time_scale=20)) as info:
        j = _run_with_fault(api, info, {"kind": "compass_reset", "slot": 0, "at_s": 15.0})
        assert j["status"] == "completed", j["reason"]
        said = [d["warning"] for k, d in read_events(api, j["id"]) if k == "step" and "warning" in d]
        assert any("slot 0: the compass reset itself during" in w and "settings were applied again" in w
                   for w in said), said


def test_a_batch_prompts_to_mount_each_unit_and_summarises(api: Api):
    with sim_station(reference_config(seed=8, time_scale=20)) as info:
        make_station(api, info)
        r = api.post("/batches", role="operator", json={"station": "lab-1", "serials": ["SN-A", "SN-B"],
                                                         "parameters": {"samples": 20}})
        assert r.status_code == 202, r.text
        bid = r.json()["id"]
        busy = api.post("/runs", role="operator", json={"station": "lab-1"})
        assert busy.status_code == 409
        answered, deadline = [], time.monotonic() + 60
        while True:
            b = api.get(f"/batches/{bid}", role="viewer").json()
            if b["status"] != "running":
                break
            assert time.monotonic() < deadline, b
            # every unit counted once: by its verdict once its calibration is judged, else as pending
            assert sum(b["tally"].values()) == 2 and b["tally"]["uncalibrated"] == 0, b["tally"]
            if b["prompt"]:
                run_id, text = b["prompt"]["run_id"], b["prompt"]["text"]
                assert b["prompt"]["id"] == "mount"
                # the operator swaps units on a level platform at home, not where the last plan ended (rolled)
                axes = info["station"].table.axes
                assert all(abs(axes[a].position_deg()) < 0.01 for a in "zyx"), {a: axes[a].position_deg() for a in "zyx"}
                assert api.post(f"/runs/{run_id}/prompts/unmount", role="operator", json={"answer": "x"}).status_code == 404
                mount(info, ["SN-A", "SN-B"][len(answered)])  # the unit it names, which reports its own serial
                # a mount prompt has one answer: "skip" went on, and the unit was measured and certified
                r = api.post(f"/runs/{run_id}/prompts/mount", role="operator", json={"answer": "skip"})
                assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.answer" and "'done'" in r.text
                r = api.post(f"/runs/{run_id}/prompts/mount", role="operator", json={"answer": " Done "})
                assert r.status_code == 200, r.text
                answered.append(text)
            time.sleep(0.05)
        assert answered[0] == "mount unit SN-A in slot 0"
        assert answered[1].startswith("unmount unit SN-A (") and answered[1].endswith("then mount unit SN-B in slot 0")
        assert b["status"] == "completed" and b["station"] == "lab-1"
        assert set(b["summary"]) == {"SN-A", "SN-B"} and set(b["summary"].values()) <= {"PASS", "MARGINAL"}, b["summary"]
        assert [(u["serial"], u["status"]) for u in b["units"]] == [("SN-A", "completed"), ("SN-B", "completed")]
        verdicts = list(b["summary"].values())
        assert b["tally"] == {"pass": verdicts.count("PASS"), "marginal": verdicts.count("MARGINAL"), "fail": 0,
                              "uncalibrated": 0, "pending": 0}, b["tally"]
        for u in b["units"]:
            run = api.get(f"/runs/{u['run_id']}", role="viewer").json()
            assert run["batch_id"] == bid and run["procedure"] == "batch_calibrate" and run["serials"] == {"0": u["serial"]}
            assert run["result"]["units"]["0"]["identified_serial"] == u["serial"]  # identified once mounted
            assert u["verdict"] == b["summary"][u["serial"]] and u["calibration_status"] == "current"
            assert u["table_seconds"] == run["table_seconds"] > 0 and u["target"] is None  # not adaptive
            cur = api.get(f"/devices/{u['serial']}/calibrations/current", role="viewer").json()
            assert cur["run_id"] == u["run_id"]
            # its certificate lists the calibration's parameters, not the batch's own (serial, unmount = None)
            params = re.search(r'<p class="params-line">(.*?)</p>', api.get(
                f"/ui/calibrations/{cur['id']}/certificate", role="viewer").text, re.S).group(1)
            assert "samples = 20" in params and "unmount" not in params and "serial =" not in params, params
            # nor, not adaptive, the targets and budget it never read ("budget_s = 180.0" was listed)
            assert "adaptive = False" in params and "budget_s" not in params and "target_level_deg" not in params, params
        assert api.get("/stations/lab-1", role="viewer").json()["batch_id"] is None
        assert len(audited(api, "run.prompt")) == 2 and len(audited(api, "batch.start")) == 1
        # listed, newest first, filtered by station and status
        listed = api.get("/batches", role="viewer").json()
        assert [x["id"] for x in listed] == [bid] and listed[0]["summary"] == b["summary"]
        assert api.get("/batches?station=lab-1&status=completed", role="viewer").json()[0]["id"] == bid
        assert api.get("/batches?status=running", role="viewer").json() == []
        # a filter no run or batch can match is a mistake, named (before: an empty list, as if none existed)
        for url, field in (("/runs?status=bogus", "query.status"), ("/runs?procedure=bogus", "query.procedure"),
                           ("/batches?status=bogus", "query.status"), ("/batches?station=nowhere", "query.station")):
            r = api.get(url, role="viewer")
            assert r.status_code == 422 and r.json()["detail"][0]["field"] == field, (url, r.text)


def test_an_interrupted_calibration_resumes_from_its_last_checkpoint(api: Api):
    """A calibration aborted mid-way is resumed by a new run (``resume``): the steps up to the last
    checkpoint it passed are its samples, taken over as they were; the table goes on from there and
    the calibration completes as a whole one would. Refusals name the field or the reason."""
    with sim_station(reference_config(seed=11, time_scale=20)) as info:
        make_station(api, info)
        body = {"station": "lab-1", "procedure": "calibrate", "parameters": {"samples": 20}}
        first = api.post("/runs", role="operator", json=body).json()["id"]
        deadline = time.monotonic() + 60
        # six checkpoints passed once a seventh pose's samples are in (the sixth pose's samples may be
        # stored just before its checkpoint, where an abort can fall: CI once saw five)
        while api.get(f"/runs/{first}", role="viewer").json()["samples_count"] < 7 * 20:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        api.put(f"/runs/{first}/state", role="operator", json={"state": "aborted", "reason": "power cut (test)"})
        assert wait_run(api, first)["status"] == "aborted"
        passed = [d["step"]["step"] if "step" in d["step"] else d["step"]["label"]
                  for kind, d in read_events(api, first) if kind == "step" and d.get("step", {}).get("kind") == "checkpoint"]
        assert len(passed) >= 6
        old = parse_recording(api.get(f"/runs/{first}/samples", role="viewer").text)

        for bad, field in (({"resume": 99999}, "body.resume"), ({"resume": first, "procedure": "rotate_z"}, "body.procedure"),
                           ({"resume": first, "parameters": {"samples": 5}}, "body.parameters")):
            r = api.post("/runs", role="operator", json={"station": "lab-1", **bad})
            assert r.status_code == 422 and r.json()["detail"][0]["field"] == field, r.text
        # another unit in the fixture than the one the run calibrated (as the unit reported itself): refused,
        # the table untouched
        from service.db import Run
        with api.client.app.state.sessions() as s:
            row = s.get(Run, first)
            meta = json.loads(json.dumps(row.meta))
            for ids in (meta["result"]["identities"], meta["identities"]):
                ids["0"]["identified_serial"] = "SN-OTHER"
            row.meta, kept = meta, row.meta
            s.commit()
        other = wait_run(api, api.post("/runs", role="operator", json={"station": "lab-1", "resume": first}).json()["id"])
        assert other["status"] == "failed" and "slot 0 holds" in other["reason"] and "not SN-OTHER" in other["reason"]
        assert other["samples_count"] == 0 and api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        with api.client.app.state.sessions() as s:
            row = s.get(Run, first)  # the unit as it reported itself again (what the refused resume added stays)
            row.meta = {**row.meta, "result": kept["result"], "identities": kept["identities"]}
            s.commit()
        second = api.post("/runs", role="operator", json={"station": "lab-1", "resume": first})
        assert second.status_code == 202, second.text
        # one continuation (the failed one above does not count): a second would complete the run again
        again = api.post("/runs", role="operator", json={"station": "lab-1", "resume": first})
        assert again.status_code == 409 and f"already resumed by run {second.json()['id']}" in again.text, again.text
        done = wait_run(api, second.json()["id"], timeout=90)
        assert done["status"] == "completed", done
        assert done["procedure"] == "calibrate" and done["parameters"]["samples"] == 20
        assert done["samples_count"] == 18 * 20 and done["result"]["units"]["0"].get("verdict") in ("PASS", "MARGINAL"), done["result"]
        events = read_events(api, done["id"])
        [resumed] = [d for kind, d in events if kind == "step" and "resumed_from" in d]
        assert resumed["resumed_from"] == first and resumed["samples"] == 20 * len(passed)
        new = parse_recording(api.get(f"/runs/{done['id']}/samples", role="viewer").text)
        # the replayed part: exactly the first run's first samples, those of the poses it passed (the
        # abort may have come after the next pose acquired, before its checkpoint: those are not replayed;
        # several poses share a label, so the rows are taken in order, not by label)
        n = 20 * len(passed)
        assert len(old) >= n and set(map(str, old.step[:n])) <= set(map(str, passed))
        assert np.array_equal(new.mag[:n], old.mag[:n]) and np.array_equal(new.t[:n], old.t[:n])
        assert np.all(np.diff(new.t) >= 0) and new.t[n] > new.t[n - 1]  # table time goes on after the replay
        # and the run's table time counts the replayed part by its steps' nominal seconds (the first run's
        # sample times also hold any time it stood paused), the live steps adding to it (not the clock: under
        # load the pauses between steps, which the recording's t counts, are not table time, so the total may
        # be well below t[-1], never above it)
        live = [d["table_s"] for kind, d in events[events.index(("step", resumed)) + 1:] if kind == "progress"]
        assert live and live[0] > 0 and resumed["t"] > new.t[n - 1] and live == sorted(live), (resumed, live[:3])
        assert live[-1] <= done["table_seconds"] <= new.t[-1] + 2.0, (done["table_seconds"], new.t[n - 1], new.t[-1])
        assert new.meta.get("resumed_from") == str(first)
        # both runs say it, both ways (before: only the CSV header and a step event did), and so do their
        # page and the certificate, whose data came from two sessions
        assert done["resumed_from"] == first and done["resumed_by"] == []
        assert api.get(f"/runs/{first}", role="viewer").json()["resumed_by"] == [other["id"], done["id"]]
        assert api.get(f"/runs/{other['id']}", role="viewer").json()["resumed_from"] == first
        page = api.get(f"/ui/runs/{done['id']}", role="viewer").text
        assert f'<dd id="resumed-from"><a href="/ui/runs/{first}">run {first}</a>' in page
        assert f'<a href="/ui/runs/{done["id"]}">run {done["id"]}</a>' in api.get(f"/ui/runs/{first}", role="viewer").text
        cal_id = done["result"]["units"]["0"]["calibration_id"]
        cert = api.get(f"/ui/calibrations/{cal_id}/certificate", role="viewer").text
        assert "Resumes run" in cert and f"{first}: its samples up to its last checkpoint, taken over by run {done['id']}" in cert
        # issued when the calibration was stored: a second copy says the same (each render said its own time)
        issued = re.search(r"Issued ([^<]+?) by compasscal", cert).group(1)
        stored = api.get(f"/calibrations/{cal_id}", role="viewer").json()["created_at"]
        assert issued.replace(" UTC", "") in stored.replace("T", " "), (issued, stored)
        time.sleep(1.1)
        assert f"Issued {issued} by" in api.get(f"/ui/calibrations/{cal_id}/certificate", role="viewer").text
        # a completed run is not resumed
        r = api.post("/runs", role="operator", json={"station": "lab-1", "resume": done["id"]})
        assert r.status_code == 409 and "only a failed or aborted run" in r.json()["detail"]


@pytest.mark.parametrize("target", ["running", "aborted"])
def test_transition_table_is_explicit(target: str):
    from procedures.states import OPERATOR_TRANSITIONS as TRANSITIONS
    assert ("completed", target) not in TRANSITIONS and ("failed", target) not in TRANSITIONS
    assert ("queued", "paused") not in TRANSITIONS and ("paused", "running") in TRANSITIONS


def test_shutdown_aborts_active_runs_quickly_and_a_restart_recovers(db_url: str):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.auth import create_key
    from service.db import Run

    app = create_app(db_url)
    with sim_station(reference_config(seed=9, time_scale=20)) as info:
        with TestClient(app) as client:
            with app.state.sessions() as s:
                keys = {role: create_key(s, f"{role}-user", role) for role in ("viewer", "operator", "admin")}
            api = Api(client, keys)
            make_station(api, info)
            rid = api.post("/runs", role="operator", json={"station": "lab-1", "parameters": {"samples": 20}}).json()["id"]
            wait_run(api, rid, ("running",))
            deadline = time.monotonic() + 40.0  # shut down once samples are recorded (not racing the first pose)
            while api.get(f"/runs/{rid}", role="viewer").json()["samples_count"] == 0:
                assert time.monotonic() < deadline, "no sample recorded in 40 s"
                time.sleep(0.05)
            with app.state.sessions() as s:  # as if a previous process had died mid-run
                s.add(Run(procedure="calibrate", procedure_version="2", parameters={}, status="running",
                          operator="ghost", software_version="0"))
                s.commit()
            t0 = time.monotonic()
        assert time.monotonic() - t0 < 8.0  # the lifespan's shutdown aborted the run
    again = create_app(db_url)
    with TestClient(again) as client:
        api = Api(client, keys)
        j = api.get(f"/runs/{rid}", role="viewer").json()
        assert j["status"] == "aborted" and j["reason"] == "service shutting down" and j["samples_count"] > 0
        ev = read_events(api, rid)  # the whole history, from the database, to the new process
        assert ev[0] == ("state", {"state": "queued", "reason": None})
        assert ev[-1] == ("state", {"state": "aborted", "reason": "service shutting down"})
        ghost = api.get("/runs?status=failed", role="viewer").json()
        assert [g["operator"] for g in ghost] == ["ghost"] and "stopped" in ghost[0]["reason"]


def test_a_restarted_service_stops_every_axis_first(db_url: str):
    """A service killed mid-run may leave an axis turning: the next start stops every station's axes
    before it takes any job."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.auth import create_key

    with sim_station(reference_config(seed=12, time_scale=20)) as info:
        app = create_app(db_url)
        with TestClient(app) as client:
            with app.state.sessions() as s:
                keys = {role: create_key(s, f"{role}-user", role) for role in ("viewer", "operator", "admin")}
            make_station(Api(client, keys), info)
        axis = info["station"].table.axes["z"]
        axis.enabled, axis.jog_dir, axis.mode = True, 1, "jog"  # as a killed service could have left it
        time.sleep(0.2)
        assert axis.mode == "jog"
        app = create_app(db_url)
        with TestClient(app):
            assert axis.mode != "jog"


def test_an_unanswered_prompt_frees_the_station(db_url: str, monkeypatch: pytest.MonkeyPatch):
    """Nobody answers a batch's mount prompt: after the prompt timeout the unit's run fails saying
    so, and the batch ends there, the rest not run (no one is there to mount them either: each unit held
    the station for the whole timeout in turn, 5 h for 20 units); the station is free, not in fault."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.auth import create_key

    monkeypatch.setenv("COMPASSCAL_PROMPT_TIMEOUT_S", "1")
    app = create_app(db_url)
    with sim_station(reference_config(seed=13, time_scale=20)) as info, TestClient(app) as client:
        with app.state.sessions() as s:
            keys = {role: create_key(s, f"{role}-user", role) for role in ("viewer", "operator", "admin")}
        api = Api(client, keys)
        make_station(api, info)
        bid = api.post("/batches", role="operator", json={"station": "lab-1", "serials": ["SN-P1", "SN-P2", "SN-P3"]}).json()["id"]
        deadline = time.monotonic() + 30
        while (b := api.get(f"/batches/{bid}", role="viewer").json())["status"] == "running":
            assert time.monotonic() < deadline, b
            time.sleep(0.05)
        assert b["status"] == "failed" and [u["status"] for u in b["units"]] == ["failed", "not run", "not run"], b
        assert b["units"][0]["reason"] == "no answer to prompt 'mount' within 1 s", b["units"][0]  # no class name
        assert b["summary"]["SN-P2"] == b["summary"]["SN-P3"] == \
            "not run: unit SN-P1 was never mounted (no answer to prompt 'mount' within 1 s)", b["summary"]
        assert b["units"][1]["reason"] == "unit SN-P1 was never mounted (no answer to prompt 'mount' within 1 s)"
        st = api.get("/stations/lab-1", role="viewer").json()
        assert st["state"] == "idle" and st["run_id"] is None and st["batch_id"] is None


def test_an_adaptive_calibration_over_the_api_says_whether_the_unit_reached_its_target(api: Api):
    """POST /runs with ``adaptive``: a budget the short plan leaves room in; the stored calibration carries
    the prediction, the verdict on the targets and why, in its notes (which the certificate lists). A comparison
    method cannot be adaptive: 422 naming the rule."""
    with sim_station(reference_config(seed=1, time_scale=20)) as info:
        make_station(api, info)
        bad = api.post("/runs", role="operator", json={"station": "lab-1", "procedure": "calibrate",
                                                         "parameters": {"adaptive": True, "method": "ellipsoid"}})
        assert bad.status_code == 422 and bad.json()["detail"] == [
            {"field": "body.parameters.adaptive", "problem": "needs method 'joint' (the covariance it predicts from), got 'ellipsoid'"}]
        # a budget the plan alone overruns, a budget with nothing to spend it, a yes that is not a boolean: the field named
        for params, field, words in (({"adaptive": True, "budget_s": 50}, "budget_s", ("50 s is shorter than the plan", "106.4 s")),
                                     ({"budget_s": 150}, "budget_s", ("set adaptive true",)),
                                     ({"adaptive": "yes"}, "adaptive", ("valid boolean",))):
            bad = api.post("/runs", role="operator", json={"station": "lab-1", "parameters": params})
            assert bad.status_code == 422, bad.text
            [err] = bad.json()["detail"]
            assert err["field"] == f"body.parameters.{field}" and all(w in err["problem"] for w in words), err
        body = {"station": "lab-1", "procedure": "calibrate",
                "parameters": {"samples": 10, "adaptive": True, "target_level_deg": 0.001, "budget_s": 90}}
        r = api.post("/runs", role="operator", json=body)
        assert r.status_code == 202, r.text
        # each round of the extension predicts every candidate pose's gain (CPU-bound fits, not table time): with
        # three test workers on two busy cores a run took over 40 s, so the guard against a hang is wider here
        done = wait_run(api, r.json()["id"], timeout=180.0)
        assert done["status"] == "completed", done["reason"]
        assert done["samples_count"] > 18 * 10  # an unreachable level target: poses were added
        cal = api.get("/devices/GAO2017-REF/calibrations/current", role="viewer").json()
        pr = cal["quality"]["precision"]
        assert pr["met"] is False and pr["stopped"] == "budget" and pr["added_poses"] > 0 and pr["table_s"] <= 90
        assert pr["predicted_level_deg"] > 0.001 and pr["why"] in cal["notes"]
        # progress counts the budget's reserve: the added poses are not reported as done, and it ends at 100
        events = read_events(api, done["id"])
        progress = [d["percent"] for kind, d in events if kind == "progress"]
        assert progress == sorted(progress) and progress[-1] == 100.0
        assert sum(1 for x in progress if x < 100.0) > 3 * 18, str(progress)  # move, settle, acquire per planned pose, and more
        # each round's refit is said as the work it is (a second or more with the table still), then the fit
        said = [d["step"]["label"] for kind, d in events if kind == "step" and d.get("step", {}).get("kind") == "compute"
                and d["step"]["percent"] is None]  # (a retried step's event has no "step")
        assert said[0] == "fit and predicted heading error of each unit" and said[-1] == "calibration fit", said
        assert said.count("fit and predicted heading error of each unit") >= 2, said  # after the plan, after added poses


def test_a_stored_run_the_procedure_now_refuses_fails_and_the_worker_goes_on(api: Api, monkeypatch):
    """Parameters are checked when a run is made and again when a worker takes it (a run may wait in
    the queue across an upgrade whose rules are stricter): one refused then fails, saying which field
    and why, instead of taking the worker down with it; the station is free for the next run."""
    from dataclasses import replace

    from pydantic import field_validator

    import service.worker as worker
    from procedures.calibrate import PROCEDURES, CalibrateParams

    class Stricter(CalibrateParams):
        @field_validator("samples")
        @classmethod
        def _more(cls, v: int) -> int:
            if v < 50:
                raise ValueError("at least 50 samples now")
            return v

    with sim_station(reference_config(seed=8, time_scale=20)) as info:
        make_station(api, info)
        monkeypatch.setattr(worker, "PROCEDURES", {**PROCEDURES, "calibrate": replace(PROCEDURES["calibrate"], params=Stricter)})
        r = api.post("/runs", role="operator", json={"station": "lab-1", "parameters": {"samples": 20}})
        assert r.status_code == 202, r.text
        j = wait_run(api, r.json()["id"], timeout=30)
        assert j["status"] == "failed" and j["reason"].startswith("parameters refused: samples:"), j
        assert "at least 50 samples now" in j["reason"] and j["samples_count"] == 0
        monkeypatch.setattr(worker, "PROCEDURES", PROCEDURES)
        r = api.post("/runs", role="operator", json={"station": "lab-1", "parameters": {"samples": 10}})
        assert r.status_code == 202, r.text
        assert wait_run(api, r.json()["id"], timeout=90)["status"] == "completed"


def test_a_station_change_keeps_what_it_does_not_name(api: Api):
    """A PUT that gave new URLs only reset a simulator's time scale of 20 to 1 (its next run's samples were
    stamped 20 times too close together, without a word); an omitted time scale is now kept, as the
    serial policy is. A station made by PUT still starts at 1."""
    body = {"name": "lab-7", "modbus": "tcp://127.0.0.1:1577", "compasses": ["socket://127.0.0.1:4077"], "time_scale": 20}
    assert api.post("/stations", json=body).status_code == 201
    moved = {"modbus": "tcp://127.0.0.1:1578", "compasses": ["socket://127.0.0.1:4078"]}
    r = api.put("/stations/lab-7", json=moved)
    assert r.status_code == 200 and r.json()["time_scale"] == 20 and r.json()["modbus"] == moved["modbus"], r.text
    assert api.put("/stations/lab-7", json={**moved, "time_scale": 1}).json()["time_scale"] == 1
    r = api.put("/stations/lab-8", json={"modbus": "tcp://127.0.0.1:1579", "compasses": ["socket://127.0.0.1:4079"]})
    assert r.status_code == 200 and r.json()["time_scale"] == 1, r.text


def test_a_station_s_serial_policy_changes_alone_with_patch(api: Api):
    """PUT wants a station's URLs as well (an outside prober: to change only its serial policy); PATCH changes
    what it is given and keeps the rest, with the same checks, and names what is wrong."""
    body = {"name": "lab-9", "modbus": "tcp://127.0.0.1:1591", "compasses": ["socket://127.0.0.1:4091"], "time_scale": 20}
    assert api.post("/stations", json=body).status_code == 201
    r = api.patch("/stations/lab-9", json={"serial_policy": "refuse"})
    assert r.status_code == 200, r.text
    got = r.json()
    assert (got["serial_policy"], got["modbus"], got["compasses"], got["time_scale"]) == (
        "refuse", body["modbus"], body["compasses"], 20), got
    assert api.patch("/stations/lab-9", json={"time_scale": 1}).json()["serial_policy"] == "refuse"
    r = api.patch("/stations/lab-9", json={})
    assert r.status_code == 422 and "nothing to change" in r.text, r.text
    r = api.patch("/stations/lab-9", json={"serial_policy": "maybe"})
    assert r.status_code == 422 and "serial_policy" in r.text, r.text
    r = api.patch("/stations/lab-9", json={"modbus": "ftp://x"})
    assert r.status_code == 422 and "modbus" in r.text, r.text
    assert api.patch("/stations/nowhere", json={"serial_policy": "refuse"}).status_code == 404
    assert api.patch("/stations/lab-9", json={"serial_policy": "refuse"}, role="operator").status_code == 403


def test_a_station_at_another_time_scale_than_its_simulator_is_said(api: Api):
    """A station registered at time scale 1 on a simulator running at 20 completed its runs with samples
    stamped 20 times too close together and no word (the command line said it; the service did not).
    The run's notes now say it, and how to set it right; at the right scale nothing is said."""
    with sim_station(reference_config(seed=6, time_scale=20)) as info:
        body = {"name": "lab-1", "modbus": info["modbus"], "compasses": [c["url"] for c in info["compasses"]],
                "time_scale": 1}
        assert api.post("/stations", json=body).status_code == 201
        run = {"station": "lab-1", "procedure": "rotate_z", "parameters": {"samples": 5, "step_deg": 90}}
        j = wait_run(api, api.post("/runs", role="operator", json=run).json()["id"], timeout=90)
        assert j["status"] == "completed", j
        notes = " ".join(j["result"]["notes"])
        assert "times the plan's nominal" in notes and "set the station's time_scale (PUT /stations/lab-1)" in notes, j
        # an answer to an ended run says it ended (it said "no prompt waiting", as if the id were wrong)
        r = api.post(f"/runs/{j['id']}/prompts/mount", role="operator", json={"answer": "done"})
        assert r.status_code == 409 and "has ended (completed)" in r.text, r.text
        assert api.put("/stations/lab-1", json={**body, "time_scale": 20}).status_code == 200
        j = wait_run(api, api.post("/runs", role="operator", json=run).json()["id"], timeout=90)
        assert j["status"] == "completed" and "plan's nominal" not in " ".join(j["result"]["notes"]), j
