"""Calibrate one unit through the compasscal REST API, follow its progress, fetch the result and the
unit's history. Standard library only, so it runs anywhere Python 3.9+ does.

    COMPASSCAL_URL=http://127.0.0.1:8000 COMPASSCAL_KEY=cc_... python calibrate_unit.py lab-1 SN-0001

The key needs the operator role (`compasscal keys create --owner you --role operator`).
"""

import json
import os
import sys
import urllib.error
import urllib.request

BASE = os.environ.get("COMPASSCAL_URL", "http://127.0.0.1:8000").rstrip("/")
KEY = os.environ.get("COMPASSCAL_KEY")


def fail(message):
    """One line on stderr and a non-zero exit: what went wrong and what to do."""
    sys.exit(f"calibrate_unit.py: {message}")


def open_url(req):
    """urlopen with the errors a technician meets (wrong URL, service down, wrong key) as one line."""
    try:
        return urllib.request.urlopen(req)
    except urllib.error.HTTPError as e:
        fail(f"{req.get_method()} {req.full_url}: {e.code} {e.read().decode(errors='replace')}")
    except urllib.error.URLError as e:
        fail(f"cannot reach the compasscal service at {BASE} ({e.reason}); check COMPASSCAL_URL and that the service runs")
    except ValueError as e:  # not a URL at all, e.g. no http://
        fail(f"COMPASSCAL_URL={BASE!r} is not a usable URL ({e}); e.g. http://127.0.0.1:8000")
    except OSError as e:  # the connection dropped or timed out
        fail(f"{req.full_url}: {e}")


def call(method, path, body=None):
    req = urllib.request.Request(BASE + path, method=method, headers={"X-API-Key": KEY, "Content-Type": "application/json"},
                                 data=None if body is None else json.dumps(body).encode())
    with open_url(req) as r:
        try:
            return json.loads(r.read())
        except ValueError:
            fail(f"{method} {BASE + path}: the answer is not JSON; is COMPASSCAL_URL a compasscal service?")


def wall_seconds_left(progress, time_scale):
    """The time left as the run page shows it, in wall-clock seconds: ``left_wall_s`` (``left_s`` is
    table time, which a simulated station runs time_scale times faster; an older service sends only that)."""
    left = progress.get("left_wall_s")
    return progress["left_s"] / time_scale if left is None else left


#: A prompt whose id starts so asks which serial number the unit is certified under (the unit reports
#: another than the one typed); it takes one of these answers.
SERIAL_PROMPT, SERIAL_ANSWERS = "serial-", ("typed", "identified", "skip")


def answer(run_id, prompt_id):
    """The operator's answer to a prompt, from the keyboard: one of SERIAL_ANSWERS to a serial prompt,
    Enter once done to any other. Without a keyboard (stdin closed) the run is aborted, not left waiting."""
    try:
        if not prompt_id.startswith(SERIAL_PROMPT):
            input("press Enter when done ")
            return "done"
        while True:
            text = input(f"answer {', '.join(SERIAL_ANSWERS)}: ").strip().lower()
            if text in SERIAL_ANSWERS:
                return text
    except EOFError:
        call("PUT", f"/runs/{run_id}/state", {"state": "aborted", "reason": "no operator to answer its prompt"})
        fail(f"run {run_id} asks the operator (prompt {prompt_id}) and there is no keyboard to answer: run aborted")


def follow(run_id):
    """Print progress from the run's server-sent events until it ends; returns the final state."""
    time_scale = float((call("GET", f"/runs/{run_id}").get("station_snapshot") or {}).get("time_scale") or 1.0)
    req = urllib.request.Request(f"{BASE}/runs/{run_id}/events", headers={"X-API-Key": KEY})
    state, kind = None, None
    with open_url(req) as stream:
        for raw in stream:
            line = raw.decode().strip()
            if line.startswith("event:"):
                kind = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                data = json.loads(line.split(":", 1)[1])
                if kind == "progress":
                    print(f"\r{data['percent']:5.1f} %  ~{wall_seconds_left(data, time_scale):.0f} s left", end="", flush=True)
                elif kind == "prompt" and not data.get("answered"):  # (an answered one comes back as said)
                    print(f"\noperator: {data['text']}")
                    call("POST", f"/runs/{run_id}/prompts/{data['id']}", {"answer": answer(run_id, data["id"])})
                elif kind == "state":
                    state = data["state"]
    print()
    return state


if len(sys.argv) != 3:
    fail("usage: calibrate_unit.py STATION SERIAL (with COMPASSCAL_URL and COMPASSCAL_KEY set)")
if not BASE.startswith(("http://", "https://")):
    fail(f"COMPASSCAL_URL={BASE!r} is not an http:// or https:// URL; e.g. http://127.0.0.1:8000")
if not KEY:
    fail("COMPASSCAL_KEY is not set: give an operator key (compasscal keys create --owner you --role operator)")
station, serial = sys.argv[1], sys.argv[2]
run = call("POST", "/runs", {"station": station, "procedure": "calibrate", "serials": {"0": serial}})
print(f"run {run['id']} started on {station} for {serial}")
state = follow(run["id"])
print(f"run {run['id']}: {state}")
if state != "completed":  # say why, as the run page does
    reason = call("GET", f"/runs/{run['id']}").get("reason")
    print(f"  reason: {reason or 'none given'}")
unit = ((call("GET", f"/runs/{run['id']}").get("result") or {}).get("units") or {}).get("0") or {}
if state == "completed" and "calibration_id" in unit:
    serial = unit.get("serial") or serial  # the serial it was certified under (the unit may report another)
    cal = call("GET", f"/calibrations/{unit['calibration_id']}")
    print(f"{serial}: verdict {cal['verdict']}; sensitivities {cal['magnetometer']['k']}; bias {cal['magnetometer']['bias']}")
elif state == "completed":
    print(f"no calibration: {unit.get('error', 'none stored')}")
for c in call("GET", f"/devices/{serial}/calibrations") if state == "completed" and "calibration_id" in unit else []:
    print(f"{c['created_at']}  {c['status']:<10} {c['verdict']:<8} run {c['run_id']}")
