"""The FastAPI application: health, devices and their calibration history, acceptance limits,
uploads of foreign recordings. Stations, runs and batches live in service/runs.py, with the run
manager that owns the hardware. OpenAPI at /docs.
"""

from __future__ import annotations

import asyncio
import json
from contextlib import asynccontextmanager
from typing import Any, AsyncIterator

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request, Response
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy import Text, cast, func, select
from sqlalchemy.orm import Session

from physics.recording import RecordingError, parse_recording
from service.auth import Caller, audit, require
from service.db import Calibration, Device, Limit, Run, make_engine, sessions, upgrade
from service.runtime import SOFTWARE_VERSION, DomainError, field_errors, invalid
from service.store import insert_samples


#: Largest accepted upload (a recording of a few hours at 100 Hz).
MAX_UPLOAD_BYTES = 50 * 1024 * 1024

router = APIRouter()


def unprocessable(field: str, problem: str) -> HTTPException:
    """A 422 for one field, in the same shape as :func:`service.runtime.invalid`."""
    return HTTPException(422, invalid(field, problem).detail)


def db(request: Request) -> Session:
    """A session per request (FastAPI dependency)."""
    with request.app.state.sessions() as session:
        yield session


@router.get("/health", tags=["service"])
def health(request: Request) -> dict[str, Any]:
    """Liveness and the database in use; needs no key."""
    with request.app.state.sessions() as session:
        session.execute(select(1))
    return {"status": "ok", "version": SOFTWARE_VERSION, "database": request.app.state.engine.dialect.name}


# ------------------------------------------------------------------------------------------ devices

def calibration_json(row: Calibration) -> dict[str, Any]:
    """A stored calibration: the physics JSON plus its id, run, time, status and verdict."""
    return {**row.data, "id": row.id, "run_id": row.run_id, "created_at": row.created_at, "status": row.status,
            "verdict": row.verdict, "reasons": row.reasons, "serial": row.device.serial}


def _device(session: Session, serial: str) -> Device:
    dev = session.scalar(select(Device).where(Device.serial == serial))
    if dev is None:
        raise HTTPException(404, f"no device with serial number {serial!r}")
    return dev


@router.get("/devices/{serial}", tags=["devices"])
def get_device(serial: str, session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """A unit: model, firmware, number of calibrations and the current one's id."""
    dev = _device(session, serial)
    count = session.scalar(select(func.count()).select_from(Calibration).where(Calibration.device_id == dev.id))
    current = session.scalar(select(Calibration.id).where(Calibration.device_id == dev.id, Calibration.status == "current"))
    return {"serial": dev.serial, "model": dev.model, "firmware": dev.firmware, "created_at": dev.created_at,
            "calibrations": count, "current_calibration_id": current}


@router.get("/devices/{serial}/calibrations", tags=["devices"])
async def device_calibrations(request: Request, serial: str, limit: int = Query(100, ge=1, le=1000),
                              offset: int = Query(0, ge=0), _: Caller = Depends(require("viewer"))) -> Response:
    """The unit's calibration history, newest first (status current, superseded or rejected), with
    the figures the acceptance limits judged; the full documents are at /calibrations/{id}."""
    # The quality engineers' most frequent query: one indexed query of small columns on the event
    # loop (no thread-pool hops), the stored JSON spliced in as text instead of decoded and re-encoded.
    with request.app.state.sessions() as session:
        rows = session.execute(
            select(Calibration.id, Calibration.run_id, Calibration.created_at, Calibration.status, Calibration.verdict,
                   cast(Calibration.reasons, Text), Calibration.method, Calibration.slot, cast(Calibration.figures, Text))
            .join(Device, Device.id == Calibration.device_id).where(Device.serial == serial)
            .order_by(Calibration.created_at.desc(), Calibration.id.desc()).limit(limit).offset(offset)).all()
        if not rows and offset == 0:
            _device(session, serial)  # 404 for an unknown serial; a known one may have no calibrations
    body = ",".join(
        f'{{"id":{r[0]},"run_id":{r[1]},"created_at":"{r[2].isoformat()}","status":"{r[3]}","verdict":"{r[4]}",'
        f'"reasons":{r[5] or "[]"},"method":{json.dumps(r[6])},"slot":{r[7]},"figures":{r[8] or "null"}}}' for r in rows)
    return Response(f"[{body}]", media_type="application/json")


@router.get("/devices/{serial}/calibrations/current", tags=["devices"])
def current_calibration(serial: str, session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """The calibration in force (the physics calibration JSON plus id, run_id, created_at, verdict)."""
    dev = _device(session, serial)
    row = session.scalar(select(Calibration).where(Calibration.device_id == dev.id, Calibration.status == "current"))
    if row is None:
        raise HTTPException(404, f"{serial!r} has no current calibration")
    return calibration_json(row)


@router.get("/calibrations/{cal_id}", tags=["devices"])
def get_calibration(cal_id: int, session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One stored calibration by id."""
    row = session.get(Calibration, cal_id)
    if row is None:
        raise HTTPException(404, f"no calibration {cal_id}")
    return calibration_json(row)


# ------------------------------------------------------------------------------------------- limits

class LimitIn(BaseModel):
    """An acceptance limit: above ``marginal`` MARGINAL, above ``fail`` FAIL."""

    marginal: float = Field(ge=0)
    fail: float = Field(ge=0)


@router.get("/limits", tags=["limits"])
def get_limits(session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """The acceptance limits every new calibration is judged by."""
    return [{"name": r.name, "marginal": r.marginal, "fail": r.fail, "unit": r.unit, "description": r.description}
            for r in session.scalars(select(Limit).order_by(Limit.name))]


@router.put("/limits/{name}", tags=["limits"])
def put_limit(name: str, body: LimitIn, session: Session = Depends(db), caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Change one limit (admin). Calibrations already judged keep their verdicts."""
    row = session.get(Limit, name)
    if row is None:
        raise HTTPException(404, f"no limit {name!r}; known: " + ", ".join(session.scalars(select(Limit.name))))
    if body.fail < body.marginal:
        raise unprocessable("body.fail", "must be >= marginal")
    old = {"marginal": row.marginal, "fail": row.fail}
    row.marginal, row.fail = body.marginal, body.fail
    audit(session, caller, "limit.update", name, {"old": old, "new": body.model_dump()})
    session.commit()
    return {"name": name, **body.model_dump(), "unit": row.unit}


# ------------------------------------------------------------------------------------------ uploads

@router.post("/recordings", status_code=201, tags=["runs"])
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
        raise unprocessable("body", "not UTF-8 text") from None
    except RecordingError as e:
        raise unprocessable("body", str(e)) from None
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


# -------------------------------------------------------------------------------------------- app

def create_app(database_url: str | None = None, worker: bool = True) -> FastAPI:
    """The service. The database is upgraded to the newest migration on start.

    ``worker``: run a worker for every station in this process (the default; the only way on SQLite,
    whose job queue lives in memory). Off when the stations have workers of their own
    (``compasscal worker``) and the API runs as several processes (``compasscal serve --workers N``)."""
    from service.analyses import router as analyses_router
    from service.db import default_url
    from service.runs import router as runs_router
    from service.runtime import HEARTBEAT_S, LOST_AFTER_S, Notifier, reap_lost_workers
    from service.web import router as web_router
    from service.worker import Jobs, WorkerContext

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        url = database_url or default_url()
        engine = make_engine(url)
        await asyncio.to_thread(upgrade, engine)
        app.state.engine = engine
        app.state.sessions = sessions(engine)
        app.state.notifier = Notifier(url)
        await app.state.notifier.start()
        app.state.jobs = Jobs(url, WorkerContext(app.state.sessions, SOFTWARE_VERSION, poke=app.state.notifier.poke),
                              embedded=worker)
        await app.state.jobs.start()

        async def reap() -> None:  # runs whose worker died: failed, "worker lost"
            loop = asyncio.get_running_loop()
            reachable_since = loop.time()
            while True:
                await asyncio.sleep(HEARTBEAT_S)
                if loop.time() - reachable_since < LOST_AFTER_S:
                    # after the database was away, workers need a few beats too: judge none before
                    try:
                        await asyncio.to_thread(reap_lost_workers, app.state.sessions, judge=False)
                    except Exception:  # noqa: BLE001 - still away
                        reachable_since = loop.time()
                    continue
                try:
                    for run_id in await asyncio.to_thread(reap_lost_workers, app.state.sessions):
                        app.state.notifier.poke(run_id)
                except Exception:  # noqa: BLE001 - the database is away for a moment
                    reachable_since = loop.time()
        reaper = asyncio.create_task(reap())
        try:
            yield
        finally:
            reaper.cancel()
            await asyncio.gather(reaper, return_exceptions=True)
            await app.state.jobs.stop()
            await app.state.notifier.stop()
            engine.dispose()

    app = FastAPI(title="compasscal", version=SOFTWARE_VERSION, lifespan=lifespan,
                  description="Electronic-compass calibration station: stations, runs, batches, calibration history.")

    @app.exception_handler(DomainError)
    async def _domain(request: Request, exc: DomainError) -> JSONResponse:
        # the run-time layer's refusals (no FastAPI there): one mapping to HTTP
        return JSONResponse(status_code=exc.status, content=jsonable_encoder({"detail": exc.detail}))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        # 422 naming each bad field by its path and the problem
        return JSONResponse(status_code=422, content=jsonable_encoder({"detail": field_errors(exc.errors())}))

    app.include_router(router)
    app.include_router(runs_router)
    app.include_router(analyses_router)
    app.include_router(web_router)
    return app


def app_from_env() -> FastAPI:
    """The app of ``compasscal serve`` (a factory, so each of several API processes builds its own):
    COMPASSCAL_STATION_WORKER=0 leaves the stations to their own workers."""
    import os

    return create_app(worker=os.environ.get("COMPASSCAL_STATION_WORKER", "1") != "0")
