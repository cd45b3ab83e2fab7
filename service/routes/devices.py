"""Units and their calibration history: ``/devices/{serial}``, its calibrations (the quality
engineers' most frequent query), one calibration and its PDF certificate."""

from __future__ import annotations

import json
import re
from typing import Any
from urllib.parse import quote

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from sqlalchemy import Text, cast, func, select
from sqlalchemy.orm import Session

from service import plots
from service.auth import Caller, require
from service.db import Calibration, Device
from service.deps import db
from service.runtime import in_other_case
from service.schemas import ERRORS, CalibrationOut, DeviceOut, HistoryEntry, Id, Index, Serial, content
from service.web import certificate_context, limit_pairs

router = APIRouter(tags=["devices"])


def calibration_json(row: Calibration) -> dict[str, Any]:
    """A stored calibration: the physics JSON plus its id, run, time, status and verdict, the acceptance
    limits that verdict was judged against (null for one stored before they were kept) and the identity
    decision it was certified under (the run's result and the certificate had it; this JSON did not)."""
    return {**row.data, "id": row.id, "run_id": row.run_id, "created_at": row.created_at, "status": row.status,
            "verdict": row.verdict, "reasons": row.reasons, "serial": row.device.serial, "limits": row.limits,
            "identity": row.identity}


def _device(session: Session, serial: str) -> Device:
    dev = session.scalar(select(Device).where(Device.serial == serial))
    if dev is None:
        # a serial typed in another letter case finds nothing: name the ones that differ only so
        alike = in_other_case(session, serial)
        raise HTTPException(404, f"no device with serial number {serial!r}"
                                 + (f"; serial numbers differ in letter case: did you mean {', '.join(map(repr, alike))}?"
                                    if alike else ""))
    return dev


@router.get("/devices/{serial}", response_model=DeviceOut, responses=ERRORS)
def get_device(serial: Serial, session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """A unit: model, firmware, number of calibrations and the current one's id."""
    dev = _device(session, serial)
    count = session.scalar(select(func.count()).select_from(Calibration).where(Calibration.device_id == dev.id))
    current = session.scalar(select(Calibration.id).where(Calibration.device_id == dev.id, Calibration.status == "current"))
    return {"serial": dev.serial, "model": dev.model, "firmware": dev.firmware, "created_at": dev.created_at,
            "calibrations": count, "current_calibration_id": current}


def _utc(t: Any) -> str:
    """A time as every other answer writes it (pydantic's ISO 8601 with ``Z``)."""
    return t.isoformat().replace("+00:00", "Z")


@router.get("/devices/{serial}/calibrations", response_model=list[HistoryEntry], responses=ERRORS)
async def device_calibrations(request: Request, serial: Serial, limit: int = Query(100, ge=1, le=1000),
                              offset: Index = 0, _: Caller = Depends(require("viewer"))) -> Response:
    """The unit's calibration history, newest first (status current, superseded or rejected), with
    the figures the acceptance limits judged; the full documents are at /calibrations/{id}."""
    # The quality engineers' most frequent query: one indexed query of small columns on the event
    # loop, the stored JSON spliced in as text instead of decoded and re-encoded. (In the thread pool
    # instead, 50 clients starting at the same instant wait less, but every later request waits
    # 3-5x longer: benchmarks/service_speed.py, README.)
    with request.app.state.sessions() as session:
        rows = session.execute(
            select(Calibration.id, Calibration.run_id, Calibration.created_at, Calibration.status, Calibration.verdict,
                   cast(Calibration.reasons, Text), Calibration.method, Calibration.slot, cast(Calibration.figures, Text),
                   cast(Calibration.identity, Text))
            .join(Device, Device.id == Calibration.device_id).where(Device.serial == serial)
            .order_by(Calibration.created_at.desc(), Calibration.id.desc()).limit(limit).offset(offset)).all()
        if not rows and offset == 0:
            _device(session, serial)  # 404 for an unknown serial; a known one may have no calibrations
    body = ",".join(
        f'{{"id":{r[0]},"run_id":{json.dumps(r[1])},"created_at":"{_utc(r[2])}","status":"{r[3]}","verdict":{json.dumps(r[4])},'
        f'"reasons":{r[5] or "[]"},"method":{json.dumps(r[6])},"slot":{r[7]},"figures":{r[8] or "null"},'
        f'"identity":{r[9] or "null"}}}' for r in rows)
    return Response(f"[{body}]", media_type="application/json")


@router.get("/devices/{serial}/calibrations/current", response_model=CalibrationOut, responses=ERRORS)
def current_calibration(serial: Serial, session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """The calibration in force (the physics calibration JSON plus id, run_id, created_at, verdict)."""
    dev = _device(session, serial)
    row = session.scalar(select(Calibration).where(Calibration.device_id == dev.id, Calibration.status == "current"))
    if row is None:
        raise HTTPException(404, f"{serial!r} has no current calibration")
    return calibration_json(row)


@router.get("/calibrations/{cal_id}", response_model=CalibrationOut, responses=ERRORS)
def get_calibration(cal_id: Id, session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One stored calibration by id."""
    row = session.get(Calibration, cal_id)
    if row is None:
        raise HTTPException(404, f"no calibration {cal_id}")
    return calibration_json(row)


@router.get("/calibrations/{cal_id}/certificate.pdf", response_class=Response,
            responses=content("application/pdf", "the certificate, A4", binary=True))
def certificate_pdf(request: Request, cal_id: Id, _: Caller = Depends(require("viewer"))) -> Response:
    """The calibration certificate as a PDF (A4: identification and parameters with uncertainties,
    the heading-error curves, the acceptance limits and the verdict)."""
    with request.app.state.sessions() as s:
        row = s.get(Calibration, cal_id)
        if row is None:
            raise HTTPException(404, f"no calibration {cal_id}")
        cert, cal, rec, limits = certificate_context(s, row)
    pdf = plots.certificate_pdf(cert, cal, rec, limit_pairs(limits))
    name = f"certificate-{cert['serial']}-{cert['number']}.pdf"
    return Response(pdf, media_type="application/pdf", headers={"Content-Disposition": content_disposition("inline", name)})


def content_disposition(kind: str, name: str) -> str:
    """A Content-Disposition header naming a file (RFC 6266): ``filename`` an ASCII fallback,
    ``filename*`` the name in UTF-8, percent-encoded. Neither carries a path: a serial stored before
    serials were checked (``../../etc/passwd``, ``a/b``) or outside Latin-1 (which a header cannot
    carry raw) still gives a plain file name."""
    name = re.sub(r"\.{2,}", ".", re.sub(r"[\x00-\x1f\x7f/\\]", "_", name))  # no directory, "..", control character
    ascii_name = re.sub(r"[^A-Za-z0-9._+-]", "_", name)  # nothing a quoted string would need to escape
    return f"{kind}; filename=\"{ascii_name}\"; filename*=UTF-8''{quote(name, safe='')}"
