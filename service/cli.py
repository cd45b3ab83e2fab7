"""The ``compasscal`` command line (typer)."""

from __future__ import annotations

import json
import os
import re
import socket
from collections import Counter
from enum import Enum
from pathlib import Path
from typing import Any, NoReturn, Optional

import numpy as np
import typer
import typer.core
from pydantic import ValidationError
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from drivers import keep_drivers_responsive
from physics.calibration import FORMAT as CALIBRATION_FORMAT, Calibration, json_safe, staged_truth_errors, truth_summary
from physics.errorsep import InsufficientData
from physics.fit import METHODS, fit as fit_recording, index_list
from physics.recording import SKIPPED_AT_KEY, SKIPPED_KEY, Recording, RecordingError, file_row, format_recording
from physics.sensor import random_unit, reference_unit
from physics.simulate import World, plan_cost, simulate_recording, truth_from_json, truth_json
from physics.table import TableGeometry
from procedures.calibrate import CalibrateParams, calibration_poses, needed_budget_s

def _no_flag_types(params: list[Any]) -> list[Any]:
    """Help shows no value placeholder after a flag: it takes no value (typer prints ``<bool>``)."""
    for p in params:
        if getattr(p, "is_flag", False):
            p.display_type_rich = lambda ctx: None
    return params


class _Command(typer.core.TyperCommand):
    def get_params(self, ctx: Any) -> list[Any]:
        return _no_flag_types(super().get_params(ctx))


class _Group(typer.core.TyperGroup):
    def get_params(self, ctx: Any) -> list[Any]:
        return _no_flag_types(super().get_params(ctx))


#: Seconds a stopping service waits for open requests (live event streams included) before closing them.
SHUTDOWN_GRACE_S = 5

app = typer.Typer(help="Electronic-compass calibration station.", no_args_is_help=True, add_completion=False,
                  pretty_exceptions_show_locals=False, cls=_Group)
console = Console()
err_console = Console(stderr=True)  # errors never mix with a command's stdout (e.g. `sim`'s JSON line)


@app.callback()
def _every_command() -> None:
    """Electronic-compass calibration station."""
    keep_drivers_responsive()


class UnitKind(str, Enum):
    reference = "reference"
    random = "random"


MAPPING_HELP = ("TOML mapping that says how to read a file no built-in reader knows: columns, units, axis signs "
                "and order, angle convention or attitude quaternion, time base (see examples/mapping.toml).")


Method = Enum("Method", {m.replace("-", "_"): m for m in METHODS}, type=str)  # type: ignore[misc]


def _only_service(url: str) -> None:
    """Refuse a second service on one SQLite database (its job queue lives in the first's memory)."""
    from service.runtime import DomainError
    from service.worker import sqlite_service_lock

    try:
        held = sqlite_service_lock(url)
    except DomainError as e:
        _fail(str(e.detail))
    if held is not None:
        held.close()


def _wall_left(e: Any, time_scale: float) -> float:
    """Seconds of wall time a run has left (what a person waits), from a progress event."""
    return e.left_wall_s if e.left_wall_s is not None else e.left_s / time_scale


def _fail(message: str) -> NoReturn:
    """End the command: the message on stderr (taken literally, not as rich markup: ``M[xm,xb]``), exit 2."""
    err_console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)
    raise typer.Exit(code=2)


def _seed_list(text: Optional[str]) -> int | list[int] | None:
    """``--seed``: one integer >= 0, or several joined by commas (as an analysis JSON's ``"seed"`` may be,
    e.g. an older service analysis's [run id, slot]); None when not given."""
    if text is None:
        return None
    try:
        values = [int(x) for x in text.replace("[", "").replace("]", "").split(",")]
    except ValueError:
        values = [-1]
    if any(v < 0 for v in values):
        _fail(f"--seed {text!r}: an integer >= 0, or several joined by commas (e.g. 6,0)")
    return values[0] if len(values) == 1 else values


def _write(path: Path, text: str) -> None:
    """Write an output file (its directory made), or end the command saying why it cannot be written
    (the up-front check cannot foresee everything: /proc refuses at the write, after the work)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    except OSError as e:
        _fail(f"cannot write {path}: {e.strerror or e}")


def _note(message: str) -> None:
    """A note on stderr (stdout stays the command's output)."""
    err_console.print(f"[dim]note:[/] {escape(message)}", soft_wrap=True)


def _note_skipped(rec: Recording, recording: Path) -> None:
    """Say how many malformed rows ``--skip-bad-rows`` dropped from ``recording``."""
    skipped = rec.meta.get(SKIPPED_KEY)
    at = [int(x) for x in rec.meta.get(SKIPPED_AT_KEY, "").split(",") if x.strip()]
    where = f" (data rows {index_list(at)}, 0-based, header and comments not counted)" if at else ""
    _note(f"--skip-bad-rows: {skipped} malformed row(s) of {recording.name} skipped{where}" if skipped is not None
          else f"--skip-bad-rows: {recording.name} is not a text file with rows to skip; nothing skipped")


def _plot_file(path: Optional[Path], option: str = "--plot") -> None:
    """:func:`_output_file`, and a picture format matplotlib writes, named by the file's extension (one
    it does not know failed with a traceback after the fit; none wrote a .png under another name)."""
    if path is None:
        return
    _output_file(path, option)
    from matplotlib.figure import Figure  # local: matplotlib is slow to import

    known = sorted(Figure().canvas.get_supported_filetypes())
    if path.suffix.lower().lstrip(".") not in known:
        _fail(f"{option} {path}: name the picture's format by its extension, one of {', '.join('.' + k for k in known)}")


def _output_file(path: Optional[Path], option: str) -> None:
    """Refuse, before any work, an output file that cannot be written: a directory, a parent directory
    that does not exist (never created: a mistyped directory is said, as every command does), a file
    in the way of its directory, or a place this user cannot write to."""
    if path is None:
        return
    if path.is_dir():
        _fail(f"{option} {path}: is a directory; give a file name")
    parent = path.parent
    if not parent.is_dir():
        blocker = next((p for p in (parent, *parent.parents) if p.exists()), None)
        if blocker is not None and not blocker.is_dir():
            _fail(f"{option} {path}: {blocker} is a file, not a directory")
        _fail(f"{option} {path}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        _fail(f"{option} {path}: not writable")
    if not path.exists():
        # some places pass the permission check and still refuse a file (/proc, a read-only mount for
        # root): try creating it now rather than after the work (an existing file is left untouched)
        try:
            path.open("x").close()
        except OSError as e:
            _fail(f"{option} {path}: cannot create a file there ({e.strerror or e})")
        path.unlink()


def _output_dir(path: Path, option: str) -> None:
    """Refuse, before any work, an output directory that is a file or cannot be created."""
    if path.exists() and not path.is_dir():
        _fail(f"{option} {path}: is a file, not a directory")
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        _fail(f"{option} {path}: {existing} is a file, not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        _fail(f"{option} {path}: {existing} is not writable")
    try:  # now, so a place that refuses it (/proc, a read-only mount for root) is named as the option, not "station"
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        _fail(f"{option} {path}: cannot create the directory ({e.strerror or e})")


def _port(value: Optional[int], option: str, any_free: bool = False) -> None:
    """A TCP port in range (0 means "any free port" only where ``any_free``)."""
    low = 0 if any_free else 1
    if value is not None and not low <= value <= 65535:
        _fail(f"{option} must be a TCP port, {low}-65535, got {value}")


def _time_scale(value: Optional[float], option: str = "--time-scale") -> None:
    """A time scale the simulator can honour: > 0 and at most drivers.sim.config.MAX_TIME_SCALE (the
    service's limit for a station too); 1e9 was taken and reported billions of seconds of table time."""
    from drivers.sim.config import MAX_TIME_SCALE

    if value is not None and not 0 < value <= MAX_TIME_SCALE:
        _fail(f"{option} {value:g}: give a number > 0 and <= {MAX_TIME_SCALE:g} (1: real time; 20: twenty times faster)")


def _listen(host: str, port: int, option: str = "--port") -> socket.socket:
    """A listening socket on host:port for the service (uvicorn serves on it), or a clear error naming
    ``option`` (e.g. "--port 8000") when the port is taken or the address is not this machine's."""
    if not any(c.isdigit() for c in option):
        option = f"{option} {port}"
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    except socket.gaierror as e:
        _fail(f"--host {host}: {e.strerror}")
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn does: a restart need not wait
        sock.bind(addr)
        sock.listen(2048)
    except OSError as e:
        sock.close()
        taken = " (another program is listening there; choose another port)" if e.errno == 98 else ""
        _fail(f"{option}: cannot listen on {host}:{port}: {e.strerror}{taken}")
    sock.set_inheritable(True)
    return sock


def _port_free(host: str, port: int, option: str) -> None:
    """Refuse a port something else already listens on, before starting a server there (0: any, always free)."""
    if port:
        _listen(host, port, option).close()


def _shown_url(url: str) -> str:
    """A database URL for messages and logs: the password hidden."""
    return re.sub(r"(://[^:/@]*):[^@]*@", r"\1:***@", url)


def _open_database() -> str:
    """Reach the service's database (COMPASSCAL_DATABASE_URL, else the SQLite default) and bring it to the
    newest migration; any problem ends the command with one line naming the setting. Returns the URL
    (password hidden) for the user to see."""
    from sqlalchemy.exc import ArgumentError, InterfaceError, OperationalError

    from service.db import default_url, make_engine, upgrade

    try:
        url = default_url()
    except OSError as e:  # the SQLite file's directory cannot be made: a file is in the way, no permission
        source = next((v for v in ("COMPASSCAL_DATA_DIR", "XDG_DATA_HOME") if os.environ.get(v)), "home directory")
        why = "a file is in the way" if isinstance(e, (FileExistsError, NotADirectoryError)) else e.strerror
        _fail(f"{source}: cannot use {e.filename} as the directory of the SQLite database: {why}")
    shown = _shown_url(url)
    try:
        engine = make_engine(url)
        try:
            upgrade(engine)
        finally:
            engine.dispose()
    except (ArgumentError, ImportError) as e:
        _fail(f"COMPASSCAL_DATABASE_URL={shown}: not a database URL this installation can use "
              f"({' '.join(str(e).split())}); e.g. postgresql://user:password@host:5432/compasscal")
    except (OperationalError, InterfaceError) as e:
        _fail(f"database {shown}: cannot connect: {' '.join(str(e.orig).split())}")
    return shown


@app.command(cls=_Command)
def simulate(
    output: Path = typer.Option(..., "-o", "--output", help="Recording CSV to write (RECORDING.md format)."),
    unit: UnitKind = typer.Option(UnitKind.random, help="The paper's reference unit or a random production unit."),
    seed: int = typer.Option(0, min=0, help="Random seed (unit and noise), >= 0."),
    noise: Optional[float] = typer.Option(None, help="Magnetometer noise, LSB, >= 0 (default: 3 for the reference unit, the unit's own for random)."),
    inclination: float = typer.Option(55.0, help="Field inclination I, deg, -90 to 90."),
    declination: float = typer.Option(23.0, help="Field declination D from the table's zero mark, deg, -360 to 360."),
    base_tilt: tuple[float, float] = typer.Option((0.0, 0.0), metavar="<x> <y>", help="Base tilt about x and about y, deg."),
    samples: int = typer.Option(CalibrateParams().samples, help="Samples per pose."),
) -> None:
    """Simulate a unit on an ideal table running the calibration poses; writes the recording and its truth."""
    from drivers.sim.config import FULL_SCALE_LSB

    # (1e30 wrote a file every fit then refused as "beyond any sensor's reading")
    if noise is not None and not 0 <= noise <= FULL_SCALE_LSB:
        _fail(f"--noise {noise:g}: give 0 to {FULL_SCALE_LSB:g} LSB (the wire's full scale)")
    # (an inclination of 200 is the field of -20 at D + 180, which --truth then scored 180 deg off; nan crashed)
    if not -90.0 <= inclination <= 90.0:
        _fail(f"--inclination {inclination:g}: the inclination is -90 to 90 deg (positive: the field points down)")
    if not -360.0 <= declination <= 360.0:
        _fail(f"--declination {declination:g}: give -360 to 360 deg")
    if not all(-10.0 <= t <= 10.0 for t in base_tilt):
        _fail(f"--base-tilt {base_tilt[0]:g} {base_tilt[1]:g}: a base tilt is a small angle, -10 to 10 deg")
    _output_file(output, "--output")
    truth = output.with_suffix(".truth.json")
    _output_file(truth, "--output (its .truth.json)")
    rng = np.random.default_rng(seed)
    u = reference_unit(3.0 if noise is None else noise, 4.0) if unit is UnitKind.reference else random_unit(rng, mag_noise_lsb=noise)
    world = World(inclination, declination, TableGeometry(base_tilt_deg=base_tilt))
    try:
        poses = calibration_poses(CalibrateParams(samples=samples))
    except ValidationError as e:
        _fail(f"--samples {samples}: {e.errors()[0]['msg']}")
    rec = simulate_recording(u, poses, world, rng=rng, meta={"procedure": "calibrate", "seed": str(seed)})
    _write(output, format_recording(rec))
    _write(truth, json.dumps(truth_json(u, world), indent=2))
    cost = plan_cost(poses)
    console.print(f"wrote {output} ({len(rec)} samples, {cost.positions} poses, {cost.total_s:.1f} s of table time) "
                  f"and the true parameters to {truth}")


@app.command(cls=_Command)
def fit(
    recording: Path = typer.Argument(..., exists=True, dir_okay=False, help="Recording: RECORDING.md CSV, a foreign format the importers read (e.g. .mat, .hdf5), or any file with --mapping."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Calibration JSON to write."),
    method: Method = typer.Option(METHODS[0], help="Calibration method."),  # type: ignore[valid-type]
    skip_bad_rows: bool = typer.Option(False, help="Drop malformed rows instead of refusing the file."),
    plot: Optional[Path] = typer.Option(None, help="Write a PNG of the staged heading errors and the residuals."),
    truth: Optional[Path] = typer.Option(None, help="A .truth.json from `simulate`: also score against the true unit."),
    mapping: Optional[Path] = typer.Option(None, "--mapping", exists=True, dir_okay=False, help=MAPPING_HELP),
) -> None:
    """Calibrate from a recording; print the paper's tables, uncertainties and staged heading errors."""
    _output_file(output, "--output")
    _plot_file(plot)
    truth_data = _read_truth(truth, per_slot=False)[0] if truth is not None else None
    rec = _read_recording(recording, mapping=mapping, skip_bad_rows=skip_bad_rows)
    if truth_data is not None and truth_data.get("serial") and rec.serial and truth_data["serial"] != rec.serial:
        # (refused, as analyze --calibration refuses another unit's: a note was easy to miss above 19 deg of "error")
        _fail(f"--truth {truth}: the true parameters of unit {truth_data['serial']}, but {recording.name} is of unit "
              f"{rec.serial}; give that unit's .truth.json")
    if skip_bad_rows:
        _note_skipped(rec, recording)
    try:
        cal = fit_recording(rec, method.value)
    except (RecordingError, InsufficientData, ValueError) as e:
        _fail(f"{recording}: {e}")
    print_calibration(cal)
    dropped = cal.quality.get("rejected_rows") or []
    if dropped:  # bad samples the fit rejected on its own (physics.fit): which, and why
        console.print(f"[yellow]{len(dropped)} of {cal.quality.get('samples_total')} rows dropped as bad samples "
                      f"(row = 0-based data row of {recording.name} after its header, blank and comment lines "
                      f"not counted):[/]")
        for row in dropped[:20]:  # as the file counts its rows, the malformed ones skipped included
            console.print(f"  row {row['row']} (t {row['t']:g} s, step {escape(row['step'])}): "
                          f"{escape(row['reason'])}")
        if len(dropped) > 20:
            console.print(f"  ... and {len(dropped) - 20} more (all listed in the calibration JSON, quality.rejected_rows)")
    if truth_data is not None:
        print_truth(cal, truth_data)
    if output is not None:
        _write(output, json.dumps(json_safe(cal.to_json()), indent=2))  # (strict JSON: NaN as null)
        console.print(f"calibration written to {output}")
    if plot is not None:
        from service.plots import calibration_figure
        calibration_figure(rec, cal, plot)
        console.print(f"plot written to {plot}")


@app.command(cls=_Command)
def convert(
    recording: Path = typer.Argument(..., exists=True, dir_okay=False, help="Recording: a foreign format the importers read (e.g. .mat, .hdf5), or any file with --mapping."),
    output: Path = typer.Option(..., "-o", "--output", help="Recording CSV to write (RECORDING.md format)."),
    mapping: Optional[Path] = typer.Option(None, "--mapping", exists=True, dir_okay=False, help=MAPPING_HELP),
    skip_bad_rows: bool = typer.Option(False, help="Drop malformed rows instead of refusing the file."),
) -> None:
    """Write any recording the importers read as RECORDING.md CSV, with every conversion in its metadata:
    to upload it to the service (POST /recordings: stored as a run of procedure import, found by serial in
    GET /runs?serial=..., analysed with POST /runs/{id}/analysis; not fitted), to fit it here, or to hand it
    to another tool."""
    _output_file(output, "--output")
    rec = _read_recording(recording, mapping=mapping, skip_bad_rows=skip_bad_rows)
    skipped = rec.meta.get("skipped_rows")
    if skip_bad_rows and skipped not in (None, "0"):  # a conversion like the others, kept in the file
        rec.meta["converted_skipping"] = f"{skipped} malformed row(s) of {recording.name} dropped (--skip-bad-rows)"
    _write(output, format_recording(rec))
    console.print(f"wrote {output} ({len(rec)} samples{', table angles' if rec.has_angles else ', no table angles'}"
                  f"{', accelerometer' if rec.acc is not None else ''}{', temperature' if rec.temp_c is not None else ''})")


def print_calibration(cal: Calibration) -> None:
    """Print the paper's Table 1 and Table 2 with 1-sigma, the field, and the staged heading errors."""
    from service.web import calibration_tables, pm  # the same rows the web pages and certificates show

    sig = cal.sigma
    console.print(f"[bold]{cal.serial or 'unit'}[/]: method [bold]{cal.method}[/]")
    tables = calibration_tables(cal)
    t1 = Table(title="Table 1: angles between sensor and body axes (deg)")
    for c in ("axis", "x_b", "y_b", "z_b"):
        t1.add_column(c, justify="right" if c != "axis" else "left")
    for row in tables["table1"]:
        t1.add_row(*row)
    console.print(t1)
    t2 = Table(title="Table 2: sensitivities and biases (LSB)")
    for c in ("axis", "sensitivity k", "bias b", "residual rms"):
        t2.add_column(c, justify="right")
    for row in tables["table2"]:
        t2.add_row(*row)
    console.print(t2)
    he = cal.quality.get("heading_error_deg", {})
    if not np.isfinite(cal.inclination_deg):  # a method of the magnetometer alone, without table angles
        console.print("field: not determined (no table angles); no level turn to give staged heading errors")
        for note in cal.notes:
            console.print(f"[dim]note: {escape(note)}[/]")
        return
    console.print(f"field: I = {pm(cal.inclination_deg, sig.get('inclination_deg'), 4)} deg, "
                  f"D = {pm(cal.declination_deg, sig.get('declination_deg'), 4)} deg; "
                  f"base tilt (about x, about y) = {cal.base_tilt_deg[0]:.4f}, {cal.base_tilt_deg[1]:.4f} deg")
    t3 = Table(title="Staged heading error on the recording's level turn (max |error| and RMS, deg; Fig. 5)")
    labels = {"raw": "raw", "bias": "bias removed", "sensitivity": "+ sensitivity", "full": "+ non-orthogonality (full)",
              "tilted_full": "full, tilted poses (|pitch|, |roll| <= 60)"}
    t3.add_column("stage")
    t3.add_column("max error", justify="right")
    t3.add_column("RMS", justify="right")
    rms = cal.quality.get("heading_error_rms_deg") or {}  # (a calibration stored before it was kept has none)
    for key, label in labels.items():
        if he.get(key) is not None:
            t3.add_row(label, f"{he[key]:.4f}", f"{rms[key]:.4f}" if rms.get(key) is not None else "-")
    console.print(t3)
    if cal.heading_model:
        console.print(f"heading model: {escape(str(cal.heading_model))}")
    for note in cal.notes:
        console.print(f"[dim]note: {escape(note)}[/]")


def print_truth(cal: Calibration, truth: dict[str, object]) -> None:
    """Score the calibration against the true unit of a simulation."""
    unit, world = truth_from_json(truth)
    s = truth_summary(cal, unit, world)
    st = staged_truth_errors(cal, unit, world)
    console.print("against the true unit: heading error max {level_max:.4f} deg level, {tilted_max:.4f} deg at pitch and roll "
                  "up to 60 deg; staged (level) ".format(**s)
                  + ", ".join(f"{k} {v:.3f}" for k, v in st.items()))


def _read_recording(path: Path, mapping: Optional[Path] = None, skip_bad_rows: bool = False) -> Recording:
    """A recording from a file: RECORDING.md CSV, a foreign format, or any file with a mapping
    (service.imports); errors end the command naming the file and the line, column or key."""
    from service.imports import read_recording_file

    try:
        return read_recording_file(path, mapping=mapping, skip_bad_rows=skip_bad_rows)
    except (ValueError, OSError) as e:  # RecordingError, undecodable text, unreadable file
        msg = str(e)
        _fail(msg if msg.startswith(f"{path.name}:") else f"{path}: {msg}")  # the importers name the file already
    raise AssertionError  # not reached: _fail exits


def _read_json(path: Path, option: str) -> Any:
    """A JSON file given as an option; errors end the command naming the option, the file and the line."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        _fail(f"{option} {path}: not JSON: line {e.lineno}, column {e.colno}: {e.msg}")
    except (ValueError, OSError) as e:  # missing, a directory, unreadable, not UTF-8
        _fail(f"{option} {path}: {getattr(e, 'strerror', None) or e}")


def _read_truth(path: Path, per_slot: bool) -> list[dict[str, Any]]:
    """The true units of ``--truth``, checked before any table time is spent on them: ``per_slot`` a
    list by slot (what ``sim --truth`` writes), else one unit (``simulate``'s .truth.json, or a list
    of one). A file of another shape ends the command naming what it holds and what was expected."""
    data = _read_json(path, "--truth")
    where = f"--truth {path}"
    if not isinstance(data, (list, dict)):
        _fail(f"{where}: a JSON {type(data).__name__}; expected the true parameters of a unit")
    if per_slot and isinstance(data, dict):
        _fail(f"{where}: a JSON object; expected the list by slot that `sim --truth` writes (one unit's, as "
              "`simulate` writes it, is for `fit --truth`)")
    if not per_slot and isinstance(data, list):
        if len(data) != 1:
            _fail(f"{where}: a list of {len(data)} units (what `sim --truth` writes); expected one unit: "
                  "the .truth.json of `simulate`, or a list of one")
    units = data if isinstance(data, list) else [data]
    for i, unit in enumerate(units):
        item = f"{where}: entry {i}" if isinstance(data, list) else where
        if not isinstance(unit, dict):
            _fail(f"{item}: a JSON {type(unit).__name__}; expected the true parameters of a unit")
        if unit.get("format") == CALIBRATION_FORMAT:  # a calibration scored against itself: 0.0000 deg
            _fail(f"{item}: a calibration (`fit -o`), not the true parameters of a unit; give the .truth.json "
                  "that `simulate` wrote beside the recording")
        try:
            truth_from_json(unit)
        except KeyError as e:
            _fail(f"{item}: no {e.args[0]!r}; expected the true parameters written by `simulate` or `sim --truth`")
        except (TypeError, ValueError, IndexError, AssertionError) as e:
            _fail(f"{item}: not the true parameters of a unit ({e or type(e).__name__})")
    return units


def _read_calibration(path: Path) -> Calibration:
    """A calibration JSON (``fit -o``) as the nominal model; errors name the file and the field."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        _fail(f"{path}: not JSON: line {e.lineno}, column {e.colno}: {e.msg}")
    except (ValueError, OSError) as e:
        _fail(f"{path}: {e}")
    if not isinstance(data, dict):
        _fail(f"{path}: expected a calibration JSON object, got {type(data).__name__}")
    try:
        return Calibration.from_json(data)
    except (ValueError, TypeError, KeyError) as e:
        _fail(f"{path}: {e}")
    raise AssertionError


@app.command(cls=_Command)
def analyze(
    recording: Path = typer.Argument(..., exists=True, dir_okay=False, help="Recording: RECORDING.md CSV, a foreign format the importers read (e.g. .mat, .hdf5), or any file with --mapping."),
    calibration: Optional[Path] = typer.Option(None, "--calibration", exists=True, dir_okay=False, help="The unit's calibration JSON (from `fit -o`): the nominal model the recording's own fit is compared with (shifted parameters are reported)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the analysis JSON here."),
    html: Optional[Path] = typer.Option(None, "--html", help="Write the HTML report (self-contained, plots inline) here."),
    null_sims: int = typer.Option(200, "--null-sims", min=0, help="Simulated null recordings that calibrate the tests' false-alarm rate."),
    seed: Optional[str] = typer.Option(None, help="Seed of the null simulations: an integer >= 0, or several joined by "
                                       "commas (the analysis JSON's \"seed\"); default: the recording's own fingerprint, "
                                       "so that the same recording gives the same analysis here and in the service."),
    alpha: float = typer.Option(0.01, min=1e-6, max=0.5, help="Significance after correction for the number of tests."),
    mapping: Optional[Path] = typer.Option(None, "--mapping", exists=True, dir_okay=False, help=MAPPING_HELP),
    skip_bad_rows: bool = typer.Option(False, help="Drop malformed rows instead of refusing the file (as fit does)."),
) -> None:
    """Find where a recording departs from the nominal model, name the missing physics, and show the
    fit before and after (held out)."""
    seeds = _seed_list(seed)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from physics.discrepancy import analyze as run_analysis

    _output_file(json_out, "--json")
    _output_file(html, "--html")
    rec = _read_recording(recording, mapping=mapping, skip_bad_rows=skip_bad_rows)
    if skip_bad_rows:
        _note_skipped(rec, recording)
    cal = _read_calibration(calibration) if calibration is not None else None
    if cal is not None and cal.serial and rec.serial and cal.serial != rec.serial:
        # another unit's calibration makes every difference between two units a "parameter shift" (as the API says)
        _fail(f"--calibration {calibration}: the calibration of unit {cal.serial}, but {recording.name} is of unit "
              f"{rec.serial}: give one of {rec.serial}'s calibrations")
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f} %"),
                  TimeElapsedColumn(), console=err_console, transient=True) as bar:
        task = bar.add_task("analyse", total=1.0)

        def progress(stage: str, fraction: float) -> None:
            bar.update(task, description=f"analyse: {stage}", completed=max(0.0, min(1.0, float(fraction))))

        try:
            a = run_analysis(rec, cal, alpha=alpha, null_sims=null_sims, seed=seeds, progress=progress)
        except ValueError as e:  # the recording cannot support the analysis (e.g. no static hold): say why
            _fail(f"{recording}: {e}")
    print_analysis(a.result)
    if json_out is not None:
        _write(json_out, json.dumps(a.to_json(), indent=2))
        console.print(f"analysis JSON written to {json_out}")
    if html is not None:
        from service.report import analysis_html

        _write(html, analysis_html(a.result, a.series, f"Discrepancy analysis: {rec.serial or recording.name}"))
        console.print(f"HTML report written to {html}")


def print_analysis(result: dict[str, object]) -> None:
    """The analysis for a terminal: verdict, noise floor, fit before and after, ranked findings with
    their evidence, parameters, heading impact and confusions, and what could not be tested."""
    from rich.markup import escape

    from service.plots import residual_names
    from service.report import model_text, num, parameter_rows, text

    r: dict[str, Any] = dict(result)
    verdict = str(r.get("verdict"))
    color = "red" if verdict == "discrepancy" else "green"
    console.print(f"verdict: [bold {color}]{escape(verdict)}[/] (model {escape(str(r.get('model')))}, {r.get('samples')} samples "
                  f"over {num(r.get('duration_s'), 5)} s, alpha {num(r.get('alpha'), 3)})")
    if r.get("summary"):
        console.print(f"[bold]{escape(text(r.get('summary')))}[/]")
    held = r.get("heldout") or {}
    free = r.get("model") == "attitude_free"
    t = Table(title="Noise floor and fit (LSB)")
    t.add_column("")
    for name in ("m_x", "m_y", "m_z"):  # the noise is per axis; without angles the residual is |m|'s (first column)
        t.add_column(name, justify="right")
    rows = [("noise floor (1 sigma)", r.get("noise_floor_lsb"), 3), ("noise slow part: AR(1) phi", r.get("noise_ar1"), 3),
            ("rms before (in-sample)", r.get("residual_rms_before_lsb"), 4),
            ("rms after (in-sample)", r.get("residual_rms_after_lsb"), 4),
            ("rms before (held out)", held.get("rms_before_lsb"), 4),
            ("rms after (held out)", held.get("rms_after_lsb"), 4)]
    names = residual_names(r)
    for k, (label, vals, digits) in enumerate(rows):
        v = list(vals) if isinstance(vals, (list, tuple)) else []
        cells = [num(v[i] if i < len(v) else None, digits) for i in range(3)]
        if free and k >= 2:  # residuals of the field magnitude (and the dip), not of the axes
            cells = [f"{n} {c}" if n else "" for n, c in zip(names, cells)]
        t.add_row(escape(label), *cells)
    console.print(t)
    he = r.get("heading_error_deg") or {}
    console.print(f"held-out improvement: [bold]{num(held.get('improvement_pct'), 3)} %[/] "
                  f"({escape(str(held.get('scheme', 'scheme not given')))})")
    if all(he.get(k) is None for k in ("rms_before", "rms_after", "before", "after")):
        # (it printed "RMS - deg before, - deg after" for a recording that has no heading reference)
        console.print("level heading error: not available (no level holds with a heading reference)")
    else:
        console.print(f"level heading error: RMS {num(he.get('rms_before'), 3)} deg before, {num(he.get('rms_after'), 3)} "
                      f"deg after the fitted effects; maximum {num(he.get('before'), 3)} before, {num(he.get('after'), 3)} after"
                      + (f"; the readings' noise alone makes about {num(he['noise_rms'], 2)} deg RMS"
                         if he.get("noise_rms") is not None else ""))
    findings = r.get("findings") or []
    if not findings:
        console.print("findings: none beyond the noise")
    for rank, f in enumerate(findings, start=1):
        console.print(f"[bold]{rank}. {escape(str(f.get('effect')))}[/]: statistic {num(f.get('statistic'))} (df {num(f.get('df'))}), "
                      f"p {num(f.get('p_value'), 3)}, adjusted {num(f.get('p_adjusted'), 3)}; heading impact "
                      f"{num(f.get('heading_impact_deg'), 3)} deg")
        console.print(f"   model: {escape(model_text(f))}")
        for name, value in parameter_rows(f):
            console.print(f"   {escape(name)} = {escape(value)}")
        if f.get("where"):
            console.print(f"   where: {escape(text(f.get('where')))}")
        if f.get("explanation"):
            console.print(f"   {escape(text(f.get('explanation')))}")
        if f.get("confusable_with"):
            console.print(f"   confusable with {escape(', '.join(str(x) for x in f['confusable_with']))}: "
                          f"{escape(text(f.get('separating_experiment') or 'no separating experiment named'))}")
    untestable = r.get("untestable") or []
    if untestable:
        console.print("untestable on this recording:")
        for u in untestable:
            console.print(f"   {escape(str(u.get('effect')))}: {escape(text(u.get('reason')))}")
    for note in r.get("notes") or []:
        console.print(f"[dim]note: {escape(text(note))}[/]")


def output_names(serials: dict[int, str]) -> tuple[dict[int, str], list[str]]:
    """The name each slot's files (``<name>.csv``, ``.cal.json``, ``.png``) take in the output directory,
    and one note per slot not named by its serial. A serial that cannot name a file (the serial rule of
    service.identity: no '/', so "../evil/SN 1" would write outside the directory) gives ``slot<N>``;
    a name two slots would share gets ``-slot<N>`` on each, so neither overwrites the other."""
    from service.identity import check_serial

    names: dict[int, str] = {}
    notes: list[str] = []
    for slot, serial in sorted(serials.items()):
        try:
            names[slot] = check_serial(serial)
        except ValueError as e:
            names[slot] = f"slot{slot}"
            notes.append(f"slot {slot}: its unit's serial {serial!r} cannot name a file ({e}); "
                         f"its files are named slot{slot}.*")
    shared = {name for name, n in Counter(names.values()).items() if n > 1}
    for name in sorted(shared):
        slots = [slot for slot in sorted(names) if names[slot] == name]
        for slot in slots:
            names[slot] = f"{name}-slot{slot}"
        notes.append(f"slots {', '.join(map(str, slots))}: their units report the same serial {name}; their files are "
                     f"named " + ", ".join(f"{names[slot]}.*" for slot in slots))
    return names, notes


async def _calibrate_station(modbus: str, compasses: list[str], out: Path, time_scale: float, params: dict[str, object],
                             truth: list[dict[str, object]] | None, evaluate: bool) -> int:
    """Calibrate every unit of a station with a progress bar, write recordings and calibrations to
    ``out``, print the tables; optionally check each calibration on the table and against the truth.
    Returns the number of units that failed."""
    import asyncio
    import signal

    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from drivers.station import open_station
    from procedures.engine import RecordingSink, run_procedure, table_time_note
    from procedures import events
    from procedures.steps import Acquire, Compute
    from service.plots import calibration_figure

    out.mkdir(parents=True, exist_ok=True)
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f} %"),
                  TextColumn("{task.fields[info]}"), TimeRemainingColumn(), console=console, transient=False) as bar:
        task = bar.add_task("calibrate", total=100.0, info="")

        def on_event(e: events.Event) -> None:
            if isinstance(e, events.Progress):
                bar.update(task, completed=e.percent,
                           info=f"table {e.table_s:.0f} s, {e.samples} samples, ~{_wall_left(e, time_scale):.0f} s left")
            elif isinstance(e, events.StepStarted) and isinstance(e.step, Acquire):
                bar.update(task, description=f"calibrate: {e.step.step}")
            elif isinstance(e, events.StepStarted) and isinstance(e.step, Compute):
                bar.update(task, description=f"calibrate: computing the {e.step.label}")
            elif isinstance(e, events.StepWarning):  # e.g. bad samples flagged: said as it happens
                bar.console.print(f"[yellow]warning:[/] {escape(e.warning)}")

        # Ctrl-C or SIGTERM (a terminal closed, a service manager): the run is aborted as by an operator,
        # the axes stopped and every sample kept (SIGTERM had killed the process with an axis still turning)
        engines: list[Any] = []
        interrupted: list[str] = []
        names: dict[int, str] = {}
        name_notes: list[str] = []

        def name_files(engine: Any) -> None:
            """The calibration's engine, before it records anything: its files named safely in ``out``."""
            engines.append(engine)
            if isinstance(engine.sink, RecordingSink):  # it names them by serial, whatever the unit reports
                chosen, notes = output_names(engine.serials)
                names.update(chosen)
                name_notes.extend(notes)
                engine.sink.names = names

        current = asyncio.current_task()

        def interrupt(name: str) -> None:
            interrupted.append(name)
            if engines:
                engines[-1].abort(f"interrupted by {name}")
            elif current is not None:
                current.cancel()  # nothing has moved yet
        loop = asyncio.get_running_loop()
        stops = (signal.SIGINT, signal.SIGTERM)
        for sig in stops:
            loop.add_signal_handler(sig, interrupt, sig.name)
        try:
            async with open_station(modbus, compasses, time_scale=time_scale) as station:
                result, serials, sink = await run_procedure(station, "calibrate", params, out_dir=out, on_event=on_event,
                                                            engine_hook=name_files)
                # the bar's last line says how it ended, not the time it had left ("failed ... ~16 s left")
                bar.update(task, description=f"calibrate: {result.state.value}", info=f"{result.samples} samples kept")
                check = None
                if evaluate and result.outcome is not None and not interrupted:
                    cals = {slot: r["calibration"].to_json() for slot, r in result.outcome.results.items() if "calibration" in r}
                    if cals:
                        eval_task = bar.add_task("evaluate", total=100.0, info="")

                        def on_evaluate_event(e: events.Event) -> None:
                            if isinstance(e, events.Progress):
                                bar.update(eval_task, completed=e.percent)

                        check, _, _ = await run_procedure(station, "evaluate", {"calibrations": cals}, on_event=on_evaluate_event,
                                                          engine_hook=engines.append)
        except asyncio.CancelledError:
            if not interrupted:
                raise
            _fail(f"interrupted by {interrupted[0]} before the run began: nothing moved, nothing recorded")
        finally:
            for sig in stops:
                loop.remove_signal_handler(sig)
    console.print(f"run {result.state.value}" + (f": {escape(str(result.reason))}" if result.reason else "")
                  + f" after {result.table_seconds:.1f} s of table time (the plan's nominal {result.plan_seconds:.1f} s "
                  + f"from where the table stood{', before the adaptive poses' if params.get('adaptive') else ''}), "
                  + f"{result.samples} samples kept")
    for note in name_notes:
        _note(note)
    said = table_time_note(result, bool(params.get("adaptive")), time_scale)
    if said:
        text, mismatch = said
        _note(f"{text}: give --control (it tells the scale) or --time-scale (now --time-scale {time_scale:g})"
              if mismatch else text)
    for slot in sorted(serials):
        if slot in sink.parts:
            console.print(f"slot {slot} ({escape(str(serials[slot]))}): recording {escape(str(sink.path(slot)))}")
    if interrupted:  # the shell's convention: 128 + the signal's number
        err_console.print(f"interrupted by {interrupted[0]}: the axes were stopped and the samples so far kept")
        raise typer.Exit(code=128 + getattr(signal, interrupted[0]).value)
    if result.outcome is None:
        return len(compasses)
    failed = 0
    for slot, r in sorted(result.outcome.results.items()):
        if "calibration" not in r:
            err_console.print(f"[bold red]slot {slot} ({escape(str(serials.get(slot)))}): {escape(str(r.get('error')))}[/]")
            failed += 1
            continue
        cal = r["calibration"]
        path, figure = out / f"{names[slot]}.cal.json", out / f"{names[slot]}.png"
        _write(path, json.dumps(json_safe(cal.to_json()), indent=2))
        print_calibration(cal)
        calibration_figure(sink.recording(slot), cal, figure)
        console.print(f"calibration written to {path}, plot to {figure}")
        if "precision" in cal.quality:
            pr = cal.quality["precision"]
            colour = "green" if pr["met"] else "yellow"
            # the sentence itself is among the calibration's notes printed above; here what to do next
            # the budget counts the poses' nominal seconds, which the measured table time above exceeds a little
            spent = f"{pr['table_s']:.0f} s of the {pr['budget_s']:g}-s budget (nominal), poses added: {pr['added_poses']}"
            need = needed_budget_s(pr)
            said = (f"targets met after {spent}" if pr["met"] else f"targets not met: the budget ended after {spent}"
                    + (f"; run again with --budget {need:.0f} to reach them" if need is not None else ""))
            console.print(f"[{colour}]adaptive: {said}[/]")
        if check is not None and check.outcome is not None and slot in check.outcome.results:
            ev = check.outcome.results[slot]
            console.print(f"evaluate on the table: heading error max {ev['level_max_deg']:.4f} deg level, "
                          f"{ev['tilted_max_deg']:.4f} deg at pitch and roll up to 60 deg (each pose's own noise about "
                          f"{ev['level_noise_deg']:.4f} and {ev['tilted_noise_deg']:.4f} deg)")
        if truth is not None and slot < len(truth):
            print_truth(cal, truth[slot])
    return failed


def _station_urls(modbus: str, compasses: list[str]) -> None:
    """Refuse, before connecting anything, a table or compass URL the drivers cannot use."""
    import serial

    from drivers.modbus import BusURL

    try:
        BusURL.parse(modbus)
    except ValueError as e:
        _fail(f"--modbus {modbus}: {e}; expected tcp://HOST:PORT, rtu+tcp://HOST:PORT, serial:///dev/ttyX?baud=N "
              "or a device path")
    for url in compasses:
        try:
            serial.serial_for_url(url, do_not_open=True)  # checks the URL's scheme without opening anything
        except ValueError as e:
            _fail(f"--compass {url}: {e}; expected a device path or socket://HOST:PORT")
    for url, n in Counter(compasses).items():
        if n > 1:  # two slots cannot read one compass (the API refuses it too)
            slots = [str(i) for i, u in enumerate(compasses) if u == url]
            _fail(f"--compass {url}: compass URL given for two slots ({' and '.join(slots)}); give each slot its own compass")


def _procedure_params(procedure: str, parameters: dict[str, Any]) -> dict[str, Any]:
    """The procedure's own validation, before connecting the station: a bad value names its option."""

    from procedures.calibrate import PROCEDURES

    try:
        PROCEDURES[procedure].validate(parameters)
    except ValidationError as e:
        err = e.errors()[0]
        field = ".".join(str(x) for x in err["loc"])
        if not field:  # a rule across options (e.g. --adaptive needs the joint method): its message names them
            msg = str(err["msg"]).removeprefix("Value error, ")
            _fail(msg.replace("budget_s: ", "--budget: ", 1).replace("adaptive: ", "--adaptive: ", 1))
        option = {"budget_s": "budget"}.get(field, field)
        _fail(f"--{option.replace('_', '-')} {err.get('input')}: {err['msg']}")
    return parameters


def _run(coro: object) -> int:
    """Run a station coroutine; driver and network errors end the command with a clear message."""
    import asyncio

    from drivers import DriverError
    try:
        return asyncio.run(coro)  # type: ignore[arg-type]
    except (DriverError, OSError) as e:
        _fail(f"station: {e}")
    return 1


def _control_time_scale(url: str, given: float | None) -> float:
    """The time scale a simulated station reports on its control port; a --time-scale that says
    otherwise is refused (the recording's t would be neither table nor wall time)."""
    import asyncio

    from drivers.sim.station import control_request
    try:
        reported = float(asyncio.run(control_request(url, {"time": None}))["time_scale"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        _fail(f"--control {url}: {e}")
    if given is not None and abs(given - reported) > 1e-9 * reported:
        _fail(f"--time-scale {given:g}: the station at --control {url} runs at time scale {reported:g}")
    return reported


@app.command(cls=_Command)
def calibrate(
    modbus: str = typer.Option(..., metavar="<url>", help="The table's Modbus URL: tcp://HOST:PORT, rtu+tcp://HOST:PORT or a serial device."),
    compass: list[str] = typer.Option(..., metavar="<url>", help="A compass's serial URL (a device path or socket://HOST:PORT); repeat per slot."),
    output: Path = typer.Option(Path("out"), "-o", "--output", help="Directory for recordings and calibrations."),
    time_scale: Optional[float] = typer.Option(None, help="The station's time scale (a simulator run faster than real time; default 1, or what --control reports)."),
    control: Optional[str] = typer.Option(None, metavar="<url>", help="A simulator's control port (the `control` of `compasscal sim`'s line): the time scale is learnt from it, so the recording's t is table time."),
    samples: int = typer.Option(CalibrateParams().samples, help="Samples per pose."),
    method: Method = typer.Option(METHODS[0], help="Calibration method."),  # type: ignore[valid-type]
    adaptive: bool = typer.Option(False, help="After the plan, add poses until every unit's predicted heading error meets the targets (0.02 deg level, 0.05 deg tilted) at 95 % confidence, or --budget ends (joint method)."),
    budget: Optional[float] = typer.Option(None, metavar="<seconds>", help=f"With --adaptive: table seconds the whole calibration may take (default {CalibrateParams().budget_s:g})."),
    evaluate: bool = typer.Option(False, help="Then check each calibration on the table, level and at pitch and roll up to 60 deg."),
    truth: Optional[Path] = typer.Option(None, help="True parameters written by `sim --truth`: also score against them."),
) -> None:
    """Run the calibration procedure on a station (real or simulated) and calibrate every unit in its fixture."""
    _station_urls(modbus, compass)
    _time_scale(time_scale)
    if control is not None:
        time_scale = _control_time_scale(control, time_scale)
    time_scale = 1.0 if time_scale is None else time_scale
    given = {"samples": samples, "method": method.value}
    if adaptive:
        given.update(adaptive=True)
    if budget is not None and not adaptive:  # a budget nothing spends would be a silent no-op
        _fail(f"--budget {budget:g}: only the adaptive extension has a table-time budget; add --adaptive, or leave --budget out")
    if budget is not None:
        given.update(budget_s=budget)
    params = _procedure_params("calibrate", given)
    _output_dir(output, "--output")
    truths = _read_truth(truth, per_slot=True) if truth is not None else None
    failed = _run(_calibrate_station(modbus, compass, output, time_scale, params, truths, evaluate))
    if failed:
        raise typer.Exit(code=1)


@app.command(cls=_Command)
def demo(
    output: Path = typer.Option(Path("out/demo"), "-o", "--output", help="Directory for recordings and calibrations."),
    config: Optional[Path] = typer.Option(None, "--config", help="Station TOML for the simulator (default: the paper's reference unit, 3 LSB noise, base tilt 0.05/-0.03 deg)."),
    time_scale: float = typer.Option(20.0, help="Simulated seconds per wall second."),
    seed: int = typer.Option(1, min=0, help="Noise seed."),
    api: bool = typer.Option(False, "--api", help="Run the service too and calibrate through its REST API (its database: COMPASSCAL_DATABASE_URL, else the SQLite default)."),
    port: int = typer.Option(8000, help="With --api: the service's port."),
    serve_after: bool = typer.Option(True, "--serve/--no-serve", help="With --api: keep serving after the calibration until interrupted."),
) -> None:
    """Start a simulated station in-process, calibrate its unit(s) over the real protocols, check the
    result on the table and against the simulator's truth. With --api, through the REST service."""
    from drivers.sim.config import ConfigError, load_config, reference_config
    from drivers.sim.station import SimStation

    _time_scale(time_scale)
    if api:
        _port(port, "--port")
    else:
        _output_dir(output, "--output")
    try:
        cfg = load_config(config) if config else reference_config(seed)
    except ConfigError as e:
        _fail(str(e))
    cfg.world.time_scale = time_scale

    async def main() -> int:
        async with SimStation(cfg, control_port=None) as st:
            d = st.describe()
            console.print(f"simulated station: table {d['modbus']}, compasses "
                          + ", ".join(f"{c['serial']} at {c['url']}" for c in d["compasses"]) + f", time scale {time_scale:g}")
            return await _calibrate_station(d["modbus"], [c["url"] for c in d["compasses"]], output, time_scale, {},
                                            st.truth(), evaluate=True)

    if api:
        database = _open_database()
        sock = _listen("127.0.0.1", port)
        chosen = os.environ.get("COMPASSCAL_DATABASE_URL") or os.environ.get("COMPASSCAL_DATA_DIR")
        default = "" if chosen else (" (the user's default, shared by every checkout; for one of this checkout's "
                                     "own: make run DB=./compasscal.db, or set COMPASSCAL_DATABASE_URL)")
        console.print(f"database: {database}{default}", soft_wrap=True, markup=False, highlight=False)
        if _run(_api_demo(cfg, sock, serve_after)):
            raise typer.Exit(code=1)
        return
    if _run(main()):
        raise typer.Exit(code=1)


async def _api_demo(cfg: object, sock: socket.socket, keep_serving: bool) -> int:
    """The service's demonstration: a simulated station and the REST service (on ``sock``, listening) in
    one process; a key, the station and a calibration run made through the API as a technician's script would."""
    import asyncio

    import httpx
    import uvicorn
    from rich.progress import BarColumn, Progress, TextColumn

    from drivers.sim.station import SimStation
    from service.app import create_app
    from service.auth import create_key

    from service.db import default_url

    if default_url().startswith("sqlite"):
        _only_service(default_url())
    async with SimStation(cfg, control_port=None) as st:  # type: ignore[arg-type]
        d = st.describe()
        app = create_app()
        port = sock.getsockname()[1]
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                               timeout_graceful_shutdown=SHUTDOWN_GRACE_S))
        serving = asyncio.create_task(server.serve(sockets=[sock]))
        while not server.started:
            if serving.done():
                _fail(f"the service could not start on port {port}")
            await asyncio.sleep(0.05)
        base = f"http://127.0.0.1:{port}"
        with app.state.sessions() as session:
            admin, operator = create_key(session, "demo-admin", "admin"), create_key(session, "demo-operator", "operator")
        console.print(f"service at {base} (OpenAPI at {base}/docs); simulated station: table {d['modbus']}, "
                      f"compass {d['compasses'][0]['url']}")
        async with httpx.AsyncClient(base_url=base, timeout=30) as http:
            station = {"name": "demo", "modbus": d["modbus"], "compasses": [c["url"] for c in d["compasses"]],
                       "time_scale": st.clock.time_scale}
            r = await http.put("/stations/demo", json=station, headers={"X-API-Key": admin})
            r.raise_for_status()
            r = await http.post("/runs", json={"station": "demo", "procedure": "calibrate"}, headers={"X-API-Key": operator})
            r.raise_for_status()
            run = r.json()
            console.print(f"POST /runs -> {r.status_code}: run {run['id']} {run['status']}")
            state = "?"
            with Progress(TextColumn("run {task.fields[run]}"), BarColumn(), TextColumn("{task.percentage:>5.1f} %"),
                          console=console) as bar:
                task = bar.add_task("", total=100.0, run=run["id"])
                async with http.stream("GET", f"/runs/{run['id']}/events", headers={"X-API-Key": operator}) as events:
                    kind = ""
                    async for line in events.aiter_lines():
                        if line.startswith("event:"):
                            kind = line.split(":", 1)[1].strip()
                        elif line.startswith("data:"):
                            data = json.loads(line.split(":", 1)[1])
                            if kind == "progress":
                                bar.update(task, completed=data["percent"])
                            elif kind == "state":
                                state = data["state"]
            run = (await http.get(f"/runs/{run['id']}", headers={"X-API-Key": operator})).json()
            console.print(f"run {run['id']} {state}" + (f": {escape(str(run.get('reason')))}" if run.get("reason") else ""))
            if state != "completed":
                return 1
            serial = d["compasses"][0]["serial"]
            cal = (await http.get(f"/devices/{serial}/calibrations/current", headers={"X-API-Key": operator})).json()
            print_calibration(Calibration.from_json(cal))
            console.print(f"verdict [bold]{cal['verdict']}[/]" + ("".join(f"\n  {escape(str(x))}" for x in cal["reasons"])))
            print_truth(Calibration.from_json(cal), st.truth()[0])
        console.print(f"calibration history: {base}/devices/{serial}/calibrations ; current: {base}/devices/{serial}/calibrations/current")
        console.print(f"web pages: {base}/ui/runs/{run['id']} , {base}/ui/devices/{serial} (log in with the key below)")
        console.print(f"operator key (X-API-Key header): {operator}")
        if keep_serving:
            console.print("serving until interrupted (Ctrl-C)")
            await serving
        else:
            server.should_exit = True
            await serving
    return 0


@app.command(cls=_Command)
def sim(
    config: Optional[Path] = typer.Option(None, "--config", help=escape("Station TOML (world, table, [[unit]], [[effect]], [[fault]]). Default: one random unit on an ideal table.")),
    modbus_port: int = typer.Option(0, help="Modbus TCP port of the table (0: any free port)."),
    compass_tcp_port: Optional[int] = typer.Option(None, help="Serve compasses on TCP from this port (slot i on port+i; 0: any free ports) instead of ptys."),
    control_port: int = typer.Option(0, help="TCP port of the control channel (faults, the simulated time; 0: any free port)."),
    time_scale: Optional[float] = typer.Option(None, help="Run this many times faster than real time (overrides the config)."),
    seed: Optional[int] = typer.Option(None, min=0, help="Seed of the random unit and the noise (overrides the config)."),
    truth: Optional[Path] = typer.Option(None, help="Also write the true parameters of every unit (JSON list, slot order) here."),
    host: str = typer.Option("127.0.0.1", help="Address to serve on (0.0.0.0 for other machines)."),
) -> None:
    """Run a simulated station until interrupted. Prints one JSON line saying where to connect, then nothing."""
    import asyncio
    import signal
    import sys

    from drivers.sim.config import ConfigError, default_config, load_config
    from drivers.sim.station import SimStation

    _port(modbus_port, "--modbus-port", any_free=True)
    _port(compass_tcp_port, "--compass-tcp-port", any_free=True)
    _port(control_port, "--control-port", any_free=True)
    _output_file(truth, "--truth")
    _time_scale(time_scale)
    try:
        cfg = load_config(config) if config else default_config(seed)
    except ConfigError as e:
        _fail(str(e))
    if time_scale is not None:
        cfg.world.time_scale = time_scale
    if seed is not None:
        cfg.world.seed = seed
    _port_free(host, modbus_port, "--modbus-port")
    _port_free(host, control_port, "--control-port")
    if control_port and control_port == modbus_port:
        _fail(f"--control-port {control_port}: the table's --modbus-port; give each its own")
    if compass_tcp_port:
        if compass_tcp_port + len(cfg.unit) - 1 > 65535:
            _fail(f"--compass-tcp-port {compass_tcp_port}: slot i serves on port {compass_tcp_port}+i, past 65535 "
                  f"for {len(cfg.unit)} units")
        for slot in range(len(cfg.unit)):
            _port_free(host, compass_tcp_port + slot, f"--compass-tcp-port {compass_tcp_port} (slot {slot} on port {compass_tcp_port + slot})")

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        async with SimStation(cfg, modbus_port=modbus_port, compass_tcp_port=compass_tcp_port, control_port=control_port,
                              host=host) as station:
            if truth is not None:
                truth.write_text(json.dumps(station.truth(), indent=2))
            sys.stdout.write(json.dumps(station.describe()) + "\n")
            sys.stdout.flush()
            await stop.wait()

    try:
        asyncio.run(main())
    except OSError as e:  # e.g. the port is taken
        _fail(f"cannot start the simulated station: {e}")
    except RuntimeError as e:  # pymodbus's words for a port it cannot listen on (taken since the check above)
        if "listen" not in str(e):
            raise
        _fail(f"--modbus-port {modbus_port}: cannot listen on {host}:{modbus_port}: {e}")


keys_app = typer.Typer(help="API keys (stored hashed; a key is shown once).", no_args_is_help=True, cls=_Group)
db_app = typer.Typer(help="The database (COMPASSCAL_DATABASE_URL, default a SQLite file in the user's data directory).",
                     no_args_is_help=True, cls=_Group)
app.add_typer(keys_app, name="keys")
app.add_typer(db_app, name="db")


@keys_app.command("create", cls=_Command)
def keys_create(
    owner: str = typer.Option(..., help="Who the key belongs to (recorded with every change it makes)."),
    role: str = typer.Option(..., help="viewer (read), operator (runs, batches, prompts) or admin (stations, keys, limits)."),
) -> None:
    """Create an API key; it is printed once, alone on the last line."""
    from service.auth import create_key
    from service.db import make_engine, sessions

    _open_database()
    engine = make_engine()
    try:
        with sessions(engine)() as session:
            key = create_key(session, owner, role)
    except ValueError as e:
        _fail(str(e))
    console.print(f"API key for {escape(owner)} ({escape(role)}); store it now, it cannot be shown again:")
    print(key)


@keys_app.command("list", cls=_Command)
def keys_list() -> None:
    """Every key: id, the characters it starts with, owner, role, revoked (never the key itself)."""
    from rich.table import Table

    from service.auth import list_keys
    from service.db import make_engine, sessions

    _open_database()
    engine = make_engine()
    with sessions(engine)() as session:
        rows = list_keys(session)
        table = Table("id", "starts with", "owner", "role", "revoked", "created")
        for r in rows:
            table.add_row(str(r.id), r.prefix, escape(r.owner), r.role, "yes" if r.revoked else "",
                          r.created_at.strftime("%Y-%m-%d %H:%M"))
    console.print(table)


@keys_app.command("revoke", cls=_Command)
def keys_revoke(
    key: str = typer.Argument(..., metavar="ID|PREFIX", help="The key's id, or the characters it starts with (keys list)."),
) -> None:
    """Revoke a key (audited); services stop accepting it within 10 s."""
    import getpass

    from sqlalchemy import func, select

    from service.auth import Caller, find_key, revoke_key
    from service.db import ApiKey, make_engine, sessions

    _open_database()
    engine = make_engine()
    with sessions(engine)() as session:
        try:
            row = find_key(session, key)
        except (LookupError, ValueError) as e:
            _fail(f"ID|PREFIX: {e.args[0]}")
        if row.revoked:
            _fail(f"ID|PREFIX: key {row.id} ({row.prefix}, {row.owner}) is already revoked")
        revoke_key(session, row, Caller(f"cli:{getpass.getuser()}", "admin"))
        console.print(f"revoked key {row.id} ({row.prefix}, {escape(row.owner)}, {row.role})")
        if row.role == "admin" and not session.scalar(select(func.count()).select_from(ApiKey).where(
                ApiKey.role == "admin", ApiKey.revoked.is_(False))):
            # allowed here (the API refuses it): this command is how an administrator gets back in
            _note("that was the last admin key in force: no one can administer the service over the API until "
                  "`compasscal keys create --owner NAME --role admin` makes another")


@db_app.command("upgrade", cls=_Command)
def db_upgrade() -> None:
    """Bring the database schema to the newest migration (the service also does this on start)."""
    console.print(f"database at the newest migration: {_open_database()}", soft_wrap=True, markup=False, highlight=False)


@app.command(cls=_Command)
def serve(
    host: str = typer.Option("127.0.0.1", help="Address to listen on."),
    port: int = typer.Option(8000, help="Port to listen on."),
    workers: int = typer.Option(1, "--workers", min=1, max=64,
                                help="API processes (more than 1 needs PostgreSQL and a `compasscal worker` per station)."),
    station_worker: Optional[bool] = typer.Option(
        None, "--station-worker/--no-station-worker",
        help="Drive every station from this process (default with one API process; always on SQLite). "
             "Off: each station has its own `compasscal worker --station NAME`."),
) -> None:
    """Run the REST service (OpenAPI at /docs)."""
    import uvicorn

    from service.db import default_url

    _port(port, "--port")
    database = _open_database()
    pg = default_url().startswith("postgresql")
    embedded = (workers == 1) if station_worker is None else station_worker
    if not pg and (workers > 1 or not embedded):
        _fail(f"{'--workers ' + str(workers) if workers > 1 else '--no-station-worker'}: the SQLite default keeps its job "
              "queue in memory, inside the one service process; set COMPASSCAL_DATABASE_URL=postgresql://... for "
              "several API processes and station workers")
    if workers > 1 and embedded:
        _fail("--station-worker with --workers > 1: each API process would drive every station; run one "
              "`compasscal worker --station NAME` per station instead")
    if not pg:
        _only_service(default_url())
    if pg and embedded:  # a station with a worker of its own must not be driven from here too
        import socket

        from service.db import make_engine, sessions
        from service.runtime import other_workers
        from service.worker import served_elsewhere

        engine = make_engine(default_url())
        busy = other_workers(sessions(engine), None, f"{socket.gethostname()}:{os.getpid()}")
        engine.dispose()
        if busy:
            _fail(f"--station-worker: {served_elsewhere(busy)}; or serve with --no-station-worker")
    sock = _listen(host, port)
    console.print(f"database: {database}; {workers} API process(es); stations driven "
                  + ("here" if embedded else "by their `compasscal worker`s"), soft_wrap=True, markup=False, highlight=False)
    os.environ["COMPASSCAL_STATION_WORKER"] = "1" if embedded else "0"  # read by service.app:app_from_env
    # a run's live events stream until the run ends: without a bound, a stop waited for every watcher (a
    # browser on a run page kept the API down, its port held, until the run ended); watchers reconnect
    # with Last-Event-ID
    config = uvicorn.Config("service.app:app_from_env", factory=True, host=host, port=port, workers=workers,
                            timeout_graceful_shutdown=SHUTDOWN_GRACE_S)
    if workers > 1:
        from uvicorn.supervisors import Multiprocess
        Multiprocess(config, sockets=[sock]).run()
    else:
        uvicorn.Server(config).run(sockets=[sock])


@app.command(cls=_Command)
def worker(
    station: list[str] = typer.Option([], "--station", metavar="NAME",
                                      help="The station this worker drives (repeat for several)."),
    analyses: bool = typer.Option(True, "--analyses/--no-analyses",
                                  help="Also compute discrepancy analyses (--no-analyses keeps the PC for its table)."),
) -> None:
    """The station agent: owns the station's table and compasses, takes its runs from the job queue
    (PostgreSQL), publishes their events; first stops the axes and ends what a previous worker left.
    Without --station, a worker of analyses only."""
    import asyncio

    from service.db import default_url
    from service.runtime import DomainError
    from service.worker import serve_worker

    database = _open_database()
    url = default_url()
    if not url.startswith("postgresql"):
        _fail(f"database {database}: a station worker needs PostgreSQL (COMPASSCAL_DATABASE_URL=postgresql://...); "
              "on the SQLite default `compasscal serve` drives the stations itself")
    if not station and not analyses:
        _fail("--station: give a station to drive, or leave --analyses on (a worker with nothing to do)")
    what = [f"station(s) {', '.join(station)}"] if station else []
    console.print(f"database: {database}; worker of {' and '.join(what + (['analyses'] if analyses else []))}",
                  soft_wrap=True, markup=False, highlight=False)
    try:
        asyncio.run(serve_worker(url, list(station), analyses=analyses))
    except DomainError as e:
        _fail(f"--station: {e.detail}")
    except KeyboardInterrupt:
        pass


@app.command(cls=_Command)
def prove(
    n: int = typer.Option(10, "--n", min=0, help="Recordings per catalogue effect (non-centrality log-uniform in 3-300; 0: none)."),
    seed: int = typer.Option(0, min=0, help="Random seed of the whole proof."),
    nulls: Optional[int] = typer.Option(None, "--nulls", min=0, help="Null recordings (default max(3 n, 20))."),
    open_n: int = typer.Option(0, "--open-n", min=0,
                               help="Out-of-catalogue recordings per open-world kind (0: none; see proof.concealments)."),
    open_plan: str = typer.Option("calibrate", "--open-plan",
                                  help="Plan of the open-world cases: calibrate (level turn, calibration sweeps, six "
                                       "accelerometer poses, all in holds), sweeps (the same turns and sweeps "
                                       "continuous) or characterize."),
    open_nulls: int = typer.Option(0, "--open-nulls", min=0,
                                   help="Null recordings drawn as the open-world cases are (their plan and noise)."),
    open_large: int = typer.Option(0, "--open-large", min=0,
                                   help="Large out-of-catalogue departures per open-world kind (non-centrality "
                                        "log-uniform in 300-1e6, scored apart: is the model right to the sample?)."),
    handheld_n: int = typer.Option(0, "--handheld-n", min=0,
                                   help="Hand-held recordings without table angles per out-of-catalogue kind, "
                                        "analysed by the attitude-free model (0: none; see proof.handheld)."),
    handheld_nulls: int = typer.Option(0, "--handheld-nulls", min=0, help="Hand-held recordings without a departure."),
    workers: int = typer.Option(2, "--workers", min=1, help="Processes analysing in parallel."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the score and every case to this JSON file."),
) -> None:
    """The blind proof: recordings of random units on the characterize plan with concealed effects, nulls
    and pairs (and with --open-n, physics outside the catalogue on the calibrate plan; with --handheld-n,
    hand-held recordings without table angles); the analyser sees only the recordings; prints detection,
    false alarms, naming, recovery and the open-world success."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from procedures.calibrate import characterize_plan
    from proof.generator import OPEN_PLANS
    from proof.runner import run_handheld_proof, run_proof
    from proof.score import format_handheld_report, format_report

    if open_plan not in OPEN_PLANS:
        raise typer.BadParameter(f"expected one of {', '.join(OPEN_PLANS)}, got {open_plan!r}", param_hint="--open-plan")
    # any recording on the table (nulls default > 0)
    table = bool(n or nulls is None or nulls or open_n or open_nulls or open_large)
    if not table and not (handheld_n or handheld_nulls):  # (it printed "nothing to prove" and exit 0)
        _fail("--n 0 --nulls 0: nothing to prove; give --n or --nulls > 0 (or --open-n, --open-nulls, --open-large, "
              "--handheld-n or --handheld-nulls)")
    _output_file(json_out, "--json")  # before the minutes of work whose results it keeps
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
                  TimeRemainingColumn(), console=err_console, transient=False) as bar:
        task = bar.add_task("prove", total=None, info="")

        def on_progress(done: int, total: int, kind: str) -> None:
            bar.update(task, completed=done, total=total, info=kind)

        out = run_proof(n, seed, workers, on_progress, plan=characterize_plan(), nulls=nulls, open_n=open_n,
                        open_plan=OPEN_PLANS[open_plan](), open_nulls=open_nulls, open_large=open_large) if table else {}
        if handheld_n or handheld_nulls:
            out["handheld"] = run_handheld_proof(handheld_n, handheld_nulls, seed, workers, on_progress)
    if table:
        console.print(format_report(out["score"]), markup=False, highlight=False, soft_wrap=True)
        console.print(f"{len(out['cases'])} recordings in {out['config']['wall_s']:.0f} s", markup=False, highlight=False)
    if "handheld" in out:
        hh = out["handheld"]
        console.print(format_handheld_report(hh["score"]), markup=False, highlight=False, soft_wrap=True)
        console.print(f"{len(hh['cases'])} hand-held recordings in {hh['config']['wall_s']:.0f} s", markup=False,
                      highlight=False)
    if json_out is not None:
        _write(json_out, json.dumps(out, indent=1))
        console.print(f"score and cases written to {json_out}")


if __name__ == "__main__":
    app()
