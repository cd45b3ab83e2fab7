"""The acceptance limits every new calibration is judged by: ``/limits``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.auth import Caller, audit, require
from service.db import Limit
from service.deps import db
from service.runtime import invalid
from service.schemas import ERRORS, LimitIn, LimitOut, Name

router = APIRouter(tags=["limits"])


@router.get("/limits", response_model=list[LimitOut], responses=ERRORS)
def get_limits(session: Session = Depends(db), _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """The acceptance limits every new calibration is judged by."""
    return [{"name": r.name, "marginal": r.marginal, "fail": r.fail, "unit": r.unit, "description": r.description}
            for r in session.scalars(select(Limit).order_by(Limit.name))]


@router.put("/limits/{name}", response_model=LimitOut, responses=ERRORS)
def put_limit(name: Name, body: LimitIn, session: Session = Depends(db), caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Change one limit (admin). Calibrations already judged keep their verdicts."""
    row = session.get(Limit, name)
    if row is None:
        raise HTTPException(404, f"no limit {name!r}; known: " + ", ".join(session.scalars(select(Limit.name))))
    if body.fail < body.marginal:
        raise invalid("body.fail", "must be >= marginal")
    old = {"marginal": row.marginal, "fail": row.fail}
    row.marginal, row.fail = body.marginal, body.fail
    audit(session, caller, "limit.update", name, {"old": old, "new": body.model_dump()})
    session.commit()
    return {"name": name, **body.model_dump(), "unit": row.unit, "description": row.description}
