"""Discrepancy analyses of stored runs: ``POST /runs/{id}/analysis`` queues one analysis job per unit
and answers at once (202); ``GET /analyses/{id}`` returns its state, progress and, once completed,
the analyser's result (physics.discrepancy); ``GET /analyses/{id}/events`` streams its changes and
``GET /analyses/{id}/report`` is the HTML report (service/report.py).

An analysis takes seconds of CPU (the null simulations that calibrate its tests), so any worker
that takes the analyses' queue computes it (service/worker.py), a few at a time per process.
"""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import HTMLResponse, StreamingResponse
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from physics.calibration import Calibration as PhysCalibration
from physics.discrepancy.analysis import MIN_SAMPLES as TABLE_MIN_SAMPLES
from physics.discrepancy.attitude_free import MIN_SAMPLES as FREE_MIN_SAMPLES
from procedures.states import ACTIVE
from service.auth import Caller, audit, require
from service.db import Analysis, Calibration, Device, Run, Sample
from service.deps import event_stream
from service.runtime import ANALYSIS_FINAL, Conflict, NotFound, analysis_topic, invalid, unit_serial
from service.schemas import ERRORS, AnalysesCreated, AnalysisIn, AnalysisLine, AnalysisOut, Id, content
from service.worker import ANALYSIS_QUEUE

#: Keys the service adds to the analyser's result when it stores it (everything else is the result).
STORED_KEYS = ("run_id", "slot", "serial", "calibration_id", "null_sims")

router = APIRouter(tags=["analyses"])


def analysis_json(row: Analysis) -> dict[str, Any]:
    """An analysis as the API shows it: its state (``queued``, ``running``, ``completed``, ``failed``
    with the reason), progress and addresses, and once completed the analyser's result (plus run_id,
    slot, serial, calibration_id, null_sims; the result's ``seed`` is the recording's fingerprint)."""
    req = row.request or {}
    return {"serial": req.get("serial"), "calibration_id": req.get("calibration_id"), "null_sims": req.get("null_sims"),
            **(row.report or {}), "id": row.id, "run_id": row.run_id, "slot": row.slot, "status": row.status,
            "reason": row.reason, "progress": row.progress, "created_at": row.created_at, "started_at": row.started_at,
            "finished_at": row.finished_at, "url": f"/analyses/{row.id}", "events_url": f"/analyses/{row.id}/events",
            "report_url": f"/analyses/{row.id}/report" if row.status == "completed" else None}


def analysis_summary(row: Analysis) -> dict[str, Any]:
    """One line of a run's analyses: state, verdict and the names of the findings."""
    r, req = row.report or {}, row.request or {}
    return {"id": row.id, "run_id": row.run_id, "slot": row.slot, "serial": r.get("serial", req.get("serial")),
            "created_at": row.created_at, "status": row.status, "reason": row.reason, "progress": row.progress,
            "verdict": r.get("verdict"), "model": r.get("model"),
            "findings": [f.get("effect") for f in r.get("findings") or [] if isinstance(f, dict)],
            "report_url": f"/analyses/{row.id}/report" if row.status == "completed" else None}


def _plan(s: Session, run_id: int, body: AnalysisIn) -> tuple[Run, dict[int, int | None]]:
    """Check the request against the run; the slots to analyse, each with its nominal calibration's
    id (None to let the analyser fit one)."""
    run = s.get(Run, run_id)
    if run is None:
        raise NotFound(f"no run {run_id}")
    if run.status in ACTIVE:
        raise Conflict(f"run {run_id} is {run.status}; analyse it when it has ended")
    # samples, and samples with table angles, per slot: what the analysis needs is known before it is queued
    counts = {slot: (n, angled) for slot, n, angled in s.execute(
        select(Sample.slot, func.count(), func.count(Sample.psi_t)).where(Sample.run_id == run_id).group_by(Sample.slot))}
    slots = sorted(counts)
    if not slots:
        raise Conflict(f"run {run_id} has no samples to analyse")
    if body.slot is not None and body.slot not in slots:
        raise invalid("body.slot", f"run {run_id} has no samples from slot {body.slot} "
                                   f"(slots with samples: {', '.join(map(str, slots))})")

    def short(slot: int) -> str | None:  # why the analysis of a slot would fail for want of samples (it was queued)
        n, angled = counts[slot]
        need = TABLE_MIN_SAMPLES if angled else FREE_MIN_SAMPLES
        return f"slot {slot}: {n} samples, the analysis needs at least {need}" if n < need else None

    why = {x: short(x) for x in ([body.slot] if body.slot is not None else slots)}
    if body.slot is not None and why[body.slot]:
        raise invalid("body.slot", f"run {run_id} {why[body.slot]}")
    if all(why.values()):
        raise Conflict(f"run {run_id} has too few samples to analyse: {'; '.join(map(str, why.values()))}")
    slots = [x for x, w in why.items() if not w]
    if body.calibration_id is not None:
        cal = s.get(Calibration, body.calibration_id)
        if cal is None:
            raise invalid("body.calibration_id", f"no calibration {body.calibration_id}")
        try:
            PhysCalibration.from_json(cal.data)
        except (ValueError, TypeError, KeyError) as e:
            raise invalid("body.calibration_id", f"the stored calibration cannot be read: {e}") from None
        if len(slots) > 1:
            raise invalid("body.slot", "required with calibration_id: run "
                          f"{run_id} has samples from slots {', '.join(map(str, slots))}")
        # another unit's calibration makes every difference between two units a "parameter shift"
        owner, unit = s.get(Device, cal.device_id).serial, unit_serial(run, slots[0])
        if unit and owner != unit:
            raise invalid("body.calibration_id", f"calibration {cal.id} is of unit {owner}, not of the unit of run "
                                                 f"{run_id} slot {slots[0]} ({unit}): give one of {unit}'s calibrations")
        return run, {slots[0]: cal.id}
    plan: dict[int, int | None] = {}
    for slot in slots:
        cal_id = s.scalar(select(Calibration.id).where(Calibration.run_id == run_id, Calibration.slot == slot)
                          .order_by(Calibration.id.desc()).limit(1))
        serial = unit_serial(run, slot)
        if cal_id is None and serial:  # e.g. a characterize run: the unit's calibration in force
            cal_id = s.scalar(select(Calibration.id).join(Device, Device.id == Calibration.device_id)
                              .where(Device.serial == serial, Calibration.status == "current"))
        plan[slot] = cal_id
    return run, plan


@router.post("/runs/{run_id}/analysis", status_code=202, response_model=AnalysesCreated, responses=ERRORS)
async def create_analysis(run_id: Id, request: Request, response: Response, body: AnalysisIn | None = None,
                          caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Analyse an ended run's recordings (operator): one analysis per unit (slot), or the one asked,
    against the unit's calibration from this run, else its current one (or ``calibration_id``) as
    the nominal model. Answers 202 at once with the analyses ``queued``: follow each at its ``url``
    (poll) or ``events_url`` (server-sent events) until ``completed`` (or ``failed``, with the
    reason). The same analysis asked again while it waits or runs answers with that one. 404 unknown run,
    409 a run still active or with too few samples, 422 a bad body (a slot without samples, or with too few)."""
    body = body or AnalysisIn()
    sessions = request.app.state.sessions

    def create() -> tuple[list[int], list[int]]:
        """The analyses answering the request, and those of them made now (to queue)."""
        with sessions() as s:
            run, plan = _plan(s, run_id, body)
            ids: list[int] = []
            new: list[Analysis] = []
            for slot, cal_id in plan.items():
                asked = {"null_sims": body.null_sims, "calibration_id": cal_id}
                # the same analysis asked again while it waits or runs is that one (a script's retry queued
                # four of one run and slot, some of 200 null simulations each)
                same = next((a for a in s.scalars(select(Analysis).where(
                    Analysis.run_id == run_id, Analysis.slot == slot, Analysis.status.in_(("queued", "running"))))
                    if all((a.request or {}).get(k) == v for k, v in asked.items())), None)
                if same is not None:
                    ids.append(same.id)
                    continue
                row = Analysis(run_id=run_id, slot=slot, status="queued", report=None,
                               request={**asked, "serial": unit_serial(run, slot) or None, "operator": caller.owner})
                s.add(row)
                s.flush()
                ids.append(row.id)
                new.append(row)
            if new:
                audit(s, caller, "analysis.create", f"run {run_id}",
                      {**body.model_dump(), "analyses": [{"id": r.id, "slot": r.slot} for r in new]})
            s.commit()
            return ids, [r.id for r in new]
    ids, new = await asyncio.to_thread(create)
    for analysis_id in new:
        await request.app.state.jobs.defer("analysis", queue=ANALYSIS_QUEUE, analysis_id=analysis_id)
    response.headers["Location"] = f"/analyses/{ids[0]}"
    with sessions() as s:
        rows = [s.get(Analysis, i) for i in ids]
        return {"run_id": run_id, "analyses": [analysis_json(r) for r in rows]}


@router.get("/runs/{run_id}/analyses", response_model=list[AnalysisLine], responses=ERRORS)
def run_analyses(run_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """A run's analyses, oldest first: id, slot, serial, state, verdict and the names of the findings."""
    with request.app.state.sessions() as s:
        if s.get(Run, run_id) is None:
            raise NotFound(f"no run {run_id}")
        return [analysis_summary(r) for r in s.scalars(select(Analysis).where(Analysis.run_id == run_id).order_by(Analysis.id))]


def _get(request: Request, analysis_id: int) -> Analysis:
    with request.app.state.sessions() as s:
        row = s.get(Analysis, analysis_id)
    if row is None:
        raise NotFound(f"no analysis {analysis_id}")
    return row


@router.get("/analyses/{analysis_id}", response_model=AnalysisOut, responses=ERRORS)
def get_analysis(analysis_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One analysis: its state and progress, and once completed the analyser's result."""
    return analysis_json(_get(request, analysis_id))


@router.get("/analyses/{analysis_id}/events", response_class=StreamingResponse,
            responses=content("text/event-stream", "server-sent events: the analysis's state at each change"))
async def analysis_events(analysis_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> StreamingResponse:
    """Server-sent events of an analysis: a ``state`` event (status, progress, reason) at each change
    until it has ended. The event id is the analysis's version: ``Last-Event-ID`` resumes after it."""
    _get(request, analysis_id)

    def read(after: int) -> tuple[list[tuple[int, str, dict[str, Any]]], bool]:
        with request.app.state.sessions() as s:
            row = s.get(Analysis, analysis_id)
            over = row.status in ANALYSIS_FINAL
            data = {"id": row.id, "status": row.status, "progress": row.progress, "reason": row.reason,
                    "verdict": (row.report or {}).get("verdict")}
            return ([(row.version, "state", data)] if row.version > after else []), over
    return event_stream(request, analysis_topic(analysis_id), read)


@router.get("/analyses/{analysis_id}/report", response_class=HTMLResponse,
            responses=content("text/html", "the analysis report, a self-contained page"))
async def analysis_report(analysis_id: Id, request: Request, _: Caller = Depends(require("viewer"))) -> HTMLResponse:
    """The analysis as a self-contained HTML page (tables and the figures the stored result can
    draw; the per-sample plots are in the report ``compasscal analyze --html`` writes). 409 until
    the analysis has completed."""
    from service.report import analysis_html

    row = _get(request, analysis_id)
    if row.status != "completed":
        raise Conflict(f"analysis {analysis_id} is {row.status}" + (f": {row.reason}" if row.reason else "")
                       + "; its report exists once it has completed")
    report = dict(row.report or {})
    result = {k: v for k, v in report.items() if k not in STORED_KEYS}
    unit = f"slot {report.get('slot')}" + (f" ({report['serial']})" if report.get("serial") else "")
    title = f"Discrepancy analysis {row.id}: run {row.run_id}, {unit}"
    run_url = f"/ui/runs/{row.run_id}" if row.run_id is not None else None
    return HTMLResponse(await asyncio.to_thread(analysis_html, result, None, title, run_url))  # matplotlib: off the loop


__all__ = ["router", "analysis_json", "analysis_summary"]
