"""The run's state machine: its states, which are final, and the transitions an operator may ask for.

One definition used by the engine (which moves a run through them), the worker (which applies the
operator's commands), the API (which refuses an illegal request with 409) and the pages (which show
the buttons a state allows).
"""

from __future__ import annotations

from enum import Enum


class RunState(str, Enum):
    """Where a run is. ``completed``, ``failed`` and ``aborted`` are final."""

    queued = "queued"
    running = "running"
    paused = "paused"
    completed = "completed"
    failed = "failed"
    aborted = "aborted"


#: States of a run that is not over (it holds its station).
ACTIVE: tuple[str, ...] = (RunState.queued.value, RunState.running.value, RunState.paused.value)
#: States a run never leaves.
FINAL: tuple[str, ...] = (RunState.completed.value, RunState.failed.value, RunState.aborted.value)

#: What an operator may ask (``PUT /runs/{id}/state``): (from, to) -> what it does. Everything else
#: the run does on its own (queued -> running when a worker takes it; -> completed/failed at its end).
OPERATOR_TRANSITIONS: dict[tuple[str, str], str] = {
    ("running", "paused"): "pause at the next checkpoint",
    ("paused", "running"): "resume",
    ("queued", "aborted"): "abort before the hardware is used",
    ("running", "aborted"): "abort: axes stopped, samples kept",
    ("paused", "aborted"): "abort: axes stopped, samples kept",
}


def allowed(state: str) -> list[str]:
    """The states an operator may ask for from ``state`` (empty when it is final)."""
    return [t for (f, t) in OPERATOR_TRANSITIONS if f == state]


def check_transition(current: str, target: str) -> str:
    """What the transition does; ValueError naming from, to and what is allowed when it is illegal."""
    what = OPERATOR_TRANSITIONS.get((current, target))
    if what is None:
        options = allowed(current)
        raise ValueError(f"illegal transition {current} -> {target}"
                         + (f" (from {current}: {', '.join(options)})" if options else f" ({current} is final)"))
    return what
