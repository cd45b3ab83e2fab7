"""Batches: units calibrated in turn on slot 0 of one station (``/batches``), each unit's run
prompting its mounting; a failed unit does not stop the batch."""

from __future__ import annotations

import asyncio
from typing import Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from pydantic import ValidationError
from sqlalchemy import select, update

from procedures.calibrate import BATCH, BATCH_SETS, PROCEDURES
from procedures.states import ACTIVE
from service.auth import Caller, audit, require
from service.db import Batch, Run, Station
from service.deps import sessions
from service.runtime import (BATCH_ABORTING, Conflict, Invalid, NotFound, batch_json, check_typed, end_lost_batches,
                             field_errors, invalid, station_filter)
from service.routes.runs import change_run_state
from service.schemas import ERRORS, BatchIn, BatchOut, BatchStateIn, Id, Index, StationName
from service.worker import station_queue

router = APIRouter(tags=["batches"])


@router.post("/batches", status_code=202, response_model=BatchOut, responses=ERRORS)
async def create_batch(body: BatchIn, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Calibrate units in turn on slot 0 of a station (operator). Each unit's run first prompts
    ``mount`` (answer it with ``POST /runs/{id}/prompts/mount``); a failed unit does not stop the batch."""
    try:
        PROCEDURES[BATCH].validate({**body.parameters, "serial": body.serials[0]})
    except ValidationError as e:
        raise Invalid(field_errors(e.errors(), ("body", "parameters"))) from None
    for key in BATCH_SETS:
        if key in body.parameters:
            raise invalid(f"body.parameters.{key}", "set by the batch for each unit")
    with sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == body.station))
        if row is None:
            raise NotFound(f"no station {body.station!r}")
        if len(row.compasses or []) > 1:  # its runs would calibrate (and certify) the other slots' units too
            raise invalid("body.station", f"station {row.name} has {len(row.compasses)} compass slots; a batch mounts one "
                                          "unit at a time in slot 0: use a station of one slot, or POST /runs with "
                                          '"serials" for a full fixture')
        for i, serial in enumerate(body.serials):
            check_typed(s, f"body.serials.{i}", serial)
        batch = Batch(station_id=row.id, serials=list(body.serials), status="running", operator=caller.owner, summary={})
        s.add(batch)
        s.flush()
        claimed = s.execute(update(Station).where(Station.id == row.id, Station.run_id.is_(None), Station.batch_id.is_(None),
                                                  Station.state != "fault").values(batch_id=batch.id)).rowcount
        if claimed != 1:
            s.rollback()
            s.refresh(row)
            raise Conflict(f"station {row.name} is in fault ({row.reason}); POST /stations/{row.name}/reset first"
                           if row.state == "fault" else
                           f"station {row.name} is busy with " + (f"run {row.run_id}" if row.run_id else f"batch {row.batch_id}"))
        audit(s, caller, "batch.start", f"batch {batch.id}", body.model_dump())
        s.commit()
        batch_id = batch.id
    await request.app.state.jobs.defer("batch", queue=station_queue(body.station), lock=station_queue(body.station),
                                       batch_id=batch_id, parameters=dict(body.parameters), operator=caller.owner,
                                       serial_policy=body.serial_policy)
    with sessions(request)() as s:
        return batch_json(s, s.get(Batch, batch_id))


@router.get("/batches", response_model=list[BatchOut], responses=ERRORS)
async def list_batches(request: Request, station: StationName | None = None,
                       status: Literal["running", "aborting", "completed", "aborted", "failed"] | None = None,
                       limit: int = Query(50, ge=1, le=1000), offset: Index = 0,
                       _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Batches, newest first, filtered by station name and status (running, aborting, completed, aborted, failed)."""
    def read() -> list[dict[str, Any]]:
        q = select(Batch)
        if status is not None:
            q = q.where(Batch.status == status)
        with sessions(request)() as s:
            if station is not None:
                q = q.where(Batch.station_id == station_filter(s, station))
            rows = s.scalars(q.order_by(Batch.created_at.desc(), Batch.id.desc()).limit(limit).offset(offset)).all()
            return [batch_json(s, b) for b in rows]
    return await asyncio.to_thread(read)


@router.put("/batches/{batch_id}/state", status_code=202, response_model=BatchOut, responses=ERRORS)
async def put_batch_state(batch_id: Id, body: BatchStateIn, request: Request,
                          caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Abort a running batch (operator): its current unit's run is aborted as ``PUT /runs/{id}/state``
    would (the axes stop, its samples are kept), no further unit starts, and the summary says which
    were not run. 409 unless the batch is running."""
    with sessions(request)() as s:
        batch = s.get(Batch, batch_id)
        if batch is None:
            raise NotFound(f"no batch {batch_id}")
        if batch.status != "running":
            raise Conflict(f"batch {batch_id} is {batch.status}: only a running batch can be aborted")
        batch.status = BATCH_ABORTING
        audit(s, caller, "batch.state", f"batch {batch_id}", body.model_dump())
        s.commit()
        current = s.scalars(select(Run.id).where(Run.batch_id == batch_id, Run.status.in_(ACTIVE))).all()
        station_id = batch.station_id
        station = s.get(Station, station_id).name
    if await request.app.state.jobs.cancel_queued("batch", station_queue(station), batch_id=batch_id):
        # no worker had taken it (the station's worker is down or busy): it ends here, as an unstarted run
        # does (it stayed "aborting", and its station busy with it, until a worker came)
        with sessions(request)() as s:
            end_lost_batches(s, [station_id], "the batch was aborted before its station's worker took it",
                             queued_too=True)
            s.commit()
    for run_id in current:  # (the worker starts no unit once it sees the batch aborting)
        try:
            await change_run_state(request, run_id, "aborted", body.reason or "the batch was aborted by the operator")
        except Conflict:
            pass  # it ended meanwhile
    with sessions(request)() as s:
        return batch_json(s, s.get(Batch, batch_id))


@router.get("/batches/{batch_id}", response_model=BatchOut, responses=ERRORS)
async def get_batch(batch_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """A batch: status, one row per unit (run id, status, verdict), the waiting prompt and the summary."""
    with sessions(request)() as s:
        batch = s.get(Batch, batch_id)
        if batch is None:
            raise HTTPException(404, f"no batch {batch_id}")
        return batch_json(s, batch)
