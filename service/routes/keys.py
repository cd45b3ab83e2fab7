"""API keys (admin): ``/keys`` to list them (never their secrets), create one (shown once) and
revoke one; each change audited. The same as ``compasscal keys list|create|revoke``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Request
from sqlalchemy import func, select

from service.auth import ROLES, Caller, audit, create_key, find_key, key_json, list_keys, require, revoke_key
from service.db import ApiKey
from service.deps import sessions
from service.runtime import Conflict, NotFound, invalid
from service.schemas import ERRORS, Id, KeyCreated, KeyIn, KeyOut

router = APIRouter(tags=["keys"])


@router.get("/keys", response_model=list[KeyOut], responses=ERRORS)
def get_keys(request: Request, _: Caller = Depends(require("admin"))) -> list[dict[str, Any]]:
    """Every API key: id, the characters it starts with, owner, role, whether revoked."""
    with sessions(request)() as s:
        return [key_json(r) for r in list_keys(s)]


@router.post("/keys", status_code=201, response_model=KeyCreated, responses=ERRORS)
def post_key(body: KeyIn, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Create a key (admin): the answer carries the key itself, the only time it is shown."""
    if body.role not in ROLES:
        raise invalid("body.role", f"expected one of {', '.join(ROLES)}")
    with sessions(request)() as s:
        key = create_key(s, body.owner, body.role)
        row = s.scalar(select(ApiKey).where(ApiKey.prefix == key[:10]).order_by(ApiKey.id.desc()).limit(1))
        audit(s, caller, "key.create", f"key {row.id}", {"owner": row.owner, "role": row.role, "prefix": row.prefix})
        s.commit()
        return {**key_json(row), "key": key}


@router.delete("/keys/{key_id}", response_model=KeyOut, responses=ERRORS)
def delete_key(key_id: Id, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Revoke a key (admin); it stops working within seconds everywhere. Refused for the last
    admin key in force, which would lock every administrator out."""
    with sessions(request)() as s:
        try:
            row = find_key(s, str(key_id))
        except LookupError as e:
            raise NotFound(str(e)) from None
        if row.role == "admin" and not row.revoked:
            admins = s.scalar(select(func.count()).select_from(ApiKey).where(ApiKey.role == "admin",
                                                                              ApiKey.revoked.is_(False)))
            if admins <= 1:
                raise Conflict("this is the last admin key in force; create another admin key first")
        revoke_key(s, row, caller)
        request.app.state.key_cache = {}  # this process forgets it at once (others within KEY_CACHE_S)
        return key_json(row)
