"""The technician's example script, run as a technician would: against `make run`'s service."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_example_script_calibrates_a_unit_and_lists_its_history(tmp_path: Path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "COMPASSCAL_DATA_DIR": str(tmp_path), "COLUMNS": "200"}
    env.pop("COMPASSCAL_DATABASE_URL", None)
    demo = subprocess.Popen([sys.executable, "-m", "service.cli", "demo", "--api", "--serve", "--port", str(port),
                             "--time-scale", "40"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, key, deadline = "", None, time.monotonic() + 90
        while key is None and time.monotonic() < deadline:
            line = demo.stdout.readline()
            out += line
            m = re.search(r"operator key \(X-API-Key header\): (cc_\S+)", line)
            key = m.group(1) if m else None
        assert key, out
        r = subprocess.run([sys.executable, str(ROOT / "examples" / "calibrate_unit.py"), "demo", "GAO2017-REF"],
                           env={**env, "COMPASSCAL_URL": f"http://127.0.0.1:{port}", "COMPASSCAL_KEY": key},
                           capture_output=True, text=True, timeout=90)
        assert r.returncode == 0, r.stdout + r.stderr
        assert "completed" in r.stdout and "verdict" in r.stdout
        history = [line for line in r.stdout.splitlines() if " run " in line and ("current" in line or "superseded" in line)]
        assert len(history) == 2 and "current" in history[0] and "superseded" in history[1]  # the demo's and the script's
        # a serial typed that the unit does not report: the script asks which, until the answer is one the
        # service takes (it posted "done", which the service refused, and exited with the station held)
        r = subprocess.run([sys.executable, str(ROOT / "examples" / "calibrate_unit.py"), "demo", "OTHER-2"],
                           env={**env, "COMPASSCAL_URL": f"http://127.0.0.1:{port}", "COMPASSCAL_KEY": key},
                           input="done\nidentified\n", capture_output=True, text=True, timeout=90)
        assert r.returncode == 0, r.stdout + r.stderr
        assert "the serial number typed is OTHER-2 but the unit reports GAO2017-REF" in r.stdout
        assert r.stdout.count("answer typed, identified, skip:") == 2 and "completed" in r.stdout
        assert "GAO2017-REF: verdict" in r.stdout and len([x for x in r.stdout.splitlines() if " run " in x]) == 3
        # no keyboard: the run is aborted (not left holding the station) and the script says so
        r = subprocess.run([sys.executable, str(ROOT / "examples" / "calibrate_unit.py"), "demo", "OTHER-3"],
                           env={**env, "COMPASSCAL_URL": f"http://127.0.0.1:{port}", "COMPASSCAL_KEY": key},
                           stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=90)
        assert r.returncode == 1 and "there is no keyboard to answer: run aborted" in r.stderr, r.stdout + r.stderr
        assert "Traceback" not in r.stderr
    finally:
        demo.send_signal(signal.SIGINT)
        demo.wait(20)
