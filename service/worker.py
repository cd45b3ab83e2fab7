"""Station workers: the jobs that drive the hardware, and the processes that take them.

A station's runs, batches and resets are jobs on its own queue (``station-NAME``) with a lock of the
same name, so two jobs never share a turntable. The queue is
procrastinate: on PostgreSQL its tables, LISTEN/NOTIFY and locks; on the SQLite default its
in-memory connector, with the worker in a thread of the service's own process (the same job code,
one code path for the procedure).

``compasscal worker --station NAME`` (the station agent, one per bench PC) owns that station's Modbus
and serial connections: it first stops the axes and ends what a previous worker left (its runs
``failed``, "worker lost"), then takes the station's jobs, beats its heartbeat on the station's row
every :data:`~service.runtime.HEARTBEAT_S` s, publishes every event of a run to the database (where
any API process streams it) and obeys the commands operators leave there.

Each run executes in a thread of its own with its own event loop (procrastinate runs a synchronous
task in a thread): the worker's loop never waits on a Modbus poll or the fit at the end.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from contextlib import AsyncExitStack
from dataclasses import dataclass, field
from datetime import timedelta
from typing import IO, Any, TypeVar

import numpy as np
from procrastinate import App, JobContext, PsycopgConnector
from procrastinate.jobs import Status
from procrastinate.testing import InMemoryConnector
from pydantic import ValidationError
from sqlalchemy import select, update
from sqlalchemy.exc import DBAPIError, InterfaceError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from drivers import advised
from drivers.compass import CompassDisconnected, CompassTimeout, FixtureError, SerialFixture
from drivers.modbus import BusError
from drivers.protocol import with_advice
from drivers.station import open_station
from drivers.turntable import AxisError, Turntable
from physics.calibration import Calibration as PhysCalibration, json_safe
from physics.recording import Recording
from procedures.calibrate import BATCH, MOUNT_PROMPT, PROCEDURES
from procedures.engine import IDENTIFY_TIMEOUT_S, Engine, Replay, identify_units, table_time_note
from procedures.events import Event, PromptAnswered, Result, StateChanged, StepWarning
from procedures.states import ACTIVE, FINAL, RunState
from service.db import Analysis, Batch, Calibration, Run, RunCommand, RunEvent, Sample, Station, utcnow
from service.identity import DEFAULT_POLICY, Identity, UnitCheck
from service.runtime import (ANALYSIS_FINAL, BATCH_ABORTING, HEARTBEAT_S, IDENTITIES_KEY, NOT_RUN, SAMPLE_RATE_HZ,
                             SOFTWARE_VERSION, Conflict, DomainError, analysis_topic, create_run, end_lost_batches,
                             lost_run_result, notify, other_workers, publish, reports_itself, settle_resumed_unit, slot_result)
from service.store import insert_samples, load_recording, store_calibration

log = logging.getLogger("compasscal.worker")
T = TypeVar("T")

#: Wall seconds allowed to connect a station's table and fixture (identifying the compasses: the engine's).
OPEN_TIMEOUT_S = 15.0
#: Seconds between two looks at a run's commands.
COMMAND_POLL_S = 0.1
#: Wall seconds a run waits for an operator prompt's answer (COMPASSCAL_PROMPT_TIMEOUT_S overrides).
PROMPT_TIMEOUT_S = 900.0
#: Seconds a worker keeps trying to write while the database is away (a restart) before giving up.
DB_OUTAGE_S = 120.0
#: Seconds without a heartbeat of procrastinate's worker after which its analysis job is retried.
STALLED_S = 30.0
#: Seconds after its request an analysis without a job is taken as lost (and queued again).
REQUEUE_AFTER_S = 10.0

def served_elsewhere(busy: dict[str, str]) -> str:
    """Why a worker may not start: these stations have a live worker already."""
    return ("already served by a live worker: " + ", ".join(f"station {k} by {v}" for k, v in sorted(busy.items()))
            + "; stop it first (two workers of one station would compete for its table)")


def station_queue(name: str) -> str:
    """The queue (and the lock) of a station's jobs."""
    return f"station-{name}"


def _reason(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


def _is_hardware_error(reason: str | None) -> bool:
    """Whether a run's reason (the engine's "Type: message") is an error of the table's drivers or a
    compass that stopped answering (not one that refused a command: that one answers)."""
    names, todo = set(), [AxisError, BusError, CompassTimeout, CompassDisconnected, FixtureError]
    while todo:
        c = todo.pop()
        names.add(c.__name__)
        todo.extend(c.__subclasses__())
    return bool(reason) and reason.split(":", 1)[0].strip() in names


@dataclass
class WorkerContext:
    """What every job of a worker needs: the database, the software's version, and how to wake this
    process's event streams (a worker inside the service's process; a no-op elsewhere)."""

    sessions: sessionmaker
    software_version: str
    poke: Callable[[int], None] = lambda run_id: None
    name: str = field(default_factory=lambda: f"{socket.gethostname()}:{os.getpid()}")
    # wall seconds a run waits for an operator's answer before it fails (the station is freed)
    prompt_timeout_s: float = field(default_factory=lambda: float(os.environ.get("COMPASSCAL_PROMPT_TIMEOUT_S")
                                                                    or PROMPT_TIMEOUT_S))
    executing: dict[int, "RunControl"] = field(default_factory=dict)  # runs executing in this process
    # set when this process is asked to stop: a batch then starts no further unit (nor waits for one to be mounted)
    stopping: threading.Event = field(default_factory=threading.Event)

    def publish(self, run_id: int, kind: str, data: dict[str, Any]) -> None:
        """Append one event to the run's log (committed) and wake the streams."""
        with self.sessions() as s:
            write_event(s, run_id, kind, data)
            s.commit()
        self.poke(run_id)

    def retry(self, write: Callable[[], T], what: str, timeout: float | None = DB_OUTAGE_S) -> T:
        """``write()``, tried again every second while the database is away (it restarts), for at
        most ``timeout`` s (None: as long as it takes; a lost worker's run is then the reaper's)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                return write()
            except DBAPIError as e:
                if not db_away(e) or (deadline is not None and time.monotonic() > deadline):
                    raise
                log.warning("%s: the database is away (%s); trying again", what, type(e.orig).__name__)
                time.sleep(1.0)


def db_away(e: BaseException) -> bool:
    """Whether a database error means the server cannot be reached (restarting), not a bad write."""
    return isinstance(e, (OperationalError, InterfaceError)) or (isinstance(e, DBAPIError) and e.connection_invalidated)


def write_event(s: Session, run_id: int, kind: str, data: dict[str, Any]) -> None:
    """One event of a run, with the station's state when the run starts or pauses (not committed)."""
    publish(s, run_id, kind, data)
    if kind == "state" and data.get("state") in (RunState.running.value, RunState.paused.value):
        s.execute(update(Station).where(Station.run_id == run_id).values(state=data["state"]))


class Outbox:
    """A running run's writes (its samples, as the engine's sink, and its events), in order. A write
    the database cannot take now (a restart) waits here and goes with the next one, so the engine
    never waits on the database and nothing is lost; :meth:`drain` empties it at the end."""

    def __init__(self, ctx: WorkerContext, run_id: int) -> None:
        self.ctx, self.run_id = ctx, run_id
        self._pending: list[tuple[Callable[[Session], Any], int]] = []  # (write, samples in it)
        self._lock = threading.Lock()
        self.closed = False  # set once the run was ended elsewhere: no further sample or event is its

    def add(self, slot: int, rec: Recording) -> None:
        """The engine's sink: one slot's samples of one acquisition."""
        self._put(lambda s: insert_samples(s, self.run_id, slot, rec), len(rec))

    def publish(self, kind: str, data: dict[str, Any]) -> None:
        """One event of the run."""
        self._put(lambda s: write_event(s, self.run_id, kind, data), 0)

    @property
    def samples_waiting(self) -> int:
        """Samples not yet in the database."""
        with self._lock:
            return sum(n for _, n in self._pending)

    def _put(self, write: Callable[[Session], Any], samples: int) -> None:
        with self._lock:
            if self.closed:
                return
            self._pending.append((write, samples))
        self.flush()

    def flush(self) -> bool:
        """Write everything waiting, in order, in one transaction; False when the database is away."""
        with self._lock:
            if not self._pending:
                return True
            try:
                with self.ctx.sessions() as s:
                    if s.scalar(select(Run.status).where(Run.id == self.run_id)) in FINAL:
                        # ended elsewhere (this worker taken for lost while frozen): nothing more is the run's
                        self.closed = True
                        self._pending.clear()
                        return True
                    for write, _ in self._pending:
                        write(s)
                    s.commit()
            except DBAPIError as e:
                if not db_away(e):
                    raise
                return False
            self._pending.clear()
        self.ctx.poke(self.run_id)
        return True

    async def drain(self, timeout: float) -> bool:
        """Flush until empty (True) or ``timeout`` s have passed with the database still away."""
        deadline = time.monotonic() + timeout
        while not await asyncio.to_thread(self.flush):
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(1.0)
        return True


def _context(job: JobContext) -> WorkerContext:
    return job.additional_context["compasscal"]


# -------------------------------------------------------------------------------------- a run

@dataclass
class _Finish:
    """How a run ended."""

    status: str
    reason: str | None = None
    fault: str | None = None  # the station's fault, if the hardware needs the operator
    summary: dict[str, Any] = field(default_factory=dict)


class RunControl:
    """The operator's commands to one executing run, taken from the database in order and handed
    to its engine (kept until the engine exists)."""

    def __init__(self, ctx: WorkerContext, run_id: int) -> None:
        self.ctx, self.run_id = ctx, run_id
        self.outbox = Outbox(ctx, run_id)
        self.engine: Engine | None = None
        self.abort_reason: str | None = None
        self.ended_elsewhere: str | None = None  # why, once the run was found ended by another process
        # set before this worker writes the run's end: a last poll still in its thread then sees the run
        # ended by this worker itself, not elsewhere (it said "ended meanwhile" after a completed run)
        self.finishing = False
        self.pending: list[RunCommand] = []

    def take(self) -> None:
        """Read the commands not yet taken and apply them; and abort the run when it was ended elsewhere
        (a reaper that took this worker for lost while it stood frozen: it woke and drove the table
        through the rest of a plan whose run said failed, on a station said to be in fault)."""
        with self.ctx.sessions() as s:
            rows = list(s.scalars(select(RunCommand).where(RunCommand.run_id == self.run_id, RunCommand.taken_at.is_(None))
                                  .order_by(RunCommand.id)))
            for r in rows:
                r.taken_at = utcnow()
            ended = s.execute(select(Run.status, Run.reason).where(Run.id == self.run_id)).first()
            s.commit()
        if ended is not None and ended.status in FINAL and self.ended_elsewhere is None and not self.finishing:
            self.ended_elsewhere = f"run {self.run_id} was ended meanwhile ({ended.status}: {ended.reason})"
            self.abort_reason = self.abort_reason or self.ended_elsewhere
            self.outbox.closed = True  # what the table does now is no part of the ended run
            if self.engine is not None:
                self.engine.abort(self.ended_elsewhere)
            warning = StepWarning(f"{self.ended_elsewhere}: this worker stopped its axes and kept nothing further")
            with self.ctx.sessions() as s:
                write_event(s, self.run_id, warning.kind, warning.data())
                s.commit()
        for r in rows:
            if r.kind == "abort":
                self.abort_reason = self.abort_reason or str(r.data.get("reason") or "aborted by the operator")
            if self.engine is None:
                self.pending.append(r)
            else:
                self.apply(r)

    def apply(self, r: RunCommand) -> None:
        assert self.engine is not None
        if r.kind == "pause":
            self.engine.pause()
        elif r.kind == "resume":
            self.engine.resume()
        elif r.kind == "abort":
            self.engine.abort(str(r.data.get("reason") or "aborted by the operator"))
        elif r.kind == "answer":
            if self.engine.answer(str(r.data["id"]), str(r.data.get("answer", ""))):
                answered = PromptAnswered(r.data["id"], r.data.get("answer", ""))
                self.outbox.publish(answered.kind, answered.data())

    def attach(self, engine: Engine) -> None:
        self.engine = engine
        pending, self.pending = self.pending, []
        for r in pending:
            self.apply(r)

    async def follow(self) -> None:
        """Take commands until cancelled."""
        while True:
            try:
                await asyncio.to_thread(self.take)
            except Exception:  # noqa: BLE001 - the database is away for a moment: try again
                pass
            await asyncio.sleep(COMMAND_POLL_S)


async def execute_run(ctx: WorkerContext, run_id: int) -> None:
    """Run one queued run to its end: open the station, identify the units, drive the procedure's
    engine with the samples going to the database, store each unit's calibration, free the station.
    A run that is no longer ``queued`` (aborted before a worker took it) is left as it is."""
    def take() -> tuple[dict[str, Any], dict[str, str], str, dict[str, Any], dict[str, Any],
                        tuple[dict[str, str], dict[str, str]]] | None:
        with ctx.sessions() as s:
            run = s.get(Run, run_id)
            if run is None or run.status != RunState.queued.value:
                return None
            # this worker serves the station from now on (a station made since the last beat has none)
            s.execute(update(Station).where(Station.run_id == run_id).values(heartbeat_at=utcnow(), worker=ctx.name))
            s.commit()
            return (dict(run.station_snapshot or {}), dict(run.serials or {}), run.procedure, dict(run.parameters or {}),
                    dict(run.meta or {}), batch_certified(s, run))
    taken = ctx.retry(take, f"run {run_id}")
    if taken is None:
        return
    snapshot, given, name, parameters, meta, (seen, under) = taken
    proc = PROCEDURES[name]
    try:  # checked when the run was made; a stored run the procedure's rules now refuse ends, not the worker
        params = proc.validate(parameters)
    except ValidationError as e:
        why = "; ".join(f"{'.'.join(map(str, err['loc'])) or 'parameters'}: {err['msg']}" for err in e.errors())
        ctx.retry(lambda: _finish(ctx, run_id, _Finish(RunState.failed.value, f"parameters refused: {why}"), None),
                  f"run {run_id}", timeout=None)
        return
    check = UnitCheck(typed={int(k): str(v) for k, v in given.items()}, slots=list(range(len(snapshot["compasses"]))),
                      policy=str(meta.get("serial_policy") or DEFAULT_POLICY), seen=seen, certified_before=under,
                      mounted_after=MOUNT_PROMPT if name == BATCH else None,
                      on_settled=lambda ids: ctx.retry(lambda: _keep_identities(ctx, run_id, ids), f"run {run_id}"),
                      reports_itself=lambda serial: ctx.retry(lambda: _reports_itself(ctx, serial), f"run {run_id}"))
    control = RunControl(ctx, run_id)
    ctx.executing[run_id] = control
    follower = asyncio.create_task(control.follow())
    table_seconds: float | None = None
    fin = _Finish(RunState.failed.value)
    try:
        fin, table_seconds = await _drive(ctx, run_id, control, snapshot, proc, params, given, meta.get("resume"), check)
    except asyncio.CancelledError:  # the worker is going down: the engine has stopped the axes
        fin = _Finish(RunState.aborted.value, "worker shutting down")
    except Exception as e:  # noqa: BLE001 - a bug or closing the hardware failed: end the run, not the worker
        fin = _Finish(RunState.failed.value, f"internal error: {_reason(e)}", fault=_reason(e))
    finally:
        control.finishing = True
        follower.cancel()
        await asyncio.gather(follower, return_exceptions=True)
        ctx.executing.pop(run_id, None)
        # the run's end must reach the database: wait for it as long as it takes (a worker killed
        # meanwhile leaves the run to the reaper)
        ctx.retry(lambda: _finish(ctx, run_id, fin, table_seconds), f"run {run_id}", timeout=None)


def batch_certified(s: Session, run: Run) -> tuple[dict[str, str], dict[str, str]]:
    """What the units before this run in its batch were certified as (a calibration kept, not rejected:
    a unit that failed may be mounted again for a retest): their identified serials -> which unit (a
    unit reporting one again is the same unit mounted again), and the serials they were certified under
    -> which unit (another unit may not be certified under one of them)."""
    seen: dict[str, str] = {}
    under: dict[str, str] = {}
    if run.batch_id is None:
        return seen, under
    for r in s.scalars(select(Run).where(Run.batch_id == run.batch_id, Run.id < run.id).order_by(Run.id)):
        for entry in (((r.meta or {}).get("result") or {}).get("units") or {}).values():
            if not (isinstance(entry, dict) and entry.get("calibration_id") and entry.get("status") != "rejected"):
                continue
            serial, identified = str(entry.get("serial") or ""), entry.get("identified_serial")
            if identified:
                seen.setdefault(str(identified), f"{serial} earlier in this batch (run {r.id})")
            reports = f", which reports {identified}" if identified and identified != serial else ""
            under.setdefault(serial, f"the unit of run {r.id} earlier in this batch{reports}")
    return seen, under


def _identities_json(identities: dict[int, Identity]) -> dict[str, Any]:
    """Each slot's identity as a run keeps it (by slot as text)."""
    return {str(k): {"serial": i.serial, **i.to_json()} for k, i in sorted(identities.items())}


def _keep_identities(ctx: WorkerContext, run_id: int, identities: dict[int, Identity]) -> None:
    """The units' identities in the run's meta as soon as they are settled (``identities``): a run whose
    worker is lost has no result to carry them, and the reaper takes them from here."""
    with ctx.sessions() as s:
        run = s.get(Run, run_id)
        run.meta = {**(run.meta or {}), IDENTITIES_KEY: _identities_json(identities)}
        s.commit()


def _reports_itself(ctx: WorkerContext, serial: str) -> bool:
    with ctx.sessions() as s:
        return reports_itself(s, serial)


async def _drive(ctx: WorkerContext, run_id: int, control: RunControl, snapshot: dict[str, Any], proc: Any,
                 params: Any, given: dict[str, str], resume: dict[str, Any] | None,
                 check: UnitCheck) -> tuple[_Finish, float | None]:
    identify_first = proc.name != BATCH  # a batch's unit is mounted only after its prompt
    async with AsyncExitStack() as stack:
        try:
            station = await asyncio.wait_for(stack.enter_async_context(open_station(
                snapshot["modbus"], snapshot["compasses"], time_scale=snapshot["time_scale"],
                sample_rate_hz=SAMPLE_RATE_HZ, name=snapshot["name"])), OPEN_TIMEOUT_S)
        except Exception as e:  # noqa: BLE001 - unreachable table or compass, bad URL: the station's fault
            why = f"could not open station {snapshot['name']}: {_reason(e)}"
            return _Finish(RunState.failed.value, why, fault=advised(why)), None
        idents: dict[int, tuple[str, str, str]] = {}
        if identify_first and control.abort_reason is None:
            try:  # (a compass that cannot identify itself is left out: its unit is "not identified")
                idents = await asyncio.wait_for(identify_units(station.fixture), IDENTIFY_TIMEOUT_S)
            except Exception as e:  # noqa: BLE001 - a compass that does not answer
                why = f"could not identify the compasses: {_reason(e)}"
                return _Finish(RunState.failed.value, why, fault=why), None
            check.idents = idents  # else the engine identifies the units once they are mounted
        serials = {slot: ident[1] for slot, ident in idents.items()}
        serials.update({int(k): v for k, v in given.items()})
        if idents:
            with ctx.sessions() as s:
                s.execute(update(Run).where(Run.id == run_id).values(serials={str(k): v for k, v in sorted(serials.items())}))
                s.commit()

        def on_event(e: Event) -> None:  # in this thread, inside the engine
            if isinstance(e, StateChanged) and e.state.value in FINAL:
                return  # held back: the run ends once its calibrations are stored
            if isinstance(e, Result):
                return  # replaced by the fuller result below
            control.outbox.publish(e.kind, e.data())

        replay = None
        if resume is not None:
            moved = {slot: (str(old), idents[int(slot)][1]) for slot, old in (resume.get("serials") or {}).items()
                     if old and int(slot) in idents and idents[int(slot)][1] and idents[int(slot)][1] != str(old)}
            if moved:
                return _Finish(RunState.failed.value, f"cannot resume run {resume['run_id']}: " + ", ".join(
                    f"slot {k} holds {new}, not {old}" for k, (old, new) in sorted(moved.items()))
                    + "; mount the same units or start a new run"), None
            replay = ctx.retry(lambda: load_replay(ctx, int(resume["run_id"]), int(resume["checkpoints"])), f"run {run_id}")
        # the units' identity is checked before the table moves (a mismatch may prompt or refuse)
        engine = Engine(station, check.procedure(proc), params, control.outbox, on_event=on_event, serials=serials,
                        replay=replay, prompt_timeout_s=ctx.prompt_timeout_s)
        await asyncio.to_thread(control.take)
        if control.abort_reason is not None:
            return _Finish(RunState.aborted.value, control.abort_reason), None
        control.attach(engine)
        result = await engine.run()
        fin = _Finish(result.state.value, result.reason)
        if not await control.outbox.drain(DB_OUTAGE_S):  # samples the database could not take yet
            lost = control.outbox.samples_waiting
            fin = _Finish(RunState.failed.value, f"{lost} of {result.samples} samples lost: the database was away "
                          f"for more than {DB_OUTAGE_S:g} s")
            result.outcome = None
        elif result.state is RunState.failed:
            fin.fault = await _probe(station, result.reason)
        elif result.state is RunState.completed and check.nothing_left:
            # every unit refused, skipped or mounted again: the run calibrated nothing
            fin = _Finish(RunState.failed.value, "; ".join(check.reasons()),
                          summary={"units": {str(k): {"serial": i.serial, **i.to_json(), "error": i.note}
                                             for k, i in sorted(check.identities.items())}})
        elif result.state is RunState.completed and result.outcome is not None:
            idents = check.idents or idents  # a batch's unit was identified in the run, once mounted
            try:
                fin.summary = ctx.retry(lambda: _store(ctx, run_id, result.outcome, serials, idents, check.identities),
                                        f"run {run_id}")
            except Exception as e:  # noqa: BLE001 - the data is kept; the run says what went wrong
                fin = _Finish(RunState.failed.value, f"storing the calibrations failed: {_reason(e)}")
        if "units" not in fin.summary and check.identities:  # ended without results after naming its units: whom
            fin.summary["identities"] = _identities_json(check.identities)
        fin.summary = {**fin.summary, "samples": result.samples}
        said = table_time_note(result, bool(getattr(params, "adaptive", False)), float(snapshot["time_scale"]))
        if said and "units" in fin.summary:
            text, mismatch = said
            fin.summary["notes"] = [*fin.summary.get("notes", []), f"{text}: set the station's time_scale (PUT /stations/"
                                                                    f"{snapshot['name']}) to the simulator's" if mismatch else text]
        return fin, result.table_seconds


def load_replay(ctx: WorkerContext, run_id: int, checkpoints: int) -> Replay:
    """An interrupted run's samples (by step label and slot) and prompt answers, for a run resuming it."""
    samples: dict[str, dict[int, Recording]] = {}
    with ctx.sessions() as s:
        run = s.get(Run, run_id)
        slots = sorted(s.scalars(select(Sample.slot).where(Sample.run_id == run_id).distinct()))
        for slot in slots:
            rec = load_recording(s, run, slot)
            if rec is None:
                continue
            for label in dict.fromkeys(rec.step.tolist()):
                samples.setdefault(str(label), {})[int(slot)] = rec.select(rec.step == label)
        answers = {str(d["id"]): str(d.get("answer", "")) for d in s.scalars(
            select(RunEvent.data).where(RunEvent.run_id == run_id, RunEvent.kind == "prompt").order_by(RunEvent.id))
            if isinstance(d, dict) and d.get("answered")}
    return Replay(run_id, checkpoints, samples, answers)


async def _probe(station: Any, reason: str | None) -> str | None:
    """After a failed run: the station's fault, if its table or a compass needs the operator (else None: a
    compass that stopped talking left the station "idle", and the next run failed at its identification)."""
    try:
        status = await asyncio.wait_for(station.table.status_all(), 3.0)
    except Exception as e:  # noqa: BLE001
        return advised(f"{reason}; the table does not answer: {_reason(e)}")
    faulted = [with_advice(f"axis {n}: fault {s.fault_name or s.fault_code}", s.fault_code) for n, s in status.items()
               if s.fault]
    if faulted or _is_hardware_error(reason):
        return advised(reason or ", ".join(faulted))
    return None


def _store(ctx: WorkerContext, run_id: int, outcome: Any, serials: dict[int, str],
           idents: dict[int, tuple[str, str, str]], identities: dict[int, Identity] | None = None) -> dict[str, Any]:
    """Judge and keep each unit's calibration under the serial its identity check settled on (none
    for a unit refused, skipped or mounted again); the summary of the run's result by slot."""
    units: dict[str, Any] = {}
    with ctx.sessions() as s:
        run = s.get(Run, run_id)
        for slot, res in sorted(outcome.results.items()):
            identity = (identities or {}).get(slot)
            serial = identity.serial if identity is not None else (serials.get(slot) or "")
            entry: dict[str, Any] = {"serial": serial, **(identity.to_json() if identity is not None else {})}
            ident = idents.get(slot)
            cal = res.get("calibration")
            bad_serial = _bad_serial(serial) if serial else None
            if isinstance(cal, PhysCalibration):
                if identity is not None and not identity.certify:
                    entry["error"] = identity.note  # measured, but not certified: say why
                elif not serial:
                    entry["error"] = "the compass reported no serial number; give serials in the request"
                elif bad_serial:  # a compass's own answer, never checked at the edge: checked here
                    entry["error"] = f"the compass reported the serial {serial!r}: {bad_serial}; give serials in the request"
                else:
                    cal.serial = serial
                    row = store_calibration(s, run, slot, serial, json_safe(cal.to_json()),
                                            ident[0] if ident else None, ident[2] if ident else None,
                                            identity.to_json() if identity is not None else None)
                    entry.update(calibration_id=row.id, verdict=row.verdict, status=row.status, reasons=row.reasons,
                                 heading_error_deg=json_safe((cal.quality or {}).get("heading_error_deg")))
            elif "error" in res:
                entry["error"] = str(res["error"])
            else:
                entry["result"] = json_safe(res)
                owner = res.get("calibration_serial")
                if owner and serial and owner != serial:  # evaluated another unit's calibration on this one
                    entry["warning"] = (f"the calibration evaluated is of unit {owner}, but the unit in slot {slot} is "
                                        f"{serial}: these heading errors are not of {serial}'s calibration")
            units[str(slot)] = entry
        s.commit()
    return {"units": units, "notes": list(outcome.notes)}


def _bad_serial(serial: str) -> str | None:
    """Why a serial number cannot be stored (the API's rule), or None."""
    from service.schemas import check_serial

    try:
        check_serial(serial)
    except ValueError as e:
        return str(e)
    return None


def _finish(ctx: WorkerContext, run_id: int, fin: _Finish, table_seconds: float | None) -> None:
    """Write the run's end and free its station in one transaction, then publish it: whoever sees
    the final state can fetch the calibrations and start the next run at once."""
    with ctx.sessions() as s:
        run = s.get(Run, run_id)
        if run is None:
            return
        if run.status in FINAL:  # ended meanwhile (a reaper that thought this worker lost)
            return
        run.finished_at = utcnow()
        if table_seconds is not None:
            run.table_seconds = table_seconds
        if fin.summary:
            run.meta = {**(run.meta or {}), "result": json_safe(fin.summary)}
        s.execute(update(Station).where(Station.run_id == run_id)
                  .values(run_id=None, state="fault" if fin.fault else "idle", reason=fin.fault))
        if fin.status == RunState.completed.value:
            publish(s, run_id, "result", fin.summary)
        publish(s, run_id, "state", {"state": fin.status, "reason": fin.reason})
        batch = s.get(Batch, run.batch_id) if run.batch_id is not None else None
        if batch is not None and batch.finished_at is not None and (run.meta or {}).get("resume"):
            # a unit of an ended batch, resumed on its own (its worker lost mid-batch): the batch's summary
            # says how it came out (it kept "failed: worker lost", the certificate unlinked from the batch)
            settle_resumed_unit(batch, str((run.serials or {}).get("0", "")), f"{_verdict(run)} (resumed as run {run.id})")
        s.commit()
    ctx.poke(run_id)


def run_task(job: JobContext, run_id: int) -> None:
    """The job of one run (on its station's queue)."""
    asyncio.run(execute_run(_context(job), run_id))


# ---------------------------------------------------------------------------------- batches

async def execute_batch(ctx: WorkerContext, batch_id: int, parameters: dict[str, Any], operator: str,
                        serial_policy: str | None = None) -> None:
    """Each unit in turn on slot 0: a mount prompt, the calibration, its verdict in the summary. A
    unit that fails does not stop the batch; a station in fault does (nothing can run on it). A batch
    that calibrated none of its units ends ``failed`` (each unit's reason in the summary).
    ``serial_policy`` (None: the station's) settles a unit reporting another serial than its own;
    a unit reporting a serial already certified in the batch is not certified again."""
    with ctx.sessions() as s:
        batch = s.get(Batch, batch_id)
        station = s.get(Station, batch.station_id)
        name, serials = station.name, list(batch.serials)
    summary: dict[str, str] = {}
    status, previous, calibrated = "completed", None, 0
    try:
        for serial in serials:
            if ctx.stopping.is_set():  # the worker was asked to stop (SIGTERM): the unit on the table is done
                summary.update({x: NOT_RUN + WORKER_STOPPED for x in serials if x not in summary})
                status = "failed"
                break
            with ctx.sessions() as s:
                batch = s.get(Batch, batch_id)
                if batch.finished_at is not None:  # ended elsewhere (this worker taken for lost)
                    break
                if batch.status == BATCH_ABORTING:  # PUT /batches/{id}/state: no further unit
                    summary.update({x: NOT_RUN + "the batch was aborted" for x in serials if x not in summary})
                    status = "aborted"
                    break
                row = s.scalar(select(Station).where(Station.name == name))
                fault = row.reason if row.state == "fault" else None
                try:
                    run = None if fault else create_run(s, name, BATCH, {**parameters, "serial": serial, "unmount": previous},
                                                        {"0": serial}, operator, ctx.software_version, batch_id=batch_id,
                                                        serial_policy=serial_policy)
                except DomainError as e:
                    summary[serial] = NOT_RUN + e.detail
                    continue
            if fault:
                summary[serial], status = NOT_RUN + f"station in fault ({fault})", "failed"
                continue
            ctx.poke(run.id)
            watch = asyncio.create_task(_unmounted_on_stop(ctx, run.id, serial))
            try:
                await execute_run(ctx, run.id)
            finally:
                watch.cancel()
            with ctx.sessions() as s:
                done = s.get(Run, run.id)
                summary[serial] = _verdict(done)
                unit = slot_result((done.meta or {}).get("result"))
                calibrated += done.status == RunState.completed.value and "verdict" in unit
                reported = unit.get("identified_serial")
                mounted = _mount_answered(s, run.id)
            # the unit to take out, by what the operator typed and, when it said otherwise, what it reported
            # (none when it was never mounted: the next prompt said to unmount a unit no one had put on)
            previous = None if not mounted else f"{serial}" + (
                f" (it reports {reported})" if reported and reported != serial else "") + f" ({summary[serial]})"
            if not mounted and done.status == RunState.failed.value:
                # never mounted (no one answered its mount prompt in time): no one is at the station to mount
                # the rest either (each unit held the station for the whole prompt timeout in turn)
                summary.update({x: NOT_RUN + f"unit {serial} was never mounted ({done.reason})"
                                for x in serials if x not in summary})
                status = "failed"
                break
            _save_batch(ctx, batch_id, "running", summary, final=False)
    finally:
        with ctx.sessions() as s:
            s.execute(update(Station).where(Station.name == name, Station.batch_id == batch_id).values(batch_id=None))
            s.commit()
        if status == "completed" and not calibrated:
            status = "failed"  # it went through its units and calibrated none: the station, not the units, is suspect
        _save_batch(ctx, batch_id, status, summary, final=True)


def _mount_answered(s: Session, run_id: int) -> bool:
    """Whether the operator answered the run's mount prompt (its unit was put on the table)."""
    return any(e.data.get("id") == MOUNT_PROMPT and e.data.get("answered") for e in s.scalars(
        select(RunEvent).where(RunEvent.run_id == run_id, RunEvent.kind == PromptAnswered.kind)))


#: Why a batch's units were not run when its worker was asked to stop.
WORKER_STOPPED = "the station's worker was stopped; calibrate it in a new batch"


async def _unmounted_on_stop(ctx: WorkerContext, run_id: int, serial: str) -> None:
    """While a batch unit's run executes: once this process is asked to stop, abort the run if it is still
    waiting for its unit to be mounted (nothing measured; the prompt would hold the worker for minutes)."""
    while True:
        await asyncio.sleep(0.2)
        ctl = ctx.executing.get(run_id)
        if ctx.stopping.is_set() and ctl is not None and ctl.engine is not None and ctl.engine.waiting_for(MOUNT_PROMPT):
            ctl.engine.abort(f"{WORKER_STOPPED} (unit {serial} was not yet mounted)")
            return


def _verdict(run: Run) -> str:
    """One unit's line in a batch summary (keyed by the serial typed): its verdict, and the serial it was
    certified under when not that one; or why it has none."""
    if run.status != RunState.completed.value:
        return f"{run.status}: {run.reason}"
    unit = slot_result((run.meta or {}).get("result"))
    if "verdict" in unit:
        typed = (run.serials or {}).get("0")
        return unit["verdict"] + (f" (certified as {unit['serial']})" if unit.get("serial") and unit["serial"] != typed else "")
    return f"no calibration: {unit.get('error', 'no data from slot 0')}"


def _save_batch(ctx: WorkerContext, batch_id: int, status: str, summary: dict[str, str], final: bool) -> None:
    with ctx.sessions() as s:
        batch = s.get(Batch, batch_id)
        if batch is None or batch.finished_at is not None:
            # ended elsewhere: a reaper took this worker for lost and said what became of each unit (a worker
            # that woke from a freeze rewrote that summary)
            return
        if final or batch.status != BATCH_ABORTING:  # (an abort asked for meanwhile stands)
            # an abort asked for is what ended the batch, whatever its last unit did (a batch aborted
            # during its last unit, none calibrated, ended "failed")
            batch.status = "aborted" if batch.status == BATCH_ABORTING else status
        batch.summary = dict(summary)
        if final:
            batch.finished_at = utcnow()
        s.commit()


def batch_task(job: JobContext, batch_id: int, parameters: dict[str, Any], operator: str,
               serial_policy: str | None = None) -> None:
    """The job of one batch (on its station's queue: the station's lock is held for the whole batch)."""
    asyncio.run(execute_batch(_context(job), batch_id, parameters, operator, serial_policy))


# --------------------------------------------------------------------------------- analyses

#: The queue of discrepancy analyses: any worker that takes it computes them (no station needed).
ANALYSIS_QUEUE = "analyses"
#: Analyses computed at the same time in one process (each holds most of a core), and seconds
#: between two progress writes of one analysis.
ANALYSES_AT_ONCE = 2
PROGRESS_EVERY_S = 0.5
_analysis_slots = threading.BoundedSemaphore(ANALYSES_AT_ONCE)


def _analysis_update(ctx: WorkerContext, analysis_id: int, **values: Any) -> None:
    """Change an analysis's row, bump its version (its stream's event id) and notify its streams."""
    def write() -> None:
        with ctx.sessions() as s:
            row = s.get(Analysis, analysis_id)
            if row is None:
                return
            for k, v in values.items():
                setattr(row, k, v)
            row.version = (row.version or 0) + 1
            notify(s, analysis_topic(analysis_id))
            s.commit()
    ctx.retry(write, f"analysis {analysis_id}")
    ctx.poke(analysis_topic(analysis_id))


def execute_analysis(ctx: WorkerContext, analysis_id: int) -> None:
    """Compute one analysis (a unit of an ended run against its nominal calibration) and store its
    result, reporting progress on the row; ``failed`` with the reason when the recording cannot
    support it. An analysis already ended is left as it is (a job retried after a lost worker)."""
    from physics.discrepancy import analyze

    with _analysis_slots:
        with ctx.sessions() as s:
            row = s.get(Analysis, analysis_id)
            if row is None or row.status in ANALYSIS_FINAL:
                return
            run_id, slot, req = row.run_id, int(row.slot or 0), dict(row.request or {})
            run = s.get(Run, run_id)
            rec = load_recording(s, run, slot) if run is not None else None
            cal_id = req.get("calibration_id")
            cal = s.get(Calibration, cal_id) if cal_id is not None else None
            cal_json = cal.data if cal is not None else None
        if rec is None:
            _analysis_update(ctx, analysis_id, status="failed", finished_at=utcnow(),
                             reason=f"run {run_id} has no samples from slot {slot}")
            return
        _analysis_update(ctx, analysis_id, status="running", started_at=utcnow(), progress={"stage": "start", "percent": 0.0})
        last = [0.0, ""]

        def progress(stage: str, frac: float) -> None:  # from inside the analyser: a write at most twice a second
            now = time.monotonic()
            if stage != last[1] or now - last[0] >= PROGRESS_EVERY_S:
                last[:] = [now, stage]
                _analysis_update(ctx, analysis_id, progress={"stage": stage, "percent": round(100.0 * frac, 1)})

        null_sims = int(req.get("null_sims", 200))
        try:
            nominal = PhysCalibration.from_json(cal_json) if cal_json is not None else None
        except (ValueError, TypeError, KeyError) as e:
            _analysis_update(ctx, analysis_id, status="failed", finished_at=utcnow(),
                             reason=f"calibration {cal_id} cannot be read: {e}")
            return
        try:
            # seeded by the recording's fingerprint: the same samples analysed twice, here or by
            # `compasscal analyze` of their export, get the same null simulations, so the same p-values
            a = analyze(rec, nominal, null_sims=null_sims, progress=progress)
            report = json_safe({**a.to_json(), "run_id": run_id, "slot": slot, "serial": rec.serial or "",
                                "null_sims": null_sims, "calibration_id": cal_id})
        except ValueError as e:  # the recording cannot support the analysis: say why
            _analysis_update(ctx, analysis_id, status="failed", finished_at=utcnow(),
                             reason=f"run {run_id} slot {slot} cannot be analysed: {e}")
            return
        except Exception as e:  # noqa: BLE001 - a bug: the analysis says so, the worker carries on
            _analysis_update(ctx, analysis_id, status="failed", finished_at=utcnow(), reason=f"internal error: {_reason(e)}")
            return
        _analysis_update(ctx, analysis_id, status="completed", finished_at=utcnow(), report=report,
                         progress={"stage": "done", "percent": 100.0})


def analysis_task(job: JobContext, analysis_id: int) -> None:
    """The job of one analysis (on the analyses queue)."""
    execute_analysis(_context(job), analysis_id)


async def _requeue_analyses(app: App, ctx: WorkerContext, pg: bool) -> None:
    """Analyses whose job went with a process: on PostgreSQL the jobs of procrastinate workers that
    stopped beating are retried; then every analysis not ended that has no job waiting or running
    (its process stopped between writing the row and queueing the job, or the queue was in memory)
    is queued again. Rows younger than :data:`REQUEUE_AFTER_S` are left to the request still queueing them."""
    alive: set[int] = set()
    if pg:
        for job in await app.job_manager.get_stalled_jobs(queue=ANALYSIS_QUEUE, seconds_since_heartbeat=STALLED_S):
            await app.job_manager.retry_job(job)
        for job in await app.job_manager.list_jobs_async(queue=ANALYSIS_QUEUE, status="todo"):
            alive.add(int(job.task_kwargs.get("analysis_id", 0)))
        for job in await app.job_manager.list_jobs_async(queue=ANALYSIS_QUEUE, status="doing"):
            alive.add(int(job.task_kwargs.get("analysis_id", 0)))
    q = select(Analysis.id).where(Analysis.status.in_(("queued", "running")))
    if pg:  # (in memory, this process is the only one: nothing is on its way)
        q = q.where(Analysis.created_at < utcnow() - timedelta(seconds=REQUEUE_AFTER_S))
    with ctx.sessions() as s:
        ids = list(s.scalars(q))
    for analysis_id in ids:
        if analysis_id not in alive:
            await app.configure_task("compasscal.analysis", queue=ANALYSIS_QUEUE).defer_async(analysis_id=analysis_id)


async def _watch_analyses(app: App, ctx: WorkerContext) -> None:
    while True:
        await asyncio.sleep(STALLED_S / 2)
        try:
            await _requeue_analyses(app, ctx, True)
        except Exception:  # noqa: BLE001 - the database is away for a moment
            pass


# ----------------------------------------------------------------------------------- resets

async def reset_station(ctx: WorkerContext, name: str, token: str) -> None:
    """Reset the table's axis faults (RESET_FAULT on each faulted axis) and ask each compass who it is;
    the station becomes idle when no axis is faulted and every compass answers (a reset once said "idle"
    with a compass still silent). The outcome goes to the station's row under ``token`` (the API waits
    for it)."""
    with ctx.sessions() as s:
        row = s.scalar(select(Station).where(Station.name == name))
        if row is None:
            return
        modbus, compasses, busy = row.modbus, list(row.compasses or []), row.run_id
    out: dict[str, Any] = {"token": token}
    if busy is not None:
        out.update(ok=False, status=409, error=f"station {name} is busy with run {busy}; abort it first")
    else:
        table = Turntable(modbus)
        try:
            async def go() -> dict[str, Any]:
                await table.connect()
                before = await table.status_all()
                await table.reset_faults()
                after = await table.status_all()
                return {"reset_axes": [n for n, st in before.items() if st.fault],
                        "still_faulted": {n: with_advice(st.fault_name or str(st.fault_code), st.fault_code)
                                          for n, st in after.items() if st.fault}}
            out.update(ok=True, **await asyncio.wait_for(go(), OPEN_TIMEOUT_S))
        except Exception as e:  # noqa: BLE001 - any driver or network failure is reported; the state stays
            out.update(ok=False, status=503, error=advised(f"could not reset station {name}: {_reason(e)}"))
        finally:
            await table.close()
        if out.get("ok"):
            out["silent_compasses"] = await _silent_compasses(compasses)
    with ctx.sessions() as s:
        values: dict[str, Any] = {"reset": out}
        if out.get("ok"):
            if out["still_faulted"] or out["silent_compasses"]:
                values.update(state="fault", reason="still faulted after reset: " + ", ".join(
                    [f"axis {n}: {f}" for n, f in out["still_faulted"].items()]
                    + [f"compass slot {k} does not answer ({why}): check its cable and power"
                       for k, why in out["silent_compasses"].items()]))
            else:
                values.update(state="idle", reason=None)
        s.execute(update(Station).where(Station.name == name).values(**values))
        s.commit()


async def _silent_compasses(urls: list[str]) -> dict[str, str]:
    """The compasses (by slot) that do not answer who they are, and why; a refusal (NAK) is an answer."""
    fixture = SerialFixture(dict(enumerate(urls)))
    try:
        await asyncio.wait_for(fixture.open(), OPEN_TIMEOUT_S)
        await asyncio.wait_for(identify_units(fixture), IDENTIFY_TIMEOUT_S)
        return {}
    except FixtureError as e:
        return {str(k): _reason(x) for k, x in e.errors.items()}
    except Exception as e:  # noqa: BLE001 - a port that does not open, a fixture that does not answer in time
        return {"all": _reason(e) or "no answer in time"}
    finally:
        await fixture.close()


def reset_task(job: JobContext, station: str, token: str) -> None:
    """The job of a station reset (on the station's queue)."""
    asyncio.run(reset_station(_context(job), station, token))


# ----------------------------------------------------------------------------- the processes

#: The jobs, by name (queued as ``compasscal.NAME``).
JOBS: dict[str, Callable[..., None]] = {"run": run_task, "batch": batch_task, "reset": reset_task,
                                        "analysis": analysis_task}


def make_app(connector: Any) -> App:
    """A procrastinate app with compasscal's jobs (``compasscal.run``, ``.batch``, ``.reset``, ...)."""
    app = App(connector=connector)
    for name, fn in JOBS.items():
        app.task(name=f"compasscal.{name}", pass_context=True)(fn)
    return app


def pg_connector(database_url: str) -> PsycopgConnector:
    """procrastinate's connector for a ``postgresql://`` URL."""
    conninfo = database_url.replace("postgresql+psycopg://", "postgresql://")
    return PsycopgConnector(conninfo=conninfo, min_size=1, max_size=4)


def heartbeat(ctx: WorkerContext, stations: list[str] | None) -> None:
    """Mark the stations (None: every station) as served by this worker, now."""
    with ctx.sessions() as s:
        q = update(Station).values(heartbeat_at=utcnow(), worker=ctx.name)
        if stations is not None:
            q = q.where(Station.name.in_(stations))
        s.execute(q)
        s.commit()


def recover(ctx: WorkerContext, stations: list[str] | None, queued_too: bool, reason: str) -> list[int]:
    """End what a previous worker of these stations (None: every station) left: its running and
    paused runs (and its queued ones when their jobs are lost with it) fail with ``reason``; their
    stations go to fault when a run was cut off mid-way (the table may have stopped anywhere)."""
    states = ACTIVE if queued_too else (RunState.running.value, RunState.paused.value)
    ended = []
    with ctx.sessions() as s:
        q = select(Run).where(Run.status.in_(states))
        if stations is not None:
            q = q.where(Run.station_snapshot.is_not(None))
        for run in s.scalars(q):
            name = (run.station_snapshot or {}).get("name")
            if stations is not None and name not in stations:
                continue
            cut = run.status != RunState.queued.value
            run.status, run.reason, run.finished_at = RunState.failed.value, reason, utcnow()
            lost_run_result(run)
            st = s.scalar(select(Station).where(Station.run_id == run.id))
            if st is not None:
                st.run_id = None
                if cut:
                    st.state, st.reason = "fault", f"{reason} during run {run.id}; POST /stations/{st.name}/reset"
                else:
                    st.state = "idle"
            publish(s, run.id, "state", {"state": RunState.failed.value, "reason": reason})
            ended.append(run.id)
        # batches whose job went with the previous process (after their runs: their summaries read them)
        ids = None if stations is None else list(s.scalars(select(Station.id).where(Station.name.in_(stations))))
        end_lost_batches(s, ids, reason, queued_too=queued_too)
        s.commit()
    return ended


async def _stop_axes(ctx: WorkerContext, stations: list[str] | None) -> None:
    """A restarted worker first stops its tables (None: every station's), all at once: a killed
    worker or service may have left an axis turning."""
    with ctx.sessions() as s:
        q = select(Station.modbus)
        if stations is not None:
            q = q.where(Station.name.in_(stations))
        urls = sorted(set(s.scalars(q)))

    async def stop(url: str) -> None:
        table = Turntable(url)
        try:
            await asyncio.wait_for(table.connect(), 5.0)
            await asyncio.wait_for(table.stop_all(), 5.0)
        except Exception:  # noqa: BLE001 - a table that is off stops nothing; its next run will say so
            pass
        finally:
            await table.close()
    await asyncio.gather(*(stop(u) for u in urls))


async def _fail_stalled_jobs(app: App, queues: list[str] | None) -> None:
    """Jobs left ``doing`` by a previous worker of these stations' queues hold their station's lock:
    end them. (The analyses' queue is shared by every worker: its stalled jobs are retried instead.)"""
    for job in await app.job_manager.list_jobs_async(status="doing"):
        if job.queue != ANALYSIS_QUEUE and (queues is None or job.queue in queues):
            await app.job_manager.finish_job_by_id_async(job.id, status=Status.FAILED, delete_job=False)


async def _beat(ctx: WorkerContext, stations: list[str] | None) -> None:
    while True:
        try:
            await asyncio.to_thread(heartbeat, ctx, stations)
        except Exception:  # noqa: BLE001 - the database restarted: beat again next time
            pass
        await asyncio.sleep(HEARTBEAT_S)


async def serve_worker(database_url: str, stations: list[str], analyses: bool = True, concurrency: int = 4) -> None:
    """The station agent (``compasscal worker``): recover, stop the axes, then take the stations' jobs
    (and, with ``analyses``, the analyses' queue) until stopped. PostgreSQL only: the SQLite default
    runs its worker in the service."""
    from service.db import make_engine, sessions, upgrade

    engine = make_engine(database_url)
    await asyncio.to_thread(upgrade, engine)
    ctx = WorkerContext(sessions(engine), SOFTWARE_VERSION)
    with ctx.sessions() as s:
        known = set(s.scalars(select(Station.name).where(Station.name.in_(stations))))
    missing = [n for n in stations if n not in known]
    if missing:
        raise Conflict(f"no station {', '.join(repr(m) for m in missing)}; create it first (PUT /stations/NAME)")
    busy = await asyncio.to_thread(other_workers, ctx.sessions, stations, ctx.name)
    if busy:
        raise Conflict(served_elsewhere(busy))
    queues = [station_queue(n) for n in stations]
    app = make_app(pg_connector(database_url))
    await _stop_axes(ctx, stations)  # before anything else
    async with app.open_async():
        await _fail_stalled_jobs(app, queues)
        await asyncio.to_thread(recover, ctx, stations, False, "worker lost: the station's worker stopped mid-run")
        tasks = [asyncio.create_task(_beat(ctx, stations))]
        if analyses:
            queues.append(ANALYSIS_QUEUE)
            await _requeue_analyses(app, ctx, True)
            tasks.append(asyncio.create_task(_watch_analyses(app, ctx)))
        worker = asyncio.create_task(app.run_worker_async(
            queues=queues, concurrency=concurrency, name=ctx.name, wait=True, install_signal_handlers=False,
            additional_context={"compasscal": ctx}, fetch_job_polling_interval=1.0,
            update_heartbeat_interval=HEARTBEAT_S, shutdown_graceful_timeout=10.0))

        def stop() -> None:
            # the jobs see it at once: a batch starts no further unit and stops waiting for one to be
            # mounted; a run measuring goes on to its end (the worker waits for its job); a run standing
            # paused is aborted, to be resumed from its checkpoint (the worker waited, silent, for a resume)
            ctx.stopping.set()
            worker.cancel()
            for run_id, control in list(ctx.executing.items()):
                engine = control.engine
                if engine is not None and engine.state is RunState.paused:
                    log.warning("stopping: run %s stood paused; aborted (resume it from its last checkpoint)", run_id)
                    engine.abort("the station's worker stopped while the run stood paused: resume it (POST /runs "
                                 f'with "resume": {run_id}) once a worker runs')
                elif engine is not None:
                    log.warning("stopping: waiting for run %s to end its measuring", run_id)
        loop = asyncio.get_running_loop()
        for sig in STOP_SIGNALS:
            loop.add_signal_handler(sig, stop)
        try:
            await worker
        except asyncio.CancelledError:
            if not ctx.stopping.is_set():
                raise
        finally:
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
    engine.dispose()


#: The signals that stop a worker (``compasscal worker``): Ctrl-C, and what docker and systemd send.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def sqlite_service_lock(database_url: str) -> IO[bytes] | None:
    """The lock of the one service allowed on a SQLite database (its job queue is in that service's
    memory: a second service would end the first's runs as lost and start runs on its busy
    stations). An exclusive lock on ``DB.service-lock`` beside the database file, held while the
    returned file is open; Conflict naming the holder's pid when another service holds it."""
    import fcntl

    path = database_url.split("sqlite:///", 1)[-1] if database_url.startswith("sqlite:///") else ""
    if not path or path == ":memory:":
        return None
    lock = open(f"{path}.service-lock", "a+b")  # noqa: SIM115 - held open for the service's life
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().decode(errors="replace").strip() or "unknown"
        lock.close()
        raise Conflict(f"another compasscal service (pid {holder}) uses the database {path}; stop it first, "
                       "or give this one its own database (COMPASSCAL_DATABASE_URL)") from None
    lock.seek(0)
    lock.truncate()
    lock.write(str(os.getpid()).encode())
    lock.flush()
    return lock


class Jobs:
    """The service's side of the queue: defers jobs, cancels queued ones, and (unless the stations
    have workers of their own) runs a worker for every station in a thread of this process."""

    def __init__(self, database_url: str, ctx: WorkerContext, embedded: bool) -> None:
        self.url, self.ctx, self.embedded = database_url, ctx, embedded
        self.pg = database_url.startswith("postgresql")
        self.app: App | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._lock: IO[bytes] | None = None

    async def start(self) -> None:
        if self.pg:
            self.app = make_app(pg_connector(self.url))
            await self.app.open_async()
            if self.embedded:
                await self.app.job_manager.check_connection_async()
                await _fail_stalled_jobs(self.app, None)
        elif not self.embedded:
            raise ValueError("SQLite keeps its job queue in memory: its worker must run in the service")
        else:
            self._lock = sqlite_service_lock(self.url)
            self.app = make_app(InMemoryConnector())
        if self.embedded:
            # runs left active by a previous process: on PostgreSQL their queued jobs survive; in memory they do not
            await asyncio.to_thread(recover, self.ctx, None, not self.pg,
                                    "the service stopped while the run was active (worker lost)")
            self._thread = threading.Thread(target=self._serve, name="compasscal-worker", daemon=True)
            self._thread.start()
            await asyncio.to_thread(self._ready.wait, 30.0)
            if self._error is not None:
                raise self._error

    def _serve(self) -> None:
        try:
            asyncio.run(self._embedded())
        except BaseException as e:  # noqa: BLE001 - reported to start()
            self._error = e
            self._ready.set()

    async def _embedded(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        app = self.app if not self.pg else make_app(pg_connector(self.url))
        await _stop_axes(self.ctx, None)  # a service killed mid-run may have left an axis turning
        async with app.open_async():  # in memory: opened here, so its notifications reach this loop
            await _requeue_analyses(app, self.ctx, self.pg)
            tasks = [asyncio.create_task(_beat(self.ctx, None))]
            if self.pg:
                tasks.append(asyncio.create_task(_watch_analyses(app, self.ctx)))
            worker = asyncio.create_task(app.run_worker_async(
                queues=None, concurrency=16, name=self.ctx.name, wait=True, install_signal_handlers=False,
                additional_context={"compasscal": self.ctx}, fetch_job_polling_interval=0.5,
                listen_notify=True, update_heartbeat_interval=HEARTBEAT_S))
            self._ready.set()
            await self._stop.wait()
            worker.cancel()
            for t in tasks:
                t.cancel()
            await asyncio.gather(worker, *tasks, return_exceptions=True)

    async def defer(self, task: str, queue: str, lock: str | None = None, **kwargs: Any) -> int:
        """Queue job ``compasscal.task``; its id."""
        assert self.app is not None
        return await self.app.configure_task(f"compasscal.{task}", queue=queue, lock=lock).defer_async(**kwargs)

    async def cancel(self, job_id: int) -> bool:
        """Cancel a job no worker has taken; False when one has."""
        assert self.app is not None
        return await self.app.job_manager.cancel_job_by_id_async(job_id)

    async def cancel_queued(self, task: str, queue: str, **match: Any) -> bool:
        """Cancel the queued job of ``task`` on ``queue`` whose arguments include ``match``; False when none
        waits (a worker has taken it, or it is done)."""
        assert self.app is not None
        for job in await self.app.job_manager.list_jobs_async(queue=queue, task=f"compasscal.{task}", status="todo"):
            if all(job.task_kwargs.get(k) == v for k, v in match.items()):
                return await self.cancel(job.id)
        return False

    async def stop(self, grace_s: float = 5.0) -> None:
        """Abort the runs this process executes (axes stopped, samples kept), wait for them briefly,
        stop the worker thread and close the queue."""
        if self._thread is not None:
            self.ctx.stopping.set()  # a batch starts no further unit once its unit's run is aborted here
            runs = list(self.ctx.executing)
            if runs:
                with self.ctx.sessions() as s:
                    for run_id in runs:
                        s.add(RunCommand(run_id=run_id, kind="abort", data={"reason": "service shutting down"},
                                         created_at=utcnow()))
                    s.commit()
                deadline = asyncio.get_running_loop().time() + grace_s
                while self.ctx.executing and asyncio.get_running_loop().time() < deadline:
                    await asyncio.sleep(0.05)
            if self._loop is not None and self._stop is not None:
                try:
                    self._loop.call_soon_threadsafe(self._stop.set)
                except RuntimeError:
                    pass
            await asyncio.to_thread(self._thread.join, 5.0)
        if self.pg and self.app is not None:
            await self.app.close_async()
        if self._lock is not None:
            self._lock.close()  # releases the lock
            self._lock = None


__all__ = ["JOBS", "ANALYSIS_QUEUE", "station_queue", "execute_run", "execute_batch", "execute_analysis", "reset_station",
           "make_app", "serve_worker", "Jobs", "WorkerContext"]
