"""Foreign recordings (RECORDING.md CSV) imported as runs: ``POST /recordings``."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request

from physics.recording import RecordingError, parse_recording
from service.auth import Caller, audit, require
from service.db import Run
from service.runtime import SOFTWARE_VERSION, invalid
from service.schemas import ERRORS, RecordingOut
from service.store import insert_samples

#: Largest accepted upload (a recording of a few hours at 100 Hz).
MAX_UPLOAD_BYTES = 50 * 1024 * 1024

router = APIRouter(tags=["runs"])


@router.post("/recordings", status_code=201, response_model=RecordingOut, responses=ERRORS)
async def upload_recording(request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Store a foreign recording (a RECORDING.md CSV in the body) as a completed run of procedure
    ``import``, so it can be fitted and analysed like any other."""
    size = int(request.headers.get("content-length") or 0)
    if size > MAX_UPLOAD_BYTES:
        raise HTTPException(413, f"recording of {size} bytes; at most {MAX_UPLOAD_BYTES} accepted")
    body = await request.body()
    if len(body) > MAX_UPLOAD_BYTES:
        raise HTTPException(413, f"recording of {len(body)} bytes; at most {MAX_UPLOAD_BYTES} accepted")
    try:
        rec = await asyncio.to_thread(parse_recording, body.decode("utf-8"))
    except UnicodeDecodeError:
        raise invalid("body", "not UTF-8 text") from None
    except RecordingError as e:
        raise invalid("body", str(e)) from None
    serial = rec.serial or ""
    with request.app.state.sessions() as session:
        run = Run(procedure="import", procedure_version="1", parameters={}, status="completed", operator=caller.owner,
                  serials={"0": serial}, software_version=SOFTWARE_VERSION, meta=dict(rec.meta),
                  table_seconds=float(rec.t[-1] - rec.t[0]) if len(rec) else 0.0)
        session.add(run)
        session.flush()
        insert_samples(session, run.id, 0, rec)
        audit(session, caller, "recording.import", f"run {run.id}", {"serial": serial, "samples": len(rec)})
        session.commit()
        return {"id": run.id, "status": run.status, "procedure": "import", "samples": len(rec), "serial": serial}
