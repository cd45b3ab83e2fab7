"""Physics outside the catalogue, concealed in a simulation for the open-world proof (issue 12).

Each class is a :class:`physics.effects.Effect`, applied sample by sample by
``physics.simulate.simulate_timeline`` exactly as the catalogue's concealments are, but none of them
is an entry of ``physics.effects.CATALOGUE``: the analyser has no regressor written for them and has to
discover them. They live here, with the proof, and not in physics/, because nothing but the proof
should ever conceal them (the analyser must not be able to share a mistake with them).

Each also states the truth the scorer compares the analyser's findings with, in the schema of the
analyser's ``finding["model"]`` (:meth:`OpenEffect.model`)::

    {"frame": "sensor"|"lab"|"outer"|"middle", "form": "offset"|"gain"|"rotation",
     "against": "time"|"temp_c"|None, "segments": [[t0, t1], ...]}

with times in the simulation's (and so the recording's) own ``t``, windows half-open ``[t0, t1)``.
"""

from __future__ import annotations

import inspect
from typing import Any, Callable, Sequence

import numpy as np

from physics.effects import Effect, stage_to_body


def _vec(v: Sequence[float], n: int, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected {n} finite numbers, got {v!r}")
    return a


def _segments(segments: Sequence[Sequence[float]]) -> np.ndarray:
    s = np.asarray(segments, dtype=float).reshape(-1, 2)
    if len(s) == 0 or not np.all(np.isfinite(s)) or np.any(s[:, 1] <= s[:, 0]):
        raise ValueError(f"segments: expected [[t0, t1], ...] with t0 < t1, got {segments!r}")
    return s[np.argsort(s[:, 0])]


class OpenEffect(Effect):
    """An out-of-catalogue concealment: an :class:`Effect` that also states its truth for the scorer."""

    frame: str = ""
    form: str = ""
    against: str | None = None

    def model(self) -> dict[str, Any]:
        """The truth in the schema of the analyser's ``finding["model"]`` (module docstring)."""
        return {"frame": self.frame, "form": self.form, "against": self.against, "segments": []}


class _Windowed(OpenEffect):
    """A constant offset present only in the time windows ``segments`` (half-open ``[t0, t1)``).

    Subclasses say in which frame the offset is fixed by the stage they override.
    """

    form = "offset"

    def __init__(self, offset: Sequence[float], segments: Sequence[Sequence[float]]) -> None:
        self.offset = _vec(offset, 3, "offset")
        self.segments = _segments(segments)

    def active(self, t: float) -> bool:
        """Whether the offset is present at time ``t``."""
        return bool(np.any((self.segments[:, 0] <= t) & (t < self.segments[:, 1])))

    def params(self) -> dict[str, Any]:
        return {"offset": self.offset.tolist(), "segments": self.segments.tolist()}

    def model(self) -> dict[str, Any]:
        return {**super().model(), "segments": self.segments.tolist()}


class SensorSegmentOffset(_Windowed):
    """A magnetised object attached to the unit for a while: ``offset`` counts added to the output
    (fixed in the sensor frame) inside the windows."""

    id = "segment_offset_sensor"
    frame = "sensor"

    def mag_raw(self, t, slot, raw, temp_c):  # type: ignore[no-untyped-def]
        return raw + self.offset if self.active(t) else raw


class IntermittentInterference(SensorSegmentOffset):
    """A relay or a motor near the unit switched on and off: the same sensor-frame offset in each of
    several windows."""

    id = "intermittent_interference"


class LabSegmentOffset(_Windowed):
    """A steel object set down near the table for a while: ``offset`` (lab-field units) fixed in the lab
    frame, seen in body axes through the attitude, ``h_b += C_LP^T offset``."""

    id = "segment_offset_lab"
    frame = "lab"

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        return h_b + C_LP.T @ self.offset if self.active(t) else h_b


class StageSegmentOffset(_Windowed):
    """Something magnetic resting on the outer or middle stage for a while: ``offset`` (lab-field units)
    fixed in that stage's frame, ``h_b += Q offset`` (Q from physics.effects.stage_to_body)."""

    def __init__(self, stage: str, offset: Sequence[float], segments: Sequence[Sequence[float]]) -> None:
        stage_to_body(stage, 0.0, 0.0)  # validates the stage
        super().__init__(offset, segments)
        self.stage = stage
        self.frame = stage
        self.id = f"segment_offset_{stage}"

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        if not self.active(t):
            return h_b
        return h_b + stage_to_body(self.stage, angles_deg[1], angles_deg[2]) @ self.offset

    def params(self) -> dict[str, Any]:
        return {"stage": self.stage, **super().params()}


class _LinearDrift(OpenEffect):
    """The linear output about the bias, ``lin = raw - bias``, changes in proportion to how far ``against``
    (the temperature or the time) is from ``ref``: ``raw += change(coef * (against - ref), lin)``. Built from
    ``coef, bias, ref`` under the keywords ``names[0], "bias", names[1]`` (as :meth:`params` gives them)."""

    frame = "sensor"
    names: tuple[str, str]
    change: Callable[[np.ndarray, np.ndarray], np.ndarray]

    def __init__(self, *args: Any, **kw: Any) -> None:
        kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
        signature = inspect.Signature([inspect.Parameter(k, kind) for k in (self.names[0], "bias", self.names[1])])
        coef, bias, ref = signature.bind(*args, **kw).args  # a wrong or missing keyword is a TypeError
        self.coef, self.bias, self.ref = _vec(coef, 3, self.names[0]), _vec(bias, 3, "bias"), float(ref)

    def mag_raw(self, t, slot, raw, temp_c):  # type: ignore[no-untyped-def]
        x = temp_c if self.against == "temp_c" else t
        return raw + self.change(self.coef * (x - self.ref), raw - self.bias)

    def params(self) -> dict[str, Any]:
        return {self.names[0]: self.coef.tolist(), self.names[1]: self.ref}


class GainVsTemp(_LinearDrift):
    """The sensitivity (not the bias) follows the temperature: with the linear output about the bias
    ``raw_lin = raw - bias``, ``raw += gain_per_c * (temp_c - t_ref_c) * raw_lin`` (per axis)."""

    id = "gain_vs_temp"
    form = "gain"
    against = "temp_c"
    names = ("gain_per_c", "t_ref_c")
    change = staticmethod(np.multiply)  # type: ignore[assignment]


class MisalignmentDrift(_LinearDrift):
    """The sensor axes turn slowly: a small rotation by ``w (t - t_mid)`` growing linearly in time about
    ``t_mid``, ``w = rate_rad_per_s``. Axes turned by w (``M_o -> M_o R(w)^T``, PHYSICS.md: M_o's rows are
    the sensor axes) see the field turned the other way: ``raw -= [w (t - t_mid)]x (raw - bias)``."""

    id = "misalignment_drift"
    form = "rotation"
    against = "time"
    names = ("rate_rad_per_s", "t_mid")
    change = staticmethod(lambda w, lin: -np.cross(w, lin))  # type: ignore[assignment]


#: Every open-world kind, and how to build it from its keyword parameters.
OPEN_KINDS: tuple[str, ...] = ("segment_offset_sensor", "segment_offset_lab", "segment_offset_outer",
                               "segment_offset_middle", "gain_vs_temp", "misalignment_drift",
                               "intermittent_interference")

_CLASSES: dict[str, type[OpenEffect]] = {
    "segment_offset_sensor": SensorSegmentOffset, "segment_offset_lab": LabSegmentOffset,
    "gain_vs_temp": GainVsTemp, "misalignment_drift": MisalignmentDrift,
    "intermittent_interference": IntermittentInterference,
}


def make_open(kind: str, params: dict[str, Any]) -> OpenEffect:
    """Build the concealment of open-world ``kind`` (:data:`OPEN_KINDS`) from its keyword parameters
    (as :meth:`Effect.params` gives them, except the stage effects' stage, implied by the kind)."""
    try:
        if kind in ("segment_offset_outer", "segment_offset_middle"):
            kw = {k: v for k, v in params.items() if k != "stage"}
            return StageSegmentOffset(kind.rsplit("_", 1)[1], **kw)
        if kind in _CLASSES:
            return _CLASSES[kind](**params)
    except TypeError as e:
        raise ValueError(f"open kind {kind}: {e}") from None
    raise ValueError(f"open kind: expected one of {', '.join(OPEN_KINDS)}, got {kind!r}")
