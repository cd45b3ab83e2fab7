"""Discrepancy analyses of stored runs (issue 6): ``POST /runs/{id}/analysis`` runs the analyser
(physics.discrepancy) on each unit's recording, ``GET /analyses/{id}`` returns the stored result and
``GET /analyses/{id}/report`` the HTML report (service/report.py).

An analysis takes seconds of CPU (the null simulations that calibrate its tests), so it runs in a
worker thread, at most :data:`CONCURRENT` at a time per service: the run threads that drive the
hardware keep their share of the machine.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select
from sqlalchemy.orm import Session

from physics.calibration import Calibration as PhysCalibration, json_safe
from procedures.states import ACTIVE
from service.runtime import invalid as unprocessable  # raised: a 422 naming the field
from service.auth import Caller, audit, require
from service.db import Analysis, Calibration, Device, Run, Sample

#: Analyses computed at the same time (each holds a worker thread and most of a core).
CONCURRENT = 2
#: Keys the service adds to the analyser's result when it stores it (everything else is the result).
STORED_KEYS = ("run_id", "slot", "serial", "calibration_id", "null_sims", "seed")

router = APIRouter(tags=["analyses"])


class AnalysisIn(BaseModel):
    """What to analyse; every field optional (an empty body analyses every unit of the run)."""

    model_config = ConfigDict(extra="forbid")  # a misspelt field is an error, not silently the default

    slot: int | None = Field(None, ge=0, description="the fixture slot (unit) to analyse; default: every slot with samples")
    null_sims: int = Field(200, ge=0, le=5000, description="simulated null recordings calibrating the tests' false-alarm rate")
    calibration_id: int | None = Field(None, ge=1, description="a stored calibration as the unit's nominal model (the "
                                       "recording's own fit is compared with it: shifted parameters are reported); "
                                       "default: the run's own calibration of the unit, else the unit's current one")


def analysis_json(row: Analysis) -> dict[str, Any]:
    """A stored analysis: the analyser's result plus run_id, slot, serial, calibration_id, and its id,
    time and the address of its HTML report."""
    return {**row.report, "id": row.id, "run_id": row.run_id, "created_at": row.created_at,
            "report_url": f"/analyses/{row.id}/report"}


def analysis_summary(row: Analysis) -> dict[str, Any]:
    """One line of a run's analyses: verdict and the names of the findings."""
    r = row.report or {}
    return {"id": row.id, "run_id": row.run_id, "slot": r.get("slot"), "serial": r.get("serial"),
            "created_at": row.created_at, "verdict": r.get("verdict"), "model": r.get("model"),
            "findings": [f.get("effect") for f in r.get("findings") or [] if isinstance(f, dict)],
            "report_url": f"/analyses/{row.id}/report"}


def _sessions(request: Request) -> Any:
    return request.app.state.sessions


def _slots_lock(request: Request) -> asyncio.Semaphore:
    # per app (each app has its own event loop; a module-level semaphore would bind to the first one)
    sem = getattr(request.app.state, "analysis_slots", None)
    if sem is None:
        sem = request.app.state.analysis_slots = asyncio.Semaphore(CONCURRENT)
    return sem


def _plan(s: Session, run_id: int, body: AnalysisIn) -> tuple[Run, dict[int, tuple[int | None, dict[str, Any] | None]]]:
    """Check the request against the run; the slots to analyse, each with its nominal calibration
    (id and JSON, or None to let the analyser fit one)."""
    run = s.get(Run, run_id)
    if run is None:
        raise HTTPException(404, f"no run {run_id}")
    if run.status in ACTIVE:
        raise HTTPException(409, f"run {run_id} is {run.status}; analyse it when it has ended")
    slots = sorted(s.scalars(select(Sample.slot).where(Sample.run_id == run_id).distinct()))
    if not slots:
        raise HTTPException(409, f"run {run_id} has no samples to analyse")
    if body.slot is not None:
        if body.slot not in slots:
            raise HTTPException(409, f"run {run_id} has no samples from slot {body.slot} "
                                     f"(slots with samples: {', '.join(map(str, slots))})")
        slots = [body.slot]
    plan: dict[int, tuple[int | None, dict[str, Any] | None]] = {}
    if body.calibration_id is not None:
        cal = s.get(Calibration, body.calibration_id)
        if cal is None:
            raise unprocessable("body.calibration_id", f"no calibration {body.calibration_id}")
        if len(slots) > 1:
            raise unprocessable("body.slot", "required with calibration_id: run "
                                f"{run_id} has samples from slots {', '.join(map(str, slots))}")
        plan[slots[0]] = (cal.id, cal.data)
        return run, plan
    for slot in slots:
        cal = s.scalar(select(Calibration).where(Calibration.run_id == run_id, Calibration.slot == slot)
                       .order_by(Calibration.id.desc()).limit(1))
        serial = str((run.serials or {}).get(str(slot)) or "")
        if cal is None and serial:  # e.g. a characterize run: the unit's calibration in force
            cal = s.scalar(select(Calibration).join(Device, Device.id == Calibration.device_id)
                           .where(Device.serial == serial, Calibration.status == "current"))
        plan[slot] = (cal.id, cal.data) if cal is not None else (None, None)
    return run, plan


def _analyse(sessions: Any, run_id: int, slot: int, cal: dict[str, Any] | None, null_sims: int) -> dict[str, Any]:
    """Load one slot's recording and analyse it (in a worker thread): the result to store."""
    from physics.discrepancy import analyze
    from service.store import load_recording

    with sessions() as s:
        run = s.get(Run, run_id)
        rec = load_recording(s, run, slot)
    if rec is None:  # the samples went away between the check and now
        raise HTTPException(409, f"run {run_id} has no samples from slot {slot}")
    try:
        nominal = PhysCalibration.from_json(cal) if cal is not None else None
    except (ValueError, TypeError, KeyError) as e:
        raise unprocessable("body.calibration_id", f"the stored calibration cannot be read: {e}") from None
    seed = [run_id, slot]  # the same run analysed twice gets the same null simulations, so the same p-values
    try:
        a = analyze(rec, nominal, null_sims=null_sims, rng=np.random.default_rng(seed))
    except ValueError as e:  # the recording cannot support the analysis: say why
        raise HTTPException(409, f"run {run_id} slot {slot} cannot be analysed: {e}") from None
    return json_safe({**a.to_json(), "run_id": run_id, "slot": slot, "serial": rec.serial or "",
                  "null_sims": null_sims, "seed": seed})


@router.post("/runs/{run_id}/analysis", status_code=201)
async def create_analysis(run_id: int, request: Request, body: AnalysisIn | None = None,
                          caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Analyse an ended run's recordings (operator): one analysis per unit (slot), or the one asked,
    against the unit's calibration from this run, else its current one (or ``calibration_id``) as
    the nominal model. 201
    with the stored analyses; 404 unknown run, 409 a run still active or without samples, 422 a bad
    body. Takes seconds per unit."""
    body = body or AnalysisIn()
    sessions = _sessions(request)
    with sessions() as s:
        _, plan = _plan(s, run_id, body)
    results: dict[int, dict[str, Any]] = {}
    async with _slots_lock(request):
        for slot, (cal_id, cal) in plan.items():
            results[slot] = {**await asyncio.to_thread(_analyse, sessions, run_id, slot, cal, body.null_sims),
                             "calibration_id": cal_id}
    with sessions() as s:
        rows = [Analysis(run_id=run_id, report=report) for report in results.values()]
        s.add_all(rows)
        s.flush()
        audit(s, caller, "analysis.create", f"run {run_id}",
              {**body.model_dump(), "analyses": [{"id": r.id, "slot": r.report["slot"], "verdict": r.report.get("verdict")}
                                                 for r in rows]})
        s.commit()
        return {"run_id": run_id, "analyses": [analysis_json(r) for r in rows]}


@router.get("/runs/{run_id}/analyses")
def run_analyses(run_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """A run's analyses, oldest first: id, slot, serial, verdict and the names of the findings."""
    with _sessions(request)() as s:
        if s.get(Run, run_id) is None:
            raise HTTPException(404, f"no run {run_id}")
        return [analysis_summary(r) for r in s.scalars(select(Analysis).where(Analysis.run_id == run_id).order_by(Analysis.id))]


def _get(request: Request, analysis_id: int) -> Analysis:
    with _sessions(request)() as s:
        row = s.get(Analysis, analysis_id)
    if row is None:
        raise HTTPException(404, f"no analysis {analysis_id}")
    return row


@router.get("/analyses/{analysis_id}")
def get_analysis(analysis_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One stored analysis (the analyser's JSON plus run_id, slot, serial, calibration_id)."""
    return analysis_json(_get(request, analysis_id))


@router.get("/analyses/{analysis_id}/report", response_class=HTMLResponse)
async def analysis_report(analysis_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> HTMLResponse:
    """The analysis as a self-contained HTML page (tables and the figures the stored result can
    draw; the per-sample plots are in the report ``compasscal analyze --html`` writes)."""
    from service.report import analysis_html

    row = _get(request, analysis_id)
    report = dict(row.report)
    result = {k: v for k, v in report.items() if k not in STORED_KEYS}
    unit = f"slot {report.get('slot')}" + (f" ({report['serial']})" if report.get("serial") else "")
    title = f"Discrepancy analysis {row.id}: run {row.run_id}, {unit}"
    run_url = f"/ui/runs/{row.run_id}" if row.run_id is not None else None
    return HTMLResponse(await asyncio.to_thread(analysis_html, result, None, title, run_url))  # matplotlib: off the loop


__all__ = ["router", "analysis_json", "analysis_summary", "AnalysisIn"]
