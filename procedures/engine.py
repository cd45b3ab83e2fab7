"""The engine: runs a procedure's steps against a station's drivers (real or simulated alike).

It records every sample with the encoder angles actually reached (read back, not commanded), its
table time and the step's label, streams them to a sink as they come, emits progress events, and
handles pause and resume at checkpoints, abort, faults and per-step timeouts. Whatever happens, the
axes it moved are stopped and every sample already received stays in the sink.

Sample times are the compass's own sample clock mapped onto the host's (:func:`sample_clock`), so
arrival jitter does not reach the recording. During a :class:`~procedures.steps.Scan` the turning
axis's encoder is polled throughout, and each sample gets the encoder angle at its time
(:func:`encoder_track`).

It knows the hardware only through the roles of :mod:`drivers` (:class:`~drivers.Table`,
:class:`~drivers.Fixture`, paired in a :class:`~drivers.Station`): which drivers fill them is
:func:`drivers.station.open_station`'s business, or a test's. What it reports are the events of
:mod:`procedures.events`.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from pydantic import BaseModel

from drivers import DriverError, Sample, SampleStream, Station
from drivers.compass import CompassError, CompassNak, CompassTimeout, FixtureError
from drivers.protocol import fault_name
from drivers.turntable import MoveTimeout
from physics.fit import screen_rows
from physics.recording import Recording, concat, format_recording
from physics.table import Motion
from procedures.calibrate import PROCEDURES
from procedures.events import (COMPUTING_EVERY_S, Computing, Event, Progress, PromptAsked, Result, Resumed, SamplesStored,
                               StateChanged, StepRetried, StepStarted, StepWarning)
from procedures.states import RunState
from procedures.steps import (TIMED_STEPS, Acquire, Checkpoint, Compute, Identify, Move, Outcome, Park, Procedure, Prompt, Scan, Settle, Step,
                              Where, step_seconds)

#: Table axis turned by each Scan axis.
SCAN_AXIS = {"psi": "z", "theta": "y", "phi": "x"}
#: Table seconds without a sample that separate two replayed scans of one label (a move between them).
SCAN_GAP_S = 0.5
#: The other axes must hold within this (deg) during an acquisition or a scan.
HOLD_TOLERANCE_DEG = 0.01
#: An acquisition reads again at most this many times for lines measured before it began (then keeps
#: what it reads, so a compass whose clock the estimate misjudges cannot stall a pose).
STALE_REREADS = 3
#: A read's samples are placed on the compass's sample clock through them and up to this many of the
#: compass's lines around them (those on time before a late burst anchor the numbering: 51 s of
#: lines at 20 Hz, 2.6 wall seconds at time scale 20, longer than the simulator or a serial stack
#: holds lines back). The clock is computed per unit at every read, before a hold's stale lines are
#: read again, so its cost (about 0.3 ms per unit for 1024 lines) shows in table time under a time scale.
ANCHOR_LINES = 1024


#: Wall seconds an identification of the fixture's compasses may take.
IDENTIFY_TIMEOUT_S = 10.0
#: Threads that run the procedures' own work between steps (one per run a process drives at once;
#: their own pool, so they never queue behind the database writes of the default executor).
PROCEDURE_THREADS = ThreadPoolExecutor(max_workers=8, thread_name_prefix="procedure")


async def identify_units(fixture: Any) -> dict[int, tuple[str, str, str]]:
    """``{slot: (model, serial, firmware)}`` of the fixture's compasses. A compass that refuses the
    ID command (NAK: it cannot identify itself) is left out, so its unit counts as not identified;
    any other failure (a compass that does not answer) raises."""
    try:
        ids = await fixture.identify_all()
    except FixtureError as e:
        if not all(isinstance(x, CompassNak) for x in e.errors.values()):
            raise
        ids = e.results
    return {int(slot): (str(m), str(sn), str(fw)) for slot, (m, sn, fw) in ids.items()}


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
    # the table's working seconds: its moves, settles, acquisitions and scans, summed; not the fits,
    # prompts and pauses between them (under a time scale those would count time-scale times their
    # wall seconds: an adaptive run's refits at scale 20 once added 120 s to a 150-s plan)
    table_seconds: float
    # the plan's nominal table seconds from where the table stood when the run began (an adaptive
    # run's extension and other data-dependent tails not included): what table_seconds compares with
    plan_seconds: float = 0.0


#: A run's table time this many times its plan's nominal or more, at a time scale above 1, is said to be
#: the host's latency (every host millisecond counts time-scale milliseconds of table time).
LATENCY_RATIO = 1.25


def table_time_note(result: RunResult, adaptive: bool, time_scale: float = 1.0) -> tuple[str, bool] | None:
    """What a completed run's table time says of its station's time scale, or None; with whether it is a
    mismatch (the caller adds how to give the right scale). A simulator taken at another time scale than it
    runs at stamps every sample's ``t`` off by that factor (a 50x simulator's run took "4.2 s" of a 113-s
    plan; one at 20 taken at 1 recorded 20-Hz samples 2 ms apart, without a word). Below that, a table time
    stretched at a high time scale is the host's latency, said with its remedy (at time scale 200 a
    108-s plan took 181 s, with no word). An adaptive run's extension only adds time, so only a short
    table time is said of it. A run that never moved the table (every unit refused) says nothing."""
    if result.state is not RunState.completed or result.plan_seconds <= 0 or result.samples == 0:
        return None
    ratio = result.table_seconds / result.plan_seconds
    # a loaded machine stretches a fast simulator's table time (2-4.5 times at time scale 100 on a load of 10),
    # never shrinks it: a mismatch is said of a long table time only well beyond that
    said = f"the table time is {ratio:.3g} times the plan's nominal ({result.table_seconds:.1f} s for {result.plan_seconds:.1f} s)"
    if ratio <= 0.5 or (not adaptive and ratio >= 5.0):
        return (f"{said}: if the station is a simulator running at another time scale than the station's, every "
                "sample's t is off by that factor"), True
    if not adaptive and time_scale > 1.0 and ratio >= LATENCY_RATIO:
        return (f"{said}: at time scale {time_scale:g} every millisecond the host takes between steps counts "
                f"{time_scale:g} ms of table time; the data are sound, but for table times that mean a station's, run "
                "the simulator at time scale 20 or less"), False
    return None


#: Wall seconds between the table's status polls while a run stands paused.
PAUSED_WATCH_S = 1.0


def _faults(status: Mapping[str, Any]) -> list[str]:
    """The axes of a status poll (drivers.turntable.AxisStatus by axis) that are in fault or E-stop, in
    words: "axis z: fault 0x28 encoder error"."""
    return ([f"axis {name}: fault {fault_name(s.fault_code)}" for name, s in status.items() if s.fault]
            + [f"axis {name}: E-stop" for name, s in status.items() if s.estop and not s.fault])


class Aborted(Exception):
    """The operator aborted the run."""


class PromptTimeout(Exception):
    """An operator prompt went unanswered for the engine's ``prompt_timeout_s``."""


class ReplayError(Exception):
    """The interrupted run cannot be replayed up to its last checkpoint (its recording lacks a step)."""


@dataclass
class Replay:
    """What an interrupted run of the same procedure, parameters and units recorded up to the last
    checkpoint it passed. The engine answers the steps until that checkpoint from it (its samples go
    to this run's sink as if just taken, its prompts get the answers given then) instead of the table,
    then carries on live: the run resumes where the other was cut off."""

    run_id: int
    checkpoints: int  # how many checkpoints the interrupted run passed
    samples: dict[str, dict[int, Recording]]  # its samples by step label, then by slot, in order
    answers: dict[str, str] = field(default_factory=dict)  # prompt id -> the answer given
    taken: dict[tuple[str, int], int] = field(default_factory=dict)  # (label, slot) -> samples replayed so far

    def take(self, step: Acquire | Scan) -> dict[int, Recording]:
        """The samples that answered ``step`` then, by slot: an acquisition's next ``samples`` of its
        label (several poses share a label), a scan's next stretch of its label without a gap."""
        out: dict[int, Recording] = {}
        for slot, rec in sorted(self.samples.get(step.step, {}).items()):
            start = self.taken.get((step.step, slot), 0)
            if isinstance(step, Acquire):
                stop = start + step.samples
            else:  # a scan streams without a pause; a move (a gap in table time) separates two scans
                gaps = np.flatnonzero(np.diff(rec.t[start:]) > SCAN_GAP_S)
                stop = start + int(gaps[0]) + 1 if len(gaps) else len(rec)
            if stop > len(rec) or stop <= start:
                raise ReplayError(f"run {self.run_id} has too few samples of step {step.step!r} (slot {slot}) before "
                                  "its last checkpoint: it cannot be resumed")
            self.taken[(step.step, slot)] = stop
            out[slot] = rec.select(np.arange(start, stop))
        if not out:
            raise ReplayError(f"run {self.run_id} has no samples of step {step.step!r} before its last checkpoint: "
                              "it cannot be resumed")
        return out


def _listed(rows: list[int], most: int = 20) -> str:
    """Row numbers for a warning: the first ``most``, then how many more."""
    return ", ".join(map(str, rows[:most])) + (f" and {len(rows) - most} more" if len(rows) > most else "")


def _link_counts(compass: Any) -> tuple[int, int]:
    """A compass's resets and reconnects so far (the serial driver counts them; a test double may not)."""
    stats = getattr(compass, "stats", None)
    return (int(getattr(stats, "resets", 0)), int(getattr(stats, "reconnects", 0))) if stats is not None else (0, 0)


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
    replay: Replay | None = None  # resume an interrupted run from its last checkpoint
    prompt_timeout_s: float | None = None  # wall seconds an operator prompt waits; None: for ever

    def __post_init__(self) -> None:
        self._resume = asyncio.Event()
        self._resume.set()
        self._abort: str | None = None
        self._aborted = asyncio.Event()  # wakes a scan in progress
        self._answers: dict[str, asyncio.Future[str]] = {}
        self._t0 = time.monotonic()
        self._samples = 0
        self._clock: dict[Any, tuple[float, int]] = {}  # per slot: the last kept sample's (host time, seq)
        self._streaming = False
        self._table_used = 0.0  # table seconds of the moves, settles, acquisitions and scans so far
        # when the table's part of the current step ended, where host work follows it (a hold ends
        # with its last line; placing the lines on the sample clock and the check that the table held
        # are host work, which a time scale would multiply): None for the step's end
        self._table_done: float | None = None
        self._replayed_until = 0.0  # table time of the last sample a replay took over
        self._kept: dict[int, list[Recording]] = {}  # per slot: every recording kept, in order (the fit's rows)
        self._flagged: dict[int, set[int]] = {}  # per slot: rows already flagged as bad
        # per slot: the label of the samples kept in the step under way, screened once it ends (_flag_pending)
        self._to_flag: dict[int, str] = {}
        self._held: Any = None  # encoder angles where the table holds since the last move, if known
        self._link_events: dict[Any, tuple[int, int]] = {}  # each compass's (resets, reconnects) last seen

    # ---------------------------------------------------------------------------------- control
    def pause(self) -> None:
        """Pause at the next checkpoint (the table holds still there)."""
        self._resume.clear()

    def resume(self) -> None:
        """Continue a paused run."""
        self._resume.set()

    def abort(self, reason: str = "aborted by the operator") -> None:
        """Stop as soon as possible: axes stopped, samples kept, run marked aborted (for the first abort's
        reason: a second abort while the first is under way overwrote it)."""
        if self._abort is None:
            self._abort = reason
        self._aborted.set()
        self._resume.set()
        for fut in self._answers.values():
            if not fut.done():
                fut.cancel()

    def waiting_for(self, prompt_id: str) -> bool:
        """Whether the run waits for the operator's answer to prompt ``prompt_id``."""
        fut = self._answers.get(prompt_id)
        return fut is not None and not fut.done()

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
        nominal: list[float] = []
        self._t0 = time.monotonic()
        self._link_events = {slot: _link_counts(c) for slot, c in self.station.fixture.compasses.items()}
        self._set_state(RunState.running)
        outcome: Outcome | None = None
        gen = self.procedure.run(self.params)
        computing: asyncio.Future[tuple[bool, Any]] | None = None
        reply: Any = None
        replaying, passed = self.replay is not None and self.replay.checkpoints > 0, 0
        try:
            start = await self._prepare()
            # progress weighs each step by its nominal table time (a scan lasts far longer than a move),
            # from where the table stands: a run after another starts where that one ended (its first
            # move back from psi 315 takes 11 s that a plan laid out from home would not count)
            nominal = [w for s, w in zip(plan, step_seconds(plan, self._motion(), start)) if isinstance(s, TIMED_STEPS)]
            reserve = self.procedure.reserve(self.params) if self.procedure.reserve else 0.0
            total = max(sum(nominal) + reserve, 1e-9)
            # the last commanded pose (for a tail step's nominal seconds); self._held is what the encoders said
            left_nominal, done, commanded = total, 0, start
            while True:
                self._check_abort()
                # the procedure's own work between steps (its fits; a characterize run's analysis takes
                # a minute) runs off this loop, which meanwhile polls the table and takes the operator's
                # commands (an abort ends the run at once)
                computing = asyncio.get_running_loop().run_in_executor(PROCEDURE_THREADS, _advance, gen, reply)
                await self._unless_aborted(computing)
                finished, value = computing.result()
                if finished:
                    outcome = value
                    break
                step = value
                replayed = replaying and not self._live_in_replay(step)
                if replayed:
                    reply = self._replayed(step)
                    if isinstance(step, Checkpoint):
                        passed += 1
                        if passed == self.replay.checkpoints:
                            replaying = False
                            self._go_live(step.label)
                else:
                    began = self.table_time()
                    self._table_done = None
                    self.on_event(StepStarted(step, began))
                    try:
                        reply = await self._do(step)
                        if isinstance(step, TIMED_STEPS):
                            done_at = self._table_done if self._table_done is not None else self.table_time()
                            self._table_used += done_at - began
                    finally:
                        # after the step's table time: host work, which a time scale would multiply
                        self._flag_pending()
                if isinstance(step, TIMED_STEPS):
                    # a data-dependent tail beyond the plan spends the reserve by its steps' nominal seconds,
                    # as the procedure spends its budget (so the two agree on what is left)
                    spent = nominal[done] if done < len(nominal) else step_seconds([step], self._motion(), commanded)[0]
                    if replayed:
                        # a replayed step counts its nominal seconds: the interrupted run's sample times also
                        # hold the time it stood paused, which is no table time (a resume after a pause
                        # reported 219 s for a plan of 120)
                        self._table_used += spent
                    elapsed = self._table_used
                    left_nominal -= min(spent, left_nominal)
                    done += 1
                    if isinstance(step, Move):
                        commanded = (step.psi, step.theta, step.phi)
                    frac = min(1.0, max(0.0, 1.0 - left_nominal / total))
                    # the plan's remaining table time at the pace so far (table s per planned s), that
                    # pace trusted as the plan gets done: early on it mostly measures the homing (a
                    # run of 4 s once said "~44 s left" after its first short move)
                    pace = elapsed / (total - left_nominal) if frac > 0 else 1.0
                    trust = frac / (frac + 0.05)
                    left = left_nominal * (trust * pace + 1.0 - trust)
                    # to 0.1 s, and exactly 0 once done (not a rounding residue such as 2.56e-14)
                    left = 0.0 if frac >= 1.0 else max(0.0, round(left, 1))
                    self.on_event(Progress(round(100.0 * frac, 1), elapsed, left, self._samples,
                                           left_wall_s=round(left / self.station.time_scale, 1)))
            if left_nominal > 1e-6 * total and done:  # a tail that used less than its reserve: done now
                self.on_event(Progress(100.0, self._table_used, 0.0, self._samples, left_wall_s=0.0))
            self._reconcile_flags(outcome)
            self._set_state(RunState.completed)
            self.on_event(Result(tuple(sorted(outcome.results)) if outcome else ()))
        except Aborted:
            await self._stop_and_end(RunState.aborted, self._abort)
        except (DriverError, asyncio.TimeoutError) as e:
            await self._stop_and_end(RunState.failed, _reason(e))
        except BaseException as e:  # a bug or a cancellation: still stop the table, keep the data
            await self._stop_and_end(RunState.failed, _reason(e))
            if isinstance(e, (asyncio.CancelledError, KeyboardInterrupt)):
                raise
        finally:
            if computing is None or computing.done():
                gen.close()
            else:  # cancelled while the procedure computes: close it once its thread is done with it
                computing.add_done_callback(lambda _: gen.close())
        return RunResult(self.state, self.reason, outcome, self._samples, self._table_used, sum(nominal))

    def _motion(self) -> Motion:
        st = self.station
        return Motion(st.speed_dps, st.accel_dps2, st.settle_s, float(st.sample_rate_hz))

    async def _prepare(self) -> tuple[float, float, float]:
        """Enable and home the axes if needed, and return where the table stands then. (The compasses
        are set streaming at the first acquisition, and again after a prompt: the operator may have
        mounted another unit.)

        An axis already in fault is not reset behind the operator's back: the run fails saying so."""
        table = self.station.table
        status = await table.status_all()
        faulted = _faults(status)
        if faulted:
            raise DriverError("axis fault before the run (reset it first): " + ", ".join(faulted))
        if not all(s.enabled for s in status.values()):
            await table.enable_all()
        if not all(s.homed for s in status.values()):
            await table.home_all(vel_dps=self.station.speed_dps, acc_dps2=self.station.accel_dps2)
        return await table.positions()

    async def _do(self, step: Step) -> Any:
        if isinstance(step, Compute):  # the table holds where it is
            return self._computing(step)
        if isinstance(step, Where):
            return tuple(await self.station.table.positions())
        if isinstance(step, Move):
            try:
                self._held = await self._retry(lambda: self.station.table.move_to(
                    step.psi, step.theta, step.phi, speed_dps=self.station.speed_dps, accel_dps2=self.station.accel_dps2), MoveTimeout)
            except (DriverError, asyncio.TimeoutError) as e:
                if not isinstance(step, Park):
                    raise
                stopped = await self._stop_axes()
                self._held = None
                self.on_event(StepWarning(f"the table did not reach its rest pose ({_reason(e)}): "
                                          f"{stopped or 'axes stopped'}; the run's data and result are whole; reset the "
                                          "station before the next run"))
            return self._held
        if isinstance(step, Settle):
            await asyncio.sleep(step.seconds / self.station.time_scale)
            return None
        if isinstance(step, Acquire):
            await self._stream()
            try:
                return await self._acquire(step)
            finally:
                self._say_resets(step.step)
        self._held = None  # anything else (a scan, a prompt, a pause): read the encoders afresh
        if isinstance(step, Scan):
            await self._retry(lambda: self.station.table.move_to(
                *step.start_angles, speed_dps=self.station.speed_dps, accel_dps2=self.station.accel_dps2), MoveTimeout)
            await self._stream()
            self._check_abort()
            try:
                return await self._scan(step)  # never retried: it would repeat samples already kept
            finally:
                self._say_resets(step.step)
        if isinstance(step, Checkpoint):
            if not self._resume.is_set():
                self._set_state(RunState.paused)
                await self._paused()
                self._check_abort()
                self._set_state(RunState.running)
            return None
        if isinstance(step, Identify):
            return await asyncio.wait_for(identify_units(self.station.fixture), IDENTIFY_TIMEOUT_S)
        if isinstance(step, Prompt):
            fut: asyncio.Future[str] = asyncio.get_running_loop().create_future()
            self._answers[step.id] = fut
            self._streaming = False
            self.on_event(PromptAsked(step.id, step.text))
            try:
                if self.prompt_timeout_s is None:
                    return await fut
                return await asyncio.wait_for(fut, self.prompt_timeout_s)
            except asyncio.TimeoutError:
                # nobody at the station: the run must not hold the table forever
                self._answers.pop(step.id, None)
                raise PromptTimeout(f"no answer to prompt {step.id!r} within {self.prompt_timeout_s:g} s") from None
            except asyncio.CancelledError:
                self._check_abort()
                raise
        raise TypeError(f"unknown step {step!r}")

    def _live_in_replay(self, step: Step) -> bool:
        """Whether a step is done live even while replaying: an identification (the units mounted now
        are the ones to name) and a prompt the interrupted run has no answer to (never asked there)."""
        assert self.replay is not None
        return isinstance(step, Identify) or (isinstance(step, Prompt) and step.id not in self.replay.answers)

    def _replayed(self, step: Step) -> Any:
        """A step answered from the interrupted run (see :class:`Replay`), not the table."""
        assert self.replay is not None
        if isinstance(step, (Acquire, Scan)):
            recs = self.replay.take(step)
            for slot, rec in sorted(recs.items()):
                self.sink.add(slot, rec)
                self._kept.setdefault(slot, []).append(rec)
                self._flag_bad(slot, step.step)
                self._samples += len(rec)
                self._replayed_until = max(self._replayed_until, float(rec.t[-1]))
            return dict(recs)
        if isinstance(step, Prompt):
            return self.replay.answers.get(step.id, "")
        return None

    def _go_live(self, label: str) -> None:
        """The replay has reached its last checkpoint: table time goes on after its last sample."""
        assert self.replay is not None
        t = self._replayed_until + 1.0
        # the replayed steps counted their nominal seconds from where the table stands now (the
        # interrupted run stopped it further on, so its first move back looks long): they took no more
        # table time than their samples span
        self._table_used = min(self._table_used, self._replayed_until)
        self._t0 = time.monotonic() - t / self.station.time_scale  # (the samples' t goes on from there)
        self.on_event(Resumed(self.replay.run_id, label, self._samples, t))

    async def _stream(self) -> None:
        if not self._streaming:
            await self.station.fixture.set_rate_all(self.station.sample_rate_hz)
            self._streaming = True

    async def _retry(self, action: Callable[[], Any], timeout_type: type[Exception]) -> Any:
        for attempt in range(self.retries + 1):
            self._check_abort()
            try:
                return await action()
            except timeout_type as e:
                if attempt == self.retries:
                    raise
                self.on_event(StepRetried(attempt + 1, _reason(e)))
        raise AssertionError("unreachable")

    def _say_resets(self, label: str) -> None:
        """A warning for each compass that reset itself (or reconnected) since the last look: its driver
        applied its settings again and the run went on, but only the worker's log had said so."""
        for slot, compass in self.station.fixture.compasses.items():
            now = _link_counts(compass)
            before = self._link_events.setdefault(slot, now)
            if now != before:
                what = " and ".join(x for x, n in (("reset itself", now[0] - before[0]),
                                                   ("reconnected", now[1] - before[1])) if n > 0)
                self.on_event(StepWarning(f"slot {slot}: the compass {what} during {label} (its settings were applied "
                                          "again and its samples kept); a unit that resets itself may have a supply "
                                          "or cable fault"))
                self._link_events[slot] = now

    async def _acquire(self, step: Acquire) -> dict[int, Recording]:
        """Hold still and take exactly ``step.samples`` samples per slot.

        A read that times out keeps what arrived (sent to the sink at once) and the retry reads only
        what is missing, so a pose holds its planned count however late a busy host delivers lines."""
        # where the last move stopped (read back in position), else the encoders now: a round trip
        # saved per pose is a time-scale's worth of table time on a simulated station
        before = self._held if self._held is not None else await self.station.table.positions()
        parts: dict[int, list[Recording]] = {}
        await self._retry(lambda: self._read_missing(step, parts, before), CompassTimeout)
        after = await self._still_sound(step.step)
        moved = float(np.max(np.abs(np.subtract(after, before))))
        if moved > HOLD_TOLERANCE_DEG:
            raise DriverError(f"the table moved {moved:.3f} deg while {step.step} was acquiring")
        self._held = before
        return {slot: concat(recs) for slot, recs in parts.items()}

    async def _paused(self) -> None:
        """Wait for the operator's resume (or abort) while watching the station: an axis that faults, is
        E-stopped or stops answering, or a streaming compass that stops talking, while the run stands
        paused fails it at once (both were said only when the operator resumed)."""
        while True:
            try:
                await asyncio.wait_for(self._resume.wait(), PAUSED_WATCH_S)
                return
            except asyncio.TimeoutError:
                await self._sound_status("while the run was paused")
                if self._streaming:
                    await self._still_talking("while the run was paused")

    async def _still_talking(self, when: str) -> None:
        """Every compass sends samples: one sample of each read, retried as an acquisition's read is
        (a silent or vanished compass raises the read's error, then ``when``)."""
        try:
            await self._retry(lambda: self.station.fixture.read_all(1, timeout=None), FixtureError)
        except FixtureError as e:
            timeouts = all(isinstance(err, CompassTimeout) for err in e.errors.values())
            raise (CompassTimeout if timeouts else CompassError)(f"{e} {when}") from e

    async def _still_sound(self, label: str) -> tuple[float, float, float]:
        """After a pose's or a scan's samples: every axis's status (one poll each, as the positions
        alone cost), refusing the samples' angles when an axis is in fault or E-stop (an encoder error
        raised while the table held went unnoticed: the run completed and certified the unit, the
        station idle). The positions (psi, theta, phi) otherwise."""
        status = await self._sound_status(f"at the end of {label}: its samples are kept, but their table angles "
                                          "cannot be trusted")
        return tuple(s.position_deg for s in status.values())  # type: ignore[return-value]

    async def _sound_status(self, when: str) -> Mapping[str, Any]:
        """Every axis's status; DriverError naming each axis in fault or E-stop, then ``when``."""
        status = await self.station.table.status_all()
        faulted = _faults(status)
        if faulted:
            raise DriverError(f"{', '.join(faulted)} {when}")
        return status

    async def _read_missing(self, step: Acquire, parts: dict[int, list[Recording]], held: Any) -> None:
        """Read what each slot still lacks of ``step.samples`` (a slot that got more than it needed in
        a failed read has the surplus left out; lines measured before the read began are left out and
        read again, see `_measured_before`), keep it (`_keep`) and add it to ``parts``; then raise the
        read's error, if any (a `CompassTimeout` when every failed slot timed out)."""
        start = time.monotonic()
        for attempt in range(STALE_REREADS + 1):
            have = {int(slot): sum(len(r) for r in parts.get(int(slot), [])) for slot in self.station.fixture.compasses}
            need = step.samples - min(have.values(), default=0)
            if need <= 0:
                return
            timeout = need / self.station.sample_rate_hz / self.station.time_scale + self.acquire_margin_s
            error: CompassError | None = None
            got: dict[Any, Sequence[Sample]]
            try:
                got = dict(await self.station.fixture.read_all(need, timeout=timeout))
            except FixtureError as e:
                got = dict(e.results)
                got.update({slot: err.samples for slot, err in e.errors.items() if isinstance(err, CompassError)})
                timeouts = all(isinstance(err, CompassTimeout) for err in e.errors.values())
                error = CompassTimeout(str(e)) if timeouts else e
            self._table_done = self.table_time()
            keep: dict[Any, list[Sample]] = {}
            times: dict[Any, np.ndarray] = {}
            for slot, samples in got.items():
                samples = list(samples)
                clock = self._on_sample_clock(slot, samples) if samples else None
                # a line measured before the read began (while the table was still moving) but
                # delivered after it is not this pose's: left out, and read again
                skip = _measured_before(clock, start) if attempt < STALE_REREADS else 0
                stop = skip + step.samples - have.get(int(slot), 0)
                keep[slot] = samples[skip:stop]
                if keep[slot]:
                    times[slot] = self._sample_times(slot, keep[slot], None if clock is None else clock[skip:stop])
            kept = self._keep(step.step, keep, held, times)
            for slot, rec in kept.items():
                parts.setdefault(slot, []).append(rec)
            if error is not None:
                raise error

    async def _scan(self, step: Scan) -> dict[int, Recording]:
        """Turn one axis while every compass streams; label each sample with the encoder angles at
        its time (the scanned axis from its encoder polls, see :func:`encoder_track`; the others as
        held, checked at the end).

        The move and the per-slot sample collection run concurrently; the first error of either stops
        the table, keeps every sample received up to the last encoder poll, and is raised."""
        table, fixture = self.station.table, self.station.fixture
        name, i = SCAN_AXIS[step.axis], step.index
        before = await table.positions()
        got: dict[Any, list[Sample]] = {slot: [] for slot in fixture.compasses}
        # a compass whose stream stalls for this long fails the scan (wall seconds)
        stale = 3.0 / self.station.sample_rate_hz / self.station.time_scale + self.acquire_margin_s
        collectors = [asyncio.create_task(_collect(c, got[slot], stale)) for slot, c in fixture.compasses.items()]
        await asyncio.sleep(0)  # let each collector start listening before the table moves
        t_begin = time.monotonic()
        trace: list[tuple[float, float, float]] = [(t_begin, t_begin, before[i])]  # at rest at the start
        motion = asyncio.create_task(table.scan(name, step.stop_deg, step.speed_dps, self.station.accel_dps2, trace=trace))
        aborted = asyncio.create_task(self._aborted.wait())
        error: BaseException | None = None
        try:
            await asyncio.wait([motion, aborted, *collectors], return_when=asyncio.FIRST_COMPLETED)
            if aborted.done():
                error = Aborted(self._abort or "aborted")
            elif motion.done() and motion.exception() is None:
                await _until_after(got, trace[-1][1], stale)  # the samples up to the end are in flight
            for task in (motion, *collectors):
                if error is None and task.done() and not task.cancelled() and task.exception() is not None:
                    error = task.exception()
        finally:
            await _cancel_all([motion, aborted, *collectors])
        self._table_done = self.table_time()
        out = self._keep_scan(step, got, t_begin, trace, before)
        if error is not None:
            raise error
        after = await self._still_sound(step.step)
        held = [j for j in range(3) if j != i]
        moved = max(abs(after[j] - before[j]) for j in held)
        if moved > HOLD_TOLERANCE_DEG:
            raise DriverError(f"an axis that should hold moved {moved:.3f} deg during scan {step.step}")
        return out

    def _keep_scan(self, step: Scan, got: dict[Any, list[Sample]], t_begin: float,
                   trace: list[tuple[float, float, float]], held: tuple[float, float, float]) -> dict[int, Recording]:
        """Keep the samples of a scan received between its start and its last encoder poll."""
        t_end = trace[-1][1]
        scale = self.station.time_scale
        encoder = encoder_track(trace, held[step.index], step.stop_deg, step.speed_dps * scale,
                                self.station.accel_dps2 * scale * scale)
        kept: dict[Any, list[Sample]] = {}
        angles: dict[Any, np.ndarray] = {}
        times: dict[Any, np.ndarray] = {}
        for slot, samples in got.items():
            samples = [s for s in samples if t_begin <= s.t_host <= t_end]
            if not samples:
                continue
            t = self._sample_times(slot, samples)
            a = np.tile(np.asarray(held, dtype=float), (len(samples), 1))
            a[:, step.index] = encoder(t)
            kept[slot], angles[slot], times[slot] = samples, np.round(a, 6), t
        return self._keep(step.step, kept, angles, times)

    def _keep(self, label: str, got: dict[Any, list[Sample]], angles: Any,
              times: dict[Any, np.ndarray]) -> dict[int, Recording]:
        """Send samples to the sink (before anything else can go wrong) and return them as recordings.
        ``angles``: the held (psi, theta, phi), or per slot an (n, 3) array; ``times``: per slot host
        times of the samples on the compass's sample clock (`_sample_times`)."""
        out: dict[int, Recording] = {}
        for slot, samples in got.items():
            if not samples:
                continue
            a = angles[slot] if isinstance(angles, dict) else np.tile(np.asarray(angles, dtype=float), (len(samples), 1))
            rec = self._recording(int(slot), samples, label, a, times[slot])
            self.sink.add(int(slot), rec)
            self._kept.setdefault(int(slot), []).append(rec)
            self._to_flag[int(slot)] = label
            out[int(slot)] = rec
            self._samples += len(samples)
        self.on_event(SamplesStored(label, self._samples))
        return out

    def _flag_pending(self) -> None:
        """`_flag_bad` for the samples the last step kept."""
        for slot, label in self._to_flag.items():
            self._flag_bad(slot, label)
        self._to_flag.clear()

    def _flag_bad(self, slot: int, label: str) -> None:
        """Screen the slot's samples so far (``_kept``) as the fit will (physics.fit.screen_rows: a
        brown-out's zeros, a reading far off its pose's median) and warn, as it happens, of each bad
        sample not flagged before, by its row in the unit's recording (the fit lists the rows it drops in
        quality.rejected_rows; :meth:`_reconcile_flags` says which flagged ones it kept). The samples stay recorded: the fit drops them, the recording keeps what
        the compass said."""
        kept = self._kept.get(slot, [])
        flagged = self._flagged.setdefault(slot, set())
        bad = {i: why for i, why in screen_rows(concat(kept)).items() if i not in flagged}
        if not bad:
            return
        flagged.update(bad)
        rows = sorted(bad)
        listed = _listed(rows)
        why = "; ".join(f"row {i}: {bad[i]}" for i in rows[:2])
        who = self.serials.get(slot) or f"slot {slot}"
        self.on_event(StepWarning(f"{who}: {len(rows)} bad sample(s) flagged after {label}, rows {listed} "
                                  f"(the fit drops them): {why}"))

    def _reconcile_flags(self, outcome: Outcome | None) -> None:
        """Say which rows flagged during the run the fit kept after all. The live screen sees the run so
        far: early on an axis's amplitude is what the first holds swept (the level turn hardly moves z),
        so a reading 64 LSB off can be gross then and ordinary once the sweeps have turned z through the
        field; the fit screens the whole run. The rows it dropped are its ``quality.rejected_rows``."""
        for slot, res in sorted((outcome.results if outcome else {}).items()):
            flagged = self._flagged.get(slot)
            quality = getattr(res.get("calibration"), "quality", None) if isinstance(res, dict) else None
            if not flagged or not isinstance(quality, dict) or "rejected_rows" not in quality:
                continue
            kept = sorted(flagged - {int(r["index"]) for r in quality["rejected_rows"]})
            if kept:
                who = self.serials.get(slot) or f"slot {slot}"
                self.on_event(StepWarning(f"{who}: {len(kept)} row(s) flagged during the run were kept by the fit, "
                                          f"rows {_listed(kept)}: on the whole run's readings they are within range"))

    def _on_sample_clock(self, slot: Any, samples: list[Sample]) -> np.ndarray | None:
        """When the compass measured ``samples`` (consecutive lines as received; host seconds), on its
        own sample clock (:func:`sample_clock`) through its latest lines: those delivered on time
        before a late burst anchor the steady numbering, so the burst's lines show their true age,
        which the burst alone (its lines sharing one arrival time) cannot. None when the samples are
        no longer in the compass's history."""
        latest = self.station.fixture.compasses[slot].recent(len(samples) + ANCHOR_LINES)
        first = next((i for i in range(len(latest) - 1, -1, -1) if latest[i] is samples[0]), None)
        if first is None or first + len(samples) > len(latest) or latest[first + len(samples) - 1] is not samples[-1]:
            return None
        t = sample_clock(np.array([s.t_host for s in latest]), np.array([s.seq for s in latest]),
                         self.station.sample_rate_hz * self.station.time_scale)
        return t[first:first + len(samples)]

    def _sample_times(self, slot: Any, samples: list[Sample], clock: np.ndarray | None = None) -> np.ndarray:
        """The samples' times on the compass's clock (``clock`` if already placed, else
        `_on_sample_clock`), continuing the slot's previous step and never before it."""
        seq = np.array([s.seq for s in samples])
        after = self._clock.get(slot)
        t = clock if clock is not None else self._on_sample_clock(slot, samples)
        if t is None:
            t = sample_clock(np.array([s.t_host for s in samples]), seq,
                             self.station.sample_rate_hz * self.station.time_scale, after=after)
        elif after is not None:
            t = np.maximum(t, after[0] + 1e-6)
        self._clock[slot] = (float(t[-1]), int(seq[-1]))
        return t

    def _recording(self, slot: int, samples: list[Sample], step: str, angles: np.ndarray,
                   t_host: np.ndarray) -> Recording:
        n = len(samples)
        return Recording.from_arrays(
            t=(t_host - self._t0) * self.station.time_scale, step=[step] * n,
            psi_t=angles[:, 0], theta_t=angles[:, 1], phi_t=angles[:, 2],
            mag=[s.mag for s in samples], acc=[s.acc for s in samples], temp_c=[s.temp_c for s in samples],
            meta={"serial": self.serials.get(slot, ""), "slot": str(slot)},
        )

    def _computing(self, step: Compute) -> Callable[[str, float], None]:
        """The ``progress(stage, fraction)`` a Compute step's computation reports through, from its
        thread: a :class:`Computing` event on this loop, at most every :data:`COMPUTING_EVERY_S` within
        a stage, and none once the run has ended (an abort does not wait for the computation)."""
        loop = asyncio.get_running_loop()
        last = [0.0, ""]

        def emit(event: Computing) -> None:
            if self.state in (RunState.running, RunState.paused) and self._abort is None:
                self.on_event(event)

        def progress(stage: str, fraction: float) -> None:
            now = time.monotonic()
            if stage == last[1] and now - last[0] < COMPUTING_EVERY_S:
                return
            last[:] = [now, stage]
            event = Computing(Compute(step.label, stage, round(100.0 * min(max(fraction, 0.0), 1.0), 1)), self.table_time())
            try:
                loop.call_soon_threadsafe(emit, event)
            except RuntimeError:  # the run's loop is gone: nobody is following any more
                pass
        return progress

    async def _unless_aborted(self, work: asyncio.Future[Any]) -> None:
        """Wait for ``work``; an abort meanwhile raises at once (the work, which cannot be interrupted,
        ends on its own and its result is dropped)."""
        aborted = asyncio.create_task(self._aborted.wait())
        try:
            await asyncio.wait([work, aborted], return_when=asyncio.FIRST_COMPLETED)
        finally:
            aborted.cancel()
        if not work.done():
            self._check_abort()

    def _check_abort(self) -> None:
        if self._abort is not None:
            raise Aborted(self._abort)

    async def _stop_axes(self) -> str | None:
        """Stop every axis; what went wrong (said as a warning too), or None. A run that ends so carries it
        in its reason after its own (it was said only in the events: a table off its bus may still turn)."""
        try:
            await asyncio.wait_for(self.station.table.stop_all(), timeout=2.0)
        except Exception as e:  # noqa: BLE001 - report it, but the run's own reason comes first
            why = f"stopping the axes failed: {_reason(e)}"
            self.on_event(StepWarning(why))
            return why
        return None

    async def _stop_and_end(self, state: RunState, reason: str | None) -> None:
        """Stop the axes and end the run in ``state``: its reason, then any failure to stop them."""
        stopped = await self._stop_axes()
        self._set_state(state, "; ".join(filter(None, (reason, stopped))))

    def _set_state(self, state: RunState, reason: str | None = None) -> None:
        self.state, self.reason = state, reason
        self.on_event(StateChanged(state, reason, self.table_time()))


async def _collect(compass: SampleStream, into: list[Sample], timeout: float) -> None:
    """Append every sample ``compass`` streams to ``into`` until cancelled (raises what the stream raises)."""
    async for sample in compass.samples(timeout=timeout):
        into.append(sample)


async def _cancel_all(tasks: list[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and wait until all have ended. The cancellation is repeated: asyncio.wait_for
    (inside the compass driver's waits) can swallow a cancellation that arrives just as its inner wait
    completes (Python < 3.12), which would leave a collector running."""
    pending = {t for t in tasks if not t.done()}
    while pending:
        for t in pending:
            t.cancel()
        _, pending = await asyncio.wait(pending, timeout=0.05)
    for t in tasks:
        if not t.cancelled():
            t.exception()  # retrieved (raised by the caller if it matters)


async def _until_after(got: dict[Any, list[Sample]], t: float, timeout: float) -> None:
    """Wait (at most ``timeout`` wall seconds) until every slot has a sample received after ``t``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(s and s[-1].t_host >= t for s in got.values()):
            return
        await asyncio.sleep(0.001)


class Trapezoid:
    """A controller's trapezoidal (or triangular) profile over ``distance`` (> 0) at ``speed`` and
    ``accel``: distance travelled at a time from its start, and the time a distance is reached."""

    def __init__(self, distance: float, speed: float, accel: float) -> None:
        self.d, self.a = float(distance), float(accel)
        self.v = min(float(speed), math.sqrt(self.d * self.a))  # a short move never reaches full speed
        self.ta, self.da = self.v / self.a, self.v * self.v / (2 * self.a)
        self.T = 2 * self.ta + (self.d - 2 * self.da) / self.v

    def distance(self, t: np.ndarray) -> np.ndarray:
        """Distance travelled ``t`` after the start (0 before, ``distance`` after the end)."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.T)
        left = self.T - t
        return np.where(t < self.ta, 0.5 * self.a * t * t,
                        np.where(left < self.ta, self.d - 0.5 * self.a * left * left, self.da + self.v * (t - self.ta)))

    def time_at(self, x: np.ndarray) -> np.ndarray:
        """When ``x`` (0..distance) is reached."""
        x = np.clip(np.asarray(x, dtype=float), 0.0, self.d)
        return np.where(x < self.da, np.sqrt(2 * x / self.a),
                        np.where(x > self.d - self.da, self.T - np.sqrt(2 * np.maximum(self.d - x, 0.0) / self.a),
                                 self.ta + (x - self.da) / self.v))


def _most_shared(lo: np.ndarray, hi: np.ndarray, near: float) -> float:
    """The middle of the span that the most of the intervals [lo, hi] share (of several such spans,
    the one nearest ``near``)."""
    pts = np.concatenate([lo, hi])
    step = np.r_[np.ones(len(lo)), -np.ones(len(hi))]
    order = np.lexsort((-step, pts))  # at one point, starts before ends: intervals that touch share it
    pts, depth = pts[order], np.cumsum(step[order])
    tops = np.flatnonzero(depth == depth.max())  # each a start; the next point ends its span
    middles = 0.5 * (pts[tops] + pts[tops + 1])
    return float(middles[np.argmin(np.abs(middles - near))])


def encoder_track(trace: list[tuple[float, float, float]], start: float, stop: float, speed: float,
                  accel: float) -> Callable[[np.ndarray], np.ndarray]:
    """The scanned axis's encoder angle as a function of host time, from the polls of a scan.

    ``trace``: (time before the request, after the reply, encoder deg) of each poll; ``speed`` and
    ``accel`` in host time units. A poll's position was latched somewhere within its round trip,
    which a busy host stretches to milliseconds (0.03 deg each at 30 deg/s, ten times that at time
    scale 10). The controller runs a known trapezoid, so each position fixes the time since the
    profile began, and each poll's round trip bounds the profile's start: the start is the middle of
    the span the most polls at full speed agree on (`_most_shared`; the accelerating polls carry the
    servo's lag), so the quickest round trips place it, however long and lopsided the others are (a
    reply that waits on a busy loop puts the middle of its round trip milliseconds after the latch,
    and a median of those middles put the whole turn 2.2 deg off at time scale 10 in
    `tests/test_characterize.py::test_encoder_track_is_placed_by_the_quickest_round_trips_however_lopsided_the_others`). Each poll's time
    is then its profile time clamped into its own round trip, and the angle at any time is the
    profile there plus the measured departure from it (servo lag, a stop), interpolated between
    polls, never behind the start. Without enough polls in motion the polls are interpolated as they are."""
    t0, t1, pos = (np.array([p[k] for p in trace], dtype=float) for k in range(3))
    mid = 0.5 * (t0 + t1)
    sign = 1.0 if stop >= start else -1.0
    dist = abs(stop - start)
    x = sign * (pos - start)
    moving = (x > 0.002) & (x < dist - 0.002)  # beyond the encoder's resolution from either end
    if dist < 0.01 or moving.sum() < 2:
        order = np.argsort(mid, kind="stable")
        return lambda t: np.interp(t, mid[order], pos[order])
    prof = Trapezoid(dist, speed, accel)
    T = prof.time_at(x)
    cruise = moving & (T > prof.ta) & (T < prof.T - prof.ta)
    use = cruise if cruise.sum() >= 3 else moving
    tau = _most_shared(t0[use] - T[use], t1[use] - T[use], float(np.median(mid[use] - T[use])))
    when = mid.copy()
    when[moving] = np.clip(tau + prof.time_at(x[moving]), t0[moving], t1[moving])
    order = np.argsort(when, kind="stable")
    when, pos = when[order], pos[order]
    departure = pos - (start + sign * prof.distance(when - tau))

    def angle(t: np.ndarray) -> np.ndarray:
        # the servo's lag, interpolated from the first poll in motion back to rest, would put the
        # first samples of the turn behind where the axis started: it does not move backwards
        x = prof.distance(np.asarray(t, dtype=float) - tau) + sign * np.interp(t, when, departure)
        return start + sign * np.maximum(x, 0.0)
    return angle


def _measured_before(t: np.ndarray | None, start: float) -> int:
    """How many of a read's first lines, by their times on the compass's sample clock
    (`Engine._on_sample_clock`; None: not placed), the compass measured before ``start`` (host time),
    though they arrived after it: a busy host (or a USB adapter's latency timer) delivers lines late,
    in bursts, and at time scale 20 a 50-ms delay is a second of table time. The clock's estimate is
    never earlier than the truth, so a line measured after ``start`` is never left out."""
    if t is None or not len(t):
        return 0
    early = t < start
    return len(t) if early.all() else int(np.argmin(early))


def _advance(gen: Any, reply: Any) -> tuple[bool, Any]:
    """Resume a procedure with ``reply``: (False, its next step) or (True, its outcome). (A thread's
    StopIteration cannot cross into an asyncio future, hence the pair.)"""
    try:
        return False, gen.send(reply)
    except StopIteration as stop:
        return True, stop.value


def sample_clock(t_host: np.ndarray, seq: np.ndarray, rate_hz: float,
                 after: tuple[float, int] | None = None) -> np.ndarray:
    """Each sample's time on the compass's own sample clock, in host seconds.

    A sample's arrival time carries the jitter of the serial link, the kernel and the event
    loop (milliseconds: 0.03 deg each at 30 deg/s; several lines read at once share one arrival
    time; a busy host delivers late bursts). The device samples on a steady clock numbered by
    ``seq``, so within a run of consecutive sequence numbers the times are put on a line in ``seq``
    through the least-delayed arrival, so every sample gets the smallest latency seen. The line's
    slope is the nominal period (``1 / rate_hz``, host seconds), corrected when a long run shows the
    device's clock off by up to 5 %. The device's pace is read from the lower convex hull of the
    arrivals less the nominal clock (`_lower_hull`): a latency only ever delays a line, so the hull
    runs through the least-delayed lines, flat where the clock is the nominal one, and rises or
    falls only under bursts of late lines (one still arriving when the run ends makes its lines all
    look old, however long it is); the small correction is the hull's tangent at the run's middle. A
    run whose hull is within 20 % of the nominal pace over less than a quarter of its length (not the
    clock we think) keeps its arrival times.

    ``after``: (time, seq) of the last sample already timed on this clock (the previous step's). A
    first run that continues its sequence is never put before it: each step alone takes the least
    latency it saw, and a short step on a busy host can see more latency than the next by more than
    a period (5 ms at time scale 10), which would put time backwards across the steps' boundary."""
    t = np.asarray(t_host, dtype=float).copy()
    if len(t) < 1:
        return t
    period = 1.0 / rate_hz
    step = np.diff(np.asarray(seq, dtype=np.int64)) % 65536
    breaks = np.flatnonzero((step == 0) | (step > 1000)) + 1  # a restart or a long silence
    gap = (int(seq[0]) - after[1]) % 65536 if after is not None else 0
    continues = 0 < gap <= 1000
    for k, part in enumerate(np.split(np.arange(len(t)), breaks)):
        n = np.r_[0, np.cumsum(step[part[1:] - 1])].astype(float)
        r = t[part] - period * n  # latency plus a constant, if the device's clock is right
        hn, hr = _lower_hull(n, r)
        slopes = np.diff(hr) / np.diff(hn)
        nominal = float(np.sum(np.diff(hn)[np.abs(slopes) < 0.2 * period]))
        if len(part) < 2 or nominal < 0.25 * n[-1]:
            if k == 0 and continues:  # arrival times kept, but never before the previous sample
                t[part] = np.maximum(t[part], after[0] + 1e-6)
            continue
        slope = float(slopes[np.argmax(hn[1:] >= np.mean(n))])  # the hull's tangent at the mean
        if len(part) < 40 or abs(slope) > 0.05 * period:
            slope = 0.0
        line = (period + slope) * n
        start = np.min(t[part] - line)
        if k == 0 and continues:
            start = max(start, after[0] + (period + slope) * gap)
        t[part] = start + line
    return t


def _lower_hull(n: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lower convex hull of the points (n increasing, r): its vertices' n and r. A long run is
    first thinned to the least-delayed point of each stretch of 16, which keeps the hull's shape and
    its cost (a read's 4096 lines) near a millisecond."""
    if len(n) > 512:
        padded = np.full(-(-len(n) // 16) * 16, np.inf)
        padded[:len(n)] = r
        low = np.argmin(padded.reshape(-1, 16), axis=1) + 16 * np.arange(len(padded) // 16)
        n, r = n[low], r[low]
    hull: list[int] = []  # Andrew's monotone chain, lower half (on Python floats: numpy scalars cost 5x)
    nl, rl = n.tolist(), r.tolist()
    for i in range(len(nl)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            if (nl[b] - nl[a]) * (rl[i] - rl[a]) - (rl[b] - rl[a]) * (nl[i] - nl[a]) > 0:
                break
            hull.pop()
        hull.append(i)
    return n[hull], r[hull]


def _reason(e: BaseException) -> str:
    if isinstance(e, PromptTimeout):  # its message is the whole story (no class name for an operator to read)
        return str(e)
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


class RecordingSink:
    """Keeps each slot's samples and adds them to its recording file (RECORDING.md) after every
    acquisition, so a fault or a kill loses at most the acquisition in progress."""

    def __init__(self, directory: Path | None, names: dict[int, str], meta: dict[str, str] | None = None) -> None:
        self.directory = directory
        self.names = names
        self.meta = meta or {}
        self.parts: dict[int, list[Recording]] = {}
        self._columns: dict[int, list[str]] = {}  # per slot: the extra columns of the file as written

    def add(self, slot: int, rec: Recording) -> None:
        """Keep these samples and flush the slot's file: their rows appended when their extra columns
        are the file's (rewriting the whole file at every pose cost a run of 8 units at time scale 20 a
        fifth of its event loop), else the file rewritten with every part."""
        self.parts.setdefault(slot, []).append(rec)
        if self.directory is None:
            return
        if self._columns.get(slot) == list(rec.extra):  # (a missing acc or temp_c is written empty either way)
            with self.path(slot).open("a") as f:
                f.write(format_recording(rec, header=False))
        else:
            whole = self.recording(slot)
            self.path(slot).write_text(format_recording(whole))
            self._columns[slot] = list(whole.extra)

    def path(self, slot: int) -> Path:
        """The slot's recording file."""
        assert self.directory is not None
        return self.directory / f"{self.names.get(slot, f'slot{slot}')}.csv"

    def recording(self, slot: int) -> Recording:
        """Everything kept for one slot, with the run's metadata."""
        rec = concat(self.parts[slot])
        rec.meta.update(self.meta)
        return rec


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
