"""The right unit (issue 14, part 1): a unit that reports another serial number than the one typed
is never certified silently. The station's serial policy, or the request's, settles it: ``prompt``
(the default) asks the operator, ``refuse`` leaves the unit uncalibrated, ``trust-typed`` certifies
the typed serial and says so on the run page and the certificate (HTML and PDF). A batch that meets
one unit twice certifies it once; a unit that cannot identify itself is calibrated as before, marked
"not identified". Through the REST API against a simulated station (its compass reports the unit's
serial, "GAO2017-REF" unless the test mounts another)."""

from __future__ import annotations

import re
import time
from typing import Any

import numpy as np
import pytest

from conftest import Api, sim_station
from drivers.protocol import Nak, sentence
from drivers.sim.config import reference_config
from service import plots
from service.db import Calibration
from service.web import certificate_context
from test_service_runs import make_station, mount, wait_run

UNIT = "GAO2017-REF"  # what the simulated compass reports
PARAMS = {"samples": 20}


def wait_prompt(api: Api, run_id: int, timeout: float = 30.0) -> dict[str, Any]:
    """The run's first waiting prompt."""
    deadline = time.monotonic() + timeout
    while True:
        j = api.get(f"/runs/{run_id}", role="viewer").json()
        if j["prompts"]:
            return j["prompts"][0]
        assert j["status"] in ("queued", "running"), j
        assert time.monotonic() < deadline, f"run {run_id} asked nothing in {timeout} s"
        time.sleep(0.05)


def start(api: Api, **body: Any) -> int:
    r = api.post("/runs", role="operator", json={"station": "lab-1", "parameters": PARAMS, **body})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def certificate_texts(api: Api, cal_id: int) -> tuple[str, str]:
    """The HTML certificate, and the text of the PDF certificate's first page (the PDF is served too)."""
    html = api.get(f"/ui/calibrations/{cal_id}/certificate", role="viewer")
    assert html.status_code == 200
    pdf = api.get(f"/calibrations/{cal_id}/certificate.pdf", role="viewer")
    assert pdf.status_code == 200 and pdf.content.startswith(b"%PDF")
    with api.client.app.state.sessions() as s:
        cert, cal, rec, limits = certificate_context(s, s.get(Calibration, cal_id))
    page1 = plots.certificate_pages(cert, cal, rec, plots_limits(limits))[0]
    return html.text, "\n".join(t.get_text() for t in page1.texts)


def plots_limits(limits: list[Any]) -> dict[str, tuple[float, float]]:
    return {lim.name: (lim.marginal, lim.fail) for lim in limits}


def cannot_identify(info: dict[str, Any], slot: int = 0) -> None:
    """The slot's compass refuses the ID command, as a compass without it does (NAK unknown command)."""
    dev = info["station"].compasses[slot].device
    dev._id = lambda args, t: dev.emit(sentence("NAK", "ID", int(Nak.UNKNOWN_COMMAND))) or True


def test_prompt_policy_asks_the_operator_before_the_table_moves(api: Api):
    """The default policy: the run waits on a prompt showing both serials, with nothing measured; a
    stray answer is refused; "skip" ends the run uncalibrated, "identified" certifies the unit under
    the serial it reports."""
    with sim_station(reference_config(seed=21, time_scale=20)) as info:
        assert make_station(api, info)["serial_policy"] == "prompt"
        rid = start(api, serials={"0": "SN-TYPED"})
        prompt = wait_prompt(api, rid)
        assert prompt["id"] == "serial-0" and "SN-TYPED" in prompt["text"] and UNIT in prompt["text"], prompt
        run = api.get(f"/runs/{rid}", role="viewer").json()
        assert run["samples_count"] == 0 and run["serial_policy"] == "prompt"
        page = api.get(f"/ui/runs/{rid}", role="operator").text
        assert all(f'data-answer="{a}"' in page for a in ("typed", "identified", "skip"))
        r = api.post(f"/runs/{rid}/prompts/serial-0", role="operator", json={"answer": "done"})
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.answer", r.text
        r = api.post(f"/runs/{rid}/prompts/serial-0", role="operator", json={"answer": "skip"})
        assert r.status_code == 200, r.text
        skipped = wait_run(api, rid)
        assert skipped["status"] == "failed" and "skipped by the operator" in skipped["reason"], skipped
        assert skipped["samples_count"] == 0 and skipped["calibrations"] == []
        assert skipped["result"]["units"]["0"]["identified_serial"] == UNIT
        assert api.get("/devices/SN-TYPED", role="viewer").status_code == 404

        # aborted at the prompt: the run still says which unit was on the table, and that unit finds it
        rid = start(api, serials={"0": "SN-TYPED"})
        assert wait_prompt(api, rid)["id"] == "serial-0"
        api.put(f"/runs/{rid}/state", role="operator", json={"state": "aborted", "reason": "wrong label"})
        aborted = wait_run(api, rid)
        ident = aborted["result"]["identities"]["0"]
        assert aborted["status"] == "aborted" and ident["identified_serial"] == UNIT and ident["serial_decision"] == "asked"
        assert rid in [r["id"] for r in api.get(f"/runs?serial={UNIT}", role="viewer").json()]
        # and its page says it too (it showed the typed serial alone)
        assert f"the unit reports <strong>{UNIT}</strong>" in api.get(f"/ui/runs/{rid}", role="viewer").text

        rid = start(api, serials={"0": "SN-TYPED"})
        assert wait_prompt(api, rid)["id"] == "serial-0"
        assert api.post(f"/runs/{rid}/prompts/serial-0", role="operator", json={"answer": "Identified"}).status_code == 200
        done = wait_run(api, rid, timeout=90)
        assert done["status"] == "completed", done
        unit = done["result"]["units"]["0"]
        assert unit["serial"] == UNIT and unit["typed_serial"] == "SN-TYPED" and unit["identified_serial"] == UNIT
        assert unit["identification"] == "differs" and unit["serial_decision"] == "identified" and "calibration_id" in unit
        assert [c["serial"] for c in done["calibrations"]] == [UNIT]
        assert api.get(f"/devices/{UNIT}/calibrations/current", role="viewer").json()["run_id"] == rid
        assert api.get("/devices/SN-TYPED", role="viewer").status_code == 404
        page = api.get(f"/ui/runs/{rid}", role="viewer").text
        assert "the unit reports <strong>GAO2017-REF</strong>" in page and "SN-TYPED" in page
        # its exported samples go by the serial it was certified as, the rejected one beside it (they said
        # "serial: SN-TYPED", and a re-import would have filed them under it)
        header = [line for line in api.get(f"/runs/{rid}/samples?slot=0", role="viewer").text.splitlines() if line[:1] == "#"]
        assert f"# serial: {UNIT}" in header and "# typed_serial: SN-TYPED" in header, header


def test_refuse_policy_fails_the_slot_with_the_reason(api: Api):
    """A station set to refuse: the unit is not calibrated, the run says why; a change of the
    station's URLs keeps its policy."""
    with sim_station(reference_config(seed=22, time_scale=20)) as info:
        station = make_station(api, info)
        body = {"modbus": station["modbus"], "compasses": station["compasses"], "time_scale": 20}
        r = api.put("/stations/lab-1", json={**body, "serial_policy": "refuse"})
        assert r.status_code == 200 and r.json()["serial_policy"] == "refuse"
        assert api.put("/stations/lab-1", json=body).json()["serial_policy"] == "refuse"
        assert api.put("/stations/lab-1", json={**body, "serial_policy": "maybe"}).status_code == 422
        # typed as an operator types it (a prompt's answer takes any case too)
        assert api.put("/stations/lab-1", json={**body, "serial_policy": " Refuse "}).json()["serial_policy"] == "refuse"
        rid = start(api, serials={"0": "SN-WRONG"})
        j = wait_run(api, rid)
        assert j["status"] == "failed" and j["serial_policy"] == "refuse", j
        assert "refused" in j["reason"] and "SN-WRONG" in j["reason"] and UNIT in j["reason"], j["reason"]
        assert j["samples_count"] == 0 and j["calibrations"] == []
        unit = j["result"]["units"]["0"]
        assert unit["serial_decision"] == "refused" and "calibration_id" not in unit and "refused" in unit["error"]
        for serial in ("SN-WRONG", UNIT):
            assert api.get(f"/devices/{serial}", role="viewer").status_code == 404
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        page = api.get(f"/ui/runs/{rid}", role="viewer").text
        assert "refused" in page and UNIT in page
        # the slot goes by the unit it held, the serial typed beside it (it was headed "SN-WRONG")
        assert f"Slot 0: unit {UNIT} <small>(typed SN-WRONG)</small>" in page, page


def test_trust_typed_is_recorded_on_the_page_and_the_certificate(api: Api):
    """The request overrides the station's policy: the typed serial is certified, and the run's
    result, its page and the certificate (HTML and PDF) show the serial the unit reported."""
    with sim_station(reference_config(seed=23, time_scale=20)) as info:
        make_station(api, info)
        done = wait_run(api, start(api, serials={"0": "SN-TRUST"}, serial_policy="trust-typed"), timeout=90)
        assert done["status"] == "completed" and done["serial_policy"] == "trust-typed", done
        unit = done["result"]["units"]["0"]
        assert unit["serial"] == "SN-TRUST" and unit["identified_serial"] == UNIT and unit["serial_decision"] == "trust-typed"
        [cal] = done["calibrations"]
        assert cal["serial"] == "SN-TRUST" and cal["identity"]["identified_serial"] == UNIT
        # the calibration's own JSON and the unit's history say it too (only the run and the certificate did)
        stored = api.get(f"/calibrations/{cal['id']}", role="viewer").json()
        assert stored["identity"]["identified_serial"] == UNIT and stored["identity"]["serial_decision"] == "trust-typed"
        [line] = api.get("/devices/SN-TRUST/calibrations", role="viewer").json()
        assert line["identity"]["typed_serial"] == "SN-TRUST" and line["identity"]["identified_serial"] == UNIT, line
        page = api.get(f"/ui/runs/{done['id']}", role="viewer").text
        assert "the unit reports <strong>GAO2017-REF</strong>" in page and "serial policy trust-typed" in page
        html, pdf = certificate_texts(api, cal["id"])
        for text in (html, pdf):
            assert "Serial typed" in text and "SN-TRUST" in text and "Identified serial" in text and UNIT in text
            assert "certified as typed (serial policy trust-typed)" in text


def test_a_run_certified_under_the_typed_serial_resumes_with_the_same_unit_and_policy(api: Api):
    """A trust-typed run (typed SN-TRUST, the unit reports GAO2017-REF) aborted mid-way resumes with the
    same unit mounted: the resumed run looks for the unit as it reported itself (it failed: "slot 0 holds
    GAO2017-REF, not SN-TRUST") and goes on under the run's own policy (it took the station's prompt)."""
    with sim_station(reference_config(seed=29, time_scale=20)) as info:
        make_station(api, info)
        first, deadline = start(api, serials={"0": "SN-TRUST"}, serial_policy="trust-typed"), time.monotonic() + 60
        while api.get(f"/runs/{first}", role="viewer").json()["samples_count"] < 5 * 20:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        api.put(f"/runs/{first}/state", role="operator", json={"state": "aborted", "reason": "power cut (test)"})
        assert wait_run(api, first)["status"] == "aborted"
        r = api.post("/runs", role="operator", json={"station": "lab-1", "resume": first})
        assert r.status_code == 202, r.text
        done = wait_run(api, r.json()["id"], timeout=90)
        assert done["status"] == "completed" and done["serial_policy"] == "trust-typed", done
        unit = done["result"]["units"]["0"]
        assert unit["serial"] == "SN-TRUST" and unit["identified_serial"] == UNIT and unit["serial_decision"] == "trust-typed"


def test_a_batch_certifies_one_unit_once(api: Api):
    """Three serials typed, one unit mounted three times (the issue's batch): the first is certified
    (trusted, as asked), the other two are the same unit again: said so, not certified."""
    with sim_station(reference_config(seed=24, time_scale=20)) as info:
        make_station(api, info)
        b, asked = run_batch(api, info, ["SN-1", "SN-2", "SN-3"], dict.fromkeys(["SN-1", "SN-2", "SN-3"], UNIT), {},
                             serial_policy="trust-typed")
        bid = b["id"]
        assert not asked  # (trust-typed: no serial prompt)
        assert b["summary"]["SN-1"] in ("PASS", "MARGINAL"), b["summary"]
        for serial in ("SN-2", "SN-3"):
            said = b["summary"][serial]
            assert said.startswith("failed") and "same physical unit mounted again" in said and "SN-1" in said, said
            assert api.get(f"/devices/{serial}", role="viewer").status_code == 404
        units = {u["serial"]: u for u in b["units"]}
        assert units["SN-1"]["calibration_id"] and units["SN-2"]["calibration_id"] is None
        dup = api.get(f"/runs/{units['SN-2']['run_id']}", role="viewer").json()
        assert dup["samples_count"] == 0 and dup["result"]["units"]["0"]["identification"] == "duplicate"
        # the batch says what each mounted unit reported, in its JSON and on its page
        assert units["SN-1"]["identified_serial"] == UNIT and units["SN-1"]["identification"] == "differs"
        assert units["SN-2"]["identified_serial"] == UNIT and units["SN-2"]["identification"] == "duplicate"
        page = api.get(f"/ui/batches/{bid}", role="viewer").text
        assert f'<td class="identified identification-duplicate">{UNIT} (duplicate)</td>' in page, page


@pytest.mark.parametrize("how", ["empty serial", "no ID command"])
def test_a_unit_that_cannot_identify_itself_is_calibrated_as_typed(api: Api, how: str):
    """A compass that reports an empty serial, or refuses the ID command: the run goes on as before
    with the typed serial (no prompt, no fault), and the result and the certificate say "not identified"."""
    with sim_station(reference_config(seed=25, time_scale=20)) as info:
        make_station(api, info)
        if how == "empty serial":
            mount(info, "")
        else:
            cannot_identify(info)
        done = wait_run(api, start(api, serials={"0": "SN-ANON"}), timeout=90)
        assert done["status"] == "completed", done
        unit = done["result"]["units"]["0"]
        assert unit["serial"] == "SN-ANON" and unit["identified_serial"] is None and unit["identification"] == "not identified"
        assert unit["verdict"] in ("PASS", "MARGINAL")
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        [cal] = done["calibrations"]
        assert cal["serial"] == "SN-ANON"
        html, pdf = certificate_texts(api, cal["id"])
        for text in (html, pdf):
            assert "Identified serial" in text and "not identified" in text
        assert "(not identified)" in api.get(f"/ui/runs/{done['id']}", role="viewer").text


def test_a_body_that_is_not_json_is_named_as_the_body(api: Api):
    r = api.post("/runs", role="operator", content=b'{"station": "lab-1",', headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    [err] = r.json()["detail"]
    assert err["field"] == "body" and err["problem"].startswith("not valid JSON at character"), err
    # bytes that are no UTF-8 text, and a body nested beyond the parser: 422 naming the body (a bare 400
    # "There was an error parsing the body", documented nowhere)
    for body, words in ((b'\xff\xfe{', "not UTF-8 text"), (b"[" * 100_000, "nested too deeply")):
        r = api.post("/runs", role="operator", content=body, headers={"Content-Type": "application/json"})
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body" and words in r.text, r.text


def test_one_serial_typed_for_two_slots_is_refused(api: Api):
    """Two slots typed with one serial number would certify two units under it (the second superseding
    the first): refused at the door, naming the field and the serial, as a batch's list is."""
    for serials in ({"0": "SAME-1", "1": "SAME-1"}, {"0": "SAME-1", "1": " SAME-1 "}):
        r = api.post("/runs", role="operator", json={"station": "lab-1", "serials": serials})
        assert r.status_code == 422, r.text
        [err] = r.json()["detail"]
        assert err["field"] == "body.serials" and "listed twice: SAME-1" in err["problem"], err
    r = api.post("/batches", role="operator", json={"station": "lab-1", "serials": ["SAME-1", "SAME-1"]})
    assert r.status_code == 422 and "listed twice: SAME-1" in r.text
    # in another letter case: most likely one unit typed twice (two devices, two certificates before)
    r = api.post("/batches", role="operator", json={"station": "lab-1", "serials": ["SN-1", "sn-1", "SN-2"]})
    assert r.status_code == 422 and "differ only in letter case: SN-1 and sn-1" in r.text, r.text
    # a serial looked up in another letter case is pointed at the one stored
    from service.db import Device

    with api.client.app.state.sessions() as s:
        s.add(Device(serial="SN-QE-1"))
        s.commit()
    r = api.get("/devices/sn-qe-1", role="viewer")
    assert r.status_code == 404 and "did you mean 'SN-QE-1'" in r.text, r.text


def test_a_unit_with_no_serial_at_all_is_refused_before_the_table_moves(api: Api):
    """A unit that reports no serial number, with none typed, has nothing to be certified under: the
    run fails before the table's first step, saying to type its serial, instead of running the plan."""
    with sim_station(reference_config(seed=26, time_scale=20)) as info:
        make_station(api, info)
        mount(info, "")
        j = wait_run(api, start(api), timeout=60)
        assert j["status"] == "failed", j
        assert "did not report a serial number and none was typed" in j["reason"] and '"serials"' in j["reason"], j
        assert j["samples_count"] == 0 and j["calibrations"] == []
        assert j["result"]["units"]["0"]["identification"] == "not identified"
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"


def test_a_unit_reporting_what_is_no_serial_number_is_treated_as_not_identified(api: Api):
    """A compass whose ID answer is no serial number the station can store (a '/' that no URL
    /devices/{serial} reads back, or a garbled answer) is not certified under it: with none typed the run
    fails before the table moves, naming what it reported and the rule; with one typed, the unit is
    calibrated as typed and marked "not identified", the note saying why."""
    with sim_station(reference_config(seed=27, time_scale=20)) as info:
        make_station(api, info)
        mount(info, "UNIT/7")
        j = wait_run(api, start(api), timeout=60)
        assert j["status"] == "failed", j
        assert "'UNIT/7'" in j["reason"] and "not a serial number" in j["reason"] and '"serials"' in j["reason"], j
        assert j["samples_count"] == 0 and j["calibrations"] == []
        done = wait_run(api, start(api, serials={"0": "SN-TYPED"}), timeout=90)
        assert done["status"] == "completed", done
        unit = done["result"]["units"]["0"]
        assert unit["serial"] == "SN-TYPED" and unit["identification"] == "not identified", unit
        assert unit["identified_serial"] == "UNIT/7" and "certified as the typed SN-TYPED" in unit["serial_note"], unit
        assert [c["serial"] for c in done["calibrations"]] == ["SN-TYPED"]
        assert api.get("/devices/UNIT%2F7", role="viewer").status_code in (404, 422)


def test_one_serial_is_never_certified_twice_in_a_run(api: Api):
    """Slot 0 typed (and trusted) as the serial the unit in slot 1 reports: once both were certified under it,
    the second superseding the first while the run's result called both current; then slot 0 was certified
    under it and slot 1's unit, the real one, left out as a duplicate. Slot 0 is refused now, naming the slot
    whose unit that serial is, and slot 1's unit is certified as itself, once."""
    from test_engine import two_units

    with sim_station(two_units()) as info:
        make_station(api, info)
        done = wait_run(api, start(api, serials={"0": "SN-RANDOM"}, serial_policy="trust-typed"), timeout=120)
        assert done["status"] == "completed", done
        units = done["result"]["units"]
        assert units["0"]["identified_serial"] == UNIT and units["0"]["serial_decision"] == "refused", units["0"]
        assert "unit SN-RANDOM is the one in slot 1 (it reports SN-RANDOM)" in units["0"]["serial_note"], units["0"]
        assert units["1"]["identification"] == "identified" and units["1"]["serial"] == "SN-RANDOM", units["1"]
        assert [(c["serial"], c["status"]) for c in done["calibrations"]] == [("SN-RANDOM", "current")]


def start_batch(api: Api, serials: list[str], **body: Any) -> int:
    """A batch of ``serials`` on lab-1 started (its id)."""
    r = api.post("/batches", role="operator", json={"station": "lab-1", "serials": serials, "parameters": PARAMS, **body})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def run_batch(api: Api, info: dict[str, Any], serials: list[str], on_mount: dict[str, str], answers: dict[str, str],
              **body: Any) -> tuple[dict[str, Any], list[str]]:
    """A batch to its end: at each unit's mount prompt the unit ``on_mount[serial]`` (by the typed serial)
    is mounted, each serial prompt is answered from ``answers`` (by the typed serial). Returns the batch
    and the serial prompts' texts."""
    bid, deadline, asked = start_batch(api, serials, **body), time.monotonic() + 150, []
    while (b := api.get(f"/batches/{bid}", role="viewer").json())["status"] == "running":
        assert time.monotonic() < deadline, b
        if b["prompt"]:
            run = api.get(f"/runs/{b['prompt']['run_id']}", role="viewer").json()
            typed = run["parameters"]["serial"]
            if b["prompt"]["id"] == "mount":
                mount(info, on_mount[typed])
                answer = "done"
            else:
                asked.append(b["prompt"]["text"])
                answer = answers[typed]
            api.post(f"/runs/{run['id']}/prompts/{b['prompt']['id']}", role="operator", json={"answer": answer})
        time.sleep(0.05)
    return b, asked


def test_a_batch_never_certifies_two_units_under_one_serial(api: Api):
    """The first unit of a batch reports SN-T and is certified as SN-T; the second, another unit
    (reporting SN-U) typed as SN-T, is not certified as SN-T on a 'typed' answer: the prompt says SN-T is
    already taken, and the summary says why (before, the second unit's calibration superseded the first
    unit's, which left the line with none)."""
    with sim_station(reference_config(seed=25, time_scale=20)) as info:
        make_station(api, info)
        b, asked = run_batch(api, info, ["SN-S", "SN-T"], {"SN-S": "SN-T", "SN-T": "SN-U"},
                             {"SN-S": "identified", "SN-T": "typed"})
        assert b["status"] == "completed", b
        assert "already certified" not in asked[0] and "SN-T is already certified for the unit of run" in asked[1], asked
        said = b["summary"]["SN-T"]
        assert said.startswith("failed") and "two units would be certified under one serial number" in said, said
        # the first line says what its unit was certified as; the second unit's mount prompt what to take out
        assert b["summary"]["SN-S"].endswith("(certified as SN-T)"), b["summary"]
        second = api.get(f"/runs/{[u for u in b['units'] if u['serial'] == 'SN-T'][0]['run_id']}/events", role="viewer").text
        assert "unmount unit SN-S (it reports SN-T)" in second, second[:2000]
        # a unit's runs by any of its serial numbers: typed, reported, certified under
        runs = {u["serial"]: u["run_id"] for u in b["units"]}
        listed = lambda serial: sorted(r["id"] for r in api.get(f"/runs?serial={serial}", role="viewer").json())  # noqa: E731
        assert listed("SN-T") == sorted(runs.values()) and listed("SN-S") == [runs["SN-S"]] and listed("SN-U") == [runs["SN-T"]]
        # a serial no unit was certified under, but a unit reported: its page (which run pages link to; it
        # was a 404) lists the runs that named it, and says it was never certified
        page = api.get("/ui/devices/SN-U", role="viewer")
        assert page.status_code == 200 and 'id="uncertified"' in page.text, page.text
        assert f'href="/ui/runs/{runs["SN-T"]}"' in page.text and "no calibrations" in page.text
        # a certified unit's page lists its runs too (the one that certified it and the one refused under it)
        page = api.get("/ui/devices/SN-T", role="viewer").text
        assert all(f'<tr data-run="{i}"' in page for i in runs.values()), page
        cals = api.get("/devices/SN-T/calibrations", role="viewer").json()
        assert [c["status"] for c in cals] == ["current"], cals  # the first unit's, still current
        units = {u["serial"]: u for u in b["units"]}
        assert cals[0]["id"] == units["SN-S"]["calibration_id"] and units["SN-T"]["calibration_id"] is None


def test_a_unit_that_failed_may_be_retested_in_its_batch(api: Api):
    """A unit whose calibration was rejected (FAIL) is not certified: mounted again in the same batch, it
    is measured again, not refused as "already certified" (the batch counted rejected calibrations)."""
    with sim_station(reference_config(seed=26, time_scale=20)) as info:
        make_station(api, info)
        r = api.put("/limits/residual_rms_lsb", role="admin", json={"marginal": 0.1, "fail": 0.2})  # every unit fails
        assert r.status_code == 200, r.text
        b, _ = run_batch(api, info, ["SN-1", "SN-2"], {"SN-1": UNIT, "SN-2": UNIT}, {}, serial_policy="trust-typed")
        assert b["status"] == "completed", b  # it calibrated its units (and judged them)
        assert b["summary"] == {"SN-1": "FAIL", "SN-2": "FAIL"}, b["summary"]
        assert b["tally"] == {"pass": 0, "marginal": 0, "fail": 2, "uncalibrated": 0, "pending": 0}, b["tally"]
        units = {u["serial"]: u for u in b["units"]}
        assert units["SN-2"]["identification"] == "differs" and units["SN-2"]["calibration_id"], units["SN-2"]


def test_a_unit_never_mounted_is_not_to_be_unmounted(api: Api):
    """A batch unit's run aborted at its mount prompt (the operator skips that unit): the next prompt says
    only to mount the next unit (it said "unmount unit SN-1 (aborted: ...), then mount ...", a unit no
    one had put on the table)."""
    with sim_station(reference_config(seed=30, time_scale=20)) as info:
        make_station(api, info)
        bid, deadline = start_batch(api, ["SN-1", "SN-2"], serial_policy="trust-typed"), time.monotonic() + 60
        while not (b := api.get(f"/batches/{bid}", role="viewer").json())["prompt"]:
            assert time.monotonic() < deadline, b
            time.sleep(0.05)
        first = b["prompt"]["run_id"]
        r = api.put(f"/runs/{first}/state", role="operator", json={"state": "aborted", "reason": "unit missing"})
        assert r.status_code == 202, r.text
        while not (b := api.get(f"/batches/{bid}", role="viewer").json())["prompt"] or b["prompt"]["run_id"] == first:
            assert time.monotonic() < deadline, b
            time.sleep(0.05)
        assert b["prompt"]["text"] == "mount unit SN-2 in slot 0", b["prompt"]
        assert b["summary"]["SN-1"] == "aborted: unit missing", b["summary"]
        api.put(f"/batches/{bid}/state", role="operator", json={"state": "aborted"})
        while api.get(f"/batches/{bid}", role="viewer").json()["status"] in ("running", "aborting"):
            assert time.monotonic() < deadline
            time.sleep(0.05)


def test_a_batch_that_calibrated_none_of_its_units_ends_failed(api: Api):
    """Every unit refused (each reports another serial, the policy refuses): the batch went through its
    units but calibrated none, which says more about the station than the units, so it ends ``failed``,
    its tally and page counting them (it ended "completed", only its summary said otherwise)."""
    with sim_station(reference_config(seed=28, time_scale=20)) as info:
        make_station(api, info)
        b, _ = run_batch(api, info, ["SN-1", "SN-2"], {"SN-1": UNIT, "SN-2": UNIT}, {}, serial_policy="refuse")
        assert b["status"] == "failed", b
        assert all(line.startswith("failed: ") and "refused" in line for line in b["summary"].values()), b["summary"]
        assert b["tally"] == {"pass": 0, "marginal": 0, "fail": 0, "uncalibrated": 2, "pending": 0}, b["tally"]
        page = api.get(f"/ui/batches/{b['id']}", role="viewer").text
        assert re.search(r'<span id="batch-tally">\s*2 uncalibrated</span>', page), page


def test_a_batch_is_aborted_as_a_whole(api: Api):
    """PUT /batches/{id}/state aborts the unit being calibrated (axes stopped, its samples kept) and
    starts no further unit; the summary says which were not run (aborting the run alone moved the batch
    on to the next unit's mount prompt: a 20-unit batch took 20 aborts)."""
    with sim_station(reference_config(seed=27, time_scale=20)) as info:
        make_station(api, info)
        bid, deadline = start_batch(api, ["SN-1", "SN-2", "SN-3"], serial_policy="trust-typed"), time.monotonic() + 60
        while not (b := api.get(f"/batches/{bid}", role="viewer").json())["prompt"]:
            assert time.monotonic() < deadline, b
            time.sleep(0.05)
        run_id = b["prompt"]["run_id"]
        api.post(f"/runs/{run_id}/prompts/mount", role="operator", json={"answer": "done"})
        while api.get(f"/runs/{run_id}", role="viewer").json()["samples_count"] < 40:  # on the table now
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert api.put(f"/batches/{bid}/state", role="viewer", json={"state": "aborted"}).status_code == 403
        bad = api.put(f"/batches/{bid}/state", role="operator", json={"state": "paused"})
        assert bad.status_code == 422 and bad.json()["detail"][0]["field"] == "body.state", bad.text
        r = api.put(f"/batches/{bid}/state", role="operator", json={"state": "aborted", "reason": "line stopped"})
        assert r.status_code == 202 and r.json()["status"] in ("aborting", "aborted"), r.text
        while (b := api.get(f"/batches/{bid}", role="viewer").json())["status"] == "aborting":
            assert time.monotonic() < deadline, b
            time.sleep(0.05)
        assert b["status"] == "aborted", b
        assert b["summary"]["SN-1"] == "aborted: line stopped", b["summary"]
        assert b["summary"]["SN-2"] == b["summary"]["SN-3"] == "not run: the batch was aborted", b["summary"]
        assert b["tally"]["uncalibrated"] == 3 and b["tally"]["pending"] == 0, b["tally"]  # the batch has ended
        run = api.get(f"/runs/{run_id}", role="viewer").json()
        assert run["status"] == "aborted" and run["samples_count"] >= 40  # the samples so far are kept
        assert [u["serial"] for u in b["units"] if u["run_id"]] == ["SN-1"]  # no run made for the others
        # the aborted unit keeps what it reported (its identification was lost with the result)
        first = b["units"][0]
        assert first["identified_serial"] == UNIT and first["identification"] == "differs", first
        assert api.get("/stations/lab-1", role="viewer").json()["state"] == "idle"
        assert api.put(f"/batches/{bid}/state", role="operator", json={"state": "aborted"}).status_code == 409
        # aborted during its last unit (here its only one, at the mount prompt): aborted too, not "failed"
        # for having calibrated none
        first_bid, bid = bid, start_batch(api, ["SN-4"], serial_policy="trust-typed")
        while not api.get(f"/batches/{bid}", role="viewer").json()["prompt"]:
            assert time.monotonic() < deadline + 60
            time.sleep(0.05)
        assert api.put(f"/batches/{bid}/state", role="operator", json={"state": "aborted"}).status_code == 202
        while (b := api.get(f"/batches/{bid}", role="viewer").json())["status"] in ("running", "aborting"):
            assert time.monotonic() < deadline + 60, b
            time.sleep(0.05)
        assert b["status"] == "aborted" and b["summary"]["SN-4"].startswith("aborted"), b
        assert api.put("/batches/999/state", role="operator", json={"state": "aborted"}).status_code == 404
        assert [x["id"] for x in api.get("/batches?status=aborted", role="viewer").json()] == [bid, first_bid]


def test_one_unit_keeps_one_serial_number_whatever_is_typed(api: Api):
    """A serial typed in another letter case made a second device beside the unit's own; trust-typed filed
    another unit under a serial whose unit reports its own, superseding its current calibration without a
    word. Now a serial typed in another case than the unit reports is the one it reports; typed in another
    case than a stored unit's it is refused by its field; and trust-typed refuses a typed serial whose unit
    is known to report it itself."""
    with sim_station(reference_config(seed=24, time_scale=20)) as info:
        make_station(api, info)
        done = wait_run(api, start(api, serials={"0": UNIT.lower()}), timeout=90)
        unit = done["result"]["units"]["0"]
        assert done["status"] == "completed" and unit["serial"] == UNIT and unit["identification"] == "identified", done
        assert api.get(f"/devices/{UNIT.lower()}", role="viewer").status_code == 404
        current = api.get(f"/devices/{UNIT}/calibrations/current", role="viewer").json()
        assert current["run_id"] == done["id"], current
        for path, body, field in (("/runs", {"station": "lab-1", "serials": {"0": UNIT.title()}}, "body.serials.0"),
                                  ("/batches", {"station": "lab-1", "serials": ["SN-NEW", UNIT.lower()]}, "body.serials.1")):
            r = api.post(path, role="operator", json=body)
            assert r.status_code == 422 and r.json()["detail"][0]["field"] == field and "letter case" in r.text, r.text
        # trust-typed, typed as that unit while another unit, reporting its own serial, is on the fixture
        mount(info, "SN-B9")
        refused = wait_run(api, start(api, serials={"0": UNIT}, serial_policy="trust-typed"), timeout=90)
        assert refused["status"] == "failed" and f"unit {UNIT} reports its own serial" in refused["reason"], refused
        assert "the unit on the fixture is not" in refused["reason"], refused
        assert api.get(f"/devices/{UNIT}/calibrations/current", role="viewer").json()["id"] == current["id"]
        # a unit whose typed serial was never its own (a shared factory default) is still trusted
        done = wait_run(api, start(api, serials={"0": "SN-C1"}, serial_policy="trust-typed"), timeout=90)
        assert done["status"] == "completed" and done["result"]["units"]["0"]["serial"] == "SN-C1", done
        # another unit's calibration evaluated on this one: refused when typed so, said when the unit reports so
        other = api.get(f"/devices/{UNIT}/calibrations/current", role="viewer").json()
        evaluate = {"station": "lab-1", "procedure": "evaluate", "parameters": {
            "calibrations": {"0": other}, "samples": 5, "tilted_samples": 5, "max_tilt_deg": 0}}
        r = api.post("/runs", role="operator", json={**evaluate, "serials": {"0": "SN-B9"}})
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.parameters.calibrations.0", r.text
        assert f"a calibration of unit {UNIT}" in r.text, r.text
        j = wait_run(api, api.post("/runs", role="operator", json=evaluate).json()["id"], timeout=90)
        unit = j["result"]["units"]["0"]
        assert j["status"] == "completed" and unit["serial"] == "SN-B9", j
        assert f"the calibration evaluated is of unit {UNIT}, but the unit in slot 0 is SN-B9" in unit["warning"], unit
        # its page shows the evaluation (it said "no calibration from this slot")
        page = " ".join(api.get(f"/ui/runs/{j['id']}", role="viewer").text.split())
        assert f"evaluated with the calibration of {UNIT}" in page and "heading error, level: max" in page, page[-3000:]
        assert "no calibration from this slot" not in page and "but the unit in slot 0 is SN-B9" in page


def test_what_a_unit_reported_that_is_no_serial_number_is_kept_findable_and_uploads_again(api: Api):
    """A unit whose answer is no serial number ("SN B/1") was exported as "# serial: SN B/1", and that file
    was refused on upload ("character '/' ... is not allowed"); nor could its runs be looked up by what it
    reported (422). The export says it as ``reported_serial``, the file uploads, and the search finds it."""
    from physics.simulate import World, simulate_recording
    from physics.sensor import reference_unit
    from procedures.calibrate import CalibrateParams, calibration_poses
    from service.db import Run
    from service.store import insert_samples

    rec = simulate_recording(reference_unit(3.0, 4.0), calibration_poses(CalibrateParams(samples=3)), World(),
                             rng=np.random.default_rng(2))
    with api.client.app.state.sessions() as s:
        run = Run(procedure="calibrate", procedure_version="2", parameters={}, status="completed", operator="t",
                  software_version="t", meta={"result": {"units": {"0": {"serial": "SN B/1", "identified_serial": "SN B/1",
                                                                         "error": "not a serial number"}}}})
        s.add(run)
        s.flush()
        insert_samples(s, run.id, 0, rec)
        s.commit()
        rid = run.id
    text = api.get(f"/runs/{rid}/samples?slot=0", role="viewer").text
    header = [line for line in text.splitlines() if line.startswith("#")]
    assert "# reported_serial: SN B/1" in header and not any(h.startswith("# serial:") for h in header), header
    r = api.post("/recordings", role="operator", content=text.encode(), headers={"content-type": "text/csv"})
    assert r.status_code == 201, r.text
    found = api.get("/runs", role="viewer", params={"serial": "SN B/1"})
    assert found.status_code == 200 and rid in [j["id"] for j in found.json()], found.text
    assert api.get("/runs", role="viewer", params={"serial": "A\x00B"}).status_code == 422


def test_a_refused_units_samples_go_by_the_serial_it_reported(api: Api):
    """A unit refused (or skipped, or left at its prompt) on a fixture whose other units ran: its samples were
    exported under the typed serial just ruled out, and their analysis took that serial's calibration (another
    unit's) and named a "parameter shift". They now go by the serial the unit reported, the typed one beside it."""
    from physics.simulate import World, simulate_recording
    from physics.sensor import reference_unit
    from procedures.calibrate import CalibrateParams, calibration_poses
    from service.db import Run
    from service.runtime import unit_serial
    from service.store import insert_samples

    rec = simulate_recording(reference_unit(3.0, 4.0), calibration_poses(CalibrateParams(samples=3)), World(),
                             rng=np.random.default_rng(3))
    with api.client.app.state.sessions() as s:
        ids = []
        for decision in ("refused", "skip", "asked"):
            entry = {"serial": "SN-WRONG", "typed_serial": "SN-WRONG", "identified_serial": UNIT, "identification": "differs",
                     "serial_decision": decision}
            run = Run(procedure="calibrate", procedure_version="2", parameters={}, status="completed", operator="t",
                      software_version="t", serials={"0": "SN-WRONG"}, meta={"result": {"units": {"0": entry}}})
            s.add(run)
            s.flush()
            assert unit_serial(run, 0) == UNIT, decision
            insert_samples(s, run.id, 0, rec)
            ids.append(run.id)
        s.commit()
    header = [line for line in api.get(f"/runs/{ids[0]}/samples?slot=0", role="viewer").text.splitlines() if line[:1] == "#"]
    assert f"# serial: {UNIT}" in header and "# typed_serial: SN-WRONG" in header, header
