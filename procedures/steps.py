"""The step language of procedures: what to do, never how.

A procedure is a generator function ``(params) -> Generator[Step, Reply, Outcome]``. It yields steps;
whoever runs it (the engine against a station, or a fake engine in a test) does each step and sends
back the reply: the samples of an :class:`Acquire` or a :class:`Scan`, the operator's answer to a
:class:`Prompt`, ``None`` otherwise. What the generator returns is the run's outcome (e.g. each unit's calibration).
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any, Union

from pydantic import BaseModel, ValidationError

from physics.recording import Recording
from physics.sensor import Unit
from physics.simulate import SCAN_AXES, Pose, Scan, World, simulate_recording  # noqa: F401  (Scan, SCAN_AXES: re-exported, steps of the step language)
from physics.table import Motion, move_seconds


@dataclass(frozen=True)
class Move:
    """Move the table to these encoder angles (deg) and wait until every axis is in position."""

    psi: float
    theta: float = 0.0
    phi: float = 0.0


@dataclass(frozen=True)
class Park(Move):
    """Move the table where the operator works once the run's data are in (a batch unit's load pose).
    A fault on the way stops the axes and is a warning, not the run's failure: what the run measured is
    whole (the next run finds the axis in fault and says to reset it). Reply: the encoder angles, or None."""


@dataclass(frozen=True)
class Settle:
    """Wait this long (table time) after the move, so the mechanics and the sensor filters settle."""

    seconds: float


@dataclass(frozen=True)
class Acquire:
    """Take ``samples`` samples from every compass of the fixture, labelled ``step`` in the recording.

    Reply: ``dict[slot, Recording]`` of just these samples, with the encoder angles read back."""

    samples: int
    step: str


# Scan (turn one axis while acquiring; reply like Acquire) is physics.simulate.Scan: the same object is
# a step of a procedure and an item of a plan the offline simulator runs.


@dataclass(frozen=True)
class Prompt:
    """Ask the operator something (e.g. "mount unit SN-7 in slot 0"). Reply: the answer (str)."""

    text: str
    id: str = "prompt"


@dataclass(frozen=True)
class Identify:
    """Ask every compass of the fixture who it is (once the units are mounted).

    Reply: ``dict[slot, (model, serial, firmware)]`` of the compasses that answered; a compass that
    refuses the command (it cannot identify itself) is left out."""


@dataclass(frozen=True)
class Where:
    """Ask where the table stands now. Reply: its encoder angles ``(psi, theta, phi)`` in deg, or None
    from an engine that cannot say (a step replayed from an interrupted run)."""


@dataclass(frozen=True)
class Checkpoint:
    """A safe place to pause or abort (the table holds still here)."""

    label: str


@dataclass(frozen=True)
class Compute:
    """Say what the procedure computes next (a fit, an analysis), so that the operator sees it while it
    runs. Reply: a ``progress(stage, fraction)`` function to report how far it has got, or None (an engine
    that does not follow it)."""

    label: str
    stage: str = ""
    percent: float | None = None  # how far, as the engine last reported it


Step = Union[Move, Settle, Acquire, Scan, Prompt, Identify, Where, Checkpoint, Compute]
#: Steps that take table time (progress counts them).
TIMED_STEPS = (Move, Settle, Acquire, Scan)
Reply = Union[dict[int, Recording], dict[int, tuple[str, str, str]], str, None]


@dataclass
class Outcome:
    """What a run produced, per slot: calibrations, evaluations, or any result a procedure defines."""

    results: dict[int, dict[str, Any]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


ProcedureGen = Generator[Step, Reply, Outcome]


def request_number(value: Any) -> Any:
    """A number as a request brings it (a pydantic before-validator): true/false and strings are refused,
    which pydantic's lax mode reads as numbers (``"samples": true`` was one sample, ``"60"`` sixty): a
    script's mistake, where a request is checked whole. Anything else is left to the field's type."""
    if isinstance(value, bool):
        raise ValueError("a number is required, not true or false")
    if isinstance(value, str):
        raise ValueError(f"a number is required, not the string {value!r}")
    return value


#: The longest plan a run may have, nominal table seconds: a day. A step or a count mistyped by orders of
#: magnitude is refused before a station is claimed, not found on the table days later.
MAX_PLAN_S = 24 * 3600.0


@dataclass(frozen=True)
class Procedure:
    """A named, versioned procedure with its parameter schema (validated before a run starts)."""

    name: str
    version: str
    params: type[BaseModel]
    run: Callable[[Any], ProcedureGen]
    doc: str = ""
    #: Table seconds the data-dependent tail (left out of :meth:`plan`) may add at most, from the
    #: parameters: progress and time left count it until the run ends (an adaptive extension's budget).
    reserve: Callable[[Any], float] | None = None

    def validate(self, parameters: dict[str, Any] | None) -> BaseModel:
        """Validated parameters (pydantic raises, naming each bad field; a plan longer than
        :data:`MAX_PLAN_S` is refused as a whole, naming its length)."""
        params = self.params.model_validate(parameters or {})
        seconds = sum(step_seconds(self.plan(params)))
        if seconds > MAX_PLAN_S:
            msg = (f"the plan would take {seconds / 3600:,.0f} h of table time (nominal); a run may plan at most "
                   f"{MAX_PLAN_S / 3600:.0f} h: check its steps and sample counts")
            raise ValidationError.from_exception_data(self.params.__name__, [
                {"type": "value_error", "loc": (), "input": parameters, "ctx": {"error": ValueError(msg)}}])
        return params

    def plan(self, params: BaseModel) -> list[Step]:
        """The steps of a run whose acquisitions all return nothing: the run's length, for progress and
        time estimates. The data-dependent tail (a fit on no data, an adaptive move) is left out."""
        steps: list[Step] = []
        try:
            drive(self.run(params), lambda step: steps.append(step) or _empty_reply(step))
        except Exception:  # noqa: BLE001 - the tail that needs real data is not part of the plan
            pass
        return steps


def _empty_reply(step: Step) -> Reply:
    return {} if isinstance(step, (Acquire, Scan, Identify)) else ("" if isinstance(step, Prompt) else None)


def step_seconds(steps: list[Step], motion: Motion = Motion(),
                 start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> list[float]:
    """Nominal table seconds of each step under ``motion`` (speed, acceleration, the drives' settling,
    sample rate), from ``start``: moves as trapezoids plus ``motion.settle_s`` (the servos settling into
    position before the axes report it), settles as given, acquisitions at the sample rate, scans as the
    move to their start plus the turn at their own speed. Prompts, identifications and checkpoints take none."""
    here = list(start)
    out: list[float] = []
    for s in steps:
        if isinstance(s, Move):
            there = [s.psi, s.theta, s.phi]
            out.append(move_seconds([b - a for a, b in zip(here, there)], motion) + motion.settle_s)
            here = there
        elif isinstance(s, Settle):
            out.append(float(s.seconds))
        elif isinstance(s, Acquire):
            out.append(s.samples / motion.sample_rate_hz)
        elif isinstance(s, Scan):
            first = list(s.start_angles)
            turn = Motion(s.speed_dps, motion.max_accel_dps2, motion.settle_s, motion.sample_rate_hz)
            out.append(move_seconds([b - a for a, b in zip(here, first)], motion) + motion.settle_s
                       + move_seconds([s.stop_deg - s.start_deg], turn))
            here = list(s.stop_angles)
        else:
            out.append(0.0)
    return out


def drive(gen: ProcedureGen, respond: Callable[[Step], Reply]) -> Outcome:
    """Run a procedure synchronously, answering each step with ``respond`` (a fake engine for tests and
    offline simulation; the real engine is asynchronous and lives in procedures/engine.py)."""
    reply: Reply = None
    while True:
        try:
            step = gen.send(reply)
        except StopIteration as stop:
            return stop.value
        reply = respond(step)


def simulate_run(gen: ProcedureGen, unit: Unit, world: World, rng: Any, pause_s: float = 5.0) -> tuple[Outcome, list[Move]]:
    """Run a procedure offline on one simulated unit in slot 0 (physics.simulate): each acquisition is
    answered with the samples the unit gives at the angles of the last move, ``pause_s`` of table
    time after the previous one, so a plan that depends on its data gets data. Scans are not
    simulated here. Returns the outcome and the moves made."""
    here, t, moves = Move(0.0), [0.0], []

    def respond(step: Step) -> Reply:
        nonlocal here
        if isinstance(step, Move):
            here = step
            moves.append(step)
        elif isinstance(step, Acquire):
            rec = simulate_recording(unit, [Pose(step.step, here.psi, here.theta, here.phi, step.samples)], world, rng=rng)
            rec.t = rec.t + t[0]
            t[0] = float(rec.t[-1]) + pause_s
            return {0: rec}
        elif isinstance(step, Scan):
            raise NotImplementedError("simulate_run does not simulate scans (physics.simulate.simulate_timeline does)")
        elif isinstance(step, Where):
            return (here.psi, here.theta, here.phi)
        return _empty_reply(step)
    return drive(gen, respond), moves
