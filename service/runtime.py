"""The run-time layer shared by the API processes and the station workers (no FastAPI here).

The database is the only state they share:

- a station's row says what its worker reports (``idle``, ``running``, ``paused``, ``fault``, the
  run holding it, the worker's heartbeat);
- a run's row carries its status and its live view (pause requested, waiting prompts, progress);
- ``run_events`` holds every event a worker published, in order (the server-sent events replay it,
  so any API process can stream any run and a reconnect resumes with ``Last-Event-ID``);
- ``run_commands`` holds what operators asked (pause, resume, abort, a prompt's answer), which the
  run's worker takes in order.

Runs, batches, station resets and analyses are jobs (service/worker.py). The API validates a
request, claims the station in one conditional UPDATE (so two API processes can never start two
runs on one table), writes the run's row and defers its job; everything after that is the worker's.

Errors are domain errors (:class:`DomainError` and its kinds); service/app.py maps them to HTTP in
one handler.
"""

from __future__ import annotations

import asyncio
import json
import re
import threading
from dataclasses import dataclass
from datetime import datetime, timedelta
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from pydantic import ValidationError
from sqlalchemy import ColumnElement, String, cast, func, or_, select, text, update
from sqlalchemy.orm import Session, sessionmaker

from physics.calibration import json_safe
from procedures.calibrate import BATCH, LOOKAHEAD_S, MOUNT_PROMPT, needed_budget_s
from procedures.states import ACTIVE, FINAL, RunState, check_transition
from service.db import Batch, Calibration, Device, Run, RunCommand, RunEvent, Station, utcnow
from service.identity import CHOICES, DEFAULT_POLICY, POLICIES, check_serial, is_serial_prompt, normalise

try:
    SOFTWARE_VERSION = version("compasscal")
except PackageNotFoundError:  # running from a checkout that is not installed
    SOFTWARE_VERSION = "0+unknown"

#: Compass stream rate of every run (the engine's default; recorded in the run's metadata).
SAMPLE_RATE_HZ = 20
#: Seconds between a worker's heartbeats, and how many missed ones mean it is lost.
HEARTBEAT_S = 2.0
LOST_AFTER_S = 4 * HEARTBEAT_S
#: The PostgreSQL channel a worker notifies after each event it commits (payload: the run id).
CHANNEL = "compasscal_events"
#: The statuses of an analysis that has ended.
ANALYSIS_FINAL = ("completed", "failed")
#: Seconds an API call waits for a worker to act on a command it must confirm (a reset, an answer).
CONFIRM_S = 20.0


# -------------------------------------------------------------------------------------- errors

class DomainError(Exception):
    """A request the run-time layer refuses; ``status`` is the HTTP code service/app.py answers."""

    status = 400

    def __init__(self, detail: Any) -> None:
        super().__init__(detail if isinstance(detail, str) else json.dumps(detail))
        self.detail = detail


class NotFound(DomainError):
    status = 404


class Conflict(DomainError):
    status = 409


class Invalid(DomainError):
    """Bad input: ``detail`` is ``[{"field": ..., "problem": ...}]``."""

    status = 422


class Unavailable(DomainError):
    status = 503


#: A rule across fields says which field it faults first ("budget_s: ..."): the 422 names that field.
_RULE_FIELD = re.compile(r"^Value error, ([a-z_][a-z0-9_]*): (.*)$", re.S)


def field_errors(errors: list[Any], prefix: tuple[str, ...] = ()) -> list[dict[str, str]]:
    """Pydantic errors as the service's 422 detail: ``[{"field": "body.parameters.samples", "problem": ...}]``."""
    out = []
    for e in errors:
        loc, msg = [str(p) for p in e["loc"]], str(e["msg"])
        rule = _RULE_FIELD.match(msg) if not loc else None
        if rule:
            loc, msg = [rule.group(1)], rule.group(2)
        if e.get("type") == "json_invalid":  # its loc is (body, character offset): the field is the body
            at = f" at character {loc[1]}" if len(loc) > 1 else ""
            loc, msg = loc[:1], f"not valid JSON{at}: {(e.get('ctx') or {}).get('error', msg)}"
        out.append({"field": ".".join([*prefix, *loc]), "problem": msg})
    return out


#: A run's meta key holding its units' identities from the moment they are settled (service.worker).
IDENTITIES_KEY = "identities"
#: Serial decisions that certified no serial (refused, skipped by the operator, asked and never answered).
UNSETTLED = ("refused", "skip", "asked")


def lost_run_result(run: Run) -> None:
    """A run ended by the loss of its worker: its result names the units it had identified (the worker
    kept them in its meta), as a run that ends early does, where it has no result of its own."""
    meta = run.meta or {}
    if meta.get("result") is None and meta.get(IDENTITIES_KEY):
        run.meta = {**meta, "result": {"identities": meta[IDENTITIES_KEY]}}


def slot_result(result: dict[str, Any] | None, slot: int = 0) -> dict[str, Any]:
    """What a run's result holds of one slot's unit: serial, identity, verdict (a run that ended without
    results: its identity alone, ``identities``); {} without either."""
    result = result or {}
    return (result.get("units") or {}).get(str(slot)) or (result.get("identities") or {}).get(str(slot)) or {}


def unit_serial(run: Run, slot: int) -> str:
    """The serial number the unit in ``slot`` of a run goes by: the one its identity check settled on (the
    operator's answer, the unit's own when none was typed), else the one typed ("" if neither). Its
    exported samples and its analyses are labelled with it: the typed serial an operator rejected
    labelled them, and a re-import would have filed them under it."""
    meta = run.meta or {}
    for entry in (slot_result(meta.get("result"), slot), (meta.get(IDENTITIES_KEY) or {}).get(str(slot)) or {}):
        if entry.get("serial_decision") in UNSETTLED and entry.get("identified_serial"):
            # the typed serial was refused, skipped or never decided: the unit on the table is the one it reports
            # (its samples went by the refused serial, and their analysis took that unit's calibration)
            return str(entry["identified_serial"])
        if entry.get("serial"):
            return str(entry["serial"])
    return str((run.serials or {}).get(str(slot)) or "")


def runs_of_serial(serial: str) -> ColumnElement[bool]:
    """The runs of a unit by any of its serial numbers: typed for the run (serials is a small JSON object
    {"0": "SN-1"}, its text holds each serial JSON-quoted on both databases), reported by its unit (the
    result's identified_serial), or certified under (a unit typed otherwise: those runs were not found)."""
    needle = json.dumps(serial).replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
    certified = select(Calibration.run_id).join(Device, Device.id == Calibration.device_id).where(Device.serial == serial)
    return or_(cast(Run.serials, String).like(f"%{needle}%", escape="\\"),
               cast(Run.meta, String).like(f'%"identified_serial": {needle}%', escape="\\"),
               Run.id.in_(certified))


def invalid(field: str, problem: str) -> Invalid:
    """A 422 for one field, in the same shape."""
    return Invalid([{"field": field, "problem": problem}])


def station_filter(s: Session, name: str) -> int:
    """The id of the station a list is filtered by; a 422 naming ``query.station`` when there is none
    (a misspelt name listed nothing, as if the station had made no run)."""
    sid = s.scalar(select(Station.id).where(Station.name == name))
    if sid is None:
        known = s.scalars(select(Station.name).order_by(Station.name)).all()
        raise invalid("query.station", f"no station {name!r}; known: {', '.join(known) or 'none'}")
    return sid


# -------------------------------------------------------------------------------------- events

def publish(session: Session, run_id: int, kind: str, data: dict[str, Any]) -> None:
    """Append an event to the run's log and update the run's live view (committed by the caller).
    On PostgreSQL the commit also notifies every API process listening on :data:`CHANNEL`."""
    data = json_safe(data)
    session.add(RunEvent(run_id=run_id, kind=kind, data=data, created_at=utcnow()))
    run = session.get(Run, run_id)
    if run is not None:
        if kind == "prompt":
            prompts = dict(run.prompts or {})
            if data.get("answered"):
                prompts.pop(str(data.get("id")), None)
            else:
                prompts[str(data["id"])] = data.get("text", "")
            run.prompts = prompts
        elif kind == "progress":
            run.progress = data
        elif kind == "state":
            run.status = data["state"]
            if data["state"] != RunState.running.value:
                run.pause_requested = False
            if data["state"] == RunState.running.value and run.started_at is None:
                run.started_at = utcnow()
            if data["state"] in FINAL:
                run.prompts = {}
                run.reason = data.get("reason")
                if run.progress and data["state"] != RunState.completed.value:
                    # an ended run has no time left (its last progress still counted some: "~16 s left")
                    # and its samples are those kept (its last progress counted those of a pose before it ended:
                    # 360 against 407 kept)
                    run.progress = {**run.progress, "left_s": 0.0, "left_wall_s": 0.0,
                                    **({"samples": run.samples_count} if run.samples_count is not None else {})}
    notify(session, run_id)


def events_after(session: Session, run_id: int, after: int, limit: int = 500) -> list[RunEvent]:
    """The run's events with an id above ``after``, oldest first."""
    return list(session.scalars(select(RunEvent).where(RunEvent.run_id == run_id, RunEvent.id > after)
                                .order_by(RunEvent.id).limit(limit)))


def analysis_topic(analysis_id: int) -> str:
    """What an analysis's changes are notified as (a run's are its id)."""
    return f"analysis:{analysis_id}"


def notify(session: Session, topic: int | str) -> None:
    """On PostgreSQL, notify every listening API process of ``topic`` when the session commits."""
    if session.get_bind().dialect.name == "postgresql":
        session.execute(text("SELECT pg_notify(:channel, :topic)"), {"channel": CHANNEL, "topic": str(topic)})


class Notifier:
    """Wakes the API's event streams when a worker publishes: PostgreSQL's LISTEN on one connection
    per API process, or :meth:`poke` from a worker in this process. A topic is a run's id or
    :func:`analysis_topic`. Streams also re-read the database every second, so a lost notification
    delays an event, never loses it."""

    def __init__(self, database_url: str | None) -> None:
        self.url = database_url if database_url and database_url.startswith("postgresql") else None
        self._waiters: dict[str, asyncio.Event] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        if self.url:
            self._task = asyncio.create_task(self._listen(), name="notifier")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    async def _listen(self) -> None:
        import psycopg

        conninfo = self.url.replace("postgresql+psycopg://", "postgresql://")
        while True:
            try:
                async with await psycopg.AsyncConnection.connect(conninfo, autocommit=True) as conn:
                    await conn.execute(f"LISTEN {CHANNEL}")
                    async for n in conn.notifies():
                        self._wake(n.payload)
            except asyncio.CancelledError:
                raise
            except Exception:  # noqa: BLE001 - the database restarted: listen again (streams poll meanwhile)
                await asyncio.sleep(1.0)

    def _wake(self, topic: str) -> None:
        ev = self._waiters.pop(topic, None)
        if ev is not None:
            ev.set()

    def poke(self, topic: int | str) -> None:
        """Wake the streams of ``topic`` (thread-safe; a worker in this process calls it)."""
        if self._loop is None or self._loop.is_closed():
            return
        if threading.get_ident() == getattr(self._loop, "_thread_id", None):
            self._wake(str(topic))
        else:
            try:
                self._loop.call_soon_threadsafe(self._wake, str(topic))
            except RuntimeError:  # the loop has closed
                pass

    async def wait(self, topic: int | str, timeout: float) -> None:
        """Until ``topic`` (a run's id, an analysis's topic) publishes or ``timeout`` passes."""
        ev = self._waiters.setdefault(str(topic), asyncio.Event())
        try:
            await asyncio.wait_for(ev.wait(), timeout)
        except asyncio.TimeoutError:
            pass


# --------------------------------------------------------------------------------------- views

def worker_alive(row: Station, now: datetime | None = None) -> bool:
    """Whether a worker has served the station within :data:`LOST_AFTER_S`."""
    return row.heartbeat_at is not None and (now or utcnow()) - row.heartbeat_at < timedelta(seconds=LOST_AFTER_S)


def station_json(row: Station) -> dict[str, Any]:
    """A station as the API shows it: configuration, state, current run, fault, its worker."""
    return {"name": row.name, "modbus": row.modbus, "compasses": row.compasses, "time_scale": row.time_scale,
            "created_at": row.created_at, "state": row.state, "run_id": row.run_id, "fault": row.reason,
            "batch_id": row.batch_id, "worker": row.worker, "worker_alive": worker_alive(row),
            "heartbeat_at": row.heartbeat_at, "serial_policy": row.serial_policy or DEFAULT_POLICY}


def run_json(row: Run) -> dict[str, Any]:
    """A run as the API shows it: its row with its live view (prompts, progress) while it runs."""
    snap = row.station_snapshot or {}
    live = row.status in ACTIVE
    return {"id": row.id, "status": row.status, "reason": row.reason, "station": snap.get("name"),
            "procedure": row.procedure, "procedure_version": row.procedure_version, "parameters": row.parameters,
            "serials": row.serials, "operator": row.operator, "batch_id": row.batch_id,
            "software_version": row.software_version, "station_snapshot": row.station_snapshot,
            "created_at": row.created_at, "started_at": row.started_at, "finished_at": row.finished_at,
            "table_seconds": row.table_seconds, "samples_count": row.samples_count or 0,
            "result": (row.meta or {}).get("result"), "serial_policy": (row.meta or {}).get("serial_policy"),
            # a resumed run's samples up to its checkpoint are the run it continues; that run lists its continuations
            "resumed_from": ((row.meta or {}).get("resume") or {}).get("run_id"),
            "resumed_by": list((row.meta or {}).get("resumed_by") or []),
            "pause_requested": bool(live and row.pause_requested),
            "prompts": [{"id": k, "text": v} for k, v in (row.prompts or {}).items()] if live else [],
            "progress": row.progress}


def batch_json(s: Session, batch: Batch) -> dict[str, Any]:
    """A batch: status, one row per unit (run, status, verdict), the waiting prompt and the summary."""
    station = s.get(Station, batch.station_id)
    runs = s.scalars(select(Run).where(Run.batch_id == batch.id).order_by(Run.id)).all()
    by_serial: dict[str, Run] = {}
    for r in runs:
        by_serial[str((r.serials or {}).get("0", ""))] = r  # the latest run of each unit
    # a batch's unit is slot 0's (its run's other rows, if any, are not the batch's)
    cals = {c.run_id: c for c in s.scalars(select(Calibration).where(Calibration.run_id.in_([r.id for r in runs]),
                                                                      Calibration.slot == 0))} if runs else {}
    units, prompt = [], None
    ended = batch.finished_at is not None
    for serial in batch.serials:
        r = by_serial.get(serial)
        if r is None:
            # a unit of an ended batch without a run was never run (its summary says why), not pending
            units.append({"serial": serial, "run_id": None, "status": "not run" if ended else "pending", "verdict": None,
                          "reason": (batch.summary or {}).get(serial, "").removeprefix(NOT_RUN) or None if ended else None})
            continue
        j = run_json(r)
        c = cals.get(r.id)
        ident = slot_result(j["result"])  # what the mounted unit reported
        units.append({"serial": serial, "run_id": r.id, "status": j["status"], "reason": j["reason"],
                      "identified_serial": ident.get("identified_serial"), "identification": ident.get("identification"),
                      "verdict": c.verdict if c else None, "calibration_id": c.id if c else None,
                      "calibration_status": c.status if c else None, "prompts": j["prompts"],
                      "table_seconds": j["table_seconds"], "target": target_said(c.data) if c else None})
        if j["prompts"]:
            prompt = {"run_id": r.id, **j["prompts"][0]}
    return {"id": batch.id, "station": station.name if station else None, "status": batch.status,
            "operator": batch.operator, "serials": batch.serials, "created_at": batch.created_at,
            "finished_at": batch.finished_at, "summary": batch.summary or {}, "units": units, "prompt": prompt,
            "tally": batch_tally(units, ended=batch.status not in ("running", BATCH_ABORTING))}


#: A batch's units counted by outcome (`batch_tally`): its verdicts, then those without one.
TALLY = ("pass", "marginal", "fail", "uncalibrated", "pending")


def batch_tally(units: list[dict[str, Any]], ended: bool) -> dict[str, int]:
    """How many of a batch's units PASS, are MARGINAL or FAIL, ended without a calibration (a failed,
    aborted or refused run, or never run in a batch that has ended) and are still to be done: what a
    line supervisor reads first."""
    tally = dict.fromkeys(TALLY, 0)
    for u in units:
        if u.get("verdict"):
            tally[u["verdict"].lower()] += 1
        else:
            tally["uncalibrated" if ended or u["status"] in FINAL else "pending"] += 1
    return tally


def target_said(calibration: dict[str, Any]) -> str | None:
    """An adaptive calibration's outcome against its targets in a few words (None when not adaptive):
    "met", or "not met: a 236-s budget would reach them" (the budget the unit needed, as predicted)."""
    pr = (calibration.get("quality") or {}).get("precision")
    if not pr:
        return None
    if pr.get("met"):
        return "met"
    need = needed_budget_s(pr)
    if need is None:
        return f"not met: needs more than {LOOKAHEAD_S / 60:.0f} min more table time"
    return f"not met: a {need:.0f}-s budget would reach them"


# ------------------------------------------------------------------------------------ requests

def _busy(row: Station, batch_id: int | None = None) -> str | None:
    """Why no run can start on the station now (None when one can)."""
    if row.run_id is not None:
        return f"station {row.name} is busy with run {row.run_id}"
    if row.state == "fault":
        return f"station {row.name} is in fault ({row.reason}); POST /stations/{row.name}/reset first"
    if row.batch_id is not None and row.batch_id != batch_id:
        return f"station {row.name} is busy with batch {row.batch_id}"
    return None


def checkpoints_passed(s: Session, run_id: int) -> list[str]:
    """The labels of the checkpoints a run passed, in order (from its event log)."""
    rows = s.scalars(select(RunEvent.data).where(RunEvent.run_id == run_id, RunEvent.kind == "step")
                     .order_by(RunEvent.id))
    return [str(d["step"].get("label")) for d in rows
            if isinstance(d, dict) and isinstance(d.get("step"), dict) and d["step"].get("kind") == "checkpoint"]


def _resumable(s: Session, resume: int, station_name: str, procedure: str | None,
               parameters: dict[str, Any] | None) -> tuple[Run, list[str]]:
    """The interrupted run a new run resumes, checked: same station, an end that was not completion,
    a checkpoint passed; the request's procedure and parameters, if given, must be its own."""
    old = s.get(Run, resume)
    if old is None:
        raise invalid("body.resume", f"no run {resume}")
    if old.status not in (RunState.failed.value, RunState.aborted.value):
        raise Conflict(f"run {resume} is {old.status}; only a failed or aborted run can be resumed")
    if (old.station_snapshot or {}).get("name") != station_name:
        raise invalid("body.resume", f"run {resume} ran on station {(old.station_snapshot or {}).get('name')}, "
                      f"not {station_name}: a run resumes on its own table")
    if procedure is not None and procedure != old.procedure:
        raise invalid("body.procedure", f"run {resume} was {old.procedure}; a resumed run is the same procedure")
    if parameters and parameters != old.parameters:
        raise invalid("body.parameters", f"run {resume}'s parameters are taken over; leave them out")
    # one continuation of a run: two would each complete it (their calibrations superseding each other);
    # a continuation that failed or was aborted leaves the run to resume again (or that one to resume)
    for later in s.scalars(select(Run).where(Run.station_id == old.station_id, Run.id > old.id)):
        if ((later.meta or {}).get("resume") or {}).get("run_id") == old.id and \
                later.status not in (RunState.failed.value, RunState.aborted.value):
            raise Conflict(f"run {resume} is already resumed by run {later.id} ({later.status})")
    passed = checkpoints_passed(s, resume)
    if not passed:
        raise Conflict(f"run {resume} passed no checkpoint: nothing to resume from; start a new run")
    return old, passed


def in_other_case(s: Session, serial: str) -> list[str]:
    """The devices' serial numbers that differ from ``serial`` in letter case only (one unit, typed otherwise)."""
    return [d for d in s.scalars(select(Device.serial).where(func.lower(Device.serial) == serial.lower()))
            if d != serial]


def check_typed(s: Session, field: str, serial: str) -> str:
    """A typed serial number by the service's rule, and not a stored unit's in another letter case (typed
    "sim-a1" for unit SIM-A1, its calibration made a second device)."""
    try:
        serial = check_serial(serial)
    except ValueError as e:
        raise invalid(field, str(e)) from None
    alike = in_other_case(s, serial)
    if alike:
        raise invalid(field, f"{serial!r} differs from the stored unit {', '.join(map(repr, alike))} in letter case only: "
                             "type it as stored (one unit, one serial number)")
    return serial


def reports_itself(s: Session, serial: str) -> bool:
    """Whether a unit certified under ``serial`` reported that serial itself (it identifies itself)."""
    rows = s.scalars(select(Calibration.identity).join(Device, Device.id == Calibration.device_id)
                     .where(Device.serial == serial))
    return any(isinstance(i, dict) and i.get("identified_serial") == serial for i in rows)


def create_run(s: Session, station_name: str, procedure: str | None, parameters: dict[str, Any] | None,
               serials: dict[str, str] | None, operator: str, software_version: str,
               batch_id: int | None = None, resume: int | None = None, serial_policy: str | None = None) -> Run:
    """Validate a run, write its row (``queued``, with its provenance) and claim the station for it,
    in one transaction (committed). NotFound, Invalid (naming the field) or Conflict (busy, fault).

    ``serial_policy``: what the run does when a unit reports another serial number than the one
    typed (service/identity.py); None: the station's. Kept in the run's ``meta``.

    ``resume``: a failed or aborted run of this station to continue from the last checkpoint it
    passed: its procedure, parameters and units are taken over, and its worker replays its samples
    up to there (``procedure`` None: the resumed run's, else "calibrate")."""
    from procedures.calibrate import PROCEDURES

    resumed: dict[str, Any] | None = None
    if resume is not None:
        old, passed = _resumable(s, resume, station_name, procedure, parameters)
        procedure, parameters = old.procedure, dict(old.parameters or {})
        serials = {**{str(k): str(v) for k, v in (old.serials or {}).items() if v}, **(serials or {})}
        # the units to find mounted again: as each reported itself (trust-typed or an operator's answer may
        # have certified it under another serial than the one it reports), else as typed
        meta = old.meta or {}
        reported = {slot: (slot_result(meta.get("result"), int(slot)) or (meta.get(IDENTITIES_KEY) or {}).get(slot) or {})
                    .get("identified_serial") or (old.serials or {}).get(slot)
                    for slot in {*(old.serials or {}), *(meta.get(IDENTITIES_KEY) or {})}}
        resumed = {"run_id": old.id, "checkpoints": len(passed), "label": passed[-1],
                   "serials": {k: str(v) for k, v in sorted(reported.items()) if v}}
        serial_policy = serial_policy or meta.get("serial_policy")  # the run's own policy goes on with it
        batch_id = batch_id if batch_id is not None else old.batch_id  # a batch's unit stays the batch's
    procedure = procedure or "calibrate"
    proc = PROCEDURES.get(procedure)
    if proc is None:
        raise invalid("body.procedure", f"unknown procedure {procedure!r}; known: {', '.join(sorted(PROCEDURES))}")
    if procedure == BATCH and batch_id is None and resume is None:  # its unit's serial is the batch's to type
        raise invalid("body.procedure", f"{BATCH} is one unit of a batch: start it with POST /batches (or calibrate one "
                                        'unit with procedure calibrate and "serials")')
    try:
        params = proc.validate(parameters)
    except ValidationError as e:
        raise Invalid(field_errors(e.errors(), ("body", "parameters"))) from None
    row = s.scalar(select(Station).where(Station.name == station_name))
    if row is None:
        raise NotFound(f"no station {station_name!r}")
    # a procedure's per-slot parameters (evaluate's calibrations) name slots of this station (one that did
    # not ran the whole plan and ended "completed" with nothing evaluated)
    for slot in getattr(params, "calibrations", None) or {}:
        if not 0 <= int(slot) < len(row.compasses):
            raise invalid(f"body.parameters.calibrations.{slot}",
                          f"not a slot of station {row.name} (slots 0 to {len(row.compasses) - 1})")
    given: dict[str, str] = {}
    for key, serial in (serials or {}).items():
        if not (key.isascii() and key.isdigit() and int(key) < len(row.compasses)):
            raise invalid(f"body.serials.{key}", f"not a slot of station {row.name} (slots 0 to {len(row.compasses) - 1})")
        if str(int(key)) in given:  # "0" and "00": one slot typed twice (the second silently won)
            raise invalid(f"body.serials.{key}", f"slot {int(key)} is given twice; give each slot once")
        # the API checked the rule already; a batch's unit and a resumed run's serials come this way too
        given[str(int(key))] = check_typed(s, f"body.serials.{key}", str(serial))
    for slot, cal in (getattr(params, "calibrations", None) or {}).items():
        owner, typed = str(cal.get("serial") or ""), given.get(str(int(slot)))
        if owner and typed and owner != typed:  # another unit's calibration evaluated on this one (15 deg, no word)
            raise invalid(f"body.parameters.calibrations.{slot}", f"a calibration of unit {owner}, but slot {slot} is "
                                                                  f"typed {typed}: give {typed}'s calibration")
    policy = serial_policy or row.serial_policy or DEFAULT_POLICY
    if policy not in POLICIES:
        raise invalid("body.serial_policy", f"expected one of {', '.join(POLICIES)}")
    why = _busy(row, batch_id)
    if why:
        raise Conflict(why)
    snapshot = {"name": row.name, "modbus": row.modbus, "compasses": list(row.compasses), "time_scale": float(row.time_scale)}
    run = Run(station_id=row.id, batch_id=batch_id, procedure=proc.name, procedure_version=proc.version,
              parameters=json_safe(params.model_dump()), status=RunState.queued.value, operator=operator,
              station_snapshot=snapshot, serials=given, software_version=software_version, prompts={},
              meta={"station": row.name, "sample_rate_hz": str(SAMPLE_RATE_HZ), "time_scale": f"{row.time_scale:g}",
                    "parameters": params.model_dump_json(), "serial_policy": policy,
                    **({"resume": resumed, "resumed_from": str(resumed["run_id"])} if resumed else {})})
    s.add(run)
    s.flush()
    # the claim: one conditional UPDATE, so two API processes racing for one table cannot both win
    claimed = s.execute(update(Station).where(Station.id == row.id, Station.run_id.is_(None), Station.state != "fault",
                                              (Station.batch_id.is_(None)) | (Station.batch_id == batch_id))
                        .values(run_id=run.id, state="running")).rowcount
    if claimed != 1:
        s.rollback()
        s.refresh(row)
        raise Conflict(_busy(row, batch_id) or f"station {station_name} is busy")
    if resumed:  # the run taken over names its continuations (the API, its page and certificate say both ways)
        old = s.get(Run, resumed["run_id"])
        old.meta = {**(old.meta or {}), "resumed_by": [*((old.meta or {}).get("resumed_by") or []), run.id]}
    publish(s, run.id, "state", {"state": RunState.queued.value, "reason": None})
    s.commit()
    return run


def request_state(s: Session, run_id: int, target: str, reason: str | None) -> tuple[str, bool]:
    """Check ``PUT /runs/{id}/state`` against the state machine and queue the command for the run's
    worker (committed). Returns what it does and whether the caller must also cancel a queued job."""
    row = s.get(Run, run_id)
    if row is None:
        raise NotFound(f"no run {run_id}")
    if (row.status, target) == ("running", "running") and row.pause_requested:
        row.pause_requested = False
        s.add(RunCommand(run_id=run_id, kind="resume", data={}, created_at=utcnow()))
        s.commit()
        return "pause request withdrawn", False
    try:
        what = check_transition(row.status, target)
    except ValueError as e:
        raise Conflict(str(e)) from None
    kind = {"paused": "pause", "running": "resume", "aborted": "abort"}[target]
    if kind == "pause":
        row.pause_requested = True
    s.add(RunCommand(run_id=run_id, kind=kind, data={"reason": reason or "aborted by the operator"} if kind == "abort" else {},
                     created_at=utcnow()))
    s.commit()
    return what, kind == "abort" and row.status == RunState.queued.value


def finish_unstarted(s: Session, run_id: int, status: str, reason: str) -> bool:
    """End a run no worker has taken (its job was cancelled, or its worker is lost): final status,
    station freed. False when a worker took it meanwhile (it then ends the run itself)."""
    done = s.execute(update(Run).where(Run.id == run_id, Run.status == RunState.queued.value)
                     .values(status=status, reason=reason, finished_at=utcnow())).rowcount
    if done != 1:
        s.rollback()
        return False
    s.execute(update(Station).where(Station.run_id == run_id).values(run_id=None, state="idle"))
    publish(s, run_id, "state", {"state": status, "reason": reason})
    s.commit()
    return True


def queue_answer(s: Session, run_id: int, prompt_id: str, answer: str) -> int:
    """Queue the operator's answer to a waiting prompt (committed; its command's id); Conflict when the run
    has ended, NotFound when no such prompt is waiting, Invalid when a serial prompt's answer is not one of
    :data:`~service.identity.CHOICES` or a mount prompt's not "done"."""
    row = s.get(Run, run_id)
    if row is None:
        raise NotFound(f"no run {run_id}")
    if row.status not in ACTIVE:  # (it said "no prompt waiting", as if the id were wrong)
        raise Conflict(f"run {run_id} has ended ({row.status}{': ' + row.reason if row.reason else ''}); "
                       "it waits for no answer")
    waiting = dict(row.prompts or {})
    if prompt_id not in waiting:
        raise NotFound(f"run {run_id} has no prompt {prompt_id!r} waiting"
                       + (f" (waiting: {', '.join(waiting)})" if waiting else ""))
    if is_serial_prompt(prompt_id) and normalise(answer) not in CHOICES:
        # which serial a unit is certified under is not left to a guess at a stray answer
        raise invalid("body.answer", f"answer {', '.join(repr(c) for c in CHOICES)} to a serial prompt")
    if prompt_id == MOUNT_PROMPT and normalise(answer) != "done":
        # any answer went on with the unit measured and certified ("skip" too): there is one answer
        raise invalid("body.answer", "answer 'done' to a mount prompt once the unit is on the fixture (to stop, "
                                     "abort the batch: PUT /batches/{id}/state)")
    command = RunCommand(run_id=run_id, kind="answer", data={"id": prompt_id, "answer": answer}, created_at=utcnow())
    s.add(command)
    s.commit()
    return command.id


def reap_lost_workers(sessions: sessionmaker, now: datetime | None = None, judge: bool = True) -> list[int]:
    """Runs whose station's worker stopped beating (killed, its PC off): failed with reason "worker
    lost", the station in fault until reset; and such a station's batch, ended (`end_lost_batches`).
    Returns the runs so ended. ``judge=False`` only checks
    that the database answers (the caller was cut off from it: the workers may have been too)."""
    now = now or utcnow()
    ended = []
    with sessions() as s:
        if not judge:
            s.execute(select(1))
            return ended
        rows = s.execute(select(Run, Station).join(Station, Station.run_id == Run.id)
                         .where(Run.status.in_((RunState.running.value, RunState.paused.value)))).all()
        for run, station in rows:
            if station.heartbeat_at is None or worker_alive(station, now):
                continue  # (never beaten: the station was made after its worker's last beat)
            why = f"worker lost: station {station.name}'s worker stopped beating"
            n = s.execute(update(Run).where(Run.id == run.id, Run.status.in_(ACTIVE))
                          .values(status=RunState.failed.value, reason=why, finished_at=now)).rowcount
            if n:
                s.refresh(run)
                lost_run_result(run)
                s.execute(update(Station).where(Station.id == station.id, Station.run_id == run.id)
                          .values(run_id=None, state="fault",
                                  reason=f"worker lost during run {run.id}: the table may have stopped anywhere; start "
                                         f"its worker (compasscal worker --station {station.name}), then "
                                         f"POST /stations/{station.name}/reset"))
                publish(s, run.id, "state", {"state": RunState.failed.value, "reason": why})
                ended.append(run.id)
        # a batch between units (or whose unit's run just ended above) has no run to be caught by
        for station in s.scalars(select(Station).where(Station.batch_id.is_not(None))):
            if station.heartbeat_at is not None and not worker_alive(station, now):
                end_lost_batches(s, [station.id], f"station {station.name}'s worker stopped beating", now=now)
        s.commit()
    return ended


#: A batch's status once the operator aborted it, until its worker has stopped it ("aborted").
BATCH_ABORTING = "aborting"
#: How a batch summary's line of a unit that was never run begins (the reason follows).
NOT_RUN = "not run: "
#: The verdicts a batch summary's line of a calibrated unit begins with.
VERDICTS = ("PASS", "MARGINAL", "FAIL")


def summary_verdict(line: str) -> str | None:
    """The verdict a batch summary's line begins with ("PASS (resumed as run 19)": PASS), or None."""
    first = str(line).split(" ", 1)[0]
    return first if first in VERDICTS else None


def settle_resumed_unit(batch: Batch, serial: str, line: str) -> None:
    """An ended batch's unit, resumed on its own (its worker lost mid-batch), came out as ``line``: the
    batch's summary says so (it kept "failed: worker lost"), and a batch that failed for that unit alone,
    all its units now run and some calibrated, is completed, as a batch that went through is (it said
    "failed" beside "1 pass")."""
    batch.summary = {**(batch.summary or {}), serial: line}
    lines = [str(v) for v in batch.summary.values()]
    if batch.status == "failed" and set(batch.serials or []) <= set(batch.summary) \
            and not any(v.startswith(NOT_RUN) for v in lines) and any(map(summary_verdict, lines)):
        batch.status = "completed"


def end_lost_batches(s: Session, station_ids: list[int] | None, why: str, queued_too: bool = False,
                     now: datetime | None = None) -> list[int]:
    """End the batches of these stations (None: every station's) whose job went with a worker: those it
    had started (a unit's run made), running or being aborted; with ``queued_too`` (the jobs went with an
    in-memory queue) those not yet started as well, whose jobs otherwise wait in the queue for a worker.
    Each ends ``failed`` (``aborted`` when the operator had asked for it) with every unit it had not
    judged in its summary: the unit whose run was cut off by that run's state and reason, the rest "not
    run"; its station is freed for the next run. Call after the lost runs are ended (their reasons are
    read). Returns the batches so ended."""
    q = select(Batch).where(Batch.status.in_(("queued", "running", BATCH_ABORTING)))
    if station_ids is not None:
        q = q.where(Batch.station_id.in_(station_ids))
    ended = []
    for batch in s.scalars(q):
        runs = {(r.serials or {}).get("0"): r for r in s.scalars(select(Run).where(Run.batch_id == batch.id).order_by(Run.id))}
        if not runs and not queued_too:
            continue  # its job waits in the queue (a batch is "running" from its request on)
        summary = dict(batch.summary or {})
        for serial in batch.serials:
            run = runs.get(serial)
            if serial not in summary:
                summary[serial] = (f"{run.status}: {run.reason}" if run is not None and run.status in FINAL
                                   else NOT_RUN + why)
        batch.summary = summary
        batch.status = "aborted" if batch.status == BATCH_ABORTING else "failed"
        batch.finished_at = now or utcnow()
        s.execute(update(Station).where(Station.batch_id == batch.id).values(batch_id=None))
        ended.append(batch.id)
    return ended


def other_workers(sessions: sessionmaker, stations: list[str] | None, me: str, wait_s: float = LOST_AFTER_S + 1.0,
                  every: float = 0.5) -> dict[str, str]:
    """Stations (None: every station) served by a live worker other than ``me``, by name: a second
    worker of a station would compete with the first for its table. A worker that has just died
    still looks alive for :data:`LOST_AFTER_S`: wait up to ``wait_s`` for its heartbeat to go stale."""
    import time

    deadline = time.monotonic() + wait_s
    while True:
        with sessions() as s:
            q = select(Station)
            if stations is not None:
                q = q.where(Station.name.in_(stations))
            busy = {r.name: r.worker for r in s.scalars(q) if r.worker and r.worker != me and worker_alive(r)}
        if not busy or time.monotonic() > deadline:
            return busy
        time.sleep(every)


@dataclass
class Waited:
    """What a confirmation wait saw."""

    ok: bool
    value: Any = None


async def wait_for(check: Any, timeout: float, every: float = 0.1) -> Waited:
    """Poll ``check()`` (a sync function returning a value or None) until it returns something."""
    deadline = asyncio.get_running_loop().time() + timeout
    while True:
        value = await asyncio.to_thread(check)
        if value is not None:
            return Waited(True, value)
        if asyncio.get_running_loop().time() > deadline:
            return Waited(False)
        await asyncio.sleep(every)


__all__ = ["DomainError", "NotFound", "Conflict", "Invalid", "Unavailable", "field_errors", "invalid", "publish",
           "events_after", "notify", "analysis_topic", "Notifier", "station_json", "run_json", "batch_json", "create_run", "request_state",
           "finish_unstarted", "queue_answer", "reap_lost_workers", "worker_alive", "other_workers", "wait_for"]
