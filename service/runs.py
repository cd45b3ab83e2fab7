"""Stations, runs and batches: the run manager that owns each station's hardware, and their routes.

The manager
-----------
:class:`RunManager` keeps, per station, its state (``idle``, ``running``, ``paused``, ``fault``) and
the run on it; at most one run is active per station. A run executes in a thread of its own with
its own event loop: that thread opens the station's table and fixture, identifies the compasses,
drives the procedures' :class:`~procedures.engine.Engine` with a :class:`~service.store.DbSink`
(samples committed per acquisition), stores each unit's calibration and closes the hardware. The
service's loop therefore never waits on a Modbus poll, a sample insert or the fit at the end of a
calibration (about 0.6 s of CPU), and an exception in a driver ends one run, never the service.
Control (pause, resume, abort, prompt answers) is handed to the run's loop thread-safely, and the
engine's events come back to the service's loop, where each run keeps its history for
``GET /runs/{id}/events``.

Statuses and the transition table
---------------------------------
A run is ``queued`` (created; the hardware is being opened), then ``running``, ``paused``, and ends
``completed``, ``failed`` or ``aborted``. ``PUT /runs/{id}/state`` accepts only the transitions of
:data:`TRANSITIONS`; anything else is 409 naming from and to. A pause takes effect at the procedure's
next checkpoint (the table holds still there): until the engine reports it, the run stays
``running`` with ``pause_requested`` true; ``running -> running`` then withdraws the request.

A run is reported ``completed`` only after its calibrations are stored and its station is free
again, so a client that sees ``completed`` can fetch the calibration and start the next run at once.

Station faults
--------------
A station goes to ``fault`` when its hardware cannot be opened (table or a compass unreachable),
or a run fails and the table reports an axis fault, cannot be read, or the failure was the table's
(an axis or Modbus error). It stays there, refusing runs, until ``POST /stations/{name}/reset``
resets the axis faults. A run that fails because of its unit (a compass falling silent mid-run)
leaves a healthy station ``idle``. Station states live in memory: after a restart every station is
``idle`` and runs left active by the previous process are marked failed.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from contextlib import AsyncExitStack
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, Field, ValidationError, field_validator
from sqlalchemy import String, cast, select, update
from sqlalchemy.orm import Session, sessionmaker

from drivers.modbus import BusError, BusURL
from drivers.turntable import AxisError, Turntable
from physics.calibration import Calibration as PhysCalibration, json_safe
from physics.recording import format_recording
from procedures.calibrate import PROCEDURES as BASE_PROCEDURES, CalibrateParams, calibrate
from procedures.engine import Engine, Event, open_station
from procedures.steps import Procedure, ProcedureGen, Prompt
from service.api import field_errors, unprocessable
from service.auth import Caller, audit, require
from service.db import Batch, Calibration, Device, Run, Station, utcnow
from service.store import DbSink, load_recording, store_calibration

#: Allowed ``PUT /runs/{id}/state`` transitions (from, to) and what each does.
TRANSITIONS: dict[tuple[str, str], str] = {
    ("running", "paused"): "pause at the next checkpoint",
    ("paused", "running"): "resume",
    ("queued", "aborted"): "abort before the hardware is used",
    ("running", "aborted"): "abort: axes stopped, samples kept",
    ("paused", "aborted"): "abort: axes stopped, samples kept",
}
ACTIVE = ("queued", "running", "paused")
FINAL = ("completed", "failed", "aborted")

#: Compass stream rate of every run (the engine's default; recorded in the run's metadata).
SAMPLE_RATE_HZ = 20
#: Wall seconds allowed to connect a station's table and fixture, and to identify the compasses.
OPEN_TIMEOUT_S = 15.0
IDENTIFY_TIMEOUT_S = 10.0
#: How many finished runs keep their event history in memory (older ones replay from the DB row).
HISTORY_RUNS = 200
#: Seconds between SSE keep-alive comments (proxies close idle streams).
KEEPALIVE_S = 15.0


# ------------------------------------------------------------------------------ batch procedure

class BatchCalibrateParams(CalibrateParams):
    """The calibration of one unit of a batch: the operator is asked to mount it first."""

    serial: str = Field(min_length=1, description="the unit to mount in slot 0")
    unmount: str | None = Field(None, description="the previous unit (with its result), to take out first")


def batch_calibrate(p: BatchCalibrateParams) -> ProcedureGen:
    """Prompt the operator to swap units, then the full calibration.

    There is no unmount prompt at the end: the unit's verdict is only known once its calibration is
    judged after the run, so the next unit's mount prompt says which unit to take out and how it did
    (the operator sorts it into the right bin), and the batch's summary covers the last one."""
    text = f"mount unit {p.serial} in slot 0"
    if p.unmount:
        text = f"unmount unit {p.unmount}, then {text}"
    yield Prompt(text, id="mount")
    return (yield from calibrate(p))


BATCH_PROCEDURE = Procedure("batch_calibrate", "1", BatchCalibrateParams, batch_calibrate,
                            "one unit of a batch: mount prompt, then the error-separation calibration")
#: What runs accept: the procedures' registry plus the batch wrapper (kept here, not in procedures/).
PROCEDURES: dict[str, Procedure] = {**BASE_PROCEDURES, BATCH_PROCEDURE.name: BATCH_PROCEDURE}


# ------------------------------------------------------------------------------------- helpers

def _reason(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


def _subclass_names(*roots: type) -> frozenset[str]:
    names, todo = set(), list(roots)
    while todo:
        c = todo.pop()
        names.add(c.__name__)
        todo.extend(c.__subclasses__())
    return frozenset(names)


def _is_table_error(reason: str | None) -> bool:
    """Whether a run's reason (the engine's "Type: message") is an error of the table's drivers."""
    names = _subclass_names(AxisError, BusError)
    return bool(reason) and reason.split(":", 1)[0].strip() in names


def _run_in_thread(name: str, fn: Callable[[], Any]) -> asyncio.Future[Any]:
    """Run ``fn`` in a thread of its own; the result arrives as a future of the calling loop.

    A dedicated thread (not the default executor): a run lasts minutes to hours, and the executor's
    few workers are shared with short jobs (migrations, parsing uploads)."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[Any] = loop.create_future()

    def settle(ok: bool, value: Any) -> None:
        if not fut.done():
            fut.set_result(value) if ok else fut.set_exception(value)

    def target() -> None:
        try:
            out: tuple[bool, Any] = (True, fn())
        except BaseException as e:  # noqa: BLE001 - handed to the waiting loop
            out = (False, e)
        try:
            loop.call_soon_threadsafe(settle, *out)
        except RuntimeError:  # the service's loop is gone (shut down without waiting for us)
            pass

    threading.Thread(target=target, name=name, daemon=True).start()
    return fut


# ------------------------------------------------------------------------------ in-memory state

@dataclass
class StationState:
    """What the manager knows of a station beyond its row: state, current run, fault, batch."""

    name: str
    state: str = "idle"  # idle | running | paused | fault
    run_id: int | None = None
    reason: str | None = None  # the fault's
    batch_id: int | None = None  # a batch holds the station between its units
    resetting: bool = False

    def busy(self, batch_id: int | None = None) -> str | None:
        """Why no run can start here now (None when one can)."""
        if self.resetting:
            return f"station {self.name} is being reset"
        if self.run_id is not None:
            return f"station {self.name} is busy with run {self.run_id}"
        if self.state == "fault":
            return f"station {self.name} is in fault ({self.reason}); POST /stations/{self.name}/reset first"
        if self.batch_id is not None and self.batch_id != batch_id:
            return f"station {self.name} is busy with batch {self.batch_id}"
        return None


@dataclass
class ActiveRun:
    """A run the manager executes (or executed since the service started): its control channel to the
    engine and its event history. Touched on the service's loop except where noted."""

    run_id: int
    station: str
    batch_id: int | None
    status: str = "queued"
    reason: str | None = None
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    prompts: dict[str, str] = field(default_factory=dict)  # waiting prompts: id -> text
    progress: dict[str, Any] | None = None
    samples: int = 0
    pause_requested: bool = False
    done: bool = False
    summary: dict[str, Any] = field(default_factory=dict)
    task: asyncio.Task[None] | None = None
    # shared with the run's thread, under ``lock``
    lock: threading.Lock = field(default_factory=threading.Lock)
    engine: Engine | None = None
    loop: asyncio.AbstractEventLoop | None = None
    abort_reason: str | None = None
    pending: list[tuple[str, tuple[Any, ...]]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.changed = asyncio.Event()
        self.finished = asyncio.Event()

    def add(self, kind: str, data: dict[str, Any]) -> None:
        """Record an event and wake the streams."""
        data = json_safe(data)
        self.events.append((kind, data))
        if kind == "prompt":
            if data.get("answered"):
                self.prompts.pop(data.get("id"), None)
            else:
                self.prompts[data["id"]] = data.get("text", "")
        elif kind == "progress":
            self.progress = data
        elif kind == "samples":
            self.samples = max(self.samples, int(data.get("count") or 0))
        elif kind == "state":
            self.status, self.reason = data["state"], data.get("reason")
            if self.status != "running":
                self.pause_requested = False
        self._wake()

    def finish(self) -> None:
        """No more events: close the streams."""
        self.done = True
        self.prompts.clear()
        self.finished.set()
        self._wake()

    def _wake(self) -> None:
        waiter, self.changed = self.changed, asyncio.Event()
        waiter.set()

    def control(self, method: str, *args: Any) -> None:
        """Call an engine method in the run's own loop; before the engine exists, keep the call for it."""
        with self.lock:
            if method == "abort":
                self.abort_reason = self.abort_reason or args[0]
            if self.engine is None or self.loop is None:
                self.pending.append((method, args))
                return
            engine, loop = self.engine, self.loop
        try:
            loop.call_soon_threadsafe(getattr(engine, method), *args)
        except RuntimeError:  # its loop has closed: the run is over anyway
            pass


@dataclass
class _Finish:
    """How a run's thread ended it."""

    status: str
    reason: str | None = None
    fault: str | None = None  # the station's fault, if the hardware needs the operator
    summary: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------------- manager

class RunManager:
    """Owns each station's hardware while a run uses it: at most one active run per station, runs
    executed in threads of their own, their events kept for streaming, batches run unit by unit."""

    def __init__(self, sessions: sessionmaker, software_version: str) -> None:
        self.sessions, self.software_version = sessions, software_version
        self.stations: dict[str, StationState] = {}
        self.active: dict[int, ActiveRun] = {}
        self.history: OrderedDict[int, ActiveRun] = OrderedDict()
        self.batch_tasks: dict[int, asyncio.Task[None]] = {}
        self.closing = False
        self._recover()

    def _recover(self) -> None:
        """Runs and batches a previous process left active cannot go on: mark them, so none stays
        ``running`` for ever."""
        with self.sessions() as s:
            s.execute(update(Run).where(Run.status.in_(ACTIVE))
                      .values(status="failed", reason="the service stopped while the run was active", finished_at=utcnow()))
            s.execute(update(Batch).where(Batch.status.in_(("queued", "running")))
                      .values(status="failed", finished_at=utcnow()))
            s.commit()

    # ------------------------------------------------------------------------------ stations
    def station_state(self, name: str) -> StationState:
        """The in-memory state of a station (idle until something happens)."""
        return self.stations.setdefault(name, StationState(name))

    def run(self, run_id: int) -> ActiveRun | None:
        """The run's live record, while active or while its history is kept."""
        return self.active.get(run_id) or self.history.get(run_id)

    async def reset_station(self, row: Station) -> dict[str, Any]:
        """Reset the table's axis faults (RESET_FAULT on each faulted axis) and make the station idle.

        Raises 409 while a run uses the station, 503 when the table cannot be reached or still
        reports a fault (the station stays in fault)."""
        st = self.station_state(row.name)
        if st.run_id is not None or st.resetting:
            raise HTTPException(409, f"station {row.name} is busy with run {st.run_id}; abort it first")
        st.resetting = True
        try:
            table = Turntable(row.modbus)
            try:
                async def go() -> dict[str, Any]:
                    await table.connect()
                    before = await table.status_all()
                    await table.reset_faults()
                    after = await table.status_all()
                    return {"reset_axes": [n for n, s in before.items() if s.fault],
                            "still_faulted": {n: s.fault_name or str(s.fault_code) for n, s in after.items() if s.fault}}
                out = await asyncio.wait_for(go(), OPEN_TIMEOUT_S)
            finally:
                await table.close()
        except Exception as e:  # noqa: BLE001 - any driver or network failure is reported; the state stays
            raise HTTPException(503, f"could not reset station {row.name}: {_reason(e)}") from None
        finally:
            st.resetting = False
        if out["still_faulted"]:
            st.state, st.reason = "fault", "still faulted after reset: " + ", ".join(f"axis {n}: {f}" for n, f in out["still_faulted"].items())
            raise HTTPException(503, f"station {row.name}: {st.reason}")
        st.state, st.reason = "idle", None
        return out

    # ---------------------------------------------------------------------------------- runs
    async def start_run(self, station_name: str, procedure: str, parameters: dict[str, Any] | None,
                        serials: dict[str, str] | None, operator: str, batch_id: int | None = None) -> Run:
        """Validate, create the run's row (status ``queued``, with its provenance) and start it.

        Raises 404 for an unknown station, 422 for an unknown procedure or bad parameters or serials
        (naming the field), 409 when the station is busy, in fault or shutting down."""
        if self.closing:
            raise HTTPException(409, "the service is shutting down")
        proc = PROCEDURES.get(procedure)
        if proc is None:
            raise unprocessable("body.procedure", f"unknown procedure {procedure!r}; known: {', '.join(sorted(PROCEDURES))}")
        try:
            params = proc.validate(parameters)
        except ValidationError as e:
            raise HTTPException(422, field_errors(e.errors(), ("body", "parameters"))) from None
        with self.sessions() as s:
            row = s.scalar(select(Station).where(Station.name == station_name))
            if row is None:
                raise HTTPException(404, f"no station {station_name!r}")
            snapshot = {"name": row.name, "modbus": row.modbus, "compasses": list(row.compasses),
                        "time_scale": float(row.time_scale)}
            given: dict[str, str] = {}
            for key, serial in (serials or {}).items():
                if not (key.isascii() and key.isdigit() and int(key) < len(row.compasses)):
                    raise unprocessable(f"body.serials.{key}", f"not a slot of station {row.name} "
                                         f"(slots 0 to {len(row.compasses) - 1})")
                if not str(serial).strip():
                    raise unprocessable(f"body.serials.{key}", "empty serial number")
                given[str(int(key))] = str(serial).strip()
            st = self.station_state(row.name)
            why = st.busy(batch_id)
            if why:
                raise HTTPException(409, why)
            run = Run(station_id=row.id, batch_id=batch_id, procedure=proc.name, procedure_version=proc.version,
                      parameters=json_safe(params.model_dump()), status="queued", operator=operator,
                      station_snapshot=snapshot, serials=given, software_version=self.software_version,
                      meta={"station": row.name, "sample_rate_hz": str(SAMPLE_RATE_HZ), "time_scale": f"{row.time_scale:g}",
                            "parameters": params.model_dump_json()})
            s.add(run)
            s.commit()
        # no await since the busy check: nothing else can have taken the station meanwhile
        active = ActiveRun(run.id, row.name, batch_id)
        self.active[run.id] = active
        st.run_id, st.state = run.id, "running"
        active.add("state", {"state": "queued", "reason": None})
        identify_first = proc is not BATCH_PROCEDURE  # a batch's unit is mounted only after its prompt
        active.task = asyncio.get_running_loop().create_task(
            self._supervise(active, snapshot, proc, params, given, identify_first), name=f"run {run.id}")
        return run

    def transition(self, run_id: int, target: str, reason: str | None) -> str:
        """Apply ``PUT /runs/{id}/state``; returns what was done. 404 unknown, 409 illegal."""
        active = self.active.get(run_id)
        if active is None or active.done:
            with self.sessions() as s:
                row = s.get(Run, run_id)
            if row is None:
                raise HTTPException(404, f"no run {run_id}")
            raise HTTPException(409, f"illegal transition {row.status} -> {target}: the run is {row.status}"
                                + ("" if row.status in FINAL else " and not executed by this service"))
        current = active.status
        if (current, target) == ("running", "running") and active.pause_requested:
            active.pause_requested = False
            active.control("resume")
            return "pause request withdrawn"
        what = TRANSITIONS.get((current, target))
        if what is None:
            allowed = [t for (f, t) in TRANSITIONS if f == current]
            raise HTTPException(409, f"illegal transition {current} -> {target}"
                                + (f" (from {current}: {', '.join(allowed)})" if allowed else f" ({current} is final)"))
        if target == "paused":
            active.pause_requested = True
            active.control("pause")
        elif target == "running":
            active.control("resume")
        else:
            active.control("abort", reason or "aborted by the operator")
        return what

    async def answer(self, run_id: int, prompt_id: str, text: str) -> bool:
        """Hand the operator's answer to a waiting prompt; False when no such prompt is waiting."""
        active = self.active.get(run_id)
        if active is None or prompt_id not in active.prompts:
            return False
        with active.lock:
            engine, loop = active.engine, active.loop
        if engine is None or loop is None:
            return False

        async def give() -> bool:
            return engine.answer(prompt_id, text)
        try:
            ok = await asyncio.wait_for(asyncio.wrap_future(asyncio.run_coroutine_threadsafe(give(), loop)), 5.0)
        except (RuntimeError, asyncio.TimeoutError):
            return False
        if ok:
            active.add("prompt", {"id": prompt_id, "answered": True, "answer": text})
        return ok

    # ------------------------------------------------------------------------- a run's life
    async def _supervise(self, active: ActiveRun, snapshot: dict[str, Any], proc: Procedure, params: BaseModel,
                         serials: dict[str, str], identify_first: bool) -> None:
        """Run one run in its own thread, then free the station and end the run's event stream."""
        st = self.station_state(active.station)
        main = asyncio.get_running_loop()
        try:
            fin: _Finish = await _run_in_thread(
                f"run-{active.run_id}",
                lambda: asyncio.run(self._work(active, main, snapshot, proc, params, serials, identify_first)))
        except BaseException as e:  # noqa: BLE001 - a bug in the run's thread must still end the run
            fin = _Finish("failed", f"internal error: {_reason(e)}", fault=f"internal error: {_reason(e)}")
            try:
                self._write_final(active.run_id, fin, None)
            except Exception:  # noqa: BLE001 - the database may be what failed
                pass
            if isinstance(e, asyncio.CancelledError):
                self._end(active, st, fin)
                raise
        self._end(active, st, fin)

    def _event(self, active: ActiveRun, kind: str, data: dict[str, Any]) -> None:
        """An event of a run (on the service's loop): keep it; a pause or resume shows on the station."""
        active.add(kind, data)
        st = self.station_state(active.station)
        if kind == "state" and data.get("state") in ("running", "paused") and st.run_id == active.run_id:
            st.state = data["state"]

    def _end(self, active: ActiveRun, st: StationState, fin: _Finish) -> None:
        # the station first: whoever sees the final state may start the next run at once
        st.run_id = None
        st.state, st.reason = ("fault", fin.fault) if fin.fault else ("idle", None)
        active.summary = fin.summary
        active.add("state", {"state": fin.status, "reason": fin.reason})
        active.finish()
        self.active.pop(active.run_id, None)
        self.history[active.run_id] = active
        while len(self.history) > HISTORY_RUNS:
            self.history.popitem(last=False)

    async def _work(self, active: ActiveRun, main: asyncio.AbstractEventLoop, snapshot: dict[str, Any],
                    proc: Procedure, params: BaseModel, given: dict[str, str], identify_first: bool) -> _Finish:
        """The run's thread: open the hardware, run the engine, store the calibrations, close."""
        def post(kind: str, data: dict[str, Any]) -> None:
            try:
                main.call_soon_threadsafe(self._event, active, kind, data)
            except RuntimeError:  # the service's loop is gone
                pass

        with active.lock:
            active.loop = asyncio.get_running_loop()
        table_seconds: float | None = None
        fin = _Finish("failed")
        try:
            async with AsyncExitStack() as stack:
                try:
                    station = await asyncio.wait_for(stack.enter_async_context(open_station(
                        snapshot["modbus"], snapshot["compasses"], time_scale=snapshot["time_scale"],
                        sample_rate_hz=SAMPLE_RATE_HZ, name=snapshot["name"])), OPEN_TIMEOUT_S)
                except Exception as e:  # noqa: BLE001 - unreachable table or compass, bad URL: the station's fault
                    why = f"could not open station {snapshot['name']}: {_reason(e)}"
                    fin = _Finish("failed", why, fault=why)
                    return fin
                idents: dict[int, tuple[str, str, str]] = {}
                if identify_first and active.abort_reason is None:
                    try:
                        ids = await asyncio.wait_for(station.fixture.identify_all(), IDENTIFY_TIMEOUT_S)
                        idents = {int(k): v for k, v in ids.items()}  # type: ignore[call-overload]
                    except Exception as e:  # noqa: BLE001 - a compass that does not answer
                        why = f"could not identify the compasses: {_reason(e)}"
                        fin = _Finish("failed", why, fault=why)
                        return fin
                serials = {slot: ident[1] for slot, ident in idents.items()}
                serials.update({int(k): v for k, v in given.items()})
                if idents:
                    self._update_run(active.run_id, serials={str(k): v for k, v in sorted(serials.items())})

                def on_event(e: Event) -> None:  # in this thread, inside the engine
                    if e.kind == "state":
                        if e.data["state"] in FINAL:
                            return  # held back: the run ends once its calibrations are stored
                        self._update_run(active.run_id, status=e.data["state"],
                                         started=e.data["state"] == "running")
                    elif e.kind == "result":
                        return  # replaced by the fuller result below
                    post(e.kind, e.data)

                engine = Engine(station, proc, params, DbSink(self.sessions, active.run_id), on_event=on_event,
                                serials=serials)
                with active.lock:
                    active.engine = engine
                    pending, active.pending = active.pending, []
                    aborted = active.abort_reason
                if aborted is not None:
                    fin = _Finish("aborted", aborted)
                    return fin
                for method, args in pending:
                    getattr(engine, method)(*args)
                result = await engine.run()
                table_seconds = result.table_seconds
                fin = _Finish(result.state.value, result.reason)
                if result.state.value == "failed":
                    fin.fault = await self._probe(station, result.reason)
                elif result.state.value == "completed" and result.outcome is not None:
                    if not idents:  # learn model and firmware now the unit is mounted (best effort)
                        try:
                            ids = await asyncio.wait_for(station.fixture.identify_all(), 3.0)
                            idents = {int(k): v for k, v in ids.items()}  # type: ignore[call-overload]
                        except Exception:  # noqa: BLE001 - only the device row's model is missing then
                            pass
                    try:
                        fin.summary = self._store(active.run_id, result.outcome, serials, idents)
                    except Exception as e:  # noqa: BLE001 - the data is kept; the run says what went wrong
                        fin = _Finish("failed", f"storing the calibrations failed: {_reason(e)}")
                fin.summary = {**fin.summary, "samples": result.samples}
                if fin.status == "completed":
                    post("result", fin.summary)
            return fin
        except asyncio.CancelledError:  # shutdown gave up waiting: the engine has stopped the axes
            fin = _Finish("aborted", "service shutting down")
            return fin
        except Exception as e:  # noqa: BLE001 - closing the hardware failed, or a bug: end the run, not the service
            fin = _Finish("failed", fin.reason or f"internal error: {_reason(e)}", fault=fin.fault or _reason(e))
            return fin
        finally:
            self._write_final(active.run_id, fin, table_seconds)

    async def _probe(self, station: Any, reason: str | None) -> str | None:
        """After a failed run: the station's fault, if its table needs the operator (else None)."""
        try:
            status = await asyncio.wait_for(station.table.status_all(), 3.0)
        except Exception as e:  # noqa: BLE001
            return f"{reason}; the table does not answer: {_reason(e)}"
        faulted = [f"axis {n}: fault {s.fault_name or s.fault_code}" for n, s in status.items() if s.fault]
        if faulted or _is_table_error(reason):
            return reason or ", ".join(faulted)
        return None

    def _store(self, run_id: int, outcome: Any, serials: dict[int, str],
               idents: dict[int, tuple[str, str, str]]) -> dict[str, Any]:
        """Judge and keep each unit's calibration; the summary of the run's result by slot."""
        units: dict[str, Any] = {}
        with self.sessions() as s:
            run = s.get(Run, run_id)
            for slot, res in sorted(outcome.results.items()):
                serial = serials.get(slot) or ""
                entry: dict[str, Any] = {"serial": serial}
                ident = idents.get(slot)
                if ident and serial and ident[1] and ident[1] != serial:
                    entry["identified_serial"] = ident[1]  # the request's serial wins; say so
                cal = res.get("calibration")
                if isinstance(cal, PhysCalibration):
                    if not serial:
                        entry["error"] = "the compass reported no serial number; give serials in the request"
                    else:
                        cal.serial = serial
                        row = store_calibration(s, run, slot, serial, json_safe(cal.to_json()),
                                                ident[0] if ident else None, ident[2] if ident else None)
                        entry.update(calibration_id=row.id, verdict=row.verdict, status=row.status, reasons=row.reasons,
                                     heading_error_deg=json_safe((cal.quality or {}).get("heading_error_deg")))
                elif "error" in res:
                    entry["error"] = str(res["error"])
                else:
                    entry["result"] = json_safe(res)
                units[str(slot)] = entry
            s.commit()
        return {"units": units, "notes": list(outcome.notes)}

    def _update_run(self, run_id: int, status: str | None = None, started: bool = False,
                    serials: dict[str, str] | None = None) -> None:
        """A short write to the run's row (status as the engine reports it, serials once known)."""
        with self.sessions() as s:
            run = s.get(Run, run_id)
            if run is None:
                return
            if status:
                run.status = status
            if started and run.started_at is None:
                run.started_at = utcnow()
            if serials is not None:
                run.serials = serials
            s.commit()

    def _write_final(self, run_id: int, fin: _Finish, table_seconds: float | None) -> None:
        with self.sessions() as s:
            run = s.get(Run, run_id)
            if run is None:
                return
            run.status, run.reason, run.finished_at = fin.status, fin.reason, utcnow()
            if table_seconds is not None:
                run.table_seconds = table_seconds
            if fin.summary:
                run.meta = {**(run.meta or {}), "result": json_safe(fin.summary)}
            s.commit()

    # ------------------------------------------------------------------------------- batches
    async def start_batch(self, station_name: str, serials: list[str], parameters: dict[str, Any],
                          operator: str) -> Batch:
        """Create a batch holding the station and calibrate its units in turn (404, 422, 409 as runs)."""
        if self.closing:
            raise HTTPException(409, "the service is shutting down")
        try:
            BatchCalibrateParams.model_validate({**parameters, "serial": serials[0]})
        except ValidationError as e:
            raise HTTPException(422, field_errors(e.errors(), ("body", "parameters"))) from None
        for key in ("serial", "unmount"):
            if key in parameters:
                raise unprocessable(f"body.parameters.{key}", "set by the batch for each unit")
        with self.sessions() as s:
            row = s.scalar(select(Station).where(Station.name == station_name))
            if row is None:
                raise HTTPException(404, f"no station {station_name!r}")
            st = self.station_state(row.name)
            why = st.busy()
            if why:
                raise HTTPException(409, why)
            batch = Batch(station_id=row.id, serials=list(serials), status="running", operator=operator,
                          summary={})
            s.add(batch)
            s.commit()
        st.batch_id = batch.id
        self.batch_tasks[batch.id] = asyncio.get_running_loop().create_task(
            self._batch(batch.id, row.name, list(serials), dict(parameters), operator), name=f"batch {batch.id}")
        return batch

    async def _batch(self, batch_id: int, station: str, serials: list[str], parameters: dict[str, Any],
                     operator: str) -> None:
        """Each unit in turn on slot 0: a mount prompt, the calibration, its verdict in the summary.
        A unit that fails does not stop the batch; a station in fault does (nothing can run on it)."""
        st = self.station_state(station)
        summary: dict[str, str] = {}
        status = "completed"
        previous: str | None = None
        try:
            for serial in serials:
                if self.closing:
                    summary[serial], status = "not run: the service shut down", "aborted"
                    continue
                if st.state == "fault":
                    summary[serial], status = f"not run: station in fault ({st.reason})", "failed"
                    continue
                try:
                    run = await self.start_run(station, BATCH_PROCEDURE.name,
                                               {**parameters, "serial": serial, "unmount": previous},
                                               {"0": serial}, operator, batch_id=batch_id)
                except HTTPException as e:
                    summary[serial] = f"not run: {e.detail}"
                    continue
                except Exception as e:  # noqa: BLE001 - e.g. the database: this unit is not run, the batch goes on
                    summary[serial] = f"not run: {_reason(e)}"
                    continue
                active = self.active[run.id]
                await active.finished.wait()
                summary[serial] = self._verdict(active)
                previous = f"{serial} ({summary[serial]})"
                self._save_batch(batch_id, "running", summary, final=False)
        finally:
            if st.batch_id == batch_id:
                st.batch_id = None
            self.batch_tasks.pop(batch_id, None)
            try:
                self._save_batch(batch_id, status, summary, final=True)
            except Exception:  # noqa: BLE001 - the database is gone at shutdown; the row is fixed on restart
                pass

    @staticmethod
    def _verdict(active: ActiveRun) -> str:
        """One unit's line in a batch summary: its verdict, or why it has none."""
        if active.status != "completed":
            return f"{active.status}: {active.reason}"
        unit = (active.summary.get("units") or {}).get("0") or {}
        if "verdict" in unit:
            return unit["verdict"]
        return f"no calibration: {unit.get('error', 'no data from slot 0')}"

    def _save_batch(self, batch_id: int, status: str, summary: dict[str, str], final: bool) -> None:
        with self.sessions() as s:
            batch = s.get(Batch, batch_id)
            if batch is None:
                return
            batch.status, batch.summary = status, dict(summary)
            if final:
                batch.finished_at = utcnow()
            s.commit()

    # ------------------------------------------------------------------------------ shutdown
    async def shutdown(self, grace_s: float = 5.0) -> None:
        """Abort every active run, wait briefly for the axes to stop, never hang.

        Runs still going after ``grace_s`` (a long move, a stuck driver) get their task cancelled,
        which still stops the axes; after that their daemon threads are left behind."""
        self.closing = True
        runs = list(self.active.values())
        for active in runs:
            active.control("abort", "service shutting down")
        tasks = [a.task for a in runs if a.task is not None]
        if tasks:
            _, late = await asyncio.wait(tasks, timeout=grace_s)
            if late:
                for active in runs:
                    with active.lock:
                        loop = active.loop
                    if loop is not None and not active.done:
                        try:
                            loop.call_soon_threadsafe(_cancel_all, loop)
                        except RuntimeError:
                            pass
                await asyncio.wait(late, timeout=2.0)
        batches = list(self.batch_tasks.values())
        if batches:
            _, late_batches = await asyncio.wait(batches, timeout=1.0)
            for t in late_batches:
                t.cancel()
            if late_batches:
                await asyncio.wait(late_batches, timeout=1.0)


def _cancel_all(loop: asyncio.AbstractEventLoop) -> None:
    for task in asyncio.all_tasks(loop):
        task.cancel()


# -------------------------------------------------------------------------------------- routes

router = APIRouter()


def manager(request: Request) -> RunManager:
    """The app's run manager (created in the lifespan)."""
    return request.app.state.manager


def _sessions(request: Request) -> sessionmaker:
    return request.app.state.sessions


class StationIn(BaseModel):
    """A new station: its table's Modbus URL and one serial URL per fixture slot."""

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    modbus: str = Field(min_length=1, max_length=256, description="e.g. tcp://10.0.0.5:502")
    compasses: list[str] = Field(min_length=1, description="the serial URL of slot 0, slot 1, ...")
    time_scale: float = Field(1.0, gt=0, le=1000, description="> 1 only for a simulated station running faster")

    @field_validator("modbus")
    @classmethod
    def _url(cls, v: str) -> str:
        BusURL.parse(v)  # ValueError names the problem
        return v

    @field_validator("compasses")
    @classmethod
    def _urls(cls, v: list[str]) -> list[str]:
        if any(not u.strip() for u in v):
            raise ValueError("empty compass URL")
        return v


class RunIn(BaseModel):
    """A run to start."""

    station: str
    procedure: str = "calibrate"
    parameters: dict[str, Any] = Field(default_factory=dict)
    serials: dict[str, str] | None = Field(None, description='slot -> serial, e.g. {"0": "SN-1"}; '
                                           "omitted: the compasses' own serial numbers")


class StateIn(BaseModel):
    """A requested state change of a run."""

    state: str = Field(pattern="^(paused|running|aborted)$")
    reason: str | None = Field(None, max_length=500)


class AnswerIn(BaseModel):
    """The operator's answer to a prompt."""

    answer: str = Field("", max_length=1000)


class BatchIn(BaseModel):
    """Units to calibrate in turn on slot 0 of a station."""

    station: str
    serials: list[str] = Field(min_length=1, max_length=1000)
    parameters: dict[str, Any] = Field(default_factory=dict, description="calibrate parameters for every unit")

    @field_validator("serials")
    @classmethod
    def _distinct(cls, v: list[str]) -> list[str]:
        v = [s.strip() for s in v]
        if any(not s for s in v):
            raise ValueError("empty serial number")
        dup = sorted({s for s in v if v.count(s) > 1})
        if dup:
            raise ValueError(f"serial numbers listed twice: {', '.join(dup)}")
        return v


def _station_json(row: Station, st: StationState) -> dict[str, Any]:
    return {"name": row.name, "modbus": row.modbus, "compasses": row.compasses, "time_scale": row.time_scale,
            "created_at": row.created_at, "state": st.state, "run_id": st.run_id, "fault": st.reason,
            "batch_id": st.batch_id}


def run_json(row: Run, mgr: RunManager) -> dict[str, Any]:
    """A run as the API shows it: its row, with the live status, prompts and progress while it runs."""
    live = mgr.run(row.id)
    status, reason = row.status, row.reason
    if live is not None and not live.done:
        status, reason = live.status, live.reason  # the row's final status may be written a moment early
    snap = row.station_snapshot or {}
    return {"id": row.id, "status": status, "reason": reason, "station": snap.get("name"),
            "procedure": row.procedure, "procedure_version": row.procedure_version, "parameters": row.parameters,
            "serials": row.serials, "operator": row.operator, "batch_id": row.batch_id,
            "software_version": row.software_version, "station_snapshot": row.station_snapshot,
            "created_at": row.created_at, "started_at": row.started_at, "finished_at": row.finished_at,
            "table_seconds": row.table_seconds,
            "samples_count": max(row.samples_count or 0, live.samples if live else 0),
            "result": (row.meta or {}).get("result"),
            "pause_requested": bool(live and not live.done and live.pause_requested),
            "prompts": [{"id": k, "text": v} for k, v in live.prompts.items()] if live and not live.done else [],
            "progress": live.progress if live else None}


def _get_run(s: Session, run_id: int) -> Run:
    row = s.get(Run, run_id)
    if row is None:
        raise HTTPException(404, f"no run {run_id}")
    return row


@router.get("/stations", tags=["stations"])
async def list_stations(request: Request, _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Every station with its state (idle, running, paused, fault) and current run."""
    mgr = manager(request)
    with _sessions(request)() as s:
        rows = s.scalars(select(Station).order_by(Station.name)).all()
    return [_station_json(r, mgr.station_state(r.name)) for r in rows]


@router.post("/stations", status_code=201, tags=["stations"])
async def create_station(body: StationIn, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Add a station (admin). 409 if the name is taken."""
    with _sessions(request)() as s:
        if s.scalar(select(Station.id).where(Station.name == body.name)) is not None:
            raise HTTPException(409, f"station {body.name!r} exists")
        row = Station(name=body.name, modbus=body.modbus, compasses=list(body.compasses), time_scale=body.time_scale)
        s.add(row)
        audit(s, caller, "station.create", body.name, body.model_dump())
        s.commit()
    return _station_json(row, manager(request).station_state(row.name))


class StationConfigIn(BaseModel):
    """A station's configuration (the name is in the path)."""

    modbus: str = Field(min_length=1, max_length=256, description="e.g. tcp://10.0.0.5:502")
    compasses: list[str] = Field(min_length=1, description="the serial URL of slot 0, slot 1, ...")
    time_scale: float = Field(1.0, gt=0, le=1000, description="> 1 only for a simulated station running faster")


@router.put("/stations/{name}", tags=["stations"])
async def put_station(name: str, body: StationConfigIn, request: Request, caller: Caller = Depends(require("admin"))) -> dict[str, Any]:
    """Create a station or change its URLs (admin), e.g. after moving a table to another gateway.
    409 while a run uses it; runs already made keep the configuration they ran with."""
    full = StationIn(name=name, **body.model_dump())  # the same checks as POST
    mgr = manager(request)
    if mgr.station_state(name).state in ("running", "paused"):
        raise HTTPException(409, f"station {name!r} is {mgr.station_state(name).state}; change it when idle")
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            row = Station(name=name, modbus=full.modbus, compasses=list(full.compasses), time_scale=full.time_scale)
            s.add(row)
        else:
            row.modbus, row.compasses, row.time_scale = full.modbus, list(full.compasses), full.time_scale
        audit(s, caller, "station.put", name, full.model_dump())
        s.commit()
    return _station_json(row, mgr.station_state(name))


@router.get("/stations/{name}", tags=["stations"])
async def get_station(name: str, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One station: configuration, state, current run (with its status and prompts) and any fault."""
    mgr = manager(request)
    with _sessions(request)() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            raise HTTPException(404, f"no station {name!r}")
        st = mgr.station_state(name)
        out = _station_json(row, st)
        run = s.get(Run, st.run_id) if st.run_id is not None else None
        out["run"] = run_json(run, mgr) if run is not None else None
    return out


@router.post("/stations/{name}/reset", tags=["stations"])
async def reset_station(name: str, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Reset the table's axis faults and make the station idle (operator). 409 while a run uses it;
    503 when the table cannot be reached or still reports a fault."""
    mgr = manager(request)
    with _sessions(request)() as s:  # closed before the hardware is touched: no transaction held open
        row = s.scalar(select(Station).where(Station.name == name))
    if row is None:
        raise HTTPException(404, f"no station {name!r}")
    before = mgr.station_state(name).reason
    try:
        out = await mgr.reset_station(row)
    except HTTPException as e:
        if e.status_code == 503:  # an attempt on the hardware: logged even when it failed
            with _sessions(request)() as s:
                audit(s, caller, "station.reset", name, {"ok": False, "error": e.detail})
                s.commit()
        raise
    with _sessions(request)() as s:
        audit(s, caller, "station.reset", name, {"ok": True, "fault": before, **out})
        s.commit()
    return {**_station_json(row, mgr.station_state(name)), **out}


@router.post("/runs", status_code=202, tags=["runs"])
async def create_run(body: RunIn, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Start a run (operator): 202 with the run (status ``queued``); follow it with ``GET /runs/{id}``
    or ``GET /runs/{id}/events``. 404 unknown station, 422 bad procedure/parameters/serials, 409 busy."""
    mgr = manager(request)
    run = await mgr.start_run(body.station, body.procedure, body.parameters, body.serials, caller.owner)
    with _sessions(request)() as s:
        audit(s, caller, "run.start", f"run {run.id}", {"station": body.station, "procedure": run.procedure,
                                                         "parameters": run.parameters, "serials": run.serials})
        s.commit()
    return run_json(run, mgr)


@router.get("/runs", tags=["runs"])
async def list_runs(request: Request, station: str | None = None, status: str | None = None,
                    procedure: str | None = None, serial: str | None = None,
                    limit: int = Query(50, ge=1, le=1000), offset: int = Query(0, ge=0),
                    _: Caller = Depends(require("viewer"))) -> list[dict[str, Any]]:
    """Runs, newest first, filtered by station name, status, procedure and unit serial number."""
    mgr = manager(request)
    q = select(Run)
    if station is not None:
        q = q.join(Station, Station.id == Run.station_id).where(Station.name == station)
    if status is not None:
        q = q.where(Run.status == status)
    if procedure is not None:
        q = q.where(Run.procedure == procedure)
    if serial is not None:
        # serials is a small JSON object {"0": "SN-1"}; its text holds each serial JSON-quoted on both databases
        needle = json.dumps(serial).replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        q = q.where(cast(Run.serials, String).like(f"%{needle}%", escape="\\"))
    with _sessions(request)() as s:
        rows = s.scalars(q.order_by(Run.created_at.desc(), Run.id.desc()).limit(limit).offset(offset)).all()
    return [run_json(r, mgr) for r in rows]


@router.get("/runs/{run_id}", tags=["runs"])
async def get_run(run_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """One run: provenance, live status, waiting prompts, progress, result and its calibrations."""
    mgr = manager(request)
    with _sessions(request)() as s:
        row = _get_run(s, run_id)
        out = run_json(row, mgr)
        cals = s.execute(select(Calibration, Device.serial).join(Device, Device.id == Calibration.device_id)
                         .where(Calibration.run_id == run_id).order_by(Calibration.slot)).all()
    out["calibrations"] = [{"id": c.id, "slot": c.slot, "serial": serial, "status": c.status, "verdict": c.verdict,
                            "reasons": c.reasons} for c, serial in cals]
    return out


@router.put("/runs/{run_id}/state", status_code=202, tags=["runs"])
async def put_run_state(run_id: int, body: StateIn, request: Request,
                        caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Pause, resume or abort (operator), checked against the transition table (409 otherwise).
    202: a pause takes effect at the next checkpoint, an abort as soon as the current step ends."""
    mgr = manager(request)
    what = mgr.transition(run_id, body.state, body.reason)
    with _sessions(request)() as s:
        audit(s, caller, "run.state", f"run {run_id}", {"state": body.state, "reason": body.reason, "action": what})
        s.commit()
        out = run_json(_get_run(s, run_id), mgr)
    return {**out, "requested": body.state, "action": what}


def _sse(index: int, kind: str, data: dict[str, Any]) -> str:
    return f"id: {index}\nevent: {kind}\ndata: {json.dumps(data, default=str)}\n\n"


@router.get("/runs/{run_id}/events", tags=["runs"])
async def run_events(run_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> StreamingResponse:
    """Server-sent events (state, step, progress, samples, prompt, result): the run's history, then
    live events until it ends. A ``Last-Event-ID`` header resumes after that event. A run whose
    history is no longer in memory gets one ``state`` event from its row."""
    mgr = manager(request)
    live = mgr.run(run_id)
    if live is None:
        with _sessions(request)() as s:
            row = _get_run(s, run_id)
            data = {"state": row.status, "reason": row.reason, "from": "database"}

        async def once() -> AsyncIterator[str]:
            yield _sse(0, "state", data)
        return StreamingResponse(once(), media_type="text/event-stream", headers=_SSE_HEADERS)
    last = request.headers.get("last-event-id", "")
    start = int(last) + 1 if last.isdigit() else 0

    async def stream() -> AsyncIterator[str]:
        i = start
        while True:
            while i < len(live.events):
                yield _sse(i, *live.events[i])
                i += 1
            if live.done:
                return
            waiter = live.changed  # taken before waiting: no await since the check, so no event is missed
            try:
                await asyncio.wait_for(waiter.wait(), KEEPALIVE_S)
            except asyncio.TimeoutError:
                yield ": keep-alive\n\n"
    return StreamingResponse(stream(), media_type="text/event-stream", headers=_SSE_HEADERS)


_SSE_HEADERS = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}


@router.get("/runs/{run_id}/samples", tags=["runs"])
async def run_samples(run_id: int, request: Request, slot: int = Query(0, ge=0),
                      _: Caller = Depends(require("viewer"))) -> Response:
    """One slot's samples as a RECORDING.md CSV (404 when it has none)."""
    def build() -> str | None:
        with _sessions(request)() as s:
            row = _get_run(s, run_id)
            rec = load_recording(s, row, slot)
        if rec is None:
            return None
        rec.meta.pop("result", None)  # the result summary is no recording metadata
        return format_recording(rec)
    text = await asyncio.to_thread(build)  # a long run has hundreds of thousands of rows
    if text is None:
        raise HTTPException(404, f"run {run_id} has no samples from slot {slot}")
    return Response(text, media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="run{run_id}-slot{slot}.csv"'})


@router.post("/runs/{run_id}/prompts/{prompt_id}", tags=["runs"])
async def answer_prompt(run_id: int, prompt_id: str, body: AnswerIn, request: Request,
                        caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Answer a waiting operator prompt (operator); 404 when the run has no such prompt waiting."""
    mgr = manager(request)
    with _sessions(request)() as s:
        _get_run(s, run_id)
    if not await mgr.answer(run_id, prompt_id, body.answer):
        live = mgr.active.get(run_id)
        waiting = ", ".join(live.prompts) if live else ""
        raise HTTPException(404, f"run {run_id} has no prompt {prompt_id!r} waiting"
                            + (f" (waiting: {waiting})" if waiting else ""))
    with _sessions(request)() as s:
        audit(s, caller, "run.prompt", f"run {run_id}", {"prompt": prompt_id, "answer": body.answer})
        s.commit()
    return {"run_id": run_id, "prompt": prompt_id, "answer": body.answer}


@router.post("/batches", status_code=202, tags=["batches"])
async def create_batch(body: BatchIn, request: Request, caller: Caller = Depends(require("operator"))) -> dict[str, Any]:
    """Calibrate units in turn on slot 0 of a station (operator). Each unit's run first prompts
    ``mount`` (answer it with ``POST /runs/{id}/prompts/mount``); a failed unit does not stop the batch."""
    mgr = manager(request)
    batch = await mgr.start_batch(body.station, body.serials, body.parameters, caller.owner)
    with _sessions(request)() as s:
        audit(s, caller, "batch.start", f"batch {batch.id}", body.model_dump())
        s.commit()
        return _batch_json(s, s.get(Batch, batch.id), mgr)


def _batch_json(s: Session, batch: Batch, mgr: RunManager) -> dict[str, Any]:
    station = s.get(Station, batch.station_id)
    runs = s.scalars(select(Run).where(Run.batch_id == batch.id).order_by(Run.id)).all()
    by_serial: dict[str, Run] = {}
    for r in runs:
        by_serial[str((r.serials or {}).get("0", ""))] = r  # the latest run of each unit
    cals = {c.run_id: c for c in s.scalars(select(Calibration).where(Calibration.run_id.in_([r.id for r in runs])))} if runs else {}
    units, prompt = [], None
    for serial in batch.serials:
        r = by_serial.get(serial)
        if r is None:
            units.append({"serial": serial, "run_id": None, "status": "pending", "verdict": None})
            continue
        j = run_json(r, mgr)
        c = cals.get(r.id)
        units.append({"serial": serial, "run_id": r.id, "status": j["status"], "reason": j["reason"],
                      "verdict": c.verdict if c else None, "calibration_id": c.id if c else None,
                      "calibration_status": c.status if c else None, "prompts": j["prompts"]})
        if j["prompts"]:
            prompt = {"run_id": r.id, **j["prompts"][0]}
    return {"id": batch.id, "station": station.name if station else None, "status": batch.status,
            "operator": batch.operator, "serials": batch.serials, "created_at": batch.created_at,
            "finished_at": batch.finished_at, "summary": batch.summary or {}, "units": units, "prompt": prompt}


@router.get("/batches/{batch_id}", tags=["batches"])
async def get_batch(batch_id: int, request: Request, _: Caller = Depends(require("viewer"))) -> dict[str, Any]:
    """A batch: status, one row per unit (run id, status, verdict), the waiting prompt and the summary."""
    with _sessions(request)() as s:
        batch = s.get(Batch, batch_id)
        if batch is None:
            raise HTTPException(404, f"no batch {batch_id}")
        return _batch_json(s, batch, manager(request))


__all__ = ["RunManager", "router", "TRANSITIONS", "PROCEDURES", "BatchCalibrateParams", "run_json"]
