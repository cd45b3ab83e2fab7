"""The service assembled: the FastAPI app with its routes (service/routes/, the pages of
service/web.py), its lifespan (database upgraded, notifier, job queue, the reaper of lost workers)
and the one mapping of domain errors to HTTP. OpenAPI at /docs."""

from __future__ import annotations

import asyncio
import os
from contextlib import asynccontextmanager
from typing import AsyncIterator

from fastapi import Depends, FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.db import default_url, make_engine, sessions, upgrade
from service.routes import ROUTERS
from service.runtime import (HEARTBEAT_S, LOST_AFTER_S, SOFTWARE_VERSION, DomainError, Invalid, Notifier, field_errors,
                             reap_lost_workers)
from service.web import invalid_page, router as web_router
from service.worker import Jobs, WorkerContext


def create_app(database_url: str | None = None, worker: bool = True) -> FastAPI:
    """The service. The database is upgraded to the newest migration on start.

    ``worker``: run a worker for every station in this process (the default; the only way on SQLite,
    whose job queue lives in memory). Off when the stations have workers of their own
    (``compasscal worker``) and the API runs as several processes (``compasscal serve --workers N``)."""
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

    # docs_url=None: /docs is service/web.py's, with Swagger UI from the package (FastAPI's uses a CDN);
    # no /redoc: it too would load from a CDN, a blank page offline
    app = FastAPI(title="compasscal", version=SOFTWARE_VERSION, lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Electronic-compass calibration station: stations, runs, batches, calibration history.")

    @app.exception_handler(DomainError)
    async def _domain(request: Request, exc: DomainError) -> JSONResponse:
        # the run-time layer's refusals (no FastAPI there): one mapping to HTTP
        return JSONResponse(status_code=exc.status, content=jsonable_encoder({"detail": exc.detail}))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        # a body FastAPI could not even decode (not UTF-8, nested beyond the parser's depth) was a 400 "There
        # was an error parsing the body", documented nowhere and naming nothing; a body that is no JSON is 422
        cause = exc.__cause__
        if exc.status_code == 400 and isinstance(cause, (UnicodeDecodeError, RecursionError)):
            why = "its bytes are not UTF-8 text" if isinstance(cause, UnicodeDecodeError) else "nested too deeply to read"
            return JSONResponse(status_code=422, content={"detail": [{"field": "body", "problem": f"not valid JSON: {why}"}]})
        return await http_exception_handler(request, exc)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        # 422 naming each bad field by its path and the problem; a page's as a page (/ui/runs/abc was JSON)
        detail = field_errors(exc.errors())
        if request.url.path.startswith("/ui/") and not request.url.path.endswith(".json"):
            return invalid_page(request, "; ".join(f"{d['field']}: {d['problem']}" for d in detail))
        return JSONResponse(status_code=422, content=jsonable_encoder({"detail": detail}))

    for router in ROUTERS:
        app.include_router(router, dependencies=[Depends(_known_query)])
    app.include_router(web_router)
    return app


def _known_query(request: Request) -> None:
    """A 422 naming a query parameter the route does not take: a misspelt filter (``/runs?serail=X``)
    was ignored, and a quality engineer got every run as if it were the unit's."""
    route = request.scope.get("route")
    if route is None or not hasattr(route, "dependant"):
        return
    known: set[str] = set()
    todo = [route.dependant]
    while todo:  # the route's own query parameters and its dependencies'
        d = todo.pop()
        known.update(p.alias for p in d.query_params)
        todo.extend(d.dependencies)
    unknown = sorted(set(request.query_params) - known)
    if unknown:
        raise Invalid([{"field": f"query.{k}", "problem": "not a parameter of this request; it takes "
                        + (", ".join(sorted(known)) if known else "none")} for k in unknown])


def app_from_env() -> FastAPI:
    """The app of ``compasscal serve`` (a factory, so each of several API processes builds its own):
    COMPASSCAL_STATION_WORKER=0 leaves the stations to their own workers."""
    return create_app(worker=os.environ.get("COMPASSCAL_STATION_WORKER", "1") != "0")
