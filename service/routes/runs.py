"""Runs: start one, list and read them, pause, resume or abort, stream their events, download
their samples, answer their prompts. Each answer comes from the database, so the API holds no run
state and can run as several processes; the hardware is the workers' (service/worker.py), the
rules (claiming a station, the run's state machine, commands) are the run-time layer's
(service/runtime.py).

A run is ``queued`` (created; waiting for its station's worker, which then opens the hardware), then
``running``, ``paused``, and ends ``completed``, ``failed`` or ``aborted``. ``PUT /runs/{id}/state``
accepts only the operator transitions of :mod:`procedures.states`; anything else is 409 naming from
and to. A pause takes effect at the procedure's next checkpoint (the table holds still there): until
the worker reports it, the run stays ``running`` with ``pause_requested`` true; ``running ->
running`` then withdraws the request. A run is reported ``completed`` only after its calibrations are
stored and its station is free again.
"""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import select
from sqlalchemy.orm import Session

from physics.recording import format_recording
from procedures.calibrate import PROCEDURES
from procedures.states import ACTIVE, RunState
from service.auth import Caller, audit, require
from service.db import Calibration, Device, Run, RunCommand
from service.deps import event_stream, sessions
from service.runtime import (CONFIRM_S, SOFTWARE_VERSION, Conflict, NotFound, Unavailable, create_run, events_after, finish_unstarted,
                             invalid, queue_answer, request_state, run_json, runs_of_serial, station_filter, wait_for)
from service.schemas import (ERRORS, AnswerIn, AnswerOut, ErrorOut, Id, Index, Name, ProcedureOut, RunDetail, RunIn, RunOut, RunStateOut,
                             SerialSearch, StateIn, StationName, content)
from service.store import load_recording
from service.worker import station_queue

router = APIRouter(tags=["runs"])


def _get_run(s: Session, run_id: int) -> Run:
    row = s.get(Run, run_id)
    if row is None:
        raise NotFound(f"no run {run_id}")
    return row


@router.get("/procedures", response_model=list[ProcedureOut], responses=ERRORS)
def list_procedures(caller: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """The procedures a run can take (viewer), each with its parameters' JSON Schema: the names,
    types, defaults and ranges ``parameters`` of ``POST /runs`` accepts (``POST /batches`` takes
    those of ``calibrate``)."""
    return [{"name": p.name, "version": p.version, "doc": p.doc, "parameters": p.params.model_json_schema()}
            for p in PROCEDURES.values()]


@router.post("/runs", status_code=202, response_model=RunOut, responses=ERRORS)
async def create_run_route(body: RunIn, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Start a run (operator): 202 with the run (status ``queued``); follow it with ``GET /runs/{id}``
    or ``GET /runs/{id}/events``. With ``resume``, continue an interrupted run from its last checkpoint.
    404 unknown station, 422 bad procedure/parameters/serials/resume, 409 busy or nothing to resume."""
    def create() -> Run:
        with sessions(request)() as s:
            return create_run(s, body.station, body.procedure, body.parameters, body.serials, caller.owner,
                              SOFTWARE_VERSION, resume=body.resume, serial_policy=body.serial_policy)
    run = await asyncio.to_thread(create)
    job = await request.app.state.jobs.defer("run", queue=station_queue(body.station), lock=station_queue(body.station),
                                             run_id=run.id)
    with sessions(request)() as s:
        row = s.get(Run, run.id)
        row.meta = {**(row.meta or {}), "job_id": job}
        audit(s, caller, "run.start", f"run {run.id}", {"station": body.station, "procedure": run.procedure,
                                                         "parameters": run.parameters, "serials": run.serials,
                                                         "serial_policy": (run.meta or {}).get("serial_policy"),
                                                         **({"resume": body.resume} if body.resume else {})})
        s.commit()
        return run_json(row)


@router.get("/runs", response_model=list[RunOut], responses=ERRORS)
async def list_runs(request: Request, station: StationName | None = None, status: RunState | None = None,
                    procedure: Name | None = None, serial: SerialSearch | None = None,
                    limit: int = Query(50, ge=1, le=1000), offset: Index = 0,
                    _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Runs, newest first, filtered by station name, status, procedure and unit serial number (typed for
    the run, reported by its unit, or certified under)."""
    q = select(Run)
    if status is not None:
        q = q.where(Run.status == status.value)
    if procedure is not None:
        known = sorted([*PROCEDURES, "import"])  # (import: an uploaded recording's run, routes/recordings.py)
        if procedure not in known:  # (an unknown one listed nothing, as if no run had been made)
            raise invalid("query.procedure", f"unknown procedure {procedure!r}; known: {', '.join(known)}")
        q = q.where(Run.procedure == procedure)
    if serial is not None:
        q = q.where(runs_of_serial(serial))
    with sessions(request)() as s:
        if station is not None:
            q = q.where(Run.station_id == station_filter(s, station))
        rows = s.scalars(q.order_by(Run.created_at.desc(), Run.id.desc()).limit(limit).offset(offset)).all()
        return [run_json(r) for r in rows]


@router.get("/runs/{run_id}", response_model=RunDetail, responses=ERRORS)
async def get_run(run_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One run: provenance, live status, waiting prompts, progress, result and its calibrations."""
    with sessions(request)() as s:
        row = _get_run(s, run_id)
        out = run_json(row)
        cals = s.execute(select(Calibration, Device.serial).join(Device, Device.id == Calibration.device_id)
                         .where(Calibration.run_id == run_id).order_by(Calibration.slot)).all()
    out["calibrations"] = [{"id": c.id, "slot": c.slot, "serial": serial, "status": c.status, "verdict": c.verdict,
                            "reasons": c.reasons, "identity": c.identity} for c, serial in cals]
    return out


async def change_run_state(request: Request, run_id: int, state: str, reason: str | None) -> str:
    """Queue an operator's state change of a run for its worker (an abort of a run no worker has taken
    ends it here); what it does. NotFound, or Conflict naming the transition the run's state refuses."""
    with sessions(request)() as s:
        what, queued = request_state(s, run_id, state, reason)
        job = (s.get(Run, run_id).meta or {}).get("job_id")
    if queued and job is not None and await request.app.state.jobs.cancel(int(job)):
        # no worker had taken it: end it here (else its worker sees the command before touching the table)
        with sessions(request)() as s:
            finish_unstarted(s, run_id, RunState.aborted.value, reason or "aborted by the operator")
        request.app.state.notifier.poke(run_id)
    return what


@router.put("/runs/{run_id}/state", status_code=202, response_model=RunStateOut, responses=ERRORS)
async def put_run_state(run_id: Id, body: StateIn, request: Request,
                        caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Pause, resume or abort (operator), checked against the run's state machine (409 otherwise).
    202: a pause takes effect at the next checkpoint, an abort as soon as the current step ends."""
    what = await change_run_state(request, run_id, body.state, body.reason)
    with sessions(request)() as s:
        audit(s, caller, "run.state", f"run {run_id}", {"state": body.state, "reason": body.reason, "action": what})
        s.commit()
        out = run_json(_get_run(s, run_id))
    return {**out, "requested": body.state, "action": what}


@router.get("/runs/{run_id}/events", response_class=StreamingResponse,
            responses=content("text/event-stream", "server-sent events: state, step, progress, samples, prompt, result"))
async def run_events(run_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> StreamingResponse:
    """Server-sent events (state, step, progress, samples, prompt, result): the run's history from
    the database, then live events until it ends, from whichever process runs it. A
    ``Last-Event-ID`` header resumes after that event (ids increase; any API process understands them)."""
    with sessions(request)() as s:
        _get_run(s, run_id)

    def read(after: int) -> tuple[list[tuple[int, str, dict[str, Any]]], bool]:
        with sessions(request)() as s:
            rows = [(e.id, e.kind, e.data) for e in events_after(s, run_id, after)]
            status = s.scalar(select(Run.status).where(Run.id == run_id))
        return rows, status not in ACTIVE
    return event_stream(request, run_id, read)


@router.get("/runs/{run_id}/samples", response_class=Response,
            responses=content("text/csv", "the slot's samples as a RECORDING.md CSV"))
async def run_samples(run_id: Id, request: Request, slot: Index = 0,
                      _: Caller = Depends(require("viewer"))) -> Response:
    """One slot's samples as a RECORDING.md CSV (404 when it has none)."""
    def build() -> str | None:
        with sessions(request)() as s:
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


@router.post("/runs/{run_id}/prompts/{prompt_id}", response_model=AnswerOut, responses={**ERRORS, 503: {"model": ErrorOut, "description": "the run's worker did not take the answer"}})
async def answer_prompt(run_id: Id, prompt_id: Name, body: AnswerIn, request: Request,
                        caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Answer a waiting operator prompt (operator); 404 when the run has no such prompt waiting, 422
    when a serial prompt (``serial-SLOT``) gets another answer than typed, identified or skip.
    Answers once the run's worker has taken the answer (503 if it does not within a few seconds; 409 when
    the run ended first, e.g. its worker lost: the answer was not taken)."""
    with sessions(request)() as s:
        command_id = queue_answer(s, run_id, prompt_id, body.answer)

    def taken() -> str | None:
        """"taken"; or why the answer never will be (the run ended first); None while it waits."""
        with sessions(request)() as s:
            row, command = s.get(Run, run_id), s.get(RunCommand, command_id)
            if command.taken_at is not None or (row.status in ACTIVE and prompt_id not in (row.prompts or {})):
                return "taken"
            # ended before its worker read the answer (its worker lost meanwhile): a 200 said it was taken
            return None if row.status in ACTIVE else f"{row.status}" + (f": {row.reason}" if row.reason else "")
    waited = await wait_for(taken, CONFIRM_S, every=0.05)
    if not waited.ok:
        raise Unavailable(f"run {run_id}'s worker did not take the answer within {CONFIRM_S:g} s (it is kept for it)")
    if waited.value != "taken":
        raise Conflict(f"run {run_id} ended ({waited.value}) before its worker took the answer: the answer was not taken")
    with sessions(request)() as s:
        audit(s, caller, "run.prompt", f"run {run_id}", {"prompt": prompt_id, "answer": body.answer})
        s.commit()
    return {"run_id": run_id, "prompt": prompt_id, "answer": body.answer}
