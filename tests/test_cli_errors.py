"""The command line's answers to common mistakes: one clear line on stderr naming the option or setting
and the problem, exit code 2, no traceback, and nothing long started before the check (issue 15)."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

import service.cli as cli
from conftest import free_port
from service.cli import app

ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()


def refused(args: list[str], *words: str) -> str:
    """Invoke; expect exit 2 and exactly one line on stderr containing ``words``; return that line."""
    r = runner.invoke(app, args)
    assert r.exit_code == 2, (r.exit_code, r.output, r.exception)
    assert "Traceback" not in r.output
    line = r.stderr.strip()
    assert line.startswith("error: ") and "\n" not in line, r.stderr
    for w in words:
        assert w in line, (w, line)
    return line


@pytest.fixture
def busy_port() -> Iterator[int]:
    """A port something is listening on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        yield s.getsockname()[1]


@pytest.fixture
def data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The SQLite default in a fresh directory (no COMPASSCAL_DATABASE_URL)."""
    monkeypatch.setenv("COMPASSCAL_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("COMPASSCAL_DATABASE_URL", raising=False)
    return tmp_path / "data"


@pytest.fixture
def nothing_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    """A command that should refuse must not start a server (which would serve until interrupted)."""
    import uvicorn

    import drivers.sim.station

    def started(*a: object, **k: object) -> None:
        raise AssertionError("a server was started instead of refusing")

    monkeypatch.setattr(uvicorn, "run", started)
    monkeypatch.setattr(uvicorn.Server, "run", started)
    monkeypatch.setattr(drivers.sim.station, "SimStation", started)


# -- calibrate --------------------------------------------------------------------------------------

def test_calibrate_refuses_an_unsupported_modbus_scheme_before_connecting(tmp_path: Path):
    refused(["calibrate", "--modbus", "http://127.0.0.1:1", "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)],
            "--modbus", "'http'", "tcp://HOST:PORT")


def test_calibrate_refuses_an_unsupported_compass_scheme(tmp_path: Path):
    refused(["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "http://127.0.0.1:1", "-o", str(tmp_path)],
            "--compass", "http")


def test_calibrate_refuses_bad_parameters_and_outputs_naming_the_option(tmp_path: Path):
    base = ["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1"]
    refused([*base, "--samples", "0", "-o", str(tmp_path)], "--samples")
    refused([*base, "--time-scale", "0", "-o", str(tmp_path)], "--time-scale")
    refused([*base, "--control", "127.0.0.1:1", "-o", str(tmp_path)], "--control", "tcp://HOST:PORT")
    refused([*base, "--control", f"tcp://127.0.0.1:{free_port()}", "-o", str(tmp_path)], "--control", "control port")
    (tmp_path / "afile").write_text("")
    refused([*base, "-o", str(tmp_path / "afile")], "--output", "afile")


def test_calibrate_takes_60_samples_per_pose_by_default_as_the_api_does(tmp_path: Path, monkeypatch):
    from procedures.calibrate import CalibrateParams

    seen = {}

    async def fake_station(modbus, compasses, out, time_scale, params, truth, evaluate):
        seen.update(params)
        return 0

    monkeypatch.setattr(cli, "_calibrate_station", fake_station)
    r = runner.invoke(app, ["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1",
                            "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert seen["samples"] == CalibrateParams().samples == 60


# -- serve, demo --api, sim: ports ------------------------------------------------------------------

def test_serve_names_a_port_in_use(busy_port: int, data_dir: Path, nothing_starts: None):
    refused(["serve", "--port", str(busy_port)], f"--port {busy_port}", "in use")


def test_serve_refuses_a_port_out_of_range(data_dir: Path, nothing_starts: None):
    refused(["serve", "--port", "99999"], "--port", "99999", "65535")


def test_serve_listens_on_the_port_asked_and_prints_its_database(data_dir: Path, monkeypatch):
    import uvicorn

    served = {}

    def fake_run(self, sockets=None):
        served["port"] = sockets[0].getsockname()[1]
        served["config_port"] = self.config.port
        sockets[0].close()

    monkeypatch.setattr(uvicorn.Server, "run", fake_run)
    port = free_port()
    r = runner.invoke(app, ["serve", "--port", str(port)])
    assert r.exit_code == 0, r.output
    assert served == {"port": port, "config_port": port}
    assert f"database: sqlite:///{data_dir / 'compasscal.db'}" in r.stdout


def test_a_second_service_on_one_sqlite_database_is_refused(data_dir: Path, nothing_starts: None):
    """SQLite's job queue lives in its service's memory: a second `serve` (or `demo --api`) on the same
    database would end the first's runs as lost and start runs on its busy stations. Refused, naming
    the first's pid; an in-process start is refused the same way; the lock goes with the service."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.db import default_url
    from service.runtime import Conflict

    first = create_app()
    with TestClient(first):
        said = refused(["serve", "--port", str(free_port())], "another compasscal service", f"pid {os.getpid()}")
        assert str(data_dir / "compasscal.db") in said
        refused(["demo", "--api", "--port", str(free_port())], "another compasscal service")
        with pytest.raises(Conflict):
            with TestClient(create_app()):
                pass
    with TestClient(create_app()):  # the first has stopped: its lock is free
        pass
    assert default_url().startswith("sqlite")


def test_demo_api_names_a_port_in_use(busy_port: int, data_dir: Path, nothing_starts: None):
    refused(["demo", "--api", "--port", str(busy_port)], f"--port {busy_port}", "in use")


def test_demo_api_prints_the_database_it_uses(tmp_path: Path, monkeypatch):
    async def fake_api_demo(cfg, sock, keep_serving):
        sock.close()
        return 0

    monkeypatch.setattr(cli, "_api_demo", fake_api_demo)
    for name in ("COMPASSCAL_DATABASE_URL", "COMPASSCAL_DATA_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))  # the user's default, here
    r = runner.invoke(app, ["demo", "--api", "--port", str(free_port())])
    assert r.exit_code == 0, r.output
    said = " ".join(r.stdout.split())
    assert f"database: sqlite:///{tmp_path / 'compasscal' / 'compasscal.db'}" in said
    assert "shared by every checkout" in said and "make run DB=./compasscal.db" in said
    monkeypatch.setenv("COMPASSCAL_DATABASE_URL", f"sqlite:///{tmp_path / 'own.db'}")
    r = runner.invoke(app, ["demo", "--api", "--port", str(free_port())])
    assert r.exit_code == 0, r.output
    assert f"database: sqlite:///{tmp_path / 'own.db'}" in r.stdout and "shared" not in r.stdout


def test_sim_names_a_modbus_port_in_use(busy_port: int, nothing_starts: None):
    refused(["sim", "--modbus-port", str(busy_port)], f"--modbus-port {busy_port}", "in use")


def test_sim_names_a_compass_port_in_use_and_ports_out_of_range(busy_port: int, nothing_starts: None):
    refused(["sim", "--compass-tcp-port", str(busy_port)], f"--compass-tcp-port {busy_port}", "in use")
    refused(["sim", "--modbus-port", "70000"], "--modbus-port", "70000")
    refused(["sim", "--control-port", str(busy_port)], f"--control-port {busy_port}", "in use")
    port = free_port()
    refused(["sim", "--control-port", str(port), "--modbus-port", str(port)], f"--control-port {port}", "--modbus-port")


# -- the database -----------------------------------------------------------------------------------

@pytest.mark.parametrize("args", [["keys", "create", "--owner", "alice", "--role", "admin"], ["db", "upgrade"]])
def test_a_garbage_database_url_is_named(args: list[str], monkeypatch):
    monkeypatch.setenv("COMPASSCAL_DATABASE_URL", "garbage")
    refused(args, "COMPASSCAL_DATABASE_URL=garbage", "not a database URL")


@pytest.mark.parametrize("args", [["keys", "create", "--owner", "alice", "--role", "admin"], ["db", "upgrade"]])
def test_an_unreachable_database_is_named_without_its_password(args: list[str], monkeypatch):
    monkeypatch.setenv("COMPASSCAL_DATABASE_URL", "postgresql://user:s3cret@127.0.0.1:1/compasscal")
    line = refused(args, "postgresql://user:***@127.0.0.1:1/compasscal", "cannot connect")
    assert "s3cret" not in line


def test_a_data_dir_that_is_a_file_is_named(tmp_path: Path, monkeypatch, nothing_starts: None):
    (tmp_path / "afile").write_text("")
    monkeypatch.setenv("COMPASSCAL_DATA_DIR", str(tmp_path / "afile"))
    monkeypatch.delenv("COMPASSCAL_DATABASE_URL", raising=False)
    refused(["db", "upgrade"], "COMPASSCAL_DATA_DIR", "afile")
    refused(["serve", "--port", str(free_port())], "COMPASSCAL_DATA_DIR", "afile")


# -- outputs validated before the work --------------------------------------------------------------

def test_prove_refuses_a_directory_for_json_before_running(tmp_path: Path, monkeypatch):
    import proof.runner

    def never(*a, **k):
        raise AssertionError("the proof ran before its output was checked")

    monkeypatch.setattr(proof.runner, "run_proof", never)
    refused(["prove", "--json", str(tmp_path)], "--json", "is a directory")
    refused(["prove", "--json", str(tmp_path / "no" / "such" / "p.json")], "--json", "does not exist")


def test_simulate_refuses_a_missing_directory_and_negative_noise(tmp_path: Path):
    refused(["simulate", "-o", str(tmp_path / "nonexistent" / "rec.csv")], "--output", "does not exist")
    assert not (tmp_path / "nonexistent").exists()
    refused(["simulate", "--noise", "-3", "-o", str(tmp_path / "rec.csv")], "--noise", "-3")
    refused(["simulate", "--noise", "1e30", "-o", str(tmp_path / "rec.csv")], "--noise 1e+30", "0 to 32767 LSB")
    assert not (tmp_path / "rec.csv").exists()


def test_fit_refuses_outputs_it_could_not_write_before_fitting(tmp_path: Path):
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)]).exit_code == 0
    refused(["fit", str(rec), "-o", str(tmp_path)], "--output", "is a directory")
    refused(["fit", str(rec), "--plot", str(tmp_path / "no" / "fig.png")], "--plot", "does not exist")
    refused(["fit", str(rec), "--truth", str(tmp_path / "missing.json")], "--truth", "missing.json")


@pytest.fixture
def started(monkeypatch: pytest.MonkeyPatch) -> list[tuple]:
    """``calibrate`` without a station: the arguments of each station run it would have started."""
    calls: list[tuple] = []

    async def fake_station(*args):
        calls.append(args)
        return 0

    monkeypatch.setattr(cli, "_calibrate_station", fake_station)
    return calls


def test_a_budget_is_refused_when_nothing_would_spend_it_or_the_plan_overruns_it(tmp_path: Path, started: list):
    base = ["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)]
    for budget in ("150", "180"):  # the default too: given without --adaptive, it would be spent on nothing
        refused([*base, "--budget", budget], f"--budget {budget}", "only the adaptive extension", "add --adaptive")
    refused([*base, "--adaptive", "--budget", "50"], "--budget", "50 s is shorter than the plan", "give at least 107 s")
    refused([*base, "--adaptive", "--samples", "200", "--budget", "180"], "--budget", "shorter than the plan")
    assert started == []
    assert runner.invoke(app, [*base, "--adaptive", "--budget", "150"]).exit_code == 0
    assert started and started[-1][4]["budget_s"] == 150 and started[-1][4]["adaptive"] is True


def test_a_truth_file_of_the_wrong_shape_is_refused_before_any_work(tmp_path: Path, started: list):
    """``--truth`` is checked when the command starts: one unit for fit (simulate's, or a list of one),
    the list by slot for calibrate (sim's); anything else is one line naming the file and the problem."""
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)]).exit_code == 0
    one = tmp_path / "rec.truth.json"
    listed = tmp_path / "list.json"
    listed.write_text("[" + one.read_text() + "]")
    two = tmp_path / "two.json"
    two.write_text("[" + one.read_text() + "," + one.read_text() + "]")
    (tmp_path / "a1.json").write_text('{"a": 1}')
    (tmp_path / "num.json").write_text("3")
    (tmp_path / "partial.json").write_text('{"magnetometer": {"M_o": [[1,0,0],[0,1,0],[0,0,1]]}}')
    refused(["fit", str(rec), "--truth", str(two)], "--truth", "two.json", "list of 2 units")
    refused(["fit", str(rec), "--truth", str(tmp_path / "a1.json")], "--truth", "a1.json", "'magnetometer'")
    refused(["fit", str(rec), "--truth", str(tmp_path / "num.json")], "num.json", "int")
    refused(["fit", str(rec), "--truth", str(tmp_path / "partial.json")], "partial.json", "'k'")
    for good in (one, listed):  # simulate's unit, or a list of one, scores the fit
        r = runner.invoke(app, ["fit", str(rec), "--truth", str(good)])
        assert r.exit_code == 0 and "against the true unit" in r.output, r.output

    base = ["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)]
    refused([*base, "--truth", str(one)], "--truth", "a JSON object", "`sim --truth`")
    refused([*base, "--truth", str(tmp_path / "num.json")], "--truth", "int")
    (tmp_path / "lista1.json").write_text('[{"a": 1}]')
    refused([*base, "--truth", str(tmp_path / "lista1.json")], "--truth", "entry 0", "'magnetometer'")
    assert started == []  # refused before the station was touched
    assert runner.invoke(app, [*base, "--truth", str(two)]).exit_code == 0 and len(started) == 1


# -- fit's messages ---------------------------------------------------------------------------------

def test_fit_says_how_many_rows_it_skipped(tmp_path: Path):
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)]).exit_code == 0
    lines = rec.read_text().splitlines()
    data = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#") and not ln.startswith("t,")]
    for i in data[5:7]:
        lines[i] = lines[i].rsplit(",", 1)[0] + ",oops"
    rec.write_text("\n".join(lines) + "\n")
    r = runner.invoke(app, ["fit", str(rec), "--skip-bad-rows", "-o", str(tmp_path / "cal.json")])
    assert r.exit_code == 0, r.output
    assert "2 malformed row(s) of rec.csv skipped (data rows 5, 6, 0-based" in " ".join(r.stderr.split()), r.stderr
    # the calibration keeps the trace (its JSON had no word of the rows skipped)
    cal = json.loads((tmp_path / "cal.json").read_text())
    assert cal["quality"]["skipped_malformed"] == 2 and any("2 malformed row(s) of the file were skipped" in n
                                                            for n in cal["notes"]), cal["notes"]
    assert cal["quality"]["skipped_malformed_rows"] == [5, 6]  # which, as well as how many
    # most of the file skipped (rows out of time order: a shuffled file) is no calibration of it
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("t,")]
    body = [lines[i] for i in data]
    rng = np.random.default_rng(0)
    shuffled = tmp_path / "shuffled.csv"
    shuffled.write_text("\n".join(head + [body[i] for i in rng.permutation(len(body))]) + "\n")
    r = runner.invoke(app, ["fit", str(shuffled), "--skip-bad-rows"])
    assert r.exit_code == 2 and "malformed and skipped, more than were kept" in " ".join(r.stderr.split()), r.stderr


def test_fit_counts_a_dropped_samples_row_as_the_file_does_when_malformed_rows_were_skipped(tmp_path: Path):
    """A bad sample the fit drops is named by its row in the file: the malformed rows skipped before it
    count, or the technician would look at the wrong line."""
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "10", "-o", str(rec)]).exit_code == 0
    lines = rec.read_text().splitlines()
    data = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#") and not ln.startswith("t,")]
    cells = lines[data[40]].split(",")
    cells[5] = "32000"  # a reading no unit gives: the fit drops the row (file data row 40)
    lines[data[40]] = ",".join(cells)
    for i in data[3:5]:  # two malformed rows before it
        lines[i] = lines[i].rsplit(",", 1)[0] + ",oops"
    rec.write_text("\n".join(lines) + "\n")
    r = runner.invoke(app, ["fit", str(rec), "--skip-bad-rows", "-o", str(tmp_path / "cal.json")])
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "row 40 (t" in said and "row 38 (t" not in said, said
    # the note (the calibration's notes) and the JSON count the same rows (the note said 38: the
    # recording's index)
    assert "bad samples (1 off their pose's median): data rows 40 (0-based)" in said, said
    cal = json.loads((tmp_path / "cal.json").read_text())
    assert [(x["index"], x["row"]) for x in cal["quality"]["rejected_rows"]] == [(38, 40)], cal["quality"]["rejected_rows"]
    assert any("data rows 40 (0-based)" in n for n in cal["notes"]), cal["notes"]


def test_fit_names_the_elements_a_level_only_recording_leaves_undetermined(tmp_path: Path):
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)]).exit_code == 0
    rec.write_text("".join(ln for ln in rec.read_text().splitlines(keepends=True) if ",sweep_" not in ln))
    line = refused(["fit", str(rec)], "cannot determine", "M[xm,xb]", "M[ym,yb]", "bias[x]", "bias[z]")
    assert "M, M" not in line


# -- help -------------------------------------------------------------------------------------------

def test_sim_help_shows_the_toml_array_tables():
    r = runner.invoke(app, ["sim", "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0
    assert "[[unit]]" in r.output and "[[fault]]" in r.output and "[]" not in r.output


@pytest.mark.parametrize("command", [[], ["simulate"], ["fit"], ["convert"], ["analyze"], ["calibrate"], ["demo"], ["sim"], ["serve"],
                                     ["prove"], ["keys"], ["keys", "create"], ["db"], ["db", "upgrade"]])
def test_help_has_no_type_placeholders_for_flags_or_lists(command: list[str]):
    r = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "<bool>" not in r.output and "<list[" not in r.output and "<float,float>" not in r.output


# -- the real entry point ---------------------------------------------------------------------------

def test_the_installed_command_exits_2_with_one_line(tmp_path: Path):
    r = subprocess.run([sys.executable, "-m", "service.cli", "calibrate", "--modbus", "http://127.0.0.1:1",
                        "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stdout == ""
    assert re.fullmatch(r"error: --modbus http://127\.0\.0\.1:1: [^\n]+\n", r.stderr), r.stderr


# -- the technician's example script ----------------------------------------------------------------

def example(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    base = {k: v for k, v in os.environ.items() if not k.startswith("COMPASSCAL_")}
    return subprocess.run([sys.executable, str(ROOT / "examples" / "calibrate_unit.py"), "lab-1", "SN-0001"],
                          env={**base, **env}, capture_output=True, text=True, timeout=60)


def test_example_script_without_a_key_says_so_in_one_line():
    r = example({})
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert r.stderr.count("\n") == 1 and "COMPASSCAL_KEY is not set" in r.stderr


def test_example_script_with_a_wrong_url_says_so_in_one_line():
    r = example({"COMPASSCAL_KEY": "cc_x", "COMPASSCAL_URL": f"http://127.0.0.1:{free_port()}"})
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert r.stderr.count("\n") == 1 and "cannot reach the compasscal service" in r.stderr
    r = example({"COMPASSCAL_KEY": "cc_x", "COMPASSCAL_URL": "127.0.0.1:8000"})
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert r.stderr.count("\n") == 1 and "COMPASSCAL_URL" in r.stderr


def test_fit_of_a_recording_without_table_angles_names_the_methods_that_need_none(tmp_path: Path):
    """The QMC logger's hand-held file (data/real) has no table angles: the default joint fit is refused in
    one line saying so and which methods calibrate without them (before: "SVD did not converge"), and
    the ellipsoid method calibrates it."""
    qmc = Path(__file__).resolve().parent.parent / "data" / "real" / "qmc5883l_filtered_raw_data.csv"
    refused(["fit", str(qmc)], "method joint needs the table's angles", "hand-held", "ellipsoid and maxmin")
    refused(["fit", str(qmc), "--method", "error-separation"], "method error-separation needs the table's angles")
    r = runner.invoke(app, ["fit", str(qmc), "--method", "ellipsoid"])
    assert r.exit_code == 0 and "method ellipsoid" in r.output, r.output
    # what it prints and draws is what the magnetometer alone shows: no "nan" residuals, no level turn, no
    # "heading levelled by table angles" (it has none), and a plot drawn without a warning
    said = " ".join(r.output.split())
    assert "nan" not in said and "field: not determined (no table angles)" in said, said
    assert "heading levelled by table angles" not in said and "no table angles either" in said
    plot = tmp_path / "q.png"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = runner.invoke(app, ["fit", str(qmc), "--method", "ellipsoid", "--plot", str(plot)])
    assert r.exit_code == 0 and plot.stat().st_size > 10_000, (r.output, r.exception)


def test_fit_refuses_swapped_angle_columns_and_writes_strict_json(tmp_path: Path):
    """psi_t and phi_t swapped in the header: the fit left 1000 times the noise and was accepted; now the
    misfit is looked at and the refusal names the readings of the angles that fit. A hand-held recording
    with an accelerometer calibrates with the ellipsoid (its accelerometer left alone: "SVD did not
    converge" before), and the calibration JSON is strict (NaN written as null)."""
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "-o", str(rec)]).exit_code == 0
    lines = rec.read_text().splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("t,"))
    swapped = tmp_path / "swapped.csv"
    swapped.write_text("\n".join(lines[:head] + [lines[head].replace("psi_t,theta_t,phi_t", "phi_t,theta_t,psi_t")]
                                 + lines[head + 1:]) + "\n")
    refused(["fit", str(swapped)], "the fitted model leaves", "times the noise", "far better read")
    assert runner.invoke(app, ["fit", str(rec)]).exit_code == 0  # the file as written fits
    blank = tmp_path / "noangles.csv"
    blank.write_text("\n".join(lines[:head + 1] + [",".join(c if k not in (2, 3, 4) else "" for k, c in enumerate(ln.split(",")))
                                                   for ln in lines[head + 1:]]) + "\n")
    out = tmp_path / "cal.json"
    r = runner.invoke(app, ["fit", str(blank), "--method", "ellipsoid", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "accelerometer not calibrated" in " ".join(r.output.split())
    json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in the calibration JSON"))


def test_simulate_and_fit_options_are_checked_before_any_work(tmp_path: Path):
    """Values no field or plot can have are refused in one line, exit 2 (before: tracebacks for a negative
    seed, a NaN inclination and a plot format matplotlib does not write, after the fit; raw pydantic
    wording for --samples 0; an inclination of 200 accepted and then scored 180 deg off by --truth)."""
    out = str(tmp_path / "x.csv")
    assert runner.invoke(app, ["simulate", "--seed", "-1", "-o", out]).exit_code == 2
    refused(["simulate", "--inclination", "nan", "-o", out], "--inclination nan", "-90 to 90")
    refused(["simulate", "--inclination", "200", "-o", out], "--inclination 200", "-90 to 90")
    refused(["simulate", "--samples", "0", "-o", out], "--samples 0", "greater than or equal to 1")
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", out]).exit_code == 0
    for plot in ("p.txt", "pnoext"):
        refused(["fit", out, "--plot", str(tmp_path / plot), "-o", str(tmp_path / "c.json")], f"--plot", ".png")
        assert not (tmp_path / "c.json").exists()  # refused before the fit wrote anything
    other = tmp_path / "other.csv"
    assert runner.invoke(app, ["simulate", "--seed", "4", "--samples", "3", "-o", str(other)]).exit_code == 0
    # another unit's truth, or a calibration given as the truth, is refused (the note was missed above 19 deg
    # of "error"; a calibration scored against itself said 0.0000 deg)
    refused(["fit", out, "--truth", str(other.with_suffix(".truth.json"))], "--truth", "the true parameters of unit")
    assert runner.invoke(app, ["fit", out, "-o", str(tmp_path / "c.json")]).exit_code == 0
    refused(["fit", out, "--truth", str(tmp_path / "c.json")], "--truth", "a calibration (`fit -o`)")


def test_analyze_skips_bad_rows_as_fit_does(tmp_path: Path):
    """analyze takes --skip-bad-rows (before, a file with one malformed row could only be analysed after
    convert --skip-bad-rows) and says how many it skipped."""
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "20", "-o", str(rec)]).exit_code == 0
    lines = rec.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln and not ln.startswith(("#", "t,"))) + 5
    lines[i] = lines[i].rsplit(",", 1)[0] + ",oops"
    rec.write_text("\n".join(lines) + "\n")
    r = runner.invoke(app, ["analyze", str(rec), "--null-sims", "5"])
    assert r.exit_code == 2 and "1 malformed row(s)" in r.stderr, r.output
    r = runner.invoke(app, ["analyze", str(rec), "--null-sims", "5", "--skip-bad-rows", "--json", str(tmp_path / "a.json")])
    assert r.exit_code == 0, r.output
    assert "1 malformed row(s) of rec.csv skipped" in " ".join(r.stderr.split())


def test_convert_keeps_the_rows_it_skipped_in_the_metadata(tmp_path: Path):
    """convert writes every conversion into the file's metadata: dropping malformed rows is one."""
    qmc = Path(__file__).resolve().parent.parent / "data" / "real" / "qmc5883l_filtered_raw_data.csv"
    lines = qmc.read_text().splitlines()
    lines[10] = "12,abc,5"
    bad, out = tmp_path / "q.csv", tmp_path / "out.csv"
    bad.write_text("\n".join(lines) + "\n")
    assert runner.invoke(app, ["convert", str(bad), "--skip-bad-rows", "-o", str(out)]).exit_code == 0
    assert "# converted_skipping: 1 malformed row(s) of q.csv dropped (--skip-bad-rows)" in out.read_text()


def test_a_file_without_its_column_line_or_of_one_row_is_refused_for_what_it_is(tmp_path: Path):
    """A file of numbers only was refused as "duplicate column(s): 0.0000", and one data row as "the
    reading never changes ... a dead or disconnected magnetometer axis?"."""
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)]).exit_code == 0
    lines = rec.read_text().splitlines()
    header = next(i for i, ln in enumerate(lines) if ln.startswith("t,"))
    bare = tmp_path / "bare.csv"
    bare.write_text("\n".join(lines[header + 1:header + 40]) + "\n")
    r = runner.invoke(app, ["fit", str(bare)])
    assert r.exit_code != 0 and "the file has no column line" in " ".join(r.output.split()), r.output
    one = tmp_path / "one.csv"
    one.write_text("\n".join(lines[:header + 2]) + "\n")
    r = runner.invoke(app, ["fit", str(one)])
    said = " ".join(r.output.split())
    assert r.exit_code != 0 and "1 data row(s)" in said and "dead or disconnected" not in said, r.output


def test_an_output_that_cannot_be_written_is_refused_before_the_work(tmp_path: Path, monkeypatch):
    """/proc passes the permission check (its directory exists and is writable to root) but refuses a
    file: that was a traceback and exit 1, then one line after the whole fit; now the file is tried up
    front, before the fit (and an existing output is left untouched by the check)."""
    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(rec)]).exit_code == 0

    def never(*a, **k):
        raise AssertionError("the fit ran before its output was checked")

    monkeypatch.setattr(cli, "fit_recording", never)
    refused(["fit", str(rec), "-o", "/proc/compasscal-cal.json"], "--output /proc/compasscal-cal.json")
    assert not Path("/proc/compasscal-cal.json").exists()
    # a file where its directory should be is said to be one (not "directory rec.csv does not exist")
    refused(["fit", str(rec), "-o", str(rec / "c.json")], "--output", f"{rec} is a file, not a directory")
    refused(["fit", str(rec), "-o", str(rec / "sub" / "c.json")], f"{rec} is a file, not a directory")
    # calibrate's output directory too, before any connection (it was blamed on "station" after connecting)
    refused(["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1", "-o", "/proc/compasscal-x"],
            "--output /proc/compasscal-x", "cannot create the directory")
    monkeypatch.undo()
    out = tmp_path / "c.json"
    r = runner.invoke(app, ["fit", str(rec), "-o", str(out)])
    assert r.exit_code == 0 and out.exists(), r.output
    # after the work, a write that fails anyway is still one line (cli._write), not a traceback
    with pytest.raises(typer.Exit) as e:
        cli._write(Path("/proc/compasscal-cal.json"), "{}")
    assert e.value.exit_code == 2


def test_analyze_takes_the_services_seed_to_repeat_its_analysis(tmp_path: Path):
    """An analysis JSON says its seed, which may be several integers (the service's of before were [run
    id, slot]); the CLI took one integer only, so such a result could not be repeated from the command line."""
    import numpy as np

    from physics.discrepancy import analyze
    from physics.recording import format_recording, parse_recording

    rec = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "20", "-o", str(rec)]).exit_code == 0
    out = tmp_path / "a.json"
    r = runner.invoke(app, ["analyze", str(rec), "--null-sims", "20", "--seed", "6,0", "--json", str(out)])
    assert r.exit_code == 0, r.output
    direct = analyze(parse_recording(rec.read_text()), None, null_sims=20, seed=[6, 0])
    got = json.loads(out.read_text())
    assert got["tests"] == json.loads(json.dumps(direct.to_json()))["tests"] and got["tests"]
    # without a seed: the recording's fingerprint, said in the JSON, so a file and a copy of it written
    # another way (times carrying float noise far below the millisecond a recording keeps) are analysed alike
    copy = parse_recording(rec.read_text())
    copy.t = copy.t + 1e-7
    again = tmp_path / "again.csv"
    again.write_text(format_recording(copy))
    assert again.read_text() != rec.read_text()
    outs = [tmp_path / "d1.json", tmp_path / "d2.json"]
    for path, out_path in zip((rec, again), outs):
        r = runner.invoke(app, ["analyze", str(path), "--null-sims", "20", "--json", str(out_path)])
        assert r.exit_code == 0, r.output
    d1, d2 = (json.loads(p.read_text()) for p in outs)
    assert d1["seed"] == d2["seed"] == parse_recording(rec.read_text()).fingerprint()
    # the same null simulations: every test's p-value the same to the float noise of the times
    assert [t["variant"] for t in d1["tests"]] == [t["variant"] for t in d2["tests"]] and d1["tests"]
    np.testing.assert_allclose([t["p_value"] for t in d1["tests"]], [t["p_value"] for t in d2["tests"]], rtol=1e-6)
    other = runner.invoke(app, ["analyze", str(rec), "--null-sims", "20", "--seed", "1", "--json", str(outs[1])])
    assert other.exit_code == 0 and json.loads(outs[1].read_text())["tests"] != d1["tests"]  # the seed matters
    for bad in ("-1", "6,x", ""):
        r = runner.invoke(app, ["analyze", str(rec), "--seed", bad])
        assert r.exit_code == 2 and "--seed" in r.output and "several joined by commas" in " ".join(r.output.split()), r.output


# -- the probe's findings (calibrate's file names, station configs, outputs, time scale) ---------------

def _fake_calibration_run(monkeypatch: pytest.MonkeyPatch, serials: dict[int, str]) -> None:
    """``calibrate`` on a fake station whose units report ``serials``: the real recording sink and the
    CLI's writing of each slot's files, a simulated recording and its fit as every slot's calibration."""
    import contextlib
    from types import SimpleNamespace

    import drivers.station
    import procedures.engine
    from physics.fit import fit
    from physics.sensor import reference_unit
    from physics.simulate import World, simulate_recording
    from procedures.calibrate import CalibrateParams, calibration_poses

    rec = simulate_recording(reference_unit(3.0, 4.0), calibration_poses(CalibrateParams(samples=3)), World(55.0, 23.0),
                             rng=np.random.default_rng(0))
    cal = fit(rec, "joint")

    @contextlib.asynccontextmanager
    async def fake_station(*a, **k):
        yield None

    async def fake_run(station, name, params, *, out_dir=None, on_event=lambda e: None, engine_hook=lambda e: None):
        sink = procedures.engine.RecordingSink(out_dir, dict(serials), {})
        engine_hook(SimpleNamespace(sink=sink, serials=dict(serials), abort=lambda reason: None))
        for slot in serials:
            sink.add(slot, rec)  # as the engine does after each acquisition
        result = SimpleNamespace(state=SimpleNamespace(value="completed"), reason=None, table_seconds=1.0,
                                 plan_seconds=1.0, samples=len(rec) * len(serials),
                                 outcome=SimpleNamespace(results={slot: {"calibration": cal} for slot in serials}))
        return result, dict(serials), sink

    monkeypatch.setattr(drivers.station, "open_station", fake_station)
    monkeypatch.setattr(procedures.engine, "run_procedure", fake_run)


def test_calibrate_names_each_units_files_inside_the_output_directory(tmp_path: Path, monkeypatch):
    """A unit reporting "../evil/SN 1" had its recording, calibration and plot written outside -o DIR (or
    the run failed with FileNotFoundError after the table had moved); two units reporting one serial
    overwrote each other's files. Now: slot<N> for a serial that cannot name a file (service.identity's
    rule), <serial>-slot<N> for a shared one, each said in one note; the run itself succeeds."""
    out = tmp_path / "out"
    _fake_calibration_run(monkeypatch, {0: "../evil/SN 1", 1: "SN-1", 2: "SN-1", 3: "SN 2"})
    urls = [f"socket://127.0.0.1:{p}" for p in (1, 2, 3, 4)]
    r = runner.invoke(app, ["calibrate", "--modbus", "tcp://127.0.0.1:1", *[x for u in urls for x in ("--compass", u)],
                            "-o", str(out)])
    assert r.exit_code == 0, (r.output, r.exception)
    assert not (tmp_path / "evil").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{name}{ext}" for name in ("slot0", "SN-1-slot1", "SN-1-slot2", "SN 2") for ext in (".csv", ".cal.json", ".png"))
    notes = [ln for ln in r.stderr.splitlines() if ln.startswith("note:")]
    assert len(notes) == 2, r.stderr
    assert "slot 0" in notes[0] and "'../evil/SN 1'" in notes[0] and "slot0.*" in notes[0]
    assert "SN-1-slot1.*" in notes[1] and "SN-1-slot2.*" in notes[1]
    assert "recording" + str(out / "slot0.csv") in "".join(r.stdout.split())  # (rich wraps a long path anywhere)
    # the rule itself, directly
    names, said = cli.output_names({0: "", 1: "A/B", 2: "SN-9", 3: " SN-9 "})
    assert names == {0: "slot0", 1: "slot1", 2: "SN-9-slot2", 3: "SN-9-slot3"} and len(said) == 3


def test_calibrate_refuses_one_compass_for_two_slots_and_a_modbus_url_without_port(tmp_path: Path, started: list):
    """The same --compass twice made both slots share a port (reconnect storms, tracebacks, slot 1
    overwriting slot 0's files); tcp://HOST without a port said only "cannot connect" later."""
    base = ["calibrate", "--modbus", "tcp://127.0.0.1:1", "-o", str(tmp_path)]
    refused([*base, "--compass", "/dev/pts/0", "--compass", "/dev/pts/0"],
            "--compass /dev/pts/0", "given for two slots (0 and 1)")
    refused([*base, "--compass", "socket://127.0.0.1:1", "--compass", "socket://127.0.0.1:2", "--compass", "socket://127.0.0.1:1"],
            "--compass socket://127.0.0.1:1", "two slots (0 and 2)")
    for url in ("tcp://127.0.0.1", "rtu+tcp://gateway"):
        refused(["calibrate", "--modbus", url, "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)],
                f"--modbus {url}", "no port", ":PORT")
    assert started == []
    assert runner.invoke(app, [*base, "--compass", "socket://127.0.0.1:1", "--compass", "socket://127.0.0.1:2"]).exit_code == 0


UNIT = '[[unit]]\nserial = "SN-1"\nmag_k = [3000.0, 3100.0, 3200.0]\n'


@pytest.mark.parametrize("toml, words", [
    ("[world]\nseed = -1\n" + UNIT, ["world.seed", "greater than or equal to 0", "an integer >= 0"]),
    ("[world]\ninclination_deg = \"55\"\n" + UNIT, ["world.inclination_deg", "got str '55'", "a number of degrees"]),
    ("[world]\ntime_scale = 1e9\n" + UNIT, ["world.time_scale", "<= 1000"]),
    ("[table]\nhomed = 1\n" + UNIT, ["table.homed", "got int 1", "true or false"]),
    (UNIT.replace("3100.0", "-1.0"), ["unit[0].mag_k[1]", "greater than 0", "3 sensitivities"]),
    (UNIT.replace("3100.0", "0.0"), ["unit[0].mag_k[1]", "greater than 0"]),
    (UNIT.replace("3100.0", "1e300"), ["unit[0].mag_k[1]", "less than or equal to 32767"]),
    (UNIT.replace("3100.0", "nan"), ["unit[0].mag_k[1]", "finite"]),
    (UNIT + "mag_angles_deg = [[0, 90, 90], [0, 90, 90], [90, 90, 0]]\n", ["unit[0]", "mag_angles_deg", "do not span space"]),
    (UNIT + "mag_angles_deg = [[90, 90, 90], [90, 0, 90], [90, 90, 0]]\n", ["mag_angles_deg", "sensor axis 0", "90 deg"]),
    (UNIT + "mag_M_o = [[1, 0, 0], [1, 0, 0], [0, 0, 1]]\n", ["mag_M_o", "do not span space"]),
    (UNIT + '[[fault]]\nkind = "axis_alarm"\naxis = "y"\nat_angle_deg = 10.0\nat_s = 3.0\n',
     ["fault[0]", "at_angle_deg or at_s, not both"]),
])
def test_a_station_config_value_of_the_wrong_kind_or_range_is_refused_naming_the_key(
        tmp_path: Path, nothing_starts: None, toml: str, words: list[str]):
    """seed = -1 was a traceback from numpy; "55" for a number, 1 for true, a sensitivity of 0, -1 or
    1e300, a singular orientation and a fault with two triggers were all simulated."""
    config = tmp_path / "station.toml"
    config.write_text(toml)
    refused(["sim", "--config", str(config)], "station.toml", *words)
    refused(["demo", "--config", str(config), "-o", str(tmp_path / "out")], *words)


def test_the_readmes_station_config_is_one_the_simulator_takes():
    """The README's example (with the ranges its comments give) is valid, and an integer is a number."""
    from drivers.sim.config import parse_config

    text = (ROOT / "README.md").read_text()
    example = text.split("```toml\n", 1)[1].split("```", 1)[0]
    import tomllib

    cfg = parse_config(tomllib.loads(example))
    assert cfg.unit[0].mag_k == [3268.0, 3163.4, 3201.5] and cfg.fault[0].at_angle_deg == 100.0
    assert parse_config(tomllib.loads(UNIT.replace("3100.0", "3100"))).unit[0].mag_k[1] == 3100.0


def test_analyze_refuses_a_missing_output_directory_as_the_other_commands_do(tmp_path: Path):
    """analyze created --json's and --html's missing directories (a mistyped path went unnoticed) while
    fit, simulate, convert and prove refuse them."""
    rec = tmp_path / "rec.csv"
    rec.write_text("")
    for option in ("--json", "--html"):
        refused(["analyze", str(rec), option, str(tmp_path / "nonexistent" / "a.out")], option, "does not exist")
        refused(["fit", str(rec), "-o", str(tmp_path / "nonexistent" / "a.out")], "--output", "does not exist")
    assert not (tmp_path / "nonexistent").exists()


def test_time_scale_is_bounded_alike_for_every_command(tmp_path: Path, nothing_starts: None, started: list):
    """demo --time-scale 1e9 ran and reported billions of seconds of table time; one rule (> 0, at most
    drivers.sim.config.MAX_TIME_SCALE, as the service's stations) for demo, sim and calibrate."""
    from drivers.sim.config import MAX_TIME_SCALE

    assert MAX_TIME_SCALE == 1000
    base = ["calibrate", "--modbus", "tcp://127.0.0.1:1", "--compass", "socket://127.0.0.1:1", "-o", str(tmp_path)]
    for value in ("1e9", "1001", "0", "-1", "nan"):
        for args in (["demo", "-o", str(tmp_path / "d")], ["sim"], base):
            refused([*args, "--time-scale", value], "--time-scale", "<= 1000")
    assert started == []
    assert runner.invoke(app, [*base, "--time-scale", "1000"]).exit_code == 0 and started[-1][3] == 1000


def test_prove_refuses_a_proof_of_nothing(monkeypatch):
    """--n 0 --nulls 0 (and no open-world or hand-held cases) proved nothing and exited 0."""
    import proof.runner

    def never(*a, **k):
        raise AssertionError("the proof ran")

    monkeypatch.setattr(proof.runner, "run_proof", never)
    monkeypatch.setattr(proof.runner, "run_handheld_proof", never)
    refused(["prove", "--n", "0", "--nulls", "0"], "--n 0 --nulls 0", "nothing to prove", "--open-n", "--handheld-n")
