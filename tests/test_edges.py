"""Validation at the edge (issue 15): every string and number a request brings is checked where it
enters, with the same limits on SQLite and PostgreSQL: a 422 naming the field and the problem (or a
413 for an oversized upload), never a 500, and never a run accepted that later loses its calibration.
Each test also checks that the refused request stored nothing."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import Any
from urllib.parse import quote, unquote

import numpy as np
import pytest
from sqlalchemy import func, select

from conftest import Api
from physics.recording import Recording, format_recording

#: Serial numbers every edge refuses: too long, line breaks, NUL, a path, control and non-ASCII characters.
BAD_SERIALS = ["S" * 65, "SN\r\n1", "SN\n1", "SN\x001", "SN/1", "../../etc/passwd", "SN-\u03a9", "SN-\u00e9", "SN\t1",
               "SN\x7f", "", "   "]


# ------------------------------------------------------------------------------------------ helpers

def stored(api: Api) -> dict[str, Any]:
    """What the database holds: rows per table and the limits' values (to show a refusal changed nothing)."""
    from service.db import AuditLog, Batch, Calibration, Device, Limit, Run, RunCommand, Sample, Station
    with api.client.app.state.sessions() as s:
        out: dict[str, Any] = {m.__tablename__: s.scalar(select(func.count()).select_from(m))
                               for m in (AuditLog, Batch, Calibration, Device, Run, RunCommand, Sample, Station)}
        out["limits"] = sorted((r.name, r.marginal, r.fail) for r in s.scalars(select(Limit)))
    return out


def refused(r: Any, field: str, *words: str) -> str:
    """Assert a 422 naming ``field`` with a problem that says each of ``words``; the problem."""
    assert r.status_code == 422, (r.status_code, r.text)
    detail = r.json()["detail"]
    hits = [d["problem"] for d in detail if d["field"] == field]
    assert hits, (field, detail)
    for w in words:
        assert any(w.lower() in p.lower() for p in hits), (w, detail)
    return hits[0]


def station(api: Api, name: str = "lab-1") -> None:
    """A station nothing will reach (a run accepted by mistake fails at once, after storing itself)."""
    r = api.post("/stations", json={"name": name, "modbus": "tcp://127.0.0.1:9", "compasses": ["socket://127.0.0.1:9"]})
    assert r.status_code == 201, r.text


def recording_csv(serial: str | None = "SN-UP", steps: tuple[str, ...] = ("level_0",) * 4) -> str:
    """A small RECORDING.md CSV (one row per step label)."""
    n = len(steps)
    rec = Recording.from_arrays(t=np.arange(n) * 0.05, step=list(steps), psi_t=np.zeros(n), theta_t=np.zeros(n),
                                phi_t=np.zeros(n), mag=np.tile([100.0, 0.0, 400.0], (n, 1)),
                                meta={"serial": serial} if serial is not None else {})
    return format_recording(rec)


def upload(api: Api, text: str) -> Any:
    return api.post("/recordings", role="operator", content=text.encode(), headers={"Content-Type": "text/csv"})


def raw_json(api: Api, method: str, path: str, text: str, role: str = "admin") -> Any:
    """A body as written (``Infinity``, ``NaN``: JSON that Python's parser takes and httpx would not send)."""
    return getattr(api, method)(path, role=role, content=text.encode(), headers={"Content-Type": "application/json"})


# ------------------------------------------------------------------ 1. one serial-number type everywhere

def test_the_limits_are_the_columns():
    """The edge's limits are the database's: a value the edge takes fits its column on both databases."""
    import service.db as db
    from service.schemas import NAME_MAX, SERIAL_MAX, STEP_MAX
    assert db.Device.__table__.c.serial.type.length == SERIAL_MAX == 64
    assert db.Station.__table__.c.name.type.length == NAME_MAX
    assert db.Limit.__table__.c.name.type.length == NAME_MAX
    assert db.Sample.__table__.c.step.type.length == STEP_MAX == 32
    if hasattr(db, "SampleExtra"):  # an import's extra columns, kept by name
        assert db.SampleExtra.__table__.c.name.type.length == NAME_MAX


@pytest.mark.parametrize("serial", ["SN-1", "A", "SN 0042:rev+B#7_x.y", "S" * 64, " SN-2 "])
def test_a_serial_of_the_alphabet_is_taken(serial: str):
    from service.schemas import check_serial
    assert check_serial(serial) == serial.strip(" ")


@pytest.mark.parametrize("bad", BAD_SERIALS)
def test_a_bad_serial_is_refused_wherever_it_enters(api: Api, bad: str):
    station(api)
    before = stored(api)
    refused(api.post("/runs", role="operator", json={"station": "lab-1", "serials": {"0": bad}}), "body.serials.0")
    refused(api.post("/batches", role="operator", json={"station": "lab-1", "serials": ["SN-OK", bad]}), "body.serials.1")
    # looked for, it is only text (none, or a NUL, aside): what a unit reported that is no serial number
    # ("SN/1") finds its runs
    found = api.get("/runs", role="viewer", params={"serial": bad})
    if "\x00" in bad or not bad.strip(" "):
        refused(found, "query.serial")
    else:
        assert found.status_code == 200 and found.json() == [], found.text
    for path in (f"/devices/{quote(bad, safe='')}", f"/devices/{quote(bad, safe='')}/calibrations",
                 f"/devices/{quote(bad, safe='')}/calibrations/current"):
        r = api.get(path, role="viewer")
        if "/" in bad or not bad:  # never reaches the route: no such path
            assert r.status_code == 404, (path, r.text)
        else:
            refused(r, "path.serial")
    if "\n" not in bad and "\r" not in bad and bad.strip():  # a line break would end the metadata line
        field = "body" if "\x00" in bad else "body.serial"
        refused(upload(api, recording_csv(serial=bad)), field)
    assert stored(api) == before


# ----------------------------------------------------------------------- 2. station names in the path

@pytest.mark.parametrize("bad", ["-lead", "a" * 65, "a b", "a:b", "a\x00b", "st\u00fcck", "a\nb", ".hidden"])
def test_a_bad_station_name_is_refused_in_the_path_and_the_body(api: Api, bad: str):
    station(api)
    before = stored(api)
    name = quote(bad, safe="")
    config = {"modbus": "tcp://127.0.0.1:9", "compasses": ["socket://127.0.0.1:9"]}
    refused(api.put(f"/stations/{name}", json=config), "path.name")
    refused(api.get(f"/stations/{name}", role="viewer"), "path.name")
    refused(api.post(f"/stations/{name}/reset", role="operator"), "path.name")
    refused(api.post("/stations", json={**config, "name": bad}), "body.name")
    refused(api.post("/runs", role="operator", json={"station": bad}), "body.station")
    refused(api.post("/batches", role="operator", json={"station": bad, "serials": ["SN-1"]}), "body.station")
    refused(api.get("/runs", role="viewer", params={"station": bad}), "query.station")
    assert stored(api) == before


def test_put_station_names_a_bad_modbus_url(api: Api):
    r = api.put("/stations/lab-2", json={"modbus": "http://127.0.0.1:9", "compasses": ["socket://127.0.0.1:9"]})
    refused(r, "body.modbus")
    assert stored(api)["stations"] == 0


# --------------------------------------------------------------------- 3. step labels of an upload

@pytest.mark.parametrize("label, words", [("x" * 33, ("line", "step", "32")), ("long-label-" * 5, ("line", "step")),
                                          ("lev\x00el", ("line", "NUL"))])
def test_an_upload_whose_step_labels_the_database_cannot_hold_is_refused(api: Api, label: str, words: tuple[str, ...]):
    before = stored(api)
    text = recording_csv(steps=("level_0", "level_0", label, "level_1"))
    refused(upload(api, text), "body", *words)
    assert stored(api) == before


def test_an_upload_whose_extra_column_name_the_database_cannot_hold_is_refused(api: Api):
    """Extra columns are kept by name (a String(64), like every name): a longer one is refused."""
    before = stored(api)
    text = recording_csv().replace(",temp_c\n", f",temp_c,{'c' * 65}\n")
    text = "\n".join(line + ",x" if line[:1].isdigit() else line for line in text.split("\n"))
    refused(upload(api, text), "body", "extra column", "64")
    assert stored(api) == before


def test_an_upload_with_a_32_character_step_label_is_kept(api: Api):
    label = "s" * 32
    r = upload(api, recording_csv(steps=(label,) * 3))
    assert r.status_code == 201, r.text
    assert f",{label}," in api.get(f"/runs/{r.json()['id']}/samples", role="viewer").text


def test_an_upload_with_a_nul_anywhere_is_refused_naming_the_line(api: Api):
    before = stored(api)
    text = recording_csv().replace("# serial: SN-UP", "# serial: SN-UP\n# note: a\x00b")
    problem = refused(upload(api, text), "body", "NUL")
    assert "line 3" in problem
    assert stored(api) == before


# ------------------------------------------------------------------------ 4. integers that fit a column

BAD_IDS = [2**31, 2**63, 2**64, 0, -1]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_ids_out_of_range_are_refused_naming_the_parameter(api: Api, bad: int):
    before = stored(api)
    for method, path, field, kw in [
            ("get", f"/runs/{bad}", "run_id", {}), ("get", f"/runs/{bad}/events", "run_id", {}),
            ("get", f"/runs/{bad}/samples", "run_id", {}), ("get", f"/runs/{bad}/analyses", "run_id", {}),
            ("put", f"/runs/{bad}/state", "run_id", {"json": {"state": "paused"}, "role": "operator"}),
            ("post", f"/runs/{bad}/prompts/mount", "run_id", {"json": {"answer": "ok"}, "role": "operator"}),
            ("post", f"/runs/{bad}/analysis", "run_id", {"json": {}, "role": "operator"}),
            ("get", f"/batches/{bad}", "batch_id", {}), ("get", f"/calibrations/{bad}", "cal_id", {}),
            ("get", f"/calibrations/{bad}/certificate.pdf", "cal_id", {}), ("get", f"/analyses/{bad}", "analysis_id", {}),
            ("get", f"/analyses/{bad}/events", "analysis_id", {}), ("get", f"/analyses/{bad}/report", "analysis_id", {})]:
        refused(getattr(api, method)(path, **{"role": "viewer", **kw}), f"path.{field}")
    if bad > 0:
        refused(api.get(f"/runs/1/samples?slot={bad}", role="viewer"), "query.slot")
        refused(api.get(f"/runs?offset={bad}", role="viewer"), "query.offset")
        refused(api.get(f"/devices/SN-1/calibrations?offset={bad}", role="viewer"), "query.offset")
        refused(api.post("/runs/1/analysis", role="operator", json={"slot": bad}), "body.slot")
        refused(api.post("/runs/1/analysis", role="operator", json={"calibration_id": bad}), "body.calibration_id")
    refused(api.post("/runs", role="operator", json={"station": "lab-1", "resume": bad}), "body.resume")
    assert stored(api) == before


def test_a_boolean_is_no_id_nor_slot(api: Api):
    refused(api.post("/runs", role="operator", json={"station": "lab-1", "resume": True}), "body.resume")
    refused(api.post("/runs/1/analysis", role="operator", json={"slot": True}), "body.slot")
    refused(api.post("/runs/1/analysis", role="operator", json={"calibration_id": True}), "body.calibration_id")
    refused(api.post("/runs/1/analysis", role="operator", json={"null_sims": False}), "body.null_sims")


# --------------------------------------------------------------- 5. NUL characters in paths, queries, bodies

def test_nul_characters_are_refused_wherever_they_enter(api: Api):
    station(api)
    before = stored(api)
    nul = "%00"
    refused(api.get(f"/stations/lab{nul}", role="viewer"), "path.name")  # the name's pattern says what it may be
    for method, path, field, kw in [
            ("get", f"/devices/SN{nul}", "path.serial", {}),
            ("put", f"/limits/bias_lsb{nul}", "path.name", {"json": {"marginal": 1, "fail": 2}, "role": "admin"}),
            ("post", f"/runs/1/prompts/mount{nul}", "path.prompt_id", {"json": {"answer": "ok"}, "role": "operator"}),
            ("get", f"/runs?station=lab{nul}", "query.station", {}),
            ("get", f"/runs?procedure=cal{nul}", "query.procedure", {}), ("get", f"/runs?serial=SN{nul}", "query.serial", {})]:
        refused(getattr(api, method)(path, **{"role": "viewer", **kw}), field, "NUL")
    refused(api.get(f"/runs?status=run{nul}", role="viewer"), "query.status", "'queued'")  # one of the states
    run = {"station": "lab-1"}
    for path, body, field, role in [
            ("/runs", {**run, "station": "lab\x00"}, "body.station", "operator"),
            ("/runs", {**run, "procedure": "calibrate\x00"}, "body.procedure", "operator"),
            ("/runs", {**run, "parameters": {"method": "joint\x00"}}, "body.parameters", "operator"),
            ("/runs", {**run, "parameters": {"samples\x00": 5}}, "body.parameters", "operator"),
            ("/runs", {**run, "parameters": {"deep": [{"x": ["a\x00"]}]}}, "body.parameters", "operator"),
            ("/batches", {**run, "serials": ["SN-1"], "parameters": {"method": "\x00"}}, "body.parameters", "operator"),
            ("/runs/1/prompts/mount", {"answer": "ok\x00"}, "body.answer", "operator"),
            ("/stations", {"name": "lab-2", "modbus": "tcp://127.0.0.1:9\x00", "compasses": ["socket://a:1"]}, "body.modbus", "admin"),
            ("/stations", {"name": "lab-2", "modbus": "tcp://127.0.0.1:9", "compasses": ["socket://a\x00:1"]}, "body.compasses.0", "admin")]:
        refused(api.post(path, role=role, json=body), field, "NUL")
    refused(api.put("/runs/1/state", role="operator", json={"state": "aborted", "reason": "x\x00"}), "body.reason", "NUL")
    assert stored(api) == before


# ------------------------------------------------------------------------- 6. finite, strict numbers

@pytest.mark.parametrize("fail", ["Infinity", "-Infinity", "NaN", "1e999", "true", '"20"'])
def test_a_limit_must_be_a_finite_number(api: Api, fail: str):
    before = stored(api)
    refused(raw_json(api, "put", "/limits/bias_lsb", f'{{"marginal": 1, "fail": {fail}}}'), "body.fail")
    refused(raw_json(api, "put", "/limits/bias_lsb", f'{{"marginal": {fail}, "fail": 1e6}}'), "body.marginal")
    assert stored(api) == before
    ok = raw_json(api, "put", "/limits/bias_lsb", '{"marginal": 1, "fail": 2}')  # an integer is a number
    assert ok.status_code == 200 and ok.json()["fail"] == 2.0


def test_a_limit_must_be_one_a_calibration_can_meet_or_miss(api: Api):
    """1e308 was taken as a limit (the certificates printed it as 309 digits) and a fail limit of 0 too
    (every calibration fails): refused by their field, in the limit's own unit."""
    before = stored(api)
    for name, body, field, words in (("bias_lsb", {"marginal": 1e308, "fail": 1e308}, "body.marginal", "at most 65536 LSB"),
                                     ("heading_error_level_deg", {"marginal": 0.05, "fail": 400}, "body.fail", "180 deg"),
                                     ("sensitivity_mismatch", {"marginal": 0.1, "fail": 20}, "body.fail", "10 ratio"),
                                     ("bias_lsb", {"marginal": 0, "fail": 0}, "body.fail", "every calibration fails")):
        r = api.put(f"/limits/{name}", role="admin", json=body)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == field and words in r.text, (name, r.text)
    assert stored(api) == before
    assert api.put("/limits/heading_error_level_deg", role="admin", json={"marginal": 0, "fail": 180}).status_code == 200


@pytest.mark.parametrize("scale", ["Infinity", "NaN", "1e999", "true", "false", '"2"'])
def test_a_time_scale_must_be_a_finite_number(api: Api, scale: str):
    before = stored(api)
    body = '{"name": "lab-2", "modbus": "tcp://127.0.0.1:9", "compasses": ["socket://127.0.0.1:9"], "time_scale": %s}'
    refused(raw_json(api, "post", "/stations", body % scale), "body.time_scale")
    refused(raw_json(api, "put", "/stations/lab-2", body % scale), "body.time_scale")
    assert stored(api) == before


def test_a_non_finite_number_in_the_parameters_is_refused(api: Api):
    station(api)
    before = stored(api)
    refused(raw_json(api, "post", "/runs", '{"station": "lab-1", "parameters": {"samples": 20, "x": [NaN]}}', "operator"),
            "body.parameters", "finite")
    refused(raw_json(api, "post", "/batches", '{"station": "lab-1", "serials": ["A"], "parameters": {"y": Infinity}}',
                     "operator"), "body.parameters", "finite")
    assert stored(api) == before


# -------------------------------------------------------------- 7. the PDF certificate's file name

def test_the_certificate_file_name_is_encoded_and_carries_no_path(api: Api):
    """A serial stored before the edge checked it (or reported by a compass): outside Latin-1, with
    a path in it. The certificate still answers, its file name RFC 6266-encoded and without the path."""
    from physics.fit import fit
    from physics.sensor import reference_unit
    from physics.simulate import World, simulate_recording
    from procedures.calibrate import CalibrateParams, calibration_poses
    from service.db import Run
    from service.store import store_calibration

    serial = "SN-\u03a9\u00e9/../../etc/passwd"
    rec = simulate_recording(reference_unit(3.0, 4.0, serial=serial), calibration_poses(CalibrateParams(samples=20)),
                             World(), rng=np.random.default_rng(1))
    with api.client.app.state.sessions() as s:
        run = Run(procedure="calibrate", procedure_version="2", parameters={}, status="completed", operator="t",
                  serials={"0": serial}, software_version="test")
        s.add(run)
        s.flush()
        cal_id = store_calibration(s, run, 0, serial, fit(rec, "joint").to_json()).id
        s.commit()
    r = api.get(f"/calibrations/{cal_id}/certificate.pdf", role="viewer")
    assert r.status_code == 200 and r.content.startswith(b"%PDF")
    value = r.headers["content-disposition"]
    value.encode("ascii")  # a header is ASCII; the name's other characters are percent-encoded
    parts = dict(p.strip().split("=", 1) for p in value.split(";")[1:])
    assert value.startswith("inline;")
    fallback = json.loads(parts["filename"])
    assert fallback.endswith(".pdf") and fallback.startswith("certificate-SN-")
    assert "/" not in fallback and "\\" not in fallback and ".." not in fallback and fallback.isascii()
    assert parts["filename*"].startswith("UTF-8''")
    full = unquote(parts["filename*"][len("UTF-8''"):], encoding="utf-8", errors="strict")
    assert "\u03a9\u00e9" in full and "/" not in full and full.endswith(f"-CC-{cal_id:06d}.pdf")


# -------------------------------------------------------------------------- 8. streamed uploads

def test_the_upload_declares_its_body_in_openapi(api: Api):
    op = api.get("/openapi.json", role=None).json()["paths"]["/recordings"]["post"]
    assert op["requestBody"]["content"]["text/csv"]["schema"]["type"] == "string"
    assert op["requestBody"]["required"] is True
    assert "413" in op["responses"]


def _post_chunks(api: Api, chunks: list[bytes]) -> tuple[int, int, dict[str, Any]]:
    """POST /recordings straight to the ASGI app, chunked without a Content-Length (as a client
    streaming a file sends it): the status, how many chunks the service read, the answer."""
    app, key = api.client.app, api.keys["operator"]
    read = 0
    answer: dict[str, Any] = {"status": None, "body": b""}
    answered: asyncio.Event | None = None

    async def receive() -> dict[str, Any]:
        nonlocal read
        if read < len(chunks):
            read += 1
            return {"type": "http.request", "body": chunks[read - 1], "more_body": read < len(chunks)}
        await answered.wait()  # the client has sent everything and waits for the answer
        return {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        if message["type"] == "http.response.start":
            answer["status"] = message["status"]
        elif message["type"] == "http.response.body":
            answer["body"] += message.get("body", b"")
            if not message.get("more_body"):
                answered.set()

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": "/recordings", "raw_path": b"/recordings", "root_path": "", "query_string": b"",
             "headers": [(b"host", b"testserver"), (b"x-api-key", key.encode()), (b"content-type", b"text/csv"),
                         (b"transfer-encoding", b"chunked")],
             "client": ("127.0.0.1", 50000), "server": ("testserver", 80), "state": {}}

    async def call() -> None:
        nonlocal answered
        answered = asyncio.Event()  # of the app's event loop
        await app(scope, receive, send)
    api.client.portal.call(call)
    return answer["status"], read, json.loads(answer["body"] or b"{}")


def test_a_chunked_upload_is_refused_as_soon_as_it_is_too_big(api: Api, monkeypatch: pytest.MonkeyPatch):
    import service.routes.recordings
    monkeypatch.setattr(service.routes.recordings, "MAX_UPLOAD_BYTES", 1000)
    before = stored(api)
    status, read, body = _post_chunks(api, [b"#" * 99 + b"\n"] * 100)  # 10,000 bytes in 100 chunks
    assert status == 413 and "1000" in body["detail"]
    assert read <= 11, f"read {read} chunks of 100 bytes to refuse more than 1000"
    assert stored(api) == before
    text = recording_csv().encode()  # below the limit, chunked: stored whole
    monkeypatch.setattr(service.routes.recordings, "MAX_UPLOAD_BYTES", len(text))
    status, read, body = _post_chunks(api, [text[i:i + 50] for i in range(0, len(text), 50)])
    assert status == 201 and body["samples"] == 4 and body["serial"] == "SN-UP", body


def test_an_upload_is_stored_off_the_event_loop(api: Api, monkeypatch: pytest.MonkeyPatch):
    """While a large upload is being inserted, the service answers other requests."""
    import service.routes.recordings
    real = service.routes.recordings.insert_samples
    inserting, release = threading.Event(), threading.Event()

    def slow_insert(*a: Any, **kw: Any) -> int:
        inserting.set()
        release.wait(8)
        return real(*a, **kw)
    monkeypatch.setattr(service.routes.recordings, "insert_samples", slow_insert)
    done: dict[str, Any] = {}
    t = threading.Thread(target=lambda: done.update(r=upload(api, recording_csv())))
    t.start()
    try:
        assert inserting.wait(20)
        t0 = time.monotonic()
        assert api.get("/health", role=None).status_code == 200
        waited = time.monotonic() - t0
    finally:
        release.set()
        t.join(30)
    assert waited < 5, f"/health waited {waited:.1f} s for the upload's insert"
    assert done["r"].status_code == 201


def test_a_recording_uploaded_without_a_serial_stores_none_not_an_empty_one(api: Api):
    """It stored serials {"0": ""} and answered "serial": "" (no serial number is empty)."""
    r = upload(api, recording_csv(serial=None))
    assert r.status_code == 201 and r.json()["serial"] is None, r.text
    assert api.get(f"/runs/{r.json()['id']}", role="viewer").json()["serials"] == {}
    r = upload(api, recording_csv(serial="SN-UP"))
    assert r.status_code == 201 and r.json()["serial"] == "SN-UP"
    assert api.get(f"/runs/{r.json()['id']}", role="viewer").json()["serials"] == {"0": "SN-UP"}


def test_an_upload_of_another_layout_or_as_a_form_is_told_how_to_send_it(api: Api):
    """A logger's own CSV said only "missing required column(s)"; a multipart form was read as CSV and
    said the same. The first is pointed to convert --mapping, the second to sending the CSV itself."""
    r = upload(api, "tms;Bx;By;Bz\n1000;12.5;-3.1;40.2\n")
    assert r.status_code == 422 and "compasscal convert FILE --mapping map.toml" in r.text, r.text
    r = api.post("/recordings", role="operator", files={"file": ("rec.csv", recording_csv().encode(), "text/csv")})
    assert r.status_code == 422 and "multipart form upload" in r.text and "--data-binary" in r.text, r.text
    assert upload(api, recording_csv()).status_code == 201  # the CSV itself, as before


def test_a_byte_that_is_not_utf8_is_counted_from_1_by_the_file_reader_and_the_upload(api: Api, tmp_path):
    """The CLI said "byte 40" where the upload said "byte 41" of the same text."""
    from service.imports import RecordingFileError, read_recording_file

    data = b"t,step\n\xff,x\n"
    r = api.post("/recordings", role="operator", content=data, headers={"Content-Type": "text/csv"})
    assert r.status_code == 422 and "byte 8, counting from 1" in r.text, r.text
    p = tmp_path / "bad.csv"
    p.write_bytes(data)
    with pytest.raises(RecordingFileError, match="byte 8, counting from 1"):
        read_recording_file(p)
