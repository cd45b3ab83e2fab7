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

BASE = os.environ.get("COMPASSCAL_URL", "http://127.0.0.1:8000")
KEY = os.environ["COMPASSCAL_KEY"]


def call(method, path, body=None):
    req = urllib.request.Request(BASE + path, method=method, headers={"X-API-Key": KEY, "Content-Type": "application/json"},
                                 data=None if body is None else json.dumps(body).encode())
    try:
        with urllib.request.urlopen(req) as r:
            return json.loads(r.read())
    except urllib.error.HTTPError as e:
        sys.exit(f"{method} {path}: {e.code} {e.read().decode()}")


def follow(run_id):
    """Print progress from the run's server-sent events until it ends; returns the final state."""
    req = urllib.request.Request(f"{BASE}/runs/{run_id}/events", headers={"X-API-Key": KEY})
    state, kind = None, None
    with urllib.request.urlopen(req) as stream:
        for raw in stream:
            line = raw.decode().strip()
            if line.startswith("event:"):
                kind = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                data = json.loads(line.split(":", 1)[1])
                if kind == "progress":
                    print(f"\r{data['percent']:5.1f} %  ~{data['left_s']:.0f} s left", end="", flush=True)
                elif kind == "prompt":
                    print(f"\noperator: {data['text']}")
                    input("press Enter when done ")
                    call("POST", f"/runs/{run_id}/prompts/{data['id']}", {"answer": "done"})
                elif kind == "state":
                    state = data["state"]
    print()
    return state


station, serial = sys.argv[1], sys.argv[2]
run = call("POST", "/runs", {"station": station, "procedure": "calibrate", "serials": {"0": serial}})
print(f"run {run['id']} started on {station} for {serial}")
state = follow(run["id"])
print(f"run {run['id']}: {state}")
if state == "completed":
    cal = call("GET", f"/devices/{serial}/calibrations/current")
    print(f"verdict {cal['verdict']}; sensitivities {cal['magnetometer']['k']}; bias {cal['magnetometer']['bias']}")
for c in call("GET", f"/devices/{serial}/calibrations"):
    print(f"{c['created_at']}  {c['status']:<10} {c['verdict']:<8} run {c['run_id']}")
