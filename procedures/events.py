"""What a run reports as it goes: one small frozen dataclass per kind of event.

The engine hands each to its ``on_event`` callback; the service appends ``(e.kind, e.data())`` to the
run's event log (the run_events table) and streams it as a server-sent event, the CLI draws its
progress bar from them. ``kind`` and ``data()`` are therefore a wire format: the JSON each class
makes is exactly what clients of ``GET /runs/{id}/events`` read, and must not change with the class.

Several classes share a kind on the wire (``step``: started, retried, warning, resumed; ``prompt``: asked,
answered), told apart there by their keys; here by their type, so a reader matches on the class
(``isinstance(e, Progress)``) rather than on strings and dict keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, TypeAlias

from procedures.states import RunState
from procedures.steps import Step


@dataclass(frozen=True)
class StateChanged:
    """The run entered ``state`` (``reason`` says why it failed or was aborted) at table time ``t`` (s)."""

    kind: ClassVar[str] = "state"
    state: RunState
    reason: str | None
    t: float

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"state": self.state.value, "reason": self.reason, "t": self.t}


@dataclass(frozen=True)
class StepStarted:
    """The engine began ``step`` of the procedure at table time ``t`` (s)."""

    kind: ClassVar[str] = "step"
    step: Step
    t: float

    def data(self) -> dict[str, Any]:
        """The event's JSON body: the step as ``{"kind": "move", "psi": ..., ...}``."""
        return {"step": describe_step(self.step), "t": self.t}


@dataclass(frozen=True)
class Computing:
    """How far the procedure's computation (its :class:`~procedures.steps.Compute` step) has got: the
    step again with its ``stage`` and ``percent`` (at most :data:`COMPUTING_EVERY_S` apart)."""

    kind: ClassVar[str] = "step"
    step: Step
    t: float

    def data(self) -> dict[str, Any]:
        """The event's JSON body, as a step's."""
        return {"step": describe_step(self.step), "t": self.t}


#: Seconds between two :class:`Computing` events of one stage.
COMPUTING_EVERY_S = 0.5


@dataclass(frozen=True)
class StepRetried:
    """The step in progress timed out and is tried again (``attempt`` 1 for the first retry)."""

    kind: ClassVar[str] = "step"
    attempt: int
    reason: str

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"retry": self.attempt, "reason": self.reason}


@dataclass(frozen=True)
class StepWarning:
    """Something went wrong that does not end the run by itself (e.g. stopping the axes failed)."""

    kind: ClassVar[str] = "step"
    warning: str

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"warning": self.warning}


@dataclass(frozen=True)
class Resumed:
    """The steps up to checkpoint ``checkpoint`` were answered from interrupted run ``from_run``'s
    recording (``samples`` samples taken over); the table goes on live from there at table time ``t``."""

    kind: ClassVar[str] = "step"
    from_run: int
    checkpoint: str
    samples: int
    t: float

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"resumed_from": self.from_run, "checkpoint": self.checkpoint, "samples": self.samples, "t": self.t}


@dataclass(frozen=True)
class Progress:
    """A timed step ended: ``percent`` of the plan's nominal table time done, ``table_s`` table seconds
    elapsed, ``left_s`` the estimate of those still to go, ``samples`` kept so far; ``left_wall_s``
    the same estimate in wall-clock seconds (``left_s`` over the station's time scale: what people
    wait), left out of the JSON when unknown."""

    kind: ClassVar[str] = "progress"
    percent: float
    table_s: float
    left_s: float
    samples: int
    left_wall_s: float | None = None

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        d: dict[str, Any] = {"percent": self.percent, "table_s": self.table_s, "left_s": self.left_s,
                             "samples": self.samples}
        if self.left_wall_s is not None:
            d["left_wall_s"] = self.left_wall_s
        return d


@dataclass(frozen=True)
class SamplesStored:
    """Samples of step ``step`` reached the sink; ``count`` samples kept in the run so far (all slots)."""

    kind: ClassVar[str] = "samples"
    step: str
    count: int

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"step": self.step, "count": self.count}


@dataclass(frozen=True)
class PromptAsked:
    """The run waits for the operator's answer to prompt ``id``."""

    kind: ClassVar[str] = "prompt"
    id: str
    text: str

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"id": self.id, "text": self.text}


@dataclass(frozen=True)
class PromptAnswered:
    """The run took the operator's ``answer`` to prompt ``id`` (published by whoever passed it on:
    the engine itself never emits this one)."""

    kind: ClassVar[str] = "prompt"
    id: str
    answer: str

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"id": self.id, "answered": True, "answer": self.answer}


@dataclass(frozen=True)
class Result:
    """The procedure returned: ``units``, the slots it has a result for (the service publishes a
    fuller result of its own instead)."""

    kind: ClassVar[str] = "result"
    units: tuple[int, ...]

    def data(self) -> dict[str, Any]:
        """The event's JSON body."""
        return {"units": list(self.units)}


#: Any event of a run.
Event: TypeAlias = (StateChanged | StepStarted | Computing | StepRetried | StepWarning | Resumed | Progress | SamplesStored
                    | PromptAsked | PromptAnswered | Result)


def describe_step(step: Step) -> dict[str, Any]:
    """A step as JSON: its type's name as ``kind``, then its fields."""
    d = {"kind": type(step).__name__.lower()}
    d.update({k: v for k, v in step.__dict__.items()})
    return d
