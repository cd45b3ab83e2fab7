"""The engine: runs a procedure's steps against a station's drivers (real or simulated alike).

It records every sample with the encoder angles actually reached (read back, not commanded), its
table time and the step's label, streams them to a sink as they come, emits progress events, and
handles pause and resume at checkpoints, abort, faults and per-step timeouts. Whatever happens, the
axes it moved are stopped and every sample already received stays in the sink.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from pydantic import BaseModel

from drivers import DriverError
from drivers.protocol import fault_name
from drivers.compass import CompassError, CompassSample, CompassTimeout, Fixture, FixtureError
from drivers.turntable import MoveTimeout, Turntable
from physics.recording import Recording, concat, format_recording
from procedures.calibrate import PROCEDURES
from procedures.steps import Acquire, Checkpoint, Move, Outcome, Procedure, Prompt, Settle, Step


class RunState(str, Enum):
    """Where a run is. ``completed``, ``failed`` and ``aborted`` are final."""

    queued = "queued"
    running = "running"
    paused = "paused"
    completed = "completed"
    failed = "failed"
    aborted = "aborted"


@dataclass
class Station:
    """The hardware one run drives. ``time_scale`` > 1 for a simulator running faster than real time:
    the engine then reports table time (simulated seconds) in the recording and its events."""

    table: Turntable
    fixture: Fixture
    time_scale: float = 1.0
    speed_dps: float = 30.0
    accel_dps2: float = 60.0
    sample_rate_hz: int = 20
    name: str = "station"


@dataclass
class Event:
    """A progress report: ``kind`` is state, step, progress, samples, prompt or result."""

    kind: str
    data: dict[str, Any]


class Sink(Protocol):
    """Where samples go as they are acquired (a recording file now, the database later)."""

    def add(self, slot: int, rec: Recording) -> None:
        """Keep these samples of one slot (called once per slot per acquisition)."""


@dataclass
class RunResult:
    """How a run ended."""

    state: RunState
    reason: str | None
    outcome: Outcome | None
    samples: int
    table_seconds: float  # until the table's last step ended (the fit afterwards is not table time)


class Aborted(Exception):
    """The operator aborted the run."""


@dataclass
class Engine:
    """Runs one procedure once. Control it from other tasks with :meth:`pause`, :meth:`resume`,
    :meth:`abort` and :meth:`answer` while :meth:`run` is awaited."""

    station: Station
    procedure: Procedure
    params: BaseModel
    sink: Sink
    on_event: Callable[[Event], None] = lambda e: None
    move_timeout_s: float | None = None  # table seconds; None: the driver's own deadline
    acquire_margin_s: float = 1.0  # wall seconds beyond the nominal acquisition time
    retries: int = 1  # of a step that timed out (never of a fault)
    state: RunState = RunState.queued
    reason: str | None = None
    serials: dict[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._resume = asyncio.Event()
        self._resume.set()
        self._abort: str | None = None
        self._answers: dict[str, asyncio.Future[str]] = {}
        self._t0 = time.monotonic()
        self._samples = 0
        self._streaming = False
        self._table_used = 0.0  # table seconds until the last move, settle or acquisition ended

    # ---------------------------------------------------------------------------------- control
    def pause(self) -> None:
        """Pause at the next checkpoint (the table holds still there)."""
        self._resume.clear()

    def resume(self) -> None:
        """Continue a paused run."""
        self._resume.set()

    def abort(self, reason: str = "aborted by the operator") -> None:
        """Stop as soon as possible: axes stopped, samples kept, run marked aborted."""
        self._abort = reason
        self._resume.set()
        for fut in self._answers.values():
            if not fut.done():
                fut.cancel()

    def answer(self, prompt_id: str, text: str) -> bool:
        """Answer an operator prompt; False when no such prompt is waiting."""
        fut = self._answers.get(prompt_id)
        if fut is None or fut.done():
            return False
        fut.set_result(text)
        return True

    def table_time(self) -> float:
        """Table seconds since the run started (simulated seconds under a time scale)."""
        return (time.monotonic() - self._t0) * self.station.time_scale

    # ------------------------------------------------------------------------------------- run
    async def run(self) -> RunResult:
        """Run the procedure to its end, an abort or a fault."""
        plan = self.procedure.plan(self.params)
        total = max(1, sum(isinstance(s, (Move, Acquire, Settle)) for s in plan))
        done = 0
        self._t0 = time.monotonic()
        self._set_state(RunState.running)
        outcome: Outcome | None = None
        gen = self.procedure.run(self.params)
        reply: Any = None
        try:
            await self._prepare()
            while True:
                self._check_abort()
                try:
                    step = gen.send(reply)
                except StopIteration as stop:
                    outcome = stop.value
                    break
                self.on_event(Event("step", {"step": _describe(step), "t": self.table_time()}))
                reply = await self._do(step)
                if isinstance(step, (Move, Acquire, Settle)):
                    done += 1
                    elapsed = self._table_used = self.table_time()
                    left = elapsed / done * (total - done)
                    self.on_event(Event("progress", {"percent": round(100.0 * done / total, 1), "table_s": elapsed,
                                                     "left_s": left, "samples": self._samples}))
            self._set_state(RunState.completed)
            self.on_event(Event("result", {"units": sorted(outcome.results) if outcome else []}))
        except Aborted:
            await self._stop_axes()
            self._set_state(RunState.aborted, self._abort)
        except (DriverError, asyncio.TimeoutError) as e:
            await self._stop_axes()
            self._set_state(RunState.failed, _reason(e))
        except BaseException as e:  # a bug or a cancellation: still stop the table, keep the data
            await self._stop_axes()
            self._set_state(RunState.failed, _reason(e))
            if isinstance(e, (asyncio.CancelledError, KeyboardInterrupt)):
                raise
        finally:
            gen.close()
        return RunResult(self.state, self.reason, outcome, self._samples, self._table_used)

    async def _prepare(self) -> None:
        """Enable and home the axes if needed. (The compasses are set streaming at the first
        acquisition, and again after a prompt: the operator may have mounted another unit.)

        An axis already in fault is not reset behind the operator's back: the run fails saying so."""
        table = self.station.table
        status = await table.status_all()
        faulted = [f"axis {name}: fault {fault_name(s.fault_code)}" for name, s in status.items() if s.fault]
        if faulted:
            raise DriverError("axis fault before the run (reset it first): " + ", ".join(faulted))
        if not all(s.enabled for s in status.values()):
            await table.enable_all()
        if not all(s.homed for s in status.values()):
            await table.home_all(vel_dps=self.station.speed_dps, acc_dps2=self.station.accel_dps2)

    async def _do(self, step: Step) -> Any:
        if isinstance(step, Move):
            return await self._retry(lambda: self.station.table.move_to(
                step.psi, step.theta, step.phi, speed_dps=self.station.speed_dps, accel_dps2=self.station.accel_dps2), MoveTimeout)
        if isinstance(step, Settle):
            await asyncio.sleep(step.seconds / self.station.time_scale)
            return None
        if isinstance(step, Acquire):
            if not self._streaming:
                await self.station.fixture.set_rate_all(self.station.sample_rate_hz)
                self._streaming = True
            return await self._retry(lambda: self._acquire(step), CompassTimeout)
        if isinstance(step, Checkpoint):
            if not self._resume.is_set():
                self._set_state(RunState.paused)
                await self._resume.wait()
                self._check_abort()
                self._set_state(RunState.running)
            return None
        if isinstance(step, Prompt):
            fut: asyncio.Future[str] = asyncio.get_running_loop().create_future()
            self._answers[step.id] = fut
            self._streaming = False
            self.on_event(Event("prompt", {"id": step.id, "text": step.text}))
            try:
                return await fut
            except asyncio.CancelledError:
                self._check_abort()
                raise
        raise TypeError(f"unknown step {step!r}")

    async def _retry(self, action: Callable[[], Any], timeout_type: type[Exception]) -> Any:
        for attempt in range(self.retries + 1):
            self._check_abort()
            try:
                return await action()
            except timeout_type as e:
                if attempt == self.retries:
                    raise
                self.on_event(Event("step", {"retry": attempt + 1, "reason": _reason(e)}))
        raise AssertionError("unreachable")

    async def _acquire(self, step: Acquire) -> dict[int, Recording]:
        before = await self.station.table.positions()
        timeout = step.samples / self.station.sample_rate_hz / self.station.time_scale + self.acquire_margin_s
        try:
            got = await self.station.fixture.read_all(step.samples, timeout=timeout)
        except FixtureError as e:
            # keep what did arrive (the other slots' reads and the failed ones' partial samples)
            partial = dict(e.results)
            partial.update({slot: err.samples for slot, err in e.errors.items() if isinstance(err, CompassError)})
            self._keep(step, partial, before)
            timeouts = all(isinstance(err, CompassTimeout) for err in e.errors.values())
            raise (CompassTimeout(str(e)) if timeouts else e) from None
        after = await self.station.table.positions()
        moved = float(np.max(np.abs(np.subtract(after, before))))
        if moved > 0.01:
            self._keep(step, got, before)
            raise DriverError(f"the table moved {moved:.3f} deg while {step.step} was acquiring")
        return self._keep(step, got, before)

    def _keep(self, step: Acquire, got: dict[Any, list[CompassSample]], angles: tuple[float, float, float]) -> dict[int, Recording]:
        """Send samples to the sink (before anything else can go wrong) and return them as recordings."""
        out: dict[int, Recording] = {}
        for slot, samples in got.items():
            if not samples:
                continue
            rec = self._recording(int(slot), samples, step.step, angles)
            self.sink.add(int(slot), rec)
            out[int(slot)] = rec
            self._samples += len(samples)
        self.on_event(Event("samples", {"step": step.step, "count": self._samples}))
        return out

    def _recording(self, slot: int, samples: list[CompassSample], step: str, angles: tuple[float, float, float]) -> Recording:
        n = len(samples)
        t = [(s.t_host - self._t0) * self.station.time_scale for s in samples]
        return Recording.from_arrays(
            t=t, step=[step] * n, psi_t=[angles[0]] * n, theta_t=[angles[1]] * n, phi_t=[angles[2]] * n,
            mag=[s.mag for s in samples], acc=[s.acc for s in samples], temp_c=[s.temp_c for s in samples],
            meta={"serial": self.serials.get(slot, ""), "slot": str(slot)},
        )

    def _check_abort(self) -> None:
        if self._abort is not None:
            raise Aborted(self._abort)

    async def _stop_axes(self) -> None:
        try:
            await asyncio.wait_for(self.station.table.stop_all(), timeout=2.0)
        except Exception as e:  # noqa: BLE001 - report it, but the run's own reason comes first
            self.on_event(Event("step", {"warning": f"stopping the axes failed: {_reason(e)}"}))

    def _set_state(self, state: RunState, reason: str | None = None) -> None:
        self.state, self.reason = state, reason
        self.on_event(Event("state", {"state": state.value, "reason": reason, "t": self.table_time()}))


def _describe(step: Step) -> dict[str, Any]:
    d = {"kind": type(step).__name__.lower()}
    d.update({k: v for k, v in step.__dict__.items()})
    return d


def _reason(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


class RecordingSink:
    """Keeps each slot's samples and rewrites its recording file (RECORDING.md) after every
    acquisition, so a fault or a kill loses at most the acquisition in progress."""

    def __init__(self, directory: Path | None, names: dict[int, str], meta: dict[str, str] | None = None) -> None:
        self.directory = directory
        self.names = names
        self.meta = meta or {}
        self.parts: dict[int, list[Recording]] = {}

    def add(self, slot: int, rec: Recording) -> None:
        """Keep these samples and flush the slot's file."""
        self.parts.setdefault(slot, []).append(rec)
        if self.directory is not None:
            self.path(slot).write_text(format_recording(self.recording(slot)))

    def path(self, slot: int) -> Path:
        """The slot's recording file."""
        assert self.directory is not None
        return self.directory / f"{self.names.get(slot, f'slot{slot}')}.csv"

    def recording(self, slot: int) -> Recording:
        """Everything kept for one slot, with the run's metadata."""
        rec = concat(self.parts[slot])
        rec.meta.update(self.meta)
        return rec


@asynccontextmanager
async def open_station(modbus: str, compasses: list[str], *, time_scale: float = 1.0,
                       sample_rate_hz: int = 20, name: str = "station") -> AsyncIterator[Station]:
    """Connect a station's table (Modbus URL) and fixture (one serial URL per slot); close both after."""
    table = Turntable(modbus)
    fixture = Fixture({slot: url for slot, url in enumerate(compasses)})
    await table.connect()
    try:
        await fixture.open()
        try:
            yield Station(table, fixture, time_scale=time_scale, sample_rate_hz=sample_rate_hz, name=name)
        finally:
            await fixture.close()
    finally:
        await table.close()


async def run_procedure(station: Station, name: str, parameters: dict[str, Any] | None = None, *,
                        out_dir: Path | None = None, on_event: Callable[[Event], None] = lambda e: None,
                        engine_hook: Callable[[Engine], None] = lambda e: None) -> tuple[RunResult, dict[int, str], RecordingSink]:
    """Validate the parameters, ask every compass its serial number, and run procedure ``name`` with
    a recording sink (files in ``out_dir`` when given). Returns the result, the serials by slot and the sink."""
    proc = PROCEDURES[name]
    params = proc.validate(parameters)
    ids = await station.fixture.identify_all()
    serials = {int(slot): ident[1] for slot, ident in ids.items()}  # type: ignore[call-overload]
    meta = {"procedure": proc.name, "procedure_version": proc.version, "station": station.name,
            "parameters": params.model_dump_json(), "sample_rate_hz": str(station.sample_rate_hz),
            "time_scale": f"{station.time_scale:g}"}
    sink = RecordingSink(out_dir, serials, meta)
    engine = Engine(station, proc, params, sink, on_event=on_event, serials=serials)
    engine_hook(engine)
    return await engine.run(), serials, sink
