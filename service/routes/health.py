"""The service's own state: ``GET /health``."""

from __future__ import annotations

from fastapi import APIRouter, Request
from sqlalchemy import select

from service.runtime import SOFTWARE_VERSION
from service.schemas import HealthOut

router = APIRouter(tags=["service"])


@router.get("/health", response_model=HealthOut)
def health(request: Request) -> dict[str, str]:
    """Liveness and the database in use; needs no key."""
    with request.app.state.sessions() as session:
        session.execute(select(1))
    return {"status": "ok", "version": SOFTWARE_VERSION, "database": request.app.state.engine.dialect.name}
