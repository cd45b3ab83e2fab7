"""API keys: ``X-API-Key`` header, stored as SHA-256 hashes, each with an owner and a role.

Roles are ordered: viewer (read) < operator (runs, batches, prompts) < admin (stations, keys, limits).
"""

from __future__ import annotations

import hashlib
import secrets
import time
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, Callable

from fastapi import Depends, HTTPException, Request
from fastapi.security import APIKeyHeader
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from service.db import ApiKey, AuditLog, WebSession, utcnow

ROLES = ("viewer", "operator", "admin")
#: The session cookie of the web pages: a session token (see :func:`start_session`), HttpOnly,
#: SameSite=Strict, Secure over HTTPS, expiring with the session.
COOKIE = "compasscal_key"
_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="an API key from `compasscal keys create`")


@dataclass(frozen=True)
class Caller:
    """Who is calling: the key's owner and role."""

    owner: str
    role: str


def hash_key(key: str) -> str:
    """The stored form of a key."""
    return hashlib.sha256(key.encode()).hexdigest()


def create_key(session: Session, owner: str, role: str) -> str:
    """A new key for ``owner`` with ``role``; only its hash is stored, so this is the only chance to see it."""
    if role not in ROLES:
        raise ValueError(f"role: expected one of {', '.join(ROLES)}, got {role!r}")
    if not owner.strip():
        raise ValueError("owner: must not be empty")
    key = "cc_" + secrets.token_urlsafe(24)
    session.add(ApiKey(owner=owner.strip(), role=role, key_hash=hash_key(key), prefix=key[:10]))
    session.commit()
    return key


def list_keys(session: Session) -> list[ApiKey]:
    """Every key (never its secret: its first characters, owner, role, whether revoked), oldest first."""
    return list(session.scalars(select(ApiKey).order_by(ApiKey.id)))


def find_key(session: Session, ident: str) -> ApiKey:
    """A key by its id or by the first characters it was shown with (``cc_AbCdEfG``). LookupError
    when none matches, ValueError when a prefix matches several."""
    if ident.isdigit():
        row = session.get(ApiKey, int(ident))
        if row is None:
            raise LookupError(f"no key with id {ident}")
        return row
    rows = list(session.scalars(select(ApiKey).where(ApiKey.prefix.startswith(ident, autoescape=True))))
    if not rows:
        raise LookupError(f"no key starts with {ident!r}")
    if len(rows) > 1:
        raise ValueError(f"{ident!r} starts {len(rows)} keys (ids {', '.join(str(r.id) for r in rows)}); give the id")
    return rows[0]


def revoke_key(session: Session, row: ApiKey, by: Caller) -> None:
    """Revoke a key, audited (committed). Services trust a looked-up key for :data:`KEY_CACHE_S` at most."""
    row.revoked = True
    audit(session, by, "key.revoke", f"key {row.id}", {"prefix": row.prefix, "owner": row.owner, "role": row.role})
    session.commit()


def key_json(row: ApiKey) -> dict[str, Any]:
    """A key as listed: id, the characters it starts with, owner, role, revoked, created_at."""
    return {"id": row.id, "prefix": row.prefix, "owner": row.owner, "role": row.role, "revoked": row.revoked,
            "created_at": row.created_at}


def lookup(session: Session, key: str | None) -> Caller | None:
    """The caller a key belongs to, or None."""
    if not key:
        return None
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key), ApiKey.revoked.is_(False)))
    return Caller(row.owner, row.role) if row else None


def require(role: str) -> Callable[..., Caller]:
    """A FastAPI dependency: 401 without a valid key, 403 with too low a role."""
    need = ROLES.index(role)

    # async: a cached key costs no thread-pool hop (a miss runs one short query on the loop)
    async def dep(request: Request, key: str | None = Depends(_header)) -> Caller:
        # scripts send the header; the web pages' browser session carries a session token in a cookie
        caller = caller_of(request, key)
        if caller is None:
            raise HTTPException(401, "a valid X-API-Key header is required", headers={"WWW-Authenticate": "X-API-Key"})
        if ROLES.index(caller.role) < need:
            raise HTTPException(403, f"this needs the {role} role; the key of {caller.owner} is {caller.role}")
        request.state.caller = caller
        return caller
    return dep


#: Seconds a looked-up key is trusted without asking the database again (a revocation takes this long).
KEY_CACHE_S = 10.0


def _cached(request: Request, key: str | None, find: Callable[[Session, str], Caller | None] | None = None) -> Caller | None:
    """``find`` (default :func:`lookup`) with a short per-app cache: every request checks its key or
    session token, most of them the same few."""
    if not key:
        return None
    state = request.app.state
    cache: dict[str, tuple[float, Caller | None]] = getattr(state, "key_cache", None) or {}
    state.key_cache = cache
    now = time.monotonic()
    hit = cache.get(key)
    if hit is not None and now - hit[0] < KEY_CACHE_S:
        return hit[1]
    with state.sessions() as session:
        caller = (find or lookup)(session, key)
    if len(cache) > 10_000:
        cache.clear()
    cache[key] = (now, caller)
    return caller


#: Hours a web session lasts from its login.
SESSION_HOURS = 12


def caller_of(request: Request, key: str | None = None) -> Caller | None:
    """Who calls: the ``X-API-Key`` header's key (``key``, else read here), else the web session of
    the cookie; None when neither is valid."""
    key = key or request.headers.get("x-api-key")
    if key:
        return _cached(request, key)
    token = request.cookies.get(COOKIE)
    return _cached(request, token, session_caller) if token else None


def start_session(session: Session, key: str) -> tuple[str, Caller] | None:
    """Log in with an API key: a new session token (the cookie's value; only its hash is stored)
    and the caller, or None when the key is not valid (committed)."""
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key), ApiKey.revoked.is_(False)))
    if row is None:
        return None
    token = "cs_" + secrets.token_urlsafe(32)
    session.add(WebSession(token_hash=hash_key(token), key_id=row.id,
                           expires_at=utcnow() + timedelta(hours=SESSION_HOURS)))
    session.commit()
    return token, Caller(row.owner, row.role)


def session_caller(session: Session, token: str) -> Caller | None:
    """The caller of a web session token: None when unknown, expired, or its key revoked."""
    row = session.execute(select(ApiKey.owner, ApiKey.role).join(WebSession, WebSession.key_id == ApiKey.id)
                          .where(WebSession.token_hash == hash_key(token), WebSession.expires_at > utcnow(),
                                 ApiKey.revoked.is_(False))).first()
    return Caller(row[0], row[1]) if row else None


def end_session(session: Session, token: str) -> None:
    """Log out: the session token stops working (committed)."""
    session.execute(delete(WebSession).where(WebSession.token_hash == hash_key(token)))
    session.commit()


def audit(session: Session, caller: Caller, action: str, target: str, detail: dict[str, Any] | None = None) -> None:
    """Write one audit-log row (committed with the caller's change)."""
    session.add(AuditLog(owner=caller.owner, action=action, target=target, detail=detail))
