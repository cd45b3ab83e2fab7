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

#: The largest limit of each unit that can mean anything: a heading error or angle of half a turn, a 16-bit
#: reading's whole span, a ratio of ten.
LIMIT_CEILINGS = {"deg": 180.0, "LSB": 65536.0, "ratio": 10.0}


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
    if body.fail <= 0:  # every unit would FAIL (0 was taken)
        raise invalid("body.fail", "must be > 0: with 0 every calibration fails")
    ceiling = LIMIT_CEILINGS.get(row.unit)
    for field in ("marginal", "fail"):
        if ceiling is not None and getattr(body, field) > ceiling:
            # 1e308 was taken, and the certificates printed it as 309 digits
            raise invalid(f"body.{field}", f"at most {ceiling:g} {row.unit}: no {name} can be larger")
    old = {"marginal": row.marginal, "fail": row.fail}
    row.marginal, row.fail = body.marginal, body.fail
    audit(session, caller, "limit.update", name, {"old": old, "new": body.model_dump()})
    session.commit()
    return {"name": name, **body.model_dump(), "unit": row.unit, "description": row.description}
