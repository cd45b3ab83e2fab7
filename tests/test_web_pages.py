"""The web pages and certificates without a browser (TestClient, SQLite and PostgreSQL): login and
the session cookie, redirects to the login, the run page's tables and curves, the device history,
the certificate page and its PDF. The browser tests are tests/test_web.py."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select

from physics.fit import fit
from physics.recording import format_recording, parse_recording
from physics.sensor import reference_unit
from physics.simulate import World, simulate_recording
from procedures.calibrate import CalibrateParams, calibration_poses
from service.auth import COOKIE
from service.db import Batch, Run, Station
from service.store import insert_samples, store_calibration


class Elements(HTMLParser):
    """Every start tag of a page with its attributes (enough for the DOM contract's selectors)."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str]]] = []
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, {k: v or "" for k, v in attrs}))

    def find(self, tag: str | None = None, cls: str | None = None, **attrs: str) -> list[dict[str, str]]:
        out = []
        for t, a in self.tags:
            if tag and t != tag:
                continue
            if cls and cls not in a.get("class", "").split():
                continue
            if all(a.get(k.replace("_", "-")) == v for k, v in attrs.items()):
                out.append(a)
        return out


def recording(serial: str, seed: int = 1) -> Any:
    return simulate_recording(reference_unit(3.0, 4.0, serial=serial), calibration_poses(CalibrateParams(samples=10)),
                              World(), rng=np.random.default_rng(seed))


def stored_run(api: Any, serial: str, seeds: tuple[int, ...] = (1,), status: str = "completed",
               reason: str | None = None) -> list[tuple[int, int]]:
    """Runs with their samples and calibrations stored as a run stores them: [(run_id, calibration_id)]."""
    out = []
    with api.client.app.state.sessions() as session:
        for seed in seeds:
            rec = recording(serial, seed)
            run = Run(procedure="calibrate", procedure_version="2", parameters={"samples": 10}, status=status,
                      reason=reason, operator="operator-user", serials={"0": serial}, software_version="test",
                      station_snapshot={"name": "bench-1", "modbus": "tcp://10.0.0.5:502", "compasses": ["/dev/ttyUSB0"],
                                        "time_scale": 1.0})
            session.add(run)
            session.flush()
            insert_samples(session, run.id, 0, rec)
            cal_id = None
            if status == "completed":
                row = store_calibration(session, run, 0, serial, fit(rec, "joint").to_json(), model="XDC-3", firmware="1.2.0")
                cal_id = row.id
            session.commit()
            out.append((run.id, cal_id))
    return out


def test_login_sets_the_session_cookie_and_logout_clears_it(api):
    client = api.client
    client.cookies.clear()
    r = client.get("/ui/stations", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/login?next=%2Fui%2Fstations"
    page = client.get("/ui/login?next=/ui/devices/X")
    assert page.status_code == 200
    form = Elements(page.text)
    assert form.find("input", id="api-key") and form.find("button", id="login")
    assert "a session that lasts 12 hours" in page.text  # as the cookie does (it said "this browser session only")

    bad = client.post("/ui/login", data={"key": "cc_wrong", "next": "/ui/stations"}, follow_redirects=False)
    assert bad.status_code == 401 and "not valid" in bad.text and COOKIE not in bad.headers.get("set-cookie", "")

    r = client.post("/ui/login", data={"key": api.keys["viewer"], "next": "/ui/devices/X"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/devices/X"
    cookie = r.headers["set-cookie"]
    assert cookie.startswith(f"{COOKIE}=") and "HttpOnly" in cookie and "samesite=strict" in cookie.lower()
    assert api.keys["viewer"] not in cookie and f"{COOKIE}=cs_" in cookie  # a session token, never the key
    assert f"max-age={12 * 3600}" in cookie.lower() and "secure" not in cookie.lower()  # plain HTTP here
    token = client.cookies[COOKIE]
    page = client.get("/ui/stations")  # the cookie alone now
    assert page.status_code == 200 and "viewer-user" in page.text
    assert Elements(page.text).find("table", id="stations") and Elements(page.text).find("form", id="search")
    assert not Elements(page.text).find("form", cls="start-run")  # viewers cannot start runs
    assert client.get("/limits").status_code == 200  # the JSON API takes the cookie too

    r = client.post("/ui/login", data={"key": api.keys["viewer"], "next": "//evil.example/x"}, follow_redirects=False)
    assert r.headers["location"] == "/ui/stations"  # never off the site

    token = client.cookies[COOKIE]  # this browser's session now (each login starts its own)
    r = client.post("/ui/logout", follow_redirects=False)
    assert r.status_code == 303 and f'{COOKIE}=""' in r.headers["set-cookie"]
    client.cookies.clear()
    assert client.get("/ui/stations", follow_redirects=False).status_code == 303
    # the old token, replayed after the logout, opens nothing
    assert client.get("/limits", headers={"Cookie": f"{COOKIE}={token}"}).status_code == 401


def test_pages_without_a_valid_key_redirect_to_the_login(api):
    api.client.cookies.clear()
    for path in ("/ui/runs/1", "/ui/devices/SN-1", "/ui/calibrations/1/certificate", "/ui/batches/1", "/ui/search?serial=SN"):
        r = api.get(path, role=None, follow_redirects=False)
        assert r.status_code == 303 and r.headers["location"].startswith("/ui/login?next="), path
    r = api.get("/ui/devices/SN-1", role=None, headers={"X-API-Key": "cc_wrong"}, follow_redirects=False)
    assert r.status_code == 303
    assert api.get("/calibrations/1/certificate.pdf", role=None).status_code == 401
    assert api.get("/ui/static/style.css", role=None).status_code == 200  # the login page needs it
    assert api.get("/ui/static/..%2Fweb.py", role=None).status_code == 404


def test_stations_page_offers_operators_a_start_form(api):
    r = api.put("/stations/bench-1", json={"modbus": "tcp://bench-1.local:502", "compasses": ["socket://bench-1.local:4001"]})
    assert r.status_code == 200, r.text
    page = Elements(api.get("/ui/stations", role="operator").text)
    assert page.find("tr", data_station="bench-1")
    assert page.find("td", cls="state")
    assert page.find("form", cls="start-run", data_station="bench-1")
    assert page.find("button", cls="start", id="start-bench-1")
    assert page.find("select", name="procedure") and page.find("option", value="calibrate", selected="")
    assert page.find("input", name="samples")
    # the form sends the samples only: a procedure that needs more is not offered (evaluate failed with 422)
    assert page.find("option", value="rotate_z") and not page.find("option", value="evaluate")


def test_run_page_shows_each_units_tables_curves_and_verdict(api):
    (run_id, cal_id), = stored_run(api, "SN-RUN")
    r = api.get(f"/ui/runs/{run_id}", role="viewer")
    assert r.status_code == 200
    page = Elements(r.text)
    assert page.find("section", id="results")
    assert page.find("div", cls="unit", data_slot="0", data_serial="SN-RUN")
    assert re.search(r'<span id="progress">100\.0 %</span>', r.text)
    assert page.find("span", id="state") and page.find("span", id="time-left") and page.find("span", id="samples")
    assert page.find("table", cls="table1") and page.find("table", cls="table2")
    table1 = r.text.split("class=\"table1", 1)[1].split("</caption>", 1)[1].split("</table>", 1)[0]
    assert table1.count("<tr>") == 4 and table1.count("±") == 9  # header + x_m, y_m, z_m with 1-sigma
    assert page.find("svg", cls="staged-curve") and page.find("svg", cls="tilted-curve")
    assert not page.find("svg", cls="precision-curve")  # not an adaptive calibration
    assert not re.search(r'(src|href)="(https?:)?//', r.text)  # nothing loaded from elsewhere
    assert page.find("div", cls="verdict") and re.search(r'class="verdict-word">(PASS|MARGINAL|FAIL)<', r.text)
    assert page.find("a", cls="certificate", href=f"/ui/calibrations/{cal_id}/certificate")
    assert not page.find("svg", id="live-plot") and not page.find("div", id="reason")
    # no operator controls for a viewer; present (disabled: the run is over) for an operator
    assert not page.find("button", id="abort")
    op = Elements(api.get(f"/ui/runs/{run_id}", role="operator").text)
    assert op.find("button", id="pause", disabled="") and op.find("button", id="abort", disabled="")
    live = api.get(f"/ui/runs/{run_id}/samples.json?slot=0&after=0", role="viewer").json()
    assert len(live["rows"]) == 18 * 10 and live["rows"][0][0] == "rotate_z" and not live["more"]
    again = api.get(f"/ui/runs/{run_id}/samples.json?slot=0&after={live['last']}", role="viewer").json()
    assert again["rows"] == [] and again["last"] == live["last"]
    assert api.get(f"/ui/runs/{run_id}/samples.json?slot=3", role="viewer").json()["rows"] == []


def test_run_page_of_an_imported_recording_and_of_a_failed_run(api):
    rec = recording("SN-IMP", 4)
    r = api.post("/recordings", role="operator", content=format_recording(rec).encode())
    assert r.status_code == 201
    run_id = r.json()["id"]
    page = api.get(f"/ui/runs/{run_id}", role="viewer")
    assert page.status_code == 200 and 'id="results"' in page.text and "No calibrations" in page.text
    with api.client.app.state.sessions() as session:
        run = session.get(Run, run_id)
        store_calibration(session, run, 0, "SN-IMP", fit(parse_recording(format_recording(rec)), "joint").to_json())
        session.commit()
    page = Elements(api.get(f"/ui/runs/{run_id}", role="viewer").text)
    assert page.find("div", cls="unit", data_serial="SN-IMP") and page.find("svg", cls="staged-curve")

    (failed, _), = stored_run(api, "SN-FAIL", status="failed", reason="AxisError: axis y: following error")
    r = api.get(f"/ui/runs/{failed}", role="viewer")
    assert 'id="reason"' in r.text and "following error" in r.text and 'id="results"' not in r.text
    assert api.get("/ui/runs/99999", role="viewer").status_code == 404


def test_device_history_certificate_and_pdf(api):
    runs = stored_run(api, "SN-DEV", seeds=(1, 2))
    r = api.get("/ui/devices/SN-DEV", role="viewer")
    assert r.status_code == 200
    page = Elements(r.text)
    assert page.find("table", id="history")
    ids = [int(a["data-calibration"]) for a in page.find("tr") if "data-calibration" in a]
    assert ids == [runs[1][1], runs[0][1]]  # newest first
    assert len(page.find("a", cls="certificate")) == 2
    assert page.find("a", href=f"/ui/runs/{runs[0][0]}")
    assert len(page.find("svg", cls="trend")) == 4
    # one number format per column (it said 0.016 above 0.009694)
    for column in range(5):
        cells = [re.findall(r'<td class="figure num">([^<]*)</td>', row)[column]
                 for row in re.findall(r"<tr data-calibration=.*?</tr>", r.text, re.S)]
        assert len({len(c.split(".")[1]) if "." in c else 0 for c in cells}) == 1, cells
    assert api.get("/ui/devices/NO-SUCH-UNIT", role="viewer").status_code == 404

    r = api.get("/ui/search?serial=SN-DEV", role="viewer", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/devices/SN-DEV"
    r = api.get("/ui/search?serial=sn-de", role="viewer", follow_redirects=False)
    assert r.headers["location"] == "/ui/devices/SN-DEV"  # the one partial match
    # no serial number, and no match: the search page says so (a '/' sent to a device page was a JSON 404)
    r = api.get("/ui/search?serial=SN%2FDEV", role="viewer", follow_redirects=False)
    assert r.status_code == 200 and "text/html" in r.headers["content-type"], r.text
    assert "No serial number seen by this service contains" in r.text and "&#39;/&#39; at position 3" in r.text, r.text
    # longer than a serial number: said in the API's words (the page said "at most 64 items", the API
    # "serial number of 100 characters; at most 64")
    r = api.get("/ui/search?serial=" + "A" * 100, role="viewer", follow_redirects=False)
    assert r.status_code == 200 and "serial number of 100 characters; at most 64" in r.text, r.text
        # a serial number never seen goes to its device page, which says it is unknown
    r = api.get("/ui/search?serial=NO-SUCH-UNIT", role="viewer", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/devices/NO-SUCH-UNIT"

    cal_id = runs[1][1]
    r = api.get(f"/ui/calibrations/{cal_id}/certificate", role="viewer")
    assert r.status_code == 200
    cert = Elements(r.text)
    assert cert.find("a", id="pdf", href=f"/calibrations/{cal_id}/certificate.pdf")
    assert cert.find("table", cls="table1") and cert.find("table", cls="table2") and cert.find("table", id="limits")
    assert cert.find("svg", cls="staged-curve") and cert.find("svg", cls="tilted-curve")
    for text in ("SN-DEV", "XDC-3", "1.2.0", "bench-1", "tcp://10.0.0.5:502", "operator-user", "calibrate version 2",
                 "compasscal test", "Field inclination I", "Base tilt", "heading_error_level_deg"):
        assert text in r.text, text
    assert len([a for a in cert.find("tr") if "data-limit" in a]) == 6  # every acceptance limit
    assert "@media print" in api.get("/ui/static/style.css", role=None).text

    pdf = api.get(f"/calibrations/{cal_id}/certificate.pdf", role="viewer")
    assert pdf.status_code == 200 and pdf.headers["content-type"] == "application/pdf"
    assert pdf.content.startswith(b"%PDF") and b"/Count 3" in pdf.content and len(pdf.content) > 20_000
    assert api.get("/calibrations/99999/certificate.pdf", role="viewer").status_code == 404
    assert api.get("/ui/calibrations/99999/certificate", role="viewer").status_code == 404


def new_batch(api: Any, session: Any, station: str, summary: dict[str, str]) -> Batch:
    """A completed batch of the units in ``summary`` on a new station (its runs are the caller's)."""
    r = api.put(f"/stations/{station}", json={"modbus": f"tcp://{station}.local:502", "compasses": [f"socket://{station}.local:4001"]})
    assert r.status_code == 200
    st = session.scalar(select(Station).where(Station.name == station))
    batch = Batch(station_id=st.id, serials=list(summary), status="completed", operator="operator-user", summary=summary)
    session.add(batch)
    session.flush()
    return batch


def test_batch_page_lists_units(api):
    with api.client.app.state.sessions() as session:
        batch_id = new_batch(api, session, "bench-2", {"U1": "PASS", "U2": "failed: no unit"}).id
        session.commit()
    r = api.get(f"/ui/batches/{batch_id}", role="viewer")
    page = Elements(r.text)
    assert page.find("table", id="units") and page.find("tr", data_serial="U1") and page.find("tr", data_serial="U2")
    assert "PASS" in r.text and "failed: no unit" in r.text
    assert api.get("/ui/batches/99999", role="viewer").status_code == 404
    # a running batch: operators get its abort button (batch.js: PUT /batches/{id}/state), viewers not
    assert 'id="abort-batch"' not in r.text
    with api.client.app.state.sessions() as session:
        session.get(Batch, batch_id).status = "running"
        session.commit()
    assert 'id="abort-batch"' in api.get(f"/ui/batches/{batch_id}", role="operator").text
    assert 'id="abort-batch"' not in api.get(f"/ui/batches/{batch_id}", role="viewer").text
    assert "/batches/${batchId}/state" in api.get("/ui/static/batch.js", role=None).text


def test_batch_page_shows_each_units_table_time_and_adaptive_target(api):
    """An adaptive batch: each unit's row gives its table time and its outcome against the targets, the
    budget a short unit needed included; GET /batches/{id} carries the same."""
    from service.runtime import target_said

    rounds = [{"table_s": 108.2, "level_deg": 0.031, "tilted_deg": 0.06}, {"table_s": 180.0, "level_deg": 0.024, "tilted_deg": 0.05}]
    precision = {"A1": {"met": True, "table_s": 131.5, "more_table_s": None},
                 "A2": {"met": False, "table_s": 180.0, "more_table_s": 56.2, "budget_s": 180.0, "rounds": rounds,
                        "target_level_deg": 0.02, "target_tilted_deg": 0.05}}
    with api.client.app.state.sessions() as session:
        batch = new_batch(api, session, "bench-3", {"A1": "PASS", "A2": "PASS"})
        for serial, pr in precision.items():
            rec = recording(serial)
            run = Run(procedure="batch_calibrate", procedure_version="2", parameters={"adaptive": True}, status="completed",
                      operator="operator-user", serials={"0": serial}, software_version="test", batch_id=batch.id,
                      table_seconds=pr["table_s"], station_snapshot={"name": "bench-3"})
            session.add(run)
            session.flush()
            cal = fit(rec, "joint").to_json()
            cal["quality"]["precision"] = pr
            store_calibration(session, run, 0, serial, cal)
        session.commit()
        batch_id = batch.id
    units = {u["serial"]: u for u in api.get(f"/batches/{batch_id}", role="viewer").json()["units"]}
    assert units["A1"]["table_seconds"] == 131.5 and units["A1"]["target"] == "met"
    assert units["A2"]["target"] == "not met: a 236-s budget would reach them"
    page = api.get(f"/ui/batches/{batch_id}", role="viewer").text
    for serial, time_s, target in (("A1", "132 s", "met"), ("A2", "180 s", "not met: a 236-s budget would reach them")):
        row = page[page.index(f'<tr data-serial="{serial}">'):]
        row = row[:row.index("</tr>")]
        assert f'<td class="table-s">{time_s}</td>' in row and f'<td class="target">{target}</td>' in row, row
    # the run page of the short unit plots its predicted error by round, with the budget it needed
    short = api.get(f"/ui/runs/{units['A2']['run_id']}", role="viewer").text
    assert Elements(short).find("svg", cls="precision-curve") and "would reach the targets: 236 s" in short
    assert not Elements(api.get(f"/ui/runs/{units['A1']['run_id']}", role="viewer").text).find("svg", cls="precision-curve")
    # a calibration that is not adaptive says nothing of targets; one beyond the look-ahead says so
    assert target_said({"quality": {}}) is None
    assert target_said({"quality": {"precision": {"met": False, "table_s": 180.0, "more_table_s": None}}}) == \
        "not met: needs more than 15 min more table time"


# ------------------------------------------------------------------ issue 15: pages and documents

def test_api_docs_are_served_from_the_package(api):
    """/docs works without internet: Swagger UI's script, style and icon come from this service."""
    r = api.get("/docs", role=None)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert not re.search(r"https?://|//cdn|jsdelivr|unpkg", r.text), "the docs page refers to another site"
    refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", r.text)
    assert len(refs) >= 3 and all(ref.startswith("/") and not ref.startswith("//") for ref in refs), refs
    kinds = {}
    for ref in refs:
        asset = api.get(ref, role=None)
        assert asset.status_code == 200, ref
        kinds[ref.rsplit(".", 1)[-1]] = (asset.headers["content-type"], len(asset.content))
    assert kinds["js"][0].startswith("text/javascript") and kinds["js"][1] > 500_000  # the whole bundle
    assert kinds["css"][0].startswith("text/css") and kinds["css"][1] > 50_000
    assert "url: '/openapi.json'" in r.text and api.get("/openapi.json", role=None).status_code == 200
    assert '"validatorUrl": null' in r.text  # no badge fetched from validator.swagger.io
    assert "/docs" not in api.get("/openapi.json", role=None).json()["paths"]


def test_favicon_is_served_and_linked(api):
    r = api.get("/favicon.ico", role=None)
    assert r.status_code == 200 and r.headers["content-type"] == "image/x-icon"
    assert r.content[:4] == b"\x00\x00\x01\x00"  # an ICO file
    svg = api.get("/ui/static/favicon.svg", role=None)
    assert svg.status_code == 200 and svg.headers["content-type"].startswith("image/svg+xml")
    icons = Elements(api.get("/ui/login", role=None).text).find("link", rel="icon")
    assert icons and icons[0]["href"] == "/ui/static/favicon.svg"
    # the analysis report stands alone (also a file): its icon is inline, nothing to ask the server for
    from service.web import HERE
    report = (HERE / "templates" / "analysis_report.html").read_text()
    assert re.search(r'<link rel="icon" href="data:image/svg\+xml,', report)


def live_run(sessions: Any, serials: dict[str, str] | None = None) -> int:
    """A run in progress as its worker leaves it in the database (``sessions``: the app's): rotate_z's
    samples stored, the table moved on to sweep_y (no samples of it yet), a progress event in table
    and wall seconds. (Also the browser tests' live run, tests/test_web.py.)"""
    from service.runtime import publish

    with sessions() as session:
        run = Run(procedure="calibrate", procedure_version="2", parameters={"samples": 10}, status="queued",
                  operator="operator-user", serials=serials or {}, software_version="test",
                  station_snapshot={"name": "bench-9", "modbus": "tcp://10.0.0.9:502", "compasses": ["/dev/ttyUSB0"],
                                    "time_scale": 20.0})
        session.add(run)
        session.flush()
        rec = recording("SN-LIVE")
        insert_samples(session, run.id, 0, rec.select(np.asarray(rec.step) == "rotate_z"))
        publish(session, run.id, "state", {"state": "running", "reason": None, "t": 0.0})
        publish(session, run.id, "step", {"step": {"kind": "acquire", "samples": 10, "step": "rotate_z"}, "t": 1.0})
        publish(session, run.id, "progress", {"percent": 40.0, "table_s": 53.3, "left_s": 80.0, "samples": 80,
                                               "left_wall_s": 4.0})
        publish(session, run.id, "step", {"step": {"kind": "move", "psi": 315.0, "theta": 15.0, "phi": 0.0}, "t": 54.0})
        publish(session, run.id, "step", {"step": {"kind": "acquire", "samples": 10, "step": "sweep_y"}, "t": 55.0})
        session.commit()
        return run.id


def test_run_page_names_the_live_step_the_version_and_the_last_step(api):
    run_id = live_run(api.client.app.state.sessions)
    r = api.get(f"/ui/runs/{run_id}", role="viewer")
    page = Elements(r.text)
    assert re.search(r"<small[^>]*>calibrate version 2</small>", r.text)  # not "calibrate 2"
    # the live plot waits for the step the table is at, never shows the step before as "current"
    assert page.find("section", id="run", data_live_step="sweep_y")
    assert re.search(r'id="live-caption">\(slot 0, step sweep_y\)<', r.text)
    assert re.search(r'id="step">acquire sweep_y \(10 samples\)<', r.text)
    # time left in wall seconds (80 table seconds at time scale 20)
    assert page.find("span", id="time-left", data_left_wall_s="4.0")
    assert re.search(r'id="serials">\s*-\s*<', r.text)  # no units known yet: run.js asks at the next state

    from service.runtime import publish
    with api.client.app.state.sessions() as session:
        publish(session, run_id, "state", {"state": "completed", "reason": None, "t": 90.0})
        session.commit()
    r = api.get(f"/ui/runs/{run_id}", role="viewer")
    assert re.search(r'id="step">acquire sweep_y \(10 samples\)<', r.text), "the step field of a completed run is empty"
    assert 'id="live-plot"' not in r.text


def test_time_left_is_in_wall_seconds_for_old_and_new_progress_events():
    from service.web import wall_seconds_left
    assert wall_seconds_left({"left_s": 80.0, "left_wall_s": 4.0}, 20.0) == 4.0
    assert wall_seconds_left({"left_s": 80.0}, 20.0) == 4.0  # stored before left_wall_s existed
    assert wall_seconds_left({}, 20.0) is None


def test_start_form_has_a_serial_field_per_slot(api):
    r = api.put("/stations/bench-3", json={"modbus": "tcp://bench-3.local:502", "compasses": ["socket://bench-3.local:4001", "socket://bench-3.local:4002"]})
    assert r.status_code in (200, 201), r.text
    page = Elements(api.get("/ui/stations", role="operator").text)
    serials = page.find("input", cls="serial", name="serial")
    assert [s["data-slot"] for s in serials] == ["0", "1"]
    assert all("required" not in s for s in serials)  # optional: the compass's own serial otherwise


def test_batches_page_lists_batches_and_offers_operators_a_form(api):
    r = api.put("/stations/bench-4", json={"modbus": "tcp://bench-4.local:502", "compasses": ["socket://bench-4.local:4001"]})
    assert r.status_code in (200, 201), r.text
    with api.client.app.state.sessions() as session:
        st = session.scalar(select(Station).where(Station.name == "bench-4"))
        done = Batch(station_id=st.id, serials=["U1", "U2", "U3"], status="completed", operator="operator-user",
                     summary={"U1": "PASS", "U2": "FAIL", "U3": "failed: no unit"})
        running = Batch(station_id=st.id, serials=["V1", "V2"], status="running", operator="operator-user",
                        summary={"V1": "MARGINAL"})
        # a batch whose worker was lost: one unit's run ended, one never ran (counted as its page counts)
        lost = Batch(station_id=st.id, serials=["W1", "W2", "W3", "W4"], status="failed", operator="operator-user",
                     summary={"W1": "PASS", "W2": "failed: worker lost", "W3": "not run: worker lost",
                              "W4": "not run: worker lost"})
        session.add_all([done, running, lost])
        session.commit()
        ids = (done.id, running.id)
    r = api.get("/ui/batches", role="viewer")
    assert r.status_code == 200
    page = Elements(r.text)
    assert [int(t["data-batch"]) for t in page.find("tr") if "data-batch" in t][1:] == [ids[1], ids[0]]  # newest first
    for batch_id in ids:
        assert page.find("a", href=f"/ui/batches/{batch_id}")
    assert "3 of 3" in r.text and "1 of 2" in r.text and "2 of 4" in r.text
    assert not page.find("form", id="start-batch")  # viewers only read
    assert page.find("a", id="nav-batches", href="/ui/batches")
    op = Elements(api.get("/ui/batches", role="operator").text)
    assert op.find("form", id="start-batch") and op.find("option", value="bench-4")
    assert op.find("textarea", name="serials") and op.find("button", id="start-batch-button")
    assert api.get("/ui/static/batches.js", role=None).status_code == 200
    r = api.get("/ui/batches", role=None, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"].startswith("/ui/login?next=")


def cert_context(api: Any, serial: str) -> tuple[dict[str, Any], Any, Any, Any]:
    """A stored calibration's certificate context (service/web.py), its calibration, recording and limits."""
    (_, cal_id), = stored_run(api, serial)
    return cert_context_of(api, cal_id)


def figure_texts(fig: Any) -> list[str]:
    from matplotlib.text import Text
    return [t.get_text() for t in fig.findobj(Text) if t.get_visible() and t.get_text()]


def test_certificate_limits_by_description_in_one_number_format(api):
    cert, cal, rec, limits = cert_context(api, "SN-LIM")
    r = api.get(f"/ui/calibrations/{cert['id']}/certificate", role="viewer")
    rows = re.findall(r'<tr data-limit="([^"]+)">.*?</tr>', r.text, re.S)
    assert len(rows) == 6
    for name, row in zip(rows, re.findall(r'<tr data-limit="[^"]+">(.*?)</tr>', r.text, re.S)):
        numbers = re.findall(r'<td class="num">([^<]*)</td>', row)
        assert len(numbers) == 3, (name, row)
        decimals = {len(n.split(".")[1]) if "." in n else 0 for n in numbers if n != "-"}
        assert len(decimals) == 1, f"{name}: value and limits in different formats: {numbers}"
    # one format per unit down the column too: every "deg" figure with the same decimals
    by_unit: dict[str, set[int]] = {}
    for row in cert["limits"]:
        by_unit.setdefault(row["unit"], set()).add(len(row["value_text"].split(".")[1]) if "." in row["value_text"] else 0)
    assert all(len(d) == 1 for d in by_unit.values()), by_unit

    from service import plots
    page3 = plots.certificate_pages(cert, cal, rec, limits)[2]
    text = " ".join(figure_texts(page3)).replace("\n", " ")
    for row in cert["limits"]:
        assert row["name"] not in text, f"the PDF names {row['name']} where the HTML certificate describes it"
        assert row["description"].split()[0] in text
    assert "magnitude of the magnetometer bias vector" in text
    assert "0.05 " not in text + " " and "0.0500" in text  # the level limit as its row's value is written


def blank_gap(fig: Any, footer: float = 0.06) -> float:
    """The tallest blank band (figure fraction) between the first and the last ink on a page above
    its footer."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(40)
    canvas.draw()
    img = np.asarray(canvas.buffer_rgba())[:, :, :3]
    h = img.shape[0]
    ink = (img < 235).any(axis=(1, 2))[: int(h * (1 - footer))]
    rows = np.flatnonzero(ink)
    gaps = np.diff(rows) - 1
    return float(gaps.max()) / h if len(gaps) else 0.0


def test_certificate_pdf_pages_have_no_large_blank_gaps(api):
    from service import plots
    cert, cal, rec, limits = cert_context(api, "SN-GAP")
    pages = plots.certificate_pages(cert, cal, rec, limits)
    assert len(pages) == 3
    for number in (1, 3):
        gap = blank_gap(pages[number - 1])
        assert gap < 0.06, f"page {number} has a blank band {gap:.0%} of the page high"


def test_plot_labels_and_legends_stay_out_of_the_lines(api):
    """The tilted plot's azimuth note and every legend sit outside the axes (the fail-limit line ran
    through the note), on the page's figures and the PDF's curves page alike."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from service import plots
    cert, cal, rec, limits = cert_context(api, "SN-NOTE")
    figures = {"tilted": plots.tilted_figure(cal, rec, limits), "staged": plots.staged_figure(cal, rec, limits),
               "pdf page 2": plots.certificate_pages(cert, cal, rec, limits)[1]}
    for name, fig in figures.items():
        renderer = FigureCanvasAgg(fig).get_renderer()
        fig.canvas.draw()
        notes = 0
        for ax in fig.axes:
            box = ax.get_window_extent(renderer)
            for t in ax.texts:
                assert "table azimuth" not in t.get_text(), f"{name}: the azimuth note is inside the axes"
            legend = ax.get_legend()
            if legend is not None:
                assert not legend.get_window_extent(renderer).overlaps(box), f"{name}: a legend over the axes"
            notes += "at table azimuth 315 deg" in ax.get_xlabel()
        assert notes == (0 if name == "staged" else 1), (name, [ax.get_xlabel() for ax in fig.axes])


def test_trend_axes_read_well_at_any_span():
    """One calibration: a window of minutes around it (not 2025-2029); two 12 s apart: absolute
    times with their date, no offset text; a long history: dates."""
    from datetime import datetime, timedelta

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.dates import num2date

    from physics.fit import fit as fit_recording
    from service import plots
    from service.store import figures as store_figures

    data = fit_recording(recording("SN-TREND"), "joint").to_json()
    t0 = datetime(2025, 6, 1, 10, 31, 28)

    def axis(times: list[datetime]) -> tuple[list[str], str, float]:
        hist = [{"created_at": t, "data": data, "status": "current", "figures": store_figures(data)} for t in times]
        fig = plots.trend_figures(hist)["bias"]
        FigureCanvasAgg(fig).draw()
        ax = fig.axes[0]
        lo, hi = (num2date(v) for v in ax.get_xlim())
        return ([t.get_text() for t in ax.get_xticklabels() if t.get_text()], ax.xaxis.get_offset_text().get_text(),
                (hi - lo).total_seconds())

    labels, offset, span = axis([t0])
    assert span < 3600 and offset == "" and len(labels) >= 3, (labels, span)
    assert all("2025-06-01" in label for label in labels), labels
    labels, offset, span = axis([t0, t0 + timedelta(seconds=12)])
    assert offset == "" and len(set(labels)) == len(labels) >= 3, labels
    assert all(re.match(r"\d\d:\d\d:\d\d\n2025-06-01$", label) for label in labels), labels
    labels, offset, _ = axis([t0, t0 + timedelta(days=200), t0 + timedelta(days=400)])
    assert offset == "" and all(re.match(r"20\d\d-\d\d-\d\d$", label) for label in labels), labels


def test_web_sessions_expire_end_with_their_key_and_are_secure_over_https(api):
    """A session ends at its expiry and when its key is revoked; behind an HTTPS proxy its cookie is Secure."""
    from datetime import timedelta

    from service.db import ApiKey, WebSession, utcnow

    client = api.client
    r = client.post("/ui/login", data={"key": api.keys["operator"]}, headers={"X-Forwarded-Proto": "https"},
                    follow_redirects=False)
    assert "secure" in r.headers["set-cookie"].lower()
    token = r.headers["set-cookie"].split(";")[0].split("=", 1)[1]
    client.cookies.clear()
    assert client.get("/limits", headers={"Cookie": f"{COOKIE}={token}"}).status_code == 200
    with client.app.state.sessions() as s:
        for row in s.query(WebSession).all():
            row.expires_at = utcnow() - timedelta(seconds=1)
        s.commit()
    client.app.state.key_cache = {}
    assert client.get("/limits", headers={"Cookie": f"{COOKIE}={token}"}).status_code == 401  # expired
    r = client.post("/ui/login", data={"key": api.keys["viewer"]}, follow_redirects=False)
    token = r.headers["set-cookie"].split(";")[0].split("=", 1)[1]
    client.cookies.clear()
    with client.app.state.sessions() as s:
        s.query(ApiKey).filter(ApiKey.owner == "viewer-user").one().revoked = True
        s.commit()
    client.app.state.key_cache = {}
    assert client.get("/limits", headers={"Cookie": f"{COOKIE}={token}"}).status_code == 401  # its key revoked


@pytest.mark.parametrize("path", ["/ui/runs/2147483648", "/ui/runs/99999999999999999999", "/ui/devices/a%00b",
                                  "/ui/search?serial=a%00b", "/ui/runs/1/samples.json?slot=-1", "/ui/batches/0",
                                  "/ui/calibrations/3000000000/certificate", "/ui/runs/abc"])
def test_pages_refuse_out_of_range_ids_and_nul_bytes(api, path: str):
    """The pages take ids, slots and serials with the API's own limits: a 422, never a 500 (an id
    beyond PostgreSQL's integer, a NUL it cannot store); a page as a page naming the problem (it was
    the API's JSON), the pages' JSON as JSON."""
    r = api.get(path, role="viewer")
    assert r.status_code == 422
    if ".json" in path:
        assert r.json()["detail"][0]["field"] == "query.slot", r.text
    else:
        assert "text/html" in r.headers["content-type"] and "Not a page address" in r.text, r.text
        assert re.search(r"path\.\w+|query\.\w+", r.text), r.text


def test_a_certificate_shows_the_limits_its_verdict_was_judged_against(api):
    """A limit tightened for one calibration (FAIL) and restored afterwards made its certificate list every
    figure PASS against today's limits, beside the verdict "FAIL (rejected)": the certificate contradicted
    itself. A calibration keeps the limits it was judged by; its certificate, PDF, run page and JSON show
    those. One stored before limits were kept is shown against today's."""
    from service.db import Calibration

    wide = today(api, "misalignment_deg")
    assert api.put("/limits/misalignment_deg", role="admin", json={"marginal": 1e-4, "fail": 2e-4}).status_code == 200
    (run_id, cal_id), = stored_run(api, "SN-JUDGED")
    assert api.put("/limits/misalignment_deg", role="admin",
                   json={"marginal": wide["marginal"], "fail": wide["fail"]}).status_code == 200
    cal = api.get(f"/calibrations/{cal_id}", role="viewer").json()
    assert cal["verdict"] == "FAIL" and any("misalignment_deg" in r for r in cal["reasons"])
    judged = {lim["name"]: lim for lim in cal["limits"]}
    assert judged["misalignment_deg"]["fail"] == 2e-4 and judged["bias_lsb"]["fail"] == today(api, "bias_lsb")["fail"]
    cert, _, _, limits = cert_context_of(api, cal_id)
    row = next(r for r in cert["limits"] if r["name"] == "misalignment_deg")
    assert row["result"] == "FAIL" and row["fail"] == 2e-4, row
    assert dict((n, p) for n, p in limits.items())["misalignment_deg"] == (1e-4, 2e-4)
    page = api.get(f"/ui/calibrations/{cal_id}/certificate", role="viewer").text
    misalignment = re.search(r'<tr data-limit="misalignment_deg">(.*?)</tr>', page, re.S).group(1)
    assert "FAIL" in misalignment and "PASS" not in misalignment
    assert api.get(f"/ui/runs/{run_id}", role="viewer").status_code == 200  # (its plots draw the judged limits)
    # a calibration stored before the limits were kept: today's, as before
    with api.client.app.state.sessions() as session:
        session.get(Calibration, cal_id).limits = None
        session.commit()
    cert, _, _, limits = cert_context_of(api, cal_id)
    assert limits["misalignment_deg"] == (wide["marginal"], wide["fail"])
    assert api.get(f"/calibrations/{cal_id}", role="viewer").json()["limits"] is None


def today(api: Any, name: str) -> dict[str, Any]:
    """Limit ``name`` as in force now."""
    return {lim["name"]: lim for lim in api.get("/limits", role="viewer").json()}[name]


def cert_context_of(api: Any, cal_id: int) -> tuple[dict[str, Any], Any, Any, dict[str, tuple[float, float]]]:
    from service.db import Calibration
    from service.web import certificate_context, limit_pairs

    with api.client.app.state.sessions() as session:
        cert, cal, rec, limits = certificate_context(session, session.get(Calibration, cal_id))
    return cert, cal, rec, limit_pairs(limits)
