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
    finally:
        demo.send_signal(signal.SIGINT)
        demo.wait(20)
