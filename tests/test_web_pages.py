"""The web pages and certificates without a browser (TestClient, SQLite and PostgreSQL): login and
the session cookie, redirects to the login, the run page's tables and curves, the device history,
the certificate page and its PDF. The browser tests are tests/test_web.py."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from typing import Any

import numpy as np
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

    bad = client.post("/ui/login", data={"key": "cc_wrong", "next": "/ui/stations"}, follow_redirects=False)
    assert bad.status_code == 401 and "not valid" in bad.text and COOKIE not in bad.headers.get("set-cookie", "")

    r = client.post("/ui/login", data={"key": api.keys["viewer"], "next": "/ui/devices/X"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/devices/X"
    cookie = r.headers["set-cookie"]
    assert cookie.startswith(f"{COOKIE}=") and "HttpOnly" in cookie and "samesite=strict" in cookie.lower()
    assert "expires" not in cookie.lower() and "max-age" not in cookie.lower()  # ends with the browser session
    page = client.get("/ui/stations")  # the cookie alone now
    assert page.status_code == 200 and "viewer-user" in page.text
    assert Elements(page.text).find("table", id="stations") and Elements(page.text).find("form", id="search")
    assert not Elements(page.text).find("form", cls="start-run")  # viewers cannot start runs
    assert client.get("/limits").status_code == 200  # the JSON API takes the cookie too

    r = client.post("/ui/login", data={"key": api.keys["viewer"], "next": "//evil.example/x"}, follow_redirects=False)
    assert r.headers["location"] == "/ui/stations"  # never off the site

    r = client.post("/ui/logout", follow_redirects=False)
    assert r.status_code == 303 and f'{COOKIE}=""' in r.headers["set-cookie"]
    client.cookies.clear()
    assert client.get("/ui/stations", follow_redirects=False).status_code == 303


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
    r = api.put("/stations/bench-1", json={"modbus": "tcp://127.0.0.1:1", "compasses": ["tcp://127.0.0.1:2"]})
    assert r.status_code == 200, r.text
    page = Elements(api.get("/ui/stations", role="operator").text)
    assert page.find("tr", data_station="bench-1")
    assert page.find("td", cls="state")
    assert page.find("form", cls="start-run", data_station="bench-1")
    assert page.find("button", cls="start", id="start-bench-1")
    assert page.find("select", name="procedure") and page.find("option", value="calibrate", selected="")
    assert page.find("input", name="samples")


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
    assert api.get("/ui/devices/NO-SUCH-UNIT", role="viewer").status_code == 404

    r = api.get("/ui/search?serial=SN-DEV", role="viewer", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/devices/SN-DEV"
    r = api.get("/ui/search?serial=sn-de", role="viewer", follow_redirects=False)
    assert r.headers["location"] == "/ui/devices/SN-DEV"  # the one partial match

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


def test_batch_page_lists_units(api):
    r = api.put("/stations/bench-2", json={"modbus": "tcp://127.0.0.1:1", "compasses": ["tcp://127.0.0.1:2"]})
    assert r.status_code == 200
    with api.client.app.state.sessions() as session:
        st = session.scalar(select(Station).where(Station.name == "bench-2"))
        batch = Batch(station_id=st.id, serials=["U1", "U2"], status="completed", operator="operator-user",
                      summary={"U1": "PASS", "U2": "failed: no unit"})
        session.add(batch)
        session.commit()
        batch_id = batch.id
    r = api.get(f"/ui/batches/{batch_id}", role="viewer")
    page = Elements(r.text)
    assert page.find("table", id="units") and page.find("tr", data_serial="U1") and page.find("tr", data_serial="U2")
    assert "PASS" in r.text and "failed: no unit" in r.text
    assert api.get("/ui/batches/99999", role="viewer").status_code == 404
