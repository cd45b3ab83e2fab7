"""The web pages end to end in headless Chromium (Debian's, driven by Playwright; see tests/browser.py),
against the service served by uvicorn on a local port and a simulated station, on SQLite.

The calibration as a technician and a quality engineer see it: log in, start a calibration on the
stations page, watch its progress reach 100 %, read the tables, curves and verdict, find the unit by
its serial number, its history and trends, its certificate and the certificate's PDF. Then pause,
resume and abort from the run page, a failed run's reason, what a viewer may not do, and the
redirect to the login page. Every page is screenshotted, may log no console error and raise no
error, and may load nothing from outside the machine.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import httpx
import pytest

from browser import BrowserSetupError, Guard, Shots, ensure_chromium, free_port, guarded_context, launch, serve
from conftest import fresh_database, sim_station
from drivers.sim.config import reference_config

ROOT = Path(__file__).resolve().parent.parent
SERIAL = "GAO2017-REF"  # the paper's reference unit (drivers.sim.config.reference_config)
FINAL = ("completed", "failed", "aborted")
#: Generous waits (ms); a calibration at time scale 40 takes about 5 s of wall time.
RUN_TIMEOUT_MS = 60_000
STATE_TIMEOUT_MS = 20_000
#: Records every text #progress shows, from the first paint on (to see the progress is live), in
#: sessionStorage: the run page reloads itself when the run ends, to show the server-rendered results.
PROGRESS_RECORDER = """
document.addEventListener('DOMContentLoaded', () => {
  const seen = () => {
    const el = document.getElementById('progress');
    const text = el ? el.textContent.trim() : null;
    const all = JSON.parse(sessionStorage.getItem('progress-seen') || '[]');
    if (text && all[all.length - 1] !== text) {
      all.push(text);
      sessionStorage.setItem('progress-seen', JSON.stringify(all));
    }
  };
  seen();
  new MutationObserver(seen).observe(document.documentElement, {subtree: true, childList: true, characterData: true});
});
"""


# ------------------------------------------------------------------------------------------ set-up

@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Debian's Chromium, installed first if missing (a failure, never a skip, when it cannot be)."""
    try:
        ensure_chromium()
    except BrowserSetupError as e:
        pytest.fail(str(e), pytrace=False)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("the Python package playwright is missing: pip install -e '.[test]' "
                    "(its browser download is not needed: the tests use /usr/bin/chromium)", pytrace=False)
    with sync_playwright() as p:
        b = launch(p)
        try:
            yield b
        finally:
            b.close()


@dataclass
class Site:
    """The service on a fresh SQLite database, served on a local port, with a key per role."""

    base: str
    app: Any
    keys: dict[str, str]
    shots: Shots
    http: httpx.Client
    station: dict[str, Any] | None = None
    guards: list[Guard] = field(default_factory=list)

    def api(self, method: str, path: str, role: str = "admin", **kw: Any) -> httpx.Response:
        return self.http.request(method, path, headers={"X-API-Key": self.keys[role]}, **kw)

    def run(self, run_id: int) -> dict[str, Any]:
        r = self.api("GET", f"/runs/{run_id}", "viewer")
        assert r.status_code == 200, r.text
        return r.json()

    @contextmanager
    def context(self, browser: Any) -> Iterator[tuple[Any, Guard]]:
        """A browser context of its own (cookies and all); its guard is checked at the end of the test."""
        with guarded_context(browser, self.base) as (ctx, guard):
            self.guards.append(guard)
            yield ctx, guard


def shots_dir(tmp_path: Path, request: pytest.FixtureRequest) -> Path:
    """``out/screenshots`` under the test's tmp path, or under $COMPASSCAL_SCREENSHOTS to keep them."""
    keep = os.environ.get("COMPASSCAL_SCREENSHOTS")
    return (Path(keep) / request.node.name) if keep else tmp_path / "out" / "screenshots"


@contextmanager
def site(tmp_path: Path, request: pytest.FixtureRequest, time_scale: float | None = None,
         seed: int = 1) -> Iterator[Site]:
    """The service, and with ``time_scale`` a simulated reference station registered as ``sim``.

    The station outlives the server (the server's shutdown stops any run still using it); the
    browser contexts are closed before the server stops; the guards and screenshots are checked last."""
    from service.app import create_app
    from service.auth import create_key

    with ExitStack() as stack:
        info = stack.enter_context(sim_station(reference_config(seed=seed, time_scale=time_scale))) if time_scale else None
        app = create_app(fresh_database("sqlite", tmp_path))
        base = stack.enter_context(serve(app))
        http = stack.enter_context(httpx.Client(base_url=base, timeout=15, follow_redirects=False))
        with app.state.sessions() as session:
            keys = {role: create_key(session, f"{role}-user", role) for role in ("viewer", "operator", "admin")}
        s = Site(base, app, keys, Shots(shots_dir(tmp_path, request)), http)
        if info is not None:
            s.station = {"modbus": info["modbus"], "compasses": [c["url"] for c in info["compasses"]],
                         "time_scale": time_scale}
            r = s.api("PUT", "/stations/sim", json=s.station)
            assert r.status_code in (200, 201), r.text
            assert [c["serial"] for c in info["compasses"]] == [SERIAL]
        yield s
    for guard in s.guards:
        guard.check()
    s.shots.check()


def login(page: Any, key: str, shots: Shots | None = None) -> None:
    """Log in on /ui/login with ``key``; lands on the stations page."""
    r = page.goto("/ui/login")
    assert r is not None and r.status == 200, (f"/ui/login answered {r and r.status}"
                                               + ("" if (ROOT / "service" / "web.py").exists() else
                                                  " (service/web.py, the web pages, does not exist yet)"))
    page.fill("input#api-key", key)
    if shots:
        shots(page, "login")
    page.click("button#login")
    page.wait_for_url(re.compile(r"/ui/stations(\?.*)?$"))


def wait_text(page: Any, selector: str, pattern: str, timeout: float = STATE_TIMEOUT_MS) -> str:
    """Wait until the element's trimmed text matches the regular expression; returns the text."""
    try:
        page.wait_for_function(
            """([sel, pat]) => { const el = document.querySelector(sel);
                                 return !!el && new RegExp(pat).test(el.textContent.trim()); }""",
            arg=[selector, pattern], timeout=timeout, polling=100)
    except Exception as e:
        now = page.evaluate("sel => { const el = document.querySelector(sel); return el ? el.textContent.trim() : null; }",
                            selector)
        raise AssertionError(f"{selector} on {page.url} never matched /{pattern}/ within {timeout / 1000:.0f} s; "
                             f"it shows {now!r}") from e
    return page.locator(selector).first.inner_text().strip()


def assert_drawn(locator: Any, what: str) -> None:
    """The element is visible, has an area, and any image in or at it has loaded."""
    assert locator.count() >= 1, f"no {what}"
    el = locator.first
    el.scroll_into_view_if_needed()
    assert el.is_visible(), f"{what} is not visible"
    box = el.bounding_box()
    assert box and box["width"] > 20 and box["height"] > 20, f"{what} has no area: {box}"
    broken = el.evaluate("""el => [el, ...el.querySelectorAll('img')].filter(i => i.tagName === 'IMG')
                                 .filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.src)""")
    assert not broken, f"{what}: images that did not load: {broken}"


def start_run_api(s: Site, procedure: str = "calibrate", **parameters: Any) -> int:
    r = s.api("POST", "/runs", "operator", json={"station": "sim", "procedure": procedure, "parameters": parameters})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def wait_run_api(s: Site, run_id: int, until: tuple[str, ...] = FINAL, timeout: float = 30.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while (j := s.run(run_id))["status"] not in until:
        assert time.monotonic() < deadline, f"run {run_id} still {j['status']} after {timeout} s"
        time.sleep(0.1)
    return j


# ------------------------------------------------------------------------------------------- tests

def test_calibration_end_to_end(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    """Stations page -> start a calibration -> live progress to 100 % -> tables, curves, verdict ->
    device history and trends via the search box -> certificate -> its PDF."""
    with site(tmp_path, request, time_scale=40) as s, s.context(browser) as (ctx, guard):
        ctx.add_init_script(PROGRESS_RECORDER)
        page = ctx.new_page()
        login(page, s.keys["operator"], s.shots)

        # the stations page: the simulated station, idle, with its start form
        row = page.locator('table#stations tr[data-station="sim"]')
        row.wait_for()
        assert row.locator("td.state").inner_text().strip().lower() == "idle"
        form = page.locator('form.start-run[data-station="sim"]')
        assert form.count() == 1
        procedures = form.locator("select[name=procedure] option").evaluate_all("os => os.map(o => o.value)")
        assert "calibrate" in procedures, procedures
        form.locator("select[name=procedure]").select_option("calibrate")
        form.locator("input[name=samples]").fill("20")
        s.shots(page, "stations")
        start = form.locator("button.start")
        assert start.get_attribute("id") == "start-sim"
        start.click()
        page.wait_for_url(re.compile(r"/ui/runs/\d+$"))
        run_id = int(urlsplit(page.url).path.rsplit("/", 1)[1])
        run = s.run(run_id)
        assert run["procedure"] == "calibrate" and run["parameters"]["samples"] == 20
        assert run["operator"] == "operator-user"
        # started without a serial number: the live page shows the unit once the run has read it
        # from the compass (before: "units -" until the run ended)
        page.wait_for_function(
            """serial => !!document.getElementById('live-plot')
                        && document.getElementById('serials').textContent.includes(serial)""",
            arg=SERIAL, timeout=RUN_TIMEOUT_MS, polling=100)

        # live: progress, time left, samples, the live plot
        page.locator("#live-plot").wait_for()
        for sel in ("#state", "#progress", "#time-left", "#samples", "#pause", "#resume", "#abort", "#prompts"):
            assert page.locator(sel).count() == 1, f"the run page has no {sel}"
        s.shots(page, "run-live")
        wait_text(page, "#progress", r"(^|\D)100\.0 %$", RUN_TIMEOUT_MS)
        wait_text(page, "#state", r"^completed$", STATE_TIMEOUT_MS)
        # the page's final state comes over SSE; allow the API's row a moment to agree
        run, deadline = s.run(run_id), time.monotonic() + 5.0
        while run["status"] != "completed" and time.monotonic() < deadline:
            time.sleep(0.1)
            run = s.run(run_id)
        assert run["status"] == "completed", f"run {run['status']}: {run.get('reason')}"
        # the results (the page may reload itself to show them)
        unit = page.locator(f'section#results div.unit[data-slot="0"][data-serial="{SERIAL}"]')
        unit.wait_for(timeout=STATE_TIMEOUT_MS)
        page.wait_for_load_state("load")
        progress = page.locator("#progress").inner_text().strip()
        assert progress.endswith("100.0 %"), progress
        assert page.locator("#state").inner_text().strip() == "completed"
        # the last step: the fit after the table's steps
        assert page.locator("#step").inner_text().strip() == "computing the calibration fit", "no last step shown"
        seen = json.loads(page.evaluate("sessionStorage.getItem('progress-seen') || '[]'"))
        values = [float(m.group(1)) for t in seen if (m := re.search(r"([\d.]+) %$", t))]
        assert len(set(values)) >= 3, f"#progress hardly moved while the run ran: {seen}"
        assert values == sorted(values) and values[-1] == 100.0, f"#progress went backwards or stopped short: {seen}"
        assert str(run["samples_count"]) in page.locator("#samples").inner_text(), \
            f"#samples shows {page.locator('#samples').inner_text()!r}, the run has {run['samples_count']} samples"
        for button in ("#pause", "#resume", "#abort"):
            assert page.locator(button).is_disabled(), f"{button} is still enabled on a completed run"

        # the results: the paper's two tables, the curves, the verdict, the certificate link
        assert page.locator("section#results div.unit").count() == 1
        for table in ("table.table1", "table.table2"):
            assert unit.locator(table).count() == 1, f"no {table} in the unit's results"
            assert unit.locator(f"{table} tr").count() >= 3, f"{table} has almost no rows"
            assert unit.locator(table).is_visible()
        assert_drawn(unit.locator(".staged-curve"), "the staged error-separation curves")
        assert_drawn(unit.locator(".tilted-curve"), "the tilted heading-error curves")
        cal = run["calibrations"][0]
        assert cal["serial"] == SERIAL and cal["verdict"] in ("PASS", "MARGINAL"), cal
        verdict = unit.locator("div.verdict").inner_text()
        assert cal["verdict"] in verdict, f"div.verdict shows {verdict!r}, the calibration's verdict is {cal['verdict']}"
        assert ({"PASS", "MARGINAL", "FAIL"} - {cal["verdict"]}).isdisjoint(verdict.split()), verdict
        cert_link = unit.locator("a.certificate")
        assert cert_link.count() == 1
        assert urlsplit(cert_link.get_attribute("href")).path == f"/ui/calibrations/{cal['id']}/certificate"
        assert page.locator("#reason").count() == 0 or not page.locator("#reason").inner_text().strip()
        s.shots(page, "run-results")

        # the unit's history through the search box
        page.fill("form#search input[name=serial]", SERIAL)
        page.press("form#search input[name=serial]", "Enter")
        page.wait_for_url(re.compile(rf"/ui/devices/{re.escape(SERIAL)}$"))
        history = page.locator("table#history tr:has(td)")
        history.first.wait_for()
        assert history.count() == 1, f"{history.count()} rows in the history of a unit calibrated once"
        assert cal["verdict"] in history.first.inner_text()
        trends = page.locator(".trend")
        assert trends.count() >= 1, "no trend plots on the device page"
        for i in range(trends.count()):
            assert_drawn(trends.nth(i), f"trend plot {i + 1}")
        links = page.locator("a.certificate")
        assert links.count() >= 1
        s.shots(page, "device")

        # the certificate: printable page, its content, its PDF
        links.first.click()
        page.wait_for_url(re.compile(rf"/ui/calibrations/{cal['id']}/certificate$"))
        page.wait_for_load_state("load")
        text = page.locator("body").inner_text()
        device = s.api("GET", f"/devices/{SERIAL}", "viewer").json()
        for expected in (SERIAL, device["model"], device["firmware"], cal["verdict"], "sim", "operator-user"):
            assert expected in text, f"the certificate does not mention {expected!r}"
        s.shots(page, "certificate")
        pdf = page.locator("a#pdf")
        assert pdf.count() == 1
        href = pdf.get_attribute("href")
        assert urlsplit(href).path == f"/calibrations/{cal['id']}/certificate.pdf", href
        r = page.request.get(href, timeout=30_000)  # with the browser's session cookie
        assert r.status == 200, f"{href}: {r.status} {r.text()[:300]}"
        assert r.headers["content-type"].startswith("application/pdf"), r.headers["content-type"]
        body = r.body()
        assert body.startswith(b"%PDF") and len(body) > 1000, body[:40]
        (s.shots.dir / "certificate.pdf").write_bytes(body)
        # the PDF for scripts: the X-API-Key header, and nothing without a key
        r2 = s.api("GET", f"/calibrations/{cal['id']}/certificate.pdf", "viewer")
        assert r2.status_code == 200 and r2.content.startswith(b"%PDF")
        assert s.http.get(f"/calibrations/{cal['id']}/certificate.pdf").status_code == 401
        guard.check()


def test_pause_resume_and_abort_from_the_run_page(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    with site(tmp_path, request, time_scale=20, seed=5) as s, s.context(browser) as (ctx, guard):
        page = ctx.new_page()
        page.on("dialog", lambda d: d.accept())  # an "are you sure?" before aborting is fine
        login(page, s.keys["operator"])
        run_id = start_run_api(s, samples=40)
        page.goto(f"/ui/runs/{run_id}")
        wait_text(page, "#state", r"^running$")
        s.shots(page, "running")
        page.click("#pause")
        wait_text(page, "#state", r"^paused$")
        assert s.run(run_id)["status"] == "paused"
        s.shots(page, "paused")
        page.click("#resume")
        wait_text(page, "#state", r"^running$")
        assert s.run(run_id)["status"] == "running"
        page.click("#abort")
        wait_text(page, "#state", r"^aborted$")
        run = wait_run_api(s, run_id)
        assert run["status"] == "aborted" and run["calibrations"] == []
        page.locator("div#reason").wait_for()  # the page may reload itself once the run has ended
        page.wait_for_load_state("load")
        assert "aborted" in page.locator("div#reason").inner_text()
        assert page.locator("#state").inner_text().strip() == "aborted"
        assert not page.locator("#progress").inner_text().strip().endswith("100.0 %")
        for button in ("#pause", "#resume", "#abort"):
            assert page.locator(button).is_disabled(), f"{button} is still enabled on an aborted run"
        assert page.locator("section#results div.unit").count() == 0
        s.shots(page, "aborted")
        # the stations page shows the station free again
        page.goto("/ui/stations")
        wait_text(page, 'tr[data-station="sim"] td.state', r"^idle$")
        guard.check()


def test_operator_prompts_are_answered_on_the_run_page(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    """A batch unit's run waits for the operator to mount the unit: the prompt shows on the run page,
    with an answer button for an operator and none for a viewer; answering lets the run go on."""
    with site(tmp_path, request, time_scale=40, seed=2) as s, s.context(browser) as (ctx, guard), \
            s.context(browser) as (vctx, vguard):
        page, viewer = ctx.new_page(), vctx.new_page()
        login(page, s.keys["operator"])
        login(viewer, s.keys["viewer"])
        r = s.api("POST", "/batches", "operator", json={"station": "sim", "serials": [SERIAL], "parameters": {"samples": 10}})
        assert r.status_code == 202, r.text
        deadline = time.monotonic() + 30
        while not (b := s.api("GET", f"/batches/{r.json()['id']}", "viewer").json())["prompt"]:
            assert time.monotonic() < deadline, b
            time.sleep(0.1)
        run_id = b["prompt"]["run_id"]
        page.goto(f"/ui/runs/{run_id}")
        answer = page.locator("#prompts button.answer")
        answer.wait_for()
        assert answer.count() == 1 and f"mount unit {SERIAL}" in page.locator("#prompts").inner_text()
        s.shots(page, "prompt")
        viewer.goto(f"/ui/runs/{run_id}")
        viewer.locator("#prompts").get_by_text(f"mount unit {SERIAL}").wait_for()
        assert viewer.locator("#prompts button.answer").count() == 0, "a viewer is offered to answer a prompt"
        for button in ("#pause", "#resume", "#abort"):
            assert viewer.locator(button).count() == 0 or viewer.locator(button).is_disabled(), \
                f"a viewer is offered {button}"
        s.shots(viewer, "prompt-as-viewer")
        answer.click()
        answer.wait_for(state="detached")
        viewer.locator("#prompts button.answer, #prompts .prompt").first.wait_for(state="detached")
        deadline = time.monotonic() + 10
        while (run := s.run(run_id))["prompts"] and time.monotonic() < deadline:
            time.sleep(0.1)
        assert run["prompts"] == [] and run["status"] in ("running", "completed"), run
        if run["status"] == "running":
            assert s.api("PUT", f"/runs/{run_id}/state", "operator", json={"state": "aborted"}).status_code == 202
        wait_text(page, "#state", r"^(aborted|completed)$")
        wait_text(viewer, "#state", r"^(aborted|completed)$")
        guard.check()
        vguard.check()


def test_a_failed_run_shows_its_reason(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    """A station whose table does not answer: the run fails, and the run page says why."""
    with site(tmp_path, request) as s, s.context(browser) as (ctx, guard):
        dead = {"modbus": f"tcp://127.0.0.1:{free_port()}", "compasses": [f"socket://127.0.0.1:{free_port()}"],
                "time_scale": 20}
        assert s.api("PUT", "/stations/sim", json=dead).status_code in (200, 201)
        page = ctx.new_page()
        login(page, s.keys["operator"])
        run_id = start_run_api(s, samples=5)
        page.goto(f"/ui/runs/{run_id}")
        wait_text(page, "#state", r"^failed$", 30_000)
        run = wait_run_api(s, run_id)
        assert run["status"] == "failed" and run["reason"]
        reason = page.locator("div#reason")
        reason.wait_for()
        assert reason.inner_text().strip(), "div#reason is empty"
        s.shots(page, "failed")
        guard.check()


def test_a_viewer_cannot_start_runs(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    with site(tmp_path, request) as s, s.context(browser) as (ctx, guard):
        station = {"modbus": "tcp://127.0.0.1:1502", "compasses": ["socket://127.0.0.1:4001"], "time_scale": 20}
        assert s.api("PUT", "/stations/sim", json=station).status_code in (200, 201)
        page = ctx.new_page()
        login(page, s.keys["viewer"])
        page.locator('table#stations tr[data-station="sim"]').wait_for()
        s.shots(page, "stations-as-viewer")
        start = page.locator("button.start")
        if start.count() and start.first.is_visible():  # shown anyway: the attempt must be refused
            guard.allowed.append("status of 403")
            with page.expect_response(lambda r: r.request.method == "POST", timeout=15_000) as resp:
                start.first.click()
            assert resp.value.status == 403, f"a viewer's start got {resp.value.status}"
        # the browser session's cookie carries the viewer's role to the API too
        r = page.request.post(f"{s.base}/runs", data={"station": "sim", "parameters": {"samples": 5}}, timeout=15_000)
        assert r.status == 403, f"POST /runs with a viewer's session: {r.status}"
        assert s.api("GET", "/runs", "viewer").json() == []
        guard.check()


def test_pages_without_a_key_redirect_to_the_login(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    with site(tmp_path, request) as s, s.context(browser) as (ctx, guard):
        page = ctx.new_page()
        for path in ("/ui/stations", f"/ui/devices/{SERIAL}", "/ui/runs/1", "/ui/calibrations/1/certificate"):
            page.goto(path)
            url = urlsplit(page.url)
            assert url.path == "/ui/login", f"{path} without a key ended on {page.url}"
            assert parse_qs(url.query).get("next") == [path], f"{path} without a key: {page.url}"
        s.shots(page, "login")
        # scripts: no key -> a redirect, the X-API-Key header -> the page
        r = s.http.get("/ui/stations")
        assert r.status_code in (302, 303, 307) and urlsplit(r.headers["location"]).path == "/ui/login"
        r = s.api("GET", "/ui/stations", "viewer")
        assert r.status_code == 200 and re.search(r"""id=["']?stations\b""", r.text), r.text[:300]
        # a wrong key does not log in
        guard.allowed += ["status of 401", "status of 403"]
        page.goto("/ui/login?next=/ui/stations")
        page.fill("input#api-key", "cc_not-a-key")
        page.click("button#login")
        page.wait_for_load_state("load")
        assert urlsplit(page.url).path != "/ui/stations", "a wrong key was let in"
        s.shots(page, "wrong-key")
        page.goto("/ui/stations")
        assert urlsplit(page.url).path == "/ui/login"
        # the right key, from a redirect: in, and kept for the browser session
        page.goto("/ui/stations")
        page.fill("input#api-key", s.keys["viewer"])
        page.click("button#login")
        page.wait_for_url(re.compile(r"/ui/stations$"))
        page.goto("/ui/stations")
        assert urlsplit(page.url).path == "/ui/stations"
        page.locator("table#stations").wait_for(state="attached")
        s.shots(page, "logged-in")
        guard.check()


# ------------------------------------------------------------------ issue 15: pages and documents

def test_api_docs_render_offline(browser: Any, tmp_path: Path, request: pytest.FixtureRequest):
    """/docs in a browser that cannot reach the internet: Swagger UI (from the package) lists the
    operations, and nothing is asked of another site (the guard blocks and reports it)."""
    with site(tmp_path, request) as s, s.context(browser) as (ctx, guard):
        page = ctx.new_page()
        r = page.goto("/docs")
        assert r is not None and r.status == 200
        ops = page.locator(".opblock-summary")
        ops.first.wait_for(timeout=STATE_TIMEOUT_MS)
        spec = s.http.get("/openapi.json").json()
        operations = sum(len(v) for v in spec["paths"].values())
        assert ops.count() == operations, f"Swagger UI lists {ops.count()} operations, the OpenAPI has {operations}"
        summary = page.locator(".opblock-summary-path", has_text="/runs/{run_id}/events")
        assert summary.count() >= 1, "the run events operation is not listed"
        assert page.locator(".info .title").inner_text().startswith("compasscal")
        s.shots(page, "docs")
        guard.check()


def test_live_run_page_follows_the_step_the_units_and_the_time_left(browser: Any, tmp_path: Path,
                                                                    request: pytest.FixtureRequest):
    """A run in the database as its worker writes it (tests/test_web_pages.py live_run), followed
    over the events: the live plot is the step the table is at (never the one before), the units
    appear once the run knows them, time left is wall time, and a completed run keeps its last step."""
    import numpy as np

    from test_web_pages import live_run, recording

    from service.db import Run
    from service.runtime import publish
    from service.store import insert_samples

    with site(tmp_path, request) as s, s.context(browser) as (ctx, guard):
        sessions = s.app.state.sessions
        run_id = live_run(sessions)
        page = ctx.new_page()
        login(page, s.keys["viewer"])
        page.goto(f"/ui/runs/{run_id}")
        assert "calibrate version 2" in page.locator("h1").inner_text()
        wait_text(page, "#live-caption", r"^\(slot 0, step sweep_y\)$")
        wait_text(page, "section#live", r"waiting for the samples of step sweep_y")
        assert page.locator("#live-plot polyline").count() == 0, "the plot shows rotate_z as the current step"
        wait_text(page, "#time-left", r"^4 s$")  # 80 s of table time at time scale 20
        assert page.locator("#serials").inner_text().strip() == "-"
        s.shots(page, "live-waiting")

        def publish_now(kind: str, data: dict[str, Any]) -> None:
            with sessions() as session:
                publish(session, run_id, kind, data)
                session.commit()

        # the units: the run learns them from the compasses as it starts (a state change)
        with sessions() as session:
            session.get(Run, run_id).serials = {"0": "SN-LIVE"}
            session.commit()
        publish_now("state", {"state": "running", "reason": None, "t": 56.0})
        wait_text(page, "#serials", r"slot 0: SN-LIVE")
        assert page.locator("#serials a").get_attribute("href") == "/ui/devices/SN-LIVE"

        # sweep_y's samples arrive: now the plot is theirs
        rec = recording("SN-LIVE")
        with sessions() as session:
            insert_samples(session, run_id, 0, rec.select(np.asarray(rec.step) == "sweep_y"))
            session.commit()
        publish_now("samples", {"step": "sweep_y", "count": 140})
        publish_now("progress", {"percent": 70.0, "table_s": 93.0, "left_s": 30.0, "samples": 140, "left_wall_s": 1.5})
        wait_text(page, "section#live", r"step sweep_y: \d+ poses")
        assert page.locator("#live-plot polyline").count() == 3
        wait_text(page, "#time-left", r"^2 s$")
        s.shots(page, "live-sweep_y")
        # the next step: the caption moves on at once, the plot waits again
        publish_now("step", {"step": {"kind": "acquire", "samples": 10, "step": "sweep_x"}, "t": 95.0})
        wait_text(page, "#live-caption", r"^\(slot 0, step sweep_x\)$")
        wait_text(page, "#step", r"^acquire sweep_x \(10 samples\)$")
        assert page.locator("#live-plot polyline").count() == 0

        publish_now("state", {"state": "completed", "reason": None, "t": 120.0})
        page.locator("section#results").wait_for(timeout=STATE_TIMEOUT_MS)  # the page reloads itself
        page.wait_for_load_state("load")
        assert page.locator("#state").inner_text().strip() == "completed"
        assert page.locator("#step").inner_text().strip() == "acquire sweep_x (10 samples)"
        assert page.locator("#serials").inner_text().strip() == "slot 0: SN-LIVE"
        s.shots(page, "completed")
        guard.check()


def test_start_a_run_with_a_serial_and_a_batch_from_the_pages(browser: Any, tmp_path: Path,
                                                             request: pytest.FixtureRequest):
    """The stations page's start form sends the serial number typed for a slot; the batches page
    starts a batch from a list of serial numbers and lists it."""
    with site(tmp_path, request) as s, s.context(browser) as (ctx, guard):
        for name in ("dead-1", "dead-2"):  # nothing answers: each run fails at once, which is all we need here
            dead = {"modbus": f"tcp://127.0.0.1:{free_port()}", "compasses": [f"socket://127.0.0.1:{free_port()}"],
                    "time_scale": 20}
            assert s.api("PUT", f"/stations/{name}", json=dead).status_code in (200, 201)
        page = ctx.new_page()
        login(page, s.keys["operator"])
        form = page.locator('form.start-run[data-station="dead-1"]')
        form.locator('input.serial[data-slot="0"]').fill("  SN-FORM-1 ")
        form.locator("input[name=samples]").fill("5")
        s.shots(page, "start-with-serial")
        form.locator("button.start").click()
        page.wait_for_url(re.compile(r"/ui/runs/\d+$"))
        run = s.run(int(urlsplit(page.url).path.rsplit("/", 1)[1]))
        assert run["serials"] == {"0": "SN-FORM-1"} and run["parameters"]["samples"] == 5, run

        page.goto("/ui/batches")
        assert page.locator("#nav-batches").count() == 1
        page.locator("#batch-station").select_option("dead-2")
        page.fill("#batch-serials", "B-1\n\n  B-2  \n")
        s.shots(page, "batch-form")
        page.click("#start-batch-button")
        page.wait_for_url(re.compile(r"/ui/batches/\d+$"))
        batch_id = int(urlsplit(page.url).path.rsplit("/", 1)[1])
        batch = s.api("GET", f"/batches/{batch_id}", "viewer").json()
        assert batch["station"] == "dead-2" and batch["serials"] == ["B-1", "B-2"], batch
        page.locator('#units tr[data-serial="B-2"]').wait_for()
        page.goto("/ui/batches")
        row = page.locator(f'table#batches tr[data-batch="{batch_id}"]')
        row.wait_for()
        assert "dead-2" in row.inner_text()
        s.shots(page, "batches")
        guard.check()


def test_example_script_reports_wall_time_left(tmp_path: Path, request: pytest.FixtureRequest):
    """examples/calibrate_unit.py says the time left as the run page does, in wall seconds (it said
    "~103 s left" of table time for a 6 s run); the progress events carry it, rounded, and 0 at the end."""
    import subprocess
    import sys

    from sqlalchemy import select

    from service.db import RunEvent

    with site(tmp_path, request, time_scale=40) as s:
        env = {**os.environ, "COMPASSCAL_URL": s.base, "COMPASSCAL_KEY": s.keys["operator"]}
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, str(ROOT / "examples" / "calibrate_unit.py"), "sim", SERIAL], env=env,
                           capture_output=True, text=True, timeout=120)
        wall = time.monotonic() - t0
        assert r.returncode == 0 and "completed" in r.stdout, r.stdout + r.stderr
        left = [float(x) for x in re.findall(r"~(\d+) s left", r.stdout)]
        assert len(left) >= 3 and left[-1] == 0, r.stdout
        # Table seconds would be 40 times the wall time. The margin is for an estimate, not a measurement:
        # on a busy machine a stalled step costs 40x its stall in table time, and the pace the estimate
        # extrapolates from jumps (a loaded CI run said 9 s of a 5.3 s run).
        assert max(left) <= 3 * wall + 2, f"the script said {max(left):.0f} s left of a run that took {wall:.1f} s"
        with s.app.state.sessions() as session:
            progress = list(session.scalars(select(RunEvent.data).where(RunEvent.kind == "progress").order_by(RunEvent.id)))
        assert progress and progress[-1]["left_s"] == 0 and progress[-1]["left_wall_s"] == 0, progress[-1]
        for p in progress:
            assert p["left_s"] == round(p["left_s"], 1) >= 0, p
            assert abs(p["left_wall_s"] - p["left_s"] / 40) <= 0.051, p


def test_the_run_page_says_what_the_procedure_computes():
    """A Compute step, and its progress, in the run page's status line (web.py and run.js say the same)."""
    from service.web import describe_step

    step = {"kind": "compute", "label": "discrepancy analysis of slot 0", "stage": "", "percent": None}
    assert describe_step({"step": step}) == "computing the discrepancy analysis of slot 0"
    assert describe_step({"step": {**step, "stage": "null simulations", "percent": 42.4}}) == \
        "computing the discrepancy analysis of slot 0: null simulations 42 %"
    js = (Path(__file__).resolve().parent.parent / "service" / "static" / "run.js").read_text()
    assert 'case "compute": return `computing the ${s.label || ""}`' in js
