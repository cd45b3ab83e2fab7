"""The command line end to end: simulate, fit, and the errors a user sees."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from physics.recording import parse_recording
from service.cli import app

runner = CliRunner()


def test_simulate_then_fit_writes_the_calibration_json(tmp_path: Path) -> None:
    rec = tmp_path / "rec.csv"
    r = runner.invoke(app, ["simulate", "--unit", "reference", "--seed", "2", "--samples", "15", "-o", str(rec)])
    assert r.exit_code == 0, r.output
    assert rec.read_text().startswith("# compasscal-recording: 1")
    cal_path, png = tmp_path / "cal.json", tmp_path / "fig.png"
    r = runner.invoke(app, ["fit", str(rec), "-o", str(cal_path), "--plot", str(png),
                            "--truth", str(tmp_path / "rec.truth.json")])
    assert r.exit_code == 0, r.output
    assert "Table 1" in r.output and "Table 2" in r.output and "against the true unit" in r.output
    cal = json.loads(cal_path.read_text())
    assert cal["format"] == "compasscal-calibration/1" and cal["method"] == "joint"
    assert abs(cal["magnetometer"]["angles_deg"][0][0] - 1.3020) < 0.02
    assert cal["quality"]["heading_error_deg"]["full"] < 0.05
    assert png.stat().st_size > 10_000


def test_fit_reports_malformed_rows_with_line_numbers(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("# compasscal-recording: 1\nt,step,psi_t,theta_t,phi_t,mx,my,mz\n0,a,0,0,0,1,2,3\n0.1,a,0,0,0,x,2,3\n")
    r = runner.invoke(app, ["fit", str(bad)])
    assert r.exit_code == 2
    assert "line 4" in r.output and "mx" in r.output


def test_fit_refuses_a_recording_without_tilt_sweeps(tmp_path: Path) -> None:
    rec = tmp_path / "rec.csv"
    runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)])
    lines = rec.read_text().splitlines()
    level = [ln for ln in lines if not ln.split(",")[1:2] or ln.split(",")[1] not in ("sweep_x", "sweep_y")]
    rec.write_text("\n".join(level) + "\n")
    r = runner.invoke(app, ["fit", str(rec), "--method", "error-separation"])
    assert r.exit_code == 2
    said = " ".join(r.output.split())  # rich wraps long lines
    assert "no sweep about the table's x axis" in said and "no sweep about the table's y axis" in said


def test_calibrate_against_a_sim_process_writes_recordings_and_calibrations(tmp_path: Path):
    """`compasscal sim` in its own process, `compasscal calibrate` against it over TCP and a pty."""
    import json
    import signal
    import subprocess
    import sys

    from conftest import free_port

    truth = tmp_path / "truth.json"
    control = free_port()  # a control port of one's choosing (a firewall's, a script's): it was always any free one
    sim = subprocess.Popen([sys.executable, "-m", "service.cli", "sim", "--seed", "3", "--time-scale", "20", "--truth", str(truth),
                            "--control-port", str(control)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parent.parent)
    try:
        d = json.loads(sim.stdout.readline())
        assert d["control"] == f"tcp://127.0.0.1:{control}", d
        out = tmp_path / "run"
        # no --time-scale: calibrate asks the simulator's control port; --adaptive: the plan extended as the unit needs
        r = runner.invoke(app, ["calibrate", "--modbus", d["modbus"], "--compass", d["compasses"][0]["url"],
                                "--control", d["control"], "-o", str(out), "--truth", str(truth), "--adaptive"])
        contradicted = runner.invoke(app, ["calibrate", "--modbus", d["modbus"], "--compass", d["compasses"][0]["url"],
                                           "--control", d["control"], "--time-scale", "1", "-o", str(out)])
        # no --control and no --time-scale against a simulator at 20: the run is said to be off by that factor
        unscaled = runner.invoke(app, ["calibrate", "--modbus", d["modbus"], "--compass", d["compasses"][0]["url"],
                                       "--samples", "5", "-o", str(tmp_path / "unscaled")])
    finally:
        sim.send_signal(signal.SIGINT)
        sim.communicate(timeout=10)
    assert r.exit_code == 0, r.output
    serial = d["compasses"][0]["serial"]
    said = " ".join(r.output.split())
    assert "run completed" in said and "Table 1" in said and "against the true unit" in said
    cal = json.loads((out / f"{serial}.cal.json").read_text())
    assert cal["format"] == "compasscal-calibration/1" and cal["serial"] == serial
    pr = cal["quality"]["precision"]
    assert pr["stopped"] in ("reached", "budget") and pr["met"] == (pr["stopped"] == "reached") and pr["table_s"] <= 180.0
    assert f"note: {' '.join(pr['why'].split())}" in said and said.count(' '.join(pr["why"].split())) == 1
    spent = f"{pr['table_s']:.0f} s of the 180-s budget (nominal)"
    assert f"adaptive: targets met after {spent}" in said if pr["met"] else \
        f"adaptive: targets not met: the budget ended after {spent}" in said
    assert (out / f"{serial}.csv").read_text().count("\n") > 18 * 60
    rec = parse_recording((out / f"{serial}.csv").read_text())
    # table time: the plan turns for minutes (at time scale 20 the run took seconds of wall time)
    assert np.ptp(rec.t) > 60, np.ptp(rec.t)
    assert contradicted.exit_code != 0 and "runs at time scale 20" in " ".join(contradicted.output.split())
    said = " ".join(unscaled.stderr.split())
    assert unscaled.exit_code == 0 and "times the plan's nominal" in said and "give --control" in said, unscaled.output
    assert (out / f"{serial}.png").stat().st_size > 10_000


def test_calibrate_names_an_unreachable_station(tmp_path: Path):
    r = runner.invoke(app, ["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)])
    assert r.exit_code == 2
    assert "station" in r.output and "127.0.0.1" in r.output


def test_demo_calibrates_and_checks_the_reference_unit(tmp_path: Path):
    r = runner.invoke(app, ["demo", "-o", str(tmp_path), "--time-scale", "40"])
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "evaluate on the table" in said and "against the true unit" in said
    # the demo's unit meets the accuracy target against the simulator's truth
    import re
    level, tilted = map(float, re.search(r"against the true unit: heading error max ([\d.]+) deg level, ([\d.]+) deg", said).groups())
    assert level <= 0.02 and tilted <= 0.05


def test_demo_api_calibrates_through_the_rest_service(tmp_path: Path, monkeypatch):
    import socket
    monkeypatch.setenv("COMPASSCAL_DATA_DIR", str(tmp_path))
    monkeypatch.delenv("COMPASSCAL_DATABASE_URL", raising=False)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = runner.invoke(app, ["demo", "--api", "--no-serve", "--port", str(port), "--time-scale", "40"])
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "POST /runs -> 202" in said and "run 1 completed" in said and "verdict" in said
    assert f"http://127.0.0.1:{port}/devices/GAO2017-REF/calibrations" in said
    assert (tmp_path / "compasscal.db").exists()  # the SQLite default under the user's data directory


def test_keys_create_prints_the_key_alone_on_the_last_line(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("COMPASSCAL_DATABASE_URL", f"sqlite:///{tmp_path / 'k.db'}")
    r = runner.invoke(app, ["keys", "create", "--owner", "alice", "--role", "operator"])
    assert r.exit_code == 0, r.output
    key = r.output.strip().splitlines()[-1]
    assert key.startswith("cc_") and " " not in key
    from service.auth import lookup
    from service.db import make_engine, sessions
    with sessions(make_engine(f"sqlite:///{tmp_path / 'k.db'}"))() as session:
        caller = lookup(session, key)
    assert caller is not None and caller.owner == "alice" and caller.role == "operator"
    bad = runner.invoke(app, ["keys", "create", "--owner", "bob", "--role", "boss"])
    assert bad.exit_code == 2 and "role" in bad.output


def test_keys_are_listed_and_revoked_from_the_command_line(tmp_path: Path, monkeypatch):
    """`keys list` shows each key's id, first characters, owner and role, never a secret; `keys
    revoke` takes an id or those characters, is audited, and the key stops working."""
    url = f"sqlite:///{tmp_path / 'k.db'}"
    monkeypatch.setenv("COMPASSCAL_DATABASE_URL", url)
    keys = [runner.invoke(app, ["keys", "create", "--owner", o, "--role", "viewer"]).output.strip().splitlines()[-1]
            for o in ("alice", "bob")]
    listed = runner.invoke(app, ["keys", "list"])
    assert listed.exit_code == 0 and "alice" in listed.output and "bob" in listed.output
    assert keys[0][:10] in listed.output and keys[0] not in listed.output  # the prefix, not the key
    r = runner.invoke(app, ["keys", "revoke", keys[1][:10]])
    assert r.exit_code == 0 and "revoked key 2" in r.output, r.output
    again = runner.invoke(app, ["keys", "revoke", "2"])
    assert again.exit_code == 2 and "already revoked" in again.stderr
    assert runner.invoke(app, ["keys", "revoke", "cc_nosuch"]).exit_code == 2
    # the last admin key may go here (this command is the way back in), said as such (the API refuses it)
    admin = runner.invoke(app, ["keys", "create", "--owner", "root", "--role", "admin"]).output.strip().splitlines()[-1]
    r = runner.invoke(app, ["keys", "revoke", admin[:10]])
    assert r.exit_code == 0 and "last admin key in force" in " ".join(r.stderr.split()), r.stderr
    from sqlalchemy import select

    from service.auth import lookup
    from service.db import AuditLog, make_engine, sessions
    with sessions(make_engine(url))() as session:
        assert lookup(session, keys[1]) is None and lookup(session, keys[0]) is not None
        log, _admin = session.scalars(select(AuditLog).where(AuditLog.action == "key.revoke").order_by(AuditLog.id)).all()
        assert log.target == "key 2" and log.owner.startswith("cli:")


def test_every_command_keeps_the_drivers_responsive():
    """The drivers answer on sub-second timeouts from threads that share the interpreter with fits: every
    command sets the short thread switch interval (benchmarks/drivers.py measures why) and keeps the
    objects it has made out of the full garbage collections (which stop every thread)."""
    import gc
    import sys

    from drivers import SWITCH_INTERVAL_S
    before = sys.getswitchinterval()
    sys.setswitchinterval(0.005)
    gc.unfreeze()
    try:
        assert runner.invoke(app, ["keys", "--help"]).exit_code == 0
        assert sys.getswitchinterval() == SWITCH_INTERVAL_S
        assert gc.get_freeze_count() > 100_000
    finally:
        sys.setswitchinterval(before)


def test_convert_writes_a_mapped_file_as_a_recording_the_service_takes(tmp_path: Path) -> None:
    """A logger file read through examples/mapping.toml comes out as RECORDING.md CSV with the same rows and
    the mapping's conversions in its metadata (what POST /recordings accepts)."""
    from service.imports import read_recording_file

    text = ("MyLogger v2, unit 17\n"
            "tms;Bx;By;Bz;Ax;Ay;Az;yaw;pitch;roll;T\n"
            "1000;12.5;-3.1;40.2;0.01;0.00;-1.00;10.0;0.0;0.0;24.8\n"
            "1020;12.0;-3.5;40.0;0.02;0.01;-0.99;12.5;1.0;-2.0;24.9\n")
    src, out = tmp_path / "logger.csv", tmp_path / "out.csv"
    src.write_text(text)
    mapping = Path(__file__).resolve().parent.parent / "examples" / "mapping.toml"
    r = runner.invoke(app, ["convert", str(src), "--mapping", str(mapping), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "2 samples, table angles, accelerometer, temperature" in " ".join(r.output.split())  # rich wraps lines
    got, want = parse_recording(out.read_text()), read_recording_file(src, mapping=mapping)
    assert np.allclose(got.mag, want.mag) and np.allclose(got.psi_t, want.psi_t) and np.allclose(got.t, want.t)
    assert got.serial == "SN-0017" and "file y, -x, z" in got.meta["mag_axes"]
    # a file no reader knows, without a mapping: one line naming the way out, exit 2
    r = runner.invoke(app, ["convert", str(src), "-o", str(out)])
    assert r.exit_code == 2 and "--mapping" in r.output


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_calibrate_stopped_by_a_signal_stops_the_axes_keeps_the_samples_and_says_so(tmp_path: Path, sig: str):
    """SIGTERM (a closed terminal, a service manager) killed `compasscal calibrate` with an axis still
    turning and nothing said; Ctrl-C stopped the axes but exited 130 without a word. Now either aborts the
    run as an operator would: the axes stopped, the samples so far written, what happened said, and the
    shell's exit code (128 + the signal)."""
    import signal
    import subprocess
    import sys
    import time

    from conftest import sim_station
    from drivers.sim.config import reference_config

    with sim_station(reference_config(seed=3, time_scale=10)) as info:
        out = tmp_path / "run"
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "calibrate", "--modbus", info["modbus"],
                                 "--compass", info["compasses"][0]["url"], "--time-scale", "10", "-o", str(out)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parent.parent,
                                env={**os.environ, "COLUMNS": "200"})
        table = info["station"].table
        deadline = time.monotonic() + 60
        while not any(ax.mode == "move" for ax in table.axes.values()) or not list(out.glob("*.csv")):
            assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
            time.sleep(0.01)  # moving on from a pose whose samples are written
        proc.send_signal(getattr(signal, sig))
        stdout, stderr = proc.communicate(timeout=30)
        time.sleep(0.3)
        assert proc.returncode == 128 + getattr(signal, sig).value, stdout + stderr
        assert all(ax.mode not in ("move", "jog") for ax in table.axes.values()), {n: ax.mode for n, ax in table.axes.items()}
    said = " ".join((stdout + stderr).split())
    assert f"run aborted: interrupted by {sig}" in said and f"interrupted by {sig}: the axes were stopped" in said, said
    [csv] = out.glob("*.csv")
    assert csv.name in said  # where they are
    assert len(parse_recording(csv.read_text())) >= 60
