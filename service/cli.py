"""The ``compasscal`` command line (typer)."""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from physics.calibration import Calibration, staged_truth_errors, truth_summary
from physics.errorsep import InsufficientData
from physics.fit import METHODS, fit as fit_recording
from physics.recording import RecordingError, format_recording, parse_recording
from physics.sensor import Unit, random_unit, reference_unit
from physics.simulate import World, plan_cost, simulate_recording
from physics.table import TableGeometry
from procedures.calibrate import CalibrateParams, calibration_poses

app = typer.Typer(help="Electronic-compass calibration station.", no_args_is_help=True, add_completion=False,
                  pretty_exceptions_show_locals=False)
console = Console()


class UnitKind(str, Enum):
    reference = "reference"
    random = "random"


Method = Enum("Method", {m.replace("-", "_"): m for m in METHODS}, type=str)  # type: ignore[misc]


def _fail(message: str) -> None:
    console.print(f"[bold red]error:[/] {message}")
    raise typer.Exit(code=2)


def unit_json(unit: Unit, world: World) -> dict[str, object]:
    """The true parameters of a simulated unit and world, to compare a calibration with."""
    def sensor(s: object) -> dict[str, object] | None:
        if s is None:
            return None
        return {"M_o": s.M_o.tolist(), "k": s.k.tolist(), "bias": s.bias.tolist(),  # type: ignore[attr-defined]
                "angles_deg": s.angles_deg.tolist(), "noise_lsb": s.noise_lsb}  # type: ignore[attr-defined]
    return {"serial": unit.serial, "magnetometer": sensor(unit.mag), "accelerometer": sensor(unit.acc),
            "field": {"inclination_deg": world.inclination_deg, "declination_deg": world.declination_deg},
            "base_tilt_deg": list(world.geometry.base_tilt_deg)}


@app.command()
def simulate(
    output: Path = typer.Option(..., "-o", "--output", help="Recording CSV to write (RECORDING.md format)."),
    unit: UnitKind = typer.Option(UnitKind.random, help="The paper's reference unit or a random production unit."),
    seed: int = typer.Option(0, help="Random seed (unit and noise)."),
    noise: Optional[float] = typer.Option(None, help="Magnetometer noise, LSB (default: 3 for the reference unit, the unit's own for random)."),
    inclination: float = typer.Option(55.0, help="Field inclination I, deg."),
    declination: float = typer.Option(23.0, help="Field declination D from the table's zero mark, deg."),
    base_tilt: tuple[float, float] = typer.Option((0.0, 0.0), help="Base tilt about x and about y, deg."),
    samples: int = typer.Option(CalibrateParams.samples, help="Samples per pose."),
) -> None:
    """Simulate a unit on an ideal table running the calibration poses; writes the recording and its truth."""
    rng = np.random.default_rng(seed)
    u = reference_unit(3.0 if noise is None else noise, 4.0) if unit is UnitKind.reference else random_unit(rng, mag_noise_lsb=noise)
    world = World(inclination, declination, TableGeometry(base_tilt_deg=base_tilt))
    try:
        poses = calibration_poses(CalibrateParams(samples=samples))
    except ValueError as e:
        _fail(str(e))
    rec = simulate_recording(u, poses, world, rng=rng, meta={"procedure": "calibrate", "seed": str(seed)})
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(format_recording(rec))
    truth = output.with_suffix(".truth.json")
    truth.write_text(json.dumps(unit_json(u, world), indent=2))
    cost = plan_cost(poses)
    console.print(f"wrote {output} ({len(rec)} samples, {cost.positions} poses, {cost.total_s:.1f} s of table time) "
                  f"and the true parameters to {truth}")


@app.command()
def fit(
    recording: Path = typer.Argument(..., exists=True, dir_okay=False, help="Recording CSV (RECORDING.md)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Calibration JSON to write."),
    method: Method = typer.Option(METHODS[0], help="Calibration method."),  # type: ignore[valid-type]
    skip_bad_rows: bool = typer.Option(False, help="Drop malformed rows instead of refusing the file."),
    plot: Optional[Path] = typer.Option(None, help="Write a PNG of the staged heading errors and the residuals."),
    truth: Optional[Path] = typer.Option(None, help="A .truth.json from `simulate`: also score against the true unit."),
) -> None:
    """Calibrate from a recording; print the paper's tables, uncertainties and staged heading errors."""
    try:
        rec = parse_recording(recording.read_text(encoding="utf-8"), skip_bad_rows=skip_bad_rows)
        cal = fit_recording(rec, method.value)
    except (RecordingError, InsufficientData, ValueError) as e:
        _fail(f"{recording}: {e}")
    print_calibration(cal)
    if truth is not None:
        print_truth(cal, json.loads(truth.read_text()))
    if output is not None:
        output.write_text(json.dumps(cal.to_json(), indent=2))
        console.print(f"calibration written to {output}")
    if plot is not None:
        from service.plots import calibration_figure
        calibration_figure(rec, cal, plot)
        console.print(f"plot written to {plot}")


def _pm(value: float, sigma: object, digits: int) -> str:
    s = "" if sigma is None or not np.isfinite(float(sigma)) else f" ± {float(sigma):.{digits}f}"  # type: ignore[arg-type]
    return f"{value:.{digits}f}{s}"


def print_calibration(cal: Calibration) -> None:
    """Print the paper's Table 1 and Table 2 with 1-sigma, the field, and the staged heading errors."""
    sig = cal.sigma
    console.print(f"[bold]{cal.serial or 'unit'}[/]: method [bold]{cal.method}[/]")
    t1 = Table(title="Table 1: angles between sensor and body axes (deg)")
    t1.add_column("axis")
    for b in ("x_b", "y_b", "z_b"):
        t1.add_column(b, justify="right")
    ang = cal.mag.angles_deg
    s_ang = np.asarray(sig.get("angles_deg", np.full((3, 3), np.nan)), dtype=float)
    for i, name in enumerate(("x_m", "y_m", "z_m")):
        t1.add_row(name, *[_pm(ang[i, j], s_ang[i, j], 4) for j in range(3)])
    console.print(t1)
    t2 = Table(title="Table 2: sensitivities and biases (LSB)")
    for c in ("axis", "sensitivity k", "bias b", "residual rms"):
        t2.add_column(c, justify="right")
    s_k = np.asarray(sig.get("k", np.full(3, np.nan)), dtype=float)
    s_b = np.asarray(sig.get("bias", np.full(3, np.nan)), dtype=float)
    rms = cal.quality.get("residual_rms_lsb", [None] * 3)
    for i, name in enumerate(("x_m", "y_m", "z_m")):
        r = "-" if rms[i] is None else f"{rms[i]:.2f}"
        t2.add_row(name, _pm(cal.mag.k[i], s_k[i], 3), _pm(cal.mag.bias[i], s_b[i], 3), r)
    console.print(t2)
    console.print(f"field: I = {_pm(cal.inclination_deg, sig.get('inclination_deg'), 4)} deg, "
                  f"D = {_pm(cal.declination_deg, sig.get('declination_deg'), 4)} deg; "
                  f"base tilt (about x, about y) = {cal.base_tilt_deg[0]:.4f}, {cal.base_tilt_deg[1]:.4f} deg")
    he = cal.quality.get("heading_error_deg", {})
    t3 = Table(title="Staged heading error on the recording's level turn (max |error|, deg; Fig. 5)")
    labels = {"raw": "raw", "bias": "bias removed", "sensitivity": "+ sensitivity", "full": "+ non-orthogonality (full)",
              "tilted_full": "full, tilted poses (|pitch|, |roll| <= 60)"}
    t3.add_column("stage")
    t3.add_column("max error", justify="right")
    for key, label in labels.items():
        if he.get(key) is not None:
            t3.add_row(label, f"{he[key]:.4f}")
    console.print(t3)
    if cal.heading_model:
        console.print(f"heading model: {cal.heading_model}")
    for note in cal.notes:
        console.print(f"[dim]note: {note}[/]")


def print_truth(cal: Calibration, truth: dict[str, object]) -> None:
    """Score the calibration against the true unit of a simulation."""
    mag = truth["magnetometer"]  # type: ignore[index]
    from physics.sensor import LinearSensor
    true_mag = LinearSensor(np.array(mag["M_o"]), np.array(mag["k"]), np.array(mag["bias"]))  # type: ignore[index]
    acc = truth.get("accelerometer")
    true_acc = None if acc is None else LinearSensor(np.array(acc["M_o"]), np.array(acc["k"]), np.array(acc["bias"]))  # type: ignore[index]
    fld = truth["field"]  # type: ignore[index]
    world = World(fld["inclination_deg"], fld["declination_deg"], TableGeometry(base_tilt_deg=tuple(truth["base_tilt_deg"])))  # type: ignore[index, arg-type]
    unit = Unit(str(truth.get("serial")), true_mag, true_acc)
    s = truth_summary(cal, unit, world)
    st = staged_truth_errors(cal, unit, world)
    console.print("against the true unit: heading error max {level_max:.4f} deg level, {tilted_max:.4f} deg at pitch and roll "
                  "up to 60 deg; staged (level) ".format(**s)
                  + ", ".join(f"{k} {v:.3f}" for k, v in st.items()))


if __name__ == "__main__":
    app()
