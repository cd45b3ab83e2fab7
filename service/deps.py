"""What every route needs from the running app: a database session, the job queue, the notifier,
and the server-sent events stream they share (runs and analyses)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any

from fastapi import Request
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session, sessionmaker

#: Seconds between SSE keep-alive comments (proxies close idle streams).
KEEPALIVE_S = 15.0
#: Seconds between two reads while streaming (notifications wake the stream sooner).
POLL_S = 1.0
_SSE_HEADERS = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}

#: One read of a stream: the events after an id, as (id, kind, data), and whether nothing more will come.
Read = Callable[[int], tuple[list[tuple[int, str, dict[str, Any]]], bool]]


def sessions(request: Request) -> sessionmaker:
    """The app's session factory (for routes that open several short sessions)."""
    return request.app.state.sessions


def db(request: Request) -> Iterator[Session]:
    """A session per request (FastAPI dependency)."""
    with request.app.state.sessions() as session:
        yield session


def sse(event_id: int, kind: str, data: dict[str, Any]) -> str:
    """One server-sent event."""
    return f"id: {event_id}\nevent: {kind}\ndata: {json.dumps(data, default=str)}\n\n"


def event_stream(request: Request, topic: int | str, read: Read) -> StreamingResponse:
    """Stream ``read``'s events from after the request's ``Last-Event-ID`` (0: from the start) until
    it says nothing more will come; woken by the notifier on ``topic``, read again every
    :data:`POLL_S` anyway, with a keep-alive comment every :data:`KEEPALIVE_S` of silence."""
    last = request.headers.get("last-event-id", "")
    # (an id beyond any a database holds resumes after everything: SQLite overflowed on 99999999999999999999999)
    start = min(int(last), 2**63 - 1) if last.isascii() and last.isdigit() else 0
    notifier = request.app.state.notifier

    async def stream() -> AsyncIterator[str]:
        after, quiet = start, 0.0
        while True:
            rows, over = await asyncio.to_thread(read, after)
            for i, kind, data in rows:
                yield sse(i, kind, data)
                after = i
            if over and not rows:
                return
            if rows:
                quiet = 0.0
                continue
            if quiet >= KEEPALIVE_S:
                quiet = 0.0
                yield ": keep-alive\n\n"
            t0 = asyncio.get_running_loop().time()
            await notifier.wait(topic, POLL_S)
            quiet += asyncio.get_running_loop().time() - t0
    return StreamingResponse(stream(), media_type="text/event-stream", headers=_SSE_HEADERS)
