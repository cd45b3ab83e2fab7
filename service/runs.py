"""Stations, runs and batches: their routes. Each answer comes from the database, so the API holds
no run state and can run as several processes; the hardware is the workers' (service/worker.py), the
rules (claiming a station, the run's state machine, commands) are the run-time layer's
(service/runtime.py).

Statuses
--------
A run is ``queued`` (created; waiting for its station's worker, which then opens the hardware), then
``running``, ``paused``, and ends ``completed``, ``failed`` or ``aborted``. ``PUT /runs/{id}/state``
accepts only the operator transitions of :mod:`procedures.states`; anything else is 409 naming from
and to. A pause takes effect at the procedure's next checkpoint (the table holds still there): until
the worker reports it, the run stays ``running`` with ``pause_requested`` true; ``running ->
running`` then withdraws the request. A run is reported ``completed`` only after its calibrations are
stored and its station is free again.

Station faults
--------------
A station goes to ``fault`` when its hardware cannot be opened, a run fails on the table's account
(an axis fault, Modbus), or its worker was lost mid-run. It stays there, refusing runs, until
``POST /stations/{name}/reset`` (a job for its worker) resets the axis faults.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, Field, ValidationError, field_validator
from sqlalchemy import String, cast, select, update
from sqlalchemy.orm import Session

from drivers.modbus import BusURL
from physics.recording import format_recording
from procedures.calibrate import BATCH, BatchCalibrateParams
from procedures.states import ACTIVE, OPERATOR_TRANSITIONS as TRANSITIONS, RunState
from service.auth import Caller, audit, require
from service.db import Batch, Calibration, Device, Run, Station
from service.deps import event_stream
from service.runtime import (CONFIRM_S, SOFTWARE_VERSION, Conflict, Invalid, NotFound, Unavailable, batch_json,
                             create_run, events_after, field_errors, finish_unstarted, invalid, queue_answer,
                             request_state, run_json, station_json, wait_for)
from service.store import load_recording
from service.worker import station_queue

router = APIRouter()


def _sessions(request: Request) -> Any:
    return request.app.state.sessions


class StationIn(BaseModel):
    """A new station: its table's Modbus URL and one serial URL per fixture slot."""

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    modbus: str = Field(min_length=1, max_length=256, description="e.g. tcp://10.0.0.5:502")
    compasses: list[str] = Field(min_length=1, description="the serial URL of slot 0, slot 1, ...")
    time_scale: float = Field(1.0, gt=0, le=1000, description="> 1 only for a simulated station running faster")

    @field_validator("modbus")
    @classmethod
    def _url(cls, v: str) -> str:
        BusURL.parse(v)  # ValueError names the problem
        return v

    @field_validator("compasses")
    @classmethod
    def _urls(cls, v: list[str]) -> list[str]:
        if any(not u.strip() for u in v):
            raise ValueError("empty compass URL")
        return v


class RunIn(BaseModel):
    """A run to start."""

    station: str
    procedure: str = "calibrate"
    parameters: dict[str, Any] = Field(default_factory=dict)
    serials: dict[str, str] | None = Field(None, description='slot -> serial, e.g. {"0": "SN-1"}; '
                                           "omitted: the compasses' own serial numbers")


class StateIn(BaseModel):
    """A requested state change of a run."""

    state: str = Field(pattern="^(paused|running|aborted)$")
    reason: str | None = Field(None, max_length=500)


class AnswerIn(BaseModel):
    """The operator's answer to a prompt."""

    answer: str = Field("", max_length=1000)


class BatchIn(BaseModel):
    """Units to calibrate in turn on slot 0 of a station."""

    station: str
    serials: list[str] = Field(min_length=1, max_length=1000)
    parameters: dict[str, Any] = Field(default_factory=dict, description="calibrate parameters for every unit")

    @field_validator("serials")
    @classmethod
    def _distinct(cls, v: list[str]) -> list[str]:
        v = [s.strip() for s in v]
        if any(not s for s in v):
            raise ValueError("empty serial number")
        dup = sorted({s for s in v if v.count(s) > 1})
        if dup:
            raise ValueError(f"serial numbers listed twice: {', '.join(dup)}")
        return v


def _get_run(s: Session, run_id: int) -> Run:
    row = s.get(Run, run_id)
    if row is None:
        raise HTTPException(404, f"no run {run_id}")
    return row


@router.get("/stations", tags=["stations"])
async def list_stations(request: Request, _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Every station with its state (idle, running, paused, fault), current run and worker."""
    with _sessions(request)() as s:
        rows = s.scalars(select(Station).order_by(Station.name)).all()
    return [station_json(r) for r in rows]


@router.post("/stations", status_code=201, tags=["stations"])
async def create_station(body: StationIn, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Add a station (admin). 409 if the name is taken."""
    with _sessions(request)() as s:
        if s.scalar(select(Station.id).where(Station.name == body.name)) is not None:
            raise HTTPException(409, f"station {body.name!r} exists")
        row = Station(name=body.name, modbus=body.modbus, compasses=list(body.compasses), time_scale=body.time_scale,
                      state="idle")
        s.add(row)
        audit(s, caller, "station.create", body.name, body.model_dump())
        s.commit()
        return station_json(row)


class StationConfigIn(BaseModel):
    """A station's configuration (the name is in the path)."""

    modbus: str = Field(min_length=1, max_length=256, description="e.g. tcp://10.0.0.5:502")
    compasses: list[str] = Field(min_length=1, description="the serial URL of slot 0, slot 1, ...")
    time_scale: float = Field(1.0, gt=0, le=1000, description="> 1 only for a simulated station running faster")


@router.put("/stations/{name}", tags=["stations"])
async def put_station(name: str, body: StationConfigIn, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Create a station or change its URLs (admin), e.g. after moving a table to another gateway.
    409 while a run uses it; runs already made keep the configuration they ran with."""
    full = StationIn(name=name, **body.model_dump())  # the same checks as POST
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            row = Station(name=name, modbus=full.modbus, compasses=list(full.compasses), time_scale=full.time_scale,
                          state="idle")
            s.add(row)
        else:
            if row.run_id is not None:
                raise HTTPException(409, f"station {name!r} is {row.state} (run {row.run_id}); change it when idle")
            row.modbus, row.compasses, row.time_scale = full.modbus, list(full.compasses), full.time_scale
        audit(s, caller, "station.put", name, full.model_dump())
        s.commit()
        return station_json(row)


@router.get("/stations/{name}", tags=["stations"])
async def get_station(name: str, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One station: configuration, state, current run (with its status and prompts), fault, worker."""
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            raise HTTPException(404, f"no station {name!r}")
        out = station_json(row)
        run = s.get(Run, row.run_id) if row.run_id is not None else None
        out["run"] = run_json(run) if run is not None else None
    return out


@router.post("/stations/{name}/reset", tags=["stations"])
async def reset_station(name: str, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Reset the table's axis faults and make the station idle (operator), through the station's
    worker. 409 while a run uses it; 503 when the table cannot be reached, still reports a fault, or
    no worker of the station answers."""
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            raise NotFound(f"no station {name!r}")
        if row.run_id is not None:
            raise Conflict(f"station {name} is busy with run {row.run_id}; abort it first")
        before = row.reason
    token = uuid.uuid4().hex
    await request.app.state.jobs.defer("reset", queue=station_queue(name), lock=station_queue(name), station=name, token=token)

    def outcome() -> dict[str, Any] | None:
        with _sessions(request)() as s:
            r = s.scalar(select(Station).where(Station.name == name))
            return r.reset if r is not None and (r.reset or {}).get("token") == token else None
    got = await wait_for(outcome, CONFIRM_S)
    if not got.ok:
        raise Unavailable(f"no worker of station {name} took the reset within {CONFIRM_S:g} s; "
                          f"is `compasscal worker --station {name}` running?")
    out = {k: v for k, v in got.value.items() if k not in ("token", "ok", "status", "error")}
    if not got.value.get("ok"):
        with _sessions(request)() as s:  # an attempt on the hardware: logged even when it failed
            audit(s, caller, "station.reset", name, {"ok": False, "error": got.value.get("error")})
            s.commit()
        raise HTTPException(int(got.value.get("status") or 503), got.value.get("error"))
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row.state == "fault":
            audit(s, caller, "station.reset", name, {"ok": False, "error": row.reason, **out})
            s.commit()
            raise Unavailable(f"station {name}: {row.reason}")
        audit(s, caller, "station.reset", name, {"ok": True, "fault": before, **out})
        s.commit()
        return {**station_json(row), **out}


@router.post("/runs", status_code=202, tags=["runs"])
async def create_run_route(body: RunIn, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Start a run (operator): 202 with the run (status ``queued``); follow it with ``GET /runs/{id}``
    or ``GET /runs/{id}/events``. 404 unknown station, 422 bad procedure/parameters/serials, 409 busy."""
    def create() -> Run:
        with _sessions(request)() as s:
            return create_run(s, body.station, body.procedure, body.parameters, body.serials, caller.owner,
                              SOFTWARE_VERSION)
    run = await asyncio.to_thread(create)
    job = await request.app.state.jobs.defer("run", queue=station_queue(body.station), lock=station_queue(body.station),
                                             run_id=run.id)
    with _sessions(request)() as s:
        row = s.get(Run, run.id)
        row.meta = {**(row.meta or {}), "job_id": job}
        audit(s, caller, "run.start", f"run {run.id}", {"station": body.station, "procedure": run.procedure,
                                                         "parameters": run.parameters, "serials": run.serials})
        s.commit()
        return run_json(row)


@router.get("/runs", tags=["runs"])
async def list_runs(request: Request, station: str | None = None, status: str | None = None,
                    procedure: str | None = None, serial: str | None = None,
                    limit: int = Query(50, ge=1, le=1000), offset: int = Query(0, ge=0),
                    _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Runs, newest first, filtered by station name, status, procedure and unit serial number."""
    q = select(Run)
    if station is not None:
        q = q.join(Station, Station.id == Run.station_id).where(Station.name == station)
    if status is not None:
        q = q.where(Run.status == status)
    if procedure is not None:
        q = q.where(Run.procedure == procedure)
    if serial is not None:
        # serials is a small JSON object {"0": "SN-1"}; its text holds each serial JSON-quoted on both databases
        needle = json.dumps(serial).replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        q = q.where(cast(Run.serials, String).like(f"%{needle}%", escape="\\"))
    with _sessions(request)() as s:
        rows = s.scalars(q.order_by(Run.created_at.desc(), Run.id.desc()).limit(limit).offset(offset)).all()
        return [run_json(r) for r in rows]


@router.get("/runs/{run_id}", tags=["runs"])
async def get_run(run_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One run: provenance, live status, waiting prompts, progress, result and its calibrations."""
    with _sessions(request)() as s:
        row = _get_run(s, run_id)
        out = run_json(row)
        cals = s.execute(select(Calibration, Device.serial).join(Device, Device.id == Calibration.device_id)
                         .where(Calibration.run_id == run_id).order_by(Calibration.slot)).all()
    out["calibrations"] = [{"id": c.id, "slot": c.slot, "serial": serial, "status": c.status, "verdict": c.verdict,
                            "reasons": c.reasons} for c, serial in cals]
    return out


@router.put("/runs/{run_id}/state", status_code=202, tags=["runs"])
async def put_run_state(run_id: int, body: StateIn, request: Request,
                        caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Pause, resume or abort (operator), checked against the run's state machine (409 otherwise).
    202: a pause takes effect at the next checkpoint, an abort as soon as the current step ends."""
    with _sessions(request)() as s:
        what, queued = request_state(s, run_id, body.state, body.reason)
        job = (s.get(Run, run_id).meta or {}).get("job_id")
    if queued and job is not None and await request.app.state.jobs.cancel(int(job)):
        # no worker had taken it: end it here (else its worker sees the command before touching the table)
        with _sessions(request)() as s:
            finish_unstarted(s, run_id, RunState.aborted.value, body.reason or "aborted by the operator")
        request.app.state.notifier.poke(run_id)
    with _sessions(request)() as s:
        audit(s, caller, "run.state", f"run {run_id}", {"state": body.state, "reason": body.reason, "action": what})
        s.commit()
        out = run_json(_get_run(s, run_id))
    return {**out, "requested": body.state, "action": what}


@router.get("/runs/{run_id}/events", tags=["runs"])
async def run_events(run_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> StreamingResponse:
    """Server-sent events (state, step, progress, samples, prompt, result): the run's history from
    the database, then live events until it ends, from whichever process runs it. A
    ``Last-Event-ID`` header resumes after that event (ids increase; any API process understands them)."""
    with _sessions(request)() as s:
        _get_run(s, run_id)

    def read(after: int) -> tuple[list[tuple[int, str, dict[str, Any]]], bool]:
        with _sessions(request)() as s:
            rows = [(e.id, e.kind, e.data) for e in events_after(s, run_id, after)]
            status = s.scalar(select(Run.status).where(Run.id == run_id))
        return rows, status not in ACTIVE
    return event_stream(request, run_id, read)


@router.get("/runs/{run_id}/samples", tags=["runs"])
async def run_samples(run_id: int, request: Request, slot: int = Query(0, ge=0),
                      _: Caller = Depends(require("viewer"))) -> Response:
    """One slot's samples as a RECORDING.md CSV (404 when it has none)."""
    def build() -> str | None:
        with _sessions(request)() as s:
            row = _get_run(s, run_id)
            rec = load_recording(s, row, slot)
        if rec is None:
            return None
        rec.meta.pop("result", None)  # the result summary is no recording metadata
        rec.meta.pop("job_id", None)
        return format_recording(rec)
    text = await asyncio.to_thread(build)  # a long run has hundreds of thousands of rows
    if text is None:
        raise HTTPException(404, f"run {run_id} has no samples from slot {slot}")
    return Response(text, media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="run{run_id}-slot{slot}.csv"'})


@router.post("/runs/{run_id}/prompts/{prompt_id}", tags=["runs"])
async def answer_prompt(run_id: int, prompt_id: str, body: AnswerIn, request: Request,
                        caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Answer a waiting operator prompt (operator); 404 when the run has no such prompt waiting.
    Answers once the run's worker has taken the answer (503 if it does not within a few seconds)."""
    with _sessions(request)() as s:
        queue_answer(s, run_id, prompt_id, body.answer)

    def taken() -> bool | None:
        with _sessions(request)() as s:
            row = s.get(Run, run_id)
            return True if row is None or prompt_id not in (row.prompts or {}) or row.status not in ACTIVE else None
    if not (await wait_for(taken, CONFIRM_S, every=0.05)).ok:
        raise Unavailable(f"run {run_id}'s worker did not take the answer within {CONFIRM_S:g} s (it is kept for it)")
    with _sessions(request)() as s:
        audit(s, caller, "run.prompt", f"run {run_id}", {"prompt": prompt_id, "answer": body.answer})
        s.commit()
    return {"run_id": run_id, "prompt": prompt_id, "answer": body.answer}


@router.post("/batches", status_code=202, tags=["batches"])
async def create_batch(body: BatchIn, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Calibrate units in turn on slot 0 of a station (operator). Each unit's run first prompts
    ``mount`` (answer it with ``POST /runs/{id}/prompts/mount``); a failed unit does not stop the batch."""
    try:
        BatchCalibrateParams.model_validate({**body.parameters, "serial": body.serials[0]})
    except ValidationError as e:
        raise Invalid(field_errors(e.errors(), ("body", "parameters"))) from None
    for key in ("serial", "unmount"):
        if key in body.parameters:
            raise invalid(f"body.parameters.{key}", "set by the batch for each unit")
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == body.station))
        if row is None:
            raise NotFound(f"no station {body.station!r}")
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
                                       batch_id=batch_id, parameters=dict(body.parameters), operator=caller.owner)
    with _sessions(request)() as s:
        return batch_json(s, s.get(Batch, batch_id))


@router.get("/batches/{batch_id}", tags=["batches"])
async def get_batch(batch_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """A batch: status, one row per unit (run id, status, verdict), the waiting prompt and the summary."""
    with _sessions(request)() as s:
        batch = s.get(Batch, batch_id)
        if batch is None:
            raise HTTPException(404, f"no batch {batch_id}")
        return batch_json(s, batch)


__all__ = ["router", "TRANSITIONS", "BATCH", "run_json"]
