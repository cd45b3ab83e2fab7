"""Foreign recordings (RECORDING.md CSV) imported as runs: ``POST /recordings``.

The body is read as it arrives and counted (413 as soon as it is too big, whether or not a
Content-Length announced it), then decoded, parsed, checked against the columns it is stored in
and inserted in a worker thread: a large upload does not hold up the event loop (``/health``, the
event streams)."""

from __future__ import annotations

import asyncio
import math
import re
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request
from sqlalchemy.orm import sessionmaker

from physics.fit import check_angles
from physics.recording import RecordingError, parse_recording
from service.auth import Caller, audit, require
from service.db import Run, utcnow
from service.runtime import SOFTWARE_VERSION, invalid
from service.schemas import ERRORS, NAME_MAX, STEP_MAX, ErrorOut, RecordingOut, check_serial
from service.store import insert_samples

#: Largest accepted upload (a recording of a few hours at 100 Hz).
MAX_UPLOAD_BYTES = 50 * 1024 * 1024

_LINE_BREAK = re.compile(r"\r\n|\r|\n")

router = APIRouter(tags=["runs"])

#: The request body in OpenAPI (the route reads it as a stream, so FastAPI cannot infer it).
_BODY = {"requestBody": {"required": True, "description": "a recording as RECORDING.md CSV text (UTF-8), at most "
                         f"{MAX_UPLOAD_BYTES} bytes; its '# serial:' metadata line, if any, a serial number of "
                         "1 to 64 letters, digits, '-_.:+#' and inner spaces; step labels of at most "
                         f"{STEP_MAX} characters",
                         "content": {"text/csv": {"schema": {"type": "string"}}}}}


@router.post("/recordings", status_code=201, response_model=RecordingOut, openapi_extra=_BODY,
             responses={**ERRORS, 413: {"model": ErrorOut, "description": "the recording is too big"}})
async def upload_recording(request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Store a foreign recording (a RECORDING.md CSV in the body) as a completed run of procedure
    ``import``, so it can be fitted and analysed like any other. 413 beyond the size limit; 422 for
    text that is not a recording or that the database could not hold (naming the line and column)."""
    limit = MAX_UPLOAD_BYTES  # read once: the limit of this request
    if request.headers.get("content-type", "").lower().startswith("multipart/"):
        # (a form upload read as CSV said "line 1: missing required column(s)")
        raise invalid("body", "a multipart form upload: send the recording's CSV text itself as the body "
                              "(e.g. curl --data-binary @rec.csv -H 'Content-Type: text/csv')")
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        raise HTTPException(413, f"recording of {int(declared)} bytes; at most {limit} accepted")
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():  # counted as it arrives: a chunked upload announces no length
        size += len(chunk)
        if size > limit:
            raise HTTPException(413, f"recording of more than {limit} bytes; at most {limit} accepted")
        chunks.append(chunk)
    # decoding, parsing and inserting a large recording take seconds of CPU: off the event loop
    return await asyncio.to_thread(_store, chunks, caller, request.app.state.sessions)


def _store(chunks: list[bytes], caller: Caller, sessions: sessionmaker) -> dict[str, Any]:
    """Join, decode, parse, check and insert an upload (in a worker thread); the answer's fields."""
    try:
        text = b"".join(chunks).decode("utf-8")
    except UnicodeDecodeError as e:
        raise invalid("body", f"not UTF-8 text (byte {e.start + 1}, counting from 1)") from None
    nul = text.find("\x00")
    if nul >= 0:  # PostgreSQL's text and JSON cannot hold it: refused on both databases
        line = len(_LINE_BREAK.findall(text, 0, nul)) + 1
        raise invalid("body", f"line {line}: contains a NUL character (\\x00)")
    try:
        rec = parse_recording(text, max_step_chars=STEP_MAX)  # samples.step is String(32)
    except RecordingError as e:
        # a file of another layout (a logger's own columns, units or separator): say how to bring it in
        foreign = "missing required column" in str(e) or "no column line" in str(e)
        hint = ("; a file of another layout is converted first: compasscal convert FILE --mapping map.toml -o rec.csv "
                "(the importers' own formats: compasscal convert FILE -o rec.csv)") if foreign else ""
        raise invalid("body", str(e) + hint) from None
    try:
        check_angles(rec)  # as `compasscal fit` and `analyze` read a file: before it is stored, not at its analysis
    except RecordingError as e:
        raise invalid("body", str(e)) from None
    long = [c for c in rec.extra if len(c) > NAME_MAX]
    if long:  # an extra column is kept under its name, a String(64)
        raise invalid("body", f"column line: extra column name of {len(long[0])} characters, at most {NAME_MAX} "
                              f"({long[0][:40]!r}...)")
    serial = (rec.serial or "").strip()
    if serial:
        try:
            serial = check_serial(serial)
        except ValueError as e:
            raise invalid("body.serial", f"the '# serial:' metadata line: {e}") from None
    span = float(rec.t[-1] - rec.t[0]) if len(rec) else 0.0
    if not math.isfinite(span):  # each t finite, their difference too large for a double
        raise invalid("body", "column t: the recording's time span is not a finite number of seconds")
    with sessions() as session:
        now = utcnow()  # an import starts and ends as it is stored (its run had no start or end time)
        run = Run(procedure="import", procedure_version="1", parameters={}, status="completed", operator=caller.owner,
                  # no serial: none stored (an empty one is no serial number; the run lists no unit's)
                  serials={"0": serial} if serial else {}, software_version=SOFTWARE_VERSION, meta=dict(rec.meta),
                  table_seconds=span, created_at=now, started_at=now, finished_at=now)
        session.add(run)
        session.flush()
        insert_samples(session, run.id, 0, rec)
        audit(session, caller, "recording.import", f"run {run.id}", {"serial": serial, "samples": len(rec)})
        session.commit()
        return {"id": run.id, "status": run.status, "procedure": "import", "samples": len(rec), "serial": serial or None}
