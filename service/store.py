"""What the service keeps and how: samples in bulk, devices, calibrations with their verdicts and
the never-overwrite history (a new passing calibration becomes current, the old one superseded).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from physics.calibration import Calibration as PhysCalibration
from physics.recording import Recording
from service.identity import check_serial
from service.db import Calibration, Device, Limit, Run, Sample, SampleExtra
from service.runtime import unit_serial



_SAMPLE_TYPES = ["integer", "integer", "float8", "varchar", *["float8"] * 10]
_SAMPLE_COLS = ("run_id", "slot", "t", "step", "psi_t", "theta_t", "phi_t", "mx", "my", "mz", "ax", "ay", "az", "temp_c")


def insert_samples(session: Session, run_id: int, slot: int, rec: Recording) -> int:
    """Bulk-insert a recording's rows as samples of ``run_id``/``slot`` (not committed).

    PostgreSQL gets COPY and SQLite one executemany of plain tuples: both several times faster than
    ORM or Core inserts of dictionaries, which matters at 20 Hz x units x stations.
    """
    n = len(rec)
    if n == 0:
        return 0
    acc = rec.acc if rec.acc is not None else np.full((n, 3), np.nan)
    temp = rec.temp_c if rec.temp_c is not None else np.full(n, np.nan)
    cols = np.column_stack([rec.t, rec.psi_t, rec.theta_t, rec.phi_t, rec.mag, acc, temp]).tolist()
    rows = [(run_id, slot, c[0], step, *(None if v != v else v for v in c[1:4]), c[4], c[5], c[6],
             *(None if v != v else v for v in c[7:11]))  # NaN (no table angles, accelerometer, temperature) -> NULL
            for c, step in zip(cols, rec.step.tolist())]
    conn = session.connection()
    if conn.dialect.name == "postgresql":
        # binary COPY with declared types: psycopg's C adapters do the conversion
        with conn.connection.cursor() as cur, \
                cur.copy(f"COPY samples ({', '.join(_SAMPLE_COLS)}) FROM STDIN (FORMAT BINARY)") as copy:
            copy.set_types(_SAMPLE_TYPES)
            for row in rows:
                copy.write_row(row)
    else:
        conn.exec_driver_sql(f"INSERT INTO samples ({', '.join(_SAMPLE_COLS)}) VALUES ({', '.join('?' * len(_SAMPLE_COLS))})", rows)
    session.execute(update(Run).where(Run.id == run_id).values(samples_count=Run.samples_count + n))
    for name, values in rec.extra.items():  # an import's extra columns, kept in sample order
        row = session.scalar(select(SampleExtra).where(SampleExtra.run_id == run_id, SampleExtra.slot == slot,
                                                       SampleExtra.name == name))
        if row is None:
            session.add(SampleExtra(run_id=run_id, slot=slot, name=name, values=[str(v) for v in values]))
        else:
            row.values = [*row.values, *(str(v) for v in values)]
    return n


#: How an export names what an imported recording's file said of its identity (run, operator, ...)
#: where the run it became says otherwise.
IMPORTED_PREFIX = "imported_"


def load_recording(session: Session, run: Run, slot: int) -> Recording | None:
    """The samples of one slot of a run as a recording (RECORDING.md metadata from the run)."""
    rows = session.execute(
        select(Sample.t, Sample.step, Sample.psi_t, Sample.theta_t, Sample.phi_t, Sample.mx, Sample.my, Sample.mz,
               Sample.ax, Sample.ay, Sample.az, Sample.temp_c).where(Sample.run_id == run.id, Sample.slot == slot)
        .order_by(Sample.id)).all()
    if not rows:
        return None
    a = np.array([[np.nan if v is None else v for i, v in enumerate(r) if i != 1] for r in rows], dtype=float)
    meta = {k: str(v) for k, v in (run.meta or {}).items() if isinstance(v, (str, int, float))}
    own = {"serial": unit_serial(run, slot), "run_id": str(run.id), "procedure": run.procedure,
           "procedure_version": run.procedure_version, "operator": run.operator, "slot": str(slot)}
    for key, value in own.items():
        # the run's identity wins over an imported file's own lines (an export of run 4 said "run_id: 999",
        # "operator: mallory"), which are kept as what the file said
        said = meta.get(key)
        if said and said != value:
            meta[f"{IMPORTED_PREFIX}{key}"] = said
        meta[key] = value
    if not meta["serial"]:  # no unit's serial known: no "# serial:" line (it was written empty)
        del meta["serial"]
    else:
        try:
            check_serial(meta["serial"])
        except ValueError:  # a unit's answer that is no serial number ("SN B/1"): said as what it reported,
            meta["reported_serial"] = meta.pop("serial")  # so the file uploads again (its "serial" was refused)
    typed = str((run.serials or {}).get(str(slot)) or "")
    if typed and typed != meta.get("serial"):  # the serial typed for a unit that reported another, kept beside it
        meta["typed_serial"] = typed
    extra = {e.name: list(e.values) for e in session.scalars(
        select(SampleExtra).where(SampleExtra.run_id == run.id, SampleExtra.slot == slot).order_by(SampleExtra.id))
        if len(e.values) == len(rows)}
    return Recording.from_arrays(t=a[:, 0], step=[r[1] for r in rows], psi_t=a[:, 1], theta_t=a[:, 2], phi_t=a[:, 3],
                                 mag=a[:, 4:7], acc=a[:, 7:10], temp_c=a[:, 10], meta=meta, extra=extra)


def device(session: Session, serial: str, model: str | None = None, firmware: str | None = None) -> Device:
    """The device row for a serial number, created on first sight."""
    row = session.scalar(select(Device).where(Device.serial == serial))
    if row is None:
        row = Device(serial=serial, model=model, firmware=firmware)
        session.add(row)
        session.flush()
    elif model or firmware:
        row.model, row.firmware = model or row.model, firmware or row.firmware
    return row


def figures(cal: dict[str, Any]) -> dict[str, float | None]:
    """The numbers the acceptance limits are about, from a calibration JSON."""
    c = PhysCalibration.from_json(cal)
    q = c.quality or {}
    rms = [r for r in q.get("residual_rms_lsb", []) if r is not None]
    he = q.get("heading_error_deg", {}) or {}
    M_o = c.mag.M_o
    misalign = float(np.degrees(np.arccos(np.clip(np.abs(np.diag(M_o)), -1, 1))).max())
    k = c.mag.k
    return {"residual_rms_lsb": max(rms) if rms else None,
            "heading_error_level_deg": he.get("full"),
            "heading_error_tilted_deg": he.get("tilted_full"),
            "misalignment_deg": misalign,
            "sensitivity_mismatch": float(np.max(np.abs(k / k.mean() - 1.0))),
            "bias_lsb": float(np.linalg.norm(c.mag.bias))}


def limit_result(value: Any, lim: Limit) -> str | None:
    """How one figure fares against one limit: PASS, MARGINAL or FAIL; None when it cannot be judged
    (missing or not finite)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(v):
        return None
    return "FAIL" if v > lim.fail else "MARGINAL" if v > lim.marginal else "PASS"


def judge(fig: dict[str, float | None], limits: list[Limit]) -> tuple[str, list[str]]:
    """PASS, MARGINAL or FAIL from a calibration's :func:`figures`, with the reasons (every limit
    exceeded, with the figure and the limit; and every limit its figure is missing for, which the verdict
    does not cover: a twelve-position calibration's certificate said "every figure within its marginal
    limit" beside a tilted limit "not judged")."""
    verdict, reasons = "PASS", []
    for lim in limits:
        value, result = fig.get(lim.name), limit_result(fig.get(lim.name), lim)
        if result is None:
            reasons.append(f"{lim.name} not judged: this calibration gives no figure for it (the verdict covers the "
                           "other limits)")
        elif result == "FAIL":
            verdict = "FAIL"
            reasons.append(f"{lim.name} {value:.4g} {lim.unit} above the fail limit {lim.fail:g}")
        elif result == "MARGINAL":
            verdict = "MARGINAL" if verdict == "PASS" else verdict
            reasons.append(f"{lim.name} {value:.4g} {lim.unit} above the marginal limit {lim.marginal:g}")
    return verdict, reasons


def store_calibration(session: Session, run: Run, slot: int, serial: str, cal: dict[str, Any],
                      model: str | None = None, firmware: str | None = None,
                      identity: dict[str, Any] | None = None) -> Calibration:
    """Judge a calibration against the limits and keep it: PASS or MARGINAL becomes current and the
    previous current one is superseded; FAIL is kept as rejected. Nothing is ever overwritten.
    ``identity``: the typed and identified serial numbers (service.identity.Identity.to_json)."""
    dev = device(session, serial, model, firmware)
    fig = figures(cal)
    limits = list(session.scalars(select(Limit).order_by(Limit.name)))
    verdict, reasons = judge(fig, limits)
    status = "rejected" if verdict == "FAIL" else "current"
    if status == "current":
        session.execute(update(Calibration).where(Calibration.device_id == dev.id, Calibration.status == "current")
                        .values(status="superseded"))
    row = Calibration(device_id=dev.id, run_id=run.id, slot=slot, status=status, verdict=verdict, reasons=reasons,
                      method=str(cal.get("method", "")), data=cal, figures=fig, identity=identity,
                      limits=[{"name": lim.name, "marginal": lim.marginal, "fail": lim.fail, "unit": lim.unit,
                               "description": lim.description} for lim in limits])
    session.add(row)
    session.flush()
    return row
