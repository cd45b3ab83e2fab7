"""Stations: ``/stations`` (list, create, change) and ``/stations/{name}/reset``.

A station goes to ``fault`` when its hardware cannot be opened, a run fails on the table's account
(an axis fault, Modbus), or its worker was lost mid-run. It stays there, refusing runs, until
``POST /stations/{name}/reset`` (a job for its worker) resets the axis faults.
"""

from __future__ import annotations

import uuid
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse
from sqlalchemy import select
from sqlalchemy.orm import Session

from drivers.station import hardware_key
from service.auth import Caller, audit, require
from service.db import Run, Station
from service.deps import sessions
from service.identity import DEFAULT_POLICY
from service.runtime import CONFIRM_S, Conflict, NotFound, Unavailable, invalid, run_json, station_json, wait_for
from service.schemas import (ERRORS, StationConfigIn, StationDetail, StationIn, StationName, StationOut, StationPatchIn,
                             StationResetOut, StationResetRefusedOut)
from service.worker import station_queue

router = APIRouter(tags=["stations"])


@router.get("/stations", response_model=list[StationOut], responses=ERRORS)
async def list_stations(request: Request, _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Every station with its state (idle, running, paused, fault), current run and worker."""
    with sessions(request)() as s:
        rows = s.scalars(select(Station).order_by(Station.name)).all()
    return [station_json(r) for r in rows]


def _hardware_free(s: Session, name: str, modbus: str, compasses: list[str]) -> None:
    """409 when another station already has this table or one of these compasses: two stations on one
    table would move it under each other's runs (a probe's second station failed with "port lost")."""
    # compared by the device each URL reaches: "tcp://localhost:5020?timeout=0.8" or "rtu+tcp://127.0.0.1:5020"
    # is the table of "tcp://127.0.0.1:5020" (a probe's second station so spelled moved that table during the
    # first one's run, and certified a unit)
    table = hardware_key(modbus, modbus=True)
    mine = {hardware_key(u): u for u in compasses}
    for other in s.scalars(select(Station).where(Station.name != name)):
        shared = [mine[k] for k in (hardware_key(u) for u in other.compasses or []) if k in mine]
        same_table = hardware_key(other.modbus, modbus=True) == table
        if same_table or shared:
            what = (f"table {modbus}" + (f" (as {other.modbus})" if other.modbus != modbus else "") if same_table
                    else f"compass {shared[0]}")
            raise HTTPException(409, f"station {other.name!r} already has {what}; one piece of hardware belongs to one "
                                     f"station (give {other.name!r} other hardware with PUT /stations/{other.name} first)")


@router.post("/stations", status_code=201, response_model=StationOut, responses=ERRORS)
async def create_station(body: StationIn, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Add a station (admin). 409 if the name is taken."""
    with sessions(request)() as s:
        if s.scalar(select(Station.id).where(Station.name == body.name)) is not None:
            raise HTTPException(409, f"station {body.name!r} exists")
        _hardware_free(s, body.name, body.modbus, list(body.compasses))
        row = Station(name=body.name, modbus=body.modbus, compasses=list(body.compasses), time_scale=body.time_scale,
                      state="idle", serial_policy=body.serial_policy or DEFAULT_POLICY)
        s.add(row)
        audit(s, caller, "station.create", body.name, body.model_dump())
        s.commit()
        return station_json(row)


def _same_name(body: StationConfigIn, name: str) -> None:
    """422 when the body names another station than the path (a station keeps its name)."""
    if body.name is not None and body.name != name:
        raise invalid("body.name", f"{body.name!r} is not the station of the path, {name!r} (a station keeps its name)")


def _idle(row: Station) -> None:
    """409 while a run uses the station: its settings change only when it is idle."""
    if row.run_id is not None:
        raise HTTPException(409, f"station {row.name!r} is {row.state} (run {row.run_id}); change it when idle")


@router.put("/stations/{name}", response_model=StationOut, responses=ERRORS)
async def put_station(name: StationName, body: StationConfigIn, request: Request,
                      caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Create a station or change its URLs or serial policy (admin), e.g. after moving a table to another
    gateway. 409 while a run uses it; runs already made keep the configuration they ran with."""
    # the same checks as POST: the name in the path has StationIn.name's type (a bad one: 422 path.name)
    _same_name(body, name)
    full = StationIn.model_construct(**{**body.model_dump(), "name": name})
    with sessions(request)() as s:
        _hardware_free(s, name, full.modbus, list(full.compasses))
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            row = Station(name=name, modbus=full.modbus, compasses=list(full.compasses), time_scale=full.time_scale,
                          state="idle", serial_policy=full.serial_policy or DEFAULT_POLICY)
            s.add(row)
        else:
            _idle(row)
            row.modbus, row.compasses = full.modbus, list(full.compasses)
            # omitted: kept (a URL change reset a simulator's time scale 20 to 1, and its next run's samples
            # were stamped 20 times too close together, without a word; nor may it reset the policy)
            if "time_scale" in body.model_fields_set:
                row.time_scale = full.time_scale
            if full.serial_policy is not None:
                row.serial_policy = full.serial_policy
        audit(s, caller, "station.put", name, {**full.model_dump(), "time_scale": row.time_scale,
                                               "serial_policy": row.serial_policy})
        s.commit()
        return station_json(row)


@router.patch("/stations/{name}", response_model=StationOut, responses=ERRORS)
async def patch_station(name: StationName, body: StationPatchIn, request: Request,
                        caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Change some of a station's settings (admin), e.g. ``{"serial_policy": "refuse"}``: what is given changes,
    the rest is kept (PUT wants the URLs as well). 404 for no such station, 409 while a run uses it."""
    _same_name(body, name)
    with sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            raise HTTPException(404, f"no station {name!r} (create it with POST /stations or PUT /stations/{name})")
        _idle(row)
        modbus = body.modbus if body.modbus is not None else row.modbus
        compasses = list(body.compasses) if body.compasses is not None else list(row.compasses or [])
        _hardware_free(s, name, modbus, compasses)
        row.modbus, row.compasses = modbus, compasses
        if body.time_scale is not None:
            row.time_scale = body.time_scale
        if body.serial_policy is not None:
            row.serial_policy = body.serial_policy
        audit(s, caller, "station.patch", name, body.model_dump(exclude_unset=True))
        s.commit()
        return station_json(row)


@router.get("/stations/{name}", response_model=StationDetail, responses=ERRORS)
async def get_station(name: StationName, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One station: configuration, state, current run (with its status and prompts), fault, worker."""
    with sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            raise HTTPException(404, f"no station {name!r}")
        out = station_json(row)
        run = s.get(Run, row.run_id) if row.run_id is not None else None
        out["run"] = run_json(run) if run is not None else None
    return out


@router.post("/stations/{name}/reset", response_model=StationResetOut, responses={**ERRORS, 503: {"model": StationResetRefusedOut, "description": "the table, an axis, a compass or the station's worker does not answer, or an axis is still faulted"}})
async def reset_station(name: StationName, request: Request, caller: Caller = Depends(require("operator"))) -> Any:
    """Reset the table's axis faults, check that every compass answers, and make the station idle
    (operator), through the station's worker. 409 while a run uses it; 503 when the table cannot be
    reached, an axis is still faulted, a compass does not answer, or no worker of the station takes
    the reset in time (then it is cancelled, not left to run later)."""
    with sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            raise NotFound(f"no station {name!r}")
        if row.run_id is not None:
            raise Conflict(f"station {name} is busy with run {row.run_id}; abort it first")
        before = row.reason
    token = uuid.uuid4().hex
    await request.app.state.jobs.defer("reset", queue=station_queue(name), lock=station_queue(name), station=name, token=token)

    def outcome() -> dict[str, Any] | None:
        with sessions(request)() as s:
            r = s.scalar(select(Station).where(Station.name == name))
            return r.reset if r is not None and (r.reset or {}).get("token") == token else None
    got = await wait_for(outcome, CONFIRM_S)
    if not got.ok:
        if await request.app.state.jobs.cancel_queued("reset", station_queue(name), token=token):
            # (left queued, it ran whenever a worker came, unasked: repeated clicks queued several)
            raise Unavailable(f"no worker of station {name} took the reset within {CONFIRM_S:g} s, so it was "
                              f"cancelled; start `compasscal worker --station {name}`, then reset again")
        raise Unavailable(f"the reset of station {name} is still going on after {CONFIRM_S:g} s; "
                          f"GET /stations/{name} shows its outcome")
    out = {k: v for k, v in got.value.items() if k not in ("token", "ok", "status", "error")}
    if not got.value.get("ok"):
        with sessions(request)() as s:  # an attempt on the hardware: logged even when it failed
            audit(s, caller, "station.reset", name, {"ok": False, "error": got.value.get("error")})
            s.commit()
        raise HTTPException(int(got.value.get("status") or 503), got.value.get("error"))
    with sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row.state == "fault":
            audit(s, caller, "station.reset", name, {"ok": False, "error": row.reason, **out})
            s.commit()
            # which axes and compasses, by name, beside the sentence (the README promised silent_compasses)
            return JSONResponse(status_code=503, content=jsonable_encoder(
                {"detail": f"station {name}: {row.reason}", **{k: out.get(k) for k in ("reset_axes", "still_faulted",
                                                                                       "silent_compasses") if k in out}}))
        audit(s, caller, "station.reset", name, {"ok": True, "fault": before, **out})
        s.commit()
        return {**station_json(row), **out}
